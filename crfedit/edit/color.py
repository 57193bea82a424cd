"""Colour edits: scribbled pixels take the user's colour, the rest of the view keeps its own.

Loss = mean over rays ‖C(r) − C*(r)‖² + λ_reg · Σ_tensors mean((θ − θ₀)²) with C* = the user's
colour on scribbled rays and the starting render elsewhere (keep strokes, or a seeded random
sample of the rest of the view twice the scribble's size).  The hybrid strategy trains F_rad
and the instance's colour code; density is untouched, so bottleneck features and compositing
weights of the chosen rays are computed once and every step runs F_rad alone (cache.py).

Target colour: the data's shading multiplies albedo by a lighting factor, so the user's colour
on a shaded pixel is not the albedo that would render there.  We follow the paper's protocol —
scribbled pixels target the given colour as is — so the edited part renders about that colour
where it was scribbled and brighter or darker elsewhere as the learned shading dictates.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from ..cameras import Camera, require_camera
from ..model import CategoryModel
from ..errors import CrfError
from ..names import EDIT_METHODS
from ..renderer import render_rays
from ..runtime import full_precision
from .cache import edit_passes
from .core import EditOptions, EditResult, InstanceEdit, camera_meta, finish, optimize, select_rays, since
from .losses import mse
from .scribble import as_rgb, check_masks, pick_pixels, require_on_object
from .selection import MIN_OPACITY, Selection, select_for
from .supervised import recolor_selected



@full_precision
def edit_color(
    model: CategoryModel,
    instance: int | str,
    camera: Camera,
    scribble: np.ndarray,  # [H, W] bool
    color: str | tuple[float, float, float],
    keep: np.ndarray | None = None,  # [H, W] bool
    options: EditOptions = EditOptions(),
    method: str = "selection",
    selection: Selection | None = None,
    mirror: str | None = None,
) -> EditResult:
    """Recolour the scribbled part of ``instance`` as seen from ``camera``.

    ``method="selection"`` (default): the part is the 3-D ``selection`` (computed from the
    scribbles when None, with the selection's ``mirror`` mode, :func:`.selection.options_for`) and ``color`` is the colour it should *appear* under the scribble
    (:mod:`.supervised`); ``"paper"``: the paper's loss on this view's rays.
    """
    started = time.perf_counter()
    options = options.validated()
    k = model.instance_index(instance)
    rgb = as_rgb(color)
    scribble, keep = check_masks(scribble, keep, require_camera(camera).width, camera.height)
    if method not in EDIT_METHODS:
        raise CrfError(f"--method {method}: expected one of {', '.join(EDIT_METHODS)}")
    if method == "selection":
        result = _recolor_selection(model, k, camera, scribble, rgb, keep, options, selection, mirror)
        return result if selection is not None else since(result, started)
    generator = torch.Generator().manual_seed(options.seed)
    fg, bg = pick_pixels(scribble, keep, options.rays, generator)
    edit = InstanceEdit(model, k, "color", options.strategy, options.penalty)
    rays = select_rays(camera, torch.cat([fg, bg]), model.device)
    (render,) = edit_passes(edit.field, rays, k, list(edit.params), density_changes=False, cache=options.cache)
    with torch.no_grad():
        out = render.forward()
        require_on_object(int((out.opacity[: fg.numel()] >= MIN_OPACITY).sum()))
        target = out.rgb.clone()
    target[: fg.numel()] = torch.tensor(rgb, dtype=target.dtype, device=target.device)

    def loss_fn():
        return mse(render.forward().rgb, target)

    final = optimize(edit, loss_fn, options, "colour edit")
    hyper = {
        "method": "paper", "rays": options.rays, "color": list(rgb),
        "scribble_rays": fg.numel(), "keep_rays": bg.numel(), "keep": "strokes" if keep is not None else "random",
        "cached_samples": render.n_cached, "stage": render.stage, "camera": camera_meta(camera),
    }
    return finish(edit, "color", options, hyper, final, started)


def _recolor_selection(model, k, camera, scribble, rgb, keep, options, selection, mirror=None) -> EditResult:
    """The selection-supervised recolour: the scribbled pixels' rendered colours fix the ratio."""
    scribbled = scribbled_colours(model.field_for(k), k, camera, scribble)
    if selection is None:
        selection = select_for(model, k, camera, scribble, keep, "color", mirror)
    return recolor_selected(model, k, selection, [camera], scribbled, rgb, options)


@torch.no_grad()
def scribbled_colours(field, k: int, camera: Camera, scribble: np.ndarray) -> torch.Tensor:
    """The object's own colours [n, 3] (CPU) at the scribbled pixels that cover it (opacity ≥
    MIN_OPACITY), in row-major order: each pixel's colour over no background, divided by its
    opacity.  A pixel of a thin leg is partly background, and the mix is not the leg's colour:
    over white a dark tube reads pale, and the colour asked for (how the part should *appear*)
    would be set against that.  Over a solid part the opacity is ~1 and this is the pixel.
    Their rays alone are rendered: a recolour that is handed its selection (the page,
    ``--selection``) renders no whole view."""
    pixels = torch.from_numpy(np.flatnonzero(scribble))
    out = render_rays(field, select_rays(camera, pixels, field.aabb.device), k, background=0.0, early_stop=field.cfg.early_stop)
    on = out.opacity >= MIN_OPACITY
    require_on_object(int(on.sum()))
    return (out.rgb[on] / out.opacity[on, None]).clamp(0.0, 1.0).cpu()
