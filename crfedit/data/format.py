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

import json
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..cameras import Camera, subpixel_offsets
from ..errors import CrfError, DataError
from ..io import atomic_write_text, carry_into, not_a_file, read_exr, read_image, read_json, write_exr, write_json, write_png

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


SMALL_COVER = 0.01
"""An object shown on less than this share of its training views' pixels (the median view,
:func:`median_cover`) is too small to train: one stray triangle far from a mesh scaled by its
bounding box shrank a tester's chair to 0–2 pixels a view.  ``dataset from-meshes`` notes it, and
``train`` (``dataset info``) names it when its visual hull comes out empty."""


def median_cover(alphas) -> float:
    """The median over views of the share of pixels whose alpha is above 0.5 (``alphas``: [H, W]
    arrays); 1 for no views."""
    return float(np.median([float((a > 0.5).mean()) for a in alphas])) if len(alphas) else 1.0


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


DATASET_ENTRIES = ("instances.txt", "twins.json", "twins", "ATTRIBUTION.txt")
"""What a dataset build writes at its root beside the instance folders."""


SCENE_FILES = ("parts.json", "scribble.png", "keep.png")
"""What a dataset build writes in an instance's or a twin's folder beside its transforms and frames."""


def _scene_owned(folder: Path) -> set[Path]:
    """The files of an instance's or a twin's folder that a build wrote: its transforms, each
    frame's image, depth and part map, and :data:`SCENE_FILES`."""
    owned = {folder / n for n in SCENE_FILES}
    for transforms in folder.glob("transforms_*.json"):
        owned.add(transforms)
        try:
            frames = json.loads(transforms.read_text()).get("frames", [])
        except (OSError, ValueError, AttributeError):
            continue
        for frame in frames if isinstance(frames, list) else []:
            path = frame.get("file_path") if isinstance(frame, dict) else None
            if isinstance(path, str):
                base = folder / path
                owned.update({base, base.with_name(base.name + ".png"), base.with_name(base.name + "_depth.exr"),
                              base.with_name(base.name + "_parts.png")})
    return owned


def dataset_extras(root: Path) -> list[Path]:
    """The entries of a dataset folder no dataset build wrote (a user's notes or scribbles),
    relative to ``root``: at the top, anything but the instance folders (those holding
    ``transforms_train.json``), twins, instance list and attribution; inside an instance's or a
    twin's folder, any file its transforms, frames and :data:`SCENE_FILES` do not account for
    (a folder of them as one entry).  Hidden entries are skipped.  A build that replaces the
    folder carries them over (:func:`carry_extras`)."""
    root = Path(root)
    if not root.is_dir():
        return []
    out: list[Path] = []
    scenes = [p for p in root.iterdir() if p.is_dir() and not p.is_symlink() and (p / "transforms_train.json").is_file()]
    scenes += [p for p in sorted((root / "twins").glob("*")) if p.is_dir() and not p.is_symlink() and any(p.glob("transforms_*.json"))]
    for p in sorted(root.iterdir()):
        if not p.name.startswith(".") and p.name not in DATASET_ENTRIES and p not in scenes:
            out.append(p.relative_to(root))
    if (root / "twins").is_dir():
        out += [p.relative_to(root) for p in sorted((root / "twins").iterdir()) if not p.name.startswith(".") and p not in scenes]
    for scene in scenes:
        owned = _scene_owned(scene)

        def walk(folder: Path) -> None:
            for p in sorted(folder.iterdir()):
                if p.name.startswith(".") or p in owned:
                    continue
                if p.is_dir() and not p.is_symlink():
                    if any(q in owned for q in p.rglob("*")):
                        walk(p)  # a split folder: its frames are the build's, anything else in it is not
                    else:
                        out.append(p.relative_to(root))
                else:
                    out.append(p.relative_to(root))

        walk(scene)
    return out


def carry_extras(old: Path, new: Path) -> list[str]:
    """Carry :func:`dataset_extras` of the dataset ``old`` into the folder ``new`` built to
    replace it, each at its own place (its folders made as needed, names already there left
    alone); the carried paths, relative, as the line names them."""
    carried = []
    for rel in dataset_extras(old):
        (Path(new) / rel).parent.mkdir(parents=True, exist_ok=True)
        carried += [str(rel.parent / n) if str(rel.parent) != "." else n for n in carry_into([Path(old) / rel], Path(new) / rel.parent)]
    return carried


def write_instances_txt(root: Path, names: list[str]) -> None:
    atomic_write_text(Path(root) / "instances.txt", "".join(f"{n}\n" for n in names))


def write_twins_json(root: Path, twins: list[TwinSpec]) -> None:
    write_json(Path(root) / "twins.json", {"twins": [asdict(t) for t in twins]})


# ----------------------------------------------------------------------------- reading files


def _data_error(e: CrfError) -> DataError:
    return e if isinstance(e, DataError) else DataError(str(e))


def _read_json(path: Path):
    try:
        return read_json(path)
    except CrfError as e:
        raise _data_error(e) from None


def srgb_from_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]: what a PNG of the
    same render stores."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def _read_rgba(path: Path) -> np.ndarray:
    """Image as float32 [H, W, 3|4] in [0, 1], straight alpha, sRGB like every PNG: an EXR image
    holds linear light with its colour premultiplied by alpha (the OpenEXR convention, which
    Blender writes), so its colour is divided by alpha and encoded as sRGB.  Read as they were,
    an EXR dataset trained 17.05 dB against its own PNG twin's 30.24 (a chair rendered dark)."""
    if path.suffix.lower() == ".exr":
        channels = _read_exr(path)
        if not {"R", "G", "B"} <= channels.keys():
            raise DataError(f"{path}: EXR image needs R, G, B channels (has {', '.join(sorted(channels))})")
        arr = np.stack([channels[c] for c in ("R", "G", "B", "A") if c in channels], axis=-1).astype(np.float64)
        if not np.isfinite(arr).all():
            raise DataError(f"{path}: image has NaN or infinite pixels")
        if arr.shape[-1] == 4:
            alpha = np.clip(arr[..., 3:], 0.0, 1.0)
            arr[..., :3] = np.where(alpha > 0, arr[..., :3] / np.maximum(alpha, 1e-12), 0.0)  # premultiplied → straight
            arr[..., 3:] = alpha
        arr[..., :3] = srgb_from_linear(arr[..., :3])
        return arr.astype(np.float32)
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise DataError(f"{path}: {not_a_file(path, 'image not found')}")
    try:
        with Image.open(path) as im:
            mode = im.mode
    except Image.DecompressionBombError:
        raise DataError(f"{path}: image too large to read (past Pillow's limit on pixels)") from None
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
