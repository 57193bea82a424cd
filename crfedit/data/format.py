"""Category datasets on disk: the EditNeRF layout, i.e. one NeRF-synthetic scene per instance.

Layout (see docs/datasets.md)::

    root/instances.txt                 one instance folder name per line
    root/<name>/transforms_{split}.json  camera_angle_x (or focal / fl_x in pixels) and frames[]
    root/<name>/<file_path>.png        RGBA, straight alpha
    root/<name>/<file_path>_depth.exr  optional, channel "Z": distance along the unit ray, +inf = background
    root/<name>/<file_path>_parts.png  optional, uint8, 0 = background, k = part k
    root/<name>/parts.json             optional, [{"id", "name", "color"}]
    root/twins.json                    optional ground-truth edit twins (not training instances)

A folder holding ``transforms_train.json`` but no ``instances.txt`` is a single NeRF-synthetic
scene and loads as a 1-instance category named after the folder.  Every problem with the files is
a one-line :class:`~crfedit.errors.DataError` that names the file.
"""

from __future__ import annotations

import hashlib
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ..cameras import Camera, focal_from_angle, rays_from_camera, subpixel_offsets
from ..errors import CrfError, DataError
from ..io import atomic_write_text, read_exr, read_image, read_json, write_exr, write_json, write_png

SPLITS = ("train", "val", "test")
IMAGE_MODES = ("RGB", "RGBA", "L", "LA", "P", "PA", "1", "I", "I;16", "I;16L", "I;16B")
"""Pillow modes we accept for images; 16-bit ones are scaled to [0, 1]."""
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp")


# ----------------------------------------------------------------------------- writing


@dataclass(frozen=True, eq=False)
class Frame:
    """One rendered view to write."""

    camera: Camera
    rgba: np.ndarray  # [H, W, 4] float32 in [0, 1], straight alpha, rgb already shaded
    depth: np.ndarray | None  # [H, W] float32 ray distance, +inf where background
    parts: np.ndarray | None  # [H, W] uint8, 0 = background


def box_filter(rgb: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Average supersamples into straight-alpha pixels.  rgb [S, N, 3], hit [S, N] → rgba [N, 4]

    alpha = fraction of samples that hit; rgb = mean colour of the hits (white where none hit),
    so compositing on white, ``rgb·α + (1−α)``, equals the box-filtered image on white.
    """
    n_hit = hit.sum(axis=0)
    alpha = n_hit / hit.shape[0]
    total = (rgb * hit[..., None]).sum(axis=0)
    color = np.where(n_hit[:, None] > 0, total / np.maximum(n_hit, 1)[:, None], 1.0)
    return np.concatenate([color, alpha[:, None]], axis=1)


def supersampled_frame(
    camera: Camera, aa: int, cast: Callable[[tuple[float, float]], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
) -> Frame:
    """Render ``camera`` with aa×aa rays per pixel.

    ``cast(offset)`` ray-casts the rays through ``offset`` (pixels from each pixel's top-left
    corner) of every pixel and returns (distance [N], part id [N], shaded rgb [N, 3], hit [N]).
    Colour and alpha are box-filtered (:func:`box_filter`) over the aa×aa casts; depth and part ids come
    from the pixel-center cast (one of them when aa is odd, an extra one when it is even).
    """
    offsets = subpixel_offsets(aa)
    center_is_a_sample = offsets[0] == (0.5, 0.5)
    if not center_is_a_sample:
        offsets = [(0.5, 0.5), *offsets]
    colors, hits = [], []
    for i, offset in enumerate(offsets):
        t, part, rgb, hit = cast(offset)
        if i == 0:
            depth, parts = t, part
        if i > 0 or center_is_a_sample:
            colors.append(rgb)
            hits.append(hit)
    shape = (camera.height, camera.width)
    rgba = box_filter(np.stack(colors), np.stack(hits)).reshape(*shape, 4)
    return Frame(camera, rgba.astype(np.float32), depth.reshape(shape).astype(np.float32), parts.reshape(shape).astype(np.uint8))


@dataclass(frozen=True)
class TwinSpec:
    """A ground-truth twin of a source instance: what an edit of it should produce."""

    name: str
    kind: str  # "color" | "remove"
    source: str  # source instance name
    view: str  # view spec of the scribbled view in the source, e.g. "train:7"
    part: str  # name of the edited part
    color: str | None  # "#rrggbb" target color when kind == "color"
    scribble: str  # foreground scribble mask PNG, relative to the category root
    keep: str  # background ("keep") scribble mask PNG, relative to the category root
    folder: str  # twin's rendered test views (NeRF format, the source's test poses), relative to root


TWIN_KINDS = ("color", "remove")


def frame_file_path(split: str, index: int, count: int) -> str:
    """``./train/r_007``: the relative, extension-less path NeRF-synthetic uses for a frame."""
    return f"./{split}/r_{index:0{max(3, len(str(count - 1)))}d}"


def _check_frame(k: int, frame: Frame, cam0: Camera) -> None:
    cam = frame.camera
    shape = (cam.height, cam.width)
    if (cam.width, cam.height) != (cam0.width, cam0.height) or not math.isclose(cam.focal, cam0.focal):
        raise ValueError(f"frame {k}: other intrinsics than frame 0 (camera_angle_x is per split)")
    if frame.rgba.shape != (*shape, 4):
        raise ValueError(f"frame {k}: rgba shape {frame.rgba.shape} != {(*shape, 4)}")
    if frame.depth is not None and frame.depth.shape != shape:
        raise ValueError(f"frame {k}: depth shape {frame.depth.shape} != {shape}")
    if frame.parts is not None and (frame.parts.shape != shape or frame.parts.dtype != np.uint8):
        raise ValueError(f"frame {k}: parts must be uint8 {shape}")


def _write_frame_files(base: Path, frame: Frame) -> None:
    """``base.png`` (+ ``base_depth.exr``, ``base_parts.png``)."""
    write_png(base.with_name(base.name + ".png"), frame.rgba)
    if frame.depth is not None:
        write_exr(base.with_name(base.name + "_depth.exr"), {"Z": frame.depth})
    if frame.parts is not None:
        write_png(base.with_name(base.name + "_parts.png"), frame.parts)


def write_split(instance_dir: Path, split: str, frames: list[Frame]) -> None:
    """Write ``frames`` as ``<split>/r_###.png`` (+ depth/parts) and ``transforms_<split>.json``.

    All frames must share one intrinsics (``camera_angle_x`` is per split).  Image files are
    written by a thread pool (each atomic write waits on fsync; overlapping them is ~5× faster);
    the transforms file comes last, so a split is listed only once its images exist.
    """
    instance_dir = Path(instance_dir)
    if not frames:
        raise ValueError(f"write_split({split!r}): no frames")
    cam0 = frames[0].camera
    for k, frame in enumerate(frames):
        _check_frame(k, frame, cam0)
    (instance_dir / split).mkdir(parents=True, exist_ok=True)
    rels = [frame_file_path(split, k, len(frames)) for k in range(len(frames))]
    with ThreadPoolExecutor(max_workers=min(16, len(frames))) as pool:
        list(pool.map(lambda rel, frame: _write_frame_files(instance_dir / rel, frame), rels, frames))
    records = [{"file_path": rel, "transform_matrix": np.asarray(f.camera.c2w, np.float64).tolist()} for rel, f in zip(rels, frames)]
    write_json(instance_dir / f"transforms_{split}.json", {"camera_angle_x": cam0.camera_angle_x, "frames": records})


def write_parts(instance_dir: Path, parts: list[dict]) -> None:
    """Write ``parts.json``: ``[{"id": 1, "name": "seat", "color": "#rrggbb"}, ...]``."""
    write_json(Path(instance_dir) / "parts.json", list(parts))


def write_instances_txt(root: Path, names: list[str]) -> None:
    atomic_write_text(Path(root) / "instances.txt", "".join(f"{n}\n" for n in names))


def write_twins_json(root: Path, twins: list[TwinSpec]) -> None:
    write_json(Path(root) / "twins.json", {"twins": [asdict(t) for t in twins]})


# ----------------------------------------------------------------------------- loaded data


@dataclass(frozen=True, eq=False)
class View:
    """One loaded view; ``rgb`` is composited on white."""

    camera: Camera
    rgb: np.ndarray  # [H, W, 3] float32, rgb*a + (1 - a)
    alpha: np.ndarray  # [H, W] float32, all ones if the image has no alpha
    depth: np.ndarray | None  # [H, W] float32 ray distance, +inf = background
    parts: np.ndarray | None  # [H, W] uint8
    file_path: str


def parse_view_spec(spec: str) -> tuple[str, int]:
    """``"train:7"`` → ``("train", 7)``."""
    split, sep, index = str(spec).partition(":")
    if not sep or split not in SPLITS or not index.strip().isdigit():
        raise DataError(f"view {spec!r}: expected SPLIT:INDEX with SPLIT one of {', '.join(SPLITS)}, e.g. train:7")
    return split, int(index)


@dataclass(frozen=True, eq=False)
class InstanceData:
    name: str
    path: Path
    splits: dict[str, list[View]]  # only the splits whose transforms file exists

    def view(self, spec: str) -> View:
        """The view named by ``spec`` (``"train:7"``)."""
        split, index = parse_view_spec(spec)
        views = self.splits.get(split)
        if views is None:
            raise DataError(f"{self.name}: has no {split} split (view {spec})")
        if index >= len(views):
            raise DataError(f"{self.name}: view {spec} out of range ({split} has {len(views)} views)")
        return views[index]


@dataclass(frozen=True, eq=False)
class Category:
    root: Path
    instances: list[InstanceData]
    fingerprint: str  # first 16 hex chars of sha256 over instances.txt and every transforms json

    @property
    def names(self) -> list[str]:
        return [inst.name for inst in self.instances]

    def instance(self, key: str | int) -> InstanceData:
        """An instance by name or index; unknown → DataError listing a few valid names."""
        names = self.names
        if isinstance(key, str) and key in names:
            return self.instances[names.index(key)]
        if isinstance(key, int) or (isinstance(key, str) and key.strip().isdigit()):
            index = int(key)
            if 0 <= index < len(names):
                return self.instances[index]
            raise DataError(f"instance index {index} out of range (0..{len(names) - 1})")
        shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
        raise DataError(f"unknown instance {key!r} (valid: {shown}; {len(names)} in all)")


# ----------------------------------------------------------------------------- reading files


def _data_error(e: CrfError) -> DataError:
    return e if isinstance(e, DataError) else DataError(str(e))


def _read_json(path: Path):
    try:
        return read_json(path)
    except CrfError as e:
        raise _data_error(e) from None


def _read_rgba(path: Path) -> np.ndarray:
    """Image as float32 [H, W, 3|4] in [0, 1]; EXR images are read as linear R, G, B(, A)."""
    if path.suffix.lower() == ".exr":
        channels = _read_exr(path)
        if not {"R", "G", "B"} <= channels.keys():
            raise DataError(f"{path}: EXR image needs R, G, B channels (has {', '.join(sorted(channels))})")
        arr = np.stack([channels[c] for c in ("R", "G", "B", "A") if c in channels], axis=-1)
        if not np.isfinite(arr).all():
            raise DataError(f"{path}: image has NaN or infinite pixels")
        return np.clip(arr, 0.0, 1.0).astype(np.float32)
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise DataError(f"{path}: image not found")
    try:
        with Image.open(path) as im:
            mode = im.mode
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise DataError(f"{path}: not a readable image ({e.__class__.__name__})") from None
    if mode not in IMAGE_MODES:
        raise DataError(f"{path}: image mode {mode} is not supported (expected RGB, RGBA, L, LA or P)")
    try:
        arr = read_image(path)
    except CrfError as e:
        raise _data_error(e) from None
    if not np.isfinite(arr).all():
        raise DataError(f"{path}: image has NaN or infinite pixels")
    return arr


def _read_exr(path: Path) -> dict[str, np.ndarray]:
    try:
        return read_exr(path)
    except CrfError as e:
        raise _data_error(e) from None


def _read_depth(path: Path, shape: tuple[int, int]) -> np.ndarray:
    channels = _read_exr(path)
    if "Z" in channels:
        depth = channels["Z"]
    elif len(channels) == 1:
        depth = next(iter(channels.values()))
    else:
        raise DataError(f"{path}: depth EXR has no Z channel (has {', '.join(sorted(channels))})")
    if depth.shape != shape:
        raise DataError(f"{path}: depth size {depth.shape[1]}x{depth.shape[0]} != image {shape[1]}x{shape[0]}")
    if np.isnan(depth).any():
        raise DataError(f"{path}: depth has NaN pixels")
    return depth.astype(np.float32)


def read_mask(path: Path, width: int | None = None) -> np.ndarray:
    """An 8-bit mask PNG (255 = on) as bool [H, W]; optionally resized to ``width`` (nearest)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: mask not found")
    try:
        with Image.open(path) as im:
            if im.mode not in ("L", "1", "P", "RGB", "RGBA", "LA"):
                raise DataError(f"{path}: mask mode {im.mode} is not supported (expected 8-bit grayscale)")
            im = im.convert("L")
            if width is not None and width != im.width:
                im = im.resize((width, max(1, round(im.height * width / im.width))), Image.NEAREST)
            return np.asarray(im) >= 128
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise DataError(f"{path}: not a readable image ({e.__class__.__name__})") from None


def _read_parts(path: Path, shape: tuple[int, int]) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.mode not in ("L", "P"):
                raise DataError(f"{path}: part map mode {im.mode} is not supported (expected 8-bit L)")
            parts = np.array(im, dtype=np.uint8)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise DataError(f"{path}: not a readable image ({e.__class__.__name__})") from None
    if parts.shape != shape:
        raise DataError(f"{path}: part map size {parts.shape[1]}x{parts.shape[0]} != image {shape[1]}x{shape[0]}")
    return parts


# ----------------------------------------------------------------------------- resizing


def resize_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average float32 [H, W, C] → [height, width, C] (Pillow BOX, per channel).

    Resizing the white-composited rgb and the alpha this way equals resizing premultiplied
    RGBA: ``box(rgb*a + 1 - a) = box(rgb*a) + 1 - box(a)``.  A 2× shrink is an exact 2×2 mean.
    """
    from PIL import Image

    chans = [
        np.asarray(Image.fromarray(np.ascontiguousarray(image[..., c], dtype=np.float32)).resize((width, height), Image.BOX))
        for c in range(image.shape[-1])
    ]
    return np.stack(chans, axis=-1).astype(np.float32)


def resize_nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of a [H, W] float32 or uint8 map (depth, part ids)."""
    from PIL import Image

    return np.asarray(Image.fromarray(np.ascontiguousarray(image)).resize((width, height), Image.NEAREST)).copy()


# ----------------------------------------------------------------------------- loading


def _matrix(path: Path, k: int, frame) -> np.ndarray:
    m = frame.get("transform_matrix") if isinstance(frame, dict) else None
    try:
        c2w = np.array(m, dtype=np.float64)
    except (TypeError, ValueError):
        c2w = None
    if c2w is None or c2w.shape != (4, 4):
        raise DataError(f"{path}: frames[{k}].transform_matrix is not a 4x4 matrix")
    if not np.isfinite(c2w).all():
        raise DataError(f"{path}: frames[{k}].transform_matrix has non-finite values")
    if abs(np.linalg.det(c2w[:3, :3])) < 1e-8 or abs(np.linalg.det(c2w)) < 1e-8:
        raise DataError(f"{path}: frames[{k}].transform_matrix is not invertible")
    return c2w


def _image_path(instance_dir: Path, file_path: str) -> Path:
    """``file_path`` + ``.png``, unless it already ends in an image extension."""
    path = instance_dir / file_path
    return path if path.suffix.lower() in IMAGE_EXTENSIONS else path.with_name(path.name + ".png")


def _sidecar(instance_dir: Path, file_path: str, tail: str) -> Path:
    """``r_000`` → ``r_000<tail>`` (``_depth.exr``, ``_parts.png``), image extension dropped."""
    path = instance_dir / file_path
    stem = path.stem if path.suffix.lower() in IMAGE_EXTENSIONS else path.name
    return path.with_name(stem + tail)


def _load_split(
    instance_dir: Path, split: str, res: int | None, with_depth: bool, with_parts: bool
) -> list[View] | None:
    """Views of one split, or None when its transforms file does not exist."""
    path = instance_dir / f"transforms_{split}.json"
    if not path.is_file():
        return None
    meta = _read_json(path)
    if not isinstance(meta, dict):
        raise DataError(f"{path}: expected a JSON object with camera_angle_x and frames")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{path}: missing frames list")
    if not frames:
        raise DataError(f"{path}: empty split (no frames)")
    angle = meta.get("camera_angle_x")
    focal_px = meta.get("focal", meta.get("fl_x"))
    if not isinstance(angle, (int, float)) and not isinstance(focal_px, (int, float)):
        raise DataError(f"{path}: missing camera_angle_x (or focal / fl_x)")
    views, first_size = [], None
    for k, frame in enumerate(frames):
        file_path = frame.get("file_path") if isinstance(frame, dict) else None
        if not isinstance(file_path, str) or not file_path:
            raise DataError(f"{path}: frames[{k}] has no file_path")
        c2w = _matrix(path, k, frame)
        image_path = _image_path(instance_dir, file_path)
        image = _read_rgba(image_path)
        h, w = image.shape[:2]
        if first_size is None:
            first_size = (w, h)
        elif (w, h) != first_size:
            raise DataError(f"{image_path}: size {w}x{h} differs from {first_size[0]}x{first_size[1]} of the split's first image")
        if isinstance(angle, (int, float)):
            focal = focal_from_angle(float(angle), w)
        else:
            focal = float(focal_px) * w / float(meta.get("w", w))
        if not (math.isfinite(focal) and focal > 0):
            raise DataError(f"{path}: camera_angle_x / focal gives a non-positive focal length")
        alpha = image[..., 3] if image.shape[2] == 4 else np.ones((h, w), np.float32)
        rgb = image[..., :3] * alpha[..., None] + (1.0 - alpha[..., None]) if image.shape[2] == 4 else image[..., :3]
        depth = parts = None
        depth_path = _sidecar(instance_dir, file_path, "_depth.exr")
        if with_depth and depth_path.is_file():
            depth = _read_depth(depth_path, (h, w))
        parts_path = _sidecar(instance_dir, file_path, "_parts.png")
        if with_parts and parts_path.is_file():
            parts = _read_parts(parts_path, (h, w))
        camera = Camera(c2w, focal, w, h)
        if res is not None and res != w:
            rh = max(1, round(h * res / w))
            resized = resize_area(np.concatenate([rgb, alpha[..., None]], axis=-1), res, rh)
            rgb, alpha = resized[..., :3], resized[..., 3]
            depth = None if depth is None else resize_nearest(depth, res, rh)
            parts = None if parts is None else resize_nearest(parts, res, rh)
            camera = camera.resized(res, rh)
        rgb, alpha = np.ascontiguousarray(rgb, np.float32), np.ascontiguousarray(alpha, np.float32)
        views.append(View(camera, rgb, alpha, depth, parts, file_path))
    return views


def load_instance_dir(
    path: Path,
    name: str,
    res: int | None = None,
    splits: tuple[str, ...] = SPLITS,
    with_depth: bool = False,
    with_parts: bool = False,
) -> InstanceData:
    """One NeRF-synthetic folder; splits without a transforms file are left out."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: instance folder not found")
    if res is not None and res < 1:
        raise DataError(f"--res {res}: must be a positive number of pixels")
    loaded = {}
    for split in splits:
        views = _load_split(path, split, res, with_depth, with_parts)
        if views is not None:
            loaded[split] = views
    if not loaded:
        wanted = ", ".join(f"transforms_{s}.json" for s in splits)
        raise DataError(f"{path}: no transforms file found (looked for {wanted})")
    return InstanceData(name, path, loaded)


def instance_names(root: Path) -> list[str]:
    """Names from ``root/instances.txt``, or ``[root.name]`` for a single NeRF-synthetic scene."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found")
    listing = root / "instances.txt"
    if not listing.is_file():
        if (root / "transforms_train.json").is_file():
            return [root.resolve().name]
        raise DataError(f"{listing}: file not found (neither a category folder, a NeRF-synthetic scene nor nerfstudio transforms.json scenes)")
    try:
        lines = listing.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{listing}: cannot read ({e.__class__.__name__})") from None
    names = [ln.strip() for ln in lines if ln.strip() and not ln.strip().startswith("#")]
    if not names:
        raise DataError(f"{listing}: lists no instances")
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise DataError(f"{listing}: instance {dupes[0]} is listed twice")
    for n in names:
        if not (root / n).is_dir():
            raise DataError(f"{listing}: instance folder {n} not found in {root}")
    return names


def _instance_dir(root: Path, name: str) -> Path:
    return root if not (root / "instances.txt").is_file() else root / name


def category_fingerprint(root: Path, names: list[str]) -> str:
    """sha256 (16 hex) over instances.txt (or the scene name) and every transforms file, by relative name."""
    root = Path(root)
    h = hashlib.sha256()
    listing = root / "instances.txt"
    h.update(listing.read_bytes() if listing.is_file() else f"scene:{names[0]}\n".encode())
    for name in names:
        for split in SPLITS:
            path = _instance_dir(root, name) / f"transforms_{split}.json"
            if path.is_file():
                h.update(f"\n{name}/transforms_{split}.json\n".encode())
                h.update(path.read_bytes())
    return h.hexdigest()[:16]


def load_category(
    root: Path,
    res: int | None = None,
    splits: tuple[str, ...] = SPLITS,
    with_depth: bool = False,
    with_parts: bool = False,
) -> Category:
    """Load every instance listed in ``instances.txt`` (or the single scene at ``root``, or
    nerfstudio ``transforms.json`` scenes: :mod:`crfedit.data.nerfstudio`)."""
    root = Path(root)
    if root.is_dir() and not (root / "instances.txt").is_file() and not (root / "transforms_train.json").is_file():
        from .nerfstudio import load_nerfstudio_category, scene_folders

        if scene_folders(root):
            return load_nerfstudio_category(root, res, splits)
    names = instance_names(root)
    instances = [load_instance_dir(_instance_dir(root, n), n, res, splits, with_depth, with_parts) for n in names]
    return Category(root, instances, category_fingerprint(root, names))


def read_twin_specs(root: Path) -> list[TwinSpec]:
    """The twins listed in ``root/twins.json``; [] when there is none."""
    path = Path(root) / "twins.json"
    if not path.is_file():
        return []
    meta = _read_json(path)
    entries = meta.get("twins") if isinstance(meta, dict) else None
    if not isinstance(entries, list):
        raise DataError(f"{path}: expected {{\"twins\": [...]}}")
    names = [f.name for f in fields(TwinSpec)]
    specs = []
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict) or set(names) - set(entry) - {"color"}:
            missing = sorted(set(names) - set(entry) - {"color"}) if isinstance(entry, dict) else names
            raise DataError(f"{path}: twins[{k}] is missing {', '.join(missing)}")
        spec = TwinSpec(**{n: entry.get(n) for n in names})
        if spec.kind not in TWIN_KINDS:
            raise DataError(f"{path}: twins[{k}].kind {spec.kind!r} is not one of {', '.join(TWIN_KINDS)}")
        if spec.kind == "color" and not (isinstance(spec.color, str) and len(spec.color) == 7 and spec.color.startswith("#")):
            raise DataError(f"{path}: twins[{k}].color must be #rrggbb for a color twin")
        parse_view_spec(spec.view)
        specs.append(spec)
    return specs


def load_twins(root: Path, res: int | None = None) -> list[tuple[TwinSpec, InstanceData]]:
    """Each twin of ``root/twins.json`` with its rendered test views; [] when there are none."""
    root = Path(root)
    twins = []
    for spec in read_twin_specs(root):
        for rel in (spec.scribble, spec.keep):
            if not (root / rel).is_file():
                raise DataError(f"{root / 'twins.json'}: twin {spec.name}: scribble {root / rel} not found")
        twins.append((spec, load_instance_dir(root / spec.folder, spec.name, res, ("test",), with_depth=True, with_parts=True)))
    return twins


# ----------------------------------------------------------------------------- derived


@dataclass(frozen=True, eq=False)
class TrainingRays:
    """Every pixel ray of one split of a category, flattened."""

    origins: torch.Tensor  # [N, 3] float32
    directions: torch.Tensor  # [N, 3] float32, unit length
    rgb: torch.Tensor  # [N, 3] float32, composited on white
    alpha: torch.Tensor  # [N] float32
    instance: torch.Tensor  # [N] int64 instance index


def training_rays(category: Category, split: str = "train", instances: Sequence[int] | None = None) -> TrainingRays:
    """All rays of ``split`` over all instances (or those indexed by ``instances``: a rank's
    share), in instance, view, row-major pixel order."""
    o, d, rgb, alpha, inst = [], [], [], [], []
    for index in range(len(category.instances)) if instances is None else instances:
        instance = category.instances[index]
        for view in instance.splits.get(split, []):
            rays = rays_from_camera(view.camera)
            o.append(rays.origins)
            d.append(rays.directions)
            rgb.append(torch.from_numpy(view.rgb.reshape(-1, 3)))
            alpha.append(torch.from_numpy(view.alpha.reshape(-1)))
            inst.append(torch.full((view.alpha.size,), index, dtype=torch.int64))
    if not o:
        raise DataError(f"{category.root}: no {split} views in any instance")
    return TrainingRays(torch.cat(o), torch.cat(d), torch.cat(rgb), torch.cat(alpha), torch.cat(inst))


def _depth_points(view: View) -> np.ndarray:
    """World points of the finite-depth pixels of ``view``.  [M, 3]"""
    rays = rays_from_camera(view.camera)
    t = view.depth.reshape(-1)
    keep = np.isfinite(t)
    return rays.origins.numpy()[keep].astype(np.float64) + rays.directions.numpy()[keep] * t[keep, None]


def bounding_box(category: Category) -> tuple[np.ndarray, np.ndarray, str]:
    """(min, max, source): from depth maps' finite points when loaded, else camera centers."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    views = [v for inst in category.instances for vs in inst.splits.values() for v in vs]
    for view in views:
        if view.depth is not None and np.isfinite(view.depth).any():
            pts = _depth_points(view)
            lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
    if np.isfinite(lo).all():
        return lo, hi, "depth"
    centers = np.stack([v.camera.center for v in views])
    return centers.min(0), centers.max(0), "cameras"


def dataset_info(category: Category) -> dict:
    """Instances, views per split, resolutions, bounding box, twins and fingerprint, as plain JSON types."""
    views, per_instance = {}, {}
    for split in SPLITS:
        counts = [len(inst.splits[split]) for inst in category.instances if split in inst.splits]
        if counts:
            views[split] = sum(counts)
            per_instance[split] = [min(counts), max(counts)]
    sizes = sorted({(v.camera.width, v.camera.height) for inst in category.instances for vs in inst.splits.values() for v in vs})
    lo, hi, source = bounding_box(category)
    return {
        "root": str(category.root),
        "instances": len(category.instances),
        "names": category.names,
        "views": views,
        "views_per_instance": per_instance,
        "resolutions": [f"{w}x{h}" for w, h in sizes],
        "bbox": {"min": [round(float(x), 6) for x in lo], "max": [round(float(x), 6) for x in hi], "source": source},
        "twins": len(read_twin_specs(category.root)),
        "fingerprint": category.fingerprint,
    }
