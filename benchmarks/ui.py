"""The ``crfedit ui`` page in a real headless Chromium: latencies measured in the browser, and
the screenshots of docs/ui.md.  tests/test_ui_browser.py drives the page with this module too.

    python benchmarks/ui.py MODEL --data DATA                       # latencies, printed
    python benchmarks/ui.py MODEL --data DATA --md docs/benchmarks.md --shots docs/img

Chromium is Debian's ``chromium`` driven by Selenium through Debian's ``chromium-driver``.
Latencies are the page's own User Timing measures (``performance.measure``), from the click or
slider move to the new image decoded on screen: a view switch, the selection preview, a colour
edit and a removal applied and shown, and the 8-view turntable.  Each is the median of
``--repeats`` runs.  The section goes between ``<!-- ui:begin -->`` and ``<!-- ui:end -->`` of --md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- ui:begin -->", "<!-- ui:end -->"
BROWSERS = ("chromium", "chromium-browser", "google-chrome")
DRIVERS = ("chromedriver", "chromium-driver")


def find_chromium() -> tuple[str | None, str | None, str]:
    """(browser, driver, why not): the executables, or None and the reason they are missing."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return None, None, "selenium is not installed (pip install 'crfedit[test]')"
    browser = next((p for p in map(shutil.which, BROWSERS) if p), None)
    driver = next((p for p in map(shutil.which, DRIVERS) if p), None)
    if browser is None:
        return None, None, "no Chromium found (Debian: apt-get install chromium chromium-driver)"
    if driver is None:
        return None, None, "no chromedriver found (Debian: apt-get install chromium-driver)"
    return browser, driver, ""


class Page:
    """The page in headless Chromium, driven like a user: clicks, pointer drags, inputs."""

    def __init__(self, url: str, width: int = 1400, height: int = 1000):
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        browser, driver, why = find_chromium()
        if browser is None:
            raise RuntimeError(why)
        options = webdriver.ChromeOptions()
        options.binary_location = browser
        for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                     f"--window-size={width},{height}", "--force-device-scale-factor=1", "--no-first-run"):
            options.add_argument(flag)
        self.driver = webdriver.Chrome(service=Service(executable_path=driver), options=options)
        self.driver.set_script_timeout(120)
        self.driver.get(url)
        self.wait("return typeof S !== 'undefined' && S.info !== null && document.getElementById('view').dataset.state !== undefined", 60)

    def js(self, script: str, *args):
        return self.driver.execute_script(script, *args)

    def wait(self, condition: str, timeout: float = 60.0):
        """Until the JavaScript ``condition`` (a statement returning a value) is truthy."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = self.js(condition)
            if value:
                return value
            time.sleep(0.02)
        error = self.js("return document.getElementById('error').hidden ? '' : document.getElementById('error-text').textContent")
        raise TimeoutError(f"waited {timeout:g} s for: {condition}" + (f" (the page says: {error})" if error else ""))

    def click(self, css: str) -> None:
        self.driver.find_element("css selector", css).click()

    def set_input(self, css: str, value) -> None:
        """Set an input's value as a user would and fire its input and change events."""
        self.js("const e = document.querySelector(arguments[0]); e.value = arguments[1];"
                "e.dispatchEvent(new Event('input', {bubbles: true})); e.dispatchEvent(new Event('change', {bubbles: true}));",
                css, value)

    def draw(self, points, tool: str = "fg") -> None:
        """Drag the mouse over the canvas through ``points`` (view pixels, x right, y down)."""
        from selenium.webdriver.common.action_chains import ActionChains

        self.click(f'input[name="tool"][value="{tool}"]')
        canvas = self.driver.find_element("css selector", "#strokes")
        w, h = self.js("return [S.info.width, S.info.height]")
        rect = canvas.rect
        css = [((x + 0.5) * rect["width"] / w - rect["width"] / 2, (y + 0.5) * rect["height"] / h - rect["height"] / 2) for x, y in points]
        chain = ActionChains(self.driver, duration=10).move_to_element_with_offset(canvas, round(css[0][0]), round(css[0][1])).click_and_hold()
        last = css[0]
        for x, y in css[1:]:
            chain = chain.move_by_offset(round(x) - round(last[0]), round(y) - round(last[1]))
            last = (x, y)
        chain.release().perform()

    def pixels(self, css: str = "#view") -> np.ndarray:
        """The RGB pixels [H, W, 3] uint8 of an image element as the page decoded it."""
        data = self.js(
            "const img = document.querySelector(arguments[0]); const c = document.createElement('canvas');"
            "c.width = img.naturalWidth; c.height = img.naturalHeight; const x = c.getContext('2d');"
            "x.drawImage(img, 0, 0); return [c.width, c.height, Array.from(x.getImageData(0, 0, c.width, c.height).data)];", css)
        w, h, flat = data
        return np.asarray(flat, dtype=np.uint8).reshape(h, w, 4)[..., :3]

    def measures(self, name: str) -> list[float]:
        """Milliseconds of the page's ``crfedit:<name>`` measures, oldest first."""
        return self.js(f"return performance.getEntriesByName('crfedit:{name}').map(e => e.duration)")

    def count(self, name: str) -> int:
        return len(self.measures(name))

    def error(self) -> str:
        return self.js("return document.getElementById('error').hidden ? '' : document.getElementById('error-text').textContent")

    def screenshot(self, path: Path) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.driver.save_screenshot(str(path))

    def close(self) -> None:
        self.driver.quit()


def pick_view(page: Page, spec: str) -> None:
    """Open the split's list and click the view ``spec`` (``train:3``); wait until it is shown."""
    split = spec.split(":")[0]
    n = page.count("view")
    page.js("for (const d of document.querySelectorAll('#split-views details'))"
            " if (d.querySelector('summary').textContent.startsWith(arguments[0])) d.open = true;", split)
    page.click(f'#split-views [title="{spec}"]')
    page.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy")


def apply_edit(page: Page, kind: str, timeout: float = 300.0) -> float:
    """Choose ``kind``, press Apply and wait for the result on screen; returns the page's ms."""
    page.set_input("#edit-kind", kind)
    n = page.count(f"apply-{kind}")
    page.click("#apply")
    page.wait(f"return performance.getEntriesByName('crfedit:apply-{kind}').length > {n} || !document.getElementById('error').hidden", timeout)
    if page.error():
        raise RuntimeError(f"the page says: {page.error()}")
    page.wait("return !S.viewBusy")
    return page.measures(f"apply-{kind}")[-1]


def stroke_on_part(parts: np.ndarray, opacity: np.ndarray) -> tuple[list[list[float]], int]:
    """A horizontal stroke inside the largest visible part of a part map [H, W] (0 = none), and that part."""
    labels, counts = np.unique(parts[(parts > 0) & (opacity > 0.9)], return_counts=True)
    part = int(labels[np.argmax(counts)])
    inside = (parts == part) & (opacity > 0.9)
    inner = inside[1:-1, 1:-1] & inside[:-2, 1:-1] & inside[2:, 1:-1] & inside[1:-1, :-2] & inside[1:-1, 2:]
    core = np.zeros_like(inside)
    core[1:-1, 1:-1] = inner
    best = (0, 0, 0, 0)
    for y in range(core.shape[0]):
        run = 0
        for x in range(core.shape[1]):
            run = run + 1 if core[y, x] else 0
            if run > best[0]:
                best = (run, y, x - run + 1, x)
    _, y, x0, x1 = best
    return [[float(x0), float(y)], [float(x1), float(y)]], part


# ----------------------------------------------------------------------------- the benchmark


def run(model: Path, data: Path | None, repeats: int, shots: Path | None) -> dict:
    """Latencies of the page on ``model`` (ms, medians), and the docs' screenshots when ``shots``."""
    from crfedit.ui.server import run_in_thread
    from crfedit.ui.session import open_session

    work = Path(tempfile.mkdtemp(prefix="crfedit-ui-bench-"))
    session, _ = open_session(model, data, [], work, "cpu")
    server = run_in_thread(session)
    page = Page(server.url)
    try:
        view, instance = "train:0", 0
        pick_view(page, view)
        if shots:
            page.screenshot(shots / "ui-start.png")
        camera = session.model.views["train"].cameras(instance)[0]
        out = _render(session, instance, camera)
        parts = session.category.instance(session.base.names[instance]).view(view).parts if session.category else None
        stroke, _ = stroke_on_part(parts if parts is not None else (out > 0.5).astype(np.uint8), out)
        page.draw(stroke)
        times = {k: [] for k in ("view", "select", "apply-color", "apply-remove", "turntable")}
        for i in range(repeats):  # view switches: orbit positions never shown before
            n = page.count("view")
            page.set_input("#azimuth", (10 + 37 * i) % 360)
            page.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy")
            times["view"].append(page.measures("view")[-1])
        pick_view(page, view)
        for i in range(repeats):
            page.js("S.tint = false;")
            n = page.count("select")
            page.click("#select")
            page.wait(f"return performance.getEntriesByName('crfedit:select').length > {n} && !S.viewBusy", 120)
            times["select"].append(page.measures("select")[-1])
            page.wait(f"return performance.getEntriesByName('crfedit:turntable').length > {len(times['turntable'])}", 120)
            times["turntable"].append(page.measures("turntable")[-1])
        if shots:
            page.screenshot(shots / "ui-select.png")
        page.set_input("#color", "#2f6fd8")
        for i in range(repeats):
            times["apply-color"].append(apply_edit(page, "color"))
            if i + 1 < repeats:
                toggle_last(page, False)
        if shots:
            page.set_input("#compare", "side")
            page.wait("return !document.getElementById('sidebox').hidden && !S.viewBusy")
            time.sleep(0.5)
            page.screenshot(shots / "ui-recolor.png")
            page.set_input("#compare", "off")
        for i in range(repeats):
            times["apply-remove"].append(apply_edit(page, "remove"))
            toggle_last(page, False)
        return {"ms": {k: statistics.median(v) for k, v in times.items()}, "runs": times, "repeats": repeats,
                "size": f"{camera.width}×{camera.height}", "instances": len(session.base.names)}
    finally:
        page.close()
        server.stop()
        shutil.rmtree(work, ignore_errors=True)


def _render(session, instance: int, camera) -> np.ndarray:
    from crfedit.renderer import render_camera

    return render_camera(session.model.field_for(instance), camera, instance).opacity.cpu().numpy()


def toggle_last(page: Page, on: bool) -> None:
    """Turn the newest edit of the stack on or off and wait for the view."""
    n = page.count("view")
    page.js("const boxes = document.querySelectorAll('#stack input.toggle'); const b = boxes[boxes.length - 1];"
            "if (b.checked !== arguments[0]) b.click();", on)
    page.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy", 120)


def markdown(result: dict, command: str) -> str:
    from crfedit.machine import machine_info

    m = machine_info()
    m["cpu"] = f"{m['cpu']} ({m['cores']} cores, {m['threads']} torch thread(s))"
    load = os.getloadavg()
    ms = result["ms"]
    rows = [
        ("view switch (orbit slider → new view shown)", ms["view"], "≤ 150 ms"),
        ("selection preview (Select → tinted view shown)", ms["select"], ""),
        ("colour edit applied and shown (Apply → recoloured view)", ms["apply-color"], "≤ 500 ms"),
        ("removal applied and shown (Apply → view)", ms["apply-remove"], ""),
        ("turntable of 8 views (all shown)", ms["turntable"], ""),
    ]
    lines = [
        f"Measured by `{command}` on {m['cpu']}, torch {m['torch']}, {m['date']}, revision {m['revision']}; "
        f"load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} at the end. Headless Chromium on the same machine; "
        f"{result['instances']} instances at {result['size']}; medians of {result['repeats']} runs, in the browser "
        "(`performance.measure` from the click to the image decoded).",
        "",
        "| action | median | goal |",
        "|---|---:|---|",
        *[f"| {a} | {v:.0f} ms | {g} |" for a, v, g in rows],
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("--data", type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--shots", type=Path, help="folder for ui-*.png screenshots (docs/img)")
    ap.add_argument("--md", type=Path, help="markdown file whose ui:begin/ui:end block gets the table")
    args = ap.parse_args(argv)
    browser, _, why = find_chromium()
    if browser is None:
        print(f"error: {why}", file=sys.stderr)
        return 2
    result = run(args.model, args.data, args.repeats, args.shots)
    command = "python benchmarks/ui.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = markdown(result, command)
    print(text)
    print({k: [round(x) for x in v] for k, v in result["runs"].items()})
    if args.md:
        from crfedit.report import update_markdown

        update_markdown(args.md, f"{BEGIN}\n{text}\n{END}", BEGIN, END)
    return 0


if __name__ == "__main__":
    sys.exit(main())
