"""Compositing: volume-rendering math as small pure functions over tensors.

Samples along a ray are intervals ``[t_starts, t_ends)`` with densities ``sigmas``; where they
lie is chosen by :mod:`crfedit.sampling`, the field is run on them by :mod:`crfedit.renderer`.
Two layouts, named in the functions that take them:

* **dense** — batched over leading dimensions ``[..., N]`` (N samples per ray, sorted by t); a
  sample with σ = 0 contributes nothing, which is how skipped (empty) space and padding are
  represented (:func:`composite_dense`);
* **packed** — [M] samples grouped by ray, only the evaluated ones (:func:`composite_packed`).

Transmittance is computed from an exclusive cumulative sum of σδ — never as a product of many
(1 - α) — so it stays accurate and finite for σ from 0 to 1e8 and δ from 0 to 1e10.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .sampling import PackedSamples, dense_from_packed


class Composite(NamedTuple):
    rgb: Tensor  # [..., 3]
    depth: Tensor  # [...]  expected distance Σ wᵢ tᵢ (not normalized by opacity)
    opacity: Tensor  # [...]  Σ wᵢ = 1 - T_final
    weights: Tensor  # [..., N]


def optical_depth_from_density(t_starts: Tensor, t_ends: Tensor, sigmas: Tensor) -> Tensor:
    """σᵢ·δᵢ with δᵢ = tᵢ₊ - tᵢ clamped at 0.  [..., N]  A zero-length interval has depth 0 whatever
    its σ (an infinite σ there made inf·0 = NaN, and a padding row is such an interval)."""
    delta = (t_ends - t_starts).clamp_min(0.0)
    return torch.where(delta > 0, sigmas * delta, torch.zeros((), dtype=sigmas.dtype, device=sigmas.device))


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


def composite_dense(
    t_starts: Tensor,  # [..., N]
    t_ends: Tensor,  # [..., N]
    sigmas: Tensor,  # [..., N]
    rgbs: Tensor,  # [..., N, 3]
    background: Tensor | float = 1.0,  # [3] or scalar
) -> Composite:
    """Colour = Σ wᵢ cᵢ + (1 - Σ wᵢ)·background over the dense layout; depth uses interval midpoints.

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


def exclusive_cumsum_packed(x: Tensor, ray: Tensor, n_rays: int, first: Tensor | None = None) -> Tensor:
    """Per-ray exclusive cumulative sum of packed values ``x`` [M] whose ``ray`` [M] is sorted
    (each ray's samples contiguous, in order): [0, x₀, x₀+x₁, …] within every ray.

    One running sum over all M values, minus each ray's value at its first sample.  It runs in
    float64 on values capped at :data:`TAU_CAP`, so the subtraction loses < M·1e3·2⁻⁵² ≈ 1e-8;
    a NaN counts 0 in the running sum (its own ray's weight at it is NaN all the same).
    ``first`` [n_rays] (each ray's first index) is counted from ``ray`` when not given; a caller
    that knows it (:func:`crfedit.sampling.pack_mask`) saves the ``bincount``, which reads its
    input's maximum back to the host on a GPU.
    """
    x64 = x.double().nan_to_num(nan=0.0).clamp(max=TAU_CAP)  # a NaN sample spoils its own ray only, not every ray after it
    before = torch.cumsum(x64, 0) - x64  # global exclusive sum
    if first is None:
        counts = torch.bincount(ray, minlength=n_rays)
        first = torch.cumsum(counts, 0) - counts
    return (before - before[first[ray]]).to(x.dtype)


def composite_packed(
    ray: Tensor,  # [M] long, sorted
    t_starts: Tensor,  # [M]
    t_ends: Tensor,  # [M]
    sigmas: Tensor,  # [M]
    rgbs: Tensor,  # [M, 3]
    n_rays: int,
    background: Tensor | float = 1.0,
    first: Tensor | None = None,  # [n_rays] long: each ray's first sample (see exclusive_cumsum_packed)
) -> Composite:
    """:func:`composite_dense` on packed samples (only the evaluated ones, grouped by
    ray), as nerfacc does: no dense [rays, steps] layout.  ``weights`` is packed [M]; rays with
    no samples get the background.  Padding rows with zero-length intervals (t_ends = t_starts)
    composite to nothing, which is how a fixed-capacity buffer's unused slots pass through.
    Half-precision inputs are composited in float32 and the results returned in their dtype
    (accumulated in bf16, 512 samples a ray were 0.1 off in opacity, ten times the dense sum's
    error).
    """
    low = sigmas.dtype in (torch.float16, torch.bfloat16)
    if low:
        out = composite_packed(ray, t_starts.float(), t_ends.float(), sigmas.float(), rgbs.float(), n_rays,
                               background.float() if torch.is_tensor(background) else background, first)
        return Composite(*(t.to(sigmas.dtype) for t in out))
    tau = optical_depth_from_density(t_starts, t_ends, sigmas)
    weights = torch.exp(-exclusive_cumsum_packed(tau, ray, n_rays, first)) * -torch.expm1(-tau)
    zeros = weights.new_zeros(n_rays)
    opacity = zeros.index_add(0, ray, weights)
    rgb = weights.new_zeros(n_rays, 3).index_add(0, ray, weights[:, None] * rgbs)
    rgb = rgb + (1.0 - opacity)[:, None] * background
    depth = zeros.index_add(0, ray, weights * 0.5 * (t_starts + t_ends))
    return Composite(rgb, depth, opacity, weights)


def distortion_dense(t_starts: Tensor, t_ends: Tensor, weights: Tensor) -> Tensor:
    """Mip-NeRF 360's distortion loss of each ray [...] over the dense layout [..., N]:
    Σᵢⱼ wᵢwⱼ|mᵢ − mⱼ| + ⅓ Σᵢ wᵢ²δᵢ, mᵢ the interval midpoints (sorted along the ray).

    Small when a ray's weight sits in one short stretch (a surface), large when it is spread
    along the ray (a soft or doubled surface, floaters).  In O(N), as Barron et al.'s
    appendix: the pairs are 2 Σᵢ wᵢ (mᵢ Σ_{j<i} wⱼ − Σ_{j<i} wⱼmⱼ).  Example: all the weight
    w in one interval of length δ gives w²δ/3; two halves w/2 a distance d apart add w²d/2.
    """
    mid, delta = 0.5 * (t_starts + t_ends), (t_ends - t_starts).clamp_min(0.0)
    pairs = 2.0 * weights * (mid * exclusive_cumsum(weights) - exclusive_cumsum(weights * mid))
    return (pairs + weights.square() * delta / 3.0).sum(dim=-1)


class Distortion(NamedTuple):
    """:func:`distortion_packed`'s result: the loss of each ray, and what it carries into the
    next stretch of the same rays."""

    loss: Tensor  # [n_rays]
    weight: Tensor  # [n_rays] Σ wᵢ so far
    weighted_mid: Tensor  # [n_rays] Σ wᵢmᵢ so far


def distortion_packed(
    ray: Tensor, t_starts: Tensor, t_ends: Tensor, weights: Tensor, n_rays: int, first: Tensor | None = None,
    carry: Distortion | None = None,
) -> Distortion:
    """:func:`distortion_dense` of packed samples [M] (``ray`` sorted, ``first`` as in
    :func:`exclusive_cumsum_packed`).  ``weights`` are the rays' compositing weights (the
    transmittance before the samples included).  A march that takes a ray in stretches
    passes each stretch the last one's result as ``carry``: every earlier sample lies before
    this stretch's, so the pairs across stretches need only its sums, and the losses add up
    to the whole ray's.  Pass t relative to something near the ray's start (its entry into
    the scene box): the loss is the same, the float32 differences more exact."""
    mid, delta = 0.5 * (t_starts + t_ends), (t_ends - t_starts).clamp_min(0.0)
    w_before = exclusive_cumsum_packed(weights, ray, n_rays, first)
    wm_before = exclusive_cumsum_packed(weights * mid, ray, n_rays, first)
    if carry is not None:
        w_before, wm_before = w_before + carry.weight[ray], wm_before + carry.weighted_mid[ray]
    per_sample = 2.0 * weights * (mid * w_before - wm_before) + weights.square() * delta / 3.0
    zeros = weights.new_zeros(n_rays)
    out = Distortion(zeros.index_add(0, ray, per_sample), zeros.index_add(0, ray, weights), zeros.index_add(0, ray, weights * mid))
    if carry is None:
        return out
    return Distortion(carry.loss + out.loss, carry.weight + out.weight, carry.weighted_mid + out.weighted_mid)


def composite_packed_as_dense(
    samples: PackedSamples, sigmas: Tensor, rgbs: Tensor, background: Tensor | float = 1.0  # sigmas [M], rgbs [M, 3]
) -> Composite:
    """:func:`composite_dense` of packed samples scattered into their dense [n_rays, n_steps]
    layout (σ = 0 and δ = 0 where nothing was sampled); ``weights`` is dense [n_rays, n_steps].

    Equals :func:`composite_packed` up to rounding; the hierarchical sampler and the edit
    passes composite this way (their columns are the sample order along each ray).
    """
    dense = lambda v: dense_from_packed(samples, v)
    return composite_dense(dense(samples.t_starts), dense(samples.t_ends), dense(sigmas), dense(rgbs), background)
