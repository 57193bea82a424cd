"""``crfedit ui``'s server through an HTTP client: every endpoint, and what it refuses.

The server runs on a thread of this process (``run_in_thread``) over the shared edit fixture
(3 chairs at 32²).  Refusals are checked to be one-line errors that leave the stack and the
work dir as they were.
"""

from __future__ import annotations

import asyncio
import importlib.util
import io
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("aiohttp", reason="crfedit ui needs the [ui] extra (aiohttp)")

from crfedit.delta import apply_deltas, check_stack, read_delta  # noqa: E402
from crfedit.errors import CrfError  # noqa: E402
from crfedit.model import load_model  # noqa: E402
from crfedit.renderer import render_camera  # noqa: E402
from crfedit.ui.server import MAX_BODY, compute_threads, open_page_session, run_in_thread  # noqa: E402
from crfedit.ui.session import open_session  # noqa: E402

from cli_helpers import assert_user_error, invoke  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def bench_ui():
    """benchmarks/ui.py, the page driver the browser test and the benchmark share."""
    spec = importlib.util.spec_from_file_location("bench_ui", ROOT / "benchmarks" / "ui.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def png_array(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


class Client:
    """A tiny HTTP client for the running server: (status, headers, body) per call."""

    def __init__(self, running, session, workdir: Path):
        self.running, self.session, self.workdir = running, session, workdir
        self.base = f"http://127.0.0.1:{running.port}"
        self.token = running.token

    def call(self, method: str, path: str, body=None, token: str | None = "default", headers=None, data: bytes | None = None):
        url = self.base + path
        token = self.token if token == "default" else token
        hdrs = dict(headers or {})
        if token is not None:
            hdrs["X-Crfedit-Token"] = token
        if body is not None:
            data = json.dumps(body).encode()
            hdrs["Content-Type"] = "application/json"
        req = urllib.request.Request(url, data=data, headers=hdrs, method=method)
        try:
            with urllib.request.urlopen(req, timeout=120) as r:
                return r.status, dict(r.headers), r.read()
        except urllib.error.HTTPError as e:
            return e.code, dict(e.headers), e.read()

    def get(self, path: str) -> bytes:
        status, _, body = self.call("GET", path)
        assert status == 200, body
        return body

    def post(self, path: str, body: dict, expect: int = 200) -> dict:
        status, _, raw = self.call("POST", path, body)
        assert status == expect, raw
        return json.loads(raw)

    def error(self, method: str, path: str, body=None, expect: int = 400, **kw) -> str:
        status, _, raw = self.call(method, path, body, **kw)
        assert status == expect, (status, raw)
        message = json.loads(raw)["error"]
        assert "\n" not in message and message
        return message

    def wait_job(self, timeout: float = 120.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job = json.loads(self.get("/api/job"))
            if job["state"] != "running":
                return job
            time.sleep(0.05)
        raise TimeoutError("the edit did not finish")

    def edit(self, body: dict) -> dict:
        self.post("/api/edit", body, expect=202)
        return self.wait_job()

    def files(self) -> list[str]:
        return sorted(p.name for p in self.workdir.rglob("*")) if self.workdir.exists() else []


@pytest.fixture(scope="module")
def scene(edit_category):
    """(model file, data folder, a stroke on the largest part of instance 0's train:0 view, that
    part, the part map, the rendered opacity)."""
    path, model, category = edit_category
    view = category.instance(0).view("train:0")
    opacity = render_camera(model.field_for(0), view.camera, 0).opacity.numpy()
    stroke, part = bench_ui().stroke_on_part(view.parts, opacity)
    return path, category.root, stroke, part, view.parts, opacity


@pytest.fixture
def ui(scene, tmp_path):
    path, data, *_ = scene
    session, _ = open_session(path, data, [], tmp_path / "work", "cpu")
    running = run_in_thread(session)
    yield Client(running, session, tmp_path / "work")
    running.stop()


def strokes(scene, radius=1.0):
    return {"strokes": [scene[2]], "radius": radius}


def color_body(scene, **extra):
    fg = strokes(scene)
    return {"kind": "color", "instance": 0, "view": "train:0", "views": [{"view": "train:0", "fg": fg}], "color": "#2040ff", **extra}


# ----------------------------------------------------------------------------- page and security


def test_page_and_assets_are_served_with_the_token_and_fetch_nothing_else(ui):
    status, headers, body = ui.call("GET", f"/?token={ui.token}", token=None)
    assert status == 200 and f'content="{ui.token}"' in body.decode()
    csp = headers["Content-Security-Policy"]
    assert "default-src 'none'" in csp and "connect-src 'self'" in csp and "frame-ancestors 'none'" in csp
    static = ROOT / "crfedit" / "ui" / "static"
    for name, kind in (("app.js", "text/javascript"), ("edit.js", "text/javascript"), ("strokes.js", "text/javascript"), ("style.css", "text/css")):
        status, headers, body = ui.call("GET", f"/static/{name}")
        assert status == 200 and headers["Content-Type"].startswith(kind) and body == (static / name).read_bytes()
    for f in static.iterdir():  # offline: no CDN, font or analytics address anywhere in the page
        text = f.read_text()
        assert "http://" not in text and "https://" not in text and "@import" not in text and "url(" not in text, f.name
    assert "no such file" in ui.error("GET", "/static/secret.py", expect=404)
    assert "no such file" in ui.error("GET", "/static/..%2Fserver.py", expect=404)
    assert ui.call("GET", "/static/../server.py")[0] == 404


@pytest.mark.parametrize("method,path", [
    ("GET", "/"), ("GET", "/static/app.js"), ("GET", "/api/state"), ("GET", "/api/view?instance=0&view=train:0"),
    ("GET", "/api/thumb?instance=0"), ("GET", "/api/angles?instance=0"), ("GET", "/api/photo?instance=0&split=train&index=0"), ("POST", "/api/select"),
    ("POST", "/api/select/clear"), ("POST", "/api/edit"), ("GET", "/api/job"), ("POST", "/api/cancel"),
    ("POST", "/api/stack/toggle"), ("POST", "/api/stack/move"), ("POST", "/api/stack/save"),
    ("GET", "/api/stack/download?id=1"), ("POST", "/api/bake"), ("GET", "/api/shell"), ("GET", "/api/ws"),
])
def test_every_endpoint_refuses_a_missing_or_wrong_token(ui, method, path):
    body = {} if method == "POST" else None
    assert "session token" in ui.error(method, path, body, expect=403, token=None)
    wrong = ui.token[:-1] + ("y" if ui.token.endswith("x") else "x")  # one character off, never the token itself
    assert "session token" in ui.error(method, path, body, expect=403, token=wrong)
    assert "session token" in ui.error(method, path + ("&" if "?" in path else "?") + "token=nope", body, expect=403, token=None)
    assert ui.files() == []


def test_token_in_the_query_or_the_header_is_accepted(ui):
    assert ui.call("GET", f"/api/state?token={ui.token}", token=None)[0] == 200
    assert ui.call("GET", "/api/state")[0] == 200


def test_host_and_origin_are_checked(ui):
    assert "Host" in ui.error("GET", "/api/state", expect=403, headers={"Host": f"evil.example:{ui.running.port}"})
    assert "Host" in ui.error("GET", "/api/state", expect=403, headers={"Host": "127.0.0.1:1"})
    assert ui.call("GET", "/api/state", headers={"Host": f"localhost:{ui.running.port}"})[0] == 200
    assert ui.call("GET", "/api/state", headers={"Host": f"LocalHost:{ui.running.port}"})[0] == 200  # host names ignore case
    assert "Method Not Allowed" in ui.error("GET", "/api/edit", expect=405)  # the one-line JSON of every refusal
    status, headers, _ = ui.call("PUT", "/api/edit")
    assert status == 405 and "POST" in headers.get("Allow", ""), headers  # HTTP requires the methods a 405 allows
    message = ui.error("POST", "/api/select/clear", {"instance": 0}, expect=403, headers={"Origin": "http://evil.example"})
    assert "may not drive" in message
    ok = {"Origin": f"http://127.0.0.1:{ui.running.port}"}
    assert ui.call("POST", "/api/select/clear", {"instance": 0}, headers=ok)[0] == 200


def test_a_wildcard_bind_takes_ip_addresses_and_this_machine_s_name_but_no_other_name():
    """Bound to every address, the Host check still refuses a DNS name that is not this machine's
    (DNS rebinding needs one) and any other port."""
    import socket

    from crfedit.ui.server import Server

    server = Server(None, "t", "0.0.0.0")
    server.port = 8804
    for host in ("127.0.0.1:8804", "192.168.1.7:8804", "[::1]:8804", "[fe80::1]:8804", "localhost:8804",
                 f"{socket.gethostname()}:8804"):
        assert server._host_ok(host), host
    for host in ("evil.example:8804", "192.168.1.7:1", "192.168.1.7", "", "[::1]", ":8804"):
        assert not server._host_ok(host), host


def test_websocket_needs_the_token_and_this_origin(ui):
    import aiohttp

    async def connect(query: str, origin: str | None = None):
        async with aiohttp.ClientSession() as s:
            try:
                async with s.ws_connect(f"{ui.base}/api/ws?{query}", origin=origin) as ws:
                    return (await ws.receive_json())["type"]
            except aiohttp.WSServerHandshakeError as e:
                return e.status

    assert asyncio.run(connect(f"token={ui.token}&client=a")) == "hello"
    assert asyncio.run(connect("client=a")) == 403
    assert asyncio.run(connect(f"token={ui.token}", origin="http://evil.example")) == 403


def test_oversized_and_malformed_bodies_are_refused_and_nothing_is_written(ui, scene):
    big = b'{"kind": "color", "pad": "' + b"x" * (MAX_BODY + 10) + b'"}'
    assert "larger than" in ui.error("POST", "/api/edit", data=big, expect=413, headers={"Content-Type": "application/json"})
    assert "not valid JSON" in ui.error("POST", "/api/edit", data=b"{nope", headers={"Content-Type": "application/json"})
    assert "JSON object" in ui.error("POST", "/api/select", [1, 2])
    assert "too deeply" in ui.error("POST", "/api/select", data=b"[" * 100_000 + b"]" * 100_000,
                                    headers={"Content-Type": "application/json"})
    for path in ("/api/stack/download?id=%C2%B2", "/api/view?instance=%C2%B2&az=0&el=0"):  # "²": isdigit, but not int()
        ui.error("GET", path)
    assert json.loads(ui.get("/api/job"))["state"] == "none"
    assert ui.session.entries == [] and ui.files() == []


# ----------------------------------------------------------------------------- views


def test_state_views_thumbnails_and_photos(ui, edit_category):
    _, model, category = edit_category
    info = json.loads(ui.get("/api/state"))
    assert info["instances"] == model.names and info["width"] == 32 and info["stack"] == [] and info["state"] == "base"
    assert info["splits"]["train"] == [8, 8, 8] and "train" in info["photos"] and info["busy"] is False
    view = png_array(ui.get("/api/view?instance=0&view=train:0"))
    expected = render_camera(model.field_for(0), model.views["train"].cameras(0)[0], 0).rgb.numpy()
    assert view.shape == (32, 32, 3) and np.abs(view / 255.0 - expected).max() <= 0.5 / 255 + 1e-6
    orbit = ui.get("/api/view?instance=chair_001&az=30&el=20")
    assert png_array(orbit).shape == (32, 32, 3) and orbit != ui.get("/api/view?instance=chair_001&az=40&el=20")
    assert ui.get("/api/view?instance=0&view=train:0&state=base") == ui.get("/api/view?instance=0&view=train:0")
    assert png_array(ui.get("/api/thumb?instance=2")).shape == (32, 32, 3)
    photo = png_array(ui.get("/api/photo?instance=0&split=train&index=3"))
    assert np.array_equal(photo, np.round(category.instance(0).view("train:3").rgb * 255).astype(np.uint8))
    assert "unknown instance" in ui.error("GET", "/api/view?instance=nobody&view=train:0")
    assert "out of range" in ui.error("GET", "/api/view?instance=0&view=train:99")
    assert "SPLIT:INDEX" in ui.error("GET", "/api/view?instance=0&view=/etc/passwd")
    assert "elevation" in ui.error("GET", "/api/view?instance=0&az=0&el=95")
    assert "az=" in ui.error("GET", "/api/view?instance=0&az=x&el=0")
    assert "no view" in ui.error("GET", "/api/photo?instance=0&split=train&index=50")
    # where each stored view looks from, for the page's orbit sliders
    angles = json.loads(ui.get("/api/angles?instance=chair_001"))
    assert set(angles) == set(model.views) and len(angles["train"]) == 8
    for (az, el), cam in zip(angles["train"], model.views["train"].cameras(1)):
        eye = cam.c2w[:3, 3]
        assert abs(((np.degrees(np.arctan2(eye[1], eye[0])) - az) + 180) % 360 - 180) <= 0.5
        assert abs(np.degrees(np.arcsin(eye[2] / np.linalg.norm(eye))) - el) <= 0.5
    assert "unknown instance" in ui.error("GET", "/api/angles?instance=nobody")


def test_select_tints_the_selection_over_any_view_until_cleared(ui, scene):
    body = {"instance": 0, "views": [{"view": "train:0", "fg": strokes(scene)}]}
    info = ui.post("/api/select", body)
    assert 0 < info["selected_cells"] < info["occupied_cells"] and info["views"] == 1
    plain = png_array(ui.get("/api/view?instance=0&view=train:0"))
    tinted = png_array(ui.get("/api/view?instance=0&view=train:0&tint=1"))
    changed = np.abs(tinted.astype(int) - plain).max(-1) > 10
    row = int(scene[2][0][1])
    assert changed[row, int(scene[2][0][0]):int(scene[2][1][0]) + 1].mean() > 0.8  # under the stroke
    assert not changed[scene[5] < 0.5].any()  # never off the object
    other = ui.get("/api/view?instance=0&view=train:4&tint=1")  # switching views keeps the selection
    assert other != ui.get("/api/view?instance=0&view=train:4")
    # the page sends the edit kind, and says what the strokes and the mirror did: every kind's
    # selection lifts the strokes' centres, a recolour's reads the mirror and tries the colour join, an addition's neither
    added = ui.post("/api/select", {**body, "kind": "add"})
    assert info["strokes"].startswith(("their centres lifted (", "lifted whole (")) and added["strokes"] == info["strokes"]
    assert info["mirror"].startswith(("not used (", "the plane normal to ")) and added["mirror"] is None
    assert info["colour_join"].startswith(("took the cells of the scribbled colour (", "refused: ")) and added["colour_join"] is None
    # the page's line lists the same summaries, in select's order, the ones that apply
    from crfedit.edit.selection import SUMMARIES

    for said in (info, added):
        fields = [(label, said[label.replace(" ", "_")]) for label, _ in SUMMARIES]
        assert said["summaries"] == [[label, line] for label, line in fields if line is not None]
    assert ["colour join", info["colour_join"]] in info["summaries"] and "colour join" not in dict(added["summaries"])
    assert "a selection for 'paint'" in ui.error("POST", "/api/select", {**body, "kind": "paint"})
    ui.post("/api/select/clear", {"instance": 0})
    assert "nothing is selected" in ui.error("GET", "/api/view?instance=0&view=train:0&tint=1")


def test_strokes_on_one_instance_reuse_its_cell_points(ui, scene):
    """The page re-selects at every stroke: the cells' density ascent, the same for any
    scribble, runs once per instance and stack state, and the selection is the one a fresh
    ``select`` makes (``test_cell_points_handed_in_give_the_same_selection``)."""
    body = {"instance": 0, "views": [{"view": "train:0", "fg": strokes(scene)}]}
    first = ui.post("/api/select", body)
    wider = ui.post("/api/select", {**body, "views": [{"view": "train:0", "fg": strokes(scene, radius=2.0)}]})
    removal = ui.post("/api/select", {**body, "kind": "remove"})
    assert first["selected_cells"] > 0 and wider["selected_cells"] > 0 and removal["selected_cells"] > 0
    assert [key[1:] for key in ui.session._cell_points] == [(0, 1.0)]  # one entry: instance 0, the default ascent
    assert [key[1:] for key in ui.session._views] == [(0, "train:0")]  # and the scribbled view's render, once
    # what the page selects is what select() makes from the same strokes, bit for bit
    from crfedit.edit.selection import ScribbleView, options_for, select
    from crfedit.ui.recipe import parse_scribbles

    model = ui.session.model
    (drawn,) = parse_scribbles(body["views"], model, 0)
    page = ui.session._selection(model, ui.session.state_key, 0, (drawn,), "remove")
    fresh = select(model, 0, [ScribbleView(drawn.view.camera, drawn.fg.mask, None)], options_for("remove"))
    assert torch.equal(page.values, fresh.values)
    ui.post("/api/edit", color_body(scene), expect=202)
    assert ui.wait_job()["state"] == "done"
    ui.post("/api/select", body)  # a new stack state: its own cell points
    assert [key[1:] for key in ui.session._cell_points] == [(0, 1.0), (0, 1.0)]


def test_a_view_is_rendered_once_and_tinted_by_each_selection(ui, scene, monkeypatch):
    """The page keeps its views' renders per instance and stack state: once a view is shown,
    a Select and its tinted views (the turntable) render nothing again, and the tinted view is
    the one preview() renders afresh, bit for bit."""
    import crfedit.edit.selection.tint as tint
    import crfedit.ui.session as session_module

    body = {"instance": 0, "views": [{"view": "train:0", "fg": strokes(scene)}]}
    ui.get("/api/view?instance=0&view=train:0")
    ui.get("/api/view?instance=0&view=train:4")
    calls = []
    real = session_module.render_camera
    monkeypatch.setattr(session_module, "render_camera", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(tint, "render_camera", lambda *a, **k: calls.append(1) or real(*a, **k))
    for radius in (1.0, 2.0):  # two scribbles: two selections, each tinted over the kept views
        ui.post("/api/select", {**body, "views": [{"view": "train:0", "fg": strokes(scene, radius=radius)}]})
        tinted = ui.get("/api/view?instance=0&view=train:4&tint=1")
    assert calls == []
    model = ui.session.model
    sel = ui.session._selection(model, ui.session.state_key, 0, *ui.session._shown_scribbles(0))
    camera = model.views["train"].cameras(0)[4]
    monkeypatch.setattr(tint, "render_camera", real)
    assert tinted == session_module.png_bytes(tint.preview(model, sel, camera))


def test_a_removal_s_shown_view_is_kept_for_the_next_request(ui, scene):
    """The view a removal re-rendered to show its result is kept under the key the untinted
    view is asked for, so the page's next request for it is not rendered again."""
    job = ui.edit({"kind": "remove", "instance": 0, "view": "train:0", "views": [{"view": "train:0", "fg": strokes(scene)}], "steps": 2})
    assert job["state"] == "done", job
    key = (ui.session.state_key, 0, "train:0", None)
    assert key in ui.session._renders and key[:3] in ui.session._views  # its PNG, and its render for a Select on it
    assert ui.get("/api/view?instance=0&view=train:0") == ui.session._renders[key]


@pytest.mark.parametrize("fg,message", [
    ({"strokes": []}, "scribble is empty"),
    ({"strokes": "x"}, "expected"),
    ({"strokes": [[[1, "a"]]]}, "stroke 0 is not a list"),
    ({"strokes": [[[1, 2, 3]]]}, "stroke 0 is not a list"),
    ({"strokes": [[[1, 2]]], "radius": -1}, "radius"),
    ({"strokes": [[[1, 2]]], "radius": 1e9}, "radius"),
    ({"strokes": [[[0, 0]]] * 501}, "at most 500"),
    ({"strokes": [[[0, 0]] * 20001]}, "at most 20000"),
    ({"strokes": [{"points": [[1, 2]], "radius": "big"}]}, "radius"),
])
def test_malformed_strokes_are_refused_with_one_line_and_nothing_changes(ui, fg, message):
    for path, body in (("/api/select", {"instance": 0, "views": [{"view": "train:0", "fg": fg}]}),
                       ("/api/edit", {"kind": "color", "instance": 0, "view": "train:0", "color": "red",
                                      "views": [{"view": "train:0", "fg": fg}]})):
        assert message in ui.error("POST", path, body)
    assert ui.session.entries == [] and ui.files() == [] and json.loads(ui.get("/api/job"))["state"] == "none"


def test_bad_edit_requests_are_refused(ui, scene):
    cases = [
        ({"kind": "paint"}, "kind"),
        (color_body(scene, color="#12"), "#rgb"),
        (color_body(scene, view="train:1"), "no 'edit here' strokes"),
        (color_body(scene, steps=0), "steps"),
        (color_body(scene, lr="fast"), "lr"),
        (color_body(scene, method="magic"), "method"),
        ({"kind": "transfer", "instance": 0}, "pick an instance"),
        ({"kind": "add", "instance": 0, "view": "train:0", "donor": 1, "offset": [1, 1]}, "scribble the part to copy"),
        ({"kind": "add", "instance": 0, "view": "train:0", "donor": 1, "copy": strokes(scene)}, "click where to paste"),
        ({"kind": "remove", "instance": 0, "view": "train:0", "views": [{"view": "train:0", "fg": {"strokes": [[[0, 0]]]}}]},
         None),  # a scribble on the background: refused when the edit runs
    ]
    for body, message in cases:
        if message is not None:
            assert message in ui.error("POST", "/api/edit", body)
    job = ui.edit(cases[-1][0])
    assert job["state"] == "error" and "background" in job["message"]
    assert ui.session.entries == [] and ui.files() == []


# ----------------------------------------------------------------------------- edits and the stack


def test_colour_edit_then_toggle_save_download_bake(ui, scene, edit_category, tmp_path):
    path, model, _ = edit_category
    before = ui.get("/api/view?instance=0&view=train:0")
    job = ui.edit(color_body(scene))
    assert job["state"] == "done", job
    result = job["result"]
    assert [r["kind"] for r in result["stack"]] == ["color"] and result["image"].startswith("data:image/png;base64,")
    after = ui.get("/api/view?instance=0&view=train:0")
    mask = np.zeros((32, 32), bool)
    (x0, y), (x1, _) = scene[2]
    mask[int(y), int(x0):int(x1) + 1] = True
    target = np.array([0x20, 0x40, 0xFF])
    dist = lambda img: np.abs(png_array(img)[mask].astype(float) - target).mean()
    assert dist(after) < 0.7 * dist(before)
    assert png_array(ui.get("/api/view?instance=1&view=train:0")).tobytes() == png_array(
        ui.get("/api/view?instance=1&view=train:0&state=base")).tobytes()  # other instances untouched
    entry = result["entry"]
    off = ui.post("/api/stack/toggle", {"id": entry, "enabled": False})
    assert off["state"] == "base" and off["stack"][0]["enabled"] is False
    assert ui.get("/api/view?instance=0&view=train:0") == before
    assert ui.post("/api/stack/toggle", {"id": entry, "enabled": True})["state"] == result["state"]
    assert ui.get("/api/view?instance=0&view=train:0") == after
    saved = Path(ui.post("/api/stack/save", {"id": entry})["path"])
    assert saved.parent == ui.workdir and saved.name == "01-color-chair_000.safetensors"
    base, _ = load_model(path)
    check_stack(base, [read_delta(saved)])
    status, headers, data = ui.call("GET", f"/api/stack/download?id={entry}")
    assert status == 200 and saved.name in headers["Content-Disposition"]
    (tmp_path / "downloaded.safetensors").write_bytes(data)  # safetensors orders its metadata freely: compare contents
    downloaded = read_delta(tmp_path / "downloaded.safetensors")
    assert downloaded.meta == read_delta(saved).meta and downloaded.fingerprint == ui.session.pinned[entry].fingerprint
    baked = Path(ui.post("/api/bake", {"name": "baked.safetensors"})["model"])
    edited, _ = load_model(baked)
    camera = model.views["train"].cameras(0)[0]
    expected = render_camera(apply_deltas(base, [read_delta(saved)]).field_for(0), camera, 0).rgb
    assert torch.equal(render_camera(edited.field_for(0), camera, 0).rgb, expected)
    ui.post("/api/stack/toggle", {"id": entry, "enabled": False})
    assert "nothing to fold" in ui.error("POST", "/api/bake", {})


def test_a_removal_downloads_as_saved_and_nothing_is_overwritten(ui, scene, edit_category, tmp_path):
    """Download gives the bytes Save writes (a removal's grid change bit-packed, a file every
    command reads); Save and Bake never overwrite a file of the work dir, and saving an edit
    twice writes one file."""
    path, _, _ = edit_category
    job = ui.edit({"kind": "remove", "instance": 0, "view": "train:0", "views": [{"view": "train:0", "fg": strokes(scene)}], "steps": 2})
    assert job["state"] == "done", job
    entry = job["result"]["entry"]
    first = ui.post("/api/stack/save", {"id": entry})
    saved, again = Path(first["path"]), ui.post("/api/stack/save", {"id": entry})
    assert Path(again["path"]) == saved and ui.files() == [saved.name]
    assert (first["again"], again["again"]) == (False, True)  # the page says "already holds this edit", not "saved"
    _, _, data = ui.call("GET", f"/api/stack/download?id={entry}")
    assert len(data) == saved.stat().st_size == json.loads(ui.get("/api/state"))["stack"][0]["bytes"]
    (tmp_path / "downloaded.safetensors").write_bytes(data)
    base, _ = load_model(path)
    check_stack(base, [read_delta(tmp_path / "downloaded.safetensors")])
    (ui.workdir / "theirs.safetensors").write_bytes(b"not ours")
    assert "already in the work dir" in ui.error("POST", "/api/stack/save", {"id": entry, "name": "theirs.safetensors"})
    assert (ui.workdir / "theirs.safetensors").read_bytes() == b"not ours"
    saved.write_bytes(b"someone else's file")  # the edit's default name now holds another file
    again = Path(ui.post("/api/stack/save", {"id": entry})["path"])
    assert again.name == saved.name.replace(".safetensors", "-2.safetensors") and saved.read_bytes() == b"someone else's file"
    model_name = f"{Path(path).stem}-baked.safetensors"
    (ui.workdir / model_name).write_bytes(b"an earlier bake")
    baked = ui.post("/api/bake", {})
    assert Path(baked["model"]).name == model_name.replace(".safetensors", "-2.safetensors")
    assert [Path(p).name for p in baked["edits"]] == [again.name]  # the file that holds the edit already
    assert (ui.workdir / model_name).read_bytes() == b"an earlier bake"
    assert "already in the work dir" in ui.error("POST", "/api/bake", {"name": "theirs.safetensors"})
    # the same edit saved again, the same stack baked again: the files are left as they are
    stamps = {p.name: p.stat().st_mtime_ns for p in ui.workdir.iterdir()}
    assert Path(ui.post("/api/stack/save", {"id": entry})["path"]) == again
    rebaked = ui.post("/api/bake", {})
    assert rebaked["model"] == baked["model"] and rebaked["again"] is True and baked["again"] is False
    assert {p.name: p.stat().st_mtime_ns for p in ui.workdir.iterdir()} == stamps
    # the edit's file under another name (it moved in the stack, or the user renamed it): found, not written again
    moved = again.rename(ui.workdir / "renamed.safetensors")
    found = ui.post("/api/stack/save", {"id": entry})
    assert (Path(found["path"]), found["again"]) == (moved, True) and not again.exists()


def test_a_stack_change_reaches_every_open_page(ui, scene):
    """A toggle in one tab is heard by another tab's WebSocket (type "stack", with the stack and
    state), so its panel and views follow instead of going stale."""
    import aiohttp

    job = ui.edit(color_body(scene, steps=2))
    entry = job["result"]["entry"]

    async def run():
        async with aiohttp.ClientSession(headers={"X-Crfedit-Token": ui.token}) as s:
            async with s.ws_connect(f"{ui.base}/api/ws?client=tab2") as ws:
                assert (await ws.receive_json())["type"] == "hello"
                r = await s.post(f"{ui.base}/api/stack/toggle", json={"id": entry, "enabled": False})
                reply = await r.json()
                heard = await ws.receive_json()
                return reply, heard

    reply, heard = asyncio.run(run())
    assert heard == {"type": "stack", "stack": reply["stack"], "state": reply["state"]} and reply["state"] == "base"


@pytest.mark.parametrize("name", ["../escape.safetensors", "/tmp/abs.safetensors", "sub/dir.safetensors", "x.txt",
                                  ".hidden.safetensors", "a..b.safetensors", "", 7])
def test_file_names_outside_the_work_dir_are_refused(ui, scene, name, tmp_path):
    ui.edit(color_body(scene, steps=2))
    assert "plain file name" in ui.error("POST", "/api/stack/save", {"id": 1, "name": name})
    assert "plain file name" in ui.error("POST", "/api/bake", {"name": name})
    assert ui.files() == [] and not (tmp_path / "escape.safetensors").exists()


def test_diverged_edit_is_one_sentence_and_the_stack_is_unchanged(ui, scene):
    job = ui.edit(color_body(scene, lr=1e30, steps=3))
    assert job["state"] == "error" and "diverged" in job["message"] and "\n" not in job["message"]
    assert ui.session.entries == [] and json.loads(ui.get("/api/state"))["stack"] == [] and ui.files() == []


def test_second_edit_is_refused_while_one_runs_and_cancel_stops_it(ui, scene):
    ui.post("/api/edit", color_body(scene, steps=5000), expect=202)
    assert "already running" in ui.error("POST", "/api/edit", color_body(scene), expect=409)
    assert "already running" in ui.error("POST", "/api/stack/toggle", {"id": 1, "enabled": False}, expect=409)
    assert json.loads(ui.get("/api/state"))["busy"] is True
    ui.post("/api/cancel", {})
    job = ui.wait_job()
    assert job["state"] == "cancelled" and job["step"] < 5000
    assert ui.session.entries == [] and ui.files() == []
    assert "no edit is running" in ui.error("POST", "/api/cancel", {})


def test_a_closed_tab_cancels_its_running_edit(ui, scene):
    import aiohttp

    async def run():
        async with aiohttp.ClientSession(headers={"X-Crfedit-Token": ui.token}) as s:
            async with s.ws_connect(f"{ui.base}/api/ws?client=tab1") as ws:
                assert (await ws.receive_json())["type"] == "hello"
                r = await s.post(f"{ui.base}/api/edit", json=color_body(scene, steps=5000, client="tab1"))
                assert r.status == 202
                while (msg := await ws.receive_json())["type"] != "progress":
                    pass
                assert msg["kind"] == "color"  # what another tab shows while it runs
            # the tab is gone

    asyncio.run(run())
    job = ui.wait_job()
    assert job["state"] == "cancelled" and job["step"] < 5000
    assert ui.session.entries == [] and ui.files() == []


def test_edits_reorder_only_past_edits_of_other_tensors(ui, scene):
    assert ui.edit(color_body(scene, steps=3))["state"] == "done"
    assert ui.edit({"kind": "transfer", "instance": 2, "shape_from": 1})["state"] == "done"
    assert ui.edit(color_body(scene, steps=3, color="#ffff00"))["state"] == "done"
    rows = json.loads(ui.get("/api/state"))["stack"]
    assert [(r["up"], r["down"]) for r in rows] == [(False, True), (True, True), (True, False)]
    moved = ui.post("/api/stack/move", {"id": 2, "to": 1})["stack"]  # a transfer of chair_002 first: allowed
    assert [r["id"] for r in moved] == [2, 1, 3]
    assert "order matters" in ui.error("POST", "/api/stack/move", {"id": 3, "to": 2})  # two recolours of chair_000
    assert [r["id"] for r in json.loads(ui.get("/api/state"))["stack"]] == [2, 1, 3]
    assert "no such edit" in ui.error("POST", "/api/stack/toggle", {"id": 99, "enabled": False})
    assert "position" in ui.error("POST", "/api/stack/move", {"id": 1, "to": 9})
    for i in (1, 2, 3):  # the re-pinned files form a stack that `crfedit edits check` accepts
        ui.post("/api/stack/save", {"id": i})
    base, _ = load_model(scene[0])
    check_stack(base, [read_delta(ui.workdir / n) for n in ("01-transfer-chair_002.safetensors", "02-color-chair_000.safetensors",
                                                            "03-color-chair_000.safetensors")])


def test_copy_as_shell_replays_the_stack_to_the_same_edit_files(ui, scene, tmp_path):
    """Every kind of edit, a two-view selection and an orbit view, replayed by the shell lines:
    the commands write edit files with the page's fingerprints."""
    fg = strokes(scene)
    orbit = {"azimuth": 20, "elevation": 25}
    keep_only = {"view": {"azimuth": 200, "elevation": 25}, "bg": {"strokes": [[[3, 3], [9, 9]]], "radius": 1.5}}
    two_views = {"kind": "color", "instance": 0, "view": keep_only["view"], "color": "#2040ff", "steps": 5,  # applied on the keep-only view
                 "views": [{"view": "train:0", "fg": fg, "bg": {"strokes": [[[2, 2]]], "radius": 1}}, {"view": orbit, "fg": fg}, keep_only]}
    bodies = [two_views,
              {"kind": "remove", "instance": 1, "view": orbit, "views": [{"view": orbit, "fg": fg}], "steps": 3},
              {"kind": "add", "instance": 0, "view": "train:0", "donor": 1, "copy": fg, "offset": [1, -2], "steps": 3},
              {"kind": "transfer", "instance": 2, "color_from": 0}]
    for body in bodies:
        job = ui.edit(body)
        assert job["state"] == "done", job
        # applied from the keep-only view, the edit is drawn on the scribbled one: its render is not the view on screen
        assert ("image" in job["result"]) == (body is not two_views and body["kind"] != "transfer"), (body["kind"], list(job["result"]))
    script = ui.get("/api/shell").decode()
    assert script.count("crfedit ") >= 5 and "crfedit select" in script and "--selection" in script
    assert "--scribble none --keep" in script and "--keep none" in script  # the keep-only view; orbit's view without keep strokes
    env = dict(os.environ, CRFEDIT_THREADS="1", PYTHONPATH=str(ROOT))
    run = subprocess.run(["bash", "-c", f'crfedit() {{ "{sys.executable}" -m crfedit "$@"; }}\n{script}'],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    made = sorted((tmp_path / "crfedit-replay").glob("0*-*-chair_*.safetensors"))
    assert [read_delta(p).fingerprint for p in made] == [r["fingerprint"] for r in json.loads(ui.get("/api/state"))["stack"]]
    assert "optimized again" not in script  # every edit where it was made: the replay is exact, and says nothing
    # an edit turned off under later ones: the replay optimizes again those that read what it changed, and
    # says so. The recolour of chair 0 (F_rad and its code, unless its refit trained the bottleneck) is read by
    # no later edit: the addition onto chair 0 reads its density and features. The removal of chair 1, the
    # addition's donor, is. The transfer takes its code again, exactly.
    stack = json.loads(ui.get("/api/state"))["stack"]
    noted = lambda: [ln for ln in ui.get("/api/shell").decode().splitlines() if "optimized again" in ln]
    colour_only = all(m.startswith(("F_rad.", "color_codes")) for m in stack[0]["modules"])
    ui.post("/api/stack/toggle", {"id": stack[0]["id"], "enabled": False})
    assert len(noted()) == (0 if colour_only else 1), noted()
    ui.post("/api/stack/toggle", {"id": stack[0]["id"], "enabled": True})
    ui.post("/api/stack/toggle", {"id": stack[1]["id"], "enabled": False})
    lines = ui.get("/api/shell").decode().splitlines()
    assert [lines[i + 1].split(" --instance")[0] for i, ln in enumerate(lines) if "optimized again" in ln] == [
        "crfedit add " + shlex.quote(str(Path(scene[0]).resolve()))]


def test_edits_given_with_edit_start_the_stack(scene, tmp_path):
    path, data, *_ = scene
    session, _ = open_session(path, None, [], tmp_path / "w1", "cpu")
    running = run_in_thread(session)
    try:
        client = Client(running, session, tmp_path / "w1")
        client.edit(color_body(scene, steps=2))
        saved = Path(client.post("/api/stack/save", {"id": 1})["path"])
    finally:
        running.stop()
    again, _ = open_session(path, None, [saved], tmp_path / "w2", "cpu")
    info = again.info()
    assert [(r["kind"], r["source"], r["enabled"]) for r in info["stack"]] == [("color", saved.name, True)]
    assert info["photos"] == [] and f"--edit {shlex.quote(str(saved.resolve()))}" in again.shell()
    with pytest.raises(CrfError, match="no dataset"):
        again.photo(0, "train", 0)


def test_the_server_shares_the_cpu_threads_between_its_two_compute_threads(scene, tmp_path):
    """Each compute thread (renders, edits) keeps an OpenMP team: together they get the threads
    one process would (compute_threads), and the model loads on a thread that ends, so the
    caller keeps no third team.  A missing model is still a one-line error."""
    import threading

    assert [compute_threads(n) for n in (1, 2, 3, 4, 16)] == [1, 1, 1, 2, 8]
    before = torch.get_num_threads()
    try:
        session, _ = open_page_session(scene[0], None, [], tmp_path / "w", "cpu", threads=4)
        assert torch.get_num_threads() == 2
        assert session.info()["instances"] == ["chair_000", "chair_001", "chair_002"]
        assert not [t for t in threading.enumerate() if t.name.startswith("crfedit-load")]
        with pytest.raises(CrfError, match="no-such.safetensors"):
            open_page_session(tmp_path / "no-such.safetensors", None, [], tmp_path / "w", "cpu", threads=1)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


# ----------------------------------------------------------------------------- the command


def test_ui_command_without_the_extra_names_the_install(monkeypatch, scene):
    monkeypatch.setitem(sys.modules, "aiohttp", None)
    assert_user_error(invoke("ui", scene[0]), "pip install -e '.[ui]'")


def test_ui_command_warns_when_bound_beyond_this_machine(monkeypatch, scene, tmp_path):
    import crfedit.ui.server as server

    seen = {}
    monkeypatch.setattr(server, "serve", lambda session, host, port, on_ready: (seen.update(host=host), on_ready("http://x/?token=t")))
    before = torch.get_num_threads()
    try:
        result = invoke("ui", scene[0], "--host", "0.0.0.0", "--workdir", tmp_path / "w")
    finally:
        torch.set_num_threads(before)  # the command set the page's share of the threads
    assert result.exit_code == 0, result.output
    assert "reachable from other machines" in result.output and "open http://x/?token=t" in result.output
    assert "CPU thread" in result.output and "of the page's two compute threads" in result.output
    assert seen["host"] == "0.0.0.0" and not (tmp_path / "w").exists()


def test_a_page_that_cannot_listen_names_what_to_change(scene, tmp_path):
    """A port in use is the port's fault; a host that does not resolve or is not this machine's
    is the host's (it said "pick another --port" for both, with --port 0 too)."""
    import errno
    import socket

    from crfedit.ui.server import _listen_fix, serve
    from crfedit.ui.session import open_session

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        session, _ = open_session(scene[0], None, [], tmp_path / "w", "cpu")
        port = taken.getsockname()[1]
        with pytest.raises(CrfError, match=rf"^cannot listen on 127\.0\.0\.1:{port} \(.*\); pick another --port \(--port 0 takes a free one\)$"):
            serve(session, "127.0.0.1", port, lambda url: None)
    finally:
        taken.close()
    host_fix = "--host h is not an address of this machine (127.0.0.1 for this machine alone, 0.0.0.0 for every interface)"
    assert _listen_fix(socket.gaierror(-2, "Name or service not known"), "h") == host_fix
    assert _listen_fix(OSError(errno.EADDRNOTAVAIL, "Cannot assign requested address"), "h") == host_fix
    assert _listen_fix(OSError(errno.EADDRINUSE, "Address already in use"), "h").startswith("pick another --port")


SIGNAL_ON_A_WORKER = """
import signal, sys, threading, time
from crfedit.ui.server import serve
from crfedit.ui.session import open_session
session, _ = open_session(sys.argv[1], None, [], sys.argv[2], "cpu")
def kick():  # once the loop idles in epoll_wait, the signal goes to this thread, not the main one
    time.sleep(1.0)
    signal.pthread_kill(threading.get_ident(), signal.SIGINT)
serve(session, "127.0.0.1", 0, lambda url: threading.Thread(target=kick, daemon=True).start())
print("stopped", flush=True)
"""


def test_ui_stops_when_the_signal_lands_on_another_thread(scene, tmp_path):
    """The kernel may hand a process's SIGINT to any thread that does not block it.  Sent to a
    worker thread while the event loop sleeps in epoll_wait, asyncio.run's own handler never
    ran (the main thread never woke) and the server did not stop; the loop's signal handlers
    (its self-pipe is the wake-up fd) wake it whichever thread receives the signal."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), CRFEDIT_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", SIGNAL_ON_A_WORKER, str(scene[0]), str(tmp_path / "w")],
                          capture_output=True, text=True, env=env, timeout=30)
    assert proc.returncode == 0 and "stopped" in proc.stdout, proc.stderr


def test_a_request_in_flight_when_the_server_stops_is_answered(scene, tmp_path):
    """A view the page asks for just as the server stops reaches the render pool only after the
    stop began: the pools were shut first and it came back a 500 'unexpected RuntimeError:
    cannot schedule new futures after shutdown' (CI, once); the runner's cleanup now lets
    requests in flight finish before the pools go."""
    session, _ = open_session(scene[0], None, [], tmp_path / "w", "cpu")
    running = run_in_thread(session)
    client, run = Client(running, session, tmp_path / "w"), running.server._run

    async def late(*args, **kw):  # the request is in flight; the pool call comes after stop()
        await asyncio.sleep(0.5)
        return await run(*args, **kw)

    running.server._run = late
    answers = []
    asker = threading.Thread(target=lambda: answers.append(client.call("GET", "/api/view?instance=0&view=train:0")))
    asker.start()
    time.sleep(0.2)
    running.stop()
    asker.join(timeout=30)
    assert answers and answers[0][0] == 200, answers[0][2][:200] if answers else "no answer"


def test_ui_command_serves_until_interrupted(scene, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1", CRFEDIT_THREADS="1", PYTHONFAULTHANDLER="1")
    proc = subprocess.Popen([sys.executable, "-m", "crfedit", "ui", str(scene[0]), "--port", "0", "--workdir", str(tmp_path / "w")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if line.startswith("open "):
                url = line.split()[1]
        assert url is not None and url.startswith("http://127.0.0.1:") and "?token=" in url
        with urllib.request.urlopen(url.replace("/?token=", "/api/state?token="), timeout=30) as r:
            assert json.loads(r.read())["instances"] == ["chair_000", "chair_001", "chair_002"]
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # show where it hangs: faulthandler dumps every thread on SIGABRT
            proc.send_signal(signal.SIGABRT)
            out, err = proc.communicate(timeout=30)
            raise AssertionError(f"crfedit ui did not stop within 30 s of SIGINT; its threads:\n{err}") from None
        assert proc.returncode == 0 and "stopped" in out, err
    finally:
        if proc.poll() is None:
            proc.kill()
