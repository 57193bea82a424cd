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
        options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
        self.driver = webdriver.Chrome(service=Service(executable_path=driver), options=options)
        self.driver.set_script_timeout(120)
        self.driver.get(url)
        self.wait("return typeof S !== 'undefined' && S.info !== null && document.getElementById('view').dataset.state !== undefined", 60)

    def js(self, script: str, *args):
        return self.driver.execute_script(script, *args)

    def wait(self, condition: str, timeout: float = 60.0):
        """Until the JavaScript ``condition`` (a statement returning a value) is truthy.

        The page checks it every 10 ms itself and answers once: asking from here at every
        check (a WebDriver round trip through chromedriver and the browser) took a third of a
        core from the server it measures, on a 2-core machine half the time an edit ran."""
        self.driver.set_script_timeout(timeout + 30)
        value = self.driver.execute_async_script(
            "const done = arguments[arguments.length - 1], until = performance.now() + arguments[0];"
            f"const check = () => {{ {condition} }};"
            "(function poll() { const v = check(); if (v || performance.now() > until) done(v || null); else setTimeout(poll, 10); })();",
            timeout * 1000.0)
        if value:
            return value
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

    def console_errors(self) -> list[str]:
        """JavaScript errors the page logged since the last call."""
        return [e["message"] for e in self.driver.get_log("browser") if e["level"] == "SEVERE"]

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


def select_shown(page: Page, kind: str, timeout: float = 120.0) -> tuple[float, float]:
    """Choose ``kind``, press Select and wait for the tinted view and the turntable; returns
    the page's ms for each (the selection is of ``kind``: an Apply of that kind reuses it)."""
    page.set_input("#edit-kind", kind)
    n, t = page.count("select"), page.count("turntable")
    page.click("#select")
    page.wait(f"return performance.getEntriesByName('crfedit:select').length > {n} && !S.viewBusy", timeout)
    page.wait(f"return performance.getEntriesByName('crfedit:turntable').length > {t}", timeout)
    return page.measures("select")[-1], page.measures("turntable")[t]


def apply_edit(page: Page, kind: str, timeout: float = 300.0) -> float:
    """Choose ``kind``, press Apply and wait for the result on screen; returns the page's ms."""
    page.set_input("#edit-kind", kind)
    n, t = page.count(f"apply-{kind}"), page.count("turntable")
    page.click("#apply")
    page.wait(f"return performance.getEntriesByName('crfedit:apply-{kind}').length > {n} || !document.getElementById('error').hidden", timeout)
    if page.error():
        raise RuntimeError(f"the page says: {page.error()}")
    page.wait(f"return !S.viewBusy && performance.getEntriesByName('crfedit:turntable').length > {t}", timeout)
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


def take_shots(model: Path, data: Path | None, folder: Path, color: str = "#2f6fd8") -> list[Path]:
    """docs/ui.md's screenshots, the way tests/test_ui_browser.py drives the page: a stroke on
    the seat of the first instance's train:0 view, Select (ui-select.png), a recolour shown
    beside the view before it (ui-recolor.png)."""
    from crfedit.ui.server import open_page_session, run_in_thread

    work = Path(tempfile.mkdtemp(prefix="crfedit-ui-shots-"))
    session, _ = open_page_session(model, data, [], work, "cpu")
    server = run_in_thread(session)
    page = Page(server.url)
    try:
        pick_view(page, "train:0")
        page.js("document.querySelector('#split-views details').open = false;")
        camera = session.model.views["train"].cameras(0)[0]
        opacity = _render(server, session, 0, camera)
        parts = load_parts(data, session.base.names[0], "train:0") if data else None
        stroke, _ = stroke_on_part(parts if parts is not None else (opacity > 0.5).astype(np.uint8), opacity)
        page.draw(stroke)
        n, t = page.count("select"), page.count("turntable")
        page.click("#select")
        page.wait(f"return performance.getEntriesByName('crfedit:select').length > {n}"
                  f" && performance.getEntriesByName('crfedit:turntable').length > {t} && !S.viewBusy", 120)
        out = [folder / "ui-select.png", folder / "ui-recolor.png"]
        page.screenshot(out[0])
        page.set_input("#color", color)
        apply_edit(page, "color")
        page.set_input("#compare", "side")
        page.wait("return !document.getElementById('sidebox').hidden && document.getElementById('side-before').complete && !S.viewBusy")
        page.screenshot(out[1])
        return out
    finally:
        page.close()
        server.stop()
        shutil.rmtree(work, ignore_errors=True)


def run(model: Path, data: Path | None, repeats: int) -> dict:
    """Latencies of the page on ``model`` (ms, medians).

    torch's threads follow crfedit's policy, shared by the server's two compute threads (as
    ``crfedit ui`` sets them).  A warm-up round is
    not counted.  Each selection is of a new scribble (the stroke's radius changes), so no
    repeat is served from the server's caches; a colour edit is measured after its Select (the
    page's flow: preview, then Apply; the selection is reused) and without one ("cold"), a
    removal's Select on its own and its Apply without one.  (Until the fifty-second session
    the Select before the colour edit was of the removal kind that the round before had left
    chosen, so the colour edit made its own selection: "after Select" was "cold".)"""
    import torch

    from crfedit.runtime import configure_threads
    from crfedit.ui.server import open_page_session, run_in_thread

    configure_threads()
    work = Path(tempfile.mkdtemp(prefix="crfedit-ui-bench-"))
    session, _ = open_page_session(model, data, [], work, "cpu")
    threads = torch.get_num_threads()
    server = run_in_thread(session)
    page = Page(server.url)
    try:
        view, instance = "train:0", 0
        pick_view(page, view)
        camera = session.model.views["train"].cameras(instance)[0]
        opacity = _render(server, session, instance, camera)
        parts = load_parts(data, session.base.names[instance], view) if data else None
        stroke, _ = stroke_on_part(parts if parts is not None else (opacity > 0.5).astype(np.uint8), opacity)
        page.set_input("#color", "#2f6fd8")
        times = {k: [] for k in ("view", "select", "select-remove", "turntable", "apply-color", "apply-color-cold", "apply-remove")}
        radius = float(page.js("return S.radius"))

        def scribble(i: int) -> None:
            page.click("#clear")
            page.js("S.radius = arguments[0];", radius + 0.05 * i)
            page.draw(stroke)

        for i in range(repeats + 1):  # round 0 warms up
            keep = i > 0
            n = page.count("view")
            page.set_input("#azimuth", (10 + 37 * i) % 360)  # an orbit position not shown before
            page.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy")
            switched = page.measures("view")[-1]
            pick_view(page, view)
            scribble(i)
            selected, turntable = select_shown(page, "color")
            ms = apply_edit(page, "color")
            toggle_last(page, False)
            scribble(repeats + 1 + i)
            cold = apply_edit(page, "color")
            toggle_last(page, False)
            scribble(2 * repeats + 2 + i)
            selected_remove, _ = select_shown(page, "remove")
            scribble(3 * repeats + 3 + i)
            remove_ms = apply_edit(page, "remove")
            toggle_last(page, False)
            if keep:
                times["view"].append(switched)
                times["select"].append(selected)
                times["select-remove"].append(selected_remove)
                times["turntable"].append(turntable)
                times["apply-color"].append(ms)
                times["apply-color-cold"].append(cold)
                times["apply-remove"].append(remove_ms)
        return {"ms": {k: statistics.median(v) for k, v in times.items()}, "runs": times, "repeats": repeats,
                "size": f"{camera.width}×{camera.height}", "instances": len(session.base.names), "threads": threads}
    finally:
        page.close()
        server.stop()
        shutil.rmtree(work, ignore_errors=True)


def load_parts(data: Path, name: str, view: str):
    """The dataset's part map of one view, when it has part maps."""
    from crfedit.data import load_category

    category = load_category(data, with_parts=True)
    return category.instance(name).view(view).parts


def _render(server, session, instance: int, camera) -> np.ndarray:
    """Opacity of ``instance``'s view, rendered on the server's render thread (no third OpenMP
    team: :func:`crfedit.ui.server.compute_threads`)."""
    from crfedit.renderer import render_camera

    def work():
        return render_camera(session.model.field_for(instance), camera, instance).opacity.cpu().numpy()

    return server.server.render_pool.submit(work).result()


def toggle_last(page: Page, on: bool) -> None:
    """Turn the newest edit of the stack on or off and wait for the view."""
    n, t = page.count("view"), page.count("turntable")
    page.js("const boxes = document.querySelectorAll('#stack input.toggle'); const b = boxes[boxes.length - 1];"
            "if (b.checked !== arguments[0]) b.click();", on)
    page.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy"
              f" && performance.getEntriesByName('crfedit:turntable').length > {t}", 120)


def markdown(result: dict, command: str) -> str:
    from crfedit.machine import machine_info

    m = machine_info()
    m["cpu"] = f"{m['cpu']} ({m['cores']} cores, {result['threads']} torch thread(s) for each of the server's two compute threads)"
    load = os.getloadavg()
    ms = result["ms"]
    rows = [
        ("view switch (orbit slider → new view shown)", ms["view"], "≤ 150 ms"),
        ("selection preview of a recolour (Select → tinted view shown)", ms["select"], ""),
        ("selection preview of a removal (Select → tinted view shown)", ms["select-remove"], ""),
        ("colour edit applied and shown, after Select (Apply → recoloured view)", ms["apply-color"], "≤ 500 ms"),
        ("colour edit applied and shown, no Select before (the selection is made in Apply)", ms["apply-color-cold"], ""),
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
    if args.shots:
        for path in take_shots(args.model, args.data, args.shots):
            print(f"wrote {path}")
    result = run(args.model, args.data, args.repeats)
    command = "python benchmarks/ui.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = markdown(result, command)
    print(text)
    print({k: [round(x) for x in v] for k, v in result["runs"].items()})
    if args.md:
        from crfedit.report import update_markdown

        update_markdown(args.md, f"{BEGIN}\n{text}\n{END}", BEGIN, END)
    return 0


if __name__ == "__main__":
    from crfedit.errors import run_script

    run_script(main)
