"""Lifting scribbles to surface points, and describing any point by the field's own features:
the bottleneck, predicted colour and chromaticity, position, F_fuse, and the local shape of
the matter around it (read from the density)."""

from __future__ import annotations

import math
import threading
from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from ... import occupancy
from ...cameras import Camera, rays_from_camera
from ...errors import CrfError
from ...field import ConditionalRadianceField
from ...renderer import RenderOutput, render_camera
from .classify import chromaticity
from .options import CHROMA_OFFSET, FEATURE_GROUPS, GEOMETRY_RADIUS, MIN_OPACITY, WIDTHS


def group_width(group: str, cfg) -> int:
    """Columns of feature ``group`` in :func:`point_features` for a model of config ``cfg``."""
    return WIDTHS.get(group, {"fuse": cfg.width, "part": cfg.part_dim}.get(group, cfg.bottleneck))


@torch.no_grad()
def surface_points(
    field: ConditionalRadianceField, camera: Camera, instance: int, min_opacity: float = MIN_OPACITY,
    out: RenderOutput | None = None,
) -> tuple[Tensor, Tensor]:
    """(world points [H·W, 3], on-object mask [H·W]) at each pixel's expected surface depth,
    from ``out`` (the view's render; rendered here when None, depth and opacity only)."""
    out = render_camera(field, camera, instance, colour=False) if out is None else out
    rays = rays_from_camera(camera, field.aabb.device)
    opacity = out.opacity.reshape(-1)
    t = out.depth.reshape(-1) / opacity.clamp_min(1e-6)
    return rays.origins + t[:, None] * rays.directions, opacity >= min_opacity


@torch.no_grad()
def point_features(
    field: ConditionalRadianceField, instance: int, points: Tensor, view_from: Tensor, groups: Sequence[str], fused: Tensor | None = None,
    shape_grid: Tensor | None = None, shape_radius: int = GEOMETRY_RADIUS, chroma_offset: float = CHROMA_OFFSET,
    geometry: Tensor | None = None,
) -> Tensor:
    """The field's own description of world ``points`` [M, 3]: the chosen :data:`FEATURE_GROUPS`
    groups concatenated, unstandardized.  Colour is F_rad's output looking from ``view_from`` [3];
    position is the normalized point and its second-order terms (so that a linear classifier
    can select e.g. both arms but not the seat between them); ``fuse`` is F_fuse's output, of
    which the bottleneck is a linear map; ``geometry`` the matter's local shape
    (:func:`local_shape` of ``shape_grid``, the instance's :func:`cell_opacity` when None).
    ``fused``: F_fuse's output at the points, when the caller has it, and ``geometry`` their
    local shape; ``chroma``'s offset: :attr:`SelectOptions.chroma_offset`."""
    xn = field.normalize(points)
    fused = field.fuse_features(xn, instance) if fused is None else fused
    feat = field.bottleneck(fused)
    rgb = None
    if "color" in groups or "chroma" in groups:  # F_rad once for both colour groups
        rgb = field.radiance(feat, F.normalize(points - view_from, dim=-1), instance)
    out = []
    for group in groups:
        if group == "bottleneck":
            out.append(feat)
        elif group == "fuse":
            out.append(fused)
        elif group == "color":
            out.append(rgb)
        elif group == "chroma":  # rgb / (r + g + b): a Lambertian shading factor cancels
            out.append(chromaticity(rgb, chroma_offset))
        elif group == "position":
            x, y, z = xn.unbind(-1)
            out.append(torch.stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], dim=-1))
        elif group == "geometry":
            if geometry is None:
                grid = cell_opacity(field, instance, field.occupancy[instance]) if shape_grid is None else shape_grid
                geometry = local_shape(grid, xn, shape_radius)
            out.append(geometry)
        elif group == "part":
            if field.F_part is None:
                raise CrfError("selection feature 'part': this model has no part head (its dataset had no part maps)")
            out.append(field.part_embedding(fused))
        else:
            raise CrfError(f"selection feature {group!r}: expected one of {', '.join(FEATURE_GROUPS)}")
    return torch.cat(out, dim=-1)


class Frames(NamedTuple):
    """The local shape of the matter around points (:func:`local_frames`), per point."""

    linear: Tensor
    """(λ₁ − λ₂)/λ₁: 1 on a line of cells.  [M]"""
    planar: Tensor
    """(λ₂ − λ₃)/λ₁: 1 on a sheet.  [M]"""
    spherical: Tensor
    """λ₃/λ₁: 1 in a solid.  [M]"""
    share: Tensor
    """The block's mean weight.  [M]"""
    spread: Tensor
    """√λ₁ / r.  [M]"""
    direction: Tensor
    """v₁, a line's direction (unit; its sign arbitrary).  [M, 3]"""
    normal: Tensor
    """v₃, a sheet's normal (unit; its sign arbitrary).  [M, 3]"""


def local_frames(grid: Tensor, xn: Tensor, radius: int = GEOMETRY_RADIUS) -> Frames:
    """The shape of the matter in the (2r+1)³ block of cells around the cell of each normalized
    point ``xn`` [M, 3], each cell weighing ``grid`` [R, R, R] (a cell's opacity, or a bool
    occupancy grid): the eigenvalues λ₁ ≥ λ₂ ≥ λ₃ and eigenvectors v₁, v₂, v₃ of the weighted
    covariance of the cells' offsets (+ 10⁻³ I), as :class:`Frames`."""
    res, side = grid.shape[-1], grid.shape[-1] + 2 * radius
    padded = F.pad(grid.to(xn.dtype), (radius,) * 6).reshape(-1)  # the box's outside is empty
    ijk, _ = occupancy.cell_index(xn, res)
    ijk = ijk.clamp(0, res - 1) + radius
    r = torch.arange(-radius, radius + 1, device=xn.device)
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)  # [K, 3]
    flat = (ijk[:, 0] * side + ijk[:, 1]) * side + ijk[:, 2]
    at = flat[:, None] + ((offsets[:, 0] * side + offsets[:, 1]) * side + offsets[:, 2])[None]  # [M, K]
    w = occupancy.gather_flat(padded, at)
    n = w.sum(dim=1).clamp_min(1e-6)
    d = offsets.to(xn.dtype)
    mean = w @ d / n[:, None]
    second = (w @ (d[:, :, None] * d[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3) / n[:, None, None]
    cov = second - mean[:, :, None] * mean[:, None, :] + 1e-3 * torch.eye(3, dtype=xn.dtype, device=xn.device)
    lam, v1, v3 = sym3_eigen(cov)  # ascending
    l3, l2, l1 = lam.clamp_min(1e-6).unbind(-1)
    return Frames((l1 - l2) / l1, (l2 - l3) / l1, l3 / l1, w.mean(dim=1), l1.sqrt() / radius, v1, v3)


def sym3_eigen(a: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The eigenvalues (ascending) [M, 3] of symmetric 3×3 matrices ``a`` [M, 3, 3], and the
    unit eigenvectors of the largest [M, 3] and of the smallest [M, 3], in closed form (in
    float64 inside; returned in ``a``'s dtype).

    The eigenvalues by the trigonometric solution of the characteristic cubic (Smith 1961),
    each eigenvector as the longest cross product of two rows of a − λI.  Where an eigenvalue
    is repeated its eigenvectors are any of a plane and it is a line's normal or a sheet's
    direction, which :func:`local_shape` weighs by 0; where all three are equal (a solid
    block) the vectors are z and x, as LAPACK returns for a multiple of I.
    ``torch.linalg.eigh`` loops over the matrices: 2.5× the time on a 37 000-cell grid."""
    m = a.reshape(-1, 9).T.double().contiguous()
    a00, a01, a02, _, a11, a12, _, _, a22 = m
    q = (a00 + a11 + a22) / 3
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    p2 = (d0 * d0 + d1 * d1 + d2 * d2 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6
    p = p2.sqrt()
    det = d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
    phi = torch.acos(torch.where(p2 > 0, det / (2 * p2 * p).clamp_min(1e-300), torch.zeros_like(det)).clamp_(-1, 1)) / 3
    l1 = q + 2 * p * torch.cos(phi)
    l3 = q + 2 * p * torch.cos(phi + 2 * math.pi / 3)
    l2 = 3 * q - l1 - l3

    def vector(lam: Tensor, fallback: tuple[float, float, float]) -> Tensor:
        b0, b1, b2 = a00 - lam, a11 - lam, a22 - lam
        crosses = [(a01 * a12 - a02 * b1, a02 * a01 - b0 * a12, b0 * b1 - a01 * a01),
                   (a01 * b2 - a02 * a12, a02 * a02 - b0 * b2, b0 * a12 - a01 * a02),
                   (b1 * b2 - a12 * a12, a12 * a02 - a01 * b2, a01 * a12 - b1 * a02)]
        best, best_n = crosses[0], sum(c * c for c in crosses[0])
        for c in crosses[1:]:
            n = sum(ci * ci for ci in c)
            longer = n > best_n
            best, best_n = tuple(torch.where(longer, ci, bi) for ci, bi in zip(c, best)), torch.where(longer, n, best_n)
        ok = best_n > 1e-24 * (1 + p2) ** 2
        inv = torch.where(ok, best_n.clamp_min(1e-300).rsqrt(), torch.zeros_like(best_n))
        return torch.stack([torch.where(ok, c * inv, torch.full_like(c, f)) for c, f in zip(best, fallback)], dim=-1)

    return torch.stack([l3, l2, l1], dim=-1).to(a.dtype), vector(l1, (0.0, 0.0, 1.0)).to(a.dtype), vector(l3, (1.0, 0.0, 0.0)).to(a.dtype)


def local_shape(grid: Tensor, xn: Tensor, radius: int = GEOMETRY_RADIUS) -> Tensor:
    """:func:`local_frames` as features: linearity ℓ, planarity p, sphericity, the block's mean
    weight, √λ₁ / r, and the orientation ℓ·v₁² (a line's direction) and p·v₃² (a sheet's
    normal), per axis (squared: the eigenvectors' signs are arbitrary).  [M, 11]

    The classic point-cloud descriptors, on the grid: a tube is a line of cells, a seat or a
    shell a sheet, a cushion a solid, and a chair's legs are vertical lines where the
    stretchers between them are horizontal ones.  A part's colour and the field's features
    do not tell a dark frame from the dark seat it carries, nor legs from stretchers of their
    colour; its shape does."""
    f = local_frames(grid, xn, radius)
    return torch.cat([torch.stack([f.linear, f.planar, f.spherical, f.share, f.spread], dim=-1),
                      f.linear[:, None] * f.direction**2, f.planar[:, None] * f.normal**2], dim=-1)


SHAPE_SOURCES = ("density", "occupancy")
"""What :attr:`SelectOptions.shape_from` may name."""
SHAPE_FRACTION = 1 / 32
""":func:`cell_opacity` measures a cell's opacity across this fraction of its side."""


@torch.no_grad()
def cell_opacity(field: ConditionalRadianceField, instance: int, occupied: Tensor, sigma: Tensor | None = None) -> Tensor:
    """Each occupied cell's opacity across :data:`SHAPE_FRACTION` of its side, 1 − exp(−σ·h·f)
    with σ the density at its centre (``sigma`` [C], in the order of the occupied cells, when
    the caller has it) and h the cell's side, 0 in the empty cells.  [R, R, R]

    What :func:`local_shape` weighs.  The occupancy grid is dilated for sampling (a thin leg is
    a solid block of occupied cells, sphericity 0.8–0.9); the density is not, but an opacity
    across a whole cell saturates to 1 in the leg's halo as in its core: across 1/32 of it
    the weight is nearly the density itself, up to where a surface is."""
    res = occupied.shape[-1]
    cells = occupied.reshape(-1).nonzero().squeeze(-1)
    if sigma is None:
        xn = occupancy.cell_centers(res, occupied.device)[cells]
        sigma = field.sigma(field.raw_density(field.fuse_features(xn, instance))).reshape(-1)
    h = float((field.aabb[3:] - field.aabb[:3]).max()) / res
    out = torch.zeros(res**3, device=occupied.device)
    out[cells] = 1.0 - torch.exp(-sigma * h * SHAPE_FRACTION)
    return out.view(res, res, res)


ASCENT_CHUNK = 8192
""":func:`denser_points` takes the cells this many at a time: each piece's activations stay in
the cache (37 000 cells on one core: 126 → 114 ms, the same bits)."""


class CellPoints(NamedTuple):
    """An instance's occupied cells as a selection describes them, the same for every scribble:
    their flat indices ``cells`` [N] in the occupancy grid, ``points`` [N, 3] (normalized: the
    cell centres, moved up the density gradient when ``ascent`` > 0, :func:`denser_points`),
    F_fuse's output there [N, width] and the density at the centres [N] (both None without the
    ascent).  A caller that selects on one instance again (the page, at every stroke) computes
    them once (:func:`cell_points`) and hands them to :func:`~.pipeline.select`, which keeps
    in ``memo`` what else it derives from them and the instance alone (:meth:`kept`)."""

    cells: Tensor
    points: Tensor
    fused: Tensor | None
    sigma: Tensor | None
    ascent: float
    memo: dict | None = None
    """What :func:`~.pipeline.select` derived from these and the instance, not from a scribble:
    the mirror plane, the mirrored views' renders, the shape grid, the cells' local shape and
    frames, their neighbour table.  The same values as computed afresh, bit for bit (a test);
    None keeps nothing."""

    def fits(self, cells: Tensor, ascent: float) -> bool:
        """Whether these are the points of the occupied cells ``cells`` [N] at ``ascent``."""
        return self.ascent == ascent and self.cells.shape == cells.shape and bool(torch.equal(self.cells, cells))

    def kept(self, key: tuple, make):
        """``make()``, kept in :attr:`memo` under ``key``.  Renders (keys starting with
        "render") are kept :data:`MEMO_RENDERS` at a time, the oldest dropped first.  The page
        may select on two threads at once: the memo is read and written under a lock, and
        ``make`` runs outside it (two threads may both make a value; the first kept wins)."""
        if self.memo is None:
            return make()
        with MEMO_LOCK:
            if key in self.memo:
                return self.memo[key]
        value = make()
        with MEMO_LOCK:
            if key not in self.memo:
                renders = [k for k in self.memo if k[0] == "render"]
                if key[0] == "render" and len(renders) >= MEMO_RENDERS:
                    del self.memo[renders[0]]  # a dict keeps its keys in insertion order
                self.memo[key] = value
            return self.memo[key]


class FrameTable:
    """:func:`local_frames` of points ``xn`` [N, 3] in ``grid``, computed for the rows asked for
    and kept: a row's frame is the same bits whichever rows are computed with it (a test), so
    the table answers as computing the rows asked for would."""

    def __init__(self, grid: Tensor, xn: Tensor, radius: int):
        self.grid, self.xn, self.radius = grid, xn, radius
        self.done = torch.zeros(len(xn), dtype=torch.bool, device=xn.device)
        self.table: Frames | None = None
        self.lock = threading.Lock()  # the page selects on its render thread and in its edits

    def at(self, rows: Tensor) -> Frames:
        """The frames of the rows ``rows`` [N] bool marks."""
        with self.lock:
            todo = rows & ~self.done
            if bool(todo.any()):
                fresh = local_frames(self.grid, self.xn[todo], self.radius)
                if self.table is None:
                    self.table = Frames(*(t.new_zeros((len(self.xn), *t.shape[1:])) for t in fresh))
                for t, v in zip(self.table, fresh):
                    t[todo] = v
                self.done |= todo
            return Frames(*(t[rows] for t in self.table))


MEMO_RENDERS = 8
""":meth:`CellPoints.kept` keeps this many renders (one a scribbled view, for its mirror image)."""
MEMO_LOCK = threading.Lock()
""":meth:`CellPoints.kept`'s lock (held only to read and write a memo)."""


@torch.no_grad()
def cell_points(field: ConditionalRadianceField, instance: int, ascent: float) -> CellPoints:
    """:class:`CellPoints` of ``instance``'s occupied cells, each moved ``ascent`` × half a
    cell up the density gradient (:attr:`SelectOptions.cell_ascent`; 0: the centres)."""
    occupied = field.occupancy[instance]
    res = occupied.shape[-1]
    cells = occupied.reshape(-1).nonzero().squeeze(-1)
    centres = occupancy.cell_centers(res, occupied.device)[cells]
    if ascent <= 0:
        return CellPoints(cells, centres, None, None, ascent, {})
    # a half cell is 1/res in normalized units
    return CellPoints(cells, *denser_points(field, instance, centres, ascent / res), ascent, {})


def denser_points(field: ConditionalRadianceField, instance: int, xn: Tensor, distance: float) -> tuple[Tensor, Tensor, Tensor]:
    """Normalized points ``xn`` [N, 3], each moved ``distance`` along its density gradient where
    the density is higher there, else left where it is; F_fuse's output at the points
    returned [N, width], which :func:`point_features` takes instead of computing it again; and
    the density at ``xn`` [N], which :func:`cell_opacity` takes.

    One gradient step (a forward and backward pass, and one forward pass to check it): a cell
    centre beside a thin part moves onto it, one inside a solid part stays put or moves within
    it.  Every point's step is its own, so the points go :data:`ASCENT_CHUNK` at a time."""
    if len(xn) > ASCENT_CHUNK:
        pieces = [denser_points(field, instance, piece, distance) for piece in xn.split(ASCENT_CHUNK)]
        return tuple(torch.cat(parts) for parts in zip(*pieces))
    density = lambda fused: field.sigma(field.raw_density(fused))
    with torch.enable_grad():
        x = xn.detach().requires_grad_(True)
        fused = field.fuse_features(x, instance)
        sigma = density(fused)
        (grad,) = torch.autograd.grad(sigma.sum(), x)
    moved = xn + F.normalize(grad, dim=-1) * distance
    fused_moved = field.fuse_features(moved, instance)
    denser = (density(fused_moved) > sigma.detach())[:, None]
    return torch.where(denser, moved, xn), torch.where(denser, fused_moved, fused.detach()), sigma.detach().reshape(-1)
