"""Classifying cells: a class-balanced logistic regression fitted by Newton's method on
standardized feature groups, self-training over the view's points, and the distance tests
(appearance gate, keep strokes winning near them, chromaticity likeness)."""

from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .options import CHROMA_OFFSET


def standardizer(all_feats: Tensor, widths: Sequence[int], weights: Sequence[float], stats: tuple[Tensor, Tensor] | None = None,
                  columns: Tensor | None = None):
    """Per-dimension z-scores, each group scaled by weight/√(its width) so groups weigh alike
    (``stats``: :func:`feature_stats` of ``all_feats``, when the caller has them), of the
    ``columns`` only when given."""
    mean, std = feature_stats(all_feats) if stats is None else stats
    scale = torch.cat([torch.full((w,), g / w**0.5) for w, g in zip(widths, weights)]).to(all_feats)
    if columns is not None:
        mean, std, scale = mean[columns], std[columns], scale[columns]
        return lambda f: (f.index_select(1, columns) - mean).div_(std).mul_(scale)
    return lambda f: (f - mean).div_(std).mul_(scale)


def feature_stats(feats: Tensor) -> tuple[Tensor, Tensor]:
    """Per-dimension mean and standard deviation (at least 10⁻⁶) of ``feats`` [N, F].

    Two passes, the second in place: ``Tensor.std(dim=0)`` takes six times as long on a
    37 000 × 140 grid of cells' features, for the same values to a unit in the last place."""
    mean = feats.mean(dim=0)
    var = (feats - mean).square_().sum(dim=0) / max(len(feats) - 1, 1)
    return mean, var.sqrt_().clamp_min(1e-6)


NEWTON_STEPS = 50
"""At most this many Newton steps per logistic fit (they converge in fewer than 10)."""
NEWTON_TOL = 1e-4
"""A logistic fit stops once a step moves no weight by more than this.  Past it the fits
creep (steps of 10⁻⁵ for a dozen more iterations, the loss changing in its seventh digit
on a 115-feature removal): a cell's logit would move by about 10⁻³."""


class Logistic(NamedTuple):
    """A fitted logistic regression: x ↦ P(positive) = σ(x·w + b) for rows of x."""

    w: Tensor
    b: Tensor

    def __call__(self, x: Tensor) -> Tensor:
        return torch.sigmoid(x @ self.w + self.b)


def fit_logistic(pos: Tensor, neg: Tensor, neg_weight: Tensor, l2: float = 1e-2, start: Logistic | None = None) -> Logistic:
    """A class-balanced logistic regression pos [P, F] vs neg [N, F] (negatives weighted by
    ``neg_weight`` [N]), L2 penalty ``l2``·|w|², fitted by Newton's method from ``start``
    (zeros when None), in float64 (the curvature in float32).  The loss is strictly convex, so the start changes only how
    many steps the fit takes; with F + 1 ≈ 25 unknowns a step is one small linear solve."""
    x = torch.cat([pos, neg]).double()
    x = torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype, device=x.device)], dim=1)
    y = torch.cat([torch.ones(len(pos)), torch.zeros(len(neg))]).to(x)
    wt = torch.cat([torch.full((len(pos),), 0.5 / len(pos)).to(x), 0.5 * neg_weight.to(x) / neg_weight.sum()])
    ridge = torch.full((x.shape[1],), 2.0 * l2, dtype=x.dtype, device=x.device)
    ridge[-1] = 0.0  # the bias is not penalised
    theta = torch.zeros(x.shape[1], dtype=x.dtype, device=x.device) if start is None else torch.cat([start.w, start.b]).to(x)
    loss = lambda z, t: (wt * F.binary_cross_entropy_with_logits(z, y, reduction="none")).sum() + 0.5 * (ridge * t * t).sum()
    x32, xt32 = x.float(), x.T.float().contiguous()  # the curvature in float32 (below)
    logits = x @ theta
    current = loss(logits, theta)
    for _ in range(NEWTON_STEPS):
        p = torch.sigmoid(logits)
        grad = x.T @ (wt * (p - y)) + ridge * theta
        # float32 curvature, float64 gradient and loss: the steps head for the same minimum and
        # the line search still guards them; the product is most of a step's time, 2.7× faster
        hess = ((xt32 * (wt * p * (1 - p)).float()) @ x32).double() + torch.diag(ridge)
        step = torch.linalg.solve(hess, grad)
        scale = 1.0
        while True:  # backtrack if a full step overshoots
            trial_theta = theta - scale * step
            trial_logits = x @ trial_theta
            trial = loss(trial_logits, trial_theta)
            if trial <= current or scale < 1e-4:
                break
            scale *= 0.5
        if trial > current:  # no step lowers the loss: converged to float64 precision
            break
        theta, logits, current = trial_theta, trial_logits, trial
        if float(step.abs().max()) * scale < NEWTON_TOL:
            break
    theta = theta.to(pos.dtype)
    return Logistic(theta[:-1], theta[-1:])


def classifier(pos: Tensor, keep: Tensor, others: Tensor, rounds: int, keep_weight: float, appearance: Tensor | None = None,
               held: Tensor | None = None):
    """Positives against the keep strokes' points (each weighing ``keep_weight``) and the view's
    other surface points; each of ``rounds`` self-training rounds drops the other points the last
    fit calls positive (the unscribbled rest of the part must not stay a negative), or that a fit
    on the ``appearance`` columns alone calls positive, but never those ``held`` [len(others)]
    marks (:attr:`~.options.SelectOptions.line_negatives`).  With no negative at all (the
    scribbles cover the whole object) everything is selected.  Each round's fits start from the
    last round's."""
    active = torch.ones(len(others), dtype=torch.bool, device=others.device)
    clf = looks = None
    for _ in range(rounds + 1):
        neg = torch.cat([keep, others[active]])
        if len(neg) == 0:  # the scribble covers all of the object in every view: it means all of it
            return lambda q: torch.ones(q.shape[0], dtype=q.dtype, device=q.device)
        weight = torch.cat([torch.full((len(keep),), keep_weight), torch.ones(int(active.sum()))]).to(pos)
        clf = fit_logistic(pos, neg, weight, start=clf)
        if len(others):
            active = clf(others) < 0.5
            if appearance is not None:
                looks = fit_logistic(pos.index_select(1, appearance), neg.index_select(1, appearance), weight, start=looks)
                active &= looks(others.index_select(1, appearance)) < 0.5
            if held is not None:
                active |= held
    return clf


def chroma_alike(cells: Tensor, pos: Tensor, factor: float, floor: float = 0.01) -> Tensor:
    """Whether each cell's chromaticity [N, 3] lies within ``factor`` · r + ``floor`` of the
    positives' [P, 3] median chromaticity, r the 90th percentile of the positives' own
    distances to it."""
    return within_spread(chroma_spread(cells, pos), factor, floor)


def within_spread(spread: tuple[Tensor, Tensor, Tensor], factor: float, floor: float) -> Tensor:
    """:func:`chroma_alike`'s test on :func:`chroma_spread`'s terms: distance ≤ ``factor`` · r + ``floor``.  [N] bool"""
    distance, r, _ = spread
    return distance <= factor * r + floor


def chromaticity(rgb: Tensor, offset: float = CHROMA_OFFSET) -> Tensor:
    """rgb / (r + g + b + ``offset``) [..., 3]: a Lambertian shading factor cancels, and near
    black it shrinks toward 0 rather than amplify the colour noise."""
    return rgb / (rgb.sum(dim=-1, keepdim=True) + offset)


def chroma_spread(cells: Tensor, pos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`chroma_alike`'s terms: each cell's distance [N] to the positives' median
    chromaticity, r (the 90th percentile of the positives' own distances to it) and the median
    [3], so that one selection tests several factors without computing them again."""
    med = pos.median(dim=0).values
    r = torch.quantile((pos - med).norm(dim=-1), 0.9) if len(pos) > 1 else torch.zeros((), device=pos.device)
    return (cells - med).norm(dim=-1), r, med


def evenly(rows: Tensor, most: int) -> Tensor:
    """``rows`` [P, ...], or ``most`` of them evenly spaced when there are more."""
    return rows if len(rows) <= most else rows[torch.linspace(0, len(rows) - 1, most).long()]


def appearance_gate(cells: Tensor, pos: Tensor, factor: float, max_positives: int = 2000) -> Tensor:
    """Whether each cell's appearance [N, F] lies within ``factor`` × the positives' spacing of
    some positive [P, F] (the spacing: 95th percentile of the positives' nearest-neighbour
    distances, over at most ``max_positives`` evenly spaced positives)."""
    pos = evenly(pos, max_positives)
    if len(pos) < 2:
        return torch.ones(len(cells), dtype=torch.bool, device=cells.device)
    d = torch.cdist(pos, pos)
    d.fill_diagonal_(float("inf"))
    spacing = torch.quantile(d.amin(dim=1), 0.95)
    return nearest_distance(cells, pos, max_positives) <= factor * spacing


def nearest_distance(cells: Tensor, points: Tensor, max_points: int = 2000, chunk: int = 8192) -> Tensor:
    """Each cell's [N, F] distance to its nearest point [P, F], over at most ``max_points``
    evenly spaced points, ``chunk`` cells at a time (bounded memory on a 64³ grid).  [N]

    ``torch.cdist(c, points).min(dim=1)`` to the bit (within an ulp where the BLAS blocks
    the transposed product differently: an AMD EPYC, 130 features), without the square root
    of every pair:
    past 25 rows cdist computes its squared distances as one product of padded rows, |a|²
    − 2a·b + |b|² (:func:`_squared_distances` repeats it), then the root of each, and the
    root is monotonic, so the root of the least square is the least root.  The product is
    taken transposed, [P, chunk] (each entry the same dot product, a test), so
    that the least square is a minimum across rows, which vectorizes: a 37 000-cell grid's
    appearance gate in half the time of ``amin`` along each row."""
    points = evenly(points, max_points)
    if not len(cells):
        return cells.new_zeros(0)
    p_norm = points.pow(2).sum(-1, keepdim=True)
    p_ = torch.cat([points, torch.ones_like(p_norm), p_norm], dim=-1)
    out = []
    for c in cells.split(chunk):
        if len(c) <= 25 and len(points) <= 25:  # cdist's direct path
            out.append(torch.cdist(c, points).amin(dim=1))
        else:
            out.append(_squared_distances(c, p_).amin(dim=0).clamp_min_(1e-30).sqrt_())
    return torch.cat(out)


def _squared_distances(cells: Tensor, padded_points: Tensor) -> Tensor:
    """cdist's squared Euclidean distances past 25 rows (ATen's ``_euclidean_dist``),
    transposed [P, N]: the rows [b, 1, |b|²] (``padded_points`` [P, F + 2]) times the columns
    [−2a, |a|², 1]."""
    c_norm = cells.pow(2).sum(-1, keepdim=True)
    return padded_points.matmul(torch.cat([cells.mul(-2), c_norm, torch.ones_like(c_norm)], dim=-1).mT)


def nearest_cosine(cells: Tensor, points: Tensor, max_points: int = 2000, chunk: int = 8192) -> Tensor:
    """Each unit row of ``cells`` [N, F]: its greatest cosine with a unit row of ``points`` [P, F]
    (over at most ``max_points`` evenly spaced), ``chunk`` cells at a time; −inf without points.  [N]"""
    if not len(points):
        return cells.new_full((len(cells),), float("-inf"))
    points_t = evenly(points, max_points).mT.contiguous()
    return torch.cat([c.matmul(points_t).amax(dim=1) for c in cells.split(chunk)]) if len(cells) else cells.new_zeros(0)


def keep_wins(cells: Tensor, pos: Tensor, keep: Tensor, ratio: float) -> Tensor:
    """Whether each cell [N, F] lies nearer some keep point [K, F] than ``ratio`` × its nearest
    positive [P, F] (:attr:`SelectOptions.keep_ratio`): a Voronoi split between the two kinds
    of stroke, in whatever space the columns span.  [N] bool; all False without keep points."""
    if len(keep) == 0 or len(pos) == 0:
        return torch.zeros(len(cells), dtype=torch.bool, device=cells.device)
    return nearest_distance(cells, keep) < ratio * nearest_distance(cells, pos)
