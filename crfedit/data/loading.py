"""Loaded category datasets: View/InstanceData/Category, loading a dataset folder, twins, and
what training derives from it (ray tables, bounding box, summary).  File format: :mod:`.format`."""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..cameras import Camera, angle_from_focal, c2w_problem, focal_from_angle, narrow_view, rays_from_camera
from ..errors import DataError
from ..names import did_you_mean, is_digits
from .format import (
    IMAGE_EXTENSIONS,
    SPLITS,
    TWIN_KINDS,
    TwinSpec,
    _read_depth,
    _read_json,
    _read_parts,
    _read_rgba,
    resize_area,
    resize_nearest,
)


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
    if not sep or split not in SPLITS or not is_digits(index.strip()):
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
    notes: tuple[str, ...] = ()  # what loading left out, a line each (nerfstudio: unlisted frames, sub-folders that are no scenes)

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
        raise DataError(f"unknown instance {key!r} (valid: {shown}; {len(names)} in all){did_you_mean(key, names)}")


# ----------------------------------------------------------------------------- loading


def _matrix(path: Path, k: int, frame) -> np.ndarray:
    c2w, problem = c2w_problem(frame.get("transform_matrix") if isinstance(frame, dict) else None)
    if problem:
        raise DataError(f"{path}: frames[{k}].transform_matrix {problem}")
    return c2w


def posix_path(file_path: str) -> str:
    """A transforms file's relative path with Windows separators read as ``/`` (files written
    on Windows, or by tools built there, say ``images\\r_0.png``); a backslash inside a POSIX
    file name is rare enough to give up for it."""
    return file_path.replace("\\", "/")


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
    if isinstance(angle, (int, float)) and not 0 < angle < math.pi:  # 0 or π: no pinhole camera has it
        raise DataError(f"{path}: camera_angle_x {angle}: a field of view in radians, between 0 and π")
    views, first_size = [], None
    for k, frame in enumerate(frames):
        file_path = frame.get("file_path") if isinstance(frame, dict) else None
        if not isinstance(file_path, str) or not file_path:
            raise DataError(f"{path}: frames[{k}] has no file_path")
        file_path = posix_path(file_path)
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
        narrow = narrow_view(angle_from_focal(focal, w))
        if narrow:
            raise DataError(f"{path}: camera_angle_x / focal gives {narrow}; camera_angle_x is in radians, focal in pixels")
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
        raise DataError(f"{root}: is a file, not a dataset folder" if root.exists() else f"{root}: dataset folder not found")
    listing = root / "instances.txt"
    if not listing.is_file():
        if (root / "transforms_train.json").is_file():
            return [root.resolve().name]
        raise DataError(f"{listing}: file not found (neither a category folder, a NeRF-synthetic scene nor nerfstudio transforms.json scenes)")
    try:
        lines = listing.read_text(encoding="utf-8-sig").splitlines()  # a BOM (Windows Notepad) is not part of the first name
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


def pixels_digest(category: "Category", split: str = "train") -> str:
    """sha256 (16 hex) over the loaded views' pixels (colour and alpha, at the size loaded) of
    ``split``: what :func:`category_fingerprint` leaves out (it reads the camera files, not the
    images), for ranks to prove they train on the same data (another node's copy, ``--res``)."""
    h = hashlib.sha256()
    for inst in category.instances:
        for view in inst.splits.get(split, []):
            h.update(f"{inst.name}:{view.rgb.shape}".encode())
            h.update(np.ascontiguousarray(view.rgb).tobytes())
            h.update(np.ascontiguousarray(view.alpha).tobytes())
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
        counts = [len(inst.splits.get(split, [])) for inst in category.instances]
        if any(counts):
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
        "without_train_views": [inst.name for inst in category.instances if not inst.splits.get("train")],
        "fingerprint": category.fingerprint,
    }
