"""Feature caching: an edit renders the same rays at every step, so everything upstream of the
trained parameters is computed once.

The samples of the edit's rays are fixed up front (the deterministic samples the renderer
uses: the full occupancy-grid march, or the paper's coarse + importance samples taken at the
starting weights).  What is cached depends on what is trained (:func:`cache_stage`):

========== ===================================  ================================================
stage      trained                              cached once            each step runs
========== ===================================  ================================================
radiance   F_rad, colour code (and the          bottleneck features    F_rad; Σ wᵢcᵢ + (1−Σw)·bg
           bottleneck: :data:`FEATURES`)        (F_fuse's output if
                                                it trains), weights
fuse       F_fuse, F_dens (and F_rad, codes…)   :class:`FuseInputs`    F_fuse → σ, features → F_rad,
                                                                       compositing
points     anything upstream (F_share, codes)   normalized points      the whole field
========== ===================================  ================================================

Samples are stored *compacted*: column j of a ray is its j-th evaluated sample.  Skipped
samples have σ = 0 and contribute nothing, so compositing the compacted layout equals
compositing the march's full layout, with far fewer columns.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from ..cameras import Camera, Rays, rays_from_camera
from ..field import ConditionalRadianceField, FieldNet, FuseInputs, positional_encoding
from ..names import COLOR_CODES, MODULES
from .params import TRAINED
from ..renderer import field_at_samples
from ..rendering import composite_dense, composite_packed_as_dense, render_weight_from_density
from ..sampling import (
    PackedSamples,
    compact,
    dense_from_packed,
    fine_samples_from_coarse,
    grid_samples,
    packed_samples_from_t,
    ray_aabb_intersect,
    stratified_samples,
)

STAGES = ("radiance", "fuse", "points")
PRUNE_WEIGHT = 1e-3
"""Radiance stage: samples whose compositing weight is below this leave the trained sum; their
colour at the starting weights stays in as a constant, so the starting render is unchanged."""

_DOWNSTREAM_OF_FUSE = tuple(m + "." for m in MODULES[MODULES.index("F_fuse") :])
"""What runs on the cached :class:`FuseInputs`: F_fuse and every module after it."""


FEATURES = "bottleneck."
"""The bottleneck layer (F_fuse's output → F_rad's 8 features): a colour edit may train it
without moving density (a recolour that bled, :data:`~.supervised.WIDENED`); the radiance stage
then caches F_fuse's output and runs the layer at every step."""


def cache_stage(trained: Sequence[str], density_changes: bool) -> str:
    """The deepest stage whose inputs ``trained`` (parameter names) cannot change.

    ``density_changes`` is False for colour edits: with F_rad, the colour code and at most the
    bottleneck trained, the compositing weights are constants.
    """
    if not density_changes and all(n.startswith((*TRAINED["color"], FEATURES)) for n in trained):
        return "radiance"
    fuse = (*_DOWNSTREAM_OF_FUSE, *("coarse." + p for p in _DOWNSTREAM_OF_FUSE), COLOR_CODES)
    if all(n.startswith(fuse) for n in trained):
        return "fuse"
    return "points"


class PassOutput(NamedTuple):
    rgb: Tensor  # [N, 3]
    opacity: Tensor  # [N]
    sigmas: Tensor | None  # [N, S] compacted densities (None in the radiance stage)
    weights: Tensor | None  # [N, S] compacted compositing weights (None in the radiance stage)
    rgbs: Tensor | None  # [N, S, 3] compacted sample colours (None in the radiance stage)


@torch.no_grad()
def edit_samples(field: ConditionalRadianceField, rays: Rays, instance: int) -> list[tuple[str, PackedSamples]]:
    """The renderer's deterministic samples of ``rays`` for one instance, per network.

    Grid sampler: ``[("fine", the full march through occupied cells)]`` (no early stop, so
    samples behind a surface that an edit may uncover are there).  Hierarchical sampler:
    ``[("coarse", stratified), ("fine", coarse + importance samples)]``, the importance samples
    drawn from the starting weights and then held fixed.
    """
    n = rays.origins.shape[0]
    inst = torch.full((n,), instance, dtype=torch.long, device=rays.origins.device)
    cfg = field.cfg
    if cfg.sampler == "grid":
        return [("fine", compact(grid_samples(field, rays, inst)))]
    t_near, t_far, hit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    t_c = stratified_samples(t_near, t_far, cfg.n_coarse)
    coarse = packed_samples_from_t(rays, t_c, t_near, t_far, hit)
    if cfg.n_fine == 0:
        return [("coarse", coarse)]
    sig, rgb = field_at_samples(field.coarse, field, coarse, rays, inst)
    weights = composite_packed_as_dense(coarse, sig, rgb, 1.0).weights
    t_all = fine_samples_from_coarse(t_c, t_near, t_far, weights, cfg.n_fine)
    return [("coarse", coarse), ("fine", packed_samples_from_t(rays, t_all, t_near, t_far, hit))]


class EditPass:
    """One network's fixed samples of the edit's rays, with its stage's inputs cached.

    ``field`` is the trainable copy that renders ``instance``; :meth:`forward` reads its current
    parameters (and the instance's code rows) at every call.
    """

    def __init__(
        self,
        field: ConditionalRadianceField,
        net_name: str,
        rays: Rays,
        samples: PackedSamples,
        instance: int,
        stage: str,
        background: float = 1.0,
        prune: float = PRUNE_WEIGHT,
        features_train: bool = False,
    ):
        if stage not in STAGES:
            raise ValueError(f"stage {stage!r}: expected one of {STAGES}")
        self.field, self.instance, self.stage, self.background = field, instance, stage, background
        self.net: FieldNet = field if net_name == "fine" else field.coarse
        self.samples = samples
        self.n_rays = samples.n_rays
        dirs = rays.directions[samples.ray]  # [M, 3]
        self.encoded_dirs = positional_encoding(dirs, self.net.F_rad.pe_d)  # [M, D]: constant, encoded once
        self.t_starts, self.t_ends = self.dense(samples.t_starts), self.dense(samples.t_ends)  # [N, S]
        self.xn = field.normalize(samples.points)  # [M, 3]
        with torch.no_grad():
            shape_code, _ = field.codes(instance)
            if stage == "points":
                self.inputs = None
            else:
                self.inputs = FuseInputs(*(t.detach() if t is not None else None for t in self.net.fuse_inputs(self.xn, shape_code)))
            self.fused = None  # radiance stage, bottleneck trained: F_fuse's output of the kept samples
            if stage == "radiance":
                h = self.net.fuse_activations(self.inputs)
                raw, feat = self.net.raw_density(h), self.net.bottleneck(h)
                weights, _, _ = render_weight_from_density(self.t_starts, self.t_ends, self.dense(self.net.sigma(raw)))
                w = weights[samples.ray, samples.step]
                keep = w > prune
                per_point = self.net.F_rad.inputs(feat, dirs)  # constant during a colour edit: built once
                _, color_code = field.codes(instance)
                dropped = (w * ~keep)[:, None] * self.net.F_rad(per_point, color_code)
                self.opacity = weights.sum(dim=-1)  # [N]
                # Σ of the dropped samples' w·c, plus the background: the constant part of each ray's colour.
                self.constant = torch.zeros(samples.n_rays, 3, device=w.device).index_add(0, samples.ray, dropped)
                self.constant += (1.0 - self.opacity)[:, None] * background
                self.w, self.ray, self.per_point = w[keep], samples.ray[keep], per_point[keep]
                self.xn_kept = self.xn[keep]  # [m, 3] where each kept sample lies (a selection's lookup)
                if features_train:
                    self.fused, self.dirs_kept = h[keep], self.encoded_dirs[keep]
                self.inputs = self.encoded_dirs = None
            self.n_cached = int(self.ray.numel()) if stage == "radiance" else int(samples.ray.numel())

    def rad_inputs(self, net: FieldNet) -> Tensor:
        """Radiance stage: F_rad's inputs [m, 8 + D] of the kept samples, through ``net``'s
        bottleneck now where it trains, else the cached ones."""
        if self.fused is None:
            return self.per_point
        return torch.cat([net.bottleneck(self.fused), self.dirs_kept], dim=-1)

    def sample_rgb(self, net: FieldNet, color_code: Tensor | None) -> Tensor:
        """Radiance stage: ``net``'s F_rad colour [m, 3] of each kept sample."""
        return net.F_rad(self.rad_inputs(net), color_code)

    def radiance_rgb(self, net: FieldNet, color_code: Tensor | None, inputs: Tensor | None = None) -> Tensor:
        """Radiance stage: each ray's colour [N, 3] with ``net``'s F_rad on the cached samples
        (on ``inputs`` [m, 8 + D] instead of :meth:`rad_inputs` when given)."""
        rgb = self.sample_rgb(net, color_code) if inputs is None else net.F_rad(inputs, color_code)
        return self.constant.index_add(0, self.ray, self.w[:, None] * rgb)

    def densities(self) -> tuple[Tensor, Tensor]:
        """(σ [M], bottleneck features [M, 8]) at the current parameters (not the radiance stage)."""
        shape_code, _ = self.field.codes(self.instance)
        inputs = self.inputs if self.inputs is not None else self.net.fuse_inputs(self.xn, shape_code)
        raw, feat = self.net.density_from_fuse_inputs(inputs)
        return self.net.sigma(raw), feat

    def dense(self, values: Tensor) -> Tensor:
        """Packed per-sample values [M, ...] → compacted layout [N, S, ...] (zeros elsewhere)."""
        return dense_from_packed(self.samples, values)

    def forward(self) -> PassOutput:
        """Render the edit's rays with the field's current parameters."""
        _, color_code = self.field.codes(self.instance)
        if self.stage == "radiance":
            return PassOutput(self.radiance_rgb(self.net, color_code), self.opacity, None, None, None)
        sigma, feat = self.densities()
        rgb_s = self.net.F_rad(torch.cat([feat, self.encoded_dirs], dim=-1), color_code)
        sigmas, rgbs = self.dense(sigma), self.dense(rgb_s)
        comp = composite_dense(self.t_starts, self.t_ends, sigmas, rgbs, self.background)
        return PassOutput(comp.rgb, comp.opacity, sigmas, comp.weights, rgbs)


def edit_passes(
    field: ConditionalRadianceField, rays: Rays, instance: int, trained: Sequence[str], density_changes: bool,
    cache: bool = True,
) -> list[EditPass]:
    """The cached passes an edit optimizes: only the final network's for colour edits (the
    coarse one only places samples), every network's when density changes.  ``cache=False``
    caches nothing (stage ``points``: the whole field runs at every step)."""
    stage = cache_stage(trained, density_changes) if cache else "points"
    passes = edit_samples(field, rays, instance)
    if not density_changes:
        passes = passes[-1:]
    features = any(n.startswith(FEATURES) for n in trained)
    return [EditPass(field, name, rays, samples, instance, stage, features_train=features) for name, samples in passes]


class ViewCache:
    """One view of one instance rendered once, with everything upstream of F_rad kept.

    A colour edit changes only F_rad, the colour code and at most the bottleneck layer (a
    recolour that bled, :data:`FEATURES`), so the compositing weights and F_fuse's output of
    every sample stay valid: :meth:`render` re-renders the view after such an edit by running
    F_rad (and a changed bottleneck) alone on the cached samples (an interactive recolouring
    preview).  Samples whose weight is at most ``prune`` keep their starting colour (a
    constant); the error this leaves is at most a ray's summed pruned weight times the colour
    change (measured: ≤ 1.6e-3 at the default, under one 8-bit level; docs/benchmarks.md).
    Memory: ~25 floats per kept sample and F_fuse's width more (a 128² view keeps ~5·10⁴).
    """

    @torch.no_grad()
    def __init__(self, field: ConditionalRadianceField, camera: Camera, instance: int, prune: float = PRUNE_WEIGHT):
        rays = rays_from_camera(camera, field.aabb.device)
        name, samples = edit_samples(field, rays, instance)[-1]
        self.instance, self.net_name, self.shape = instance, name, (camera.height, camera.width)
        self.cached = EditPass(field, name, rays, samples, instance, "radiance", prune=prune, features_train=True)
        self.n_cached = self.cached.n_cached
        self.bottleneck = [t.detach().clone() for t in self.cached.net.bottleneck.parameters()]

    @torch.no_grad()
    def render(self, field: ConditionalRadianceField) -> Tensor:
        """The view [H, W, 3] with ``field``'s F_rad and colour code (its density must be the
        one the cache was built with: a colour edit's, not a shape edit's)."""
        net = field if self.net_name == "fine" else field.coarse
        _, color_code = field.codes(self.instance)
        same = all(torch.equal(a, b) for a, b in zip(net.bottleneck.parameters(), self.bottleneck))  # the usual recolour
        return self.cached.radiance_rgb(net, color_code, self.cached.per_point if same else None).view(*self.shape, 3)
