"""What an edit did to a ground-truth twin, beyond one PSNR (issue: honest edit evaluation).

For a twin and the source's test views (the same poses):

* ``psnr_before`` — the unedited model against the twin: what doing nothing scores;
* ``psnr_ceiling`` — the unedited model against the *source's* own images: the best an edit
  can hope for at this reconstruction quality;
* ``gap_closed = (psnr − psnr_before) / (psnr_ceiling − psnr_before)``;
* ``psnr_inside`` / ``psnr_outside`` — PSNR over the pixels where the twin differs from the
  source (the edit's region) and over the rest, so bleed and damage show up separately;
* ``selection_iou`` — the 3-D selection of the twin's scribbles against the part's pixels of
  the source's test views (part maps), when the dataset has them, over the pixels both the part
  map and the render show as object.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from .cameras import Camera
from .data.format import resize_nearest
from .data.loading import View
from .edit.scribble import parse_color
from .edit.selection import Selection, surface_points
from .errors import CrfError
from .io import read_json
from .model import CategoryModel

CHANGED = 2.0 / 255.0
"""A pixel belongs to the twin's edit region where any channel differs from the source by more than this."""


def changed_regions(source_views: Sequence[View], twin_views: Sequence[View]) -> list[np.ndarray]:
    """Per view, [H, W] bool: where the twin differs from the source."""
    return [np.abs(t.rgb - s.rgb).max(axis=-1) > CHANGED for s, t in zip(source_views, twin_views)]


def masked_psnr(preds: Sequence[np.ndarray], targets: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> float | None:
    """PSNR over the masked pixels of all views together (None when no pixel is masked)."""
    err = [((p - t) ** 2)[m] for p, t, m in zip(preds, targets, masks)]
    values = np.concatenate([e.reshape(-1) for e in err]) if err else np.zeros(0)
    if values.size == 0:
        return None
    mse = float(values.mean())
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def region_scores(preds, twin_views: Sequence[View], regions: Sequence[np.ndarray]) -> dict:
    """{"psnr_inside", "psnr_outside"} of ``preds`` against the twin."""
    targets = [v.rgb for v in twin_views]
    return {
        "psnr_inside": masked_psnr(preds, targets, regions),
        "psnr_outside": masked_psnr(preds, targets, [~r for r in regions]),
    }


def gap_closed(psnr: float | None, before: float | None, ceiling: float | None) -> float | None:
    """(psnr − before) / (ceiling − before); None when undefined (no gap to close)."""
    if None in (psnr, before, ceiling) or not np.isfinite([psnr, before, ceiling]).all() or ceiling - before <= 1e-9:
        return None
    return float((psnr - before) / (ceiling - before))


def part_of(instance_dir: Path, part: str) -> dict | None:
    """The part record ``{"id", "name", "color"}`` named ``part`` in ``parts.json``, if any."""
    path = Path(instance_dir) / "parts.json"
    if not path.is_file():
        return None
    parts = read_json(path)  # a BOM or malformed JSON: one line naming the file
    if not isinstance(parts, list) or not all(isinstance(p, dict) for p in parts):
        raise CrfError(f"{path}: expected a list of parts [{{\"id\", \"name\", \"color\"}}, ...]")
    return next((p for p in parts if p.get("name") == part), None)


def part_map(instance_dir: Path, view: View) -> np.ndarray | None:
    """The view's part-id map [H, W] at its size, or None when the dataset has none."""
    from PIL import Image

    path = Path(instance_dir) / f"{view.file_path}_parts.png"
    if not path.is_file():
        return None
    ids = np.asarray(Image.open(path))
    return resize_nearest(ids, view.camera.width, view.camera.height) if ids.shape != (view.camera.height, view.camera.width) else ids


def appearance(instance_dir: Path, view: View, scribble: np.ndarray, part: str, new_albedo: str) -> tuple[float, ...] | None:
    """The colour a recoloured part *appears* under ``scribble`` in ``view``: the new albedo
    times the mean shading there (source image / old albedo), as a user picking the colour they
    want to see would give it.  None without part maps or the part's albedo.

    The image is un-blended from its white background first, (rgb − (1 − α)) / α, on the
    pixels the part covers at least half of (all of them when none does): a user sees a thin
    dark tube as dark, not as its pixels' mix with the white behind it, whose ratio to the old
    albedo would give the new colour a shading of several times 1 in a channel the old one
    lacks.  A solid part's pixels (α = 1) are the same either way."""
    record, ids = part_of(instance_dir, part), part_map(instance_dir, view)
    if record is None or ids is None or "color" not in record:
        return None
    on = scribble & (ids == record["id"])
    if not on.any():
        return None
    covered = on & (view.alpha >= 0.5)
    if covered.any():
        on = covered
    alpha = np.maximum(view.alpha[on][:, None], 1e-3)
    old = np.maximum(np.array(parse_color(record["color"])), 1e-3)
    shade = (((view.rgb[on] - (1.0 - alpha)) / alpha) / old).mean(axis=0)
    return tuple(float(c) for c in np.clip(np.array(parse_color(new_albedo)) * shade, 0.0, 1.0))


@torch.no_grad()
def selection_iou(model: CategoryModel, sel: Selection, instance_dir: Path, views: Sequence[View], part: str) -> float | None:
    """IoU of the selected surface and the part's pixels over ``views`` (None without part maps),
    counted as :func:`surface_iou` counts it."""
    record = part_of(instance_dir, part)
    if record is None:
        return None
    field = model.field_for(sel.instance)
    return surface_iou(field, sel.instance, instance_dir, views, record["id"], lambda pts, _: sel.at(field.normalize(pts)))


@torch.no_grad()
def surface_iou(field, instance: int, instance_dir: Path, views: Sequence[View], part_id: int,
                predict: Callable[[Tensor, Camera], Tensor]) -> float | None:
    """IoU of ``predict(points, camera)`` ([H·W] bool at each view's rendered surface points
    [H·W, 3]) and the part's pixels, over ``views``; None without part maps or pixels to count.

    Counted over the pixels that show the object both in the part map and in the model's
    render (opacity ≥ 0.5).  A pixel the render shows but the part map calls background (the
    reconstruction's blurred halo around a thin leg) has no part label, so predicting it is
    neither right nor wrong, just as a part pixel the render misses is neither.  (Until the
    twentieth session of issue #14 such halo pixels counted as wrongly selected while the
    missed ones were left out: docs/benchmarks.md has both readings.)"""
    inter = union = 0
    for v in views:
        ids = part_map(instance_dir, v)
        if ids is None:
            return None
        pts, on = surface_points(field, v.camera, instance)
        labelled = on.cpu().numpy() & (ids.reshape(-1) > 0)
        pred = predict(pts, v.camera).cpu().numpy() & labelled
        gt = (ids.reshape(-1) == part_id) & labelled
        inter, union = inter + int((pred & gt).sum()), union + int((pred | gt).sum())
    return inter / union if union else None
