"""Rendering views of a trained model and scoring them against a dataset's images."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from .cameras import Camera
from .data.format import Category
from .errors import CrfError
from .metrics import score_images
from .model import CategoryModel
from .renderer import RenderOutput, render_camera

DEFAULT_CHUNK = 16384


def render_views(
    model: CategoryModel, instance: int, cameras: Sequence[Camera], chunk: int = DEFAULT_CHUNK
) -> list[RenderOutput]:
    """Render ``cameras`` of ``instance`` (on white), with the instance's baked overrides if any.

    Deterministic: the same model and cameras give bit-identical images.
    """
    field = model.field_for(instance)
    return [render_camera(field, cam, instance, chunk=chunk) for cam in cameras]


def score_model(
    model: CategoryModel,
    category: Category,
    split: str = "test",
    max_views: int | None = None,
    instances: Sequence[int] | None = None,
    chunk: int = DEFAULT_CHUNK,
) -> dict:
    """PSNR / SSIM (and LPIPS when weights are configured) of the model's renders of ``split``.

    ``instances`` are model indices (default: all); each is matched to the dataset's instance of
    the same name, and its first ``max_views`` views of ``split`` (default: all) are rendered with
    the dataset's cameras and scored against its images.  Returns::

        {"split": "test", "n": total views, "psnr": mean dB, "ssim": mean, "lpips": mean or None,
         "lpips_note": why LPIPS was skipped or None,
         "instances": {name: {"n", "psnr", "ssim", "lpips"}}}

    Means are over all scored views (each view counts once, whatever its instance).
    """
    if max_views is not None and max_views < 1:
        raise CrfError(f"max_views {max_views}: must be at least 1")
    indices = list(range(len(model.names))) if instances is None else list(instances)
    if not indices:
        raise CrfError("no instances to score")
    per_instance, note = {}, None
    for k in indices:
        name = model.names[k]
        if name not in category.names:
            raise CrfError(f"instance {name!r} of the model is not in the dataset {category.root}")
        views = category.instance(name).splits.get(split, [])[:max_views]
        if not views:
            continue
        outs = render_views(model, k, [v.camera for v in views], chunk)
        preds = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in outs]
        scores = score_images(preds, [v.rgb for v in views])
        note = scores["lpips_note"]
        per_instance[name] = {key: scores[key] for key in ("n", "psnr", "ssim", "lpips")}
    if not per_instance:
        raise CrfError(f"{category.root}: no {split} views for the instances scored")
    n = np.array([s["n"] for s in per_instance.values()], dtype=np.float64)

    def mean(key: str) -> float | None:
        values = [s[key] for s in per_instance.values()]
        return None if any(v is None for v in values) else float(np.sum(n * np.array(values)) / n.sum())

    return {
        "split": split,
        "n": int(n.sum()),
        "psnr": mean("psnr"),
        "ssim": mean("ssim"),
        "lpips": mean("lpips"),
        "lpips_note": note,
        "instances": per_instance,
    }
