"""Running the field over samples: a ray batch or a camera rendered to colour, depth, opacity.

The three steps live apart: :mod:`crfedit.sampling` chooses the samples, :func:`field_at_samples`
runs a network on them (here), :mod:`crfedit.rendering` composites.  Two samplers.  ``grid``
(fast preset): march each ray in equal steps through the scene box and keep only samples inside
occupied cells of the instance's occupancy grid; rendering marches in segments, composites each
segment's packed samples (:func:`~crfedit.rendering.composite_packed`) and stops a ray once its
transmittance falls below ``early_stop``.  ``hierarchical`` (paper preset): 64 stratified
samples on the coarse network, 128 importance samples on the fine one, composited in the dense
[rays, samples] layout (:func:`~crfedit.rendering.composite_packed_as_dense`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from . import occupancy
from .cameras import Camera, Rays, rays_from_camera
from .field import ConditionalRadianceField, FieldNet
from .rendering import composite_packed, composite_packed_as_dense
from .sampling import (
    PackedSamples,
    fine_samples_from_coarse,
    grid_samples,
    packed_samples_from_t,
    ray_aabb_intersect,
    stratified_samples,
)

SEGMENT = 32  # marching steps evaluated together before rays are tested for termination


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


def field_at_samples(
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


def render_rays(
    field: ConditionalRadianceField,
    rays: Rays,
    instance: Tensor | int,
    generator: torch.Generator | None = None,
    background: Tensor | float = 1.0,
    density_noise: float = 0.0,
    early_stop: float | None = None,
    jitter: Tensor | None = None,  # [N] in [0, 1)
) -> RenderOutput:
    """Render a batch of rays of one or several instances (``instance`` int or [N] long).

    With a ``generator`` sample positions are jittered (training); without, rendering is
    deterministic.  ``early_stop`` (grid sampler) drops rays whose transmittance is below it.
    ``jitter`` (grid sampler) gives each ray's sample offset within its marching steps instead
    of drawing it from ``generator``.
    """
    n = rays.origins.shape[0]
    single = int(instance) if not isinstance(instance, Tensor) else None
    instance = instance_tensor(instance, n, rays.origins.device)
    if field.cfg.sampler == "hierarchical":
        return _render_hierarchical(field, rays, instance, generator, background, density_noise, single)
    t_near, t_far, hit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    if jitter is None and generator is not None:
        jitter = torch.rand(n, generator=generator).to(rays.origins.device)
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
            sig, col = field_at_samples(field, field, samples, sub, instance[alive] if single is None else single, density_noise, generator)
            comp = composite_packed(samples.ray, samples.t_starts, samples.t_ends, sig, col, len(alive), 0.0)
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

    def run(net, t):
        samples = packed_samples_from_t(rays, t, t_near, t_far, hit)
        sig, rgb = field_at_samples(net, field, samples, rays, instance if single is None else single, density_noise, generator)
        return composite_packed_as_dense(samples, sig, rgb, background), samples.ray.numel()

    t_c = stratified_samples(t_near, t_far, cfg.n_coarse, generator)
    coarse, m_c = run(field.coarse, t_c)
    if cfg.n_fine == 0:
        return RenderOutput(coarse.rgb, coarse.depth, coarse.opacity, m_c, coarse.rgb)
    t_all = fine_samples_from_coarse(t_c, t_near, t_far, coarse.weights, cfg.n_fine, generator)
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


def ray_distance(output: RenderOutput, min_opacity: float = 1e-3) -> Tensor:
    """Distance along the unit ray to the surface: ``depth / opacity`` where the ray is at
    least ``min_opacity`` opaque, ``+inf`` elsewhere (background).  Same shape as ``depth``.

    ``depth`` is the unnormalized expectation Σ wᵢtᵢ; dividing by the opacity Σ wᵢ gives the
    weighted mean distance of the samples that were hit.  Example: weights (0.2, 0.6) at
    t = (1, 2) → depth 1.4, opacity 0.8 → distance 1.75.
    """
    hit = output.opacity > min_opacity
    return torch.where(hit, output.depth / output.opacity.clamp_min(min_opacity), torch.full_like(output.depth, float("inf")))
