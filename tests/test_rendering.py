"""Volume-rendering math and the renderer: closed forms, hand numbers, gradcheck, determinism.

Every expected value below is computed by hand (or by a one-line closed form) — never by
calling the function under test a second way.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from crfedit.cameras import Camera, Rays, look_at, rays_from_camera
from crfedit.config import PRESETS, Config
from crfedit.errors import CrfError
from crfedit.field import ConditionalRadianceField
from crfedit.renderer import render_camera, render_rays
from crfedit.rendering import (
    accumulate_along_rays,
    composite_dense,
    composite_packed,
    composite_packed_as_dense,
    distortion_dense,
    distortion_packed,
    exclusive_cumsum,
    exclusive_cumsum_packed,
    optical_depth_from_density,
    render_weight_from_density,
    transmittance_from_density,
)
from crfedit.sampling import (
    PackedSamples,
    dense_from_packed,
    fine_samples_from_coarse,
    grid_samples,
    importance_sample,
    intervals_from_points,
    ray_aabb_intersect,
    stratified_samples,
)

F64 = torch.float64


BOX = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])


def intervals(edges: list[float], dtype=F64) -> tuple[torch.Tensor, torch.Tensor]:
    """[1, N] starts and ends from N+1 sorted edges."""
    e = torch.tensor(edges, dtype=dtype)
    return e[None, :-1], e[None, 1:]


# --- compositing closed forms ------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 7, 64])
@pytest.mark.parametrize("uneven", [False, True])
def test_constant_density_opacity_is_one_minus_exp_sigma_length(n, uneven):
    sigma, near, far = 0.7, 0.4, 2.7  # L = 2.3
    if uneven:
        cuts = torch.sort(torch.rand(n - 1, generator=torch.Generator().manual_seed(n), dtype=F64)).values
        edges = torch.cat([torch.tensor([0.0], dtype=F64), cuts, torch.tensor([1.0], dtype=F64)])
    else:
        edges = torch.linspace(0.0, 1.0, n + 1, dtype=F64)
    edges = near + (far - near) * edges
    t0, t1 = edges[None, :-1], edges[None, 1:]
    comp = composite_dense(t0, t1, torch.full((1, n), sigma, dtype=F64), torch.zeros(1, n, 3, dtype=F64), 0.0)
    expected = 1.0 - math.exp(-sigma * (far - near))
    assert comp.opacity.item() == pytest.approx(expected, abs=1e-12)
    # the same in float32, the dtype rendering uses
    comp32 = composite_dense(t0.float(), t1.float(), torch.full((1, n), sigma), torch.zeros(1, n, 3), 0.0)
    assert comp32.opacity.item() == pytest.approx(expected, abs=1e-6)


def test_transmittance_docstring_example():
    # σδ = [0.5, 1.0, 2.0] → T = [1, e^-0.5, e^-1.5]
    t0, t1 = intervals([0.0, 1.0, 2.0, 3.0])
    sigmas = torch.tensor([[0.5, 1.0, 2.0]], dtype=F64)
    expected = torch.tensor([[1.0, math.exp(-0.5), math.exp(-1.5)]], dtype=F64)
    torch.testing.assert_close(transmittance_from_density(t0, t1, sigmas), expected, rtol=0, atol=1e-15)


def test_optical_depth_clamps_negative_intervals():
    tau = optical_depth_from_density(torch.tensor([0.0, 2.0]), torch.tensor([1.0, 1.5]), torch.tensor([3.0, 3.0]))
    assert tau.tolist() == [3.0, 0.0]


def test_nerfacc_weights_from_alphas():
    # alphas [0.4, 0.8, 0.1] → weights [0.4, 0.6·0.8, 0.6·0.2·0.1] = [0.4, 0.48, 0.012]
    alphas = torch.tensor([[0.4, 0.8, 0.1]], dtype=F64)
    t0, t1 = intervals([0.0, 1.0, 2.0, 3.0])
    weights, trans, got_alphas = render_weight_from_density(t0, t1, -torch.log1p(-alphas))
    torch.testing.assert_close(weights, torch.tensor([[0.4, 0.48, 0.012]], dtype=F64), rtol=0, atol=1e-14)
    torch.testing.assert_close(trans, torch.tensor([[1.0, 0.6, 0.12]], dtype=F64), rtol=0, atol=1e-14)
    torch.testing.assert_close(got_alphas, alphas, rtol=0, atol=1e-14)


def test_composite_hand_numbers_with_background():
    # α = [0.5, 0.5] → w = [0.5, 0.25], acc = 0.75
    t0, t1 = intervals([0.0, 1.0, 2.0])
    sigmas = torch.full((1, 2), math.log(2.0), dtype=F64)
    rgbs = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=F64)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=F64)
    comp = composite_dense(t0, t1, sigmas, rgbs, bg)
    # Σ wᵢcᵢ + (1 - acc)·bg = [0.5, 0.25, 0] + 0.25·[0.2, 0.4, 0.6]
    torch.testing.assert_close(comp.rgb, torch.tensor([[0.55, 0.35, 0.15]], dtype=F64), rtol=0, atol=1e-15)
    torch.testing.assert_close(comp.opacity, torch.tensor([0.75], dtype=F64), rtol=0, atol=1e-15)
    # depth at midpoints: 0.5·0.5 + 0.25·1.5 (not normalized by opacity)
    torch.testing.assert_close(comp.depth, torch.tensor([0.625], dtype=F64), rtol=0, atol=1e-15)
    torch.testing.assert_close(comp.weights, torch.tensor([[0.5, 0.25]], dtype=F64), rtol=0, atol=1e-15)
    # a scalar background is the same as a grey one
    grey = composite_dense(t0, t1, sigmas, rgbs, 0.5)
    torch.testing.assert_close(grey.rgb, torch.tensor([[0.625, 0.375, 0.125]], dtype=F64), rtol=0, atol=1e-15)


def test_accumulate_along_rays_hand_numbers():
    w = torch.tensor([[0.5, 0.25], [0.0, 1.0]], dtype=F64)
    v = torch.tensor([[[2.0], [4.0]], [[7.0], [3.0]]], dtype=F64)
    assert accumulate_along_rays(w).tolist() == [0.75, 1.0]
    assert accumulate_along_rays(w, v).tolist() == [[2.0], [3.0]]


def test_opaque_slab_depth_is_its_entry_distance():
    step, entry, exit_ = 0.01, 1.3, 1.6
    edges = torch.arange(0, 301, dtype=F64) * step  # 0 … 3
    t0, t1 = edges[None, :-1], edges[None, 1:]
    mid = 0.5 * (t0 + t1)
    sigmas = torch.where((mid > entry) & (mid < exit_), 1e4, 0.0).to(F64)
    comp = composite_dense(t0, t1, sigmas, torch.ones(1, 300, 3, dtype=F64), 0.0)
    assert comp.opacity.item() == pytest.approx(1.0, abs=1e-12)
    # all the weight sits on the first slab interval [1.30, 1.31]: its midpoint
    assert (comp.depth / comp.opacity).item() == pytest.approx(entry + step / 2, abs=1e-9)


def test_gradient_at_zero_density_is_the_interval_length():
    # opacity = 1 - exp(-Σσδ) → ∂opacity/∂σⱼ = δⱼ at σ = 0: the empty start of training must get gradient
    t0, t1 = intervals([0.0, 0.5, 2.0, 2.25])
    sigmas = torch.zeros(1, 3, dtype=F64, requires_grad=True)
    composite_dense(t0, t1, sigmas, torch.zeros(1, 3, 3, dtype=F64)).opacity.sum().backward()
    torch.testing.assert_close(sigmas.grad, torch.tensor([[0.5, 1.5, 0.25]], dtype=F64), rtol=0, atol=1e-15)


def test_gradcheck_render_weight_from_density():
    g = torch.Generator().manual_seed(0)
    t0, t1 = intervals([0.0, 0.3, 0.5, 1.1, 1.2, 2.0])
    t0, t1 = t0.expand(3, -1), t1.expand(3, -1)
    sigmas = (torch.rand(3, 5, generator=g, dtype=F64) * 3.0 + 0.05).requires_grad_()
    assert torch.autograd.gradcheck(lambda s: render_weight_from_density(t0, t1, s), (sigmas,))


def test_gradcheck_composite_dense():
    g = torch.Generator().manual_seed(1)
    t0, t1 = intervals([0.0, 0.3, 0.5, 1.1, 1.2, 2.0])
    t0, t1 = t0.expand(2, -1), t1.expand(2, -1)
    sigmas = (torch.rand(2, 5, generator=g, dtype=F64) * 3.0 + 0.05).requires_grad_()
    rgbs = torch.rand(2, 5, 3, generator=g, dtype=F64).requires_grad_()
    bg = torch.tensor([0.1, 0.5, 0.9], dtype=F64, requires_grad=True)

    def fn(s, c, b):
        comp = composite_dense(t0, t1, s, c, b)
        return comp.rgb, comp.depth, comp.opacity

    assert torch.autograd.gradcheck(fn, (sigmas, rgbs, bg))


def test_transmittance_exact_after_a_large_optical_depth():
    t0, t1 = intervals([0.0, 1.0, 2.0], dtype=torch.float32)
    sigmas = torch.tensor([[1.0, 1e8]])
    weights, trans, _ = render_weight_from_density(t0, t1, sigmas)
    torch.testing.assert_close(trans, torch.tensor([[1.0, math.exp(-1.0)]]), rtol=1e-6, atol=0)
    assert weights.sum().item() <= 1.0 + 1e-6


# --- ray / box intersection --------------------------------------------------------------


def intersect(origin, direction):
    d = torch.tensor([direction], dtype=torch.float32)
    near, far, hit = ray_aabb_intersect(torch.tensor([origin], dtype=torch.float32), d / d.norm(), BOX)
    return near.item(), far.item(), bool(hit.item())


def test_ray_aabb_head_on_hit():
    assert intersect((0.0, 0.0, -3.0), (0.0, 0.0, 1.0)) == (2.0, 4.0, True)


def test_ray_aabb_diagonal_hit():
    near, far, hit = intersect((-3.0, -3.0, 0.0), (1.0, 1.0, 0.0))
    assert hit and near == pytest.approx(2 * math.sqrt(2), abs=1e-5) and far == pytest.approx(4 * math.sqrt(2), abs=1e-5)


def test_ray_aabb_miss_and_box_behind():
    assert intersect((0.0, 3.0, -3.0), (0.0, 0.0, 1.0)) == (0.0, 0.0, False)
    assert intersect((0.0, 0.0, 3.0), (0.0, 0.0, 1.0)) == (0.0, 0.0, False)  # box behind the origin


def test_ray_aabb_start_inside_begins_at_zero():
    assert intersect((0.0, 0.0, 0.5), (0.0, 0.0, 1.0)) == (0.0, 0.5, True)
    assert intersect((0.2, -0.3, 0.0), (-1.0, 0.0, 0.0)) == pytest.approx((0.0, 1.2, True))  # exits at x = -1


def test_ray_aabb_axis_parallel_off_axis():
    # two direction components are exactly zero: no NaN, exact slab distances
    assert intersect((0.5, -0.5, -3.0), (0.0, 0.0, 1.0)) == (2.0, 4.0, True)
    assert intersect((1.5, -0.5, -3.0), (0.0, 0.0, 1.0)) == (0.0, 0.0, False)  # parallel, outside the x slab


def test_ray_aabb_grazing_counts_as_miss():
    # along a face (x = 1) and through an edge point only: zero-length overlap is a miss, without NaN
    assert intersect((1.0, 0.0, -3.0), (0.0, 0.0, 1.0)) == (0.0, 0.0, False)
    assert intersect((-2.0, 0.0, 0.0), (1.0, 1.0, 0.0)) == (0.0, 0.0, False)  # touches the edge x=-1, y=1


def test_ray_aabb_a_ray_without_a_direction_misses():
    """A zero (or NaN) direction inside the box reached 1e12 and was marched for ever."""
    o = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0], [0.0, 0.0, 1.0]])
    near, far, hit = ray_aabb_intersect(o, d, BOX)
    assert hit.tolist() == [False, False, True] and near.tolist() == [0.0, 0.0, 2.0] and far.tolist() == [0.0, 0.0, 4.0]


def test_ray_aabb_entry_and_exit_points_lie_on_the_box():
    g = torch.Generator().manual_seed(3)
    o = torch.randn(256, 3, generator=g) * 2.0
    d = torch.randn(256, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    near, far, hit = ray_aabb_intersect(o, d, BOX)
    assert hit.any() and (~hit).any()
    assert (near >= 0).all() and (far[hit] > near[hit]).all()
    p_far = o[hit] + far[hit, None] * d[hit]
    assert torch.allclose(p_far.abs().amax(dim=-1), torch.ones(()), atol=1e-5)  # exit on a face
    outside = o[hit].abs().amax(dim=-1) > 1.0
    p_near = o[hit][outside] + near[hit][outside, None] * d[hit][outside]
    assert torch.allclose(p_near.abs().amax(dim=-1), torch.ones(()), atol=1e-5)


# --- sampling ------------------------------------------------------------------------------


def test_stratified_samples_are_bin_centers_without_generator():
    near, far = torch.tensor([1.0, 0.0]), torch.tensor([2.0, 4.0])
    t = stratified_samples(near, far, 4)
    torch.testing.assert_close(t, torch.tensor([[1.125, 1.375, 1.625, 1.875], [0.5, 1.5, 2.5, 3.5]]))
    assert torch.equal(t, stratified_samples(near, far, 4))


def test_stratified_samples_with_generator_stay_in_their_bins():
    near, far, n = torch.full((64,), 0.5), torch.full((64,), 2.5), 8
    t = stratified_samples(near, far, n, torch.Generator().manual_seed(0))
    bins = near[:, None] + (far - near)[:, None] * torch.arange(n + 1) / n
    assert ((t >= bins[:, :-1]) & (t <= bins[:, 1:])).all()
    assert not torch.equal(t, stratified_samples(near, far, n))  # jittered
    assert torch.equal(t, stratified_samples(near, far, n, torch.Generator().manual_seed(0)))


def test_importance_sample_concentrates_in_heavy_bins():
    edges = torch.linspace(0.0, 8.0, 9)[None]
    weights = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]])
    t = importance_sample(edges, weights, 32)
    assert ((t >= 3.0) & (t <= 4.0)).float().mean() >= 0.95
    assert (t[:, 1:] >= t[:, :-1]).all()
    # two equal bumps share the samples evenly
    two = importance_sample(edges, torch.tensor([[0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]]), 32)
    assert ((two >= 1.0) & (two <= 2.0)).sum().item() == pytest.approx(16, abs=1)
    assert ((two >= 6.0) & (two <= 7.0)).sum().item() == pytest.approx(16, abs=1)


def test_importance_sample_all_zero_weights_is_uniform():
    edges = torch.linspace(1.0, 3.0, 5)[None]
    t = importance_sample(edges, torch.zeros(1, 4), 3)
    # evenly spaced quantiles 1/4, 2/4, 3/4 of a uniform pdf on [1, 3]
    torch.testing.assert_close(t, torch.tensor([[1.5, 2.0, 2.5]]), rtol=0, atol=1e-6)
    assert t.isfinite().all()


def test_importance_sample_with_generator_is_reproducible_and_in_range():
    edges = torch.linspace(0.0, 1.0, 17).expand(5, -1)
    weights = torch.rand(5, 16, generator=torch.Generator().manual_seed(2))
    a = importance_sample(edges, weights, 24, torch.Generator().manual_seed(7))
    b = importance_sample(edges, weights, 24, torch.Generator().manual_seed(7))
    assert torch.equal(a, b) and (a >= 0).all() and (a <= 1).all() and (a[:, 1:] >= a[:, :-1]).all()


def test_fine_samples_from_coarse_keep_the_coarse_ones_and_follow_the_weights():
    t_c = torch.tensor([[0.5, 1.5, 2.5, 3.5]])  # bins [0,1), [1,2), [2,3), [3,4] between midpoints
    near, far = torch.tensor([0.0]), torch.tensor([4.0])
    t = fine_samples_from_coarse(t_c, near, far, torch.tensor([[0.0, 0.0, 1.0, 0.0]]), 8)
    assert t.shape == (1, 12) and torch.equal(t, t.sort(dim=-1).values)
    fine = t[~torch.isin(t, t_c)]
    assert len(fine) == 8 and ((fine >= 2.0) & (fine <= 3.0)).all()  # all in the only weighted bin
    assert torch.equal(t[torch.isin(t, t_c)], t_c[0])  # every coarse sample stays


def test_dense_from_packed_places_values_at_their_columns():
    samples = PackedSamples(torch.tensor([0, 1, 1]), torch.tensor([2, 0, 1]), *torch.zeros(2, 3), torch.zeros(3, 3), 2, 3)
    got = dense_from_packed(samples, torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]))
    want = torch.tensor([[[0.0, 0.0], [0.0, 0.0], [1.0, 2.0]], [[3.0, 4.0], [5.0, 6.0], [0.0, 0.0]]])
    assert torch.equal(got, want)


def test_intervals_from_points_tile_near_to_far():
    g = torch.Generator().manual_seed(4)
    near, far = torch.tensor([0.5, 1.0, 2.0]), torch.tensor([1.5, 4.0, 2.5])
    t = torch.sort(near[:, None] + (far - near)[:, None] * torch.rand(3, 9, generator=g), dim=-1).values
    starts, ends = intervals_from_points(t, near, far)
    assert torch.equal(starts[:, 0], near) and torch.equal(ends[:, -1], far)
    assert torch.equal(starts[:, 1:], ends[:, :-1])  # contiguous: no gap, no overlap
    assert ((starts <= t) & (t <= ends)).all()
    torch.testing.assert_close((ends - starts).sum(-1), far - near, rtol=0, atol=1e-6)


def test_intervals_from_points_hand_case():
    starts, ends = intervals_from_points(torch.tensor([[1.0, 2.0, 4.0]]), torch.tensor([0.0]), torch.tensor([5.0]))
    assert starts.tolist() == [[0.0, 1.5, 3.0]] and ends.tolist() == [[1.5, 3.0, 5.0]]


# --- the renderer ---------------------------------------------------------------------------


def small_field(seed: int = 0, **overrides) -> ConditionalRadianceField:
    """A tiny fast-preset field; ``dens_bias`` raises the density everywhere."""
    dens_bias = overrides.pop("dens_bias", None)
    small = dict(code_dim=4, code_embed=4, width=16, rad_width=16, grid_res=4, grid_features=2, occ_res=32)
    cfg = dataclasses.replace(Config(), **{**small, **overrides}).validated()
    torch.manual_seed(seed)
    field = ConditionalRadianceField(cfg, 2)
    with torch.no_grad():
        field.shape_codes.normal_()
        field.color_codes.normal_()
        if dens_bias is not None:
            field.F_dens.bias.fill_(dens_bias)
    return field


def hierarchical_field(seed: int = 0) -> ConditionalRadianceField:
    cfg = dataclasses.replace(
        PRESETS["paper"], code_dim=4, code_embed=4, width=16, rad_width=16, share_layers=1, inst_layers=1,
        fuse_layers=1, n_coarse=8, n_fine=16,
    ).validated()
    torch.manual_seed(seed)
    return ConditionalRadianceField(cfg, 2)


def wide_grid_field() -> ConditionalRadianceField:
    """The fast preset's widths (64), weights perturbed off their initialization."""
    field = small_field(seed=1, width=64, rad_width=64, dens_bias=0.0)
    with torch.no_grad():
        for p in field.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(5)))
    return field


CAM = Camera(look_at((0.3, -2.0, 0.8)), 14.0, 12, 10)


def test_empty_occupancy_renders_exactly_background_with_no_samples():
    field = small_field()
    field.occupancy.zero_()
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = render_rays(field, rays_from_camera(CAM), 1, background=bg)
    assert out.n_samples == 0
    assert torch.equal(out.rgb, bg.expand(CAM.width * CAM.height, 3))
    assert torch.equal(out.opacity, torch.zeros(CAM.width * CAM.height))
    assert torch.equal(out.depth, torch.zeros(CAM.width * CAM.height))


def test_grid_samples_only_in_occupied_cells_and_tile_the_march():
    field = small_field()
    field.occupancy.zero_()
    field.occupancy[0, :, :, 16:] = True  # the upper half of the box (z > 0) for instance 0
    rays = Rays(torch.tensor([[0.1, 0.05, -2.0]]), torch.tensor([[0.0, 0.0, 1.0]]))
    s = grid_samples(field, rays, torch.tensor([0]))
    per_cell = field.cfg.steps_per_cell
    step = 1.2 / 32 / per_cell  # box side / cells / steps per cell
    n = round(16 * per_cell)  # the ray crosses 16 occupied cells (0.6 of depth)
    assert (s.points[:, 2] > 0).all() and torch.allclose(s.points[:, :2], torch.tensor([0.1, 0.05]))
    assert s.ray.numel() == n
    torch.testing.assert_close(s.t_ends - s.t_starts, torch.full((n,), step), rtol=0, atol=1e-6)
    torch.testing.assert_close(s.t_starts[1:], s.t_ends[:-1], rtol=0, atol=1e-6)
    torch.testing.assert_close(s.t_ends[-1], torch.tensor(2.6), rtol=0, atol=1e-6)  # exit of the box
    assert grid_samples(field, rays, torch.tensor([1])).ray.numel() == 0  # instance 1 is empty


def test_composite_packed_as_dense_hand_case():
    t0 = torch.tensor([0.0, 1.0, 3.0])
    samples = PackedSamples(
        ray=torch.tensor([0, 0, 1]), step=torch.tensor([0, 2, 1]), t_starts=t0, t_ends=t0 + 1.0,
        points=torch.zeros(3, 3), n_rays=2, n_steps=3,
    )
    sig = torch.tensor([math.log(2.0), math.log(2.0), math.log(4.0)])
    rgb = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    comp = composite_packed_as_dense(samples, sig, rgb, 1.0)
    # ray 0: w = [0.5, 0, 0.25]; ray 1: w = [0, 0.75, 0]
    torch.testing.assert_close(comp.rgb, torch.tensor([[0.75, 0.5, 0.25], [0.25, 0.25, 1.0]]))
    torch.testing.assert_close(comp.opacity, torch.tensor([0.75, 0.75]))
    torch.testing.assert_close(comp.depth, torch.tensor([0.5 * 0.5 + 0.25 * 1.5, 0.75 * 3.5]))


def ragged(seed: int = 0, n_rays: int = 6, dtype=torch.float32):
    """A packed batch: rays with 0…7 samples (ray 2 has none), σ spanning 0 … 1e6."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.tensor([3, 7, 0, 1, 5, 4])[:n_rays]
    ray = torch.repeat_interleave(torch.arange(n_rays), counts)
    m = int(counts.sum())
    t_starts = torch.rand(m, generator=g, dtype=dtype) * 0.1 + torch.cat([torch.arange(int(c), dtype=dtype) * 0.2 for c in counts])
    t_ends = t_starts + 0.15
    sigmas = torch.rand(m, generator=g, dtype=dtype) * 5.0
    sigmas[4], sigmas[9] = 1e6, 0.0
    rgbs = torch.rand(m, 3, generator=g, dtype=dtype)
    return ray, counts, t_starts, t_ends, sigmas, rgbs


def dense_of(counts, *values):
    """Packed → [rays, max count] (zeros after each ray's samples)."""
    n, width = len(counts), max(1, int(counts.max()))
    col = torch.cat([torch.arange(int(c)) for c in counts])
    ray = torch.repeat_interleave(torch.arange(n), counts)
    return [torch.zeros((n, width, *v.shape[1:]), dtype=v.dtype).index_put((ray, col), v) for v in values]


def test_exclusive_cumsum_packed_is_per_ray():
    ray, counts, *_ = ragged()
    x = torch.rand(len(ray), dtype=torch.float64) * 3
    got = exclusive_cumsum_packed(x, ray, len(counts))
    (dense,) = dense_of(counts, x)
    col = torch.cat([torch.arange(int(c)) for c in counts])
    torch.testing.assert_close(got, exclusive_cumsum(dense)[ray, col], rtol=0, atol=1e-12)
    # a huge optical depth in an early ray leaves later rays' sums intact
    x[0] = 1e30
    torch.testing.assert_close(exclusive_cumsum_packed(x, ray, len(counts))[counts[0]:], got[counts[0]:], rtol=0, atol=1e-9)


@pytest.mark.parametrize("background", [1.0, 0.0])
def test_composite_packed_equals_dense(background):
    ray, counts, t0, t1, sig, rgb = ragged()
    comp = composite_packed(ray, t0, t1, sig, rgb, len(counts), background)
    d0, d1, ds, dr = dense_of(counts, t0, t1, sig, rgb)
    d1 = torch.where(ds > 0, d1, d0)  # padding: zero-length intervals
    ref = composite_dense(d0, d1, ds, dr, background)
    torch.testing.assert_close(comp.rgb, ref.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(comp.opacity, ref.opacity, rtol=0, atol=1e-6)
    torch.testing.assert_close(comp.depth, ref.depth, rtol=0, atol=1e-5)
    assert comp.opacity[2] == 0 and torch.equal(comp.rgb[2], torch.full((3,), background))  # the empty ray
    assert torch.isfinite(comp.weights).all()


def test_a_nan_sample_spoils_its_own_ray_only_and_zero_length_infinite_density_is_nothing():
    """One NaN σ in ray 0 made every later ray of the batch NaN (one running sum over the
    batch); now only ray 0.  A zero-length interval of infinite σ gave inf·0 = NaN, in the dense
    and the packed layouts; it composites to nothing, as a padding row does."""
    ray = torch.tensor([0, 0, 1, 2, 2])
    t0, t1 = torch.tensor([0.0, 0.5, 0.0, 0.0, 0.5]), torch.tensor([0.5, 1.0, 1.0, 0.5, 1.0])
    sig = torch.tensor([1.0, float("nan"), 1.0, 1.0, 1.0])
    out = composite_packed(ray, t0, t1, sig, torch.full((5, 3), 0.5), 3)
    assert out.opacity[0].isnan() and torch.isfinite(out.opacity[1:]).all()
    torch.testing.assert_close(out.opacity[1:], torch.full((2,), 1 - math.exp(-1.0)), rtol=0, atol=1e-6)
    pad = torch.tensor([[0.0, 0.5, 0.5]]), torch.tensor([[0.5, 0.5, 1.0]]), torch.tensor([[1.0, float("inf"), 1.0]])
    dense = composite_dense(*pad, torch.full((1, 3, 3), 0.5))
    torch.testing.assert_close(dense.opacity, torch.tensor([1 - math.exp(-1.0)]), rtol=0, atol=1e-6)
    packed = composite_packed(torch.zeros(3, dtype=torch.long), *(t[0] for t in pad), torch.full((3, 3), 0.5), 1)
    torch.testing.assert_close(packed.opacity, dense.opacity, rtol=0, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_composite_packed_in_half_precision_is_as_close_as_dense(dtype):
    """Accumulated in bf16, a ray of 512 thin samples was 0.1 off in opacity (dense: 0.01);
    composited in float32 and returned in the inputs' dtype, packed is as close as dense."""
    g = torch.Generator().manual_seed(0)
    n, k = 20, 512
    t = torch.linspace(0, 1, k + 1)
    t0, t1 = t[:-1].repeat(n, 1), t[1:].repeat(n, 1)
    sig = torch.rand(n, k, generator=g) * 6
    rgb = torch.rand(n, k, 3, generator=g)
    ref = composite_dense(t0, t1, sig, rgb)
    ray = torch.arange(n).repeat_interleave(k)
    half = [x.to(dtype) for x in (t0, t1, sig, rgb)]
    packed = composite_packed(ray, *(x.reshape(-1) for x in half[:3]), half[3].reshape(-1, 3), n)
    dense = composite_dense(*half)
    assert packed.opacity.dtype == dtype
    err_packed = (packed.opacity.float() - ref.opacity).abs().max()
    err_dense = (dense.opacity.float() - ref.opacity).abs().max()
    assert err_packed <= max(2 * err_dense, 4 * torch.finfo(dtype).eps), (err_packed, err_dense)


def test_composite_packed_gradcheck():
    ray, counts, t0, t1, sig, rgb = ragged(dtype=torch.float64)
    sig = (sig.clamp(max=5.0) + 0.1).requires_grad_()
    rgb = rgb.requires_grad_()
    f = lambda s, c: composite_packed(ray, t0, t1, s, c, len(counts), 1.0)[:3]
    assert torch.autograd.gradcheck(f, (sig, rgb))


def brute_distortion(t0, t1, w):
    """The distortion loss by its definition, every pair: Σᵢⱼ wᵢwⱼ|mᵢ − mⱼ| + ⅓ Σᵢ wᵢ²δᵢ."""
    m = 0.5 * (t0 + t1)
    return (w[..., :, None] * w[..., None, :] * (m[..., :, None] - m[..., None, :]).abs()).sum((-1, -2)) + (w * w * (t1 - t0)).sum(-1) / 3


def test_distortion_hand_cases():
    # all the weight in one interval of length δ: w²δ/3
    t0, t1 = intervals([0.0, 0.3, 0.5, 1.0])
    w = torch.tensor([[0.0, 0.8, 0.0]], dtype=F64)
    torch.testing.assert_close(distortion_dense(t0, t1, w), torch.tensor([0.64 * 0.2 / 3], dtype=F64))
    # two halves at midpoints 0.15 and 0.75: 2·(½)(½)·0.6 + ⅓(¼·0.3 + ¼·0.5)
    w = torch.tensor([[0.5, 0.0, 0.5]], dtype=F64)
    torch.testing.assert_close(distortion_dense(t0, t1, w), torch.tensor([0.3 + (0.25 * 0.3 + 0.25 * 0.5) / 3], dtype=F64))
    # a ray of no weight costs nothing, and the loss does not depend on where the ray starts
    assert distortion_dense(t0, t1, torch.zeros(1, 3, dtype=F64)) == 0
    w = torch.tensor([[0.2, 0.3, 0.4]], dtype=F64)
    torch.testing.assert_close(distortion_dense(t0 + 7.0, t1 + 7.0, w), distortion_dense(t0, t1, w))


def test_distortion_dense_equals_every_pair():
    g = torch.Generator().manual_seed(3)
    t = torch.sort(torch.rand(5, 12, generator=g, dtype=F64), dim=-1).values
    t0, t1 = t[:, :-1], t[:, 1:]
    w = torch.rand(5, 11, generator=g, dtype=F64) / 11
    torch.testing.assert_close(distortion_dense(t0, t1, w), brute_distortion(t0, t1, w), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("split", [0, 2, 5])
def test_distortion_packed_in_stretches_equals_dense(split):
    """Packed, and packed in two stretches with the first's result carried into the second,
    equal every pair of the whole ray (the empty ray costs 0)."""
    ray, counts, t0, t1, sig, _ = ragged(dtype=F64)
    w = composite_packed(ray, t0, t1, sig, torch.zeros(len(ray), 3, dtype=F64), len(counts)).weights
    d0, d1, dw = dense_of(counts, t0, t1, w)
    expected = brute_distortion(d0, torch.where(dw > 0, d1, d0), dw)
    col = torch.cat([torch.arange(int(c)) for c in counts])
    a, b = col < split, col >= split
    first = distortion_packed(ray[a], t0[a], t1[a], w[a], len(counts))
    both = distortion_packed(ray[b], t0[b], t1[b], w[b], len(counts), None, first)
    torch.testing.assert_close(both.loss, expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(distortion_packed(ray, t0, t1, w, len(counts)).loss, expected, rtol=1e-10, atol=1e-12)
    assert both.loss[2] == 0
    torch.testing.assert_close(both.weight, torch.zeros(len(counts), dtype=F64).index_add(0, ray, w))


def test_distortion_packed_gradcheck():
    ray, counts, t0, t1, _, _ = ragged(dtype=F64)
    w = (torch.rand(len(ray), generator=torch.Generator().manual_seed(1), dtype=F64) * 0.3).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: distortion_packed(ray, t0, t1, x, len(counts)).loss, (w,))


def test_distortion_of_a_segmented_render_equals_one_march():
    """The grid march in segments carries the loss across them: the same as one segment."""
    field = small_field(dens_bias=0.5, density_scale=1.0)
    rays = rays_from_camera(CAM)
    one = render_rays(field, rays, 0, early_stop=None, distortion=True)
    segmented = render_rays(field, rays, 0, early_stop=0.0, distortion=True)
    assert one.distortion.shape == (len(rays.origins),) and float(one.distortion.detach().max()) > 0
    torch.testing.assert_close(segmented.distortion, one.distortion, rtol=1e-5, atol=1e-7)
    assert render_rays(field, rays, 0).distortion is None  # not asked: not computed


def test_a_sharper_surface_has_less_distortion():
    """The same opacity reached in a shorter stretch: lower loss (what the regularizer rewards)."""
    soft = render_rays(small_field(dens_bias=0.5, density_scale=1.0), rays_from_camera(CAM), 0, distortion=True)
    sharp = render_rays(small_field(dens_bias=0.5, density_scale=50.0), rays_from_camera(CAM), 0, distortion=True)
    hit = (soft.opacity > 0.3) & (sharp.opacity > 0.3)
    assert int(hit.sum()) > 10
    assert bool((sharp.distortion[hit] / sharp.opacity[hit] ** 2 < soft.distortion[hit] / soft.opacity[hit] ** 2).all())


def test_early_termination_matches_full_march():
    field = small_field(dens_bias=2000.0)  # σ ≈ 2000 (softplus): T falls below 1e-4 within the first segment
    rays = rays_from_camera(CAM)
    full = render_rays(field, rays, 1, early_stop=None)
    early = render_rays(field, rays, 1, early_stop=1e-4)
    assert early.n_samples < full.n_samples  # termination happened
    assert (early.rgb - full.rgb).abs().max().item() <= 1e-3
    assert (early.opacity - full.opacity).abs().max().item() <= 1e-3
    assert (early.depth - full.depth).abs().max().item() <= 1e-3


def test_grid_render_matches_one_dense_composite():
    # segments composite as T_prev·(segment): the product of segments equals one composite over the ray
    # (a density low enough that no ray's transmittance underflows to 0, which would stop it)
    field = small_field(dens_bias=0.5, density_scale=1.0)
    rays = rays_from_camera(CAM)
    one = render_rays(field, rays, 0, early_stop=None)
    segmented = render_rays(field, rays, 0, early_stop=0.0)
    torch.testing.assert_close(segmented.rgb, one.rgb, rtol=0, atol=1e-6)
    assert segmented.n_samples == one.n_samples


# The hierarchical sampler calls the network with a fixed row count per ray, so any chunking is
# bit-identical.  The grid sampler's row count depends on the chunk and CPU BLAS rounds a row
# differently for different row counts (one float32 ulp), so it is checked to 1e-6 below instead.
@pytest.mark.parametrize("sampler", ["hierarchical"])
def test_render_camera_chunking_is_bit_identical(sampler):
    field = wide_grid_field() if sampler == "grid" else hierarchical_field()
    outs = [render_camera(field, CAM, 1, chunk=c) for c in (1, 7, 64, 4096)]
    for o in outs[1:]:
        assert torch.equal(o.rgb, outs[0].rgb)
        assert torch.equal(o.depth, outs[0].depth)
        assert torch.equal(o.opacity, outs[0].opacity)
        assert o.n_samples == outs[0].n_samples


def test_render_camera_chunking_agrees_within_float32_rounding():
    field = wide_grid_field()
    outs = [render_camera(field, CAM, 1, chunk=c) for c in (1, 7, 64, 4096)]
    for o in outs[1:]:
        torch.testing.assert_close(o.rgb, outs[0].rgb, rtol=0, atol=1e-6)
        assert o.n_samples == outs[0].n_samples


def test_render_without_colour_has_the_same_depth_and_opacity_bits():
    """``colour=False`` (what a selection's lift reads) skips the bottleneck and F_rad only."""
    field = wide_grid_field()
    full, bare = render_camera(field, CAM, 1, background=0.25), render_camera(field, CAM, 1, background=0.25, colour=False)
    assert full.opacity.max() > 0.1 and full.n_samples == bare.n_samples
    assert torch.equal(bare.depth, full.depth) and torch.equal(bare.opacity, full.opacity)
    assert torch.equal(bare.rgb, (1.0 - bare.opacity)[..., None].expand(-1, -1, 3) * 0.25)  # the background alone
    assert not torch.equal(bare.rgb, full.rgb)


def test_a_camera_too_far_for_float32_samples_is_refused():
    """At 10⁶ box diagonals every float32 sample distance collapsed onto one and the view came
    out blank; up to MAX_CAMERA_REACH diagonals (a longer focal keeping the framing) it renders."""
    from crfedit.cameras import focal_from_angle
    from crfedit.renderer import MAX_CAMERA_REACH

    field = small_field()
    diagonal = float((field.aabb[3:] - field.aabb[:3]).norm())
    for reach, ok in ((0.5 * MAX_CAMERA_REACH, True), (2 * MAX_CAMERA_REACH, False)):
        cam = Camera(look_at((0.0, -reach * diagonal, 0.0)), CAM.focal * reach, CAM.width, CAM.height)
        if ok:
            assert render_camera(field, cam, 0).rgb.isfinite().all()
        else:
            with pytest.raises(CrfError, match="scene-box diagonals from the scene"):
                render_camera(field, cam, 0)
    with pytest.raises(CrfError, match="camera_angle_x 5e-324: no finite focal length"):
        focal_from_angle(5e-324, 64)
    # a field of view under MIN_FIELD_OF_VIEW sees too little: refused as a dataset split is
    from crfedit.cameras import MIN_FIELD_OF_VIEW

    for angle, ok in ((1.5 * MIN_FIELD_OF_VIEW, True), (0.5 * MIN_FIELD_OF_VIEW, False)):
        cam = Camera(CAM.c2w, focal_from_angle(angle, CAM.width), CAM.width, CAM.height)
        if ok:
            render_camera(field, cam, 0)
        else:
            with pytest.raises(CrfError, match=r"^camera: a 0\.000286° field of view, too narrow to see an object"):
                render_camera(field, cam, 0)


def test_render_camera_shapes():
    out = render_camera(small_field(), CAM, 0, chunk=50)
    assert out.rgb.shape == (10, 12, 3) and out.depth.shape == (10, 12) and out.opacity.shape == (10, 12)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float64])
def test_a_field_of_another_precision_is_one_line(dtype):
    """`field.half()` or `.double()` rendered to a raw RuntimeError of mixed dtypes; float64
    rays too.  Both are one line; rays of float16 compute in float32 as before."""
    import copy

    field = copy.deepcopy(small_field()).to(dtype)
    with pytest.raises(CrfError, match=f"the field's weights are {str(dtype)[6:]}; crfedit renders float32 fields"):
        render_camera(field, CAM, 0)
    rays = rays_from_camera(CAM)
    with pytest.raises(CrfError, match="rays of float64"):
        render_rays(small_field(), Rays(rays.origins.double(), rays.directions.double()), 0)
    assert render_rays(small_field(), Rays(rays.origins.half(), rays.directions.half()), 0).rgb.dtype == torch.float32
    part = copy.deepcopy(small_field())
    part.F_rad.to(dtype)  # one module cast alone
    with pytest.raises(CrfError, match=f"the field's weights are {str(dtype)[6:]}"):
        render_camera(part, CAM, 0)


def test_hierarchical_runs_and_is_deterministic_without_generator():
    field = hierarchical_field()
    rays = rays_from_camera(CAM)
    a = render_rays(field, rays, 1)
    b = render_rays(field, rays, 1)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and torch.equal(a.coarse_rgb, b.coarse_rgb)
    _, _, hit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)
    assert a.n_samples == int(hit.sum()) * (8 + 8 + 16)  # coarse, then coarse + fine on the fine net
    assert torch.equal(a.rgb[~hit], torch.ones(int((~hit).sum()), 3))  # misses are background
    assert ((a.rgb >= 0) & (a.rgb <= 1)).all() and a.coarse_rgb.shape == a.rgb.shape
    c = render_rays(field, rays, 1, generator=torch.Generator().manual_seed(0))
    d = render_rays(field, rays, 1, generator=torch.Generator().manual_seed(0))
    assert torch.equal(c.rgb, d.rgb) and not torch.equal(c.rgb, a.rgb)
