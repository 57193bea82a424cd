"""nerfstudio ``transforms.json`` scenes as crfedit categories (docs/datasets.md).

A scene folder holds ``transforms.json``: intrinsics ``fl_x fl_y cx cy w h`` (top level, or per
frame), and ``frames[]`` with ``file_path`` (relative, extension included), a 4×4 camera-to-world
``transform_matrix`` (OpenGL axes, as NeRF-synthetic) and an optional ``mask_path`` (0 =
background).  One scene is a one-instance category; a folder whose sub-folders are scenes is a
category of them, named by folder.  Splits: ``train_filenames`` / ``val_filenames`` /
``test_filenames`` when the file lists them, else every 10th frame (at least one) is a test view.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

from ..cameras import Camera
from .format import DataError, _read_json, _read_rgba, resize_area
from .loading import Category, InstanceData, View, _matrix, posix_path

TRANSFORMS = "transforms.json"
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def is_scene(folder: Path) -> bool:
    return (Path(folder) / TRANSFORMS).is_file()


def scene_folders(root: Path) -> list[Path]:
    """``[root]`` for a scene, else its sub-folders that are scenes (sorted); [] for neither."""
    root = Path(root)
    if is_scene(root):
        return [root]
    return sorted(p for p in root.iterdir() if p.is_dir() and is_scene(p)) if root.is_dir() else []


def _intrinsics(path: Path, meta: dict, frame: dict, k: int) -> dict[str, float]:
    values = {}
    for key in INTRINSICS:
        v = frame.get(key, meta.get(key))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise DataError(f"{path}: frames[{k}] has no valid {key} (nor the file)")
        values[key] = float(v)
    if any(abs(float(frame.get(d, meta.get(d, 0.0)) or 0.0)) > 1e-6 for d in DISTORTION):
        raise DataError(f"{path}: lens distortion (k1..p2) is not supported; undistort the images first (ns-process-data does)")
    w, h = values["w"], values["h"]
    if abs(values["fl_x"] - values["fl_y"]) > 0.01 * values["fl_x"]:
        raise DataError(f"{path}: frames[{k}]: fl_x {values['fl_x']:g} and fl_y {values['fl_y']:g} differ; crfedit cameras have square pixels")
    if abs(values["cx"] - w / 2) > 0.02 * w or abs(values["cy"] - h / 2) > 0.02 * h:
        raise DataError(f"{path}: frames[{k}]: principal point ({values['cx']:g}, {values['cy']:g}) is off the image center; crop the images around it")
    return values


def _split_of(meta: dict, names: list[str]) -> list[str]:
    """The split of each frame, from ``*_filenames`` lists, else every 10th frame (at least the
    last one) for test."""
    listed = {split: {posix_path(f) for f in meta.get(f"{split}_filenames") or [] if isinstance(f, str)} for split in ("train", "val", "test")}
    if any(listed.values()):
        return [next((s for s, files in listed.items() if isinstance(n, str) and posix_path(n) in files), "train") for n in names]
    split = ["test" if i % 10 == 9 else "train" for i in range(len(names))]
    if "test" not in split and len(split) > 1:
        split[-1] = "test"
    return split


def _view(folder: Path, path: Path, meta: dict, frame, k: int, res: int | None) -> View:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
        raise DataError(f"{path}: frames[{k}] has no file_path")
    image = _read_rgba(folder / posix_path(frame["file_path"]))
    h, w = image.shape[:2]
    intr = _intrinsics(path, meta, frame, k)
    if (intr["w"], intr["h"]) != (w, h):
        raise DataError(f"{folder / frame['file_path']}: image is {w}x{h} but transforms.json says {intr['w']:g}x{intr['h']:g}")
    alpha = image[..., 3] if image.shape[2] == 4 else np.ones((h, w), np.float32)
    if isinstance(frame.get("mask_path"), str):
        mask = _read_rgba(folder / posix_path(frame["mask_path"]))
        if mask.shape[:2] != (h, w):
            raise DataError(f"{folder / frame['mask_path']}: mask size differs from its image")
        alpha = alpha * (mask[..., :3].mean(axis=-1) >= 0.5)
    rgb = image[..., :3] * alpha[..., None] + (1.0 - alpha[..., None])
    camera = Camera(_matrix(path, k, frame), 0.5 * (intr["fl_x"] + intr["fl_y"]), w, h)
    if res is not None and res != w:
        rh = max(1, round(h * res / w))
        resized = resize_area(np.concatenate([rgb, alpha[..., None]], axis=-1), res, rh)
        rgb, alpha, camera = resized[..., :3], resized[..., 3], camera.resized(res, rh)
    return View(camera, np.ascontiguousarray(rgb, np.float32), np.ascontiguousarray(alpha, np.float32), None, None, frame["file_path"])


def load_scene(folder: Path, name: str, res: int | None = None, splits: tuple[str, ...] = ("train", "val", "test")) -> InstanceData:
    """One nerfstudio scene as an instance; splits as the module docstring says."""
    path = Path(folder) / TRANSFORMS
    meta = _read_json(path)
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{path}: missing or empty frames list")
    names = [f.get("file_path") if isinstance(f, dict) else None for f in frames]
    loaded: dict[str, list[View]] = {}
    for k, (frame, split) in enumerate(zip(frames, _split_of(meta, names))):
        if split in splits:
            loaded.setdefault(split, []).append(_view(Path(folder), path, meta, frame, k, res))
    if "train" in splits and "train" not in loaded:
        raise DataError(f"{path}: no training frames")
    return InstanceData(name, Path(folder), loaded)


def load_nerfstudio_category(root: Path, res: int | None = None, splits: tuple[str, ...] = ("train", "val", "test")) -> Category:
    """A scene (one instance, named by its folder) or a folder of scenes (one instance each)."""
    folders = scene_folders(root)
    if not folders:
        raise DataError(f"{root}: no {TRANSFORMS} in it or in its sub-folders")
    names = [f.resolve().name for f in folders]
    h = hashlib.sha256(b"nerfstudio\n")
    for name, folder in zip(names, folders):
        h.update(f"{name}/{TRANSFORMS}\n".encode())
        h.update((folder / TRANSFORMS).read_bytes())
    return Category(Path(root), [load_scene(f, n, res, splits) for f, n in zip(folders, names)], h.hexdigest()[:16])
