"""Rendering a field: sample rays, evaluate the field where it matters, composite.

Two samplers.  ``grid`` (fast preset): march each ray in equal steps through the scene box and
keep only samples inside occupied cells of the instance's occupancy grid; rendering marches in
segments and stops a ray once its transmittance falls below ``early_stop``.  ``hierarchical``
(paper preset): 64 stratified samples on the coarse network, 128 importance samples on the fine
one.  Samples are kept *packed* (only the evaluated ones); compositing scatters them into a
dense [rays, steps] layout where skipped samples have σ = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from . import occupancy
from .cameras import Camera, Rays, rays_from_camera
from .field import ConditionalRadianceField, FieldNet
from .rendering import (
    composite_from_density,
    composite_packed_samples,
    importance_sample,
    intervals_from_points,
    ray_aabb_intersect,
    stratified_samples,
)

SEGMENT = 32  # marching steps evaluated together before rays are tested for termination


class PackedSamples(NamedTuple):
    """The samples of a ray batch that fall in occupied cells."""

    ray: Tensor  # [M] long: which ray
    step: Tensor  # [M] long: column in the dense [n_rays, n_steps] layout
    t_starts: Tensor  # [M]
    t_ends: Tensor  # [M]
    points: Tensor  # [M, 3] world
    n_rays: int
    n_steps: int


@dataclass
class RenderOutput:
    rgb: Tensor  # [N, 3]
    depth: Tensor  # [N] expected distance Σ wᵢtᵢ (divide by opacity for the surface distance)
    opacity: Tensor  # [N]
    n_samples: int  # field evaluations spent
    coarse_rgb: Tensor | None = None  # [N, 3] hierarchical sampler only


def instance_tensor(instance: Tensor | int, n: int, device: torch.device) -> Tensor:
    if isinstance(instance, Tensor):
        return instance.to(device=device, dtype=torch.long).expand(n)
    return torch.full((n,), int(instance), dtype=torch.long, device=device)


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
    """Steps ``first … first+count`` of the equal-step march, kept where the grid is occupied.

    Step j spans [t_near + j·s, t_near + (j+1)·s) with s = :func:`occupancy.step_size`; its sample
    sits at fraction ``jitter`` (0.5 by default) inside the step.
    """
    cfg = field.cfg
    s = occupancy.step_size(field.aabb, cfg.occ_res, cfg.steps_per_cell)
    if t_near is None or t_far is None:
        t_near, t_far, _ = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    n = rays.origins.shape[0]
    if count is None:
        span = float((t_far - t_near).max()) if n else 0.0
        count = max(1, math.ceil(span / s) - first)
    j = torch.arange(first, first + count, device=t_near.device, dtype=t_near.dtype)
    starts = t_near[:, None] + j * s  # [N, S]
    t_mid = starts + (0.5 if jitter is None else jitter[:, None]) * s
    # Occupancy of every step at once, in the box's normalized coordinates (x ↦ 2(x−lo)/(hi−lo) − 1
    # is affine, so a ray stays a ray); only the kept samples get world positions.
    lo, hi = field.aabb[:3], field.aabb[3:]
    scale = 2.0 / (hi - lo)
    xn = ((rays.origins - lo) * scale - 1.0)[:, None, :] + t_mid[..., None] * (rays.directions * scale)[:, None, :]
    keep = occupancy.lookup_in_box(field.occupancy, instance[:, None], xn) & (t_mid <= t_far[:, None])
    ray_i, col = keep.nonzero(as_tuple=True)
    t0 = starts[ray_i, col]
    p = rays.origins[ray_i] + t_mid[ray_i, col, None] * rays.directions[ray_i]
    return PackedSamples(ray_i, col, t0, torch.minimum(t0 + s, t_far[ray_i]), p, n, count)


def evaluate(
    net: FieldNet, field: ConditionalRadianceField, samples: PackedSamples, rays: Rays, instance: Tensor | int,
    noise: float = 0.0, generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """σ [M] and rgb [M, 3] of ``net`` at the packed samples.

    ``instance``: [N] long per ray, or an int when every ray shows the same instance (a
    rendered view): its code rows then enter as biases, with no per-point selection.
    """
    shape_codes, color_codes, idx = field.select(instance if isinstance(instance, int) else instance[samples.ray])
    raw, feat = net.density_and_features(field.normalize(samples.points), shape_codes, idx)
    if noise > 0:
        raw = raw + noise * torch.randn(raw.shape, generator=generator).to(raw.device)
    rgb = net.radiance_from_codes(feat, rays.directions[samples.ray], color_codes, idx)
    return net.sigma(raw), rgb


def composite_packed(samples: PackedSamples, sigmas: Tensor, rgbs: Tensor, background: Tensor | float):
    """Scatter packed samples into the dense layout and composite (σ = 0 where nothing was sampled)."""
    shape = (samples.n_rays, samples.n_steps)
    dense = lambda v, fill=0.0: torch.full(shape + v.shape[1:], fill, dtype=v.dtype, device=v.device).index_put(
        (samples.ray, samples.step), v
    )
    t_starts, t_ends = dense(samples.t_starts), dense(samples.t_ends)
    return composite_from_density(t_starts, t_ends, dense(sigmas), dense(rgbs), background)


def render_rays(
    field: ConditionalRadianceField,
    rays: Rays,
    instance: Tensor | int,
    generator: torch.Generator | None = None,
    background: Tensor | float = 1.0,
    density_noise: float = 0.0,
    early_stop: float | None = None,
) -> RenderOutput:
    """Render a batch of rays of one or several instances (``instance`` int or [N] long).

    With a ``generator`` sample positions are jittered (training); without, rendering is
    deterministic.  ``early_stop`` (grid sampler) drops rays whose transmittance is below it.
    """
    n = rays.origins.shape[0]
    single = int(instance) if not isinstance(instance, Tensor) else None
    instance = instance_tensor(instance, n, rays.origins.device)
    if field.cfg.sampler == "hierarchical":
        return _render_hierarchical(field, rays, instance, generator, background, density_noise, single)
    t_near, t_far, hit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    jitter = None if generator is None else torch.rand(n, generator=generator).to(rays.origins.device)
    s = occupancy.step_size(field.aabb, field.cfg.occ_res, field.cfg.steps_per_cell)
    total = math.ceil(float((t_far - t_near).max()) / s) if n and bool(hit.any()) else 0
    segment = total if early_stop is None else SEGMENT
    rgb = torch.zeros(n, 3, device=rays.origins.device)
    depth = torch.zeros(n, device=rays.origins.device)
    trans = torch.ones(n, device=rays.origins.device)
    alive = torch.arange(n, device=rays.origins.device)[hit]
    n_samples = 0
    for first in range(0, total, max(segment, 1)):
        if alive.numel() == 0:
            break
        sub = Rays(rays.origins[alive], rays.directions[alive])
        samples = grid_samples(
            field, sub, instance[alive], first, segment, None if jitter is None else jitter[alive], t_near[alive], t_far[alive]
        )
        if samples.ray.numel():
            sig, col = evaluate(field, field, samples, sub, instance[alive] if single is None else single, density_noise, generator)
            comp = composite_packed_samples(samples.ray, samples.t_starts, samples.t_ends, sig, col, len(alive), 0.0)
            t_prev = trans[alive]
            rgb = rgb.index_add(0, alive, t_prev[:, None] * comp.rgb)
            depth = depth.index_add(0, alive, t_prev * comp.depth)
            trans = trans.index_put((alive,), t_prev * (1.0 - comp.opacity))
            n_samples += samples.ray.numel()
        if early_stop is not None:
            alive = alive[trans[alive] > early_stop]
    opacity = 1.0 - trans
    rgb = rgb + trans[:, None] * background
    return RenderOutput(rgb, depth, opacity, n_samples)


def _render_hierarchical(field, rays, instance, generator, background, density_noise, single=None) -> RenderOutput:
    cfg = field.cfg
    t_near, t_far, hit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    n = rays.origins.shape[0]

    def run(net, t):
        starts, ends = intervals_from_points(t, t_near, t_far)
        pts = rays.origins[:, None] + t[..., None] * rays.directions[:, None]
        ray_i, col = hit[:, None].expand_as(t).nonzero(as_tuple=True)
        samples = PackedSamples(ray_i, col, starts[ray_i, col], ends[ray_i, col], pts[ray_i, col], n, t.shape[1])
        sig, col_rgb = evaluate(net, field, samples, rays, instance if single is None else single, density_noise, generator)
        return composite_packed(samples, sig, col_rgb, background), samples.ray.numel()

    t_c = stratified_samples(t_near, t_far, cfg.n_coarse, generator)
    coarse, m_c = run(field.coarse, t_c)
    if cfg.n_fine == 0:
        return RenderOutput(coarse.rgb, coarse.depth, coarse.opacity, m_c, coarse.rgb)
    edges = torch.cat([t_near[:, None], 0.5 * (t_c[:, 1:] + t_c[:, :-1]), t_far[:, None]], dim=-1)
    t_f = importance_sample(edges, coarse.weights, cfg.n_fine, generator)
    t_all = torch.sort(torch.cat([t_c, t_f], dim=-1), dim=-1).values
    fine, m_f = run(field, t_all)
    return RenderOutput(fine.rgb, fine.depth, fine.opacity, m_c + m_f, coarse.rgb)


@torch.no_grad()
def render_camera(
    field: ConditionalRadianceField, camera: Camera, instance: int, chunk: int = 16384, background: float = 1.0
) -> RenderOutput:
    """Render a full view, ``chunk`` rays at a time so memory stays bounded at any resolution.

    Outputs are reshaped to images: rgb [H, W, 3], depth and opacity [H, W].
    """
    device = field.aabb.device
    rays = rays_from_camera(camera, device)
    outs = [
        render_rays(
            field, Rays(rays.origins[i : i + chunk], rays.directions[i : i + chunk]), instance,
            background=background, early_stop=field.cfg.early_stop,
        )
        for i in range(0, rays.origins.shape[0], chunk)
    ]
    h, w = camera.height, camera.width
    return RenderOutput(
        torch.cat([o.rgb for o in outs]).view(h, w, 3),
        torch.cat([o.depth for o in outs]).view(h, w),
        torch.cat([o.opacity for o in outs]).view(h, w),
        sum(o.n_samples for o in outs),
    )
