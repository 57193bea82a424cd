"""Shape edits: remove a scribbled part, or add a part copied from another instance.

Both train the fusion and density layers (hybrid strategy: F_fuse, F_dens, and their coarse
twins in the paper preset) on fixed samples of the chosen rays, with the inputs of F_fuse
(F_share + F_inst outputs and the skips) computed once (cache.py).  Rays that keep their look
target the starting render (keep strokes, else a seeded random sample twice the edited rays).

* **remove**: scribbled rays target the background — white, with opacity 0 — and their
  normalized densities pᵢ = σᵢ/Σσ are pushed to one peak or none by λ_dens · entropy
  (losses.py); kept rays keep their colour and opacity.  (The opacity term matters: with the
  colour target alone the edit can, and on our chairs did, whiten the part instead of removing it.)
  ``occluded`` is the paper's variant for a part in front of others: only the first density
  mode along each scribbled ray is removed — the ray targets the colour and opacity it renders
  with that mode's density zeroed, and the light that mode absorbs (Σ of its weights) is
  pushed to 0.
* **add**: the donor instance is rendered with this instance's colour code, the copy mask's
  opaque pixels are pasted at an offset into this instance's render, and the edit fits that
  image (``composite``) or, on the pasted rays, the donor's normalized density distribution by
  cross-entropy plus its opacity (``density``).  The pasted part keeps its distance from the
  camera: a pasted ray gets the donor density found at the same distance along the donor ray.

The occupancy grid follows the density.  Before adding, the cells that the donor's occupied
samples map to along the pasted rays are opened (dilated by one cell).  After either edit, the
candidate cells are re-thresholded with the edited density (a few random probes per cell,
threshold as in training) and dilated by one cell within the candidates, so cells are freed
only where no density is left nearby.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from .. import occupancy
from ..cameras import Camera, Rays
from ..errors import CrfError
from ..field import ConditionalRadianceField, density_activation
from ..model import CategoryModel
from ..renderer import grid_samples, render_camera
from ..rendering import composite_from_density
from .cache import EditPass, edit_passes
from .core import EditOptions, EditResult, InstanceEdit, camera_meta, finish, optimize, select_rays
from .losses import density_cross_entropy, density_entropy, mse
from .params import used_code_tables
from .scribble import check_masks, pick_pixels
from .transfer import swap_codes

ADD_METHODS = ("composite", "density")
MODE_ALPHA = 0.01
"""A sample belongs to a density mode while its opacity 1 − exp(−σδ) exceeds this."""
OCC_PROBES = 4


@torch.no_grad()
def rethreshold(field: ConditionalRadianceField, instance: int, candidates: Tensor, generator: torch.Generator) -> Tensor:
    """The instance's occupancy grid [R, R, R] after a shape edit: candidate cells whose edited
    density passes the training threshold at any of :data:`OCC_PROBES` random probes, dilated by
    one cell and kept within ``candidates``."""
    cfg = field.cfg
    res = candidates.shape[-1]
    shape_code, _ = field.codes(instance)

    def density(xn: Tensor) -> Tensor:
        return density_activation(field.density_and_features(xn, shape_code)[0])

    ema = torch.zeros(res**3, device=candidates.device)
    step = occupancy.step_size(field.aabb, res, cfg.steps_per_cell)
    grid = candidates.reshape(-1)
    for _ in range(OCC_PROBES):
        grid = occupancy.update_from_density(ema, candidates.reshape(-1), density, step, cfg.occ_threshold, 1.0, generator)
    return occupancy.dilate(grid.view(res, res, res), 1) & candidates


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


def _occupancy_after(edit: InstanceEdit, candidates: Tensor, generator: torch.Generator) -> tuple[dict, tuple[str, ...]]:
    """(extra overrides, extra modules) that store the re-thresholded grid (grid sampler only)."""
    field = edit.field
    if field.cfg.sampler != "grid":
        return {}, ()
    table = field.occupancy.detach().clone()
    table[edit.instance] = rethreshold(field, edit.instance, candidates, generator)
    return {"occupancy": table}, ("occupancy",)


def remove(
    model: CategoryModel,
    instance: int | str,
    camera: Camera,
    scribble: np.ndarray,  # [H, W] bool
    keep: np.ndarray | None = None,  # [H, W] bool
    occluded: bool = False,
    options: EditOptions = EditOptions(),
) -> EditResult:
    """Remove the scribbled part of ``instance`` as seen from ``camera``."""
    started = time.perf_counter()
    options = options.validated()
    k = model.instance_index(instance)
    keep = check_masks(scribble, keep, camera.width, camera.height)
    generator = torch.Generator().manual_seed(options.seed)
    import os
    fg, bg = pick_pixels(scribble, keep, options.rays, generator, also_random=bool(int(os.environ.get("EXP_RK", "0"))))
    n_fg = fg.numel()
    edit = InstanceEdit(model, k, "shape", options.strategy)
    candidates = edit.field.occupancy[k].clone()
    rays = select_rays(camera, torch.cat([fg, bg]), model.device)
    passes = edit_passes(edit.field, rays, k, list(edit.params), density_changes=True)
    targets, modes, taus0, w0, logs0 = [], [], [], [], []
    with torch.no_grad():
        for p in passes:
            out = p.forward()
            rgb, alpha = out.rgb.clone(), out.opacity.clone()
            if occluded:
                mode = first_mode(p.t_starts[:n_fg], p.t_ends[:n_fg], out.sigmas[:n_fg])
                behind = composite_from_density(
                    p.t_starts[:n_fg], p.t_ends[:n_fg], out.sigmas[:n_fg] * ~mode, out.rgbs[:n_fg], p.background
                )
                rgb[:n_fg], alpha[:n_fg] = behind.rgb, behind.opacity
                modes.append(mode)
            else:
                rgb[:n_fg], alpha[:n_fg] = p.background, 0.0
            targets.append((rgb, alpha))
            taus0.append(torch.log1p((out.sigmas * (p.t_ends - p.t_starts)).sum(-1)))
            w0.append(out.weights); logs0.append(torch.log1p(out.sigmas) if os.environ.get("EXP_L1P") else torch.log(out.sigmas.clamp_min(1e-20)))

    def loss_fn():
        total = options.lambda_reg * edit.penalty()
        for i, p in enumerate(passes):
            out = p.forward()
            rgb, alpha = targets[i]
            total = total + mse(out.rgb, rgb) + mse(out.opacity, alpha)
            if float(os.environ.get("EXP_VIS", "0")) > 0:
                lv = float(os.environ.get("EXP_VIS"))
                logs = torch.log1p(out.sigmas) if os.environ.get("EXP_L1P") else torch.log(out.sigmas.clamp_min(1e-20))
                total = total + lv * (out.weights[:n_fg].detach() * logs[:n_fg]).sum(-1).mean()
                total = total + lv * (w0[i][n_fg:] * (logs[n_fg:] - logs0[i][n_fg:]) ** 2).sum(-1).mean()
            if float(os.environ.get("EXP_TAU", "0")) > 0 and not occluded:
                tau = torch.log1p((out.sigmas * (p.t_ends - p.t_starts)).sum(-1))
                lt = float(os.environ.get("EXP_TAU"))
                total = total + lt * tau[:n_fg].mean()
                if int(os.environ.get("EXP_KT", "0")):
                    total = total + lt * ((tau[n_fg:] - taus0[i][n_fg:]) ** 2).mean()
            total = total + options.lambda_dens * density_entropy(out.sigmas[:n_fg]).mean()
            if occluded:
                total = total + torch.mean((out.weights[:n_fg] * modes[i]).sum(dim=-1) ** 2)
        return total

    final = optimize(list(edit.params.values()), loss_fn, options.steps, options.lr, "removal")
    extra, extra_modules = _occupancy_after(edit, candidates, generator)
    hyper = {
        "strategy": options.strategy, "steps": options.steps, "lr": options.lr, "rays": options.rays,
        "seed": options.seed, "lambda_reg": options.lambda_reg, "lambda_dens": options.lambda_dens,
        "occluded": occluded, "scribble_rays": n_fg, "keep_rays": bg.numel(),
        "keep": "strokes" if keep is not None else "random", "stage": passes[-1].stage,
        "cached_samples": sum(p.n_cached for p in passes), "camera": camera_meta(camera),
    }
    return finish(edit, "remove", hyper, final, started, extra, extra_modules)


def parse_offset(text: str) -> tuple[int, int]:
    """``"12,-3"`` → (12, -3): pixels right and down."""
    parts = str(text).replace(" ", "").split(",")
    if len(parts) != 2 or not all(p.lstrip("+-").isdigit() for p in parts):
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
    shape_code, _ = donor.codes(donor_instance)
    net = donor if target.net is target.field else donor.coarse
    sigma = density_activation(net.density_and_features(xn, shape_code)[0])
    if donor.cfg.sampler == "grid":
        inst = torch.full_like(ray, donor_instance)
        sigma = torch.where(occupancy.lookup(donor.occupancy, inst, xn), sigma, torch.zeros_like(sigma))
    out = torch.zeros(n, s.n_steps, device=sigma.device, dtype=sigma.dtype)
    return out.index_put((ray, step), sigma)


def add(
    model: CategoryModel,
    instance: int | str,
    camera: Camera,
    donor: int | str,
    copy_mask: np.ndarray,  # [H, W] bool, in the donor view
    offset: tuple[int, int],
    donor_camera: Camera | None = None,
    method: str = "composite",
    keep: np.ndarray | None = None,
    options: EditOptions = EditOptions(),
) -> EditResult:
    """Add the donor's part under ``copy_mask`` (donor view) to ``instance``, pasted ``offset``
    = (dx, dy) pixels away in ``camera``'s view."""
    started = time.perf_counter()
    options = options.validated()
    if method not in ADD_METHODS:
        raise CrfError(f"--method {method}: expected one of {', '.join(ADD_METHODS)}")
    k, j = model.instance_index(instance), model.instance_index(donor)
    donor_camera = donor_camera or camera
    w, h = camera.width, camera.height
    if (donor_camera.width, donor_camera.height) != (w, h):
        raise CrfError(f"--donor-view is {donor_camera.width}x{donor_camera.height} but --view is {w}x{h}; use views of one size")
    if tuple(copy_mask.shape) != (h, w):
        raise CrfError(f"copy mask is {copy_mask.shape[1]}x{copy_mask.shape[0]} but the donor view is {w}x{h}")
    if not copy_mask.any():
        raise CrfError("the copy mask is empty: no pixel is set")
    recolored = k != j and "color_codes" in used_code_tables(model.field)
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
    src_of = np.full(h * w, -1, dtype=np.int64)
    src_of[(ys + dy) * w + (xs + dx)] = ys * w + xs
    pasted = src_of.reshape(h, w) >= 0
    keep = check_masks(pasted, keep, w, h)
    generator = torch.Generator().manual_seed(options.seed)
    fg, bg = pick_pixels(pasted, keep, options.rays, generator)
    n_fg = fg.numel()
    src = torch.from_numpy(src_of[fg.numpy()])
    device = model.device
    target_img = target_out.rgb.reshape(-1, 3).clone()
    target_img[fg.to(device)] = donor_out.rgb.reshape(-1, 3)[src.to(device)]

    edit = InstanceEdit(model, k, "shape", options.strategy)
    all_dst = torch.from_numpy(np.flatnonzero(pasted))
    if edit.field.cfg.sampler == "grid":
        donor_all = select_rays(donor_camera, torch.from_numpy(src_of[all_dst.numpy()]), device)
        grid = open_donor_cells(donor_field, j, donor_all, select_rays(camera, all_dst, device), edit.field.occupancy[k])
        edit.field.occupancy[k] = grid
    candidates = edit.field.occupancy[k].clone()
    rays = select_rays(camera, torch.cat([fg, bg]), device)
    donor_rays = select_rays(donor_camera, src, device)
    passes = edit_passes(edit.field, rays, k, list(edit.params), density_changes=True)
    target = target_img[torch.cat([fg, bg]).to(device)]
    if method == "density":
        donor_sigmas = [donor_densities(donor_field, j, donor_rays, p, rays, n_fg) for p in passes]
        donor_opacity = donor_out.opacity.reshape(-1)[src.to(device)]

    def loss_fn():
        total = options.lambda_reg * edit.penalty()
        for i, p in enumerate(passes):
            out = p.forward()
            if method == "composite":
                total = total + mse(out.rgb, target)
            else:
                total = total + density_cross_entropy(donor_sigmas[i], out.sigmas[:n_fg]).mean()
                total = total + torch.mean((out.opacity[:n_fg] - donor_opacity) ** 2) + mse(out.rgb[n_fg:], target[n_fg:])
        return total

    final = optimize(list(edit.params.values()), loss_fn, options.steps, options.lr, "add edit")
    extra, extra_modules = _occupancy_after(edit, candidates, generator)
    hyper = {
        "strategy": options.strategy, "steps": options.steps, "lr": options.lr, "rays": options.rays,
        "seed": options.seed, "lambda_reg": options.lambda_reg, "method": method, "donor": model.names[j],
        "offset": [dx, dy], "pasted_rays": n_fg, "keep_rays": bg.numel(), "stage": passes[-1].stage,
        "cached_samples": sum(p.n_cached for p in passes), "camera": camera_meta(camera),
        "donor_camera": camera_meta(donor_camera),
    }
    return finish(edit, "add", hyper, final, started, extra, extra_modules)
