"""``crfedit ui`` end to end in a real headless Chromium (Debian's ``chromium`` and
``chromium-driver``, driven by Selenium through benchmarks/ui.py, the driver the benchmark and
the docs' screenshots use).

A user picks a view, draws a stroke over the seat with the mouse, picks a colour and presses
Apply: the pixels under the stroke move toward the colour, a pixel of another part far away
does not, and turning the edit off gives back the view bit for bit.  A stopped server then
shows as one sentence in the page.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("aiohttp", reason="crfedit ui needs the [ui] extra (aiohttp)")

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("bench_ui", ROOT / "benchmarks" / "ui.py")
drive = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(drive)

BROWSER, DRIVER, WHY = drive.find_chromium()
pytestmark = pytest.mark.skipif(BROWSER is None, reason=f"no headless browser for the end-to-end test: {WHY}")


@pytest.fixture
def page(edit_category, tmp_path):
    from crfedit.ui.server import run_in_thread
    from crfedit.ui.session import open_session

    path, _, category = edit_category
    session, _ = open_session(path, category.root, [], tmp_path / "work", "cpu")
    running = run_in_thread(session)
    p = drive.Page(running.url)
    yield p, running
    p.close()
    running.stop()


def test_scribble_recolour_and_toggle_in_a_real_browser(page, edit_category, tmp_path):
    from crfedit.edit.scribble import strokes_json_mask
    from crfedit.renderer import render_camera

    p, running = page
    _, model, category = edit_category
    view = category.instance(0).view("train:0")
    opacity = render_camera(model.field_for(0), view.camera, 0).opacity.numpy()
    stroke, part = drive.stroke_on_part(view.parts, opacity)

    drive.pick_view(p, "train:0")
    before = p.pixels()
    assert before.shape == (32, 32, 3) and p.error() == ""
    # the orbit sliders move to where the stored view looks from, marked as near it
    from crfedit.cameras import eye_angles

    az, el = eye_angles(view.camera.c2w[:3, 3])
    p.wait("return document.getElementById('az-out').textContent.startsWith('≈')", 30)
    assert p.js("return [Number(document.getElementById('azimuth').value), Number(document.getElementById('elevation').value)]") \
        == [round(az) % 360, round(el)]
    # the turntable follows the stored view's elevation, so a tile opens the view it shows
    p.wait(f"return S.turnEl === {round(el)}", 30)

    p.draw(stroke)
    drawn = p.js("return Strokes.toJson(marks().fg)")
    assert len(drawn["strokes"]) == 1 and len(drawn["strokes"][0]) >= 2  # the mouse drew one polyline

    n = p.count("select")  # Select: the page says what the selection took, in select's lines
    p.click("#select")
    p.wait(f"return performance.getEntriesByName('crfedit:select').length > {n}", 120)
    said = p.driver.find_element("css selector", "#selection-info").text
    assert " occupied cells selected from 1 view(s) (" in said and "; strokes: " in said and "; colour join: " in said, said

    p.set_input("#color", "#2040ff")
    drive.apply_edit(p, "color")
    after = p.pixels()
    assert len(p.driver.find_elements("css selector", "#stack li")) == 1
    said = p.driver.find_element("css selector", "#selection-info").text  # the old selection's count is gone
    assert "recolour is applied" in said and "occupied cells" not in said, said
    # the strokes the recolour used are cleared (the next edit does not take them in), Ctrl+Z brings them back
    assert p.js("return marks().fg.length") == 0
    p.js("undo()")
    assert p.js("return Strokes.toJson(marks().fg)") == drawn

    under = strokes_json_mask(drawn, 32, 32, "stroke") & (view.parts == part)
    target = np.array([0x20, 0x40, 0xFF], dtype=float)
    dist_before = np.abs(before[under] - target).mean()
    dist_after = np.abs(after[under] - target).mean()
    assert dist_after < 0.6 * dist_before, (dist_before, dist_after)
    # far away: the pixel of another part of the chair farthest from the stroke
    ys, xs = np.nonzero((view.parts > 0) & (view.parts != part) & (opacity > 0.9))
    sy, sx = np.nonzero(under)
    far = int(np.argmax(np.min(np.hypot(ys[:, None] - sy[None], xs[:, None] - sx[None]), axis=1)))
    y, x = ys[far], xs[far]
    assert np.abs(after[y, x].astype(int) - before[y, x]).max() <= 8, (y, x, before[y, x], after[y, x])

    p.screenshot(tmp_path / "recoloured.png")
    assert (tmp_path / "recoloured.png").stat().st_size > 10_000

    drive.toggle_last(p, False)
    assert p.js("return document.getElementById('view').dataset.state") == "base"
    assert np.array_equal(p.pixels(), before)
    drive.toggle_last(p, True)
    assert not np.array_equal(p.pixels(), before)
    assert p.error() == "" and p.console_errors() == []

    # a toggle the page refuses (an edit is running) leaves the box as the stack is
    p.js("S.job = {id: 'running'}; document.querySelector('#stack input.toggle').click()")
    p.wait("return !document.getElementById('error').hidden", 30)
    assert p.error().startswith("an edit is running") and p.js("return document.querySelector('#stack input.toggle').checked")
    p.js("S.job = null; clearError()")
    # a Select the server refuses (no strokes on this chair) leaves the status at ready, not "selecting…"
    n = p.count("view")
    p.js("pickInstance(1)")
    p.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy", 60)
    p.click("#select")
    p.wait("return !document.getElementById('error').hidden", 60)
    assert p.js("return document.getElementById('status-text').textContent") == "ready"
    p.js("clearError()")
    # a quick eraser swipe across a stroke erases it: the path between two pointer events counts
    left = p.js("""
        const r = document.getElementById('strokes').getBoundingClientRect();
        const at = (x, y) => ({clientX: r.left + (x + 0.5) * r.width / S.info.width, clientY: r.top + (y + 0.5) * r.height / S.info.height});
        marks().fg.push({points: [[6, 12], [20, 12]], radius: 1});
        const radius = S.radius; S.radius = 1;
        S.drag = {erase: true, last: [13, 6]}; onMove(at(13, 18)); S.drag = null; S.radius = radius;
        return marks().fg.length""")
    assert left == 0
    # the thumbnails take the keyboard: Tab reaches them, Enter picks one
    assert p.js("return [...document.querySelectorAll('#instances img, #turntable img')].every(i => i.tabIndex === 0)")
    p.js("document.querySelectorAll('#turntable img')[2].dispatchEvent(new KeyboardEvent('keydown', {key: 'Enter'}))")
    p.wait("return typeof S.view === 'object' && S.view.azimuth === 90 && S.view.elevation === S.turnEl", 30)
    n = p.count("view")
    p.js("pickInstance(0)")
    p.wait(f"return performance.getEntriesByName('crfedit:view').length > {n} && !S.viewBusy", 60)
    drive.pick_view(p, "train:0")

    # Ctrl+Z in a number field undoes the typing, not a stroke
    strokes = p.js("return marks().fg.length")
    p.js("const f = document.getElementById('steps'); f.focus(); f.dispatchEvent(new KeyboardEvent('keydown', {key: 'z', ctrlKey: true, bubbles: true}))")
    assert p.js("return marks().fg.length") == strokes
    # an edit that fails at once can report before the server's reply names it (the reply held
    # back 1.5 s here): the page shows the error and is ready again, not stuck on "starting…"
    p.js("""const f = window.fetch; window.fetch = async (u, o) => { const r = await f(u, o);
            if (String(u).includes('/api/edit')) await new Promise((res) => setTimeout(res, 1500)); return r; }""")
    p.js("window.kept = marks().fg.splice(0); marks().fg.push({points: [[0, 0], [3, 0]], radius: 1}); redraw()")  # the corner alone
    p.set_input("#edit-kind", "remove")
    p.click("#apply")
    p.wait("return !document.getElementById('error').hidden", 60)
    assert "background only" in p.error(), p.error()
    p.wait("return S.job === null && !document.getElementById('apply').disabled", 10)
    assert len(p.driver.find_elements("css selector", "#stack li")) == 1  # nothing was added
    p.js("marks().fg.splice(0, marks().fg.length, ...window.kept); redraw(); clearError()")
    # the canvas follows the view's size when compare side by side is turned off (it stayed small)
    p.set_input("#compare", "side")
    p.wait("return !document.getElementById('sidebox').hidden", 30)
    p.set_input("#compare", "off")
    p.wait("const c = document.getElementById('strokes'), v = document.getElementById('view'); "
           "return Math.abs(c.width - Math.round(v.clientWidth * (window.devicePixelRatio || 1))) <= 1", 30)
    # drawing on the donor updates the paste hint at once (it kept asking for the strokes just drawn)
    p.set_input("#edit-kind", "add")
    p.js("toggleDonor()")
    assert p.js("return document.getElementById('paste-info').textContent").startswith("Scribble the part on the donor first")
    p.js("""const r = document.getElementById('strokes').getBoundingClientRect();
            const at = (x, y) => ({clientX: r.left + (x + 0.5) * r.width / S.info.width, clientY: r.top + (y + 0.5) * r.height / S.info.height,
                                   pointerId: 1, preventDefault() {}});
            S.tool = 'fg'; onDown(at(10, 12)); onMove(at(16, 12)); onUp();""")
    assert p.js("return document.getElementById('paste-info').textContent").startswith("Now click where to paste it")
    p.js("toggleDonor(); S.copy = null; S.paste = null")
    p.set_input("#edit-kind", "color")

    # a reload of the tab keeps the strokes, the instance and the view (sessionStorage)
    p.driver.refresh()
    p.wait("return typeof S !== 'undefined' && S.info !== null && !S.viewBusy && performance.getEntriesByName('crfedit:view').length > 0", 60)
    assert p.js("return [S.instance, S.view]") == [0, "train:0"]
    assert p.js("return Strokes.toJson(marks().fg)") == drawn

    running.stop()  # a lost server is one sentence in the page
    p.wait("return !document.getElementById('error').hidden", 30)
    assert p.error().startswith("lost the server")
