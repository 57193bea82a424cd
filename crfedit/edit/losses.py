"""Loss terms of the edits, as small pure functions over tensors."""

from __future__ import annotations

from typing import Mapping

import torch
from torch import Tensor

from ..names import PENALTIES

VALID_SIGMA = 1e-20
"""Densities at or below this count as "no sample" (the compacted layout pads rays with σ = 0)."""
_MASKED = -1e4  # logit of a padded sample: exp(−1e4 − ·) = 0 exactly, yet finite


def log_density_distribution(sigmas: Tensor) -> tuple[Tensor, Tensor]:
    """(log pᵢ, valid) of pᵢ = σᵢ / Σⱼ σⱼ along the last axis, computed as a masked softmax of
    log σ so it is finite for σ from 0 to any finite size.  [..., S] → ([..., S], [..., S] bool)

    Padded samples (σ ≤ :data:`VALID_SIGMA`) get pᵢ = 0 and no gradient.  Through σ = exp(raw)
    the gradient with respect to the raw density is ∂/∂zᵢ of a softmax, bounded by 1.
    Example: σ = [1, 3, 0] → p = [0.25, 0.75, 0].
    """
    valid = sigmas > VALID_SIGMA
    logits = torch.where(valid, torch.log(sigmas.clamp_min(VALID_SIGMA)), torch.full_like(sigmas, _MASKED))
    return torch.log_softmax(logits, dim=-1), valid


def density_entropy(sigmas: Tensor) -> Tensor:
    """Entropy of the normalized densities along each ray, H = −Σᵢ pᵢ log pᵢ with pᵢ = σᵢ/Σσ.
    [..., S] → [...]

    Minimizing it makes a ray's density peaky (one surface or none).  A ray with no density
    (every σ = 0) has H = 0 and zero gradient.  Example: σ = [1, 1, 0, 0] → H = log 2.
    """
    log_p, valid = log_density_distribution(sigmas)
    h = -(log_p.exp() * log_p).sum(dim=-1)
    return torch.where(valid.any(dim=-1), h, torch.zeros_like(h))


def density_cross_entropy(target_sigmas: Tensor, sigmas: Tensor) -> Tensor:
    """−Σᵢ qᵢ log pᵢ between the normalized target densities q (no gradient) and the normalized
    densities p, per ray; 0 where the target ray is empty.  [..., S] → [...]"""
    log_q, valid_q = log_density_distribution(target_sigmas.detach())
    log_p, _ = log_density_distribution(sigmas)
    ce = -(log_q.exp() * log_p).sum(dim=-1)
    return torch.where(valid_q.any(dim=-1), ce, torch.zeros_like(ce))


def visible_log_density(weights: Tensor, sigmas: Tensor) -> Tensor:
    """Σᵢ sg(wᵢ) · log(1 + σᵢ) per ray ([..., S] → [...]): lowers the density of what each ray
    sees now, each sample in proportion to its share of the pixel (weights carry no gradient).

    A colour or opacity target alone barely moves a saturated surface: ∂αᵢ/∂σᵢ = δᵢe^(−σᵢδᵢ)
    vanishes once σδ ≫ 1, and the fast preset's exp activation reaches σδ ~ 10⁴.  Here the
    gradient with respect to the raw density is wᵢσᵢ/(1 + σᵢ): about wᵢ on a dense surface, and
    it fades as the surface clears (wᵢ → 0) or thins (σᵢ → 0).
    """
    return (weights.detach() * torch.log1p(sigmas)).sum(dim=-1)


def log_density_drift(weights0: Tensor, sigmas: Tensor, sigmas0: Tensor) -> Tensor:
    """Σᵢ w⁰ᵢ (log(1 + σᵢ) − log(1 + σ⁰ᵢ))² per ray: keeps the surfaces a ray saw (weights
    ``weights0``, no gradient) at their starting density — the counterpart of
    :func:`visible_log_density` for rays whose look must not change.  [..., S] → [...]"""
    return (weights0.detach() * (torch.log1p(sigmas) - torch.log1p(sigmas0.detach())) ** 2).sum(dim=-1)


ELEMENT_SCALE = 4096
"""The ``element`` penalty divides Σ(θ − θ₀)² by this: about the size of the largest trained
weight matrices (F_rad's first layer: 3 520 numbers, F_fuse's: 7 872), so those keep roughly
the per-number weight the ``tensor`` penalty gives them while code rows and biases lose the
100–4 000× excess that the per-tensor mean gives small tensors."""


def weight_penalty(
    current: Mapping[str, Tensor], start: Mapping[str, Tensor], rows: Mapping[str, int], per: str = "tensor",
) -> Tensor:
    """The drift of the trained tensors from their start; a code table (named in ``rows``)
    counts only the edited instance's row.

    ``per="tensor"``: Σ over tensors of mean((θ − θ₀)²).  Per-tensor means keep the penalty on
    the scale of a pixel loss whatever the tensor sizes, but weigh a number by 1/(its tensor's
    size): a 32-number code row is held ~100× harder per number than an F_rad weight, so
    strategies that train different tensors are not penalised alike.  ``per="element"``:
    Σ over every trained number of (θ − θ₀)² / :data:`ELEMENT_SCALE`, the same weight for a
    number in any tensor and any strategy."""
    if per not in PENALTIES:
        raise ValueError(f"weight_penalty: per={per!r}, expected one of {PENALTIES}")
    total = None
    for name, theta in current.items():
        theta0 = start[name]
        if name in rows:
            theta, theta0 = theta[rows[name]], theta0[rows[name]]
        sq = (theta - theta0) ** 2
        term = torch.mean(sq) if per == "tensor" else torch.sum(sq) / ELEMENT_SCALE
        total = term if total is None else total + term
    if total is None:
        raise ValueError("weight_penalty: no trained tensors")
    return total


@torch.no_grad()
def add_weight_penalty_grad_(
    current: Mapping[str, Tensor], start: Mapping[str, Tensor], rows: Mapping[str, int], per: str, scale: float,
) -> None:
    """Add ``scale`` · ∇ :func:`weight_penalty` to each tensor's ``.grad`` in place.

    The penalty is a quadratic, so its gradient is closed-form: 2(θ − θ₀) / n, with n =
    :data:`ELEMENT_SCALE` (``per="element"``) or the counted numbers of the tensor (``tensor``),
    only on the edited row of a code table.  Edits add it between the backward pass and the
    optimizer step instead of putting the penalty in the autograd graph: on a CPU an edit step
    is a few milliseconds and the penalty's ~10 tensors cost ~40 small autograd ops each step.
    """
    if per not in PENALTIES:
        raise ValueError(f"add_weight_penalty_grad_: per={per!r}, expected one of {PENALTIES}")
    for name, theta in current.items():
        if theta.grad is None:
            theta.grad = torch.zeros_like(theta)
        grad, diff = theta.grad, theta - start[name]
        if name in rows:
            grad, diff = grad[rows[name]], diff[rows[name]]
        n = ELEMENT_SCALE if per == "element" else diff.numel()
        grad.add_(diff, alpha=2.0 * scale / n)


def mse(rgb: Tensor, target: Tensor) -> Tensor:
    """Mean squared error over rays and channels."""
    return torch.mean((rgb - target) ** 2)
