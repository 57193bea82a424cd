"""What the page asks for, checked: views, strokes and edit requests, and the shell lines that
replay an edit ("Copy as shell").

Every problem is a one-line :class:`~crfedit.errors.CrfError`.  Strokes are the
``--scribble-json`` form (``{"strokes": [[[x, y], …], …], "radius": r}``, or per-stroke
``{"points": …, "radius": r}``) at the view's resolution, so an edit made in the page is the
same edit a command makes from the same files.
"""

from __future__ import annotations

import json
import math
import shlex
from dataclasses import dataclass

import numpy as np

from ..cameras import Camera
from ..data.synth import rgb_to_hex
from ..edit import EditOptions
from ..edit.scribble import parse_color, strokes_json_mask
from ..edit.supervised import turned_about_z
from ..errors import CrfError
from ..names import ADD_METHODS, EDIT_METHODS, STRATEGIES
from ..views import camera_from_json, camera_json, resolve_views

KINDS = ("color", "remove", "add", "transfer")
MAX_STROKES = 500
"""Most strokes one brush of one view may hold."""
MAX_POINTS = 20_000
"""Most stroke points one request may hold."""
MAX_VIEWS = 8
"""Most views one selection may be drawn on."""
MAX_STEPS = 5000
MAX_ELEVATION = 85.0
REPLAY_DIR = "crfedit-replay"
"""Where the replay script writes its inputs and edit files (relative to the shell's folder)."""


@dataclass(frozen=True)
class ViewRef:
    """One view of one instance as the page names it: a stored view or an orbit position."""

    label: str  # for people: "train:3", "orbit 30° / 20°"
    spec: str | None  # a --view spec naming exactly this camera (train:3); None: a camera file replays it
    camera: Camera
    key: str  # names the camera in caches (with the instance)


@dataclass(frozen=True)
class Strokes:
    """One brush's strokes on one view: the JSON as sent, and its mask [H, W] bool."""

    data: object
    mask: np.ndarray


@dataclass(frozen=True)
class ScribbleSet:
    """The strokes of one view: the part ("edit here") and what must not change ("keep")."""

    view: ViewRef
    fg: Strokes
    bg: Strokes | None


@dataclass(frozen=True)
class EditRequest:
    """One edit the page asked for, checked against the model."""

    kind: str
    instance: int
    options: EditOptions
    method: str = "selection"
    view: ViewRef | None = None
    scribbles: tuple[ScribbleSet, ...] = ()  # colour/remove: the selection's views; `view` is among them
    color: str | None = None  # '#rrggbb': how the part should appear under the scribble
    donor: int | None = None
    donor_view: ViewRef | None = None
    copy: Strokes | None = None
    offset: tuple[int, int] | None = None
    keep: Strokes | None = None  # add: keep strokes on the target view
    shape_from: int | None = None
    color_from: int | None = None
    on_screen: bool = True  # False: asked from a view with keep strokes alone, so `view` is not the one shown

    @property
    def drawn(self) -> ScribbleSet | None:
        """The scribbles of the view the edit is drawn on."""
        return next((s for s in self.scribbles if self.view is not None and s.view.key == self.view.key), None)


# ----------------------------------------------------------------------------- parsing


def _number(value, what: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not lo <= value <= hi:
        raise CrfError(f"{what} must be a number between {lo:g} and {hi:g}")
    return float(value)


def _integer(value, what: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise CrfError(f"{what} must be a whole number between {lo} and {hi}")
    return value


def instance_of(model, value, what: str = "instance") -> int:
    """An instance index from a name or an index sent by the page."""
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise CrfError(f"{what}: expected an instance name or index")
    return model.instance_index(value)


def parse_view(value, model, instance: int) -> ViewRef:
    """``"train:3"`` (a stored view of one split) or ``{"azimuth": a, "elevation": e}`` (degrees;
    the orbit of ``orbit:N@E``: around Z, looking at the origin, stored views' distance and focal)."""
    if isinstance(value, str):
        if not value.split(":", 1)[0] in ("train", "val", "test") or ":" not in value:
            raise CrfError(f"view {value[:40]!r}: expected SPLIT:INDEX such as train:3, or an orbit position")
        views = resolve_views(value, model, instance)
        if len(views) != 1:
            raise CrfError(f"view {value[:40]!r}: names {len(views)} views; pick one")
        label, camera = views[0]
        return ViewRef(label, label, camera, label)
    if not isinstance(value, dict):
        raise CrfError("view: expected SPLIT:INDEX or {\"azimuth\": degrees, \"elevation\": degrees}")
    azimuth = _number(value.get("azimuth"), "azimuth", -1e6, 1e6) % 360.0
    elevation = _number(value.get("elevation"), "elevation", -MAX_ELEVATION, MAX_ELEVATION)
    azimuth, elevation = round(azimuth, 2), round(elevation, 2)
    (_, start), = resolve_views(f"orbit:1@{elevation:.2f}", model, instance)
    camera = camera_from_json(camera_json(turned_about_z(start, azimuth)), model)
    return ViewRef(f"orbit {azimuth:g}° / {elevation:g}°", None, camera, f"orbit:{azimuth:.2f}@{elevation:.2f}")


def parse_strokes(value, camera: Camera, what: str) -> Strokes | None:
    """A brush's strokes on ``camera``'s view; None when there are none."""
    if value is None or value == [] or (isinstance(value, dict) and value.get("strokes") == []):
        return None
    strokes = value.get("strokes") if isinstance(value, dict) else value
    if isinstance(strokes, list):
        if len(strokes) > MAX_STROKES:
            raise CrfError(f"{what}: {len(strokes)} strokes; at most {MAX_STROKES}")
        points = sum(len(s.get("points", ()) if isinstance(s, dict) else s) for s in strokes if isinstance(s, (list, dict)))
        if points > MAX_POINTS:
            raise CrfError(f"{what}: {points} stroke points; at most {MAX_POINTS}")
    return Strokes(value, strokes_json_mask(value, camera.width, camera.height, what))


def parse_scribbles(value, model, instance: int) -> tuple[ScribbleSet, ...]:
    """``[{"view": V, "fg": strokes, "bg": strokes}, …]``: views with neither are dropped; a view
    with keep strokes alone stays (an empty "edit here" mask), but one view at least is scribbled."""
    if not isinstance(value, list):
        raise CrfError("views: expected a list of {\"view\", \"fg\", \"bg\"}")
    if len(value) > MAX_VIEWS:
        raise CrfError(f"views: scribbles on {len(value)} views; at most {MAX_VIEWS}")
    out: dict[str, ScribbleSet] = {}
    for i, item in enumerate(value):
        if not isinstance(item, dict):
            raise CrfError(f"views[{i}]: expected {{\"view\", \"fg\", \"bg\"}}")
        view = parse_view(item.get("view"), model, instance)
        fg = parse_strokes(item.get("fg"), view.camera, f"{view.label}: edit-here strokes")
        bg = parse_strokes(item.get("bg"), view.camera, f"{view.label}: keep strokes")
        if fg is None and bg is not None:  # keep strokes alone: they hold back what this view shows
            fg = Strokes({"strokes": []}, np.zeros((view.camera.height, view.camera.width), dtype=bool))
        if fg is not None:
            out[view.key] = ScribbleSet(view, fg, bg)
    if not any(s.fg.mask.any() for s in out.values()):
        raise CrfError("the scribble is empty: draw 'edit here' strokes on the part first (keep strokes only say what to leave)")
    return tuple(out.values())


def parse_options(body: dict, methods: tuple[str, ...]) -> tuple[EditOptions, str]:
    """(EditOptions, method) from the request's optional ``steps``, ``lr``, ``rays``, ``seed``,
    ``strategy`` and ``method`` (one of ``methods``; the first by default)."""
    d = EditOptions()
    steps = _integer(body.get("steps", d.steps), "steps", 1, MAX_STEPS)
    rays = _integer(body.get("rays", d.rays), "rays", 2, 1 << 16)
    seed = _integer(body.get("seed", d.seed), "seed", 0, 2**31 - 1)
    lr = _number(body.get("lr", d.lr), "lr", 1e-12, 1e30)
    strategy, method = body.get("strategy", d.strategy), body.get("method", methods[0])
    if strategy not in STRATEGIES:
        raise CrfError(f"strategy: expected one of {', '.join(STRATEGIES)}")
    if method not in methods:
        raise CrfError(f"method: expected one of {', '.join(methods)}")
    return EditOptions(strategy=strategy, steps=steps, lr=lr, rays=rays, seed=seed).validated(), method


def parse_edit(body, model) -> EditRequest:
    """An edit request from the page's JSON, checked (instances, views, strokes, colour, options)."""
    if not isinstance(body, dict):
        raise CrfError("expected a JSON object")
    kind = body.get("kind")
    if kind not in KINDS:
        raise CrfError(f"kind: expected one of {', '.join(KINDS)}")
    k = instance_of(model, body.get("instance"))
    options, method = parse_options(body, ADD_METHODS if kind == "add" else EDIT_METHODS)
    if kind == "transfer":
        shape_from = None if body.get("shape_from") is None else instance_of(model, body["shape_from"], "shape_from")
        color_from = None if body.get("color_from") is None else instance_of(model, body["color_from"], "color_from")
        if shape_from is None and color_from is None:
            raise CrfError("transfer: pick an instance to take the shape or the colour from")
        return EditRequest(kind, k, options, shape_from=shape_from, color_from=color_from)
    view = parse_view(body.get("view"), model, k)
    if kind == "add":
        j = instance_of(model, body.get("donor"), "donor")
        donor_view = parse_view(body.get("donor_view", body.get("view")), model, j)
        copy = parse_strokes(body.get("copy"), donor_view.camera, "copy strokes")
        if copy is None:
            raise CrfError("add: scribble the part to copy on the donor's view first")
        offset = body.get("offset")
        if not (isinstance(offset, list) and len(offset) == 2):
            raise CrfError("add: click where to paste the part (offset must be [dx, dy] pixels)")
        dxdy = tuple(_integer(v, "offset", -view.camera.width * 4, view.camera.width * 4) for v in offset)
        keep = parse_strokes(body.get("bg"), view.camera, "keep strokes")
        return EditRequest(kind, k, options, method, view, donor=j, donor_view=donor_view, copy=copy, offset=dxdy, keep=keep)
    scribbles = parse_scribbles(body.get("views"), model, k)
    color = None
    if kind == "color":
        rgb = parse_color(body.get("color", "") if isinstance(body.get("color"), str) else "")
        color = rgb_to_hex(rgb)
    request = EditRequest(kind, k, options, method, view, scribbles, color)
    if request.drawn is not None and not request.drawn.fg.mask.any():  # shown: a view with keep strokes alone
        first = next(s for s in scribbles if s.fg.mask.any())  # the edit is drawn where the part is scribbled
        request = EditRequest(kind, k, options, method, first.view, scribbles, color, on_screen=False)
    if request.drawn is None:
        raise CrfError(f"the view {view.label} has no 'edit here' strokes: scribble the part on it first")
    if method == "paper" and len(scribbles) > 1:
        raise CrfError("method paper uses the scribbles of one view: clear the strokes of the other views")
    return request


# ----------------------------------------------------------------------------- replay


class Replay:
    """Builds the replay script: each edit's input files (heredocs) and its ``crfedit`` command."""

    def __init__(self, model_path: str, names: list[str], device: str | None):
        self.model, self.names, self.device = shlex.quote(model_path), names, device
        self.lines: list[str] = []
        self.outputs: list[str] = []  # edit files applied so far, as shell words
        self._files: dict[str, str] = {}  # JSON text -> the file already holding it

    def _file(self, path: str, data) -> str:
        text = json.dumps(data, separators=(",", ":"))
        if text not in self._files:
            self._files[text] = path
            self.lines += [f"cat > {path} <<'EOF'", text, "EOF"]
        return self._files[text]

    def _view(self, prefix: str, view: ViewRef, suffix: str = "view") -> str:
        if view.spec is not None:
            return shlex.quote(view.spec)
        return self._file(f'"$out/{prefix}-{suffix}.json"', camera_json(view.camera))

    def _strokes(self, prefix: str, name: str, strokes: Strokes) -> str:
        return self._file(f'"$out/{prefix}-{name}.json"', strokes.data)

    def _tail(self, req: EditRequest) -> list[str]:
        d, o = EditOptions(), req.options
        words = [f"--edit {p}" for p in self.outputs]
        for flag, value, default in (("--strategy", o.strategy, d.strategy), ("--steps", o.steps, d.steps),
                                     ("--lr", o.lr, d.lr), ("--rays", o.rays, d.rays), ("--seed", o.seed, d.seed)):
            if value != default and req.kind != "transfer":  # a transfer optimizes nothing
                words.append(f"{flag} {value}")
        if self.device:
            words.append(f"--device {self.device}")
        return words

    def add_file(self, path: str, note: str = "") -> None:
        """An edit that exists as a file (loaded with --edit): later commands build on it."""
        if note:
            self.lines.append(f"# {note}")
        self.outputs.append(shlex.quote(path))

    def add_recipe(self, n: int, req: EditRequest, note: str = "") -> None:
        if note:
            self.lines.append(f"# {note}")
        prefix = f"{n:02d}"
        name = self.names[req.instance]
        out = f'"$out/{prefix}-{req.kind}-{name}.safetensors"'
        head = f"crfedit {'edit-color' if req.kind == 'color' else req.kind} {self.model} --instance {shlex.quote(name)}"
        words = [head]
        if req.kind == "transfer":
            for flag, j in (("--shape-from", req.shape_from), ("--color-from", req.color_from)):
                if j is not None:
                    words.append(f"{flag} {shlex.quote(self.names[j])}")
        elif req.kind == "add":
            words.append(f"--view {self._view(prefix, req.view)}")
            words.append(f"--donor {shlex.quote(self.names[req.donor])}")
            words.append(f"--copy {self._strokes(prefix, 'copy', req.copy)}")
            words.append(f"--offset {req.offset[0]},{req.offset[1]}")
            if camera_json(req.donor_view.camera) != camera_json(req.view.camera):  # train:0 of the donor is its own camera
                words.append(f"--donor-view {self._view(prefix, req.donor_view, 'donor-view')}")
            if req.keep is not None:
                words.append(f"--keep-json {self._strokes(prefix, 'keep', req.keep)}")
            if req.method != ADD_METHODS[0]:
                words.append(f"--method {req.method}")
        else:
            drawn = req.drawn
            if len(req.scribbles) > 1:
                self._select(prefix, req)
                words.append(f'--selection "$out/{prefix}-selection.safetensors"')
            words.append(f"--view {self._view(prefix, drawn.view)}")
            words.append(f"--scribble-json {self._strokes(prefix, 'fg', drawn.fg)}")
            if drawn.bg is not None:
                words.append(f"--keep-json {self._strokes(prefix, 'bg', drawn.bg)}")
            if req.kind == "color":
                words.append(f"--color '{req.color}'")
            if req.method != "selection":
                words.append(f"--method {req.method}")
        self.lines.append(" ".join([*words, *self._tail(req), f"--out {out}"]))
        self.outputs.append(out)

    def _select(self, prefix: str, req: EditRequest) -> None:
        """The ``crfedit select`` line of a selection drawn on several views."""
        any_keep = any(s.bg is not None for s in req.scribbles)
        words = [f"crfedit select {self.model} --instance {shlex.quote(self.names[req.instance])}"]
        for i, s in enumerate(req.scribbles):
            words.append(f"--view {self._view(f'{prefix}-{i}', s.view)}")
            # a view with keep strokes alone: --scribble none
            words.append(f"--scribble {self._strokes(f'{prefix}-{i}', 'fg', s.fg) if s.fg.mask.any() else 'none'}")
            if s.bg is not None:
                words.append(f"--keep {self._strokes(f'{prefix}-{i}', 'bg', s.bg)}")
            elif any_keep:  # --keep is given for every view or none
                words.append("--keep none")
        words += [f"--edit {p}" for p in self.outputs]
        words.append(f"--for {req.kind}")
        if self.device:
            words.append(f"--device {self.device}")
        self.lines.append(" ".join([*words, f'--out "$out/{prefix}-selection.safetensors"']))

    def script(self) -> str:
        head = [
            f"# The crfedit ui edit stack of {self.model}, replayed from the shell.",
            f"# It writes the strokes, cameras and edit files into ./{REPLAY_DIR}/.",
            "set -e",
            f"out={REPLAY_DIR}",
            'mkdir -p "$out"',
        ]
        tail = []
        if self.outputs:
            tail = ["# fold the stack into a new model:",
                    f"# crfedit edits bake {self.model} {' '.join('--edit ' + p for p in self.outputs)} --out \"$out/baked.safetensors\""]
        return "\n".join([*head, *self.lines, *tail]) + "\n"
