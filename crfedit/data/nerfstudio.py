"""nerfstudio ``transforms.json`` scenes as crfedit categories (docs/datasets.md).

A scene folder holds ``transforms.json``: intrinsics ``fl_x fl_y cx cy w h`` (top level, or per
frame), and ``frames[]`` with ``file_path`` (relative, extension included), a 4×4 camera-to-world
``transform_matrix`` (OpenGL axes, as NeRF-synthetic) and an optional ``mask_path`` (0 =
background).  One scene is a one-instance category; a folder whose sub-folders are scenes is a
category of them, named by folder.  Splits: ``train_filenames`` / ``val_filenames`` /
``test_filenames`` when the file lists them (frames in none are left out), else every 10th frame
(at least one) is a test view.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path, PurePosixPath

import numpy as np

from ..cameras import Camera, angle_from_focal, narrow_view
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


def _intrinsics(path: Path, meta: dict, frame: dict, k: int, size: tuple[int, int]) -> dict[str, float]:
    """``fl_x fl_y cx cy w h`` of frame ``k`` (its own, else the file's); without ``fl_x`` /
    ``fl_y``, from ``camera_angle_x`` / ``camera_angle_y`` (instant-ngp, Blender), and then
    ``w h`` default to the image's ``size`` and ``cx cy`` to its center."""
    def number(key: str) -> float | None:
        v = frame.get(key, meta.get(key))
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise DataError(f"{path}: frames[{k}]: {key} {v!r} must be a number")
        if not (math.isfinite(v) and v > 0 and (not key.startswith("camera_angle") or v < math.pi)):
            raise DataError(f"{path}: frames[{k}]: {key} {v!r} must be " + ("a field of view in radians, between 0 and π" if key.startswith("camera_angle") else "a positive number"))
        return float(v)

    values = {key: number(key) for key in INTRINSICS}
    angle_x, angle_y = number("camera_angle_x"), number("camera_angle_y")
    if values["fl_x"] is None and angle_x is not None:
        w, h = (values["w"] or size[0]), (values["h"] or size[1])
        fl_x = 0.5 * w / math.tan(0.5 * angle_x)
        fl_y = values["fl_y"] or (0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fl_x)
        values = {"fl_x": fl_x, "fl_y": fl_y, "cx": values["cx"] or w / 2, "cy": values["cy"] or h / 2, "w": w, "h": h}
    missing = [key for key in INTRINSICS if values[key] is None]
    if missing:
        raise DataError(f"{path}: frames[{k}] has no {missing[0]} (nor the file, nor camera_angle_x)")
    if any(abs(float(frame.get(d, meta.get(d, 0.0)) or 0.0)) > 1e-6 for d in DISTORTION):
        raise DataError(f"{path}: lens distortion (k1..p2) is not supported; undistort the images first (ns-process-data does)")
    w, h = values["w"], values["h"]
    narrow = narrow_view(angle_from_focal(values["fl_x"], w)) if math.isfinite(values["fl_x"]) and values["fl_x"] > 0 else "no field of view"
    if narrow:
        raise DataError(f"{path}: frames[{k}]: fl_x {values['fl_x']:g} for an image {w:g} pixels wide gives {narrow}; fl_x is in pixels")
    if abs(values["fl_x"] - values["fl_y"]) > 0.01 * values["fl_x"]:
        raise DataError(f"{path}: frames[{k}]: fl_x {values['fl_x']:g} and fl_y {values['fl_y']:g} differ; crfedit cameras have square pixels")
    if abs(values["cx"] - w / 2) > 0.02 * w or abs(values["cy"] - h / 2) > 0.02 * h:
        raise DataError(f"{path}: frames[{k}]: principal point ({values['cx']:g}, {values['cy']:g}) is off the image center; crop the images around it")
    return values


def _normal(name: str) -> str:
    """A file name as nerfstudio compares them (as a path): ``./images/a.png`` is ``images/a.png``."""
    return PurePosixPath(posix_path(name)).as_posix()


def _split_of(path: Path, meta: dict, names: list, notes: list[str]) -> list[str | None]:
    """The split of each frame, from the ``*_filenames`` lists (a frame in none is left out, with
    a note, and a listed name that is no frame's ``file_path`` is an error, as in nerfstudio),
    else every 10th frame (at least the last one) for test."""
    given = {split: meta[f"{split}_filenames"] for split in ("train", "val", "test") if isinstance(meta.get(f"{split}_filenames"), list)}
    if given:
        known = {_normal(n) for n in names if isinstance(n, str)}
        listed = {}
        for split, files in given.items():
            unknown = [f for f in files if not isinstance(f, str) or _normal(f) not in known]
            if unknown:
                raise DataError(f"{path}: {split}_filenames lists {unknown[0]!r}, which is no frame's file_path"
                                + (f" (nor are {len(unknown) - 1} more)" if len(unknown) > 1 else ""))
            listed[split] = {_normal(f) for f in files}
        split = [next((s for s, files in listed.items() if isinstance(n, str) and _normal(n) in files), None) for n in names]
        left = split.count(None)
        if left:
            notes.append(f"{path}: {left} frame{'s' * (left != 1)} in none of {', '.join(f'{s}_filenames' for s in given)} "
                         "left out (as nerfstudio does)")
        return split
    split = ["test" if i % 10 == 9 else "train" for i in range(len(names))]
    if "test" not in split and len(split) > 1:
        split[-1] = "test"
    return split


def _view(folder: Path, path: Path, meta: dict, frame, k: int, res: int | None) -> View:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
        raise DataError(f"{path}: frames[{k}] has no file_path")
    image = _read_rgba(folder / posix_path(frame["file_path"]))
    h, w = image.shape[:2]
    intr = _intrinsics(path, meta, frame, k, (w, h))
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


def load_scene(folder: Path, name: str, res: int | None = None, splits: tuple[str, ...] = ("train", "val", "test"),
               notes: list[str] | None = None) -> InstanceData:
    """One nerfstudio scene as an instance; splits as the module docstring says.  ``notes``
    gets a line on what is left out."""
    path = Path(folder) / TRANSFORMS
    meta = _read_json(path)
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{path}: missing or empty frames list")
    names = [f.get("file_path") if isinstance(f, dict) else None for f in frames]
    loaded: dict[str, list[View]] = {}
    for k, (frame, split) in enumerate(zip(frames, _split_of(path, meta, names, [] if notes is None else notes))):
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
    notes = []
    skipped = [] if is_scene(root) else sorted(p.name for p in Path(root).iterdir() if p.is_dir() and not p.name.startswith(".") and p not in folders)
    if skipped:
        notes.append(f"{root}: sub-folder{'s' * (len(skipped) != 1)} without {TRANSFORMS} skipped: {', '.join(skipped[:6])}"
                     + (f" and {len(skipped) - 6} more" if len(skipped) > 6 else ""))
    instances = [load_scene(f, n, res, splits, notes) for f, n in zip(folders, names)]
    return Category(Path(root), instances, h.hexdigest()[:16], tuple(notes))
