"""Volume-rendering math as small pure functions over tensors.

Samples along a ray are intervals ``[t_starts, t_ends)`` with densities ``sigmas``.  Everything
is batched over leading dimensions ``[..., N]`` (N samples per ray, sorted by t); a sample with
σ = 0 contributes nothing, which is how skipped (empty) space and padding are represented.
Transmittance is computed from an exclusive cumulative sum of σδ — never as a product of many
(1 - α) — so it stays accurate and finite for σ from 0 to 1e8 and δ from 0 to 1e10.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class Composite(NamedTuple):
    rgb: Tensor  # [..., 3]
    depth: Tensor  # [...]  expected distance Σ wᵢ tᵢ (not normalized by opacity)
    opacity: Tensor  # [...]  Σ wᵢ = 1 - T_final
    weights: Tensor  # [..., N]


def optical_depth_from_density(t_starts: Tensor, t_ends: Tensor, sigmas: Tensor) -> Tensor:
    """σᵢ·δᵢ with δᵢ = tᵢ₊ - tᵢ clamped at 0.  [..., N]"""
    return sigmas * (t_ends - t_starts).clamp_min(0.0)


def exclusive_cumsum(x: Tensor) -> Tensor:
    """[0, x₀, x₀+x₁, …] along the last axis.  Shifting the inclusive sum (rather than
    subtracting xᵢ from it) keeps a small prefix exact when a later xᵢ is huge."""
    return torch.cat([torch.zeros_like(x[..., :1]), torch.cumsum(x, dim=-1)[..., :-1]], dim=-1)


def transmittance_from_density(t_starts: Tensor, t_ends: Tensor, sigmas: Tensor) -> Tensor:
    """Tᵢ = exp(-Σ_{j<i} σⱼδⱼ), the light reaching the start of sample i.  [..., N]

    Example: σδ = [0.5, 1.0, 2.0] → T = [1, e^-0.5, e^-1.5].
    """
    return torch.exp(-exclusive_cumsum(optical_depth_from_density(t_starts, t_ends, sigmas)))


def render_weight_from_density(t_starts: Tensor, t_ends: Tensor, sigmas: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Compositing weights wᵢ = Tᵢ·αᵢ with αᵢ = 1 - exp(-σᵢδᵢ).  Returns (weights, T, alphas), each [..., N].

    Example (the nerfacc check): alphas [0.4, 0.8, 0.1] → weights [0.4, 0.48, 0.012].
    ``-expm1`` keeps αᵢ accurate when σᵢδᵢ is tiny.
    """
    tau = optical_depth_from_density(t_starts, t_ends, sigmas)
    alphas = -torch.expm1(-tau)
    trans = torch.exp(-exclusive_cumsum(tau))
    return trans * alphas, trans, alphas


def accumulate_along_rays(weights: Tensor, values: Tensor | None = None) -> Tensor:
    """Σᵢ wᵢ vᵢ over the sample axis; ``values`` [..., N, C] (or None → Σ wᵢ, shape [...])."""
    if values is None:
        return weights.sum(dim=-1)
    return (weights.unsqueeze(-1) * values).sum(dim=-2)


def composite_from_density(
    t_starts: Tensor,  # [..., N]
    t_ends: Tensor,  # [..., N]
    sigmas: Tensor,  # [..., N]
    rgbs: Tensor,  # [..., N, 3]
    background: Tensor | float = 1.0,  # [3] or scalar
) -> Composite:
    """Colour = Σ wᵢ cᵢ + (1 - Σ wᵢ)·background; depth uses interval midpoints.

    Closed form: a constant σ over total length L gives opacity 1 - exp(-σL) for any number
    of samples.
    """
    weights, _, _ = render_weight_from_density(t_starts, t_ends, sigmas)
    opacity = accumulate_along_rays(weights)
    rgb = accumulate_along_rays(weights, rgbs) + (1.0 - opacity).unsqueeze(-1) * background
    depth = accumulate_along_rays(weights, (0.5 * (t_starts + t_ends)).unsqueeze(-1)).squeeze(-1)
    return Composite(rgb, depth, opacity, weights)


TAU_CAP = 1e3
"""Optical depth past which a sample is opaque to float64: exp(-1e3) = 0.  Capping σδ there in
the *transmittance* sums (not in αᵢ) changes no result and bounds the packed running sum."""


def exclusive_cumsum_packed(x: Tensor, ray: Tensor, n_rays: int) -> Tensor:
    """Per-ray exclusive cumulative sum of packed values ``x`` [M] whose ``ray`` [M] is sorted
    (each ray's samples contiguous, in order): [0, x₀, x₀+x₁, …] within every ray.

    One running sum over all M values, minus each ray's value at its first sample.  It runs in
    float64 on values capped at :data:`TAU_CAP`, so the subtraction loses < M·1e3·2⁻⁵² ≈ 1e-8.
    """
    x64 = x.double().clamp(max=TAU_CAP)
    before = torch.cumsum(x64, 0) - x64  # global exclusive sum
    counts = torch.bincount(ray, minlength=n_rays)
    first = torch.cumsum(counts, 0) - counts  # index of each ray's first sample
    return (before - before[first[ray]]).to(x.dtype)


def composite_packed_samples(
    ray: Tensor,  # [M] long, sorted
    t_starts: Tensor,  # [M]
    t_ends: Tensor,  # [M]
    sigmas: Tensor,  # [M]
    rgbs: Tensor,  # [M, 3]
    n_rays: int,
    background: Tensor | float = 1.0,
) -> Composite:
    """:func:`composite_from_density` on packed samples (only the evaluated ones, grouped by
    ray), as nerfacc does: no dense [rays, steps] layout.  ``weights`` is packed [M]; rays with
    no samples get the background.
    """
    tau = optical_depth_from_density(t_starts, t_ends, sigmas)
    weights = torch.exp(-exclusive_cumsum_packed(tau, ray, n_rays)) * -torch.expm1(-tau)
    zeros = weights.new_zeros(n_rays)
    opacity = zeros.index_add(0, ray, weights)
    rgb = weights.new_zeros(n_rays, 3).index_add(0, ray, weights[:, None] * rgbs)
    rgb = rgb + (1.0 - opacity)[:, None] * background
    depth = zeros.index_add(0, ray, weights * 0.5 * (t_starts + t_ends))
    return Composite(rgb, depth, opacity, weights)


def ray_aabb_intersect(origins: Tensor, directions: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test against ``aabb = [xmin, ymin, zmin, xmax, ymax, zmax]``.

    Returns (t_near, t_far, hit), each [N]; t_near ≥ 0 (a ray starting inside begins at 0);
    rays that miss get t_near = t_far = 0 and hit = False.  Axis-parallel rays are handled
    without NaN by treating 1/0 as ±1e12.
    """
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    inv = 1.0 / safe
    t0 = (aabb[:3] - origins) * inv
    t1 = (aabb[3:] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    hit = t_far > t_near
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


def intervals_from_points(t: Tensor, t_near: Tensor, t_far: Tensor) -> tuple[Tensor, Tensor]:
    """Contiguous intervals around sorted distances ``t`` [N, n] that tile [t_near, t_far].

    Interval i spans the midpoints to its neighbours; the first starts at ``t_near`` and the
    last ends at ``t_far`` (both [N]), so the intervals meet end to end (Σδ = t_far - t_near up to rounding).
    """
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    starts = torch.cat([torch.minimum(t_near[:, None], t[:, :1]), mids], dim=-1)
    ends = torch.cat([mids, torch.maximum(t_far[:, None], t[:, -1:])], dim=-1)
    return starts, ends
