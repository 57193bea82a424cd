"""Running the field over samples: a ray batch or a camera rendered to colour, depth, opacity.

The three steps live apart: :mod:`crfedit.sampling` chooses the samples, :func:`field_at_samples`
runs a network on them (here), :mod:`crfedit.rendering` composites.  Two samplers.  ``grid``
(fast preset): march each ray in equal steps through the scene box and keep only samples inside
occupied cells of the instance's occupancy grid; rendering marches in segments, composites each
segment's packed samples (:func:`~crfedit.rendering.composite_packed`) and stops a ray once its
transmittance falls below ``early_stop``.  ``hierarchical`` (paper preset): 64 stratified
samples on the coarse network, 128 importance samples on the fine one, composited in the dense
[rays, samples] layout (:func:`~crfedit.rendering.composite_packed_as_dense`).

The grid march has two forms.  The reference packs each segment's samples with ``nonzero`` and
drops terminated rays by index, reading counts back to the host several times per batch.  The
device-resident form (``march=`` a :class:`FixedMarch`, used by training) keeps every shape
fixed: all rays march every segment, terminated ones masked out, and each segment's samples go
into a buffer of fixed capacity (:func:`~crfedit.sampling.pack_mask`), so a batch reads nothing
back and a GPU never waits for the host.  Both give the same colours to float rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from . import occupancy
from .cameras import Camera, Rays, narrow_view, rays_from_camera
from .cameras import camera_problem as camera_fault
from .errors import CrfError
from .names import whole_number
from .field import ConditionalRadianceField, FieldNet
from .rendering import composite_packed, composite_packed_as_dense, distortion_packed
from .sampling import (
    PackedSamples,
    fine_samples_from_coarse,
    grid_samples,
    march_steps,
    pack_mask,
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
    n_samples: int | Tensor  # field evaluations spent ([] long tensor from a FixedMarch: not read back)
    coarse_rgb: Tensor | None = None  # [N, 3] hierarchical sampler only
    complete: Tensor | None = None  # [N] bool (FixedMarch): every sample of the ray had a slot
    distortion: Tensor | None = None  # [N] the distortion loss of each ray (grid sampler, when asked)


def instance_tensor(instance: Tensor | int, n: int, device: torch.device) -> Tensor:
    if isinstance(instance, Tensor):
        return instance.to(device=device, dtype=torch.long).expand(n)
    return torch.full((n,), int(instance), dtype=torch.long, device=device)


def raw_field_at_samples(
    net: FieldNet, field: ConditionalRadianceField, points: Tensor, directions: Tensor, instance: Tensor | int
) -> tuple[Tensor, Tensor]:
    """Raw density [M] and rgb [M, 3] of ``net`` at world ``points`` [M, 3] seen along
    ``directions`` [M, 3]: every network layer and nothing else, the part worth compiling
    (:class:`FixedMarch` with ``compile``).

    ``instance``: [M] long per point, or an int when every point shows the same instance (a
    rendered view): its code rows then enter as biases, with no per-point selection.
    """
    shape_codes, color_codes, idx = field.select(instance)
    raw, feat = net.density_and_features(field.normalize(points), shape_codes, idx)
    return raw, net.radiance_from_codes(feat, directions, color_codes, idx)


def raw_density_at_samples(
    net: FieldNet, field: ConditionalRadianceField, points: Tensor, directions: Tensor, instance: Tensor | int
) -> tuple[Tensor, Tensor]:
    """:func:`raw_field_at_samples` without the colour: raw density [M] and zeros [M, 3] (F_fuse
    → F_dens only; no bottleneck, no F_rad).  For renders that read only depth and opacity."""
    raw = net.raw_density(field.fuse_features(field.normalize(points), instance, net))
    return raw, points.new_zeros(points.shape[0], 3)


def field_at_samples(
    net: FieldNet, field: ConditionalRadianceField, samples: PackedSamples, rays: Rays, instance: Tensor | int,
    noise: float = 0.0, generator: torch.Generator | None = None, raw_field=raw_field_at_samples,
) -> tuple[Tensor, Tensor]:
    """σ [M] and rgb [M, 3] of ``net`` at the packed samples (``instance``: [N] long per ray,
    or an int); ``noise`` is the std of Gaussian noise added to the raw density (training).
    ``raw_field`` runs the networks (:func:`raw_field_at_samples`, or a compiled copy of it)."""
    per_point = instance if isinstance(instance, int) else instance[samples.ray]
    raw, rgb = raw_field(net, field, samples.points, rays.directions[samples.ray], per_point)
    if noise > 0:
        draw = torch.randn(raw.shape, generator=generator, device=generator.device if generator is not None else None)
        raw = raw + noise * draw.to(raw.device)
    return net.sigma(raw), rgb


class FixedMarch:
    """The fixed shapes of a device-resident grid march (:func:`render_rays` with ``march=``).

    The march covers the scene box's diagonal (the longest chord of any ray) in two segments:
    the first :data:`SEGMENT` steps, where most rays end, then the rest (the reference march cuts
    the rest into :data:`SEGMENT`-step pieces too, which on a trained chair left a third segment
    with ~2 samples a batch and the full op count of a segment).  Each segment's kept samples go
    into a buffer of ``capacity`` slots.  A capacity is sized from the first batch that needs it
    (one host read, once per run; twice its count, as early batches change fast) and afterwards
    only by :meth:`resize`, which the training loop calls at its read-out steps: ``HEADROOM``
    above the most samples a batch kept since the last resize, rounded up to ``QUANTUM``.  A
    segment of at most ``DENSE_SLOTS`` steps over all rays (a small batch) gets a slot for every
    step instead: it can never overflow, and costs little at that size.  A batch that keeps more drops the rays whose samples did not fit
    (``RenderOutput.complete``) instead of reading anything back.  ``compile`` runs the
    networks through ``torch.compile`` (fewer, fused kernels; shapes change only at a resize).
    """

    HEADROOM = 0.1
    FIRST_HEADROOM = 1.0
    QUANTUM = 64
    DENSE_SLOTS = 8192

    def __init__(self, field: ConditionalRadianceField, compile: bool = False):
        cfg = field.cfg
        self.step = occupancy.step_size(field.aabb, cfg.occ_res, cfg.steps_per_cell)  # one read, here
        diagonal = float(torch.linalg.vector_norm((field.aabb[3:] - field.aabb[:3]).double()))
        n_steps = math.ceil(diagonal / self.step) + 1
        self.segments = [(0, min(SEGMENT, n_steps))] + ([(SEGMENT, n_steps - SEGMENT)] if n_steps > SEGMENT else [])
        self.capacity: list[int | None] = [None] * len(self.segments)
        self.needed: Tensor | None = None  # [segments] long: the most samples a batch kept since the last resize
        self.dropped: Tensor | None = None  # [] long: rays left out since the last resize
        self.raw_field = torch.compile(raw_field_at_samples, dynamic=True) if compile else raw_field_at_samples

    def size_for(self, kept: int, headroom: float | None = None) -> int:
        """Slots for a segment that kept ``kept`` samples: ``headroom`` (default ``HEADROOM``)
        more, a multiple of ``QUANTUM``."""
        more = self.HEADROOM if headroom is None else headroom
        return max(self.QUANTUM, math.ceil(kept * (1.0 + more) / self.QUANTUM) * self.QUANTUM)

    def observe(self, needed: Tensor, dropped: Tensor) -> None:
        """Fold one batch's kept samples per segment and its dropped rays into the running
        counts (device tensors; nothing is read)."""
        self.needed = needed if self.needed is None else torch.maximum(self.needed, needed)
        self.dropped = dropped if self.dropped is None else self.dropped + dropped

    def resize(self) -> int:
        """Size every segment's buffer from the counts since the last resize (one host read);
        returns the rays dropped since then."""
        if self.needed is None:
            return 0
        *needed, dropped = torch.cat([self.needed, self.dropped[None]]).tolist()
        self.capacity = [self.size_for(int(k)) for k in needed]
        self.needed = self.dropped = None
        return int(dropped)

    def pending_drops(self) -> int:
        """Rays dropped since the last resize (one host read; nothing changes)."""
        return 0 if self.dropped is None else int(self.dropped)

    def state(self) -> dict[str, Tensor]:
        """The capacities and running counts, for a checkpoint (a resumed run sizes its buffers
        as the uninterrupted run would, which keeps it bit-identical)."""
        out = {"march.capacity": torch.tensor([-1 if c is None else c for c in self.capacity])}
        if self.needed is not None:
            out.update({"march.needed": self.needed, "march.dropped": self.dropped})
        return out

    def load_state(self, state: dict[str, Tensor], device: torch.device) -> None:
        """Restore :meth:`state` (a checkpoint without it keeps the fresh state)."""
        stored = state.get("march.capacity")
        if stored is None or stored.numel() != len(self.segments):
            return
        self.capacity = [None if c < 0 else int(c) for c in stored.tolist()]
        if "march.needed" in state:
            self.needed, self.dropped = state["march.needed"].to(device), state["march.dropped"].to(device)


def _check_dtypes(field: ConditionalRadianceField, rays: Rays | None, every: bool = False) -> None:
    """A one-line error for a field whose weights are not float32 (``.half()``, ``.double()``:
    the grid and the MLPs mixed dtypes in a raw RuntimeError) or rays of float64; rays of
    float16 or bfloat16 compute in float32.  ``every``: every parameter (``render_camera``, once a
    view); else the first alone, a few attribute reads on the training path."""
    params = field.parameters() if every else [next(field.parameters())]  # every: render_camera's check, once a view
    dtype = next((p.dtype for p in params if p.dtype != torch.float32), torch.float32)
    if dtype != torch.float32 or field.aabb.dtype != torch.float32:
        raise CrfError(f"render: the field's weights are {str(dtype).replace('torch.', '')}; crfedit renders "
                       "float32 fields (for lower precision on a GPU, render under torch.autocast instead)")
    if rays is not None and (rays.origins.dtype == torch.float64 or rays.directions.dtype == torch.float64):
        raise CrfError("render: rays of float64; give float32 rays (Rays(origins.float(), directions.float()))")


def render_rays(
    field: ConditionalRadianceField,
    rays: Rays,
    instance: Tensor | int,
    generator: torch.Generator | None = None,
    background: Tensor | float = 1.0,
    density_noise: float = 0.0,
    early_stop: float | None = None,
    jitter: Tensor | None = None,  # [N] in [0, 1)
    march: FixedMarch | None = None,
    colour: bool = True,
    distortion: bool = False,
) -> RenderOutput:
    """Render a batch of rays of one or several instances (``instance`` int or [N] long).

    With a ``generator`` sample positions are jittered (training); without, rendering is
    deterministic.  ``early_stop`` (grid sampler) drops rays whose transmittance is below it.
    ``jitter`` (grid sampler) gives each ray's sample offset within its marching steps instead
    of drawing it from ``generator``.  ``march`` (grid sampler) marches with fixed shapes and
    no host read (:class:`FixedMarch`); without it, the reference march.  ``colour=False``
    (grid sampler, reference march) skips the bottleneck and F_rad: depth and opacity are the
    same bits, and rgb is the background alone.  ``distortion`` (grid sampler) also returns each
    ray's distortion loss (:func:`~crfedit.rendering.distortion_packed`), a training regularizer.
    """
    _check_dtypes(field, rays)
    n = rays.origins.shape[0]
    single = int(instance) if not isinstance(instance, Tensor) else None
    instance = instance_tensor(instance, n, rays.origins.device)
    if field.cfg.sampler == "hierarchical":
        if distortion:
            raise ValueError("the distortion loss needs the grid sampler")
        return _render_hierarchical(field, rays, instance, generator, background, density_noise, single)
    if jitter is None and generator is not None:
        jitter = torch.rand(n, generator=generator, device=generator.device).to(rays.origins.device)
    if march is not None:
        return _render_fixed(field, rays, instance, march, jitter, generator, background, density_noise, early_stop, single, distortion)
    t_near, t_far, hit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    s = occupancy.step_size(field.aabb, field.cfg.occ_res, field.cfg.steps_per_cell)
    total = math.ceil(float((t_far - t_near).max()) / s) if n and bool(hit.any()) else 0
    segment = total if early_stop is None else SEGMENT
    rgb = torch.zeros(n, 3, device=rays.origins.device)
    depth = torch.zeros(n, device=rays.origins.device)
    trans = torch.ones(n, device=rays.origins.device)
    alive = torch.arange(n, device=rays.origins.device)[hit]
    n_samples, dist = 0, None
    for first in range(0, total, max(segment, 1)):
        if alive.numel() == 0:
            break
        sub = Rays(rays.origins[alive], rays.directions[alive])
        samples = grid_samples(
            field, sub, instance[alive], first, segment, None if jitter is None else jitter[alive], t_near[alive], t_far[alive]
        )
        if samples.ray.numel():
            sig, col = field_at_samples(field, field, samples, sub, instance[alive] if single is None else single, density_noise, generator,
                                        raw_field_at_samples if colour else raw_density_at_samples)
            comp = composite_packed(samples.ray, samples.t_starts, samples.t_ends, sig, col, len(alive), 0.0)
            t_prev = trans[alive]
            if distortion:  # the rays' own indices: alive is ascending, so they stay sorted
                ray = alive[samples.ray]
                near = t_near[ray]
                dist = distortion_packed(ray, samples.t_starts - near, samples.t_ends - near, t_prev[samples.ray] * comp.weights, n, None, dist)
            rgb = rgb.index_add(0, alive, t_prev[:, None] * comp.rgb)
            depth = depth.index_add(0, alive, t_prev * comp.depth)
            trans = trans.index_put((alive,), t_prev * (1.0 - comp.opacity))
            n_samples += samples.ray.numel()
        if early_stop is not None:
            alive = alive[trans[alive] > early_stop]
    opacity = 1.0 - trans
    rgb = rgb + trans[:, None] * background
    loss = None if not distortion else torch.zeros(n, device=rays.origins.device) if dist is None else dist.loss  # no sample: no loss
    return RenderOutput(rgb, depth, opacity, n_samples, distortion=loss)


def _render_fixed(field, rays, instance, march, jitter, generator, background, density_noise, early_stop, single, distortion=False) -> RenderOutput:
    """:func:`render_rays`' grid march with fixed shapes: every ray marches every segment of
    ``march`` (terminated rays masked out), each segment's samples packed into its buffer."""
    n, device = rays.origins.shape[0], rays.origins.device
    t_near, t_far, alive = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    rgb = torch.zeros(n, 3, device=device)
    depth = torch.zeros(n, device=device)
    trans = torch.ones(n, device=device)
    complete = torch.ones(n, dtype=torch.bool, device=device)
    counts, n_samples, dist = [], 0, None
    for k, (first, count) in enumerate(march.segments):
        starts, t_mid, keep = march_steps(field, rays, instance, first, count, march.step, jitter, t_near, t_far)
        keep = keep & alive[:, None]
        if n * count <= march.DENSE_SLOTS:
            capacity = n * count
        else:
            if march.capacity[k] is None:  # the run's first batch sizes this buffer: its one host read
                march.capacity[k] = march.size_for(int(keep.sum()), march.FIRST_HEADROOM)
            capacity = march.capacity[k]
        pack = pack_mask(keep, capacity)
        t0 = starts[pack.ray, pack.col]
        t1 = torch.where(pack.valid, torch.minimum(t0 + march.step, t_far[pack.ray]), t0)  # padding: δ = 0
        points = rays.origins[pack.ray] + t_mid[pack.ray, pack.col, None] * rays.directions[pack.ray]
        samples = PackedSamples(pack.ray, pack.col, t0, t1, points, n, count)
        sig, col = field_at_samples(
            field, field, samples, rays, instance if single is None else single, density_noise, generator, march.raw_field
        )
        comp = composite_packed(pack.ray, t0, t1, sig, col, n, 0.0, pack.first)
        if distortion:
            near = t_near[pack.ray]
            dist = distortion_packed(pack.ray, t0 - near, t1 - near, trans[pack.ray] * comp.weights, n, pack.first, dist)
        rgb = rgb + trans[:, None] * comp.rgb
        depth = depth + trans * comp.depth
        trans = trans * (1.0 - comp.opacity)
        complete = complete & pack.fits
        counts.append(pack.count)
        n_samples = n_samples + pack.valid.sum()
        if early_stop is not None:
            alive = alive & (trans > early_stop)
    march.observe(torch.stack(counts), (~complete).sum())
    rgb = rgb + trans[:, None] * background
    return RenderOutput(rgb, depth, 1.0 - trans, n_samples, complete=complete, distortion=None if dist is None else dist.loss)


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


MAX_CAMERA_REACH = 1e4
"""A camera farther than this many scene-box diagonals from the box's centre is refused: float32
distances along its rays are spaced more coarsely than a fraction of a sample step there (at
10⁶ diagonals every sample collapses onto the last and the view renders blank)."""


def camera_far_problem(camera: Camera, aabb: Tensor) -> str | None:
    """What is wrong with ``camera``'s distance from the scene box ``aabb`` [6] (None if nothing)."""
    lo, hi = (aabb.detach().cpu().tolist()[i : i + 3] for i in (0, 3))
    diagonal = math.dist(lo, hi)
    distance = math.dist([float(x) for x in camera.center], [0.5 * (a + b) for a, b in zip(lo, hi)])
    if distance > MAX_CAMERA_REACH * diagonal:
        return (f"it lies {distance / diagonal:.3g} scene-box diagonals from the scene (at most {MAX_CAMERA_REACH:g}: "
                "float32 samples cannot resolve the scene from there); move it closer, a longer focal keeps the framing")
    return None


def camera_problem(camera: Camera, aabb: Tensor) -> str | None:
    """Why ``camera`` cannot render the scene in box ``aabb`` (too far for float32, a field of
    view too narrow), for an error line; None when it can.  Checked by :func:`render_camera`, and
    by a render of many views before the first (so the line names the view)."""
    fault = camera_fault(camera)  # a camera no scene can use (focal 0: the field of view divided by it)
    if fault:
        return fault
    far = camera_far_problem(camera, aabb)
    if far:
        return far
    narrow = narrow_view(camera.camera_angle_x)
    return f"{narrow}; camera_angle_x is in radians (a nerfstudio camera path's fov in degrees)" if narrow else None


@torch.no_grad()
def render_camera(
    field: ConditionalRadianceField, camera: Camera, instance: int, chunk: int = 16384, background: float = 1.0,
    colour: bool = True,
) -> RenderOutput:
    """Render a full view, ``chunk`` rays at a time so memory stays bounded at any resolution.
    ``colour=False``: depth and opacity only (see :func:`render_rays`).

    Outputs are reshaped to images: rgb [H, W, 3], depth and opacity [H, W].  ``instance`` is
    an index into the field's instances (a model's :meth:`~crfedit.model.CategoryModel.instance_index`
    turns a name into one); a bad index or chunk is one :class:`CrfError` line.
    """
    k = whole_number(instance)
    if k is None or not 0 <= k < field.n_instances:
        raise CrfError(f"render: instance {instance!r} is not an index of the field's {field.n_instances} instances "
                       "(CategoryModel.instance_index reads a name)")
    instance = k
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise CrfError(f"render: chunk {chunk!r} must be a whole number of rays, at least 1")
    if isinstance(background, bool) or not isinstance(background, (int, float, np.floating)) or not 0.0 <= background <= 1.0:
        raise CrfError(f"render: background {background!r} must be a grey level from 0 to 1")
    _check_dtypes(field, None, every=True)  # a module cast alone (F_rad.double()) too
    device = field.aabb.device
    problem = camera_problem(camera, field.aabb)
    if problem:
        raise CrfError(f"camera: {problem}")
    rays = rays_from_camera(camera, device)
    outs = [
        render_rays(
            field, Rays(rays.origins[i : i + chunk], rays.directions[i : i + chunk]), instance,
            background=background, early_stop=field.cfg.early_stop, colour=colour,
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
