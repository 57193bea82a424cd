"""Per-instance occupancy grids: which cells of the scene box are worth sampling.

A grid is a bool tensor [R, R, R] over the normalized box [-1, 1]³, indexed [ix, iy, iz].
It starts as the instance's visual hull (cells whose center projects inside the object's
silhouette in every training view that sees it) and is then refined from the learned density
during training (:func:`update_from_density`).  Rays march only through occupied cells, so
no network evaluations are spent on empty space.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .cameras import Camera


def cell_index(xn: Tensor, res: int) -> tuple[Tensor, Tensor]:
    """Normalized points [..., 3] → (integer cell coordinates [..., 3], inside-the-box mask [...])."""
    inside = (xn.abs() <= 1.0).all(dim=-1)
    ijk = ((xn + 1.0) * (0.5 * res)).floor().long().clamp(0, res - 1)
    return ijk, inside


def lookup(grids: Tensor, instance: Tensor, xn: Tensor) -> Tensor:
    """Occupancy of normalized points ``xn`` [..., 3] in ``grids[instance]`` (``instance``
    broadcasts against ``xn[..., 0]``); outside the box → False."""
    ijk, inside = cell_index(xn, grids.shape[-1])
    return _at_cells(grids, instance, ijk) & inside


def lookup_in_box(grids: Tensor, instance: Tensor, xn: Tensor) -> Tensor:
    """:func:`lookup` for points known to lie in the box up to rounding (a march between the
    ray's box entry and exit): coordinates are clamped onto the grid instead of tested."""
    res = grids.shape[-1]
    ijk = ((xn + 1.0) * (0.5 * res)).clamp_(0, res - 1).long()  # ≥ 0, so truncation is floor
    return _at_cells(grids, instance, ijk)


def _at_cells(grids: Tensor, instance: Tensor, ijk: Tensor) -> Tensor:
    """``grids[instance, i, j, k]`` for cell coordinates ``ijk`` [..., 3] on the grid."""
    res = grids.shape[-1]
    return gather_flat(grids.reshape(-1), ((instance * res + ijk[..., 0]) * res + ijk[..., 1]) * res + ijk[..., 2])


def gather_flat(values: Tensor, index: Tensor) -> Tensor:
    """``values[index]`` for a 1-D ``values`` and an ``index`` of any shape, the same bits by
    ``index_select``: on the CPU a third of advanced indexing's time on a 64³ grid's cells."""
    return values.index_select(0, index.reshape(-1)).view(index.shape)


def masked_trilinear(values: Tensor, known: Tensor, xn: Tensor) -> Tensor:
    """Trilinear interpolation of per-cell ``values`` [R, R, R] at normalized points ``xn``
    [M, 3] over the ``known`` cells [R, R, R] only: the weights of the other cells are dropped
    and the rest renormalized; 0 where no known cell is among the eight.  [M]

    A surface the renderer places between an occupied cell and an empty one then reads the
    occupied cell's value, not a blend with the empty cell's meaningless zero."""
    g = xn.flip(-1).reshape(1, -1, 1, 1, 3)  # grid_sample's (x, y, z) index (W, H, D) = [iz, iy, ix]
    known_f = known.to(values.dtype)
    num = F.grid_sample((values * known_f)[None, None], g, mode="bilinear", align_corners=False).reshape(-1)
    den = F.grid_sample(known_f[None, None], g, mode="bilinear", align_corners=False).reshape(-1)
    return torch.where(den > 1e-6, num / den.clamp_min(1e-6), torch.zeros_like(num))


def cell_centers(res: int, device: torch.device | str = "cpu") -> Tensor:
    """Normalized centers of all cells, in the grid's flat [ix, iy, iz] order.  [R³, 3]"""
    c = (torch.arange(res, device=device, dtype=torch.float32) + 0.5) / res * 2.0 - 1.0
    return torch.stack(torch.meshgrid(c, c, c, indexing="ij"), dim=-1).reshape(-1, 3)


def centers_of_cells(idx: Tensor, res: int) -> Tensor:
    """:func:`cell_centers` of the flat cell indices ``idx`` [C] only (the same float arithmetic,
    so the same values), without building all R³ centers.  [C, 3]"""
    ijk = torch.stack([idx // (res * res), idx // res % res, idx % res], dim=-1)
    return (ijk.to(torch.float32) + 0.5) / res * 2.0 - 1.0


def dilate(grid: Tensor, cells: int = 1) -> Tensor:
    """Grow occupied regions by ``cells`` in every direction (3-D box max filter, 26-neighbourhood
    for one cell).  The box is separable: an OR of shifted copies along each axis in turn."""
    if cells <= 0:
        return grid
    out = grid.bool()
    for axis in range(out.dim() - 3, out.dim()):
        acc = out.clone()
        n = out.shape[axis]
        for s in range(1, min(cells, n - 1) + 1):
            acc.narrow(axis, s, n - s).logical_or_(out.narrow(axis, 0, n - s))
            acc.narrow(axis, 0, n - s).logical_or_(out.narrow(axis, s, n - s))
        out = acc
    return out


def carve_visual_hull(
    cameras: Sequence[Camera], masks: Sequence[np.ndarray], aabb: Tensor, res: int, margin: int = 1
) -> Tensor:
    """Visual hull on a [res]³ grid over ``aabb``: a cell is kept if its center projects onto the
    object (mask True) in every view whose image it falls in, and falls in at least half of the
    images (captures are object-centric: the object is in view nearly always, while space near
    one camera, which projects onto the object in that view only, is seen by few).  ``margin`` cells
    of dilation make it conservative.  Masks are [H, W] bool (True = object).
    """
    lo, hi = aabb[:3].double(), aabb[3:].double()
    xn = cell_centers(res).double()
    pts = lo + (xn + 1.0) * 0.5 * (hi - lo)  # [C, 3] world
    alive = torch.arange(pts.shape[0])  # cells not carved yet: each view only projects these
    seen_count = torch.zeros(pts.shape[0], dtype=torch.int32)
    for cam, mask in zip(cameras, masks):
        p_world = pts[alive]
        c2w = torch.as_tensor(cam.c2w, dtype=torch.float64)
        p = (p_world - c2w[:3, 3]) @ c2w[:3, :3]  # camera space
        z = -p[:, 2]
        in_front = z > 1e-6
        zs = torch.where(in_front, z, torch.ones_like(z))
        u = (cam.focal * p[:, 0] / zs + 0.5 * cam.width).floor().long()
        v = (-cam.focal * p[:, 1] / zs + 0.5 * cam.height).floor().long()
        seen = in_front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        m = torch.as_tensor(np.ascontiguousarray(mask), dtype=torch.bool)
        fg = m[v.clamp(0, cam.height - 1), u.clamp(0, cam.width - 1)]
        seen_count[alive] += seen.int()
        alive = alive[~seen | fg]
    keep = torch.zeros(pts.shape[0], dtype=torch.bool)
    keep[alive] = True
    keep &= seen_count >= math.ceil(0.5 * len(masks))
    return dilate(keep.view(res, res, res), margin)


def occupied_box(grid: Tensor, aabb: Tensor, margin_cells: int = 2) -> Tensor:
    """World-space box [6] around the occupied cells of ``grid``, grown by ``margin_cells``."""
    res = grid.shape[-1]
    idx = grid.nonzero()
    if idx.numel() == 0:
        return aabb.clone()
    lo_i = (idx.min(dim=0).values - margin_cells).clamp(min=0).double()
    hi_i = (idx.max(dim=0).values + 1 + margin_cells).clamp(max=res).double()
    lo, hi = aabb[:3].double(), aabb[3:].double()
    size = (hi - lo) / res
    return torch.cat([lo + lo_i * size, lo + hi_i * size]).float()


def step_size(aabb: Tensor, res: int, steps_per_cell: float) -> float:
    """Marching step: the largest cell side divided by ``steps_per_cell``."""
    return float((aabb[3:] - aabb[:3]).max()) / res / steps_per_cell


def update_from_density(
    ema: Tensor,
    candidates: Tensor,
    density_fn: Callable[[Tensor], Tensor],
    step: float,
    threshold: float,
    decay: float = 0.95,
    generator: torch.Generator | None = None,
    cells: Tensor | None = None,
) -> Tensor:
    """One refresh of an instance's grid from its density field (as in Instant-NGP).

    ``ema`` [R³] holds a running max-decayed density per cell; ``candidates`` [R³] bool marks
    the cells that may be occupied at all (the visual hull).  Each candidate is probed at a
    random point inside it; ``ema = max(decay·ema, σ)``.  Returns the new grid: candidates
    whose ``1 - exp(-ema·step)`` exceeds ``threshold``.  ``cells`` [C] long, the indices of the
    candidates, may be given by a caller that refreshes the same candidates often (training):
    finding them is a ``nonzero``, a host read on a GPU.  The probes are drawn on the
    generator's device.
    """
    res = round(len(ema) ** (1 / 3))
    idx = candidates.nonzero().squeeze(-1) if cells is None else cells
    centers = centers_of_cells(idx, res)
    device = generator.device if generator is not None else None
    jitter = torch.rand(centers.shape, generator=generator, device=device).to(ema.device) - 0.5
    sigma = density_fn(centers + jitter * (2.0 / res))
    ema.mul_(decay)
    ema[idx] = torch.maximum(ema[idx], sigma.float())
    sigma_min = -math.log1p(-threshold) / step
    return (ema > sigma_min) & candidates
