"""Choosing sample positions along rays: where the field is evaluated.

Everything here decides *where* to sample; nothing runs the field (:mod:`crfedit.renderer`) or
composites (:mod:`crfedit.rendering`).  Two layouts:

* **dense** — distances ``t`` [N, S]: S samples on every ray (the hierarchical sampler);
* **packed** — :class:`PackedSamples`: only the samples that are evaluated, one row each ([M]
  tensors with the ray and the dense column they came from).  The occupancy march produces
  them directly; dense distances become packed with :func:`packed_samples_from_t`.

Samplers: the ray–box slab test (:func:`ray_aabb_intersect`), stratified (:func:`stratified_samples`)
and importance samples (:func:`importance_sample`, :func:`fine_samples_from_coarse`) of the
paper preset, and the equal-step march through occupied cells of the fast preset
(:func:`march_steps`), packed either by ``nonzero`` (:func:`grid_samples`: exactly the kept
samples, one host read) or into a buffer of fixed capacity (:func:`pack_mask`: no host read,
for the device-resident training step).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from . import occupancy
from .cameras import Rays
from .field import ConditionalRadianceField


class PackedSamples(NamedTuple):
    """The evaluated samples of a ray batch, one row each."""

    ray: Tensor  # [M] long: which ray
    step: Tensor  # [M] long: column in the dense [n_rays, n_steps] layout
    t_starts: Tensor  # [M]
    t_ends: Tensor  # [M]
    points: Tensor  # [M, 3] world
    n_rays: int
    n_steps: int


def dense_from_packed(samples: PackedSamples, values: Tensor) -> Tensor:
    """Packed per-sample values [M, ...] → the dense layout [n_rays, n_steps, ...], zeros where
    nothing was sampled (σ = 0 and δ = 0 there: such entries composite to nothing)."""
    out = torch.zeros((samples.n_rays, samples.n_steps, *values.shape[1:]), dtype=values.dtype, device=values.device)
    return out.index_put((samples.ray, samples.step), values)


def ray_aabb_intersect(origins: Tensor, directions: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test against ``aabb = [xmin, ymin, zmin, xmax, ymax, zmax]``.

    Returns (t_near, t_far, hit), each [N]; t_near ≥ 0 (a ray starting inside begins at 0);
    rays that miss get t_near = t_far = 0 and hit = False.  Axis-parallel rays are handled
    without NaN by treating 1/0 as ±1e12.  A ray without a direction (every component below
    1e-6, or NaN) misses: inside the box its 1e12 reach would be marched for ever.
    """
    size = directions.abs()
    safe = torch.where(size < 1e-12, torch.full_like(directions, 1e-12), directions)
    inv = 1.0 / safe
    t0 = (aabb[:3] - origins) * inv
    t1 = (aabb[3:] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    hit = (t_far > t_near) & (size.amax(dim=-1) > 1e-6)
    zero = torch.zeros_like(t_near)
    return torch.where(hit, t_near, zero), torch.where(hit, t_far, zero), hit


def stratified_samples(t_near: Tensor, t_far: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
    """One distance in each of ``n`` equal bins over [t_near, t_far] per ray.  [N, n]

    Uniformly jittered inside its bin when a generator is given (training), else at the bin
    center (rendering is deterministic).
    """
    u = (torch.arange(n, device=t_near.device, dtype=t_near.dtype) + 0.5) / n
    u = u.expand(t_near.shape[0], n)
    if generator is not None:
        jitter = torch.rand(u.shape, generator=generator, dtype=u.dtype).to(u.device)
        u = u + (jitter - 0.5) / n
    return t_near[:, None] + (t_far - t_near)[:, None] * u


def importance_sample(edges: Tensor, weights: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
    """Draw ``n`` distances per ray from the piecewise-constant pdf ∝ ``weights`` on ``edges``.

    ``edges`` [N, M+1], ``weights`` [N, M] → sorted samples [N, n] (inverse-CDF; deterministic
    evenly spaced quantiles when no generator is given).  A ray whose weights are all zero
    samples uniformly.
    """
    w = weights.detach() + 1e-5
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1).clamp(max=1.0)
    if generator is None:
        u = torch.linspace(0.0, 1.0, n + 2, device=edges.device, dtype=edges.dtype)[1:-1].expand(edges.shape[0], n)
    else:
        u = torch.rand((edges.shape[0], n), generator=generator, dtype=edges.dtype).to(edges.device)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e0, e1 = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0.0, 1.0)
    return torch.sort(e0 + frac * (e1 - e0), dim=-1).values


def fine_samples_from_coarse(
    t_coarse: Tensor,  # [N, C] sorted stratified distances
    t_near: Tensor,  # [N]
    t_far: Tensor,  # [N]
    weights: Tensor,  # [N, C] the coarse network's compositing weights
    n_fine: int,
    generator: torch.Generator | None = None,
) -> Tensor:
    """The fine network's distances: ``t_coarse`` plus ``n_fine`` importance samples drawn from
    the coarse weights on the bins between the coarse samples' midpoints, sorted.  [N, C + n_fine]"""
    edges = torch.cat([t_near[:, None], 0.5 * (t_coarse[:, 1:] + t_coarse[:, :-1]), t_far[:, None]], dim=-1)
    t_fine = importance_sample(edges, weights, n_fine, generator)
    return torch.sort(torch.cat([t_coarse, t_fine], dim=-1), dim=-1).values


def intervals_from_points(t: Tensor, t_near: Tensor, t_far: Tensor) -> tuple[Tensor, Tensor]:
    """Contiguous intervals around sorted distances ``t`` [N, n] that tile [t_near, t_far].

    Interval i spans the midpoints to its neighbours; the first starts at ``t_near`` and the
    last ends at ``t_far`` (both [N]), so the intervals meet end to end (Σδ = t_far - t_near up to rounding).
    """
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    starts = torch.cat([torch.minimum(t_near[:, None], t[:, :1]), mids], dim=-1)
    ends = torch.cat([mids, torch.maximum(t_far[:, None], t[:, -1:])], dim=-1)
    return starts, ends


def packed_samples_from_t(rays: Rays, t: Tensor, t_near: Tensor, t_far: Tensor, hit: Tensor) -> PackedSamples:
    """Dense distances ``t`` [N, S] → packed samples of the rays that ``hit`` [N] the box, with
    intervals from :func:`intervals_from_points` (rays that miss get no samples)."""
    starts, ends = intervals_from_points(t, t_near, t_far)
    pts = rays.origins[:, None] + t[..., None] * rays.directions[:, None]
    ray_i, col = hit[:, None].expand_as(t).nonzero(as_tuple=True)
    return PackedSamples(ray_i, col, starts[ray_i, col], ends[ray_i, col], pts[ray_i, col], t.shape[0], t.shape[1])


def march_steps(
    field: ConditionalRadianceField,
    rays: Rays,
    instance: Tensor,  # [N] long
    first: int,
    count: int,
    step: float,
    jitter: Tensor | None,  # [N] in [0, 1); None → sample at step centers
    t_near: Tensor,  # [N]
    t_far: Tensor,  # [N]
) -> tuple[Tensor, Tensor, Tensor]:
    """Steps ``first … first+count`` of the equal-step march, every ray, dense: (step starts
    [N, S], sample distances [N, S], keep [N, S] bool = the sample lies in an occupied cell
    before the ray leaves the box).

    Step j spans [t_near + j·s, t_near + (j+1)·s); its sample sits at fraction ``jitter`` (0.5
    by default) inside the step.  Occupancy is looked up in the box's normalized coordinates
    (x ↦ 2(x−lo)/(hi−lo) − 1 is affine, so a ray stays a ray).
    """
    j = torch.arange(first, first + count, device=t_near.device, dtype=t_near.dtype)
    starts = t_near[:, None] + j * step  # [N, S]
    t_mid = starts + (0.5 if jitter is None else jitter[:, None]) * step
    lo, hi = field.aabb[:3], field.aabb[3:]
    scale = 2.0 / (hi - lo)
    xn = ((rays.origins - lo) * scale - 1.0)[:, None, :] + t_mid[..., None] * (rays.directions * scale)[:, None, :]
    keep = occupancy.lookup_in_box(field.occupancy, instance[:, None], xn) & (t_mid <= t_far[:, None])
    return starts, t_mid, keep


def grid_samples(
    field: ConditionalRadianceField,
    rays: Rays,
    instance: Tensor,  # [N] long
    first: int = 0,
    count: int | None = None,
    jitter: Tensor | None = None,  # [N] in [0, 1); None → sample at step centers
    t_near: Tensor | None = None,
    t_far: Tensor | None = None,
) -> PackedSamples:
    """Steps ``first … first+count`` of the equal-step march (:func:`march_steps`), kept where
    the grid is occupied, packed by ``nonzero`` (exactly as many rows as kept samples; the
    device-resident twin is :func:`pack_mask`).  ``step`` of the result is j − first.
    """
    cfg = field.cfg
    s = occupancy.step_size(field.aabb, cfg.occ_res, cfg.steps_per_cell)
    if t_near is None or t_far is None:
        t_near, t_far, _ = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    n = rays.origins.shape[0]
    if count is None:
        span = float((t_far - t_near).max()) if n else 0.0
        count = max(1, math.ceil(span / s) - first)
    starts, t_mid, keep = march_steps(field, rays, instance, first, count, s, jitter, t_near, t_far)
    ray_i, col = keep.nonzero(as_tuple=True)
    t0 = starts[ray_i, col]
    p = rays.origins[ray_i] + t_mid[ray_i, col, None] * rays.directions[ray_i]
    return PackedSamples(ray_i, col, t0, torch.minimum(t0 + s, t_far[ray_i]), p, n, count)


class PackIndex(NamedTuple):
    """Where the kept entries of a dense [N, S] mask go in a buffer of fixed ``capacity`` C.

    Slots hold the kept entries in (ray, column) order, so each ray's samples are contiguous;
    the slots past the last kept entry are padding (``valid`` False, ray N − 1, column 0).
    """

    ray: Tensor  # [C] long, sorted
    col: Tensor  # [C] long
    valid: Tensor  # [C] bool
    first: Tensor  # [N] long: each ray's first slot (clamped to C − 1)
    fits: Tensor  # [N] bool: every kept entry of the ray has a slot
    count: Tensor  # [] long: kept entries, which may exceed C


def pack_mask(keep: Tensor, capacity: int) -> PackIndex:
    """Pack the True entries of ``keep`` [N, S] into ``capacity`` slots without ``nonzero``: no
    host read, so the shapes are known before the data (a device-resident step).

    Slot j holds the (j+1)-th True entry: the first flat index whose running count reaches j+1
    (``searchsorted`` over the cumulative sum).  Entries past the capacity get no slot; their
    rays are marked in ``fits`` so a caller can leave them out.  Example: keep [[T, F, T], [F,
    T, F]], capacity 4 → ray [0, 0, 1, 1], col [0, 2, 1, 0], valid [T, T, T, F], first [0, 2].
    """
    n, s = keep.shape
    per_ray = keep.sum(dim=1)
    end = torch.cumsum(per_ray, 0)
    running = torch.cumsum(keep.reshape(-1), 0)
    slots = torch.arange(1, capacity + 1, device=keep.device)
    flat = torch.searchsorted(running, slots).clamp_max(n * s - 1)
    count = end[-1]
    valid = slots <= count
    ray = torch.where(valid, flat // s, n - 1)
    col = torch.where(valid, flat % s, 0)
    return PackIndex(ray, col, valid, (end - per_ray).clamp_max(capacity - 1), end <= capacity, count)


def compact(samples: PackedSamples) -> PackedSamples:
    """The same samples sorted by (ray, t) with ``step`` = rank within the ray and
    ``n_steps`` = the most samples any ray has: the narrowest dense layout that holds them."""
    if samples.ray.numel() == 0:
        return samples._replace(n_steps=1)
    order = torch.argsort(samples.ray * samples.n_steps + samples.step, stable=True)
    ray = samples.ray[order]
    counts = torch.bincount(ray, minlength=samples.n_rays)
    first = torch.cumsum(counts, 0) - counts
    rank = torch.arange(ray.numel(), device=ray.device) - first[ray]
    return PackedSamples(
        ray, rank, samples.t_starts[order], samples.t_ends[order], samples.points[order], samples.n_rays, int(counts.max())
    )
