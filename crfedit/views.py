"""Which cameras to render: the view SPEC grammar shared by ``render`` and every edit command.

A SPEC names cameras of one instance of a trained model:

=====================  ==========================================================================
``train``              every view of that split of the instance (also ``val``, ``test``)
``test:3``             one view; ``test:0-9`` an inclusive range; ``train:1,4,7`` a list
                       (ranges and indices mix: ``train:0-3,7``)
``orbit:36``           36 cameras evenly spaced in azimuth around Z at 30° elevation, looking at
                       the origin, at the median distance and focal of the stored views
``orbit:36@45``        the same at 45° elevation
``PATH.json``          a nerfstudio ``camera_path.json`` (``camera_path[].camera_to_world``:
                       16 floats row-major or a 4×4 list, ``fov``: vertical degrees,
                       ``render_width``/``render_height``), a single camera
                       ``{"transform_matrix", "camera_angle_x", "width", "height"}``, or a
                       NeRF ``transforms_*.json`` (``camera_angle_x`` + ``frames[].transform_matrix``),
                       or a render's ``views.json`` (its cameras again, each at its own size);
                       ``FILE.json:2`` (or ``:0-4``) picks views of a file, as their labels name them
=====================  ==========================================================================

Split views come from the camera tables stored in the model file (``model.views``), so a SPEC
resolves without the dataset.  Where a file gives no image size, the stored views' size is used.
``res`` resizes every camera to that width (height keeps the aspect ratio).  Every problem is a
one-line :class:`~crfedit.errors.CrfError` that names the SPEC.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from .cameras import Camera, angle_from_focal, c2w_problem, focal_from_angle, off_centre_target, orbit_cameras
from .errors import CrfError
from .io import not_a_file, read_json

SPLITS = ("train", "val", "test")
DEFAULT_ELEVATION = 30.0
MAX_RESOLUTION = 16384
MAX_ORBIT = 100_000

_ORBIT = re.compile(r"^orbit:(\d+)(?:@([+-]?(?:\d+\.?\d*|\.\d+)))?(?::(.*))?$")


def one_view_label(spec: str, label: str) -> str:
    """What an edit records as the view it was drawn on: ``label``, except for an orbit view,
    recorded as its spec was typed (``orbit:36:5``, whose label reads ``orbit:36@30:5``)."""
    return str(spec).strip() if label.startswith("orbit:") else label


def one_view_hint(spec: str) -> str:
    """How to name one view of a spec that names several: ``train`` → ``train:0``,
    ``orbit:36@30`` → ``orbit:36@30:0``; other specs (index lists, camera files) get the
    generic example."""
    spec = str(spec).strip()
    if spec in SPLITS or (_ORBIT.match(spec) and _ORBIT.match(spec).group(3) is None):
        return f"e.g. {spec}:0 for its first view"
    return "e.g. train:5"


def parse_resolution(value: str | int | None, option: str = "--res") -> int | None:
    """A render width in pixels (``None`` passes through): an integer in 1..16384.

    ``parse_resolution("64") == 64``; ``"0"``, ``"-3"`` and ``"big"`` are one-line errors
    naming ``option``.
    """
    if value is None:
        return None
    text = str(value).strip()
    if not re.fullmatch(r"[+-]?\d+", text) or not 1 <= int(text) <= MAX_RESOLUTION:
        raise CrfError(f"{option} {value}: expected a width in pixels between 1 and {MAX_RESOLUTION}")
    return int(text)


def resolve_views(spec: str, model, instance: int | str, res: int | None = None) -> list[tuple[str, Camera]]:
    """(label, camera) for each view ``spec`` names, in order; labels read ``test:3``, ``orbit:36@30:5``,
    ``camera_path.json:12``.  ``model`` is a :class:`~crfedit.model.CategoryModel`; ``instance``
    a name or an index."""
    instance = model.instance_index(instance)
    spec = str(spec).strip()
    if not spec:
        raise CrfError("view spec is empty (expected e.g. test, test:0-4, orbit:36 or a camera JSON file)")
    name, _, rest = spec.partition(":")
    if spec == "photo":
        views = _photo_views(model, instance)
    elif name in SPLITS:
        views = _split_views(spec, name, rest, model, instance)
    elif name == "orbit":
        views = _orbit_views(spec, model, instance)
    elif (m := re.fullmatch(r"(.+\.json):([0-9,\- ]+)", spec, re.IGNORECASE)) and not Path(spec).exists():
        views = _file_views(m.group(1), model)  # FILE.json:2, one of a file's views, as its label names it
        views = [views[i] for i in parse_indices(spec, m.group(2), len(views))]
    elif Path(spec).is_file() or spec.lower().endswith(".json") or "/" in spec:
        views = _file_views(spec, model)
    else:
        raise CrfError(
            f"view spec {spec!r}: expected train, val or test (optionally :INDEX, :A-B or :I,J,K), "
            "orbit:N[@ELEVATION][:INDEX], photo (an instance fit-real added), or a camera JSON file"
        )
    res = parse_resolution(res)
    if res is not None:
        views = [(label, cam.resized(res)) for label, cam in views]
    return views


# ----------------------------------------------------------------------------- splits


def parse_indices(spec: str, text: str, count: int) -> list[int]:
    """``"3"`` → [3]; ``"0-2,7"`` → [0, 1, 2, 7]; every index must be below ``count``."""
    out: list[int] = []
    for item in text.split(","):
        item = item.strip()
        m = re.fullmatch(r"(\d+)(?:-(\d+))?", item)
        if not m:
            raise CrfError(f"view spec {spec!r}: {item!r} is not an index or an inclusive range A-B")
        lo = int(m.group(1))
        hi = int(m.group(2)) if m.group(2) is not None else lo
        if hi < lo:
            raise CrfError(f"view spec {spec!r}: range {item} runs backwards (write {hi}-{lo})")
        if hi >= count:
            raise CrfError(f"view spec {spec!r}: index {hi} out of range (0-{count - 1})")
        out.extend(range(lo, hi + 1))
    return out


def _split_views(spec: str, split: str, rest: str, model, instance: int) -> list[tuple[str, Camera]]:
    table = model.views.get(split)
    cams = table.cameras(instance) if table is not None else []
    if not cams:
        have = [s for s in SPLITS if s in model.views and model.views[s].cameras(instance)]
        name = model.names[instance] if 0 <= instance < len(model.names) else instance
        stored = (f"its stored splits: {', '.join(have)}" if have
                  else "it has no stored views: an instance fit-real added renders from its photo's camera with --views photo")
        raise CrfError(f"view spec {spec!r}: the model stores no {split} views of instance {name} ({stored}; orbit:N renders any instance)")
    indices = range(len(cams)) if not rest.strip() and ":" not in spec else parse_indices(spec, rest, len(cams))
    return [(f"{split}:{i}", cams[i]) for i in indices]


def _photo_views(model, instance: int) -> list[tuple[str, Camera]]:
    """``photo``: the camera of the photo that the fit-real edit adding ``instance`` was fitted
    to (recorded in the model's metadata by :func:`~crfedit.delta.apply_deltas`, or by a model
    that baked it), read as a camera JSON file is, so a damaged record is one line."""
    from .delta import photo_cameras

    name = model.names[instance] if 0 <= instance < len(model.names) else instance
    cam = photo_cameras(model).get(name)
    if cam is None:
        raise CrfError(f"view spec 'photo': {name} was not added by a fit-real edit in --edit or baked into the model; "
                       "photo is the camera of its photo")
    try:
        data = {"transform_matrix": cam["c2w"], "width": cam["width"], "height": cam["height"],
                "camera_angle_x": angle_from_focal(cam["focal"], cam["width"])}
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        raise CrfError(f"view spec 'photo': the record of {name}'s photo camera cannot be read") from None
    return [("photo", camera_from_json(data, model, f"photo (the camera of {name}'s photo)"))]


# ----------------------------------------------------------------------------- orbit


def _stored_cameras(model, instance: int) -> list[Camera]:
    """The instance's stored cameras of the first split that has any (train, val, test), else
    every instance's cameras of the first stored split."""
    tables = [model.views[s] for s in SPLITS if s in model.views]
    for table in tables:
        cams = table.cameras(instance)
        if cams:
            return cams
    if not tables:
        return []
    return [cam for k in sorted(set(tables[0].instance.tolist())) for cam in tables[0].cameras(k)]


def _orbit_views(spec: str, model, instance: int) -> list[tuple[str, Camera]]:
    m = _ORBIT.match(spec)
    if not m:
        raise CrfError(f"view spec {spec!r}: expected orbit:N or orbit:N@ELEVATION (degrees), e.g. orbit:36@45, "
                       "optionally :INDEX, :A-B or :I,J,K of its views (orbit:36@30:5)")
    n = int(m.group(1))
    elevation = float(m.group(2)) if m.group(2) is not None else DEFAULT_ELEVATION
    if not 1 <= n <= MAX_ORBIT:
        raise CrfError(f"view spec {spec!r}: need between 1 and {MAX_ORBIT} views")
    if not -90.0 < elevation < 90.0:
        raise CrfError(f"view spec {spec!r}: elevation {elevation:g} must lie strictly between -90 and 90 degrees")
    stored = _stored_cameras(model, instance)
    if not stored:
        raise CrfError(f"view spec {spec!r}: the model stores no cameras to take the orbit's distance and focal from")
    centre = off_centre_target(stored)  # where the cameras look, as the scene box reads it: an object off the origin stays in frame
    centre = np.zeros(3) if centre is None else centre
    radius = float(np.median([np.linalg.norm(np.asarray(c.center) - centre) for c in stored]))
    width, height = stored[0].width, stored[0].height
    focal = float(np.median([c.focal if c.width == width else c.focal * width / c.width for c in stored]))  # at the first size
    cams = orbit_cameras(n, elevation, radius, focal, width, height, centre)
    indices = range(n) if m.group(3) is None else parse_indices(spec, m.group(3), n)
    whole = f"orbit:{m.group(1)}@{m.group(2) or f'{DEFAULT_ELEVATION:g}'}"  # each label a spec of its one view
    return [(f"{whole}:{k}", cams[k]) for k in indices]


# ----------------------------------------------------------------------------- camera files


def _matrix(spec: str, where: str, value) -> np.ndarray:
    m, problem = c2w_problem(value)
    if problem:
        raise CrfError(f"view spec {spec!r}: {where} {problem}")
    return m


def _number(spec: str, where: str, value, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (lo < value < hi):
        raise CrfError(f"view spec {spec!r}: {where} must be a number between {lo:g} and {hi:g}")
    return float(value)


def _size(spec: str, data: dict, keys: tuple[str, str], model) -> tuple[int, int]:
    """(width, height) from ``data[keys]``, else the stored views' size (aspect kept)."""
    w, h = (data.get(k) for k in keys)
    for key, v in zip(keys, (w, h)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_RESOLUTION):
            raise CrfError(f"view spec {spec!r}: {key} must be an integer between 1 and {MAX_RESOLUTION}")
    if w is not None and h is not None:
        return w, h
    table = next(iter(model.views.values()), None)
    sw, sh = (table.width, table.height) if table is not None else (256, 256)
    if w is not None:
        return w, max(1, round(sh * w / sw))
    if h is not None:
        return max(1, round(sw * h / sh)), h
    return sw, sh


def _file_views(spec: str, model) -> list[tuple[str, Camera]]:
    path = Path(spec)
    if not (path.is_file() or path.is_fifo()):  # a pipe (<(…)) is read whole by read_json
        raise CrfError(f"view spec {spec!r}: camera file {not_a_file(path, 'not found')}")
    data = read_json(path)  # a malformed file is an error that names it
    if not isinstance(data, dict):
        raise CrfError(f"view spec {spec!r}: expected a JSON object (camera_path, transform_matrix, frames or views)")
    name = path.name
    if "camera_path" in data:
        return _camera_path_views(spec, name, data, model)
    if "transform_matrix" in data:
        return [(f"{name}:0", camera_from_json(data, model, spec))]
    if "frames" in data:
        frames = data["frames"]
        if not isinstance(frames, list) or not frames:
            raise CrfError(f"view spec {spec!r}: frames must be a non-empty list")
        width, height = _size(spec, data, ("w", "h"), model)
        angle = _number(spec, "camera_angle_x", data.get("camera_angle_x"), 0.0, math.pi)
        focal = focal_from_angle(angle, width)
        out = []
        for k, frame in enumerate(frames):
            where = f"frames[{k}].transform_matrix"
            c2w = _matrix(spec, where, frame.get("transform_matrix") if isinstance(frame, dict) else None)
            out.append((f"{name}:{k}", Camera(c2w, focal, width, height)))
        return out
    if "views" in data:  # a render's views.json: the cameras it rendered, each its own size
        records = data["views"]
        if not isinstance(records, list) or not records or not all(isinstance(r, dict) for r in records):
            raise CrfError(f"view spec {spec!r}: views must be a non-empty list of camera objects (a render's views.json)")
        return [(f"{name}:{k}", camera_from_json(r, model, f"{spec}: views[{k}]")) for k, r in enumerate(records)]
    raise CrfError(f"view spec {spec!r}: expected a camera_path list, a transform_matrix, a frames list, or a render's views list")


def camera_json(camera: Camera) -> dict:
    """A single-camera JSON object for ``camera`` (``transform_matrix``, ``camera_angle_x``,
    ``width``, ``height``): a camera file any ``--view`` reads back."""
    return {"transform_matrix": np.asarray(camera.c2w, dtype=np.float64).tolist(), "camera_angle_x": camera.camera_angle_x,
            "width": int(camera.width), "height": int(camera.height)}


def camera_from_json(data: dict, model, spec: str = "camera") -> Camera:
    """The camera of a single-camera JSON object, exactly as a ``--view`` camera file reads it:
    ``camera_from_json(camera_json(c), model)`` is the camera a command gets from that file."""
    width, height = _size(spec, data, ("width", "height"), model)
    angle = _number(spec, "camera_angle_x", data.get("camera_angle_x"), 0.0, math.pi)
    c2w = _matrix(spec, "transform_matrix", data.get("transform_matrix"))
    return Camera(c2w, focal_from_angle(angle, width), width, height)


def _camera_path_views(spec: str, name: str, data: dict, model) -> list[tuple[str, Camera]]:
    """A nerfstudio ``camera_path.json``: per-keyframe ``camera_to_world`` and vertical ``fov``."""
    path = data["camera_path"]
    if not isinstance(path, list) or not path:
        raise CrfError(f"view spec {spec!r}: camera_path must be a non-empty list")
    width, height = _size(spec, data, ("render_width", "render_height"), model)
    out = []
    for k, cam in enumerate(path):
        if not isinstance(cam, dict):
            raise CrfError(f"view spec {spec!r}: camera_path[{k}] is not an object")
        c2w = _matrix(spec, f"camera_path[{k}].camera_to_world", cam.get("camera_to_world"))
        fov = _number(spec, f"camera_path[{k}].fov", cam.get("fov"), 0.0, 180.0)
        focal = 0.5 * height / math.tan(0.5 * math.radians(fov))
        out.append((f"{name}:{k}", Camera(c2w, focal, width, height)))
    return out
