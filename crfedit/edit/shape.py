"""Shape edits: remove a scribbled part, or add a part copied from another instance.

Both train the fusion and density layers (hybrid strategy: F_fuse, F_dens, and their coarse
twins in the paper preset) on fixed samples of the chosen rays, with the inputs of F_fuse
(F_share + F_inst outputs and the skips) computed once (cache.py).  Kept rays — the keep
strokes *plus* a seeded random sample of the rest of the view twice the edited rays' count —
keep their colour, their opacity and (λ_surface · :func:`~.losses.log_density_drift`) the
density of the surfaces they see.  The random sample is added even with keep strokes: strokes
drawn mostly on the background leave the rest of the object unconstrained, and removals then
thinned the whole chair (docs/editing.md has the measurements).

* **remove**: scribbled rays target the background — white, opacity 0 — and the density they
  see is lowered directly (λ_surface · :func:`~.losses.visible_log_density`; a colour/opacity
  target alone cannot move a saturated surface, and the edit either whitened the part or got
  stuck).  Their normalized densities pᵢ = σᵢ/Σσ are also pushed to one peak or none by
  λ_dens · entropy, as in the paper.  ``occluded`` is the paper's variant for a part in front
  of others: only the first density mode along each scribbled ray is removed — the ray targets
  the colour and opacity it renders with that mode zeroed, only the mode's density is lowered,
  and the surface behind is held like a kept ray's.
* **add**: the donor instance is rendered with this instance's colour code, the copy mask's
  opaque pixels are pasted at an offset into this instance's render, and the edit fits that
  image, colour and opacity (``composite``), or, on the pasted rays, the donor's normalized
  density distribution by cross-entropy plus its opacity (``density``).  The pasted part keeps
  its distance from the camera: a pasted ray gets the donor density found at the same distance
  along the donor ray.  ``selection`` instead lifts the copy mask to a 3-D selection of the
  donor's part, moves it by the offset at the part's depth, and copies its density and
  bottleneck features there at points in 3-D (:func:`~.supervised.add_selected`).

The occupancy grid follows the density.  Before adding, the cells that the donor's occupied
samples map to along the pasted rays are opened (dilated by one cell).  After either edit, the
candidate cells are re-thresholded with the edited density (a few random probes per cell,
threshold as in training) and dilated by one cell within the candidates, so cells are freed
only where no density is left nearby; an addition frees none of the instance's own cells
(a few probes miss a thin surface inside a cell).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .. import occupancy
from ..cameras import Camera, Rays, require_camera
from ..errors import CrfError
from ..masks import as_mask
from ..field import ConditionalRadianceField
from ..names import ADD_METHODS, COLOR_CODES, EDIT_METHODS, is_digits
from ..model import CategoryModel
from ..renderer import render_camera
from ..rendering import composite_dense
from ..runtime import full_precision
from ..sampling import grid_samples
from .cache import EditPass, edit_passes
from .core import EditOptions, EditResult, InstanceEdit, camera_meta, finish, occupancy_after, optimize, select_rays, since
from .losses import density_cross_entropy, density_entropy, log_density_drift, mse, visible_log_density
from .params import used_code_tables
from .scribble import check_masks, pick_pixels, require_on_object
from .selection import MIN_OPACITY, Selection, select_for
from .supervised import add_selected, remove_selected
from .transfer import swap_codes

MODE_ALPHA = 0.01
"""A sample belongs to a density mode while its opacity 1 − exp(−σδ) exceeds this."""


class RemovalTarget(NamedTuple):
    """What one pass of a removal aims at, per ray of the edit (scribbled rays first)."""

    rgb: Tensor  # [N, 3]
    opacity: Tensor  # [N]
    seen: Tensor  # [N, S] weights of the surfaces to keep at their density (w⁰; the surface behind for --occluded)
    sigmas: Tensor  # [N, S] starting densities
    push: Tensor  # [n_fg, S] bool: samples of the scribbled rays whose density is to go


def first_mode(t_starts: Tensor, t_ends: Tensor, sigmas: Tensor) -> Tensor:
    """The first density mode along each ray: the first run of consecutive samples (contiguous in
    t) whose opacity exceeds :data:`MODE_ALPHA`.  [N, S] → [N, S] bool

    Example: opacities [0, 0.5, 0.9, 0, 0.7] at contiguous samples → [F, T, T, F, F].
    """
    delta = (t_ends - t_starts).clamp_min(0.0)
    active = -torch.expm1(-sigmas * delta) > MODE_ALPHA
    gap = torch.zeros_like(active)
    gap[:, 1:] = t_starts[:, 1:] - t_ends[:, :-1] > 0.5 * delta[:, :-1]
    idx = torch.arange(active.shape[-1], device=active.device)
    first = active.float().argmax(dim=-1, keepdim=True)
    breaks = (~active | gap) & (idx > first)
    end = torch.where(breaks.any(dim=-1, keepdim=True), breaks.float().argmax(dim=-1, keepdim=True), active.shape[-1])
    return (idx >= first) & (idx < end) & active.any(dim=-1, keepdim=True)


def check_occluded(occluded: bool, method: str) -> None:
    """``occluded`` belongs to the paper's losses: a selection already says which surfaces go."""
    if occluded and method != "paper":
        raise CrfError("--occluded belongs to --method paper (a selection already says which surfaces go)")


@full_precision
def remove(
    model: CategoryModel,
    instance: int | str,
    camera: Camera,
    scribble: np.ndarray,  # [H, W] bool
    keep: np.ndarray | None = None,  # [H, W] bool
    occluded: bool = False,
    options: EditOptions = EditOptions(),
    method: str = "selection",
    selection: Selection | None = None,
    mirror: str | None = None,
) -> EditResult:
    """Remove the scribbled part of ``instance`` as seen from ``camera``: the 3-D ``selection``
    (computed from the scribbles when None, with the selection's ``mirror`` mode,
    :func:`.selection.options_for`) with ``method="selection"``, or the paper's losses."""
    started = time.perf_counter()
    options = options.validated()
    k = model.instance_index(instance)
    if method not in EDIT_METHODS:
        raise CrfError(f"--method {method}: expected one of {', '.join(EDIT_METHODS)}")
    if scribble is None and (method != "selection" or selection is None):
        raise CrfError("a removal needs its scribble, or a selection to remove (with --method selection)")
    require_camera(camera)
    if scribble is not None:
        scribble, keep = check_masks(scribble, keep, camera.width, camera.height)
    if method == "selection":
        check_occluded(occluded, method)
        if selection is not None:  # the selection says what goes: the scribble, if any, only named it
            return remove_selected(model, k, selection, [camera], options)
        return since(remove_selected(model, k, select_for(model, k, camera, scribble, keep, "remove", mirror), [camera], options), started)
    generator = torch.Generator().manual_seed(options.seed)
    fg, bg = pick_pixels(scribble, keep, options.rays, generator, also_random=True)
    n_fg = fg.numel()
    edit = InstanceEdit(model, k, "shape", options.strategy, options.penalty)
    candidates = edit.field.occupancy[k].clone()
    rays = select_rays(camera, torch.cat([fg, bg]), model.device)
    passes = edit_passes(edit.field, rays, k, list(edit.params), density_changes=True, cache=options.cache)
    targets = []
    with torch.no_grad():
        for p in passes:
            out = p.forward()
            if p is passes[-1]:  # the network that renders: the coarse one only places samples
                require_on_object(int((out.opacity[:n_fg] >= MIN_OPACITY).sum()))
            rgb, alpha, seen = out.rgb.clone(), out.opacity.clone(), out.weights.clone()
            push = out.sigmas[:n_fg] > 0
            if occluded:
                push = first_mode(p.t_starts[:n_fg], p.t_ends[:n_fg], out.sigmas[:n_fg])
                behind = composite_dense(
                    p.t_starts[:n_fg], p.t_ends[:n_fg], out.sigmas[:n_fg] * ~push, out.rgbs[:n_fg], p.background
                )
                rgb[:n_fg], alpha[:n_fg], seen[:n_fg] = behind.rgb, behind.opacity, behind.weights
            else:
                rgb[:n_fg], alpha[:n_fg], seen[:n_fg] = p.background, 0.0, 0.0
            targets.append(RemovalTarget(rgb, alpha, seen, out.sigmas, push))

    def loss_fn():
        total = 0.0
        for p, target in zip(passes, targets):
            out = p.forward()
            total = total + mse(out.rgb, target.rgb) + mse(out.opacity, target.opacity)
            total = total + options.lambda_dens * density_entropy(out.sigmas[:n_fg]).mean()
            lowered = visible_log_density(out.weights[:n_fg] * target.push, out.sigmas[:n_fg])
            kept = log_density_drift(target.seen, out.sigmas, target.sigmas)
            total = total + options.lambda_surface * (lowered.mean() + kept.mean())
        return total

    final = optimize(edit, loss_fn, options, "removal")
    extra, extra_modules = occupancy_after(edit, candidates, generator)
    hyper = {
        "method": "paper", "rays": options.rays, "lambda_dens": options.lambda_dens,
        "lambda_surface": options.lambda_surface, "occluded": occluded, "scribble_rays": n_fg, "keep_rays": bg.numel(),
        "keep": "strokes+random" if keep is not None else "random", "stage": passes[-1].stage,
        "cached_samples": sum(p.n_cached for p in passes), "camera": camera_meta(camera),
    }
    return finish(edit, "remove", options, hyper, final, started, extra, extra_modules)


def same_camera(a: Camera, b: Camera, tolerance: float = 1e-4) -> bool:
    """Whether two cameras see one image: the same size, focal and pose (to ``tolerance``)."""
    return ((a.width, a.height) == (b.width, b.height) and abs(a.focal - b.focal) <= tolerance * max(a.focal, 1.0)
            and np.allclose(np.asarray(a.c2w, np.float64), np.asarray(b.c2w, np.float64), atol=tolerance))


def view_angle(a: Camera, b: Camera) -> float:
    """Degrees between two cameras' viewing directions (their −z axes)."""
    da, db = -np.asarray(a.c2w, np.float64)[:3, 2], -np.asarray(b.c2w, np.float64)[:3, 2]
    cos = float(da @ db / max(np.linalg.norm(da) * np.linalg.norm(db), 1e-12))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def parse_offset(text: str) -> tuple[int, int]:
    """``"12,-3"`` → (12, -3): pixels right and down."""
    parts = str(text).replace(" ", "").split(",")
    if len(parts) != 2 or not all(is_digits(p.lstrip("+-")) for p in parts):
        raise CrfError(f"--offset {text}: expected DX,DY in whole pixels, e.g. 10,-4")
    return int(parts[0]), int(parts[1])


@torch.no_grad()
def open_donor_cells(
    donor: ConditionalRadianceField, donor_instance: int, donor_rays: Rays, target_rays: Rays, grid: Tensor
) -> Tensor:
    """``grid`` [R, R, R] plus the cells that the donor's occupied samples along ``donor_rays``
    map to along the paired ``target_rays`` (same distance t), dilated by one cell."""
    res = grid.shape[-1]
    inst = torch.full((donor_rays.origins.shape[0],), donor_instance, dtype=torch.long, device=grid.device)
    s = grid_samples(donor, donor_rays, inst)
    t = ((s.points - donor_rays.origins[s.ray]) * donor_rays.directions[s.ray]).sum(dim=-1)
    pts = target_rays.origins[s.ray] + t[:, None] * target_rays.directions[s.ray]
    ijk, inside = occupancy.cell_index(donor.normalize(pts), res)
    ijk = ijk[inside]
    added = torch.zeros_like(grid)
    added[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return grid | occupancy.dilate(added, 1)


@torch.no_grad()
def donor_densities(
    donor: ConditionalRadianceField, donor_instance: int, donor_rays: Rays, target: EditPass, target_rays: Rays, n: int
) -> Tensor:
    """The donor's density [n, S] at the distances of the first ``n`` rays' samples of the
    ``target`` pass, along the paired donor rays (σ = 0 outside the donor's occupied cells, as
    the renderer sees it)."""
    s = target.samples
    sel = s.ray < n
    ray, step = s.ray[sel], s.step[sel]
    t = ((s.points[sel] - target_rays.origins[ray]) * target_rays.directions[ray]).sum(dim=-1)
    pts = donor_rays.origins[ray] + t[:, None] * donor_rays.directions[ray]
    xn = donor.normalize(pts)
    sigma = donor.density(xn, donor_instance, donor if target.net is target.field else donor.coarse)
    if donor.cfg.sampler == "grid":
        inst = torch.full_like(ray, donor_instance)
        sigma = torch.where(occupancy.lookup(donor.occupancy, inst, xn), sigma, torch.zeros_like(sigma))
    out = torch.zeros(n, s.n_steps, device=sigma.device, dtype=sigma.dtype)
    return out.index_put((ray, step), sigma)


@full_precision
def add(
    model: CategoryModel,
    instance: int | str,
    camera: Camera,
    donor: int | str,
    copy_mask: np.ndarray,  # [H, W] bool, in the donor view
    offset: tuple[int, int],
    donor_camera: Camera | None = None,
    method: str = "selection",
    keep: np.ndarray | None = None,
    options: EditOptions = EditOptions(),
    selection: Selection | None = None,
    on_selection: Callable[[Selection], None] | None = None,
) -> EditResult:
    """Add the donor's part under ``copy_mask`` (donor view) to ``instance``, pasted ``offset``
    = (dx, dy) pixels away in ``camera``'s view.

    ``on_selection`` is told the donor selection the edit makes (with ``method`` selection and
    no ``selection``), once the inputs have been checked: the CLI prints it as ``select`` would.

    ``method``: ``composite`` (the paper's: fit the pasted image along the pasted rays),
    ``density`` (match the donor's density along them) or ``selection`` (lift the copy mask to
    a 3-D selection of the donor, or take ``selection``, and copy that part's density and
    features at points in 3-D: :func:`~crfedit.edit.supervised.add_selected`)."""
    started = time.perf_counter()
    options = options.validated()
    if method not in ADD_METHODS:
        raise CrfError(f"--method {method}: expected one of {', '.join(ADD_METHODS)}")
    k, j = model.instance_index(instance), model.instance_index(donor)
    if k == j and tuple(offset) == (0, 0):
        raise CrfError(f"add: {model.names[k]} is its own donor at offset 0,0: the part is already there (give another --donor, or an --offset)")
    donor_camera = require_camera(donor_camera or camera, "donor camera")
    w, h = require_camera(camera).width, camera.height
    if (donor_camera.width, donor_camera.height) != (w, h):
        raise CrfError(f"--donor-view is {donor_camera.width}x{donor_camera.height} but --view is {w}x{h}; use views of one size")
    if method != "selection" and not same_camera(camera, donor_camera):
        raise CrfError(f"--method {method} pastes the donor view's pixels into --view, so both need one camera, but they look "
                       f"{view_angle(camera, donor_camera):.0f}° apart: use --method selection (the default), or a view both "
                       "instances share (orbit:N, a camera JSON)")
    if method == "selection" and keep is not None and np.asarray(keep).any():
        raise CrfError("--keep belongs to --method composite and density: the default method copies the donor's part "
                       "in 3-D and holds the rest of the chair in every view")
    copy_mask = as_mask(copy_mask, "copy")
    if tuple(copy_mask.shape) != (h, w):
        raise CrfError(f"copy mask is {copy_mask.shape[1]}x{copy_mask.shape[0]} but the donor view is {w}x{h}")
    if not copy_mask.any():
        raise CrfError("the copy mask is empty: no pixel is set")
    recolored = k != j and COLOR_CODES in used_code_tables(model.field)
    donor_field = (swap_codes(model, j, color_from=k) if recolored else model).field_for(j)
    donor_out = render_camera(donor_field, donor_camera, j)
    target_out = render_camera(model.field_for(k), camera, k)
    ys, xs = np.nonzero(copy_mask & (donor_out.opacity.cpu().numpy() > 0.5))
    dx, dy = offset
    inside = (ys + dy >= 0) & (ys + dy < h) & (xs + dx >= 0) & (xs + dx < w)
    if len(ys) == 0:
        raise CrfError("nothing to copy: the copy mask covers none of the donor's opaque pixels in the donor view")
    if not inside.any():
        raise CrfError(f"--offset {dx},{dy} moves the whole copied region out of the {w}x{h} view")
    ys, xs = ys[inside], xs[inside]
    if method == "selection":
        if selection is not None:
            return add_selected(model, k, j, selection, camera, offset, options)
        selection = select_for(model, j, donor_camera, copy_mask, None, "add")
        if on_selection is not None:
            on_selection(selection)
        return since(add_selected(model, k, j, selection, camera, offset, options), started)
    src_of = np.full(h * w, -1, dtype=np.int64)
    src_of[(ys + dy) * w + (xs + dx)] = ys * w + xs
    pasted = src_of.reshape(h, w) >= 0
    pasted, keep = check_masks(pasted, keep, w, h)
    generator = torch.Generator().manual_seed(options.seed)
    fg, bg = pick_pixels(pasted, keep, options.rays, generator, also_random=True)
    n_fg = fg.numel()
    src = torch.from_numpy(src_of[fg.numpy()])
    device = model.device
    pixels = torch.cat([fg, bg]).to(device)
    target_rgb = target_out.rgb.reshape(-1, 3)[pixels].clone()
    target_alpha = target_out.opacity.reshape(-1)[pixels].clone()
    target_rgb[:n_fg] = donor_out.rgb.reshape(-1, 3)[src.to(device)]
    target_alpha[:n_fg] = donor_out.opacity.reshape(-1)[src.to(device)]

    edit = InstanceEdit(model, k, "shape", options.strategy, options.penalty)
    original = edit.field.occupancy[k].clone()
    if edit.field.cfg.sampler == "grid":
        all_dst = torch.from_numpy(np.flatnonzero(pasted))
        donor_all = select_rays(donor_camera, torch.from_numpy(src_of[all_dst.numpy()]), device)
        edit.field.occupancy[k] = open_donor_cells(donor_field, j, donor_all, select_rays(camera, all_dst, device), original)
    candidates = edit.field.occupancy[k].clone()
    rays = select_rays(camera, pixels, device)
    passes = edit_passes(edit.field, rays, k, list(edit.params), density_changes=True, cache=options.cache)
    seen, sigmas0, donor_sigmas = [], [], []
    with torch.no_grad():
        for p in passes:
            out = p.forward()
            # what the kept rays saw before the cells were opened (the surfaces to hold)
            inside = occupancy.lookup(original[None], torch.zeros_like(p.samples.ray), p.xn) if edit.field.cfg.sampler == "grid" else None
            before = out.sigmas if inside is None else out.sigmas * p.dense(inside.to(out.sigmas.dtype))
            w0 = composite_dense(p.t_starts, p.t_ends, before, out.rgbs, p.background).weights
            w0[:n_fg] = 0.0
            seen.append(w0)
            sigmas0.append(out.sigmas)
            if method == "density":
                donor_sigmas.append(donor_densities(donor_field, j, select_rays(donor_camera, src, device), p, rays, n_fg))

    def loss_fn():
        total = 0.0
        for i, p in enumerate(passes):
            out = p.forward()
            if method == "composite":
                total = total + mse(out.rgb, target_rgb) + mse(out.opacity, target_alpha)
            else:
                total = total + options.lambda_match * density_cross_entropy(donor_sigmas[i], out.sigmas[:n_fg]).mean()
                total = total + mse(out.opacity[:n_fg], target_alpha[:n_fg])
                total = total + mse(out.rgb[n_fg:], target_rgb[n_fg:]) + mse(out.opacity[n_fg:], target_alpha[n_fg:])
            total = total + options.lambda_surface * log_density_drift(seen[i], out.sigmas, sigmas0[i]).mean()
        return total

    final = optimize(edit, loss_fn, options, "add edit")
    extra, extra_modules = occupancy_after(edit, candidates, generator, kept=original)
    hyper = {
        "rays": options.rays, "lambda_surface": options.lambda_surface,
        "lambda_match": options.lambda_match, "method": method, "donor": model.names[j],
        "offset": [dx, dy], "pasted_rays": n_fg, "keep_rays": bg.numel(), "stage": passes[-1].stage,
        "cached_samples": sum(p.n_cached for p in passes), "camera": camera_meta(camera),
        "donor_camera": camera_meta(donor_camera),
    }
    return finish(edit, "add", options, hyper, final, started, extra, extra_modules)
