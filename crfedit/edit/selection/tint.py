"""Preview: the instance rendered with the selected surface tinted."""

from __future__ import annotations

import numpy as np
import torch

from ...cameras import Camera
from ...model import CategoryModel
from ...renderer import RenderOutput, render_camera
from .base import Selection
from .features import surface_points

TINT = (1.0, 0.15, 0.1)
"""Colour blended over the selected surface in a preview."""


@torch.no_grad()
def preview(model: CategoryModel, sel: Selection, camera: Camera, strength: float = 0.6,
            out: RenderOutput | None = None, field=None) -> np.ndarray:
    """The instance's render from ``camera`` [H, W, 3] with the selected surface tinted, so the
    user sees what an edit will change before any weight moves.  ``out``: that render, when the
    caller has it (the page keeps its views'); ``field``: the instance's field, likewise (the
    page, which checked the selection when it made it; without it the selection must be of
    ``model``, :meth:`Selection.check_for`)."""
    if field is None:
        sel.check_for(model, sel.instance)
        field = model.field_for(sel.instance)
    out = render_camera(field, camera, sel.instance) if out is None else out
    pts, on = surface_points(field, camera, sel.instance, out=out)
    hit = (sel.at(field.normalize(pts)) & on).reshape(camera.height, camera.width, 1)
    tint = torch.tensor(TINT, device=out.rgb.device)
    rgb = torch.where(hit, (1 - strength) * out.rgb + strength * tint, out.rgb)
    return rgb.clamp(0, 1).cpu().numpy()
