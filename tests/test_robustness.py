"""Robustness of compositing and rendering at the edges: empty and saturated rays, zero and huge
intervals, near = far, misses, one sample, one ray, bfloat16 autocast.

Run ``python tests/test_robustness.py`` to print the table of docs/robustness.md (measured values).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from crfedit.cameras import Rays
from crfedit.config import PRESETS, Config
from crfedit.field import ConditionalRadianceField
from crfedit.renderer import render_rays
from crfedit.rendering import composite_dense
from crfedit.sampling import intervals_from_points, ray_aabb_intersect, stratified_samples


# --- compositing cases (float32, the dtype rendering uses) ----------------------------------

Case = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]  # t0, t1, σ, rgb, bg


def uniform(n: int, length: float = 2.0, rays: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    e = torch.linspace(0.0, length, n + 1).expand(rays, -1)
    return e[:, :-1].contiguous(), e[:, 1:].contiguous()


def colours(rays: int, n: int) -> torch.Tensor:
    return torch.rand(rays, n, 3, generator=torch.Generator().manual_seed(n))


BG = torch.tensor([0.2, 0.5, 0.9])


def case_zero_density() -> Case:
    t0, t1 = uniform(16)
    return t0, t1, torch.zeros(3, 16), colours(3, 16), BG


def case_huge_density() -> Case:
    t0, t1 = uniform(16)
    return t0, t1, torch.full((3, 16), 1e8), colours(3, 16), BG


def case_huge_density_after_thin() -> Case:
    t0, t1 = uniform(16)
    sig = torch.full((3, 16), 0.5)
    sig[:, 8:] = 1e8  # a surface half-way
    return t0, t1, sig, colours(3, 16), BG


def case_zero_intervals() -> Case:
    t = torch.full((3, 16), 1.5)
    return t, t.clone(), torch.full((3, 16), 10.0), colours(3, 16), BG


def case_last_interval_1e10() -> Case:
    t0, t1 = uniform(16)
    t1[:, -1] = 1e10  # NeRF's "infinite" last interval
    return t0, t1, torch.full((3, 16), 0.5), colours(3, 16), BG


def case_empty_with_last_interval_1e10() -> Case:
    t0, t1, sig, rgb, bg = case_last_interval_1e10()
    return t0, t1, torch.zeros_like(sig), rgb, bg


def case_near_equals_far() -> Case:
    near = far = torch.full((3,), 1.25)
    t = stratified_samples(near, far, 16)
    t0, t1 = intervals_from_points(t, near, far)
    return t0, t1, torch.full((3, 16), 10.0), colours(3, 16), BG


def case_missed_rays() -> Case:
    o = torch.tensor([[0.0, 3.0, -3.0], [5.0, 5.0, 5.0], [0.0, 0.0, 3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    near, far, hit = ray_aabb_intersect(o, d, torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]))
    assert not hit.any()
    t = stratified_samples(near, far, 16)
    t0, t1 = intervals_from_points(t, near, far)
    return t0, t1, torch.full((3, 16), 10.0), colours(3, 16), BG


def case_single_sample() -> Case:
    t0, t1 = uniform(1)
    return t0, t1, torch.tensor([[0.0], [0.7], [1e8]]), colours(3, 1), BG


def case_one_ray() -> Case:
    t0, t1 = uniform(16, rays=1)
    return t0, t1, torch.linspace(0.0, 5.0, 16)[None], colours(1, 16), BG


COMPOSITE_CASES: dict[str, Callable[[], Case]] = {
    "σ = 0 along the whole ray": case_zero_density,
    "σ = 1e8 everywhere": case_huge_density,
    "σ = 1e8 after σ = 0.5 (a surface)": case_huge_density_after_thin,
    "δ = 0 (all intervals empty)": case_zero_intervals,
    "last interval 1e10": case_last_interval_1e10,
    "σ = 0 with a last interval of 1e10": case_empty_with_last_interval_1e10,
    "near = far": case_near_equals_far,
    "rays that miss the box": case_missed_rays,
    "one sample per ray": case_single_sample,
    "a batch of one ray": case_one_ray,
}


def composite_with_grads(case: Case) -> tuple:
    """Composite, back-propagate rgb.sum() + opacity.sum(); returns (comp, ∂σ, ∂rgb, ∂bg)."""
    t0, t1, sig, rgb, bg = case
    sig, rgb, bg = (v.clone().requires_grad_() for v in (sig, rgb, bg))
    comp = composite_dense(t0, t1, sig, rgb, bg)
    (comp.rgb.sum() + comp.opacity.sum()).backward()
    return comp, sig.grad, rgb.grad, bg.grad


def finite(*tensors: torch.Tensor) -> bool:
    return all(bool(t.isfinite().all()) for t in tensors)


@pytest.mark.parametrize("name", COMPOSITE_CASES)
def test_compositing_edge_case_is_finite_with_finite_gradients(name):
    case = COMPOSITE_CASES[name]()
    comp, g_sig, g_rgb, g_bg = composite_with_grads(case)
    assert finite(comp.rgb, comp.depth, comp.opacity, comp.weights)
    assert finite(g_sig, g_rgb, g_bg)
    assert (comp.weights >= 0).all() and (comp.opacity >= 0).all()


@pytest.mark.parametrize(
    "name",
    ["σ = 0 along the whole ray", "σ = 0 with a last interval of 1e10", "δ = 0 (all intervals empty)", "near = far",
     "rays that miss the box"],
)
def test_empty_rays_are_exactly_background(name):
    comp, g_sig, _, g_bg = composite_with_grads(COMPOSITE_CASES[name]())
    assert torch.equal(comp.rgb, BG.expand_as(comp.rgb)) and torch.equal(comp.opacity, torch.zeros_like(comp.opacity))
    assert torch.equal(g_bg, torch.full((3,), float(comp.rgb.shape[0])))  # ∂(Σ rgb)/∂bg = number of rays


def test_zero_density_gradient_is_the_interval_length():
    # ∂(Σrgb + opacity)/∂σⱼ at σ = 0 is δⱼ·(Σ_c (cⱼ - bg) + 1): the empty start of training gets gradient
    t0, t1, sig, rgb, bg = case_zero_density()
    _, g_sig, _, _ = composite_with_grads((t0, t1, sig, rgb, bg))
    expected = (t1 - t0) * ((rgb - bg).sum(-1) + 1.0)
    torch.testing.assert_close(g_sig, expected, rtol=1e-5, atol=1e-6)


def test_huge_density_is_opaque_at_the_first_sample():
    comp, g_sig, _, _ = composite_with_grads(case_huge_density())
    assert torch.equal(comp.opacity, torch.ones(3))
    torch.testing.assert_close(comp.rgb, colours(3, 16)[:, 0])
    assert torch.equal(g_sig, torch.zeros_like(g_sig))  # saturated: e^(-σδ) underflows to 0


@pytest.mark.parametrize("name", ["σ = 1e8 after σ = 0.5 (a surface)", "last interval 1e10"])
def test_huge_optical_depth_after_a_thin_prefix_keeps_weights_a_partition(name):
    comp, *_ = composite_with_grads(COMPOSITE_CASES[name]())
    assert (comp.weights.sum(-1) <= 1.0 + 1e-6).all()
    assert (comp.opacity <= 1.0 + 1e-6).all()


# --- properties -------------------------------------------------------------------------------

sigma_st = st.one_of(st.just(0.0), st.floats(-6.0, 8.0).map(lambda e: 10.0**e))


@st.composite
def rays_st(draw, max_delta_exp: float):
    n = draw(st.integers(1, 12))
    deltas = draw(st.lists(st.one_of(st.just(0.0), st.floats(-4.0, 0.0).map(lambda e: 10.0**e)), min_size=n, max_size=n))
    if max_delta_exp > 0 and draw(st.booleans()):
        deltas[-1] = 10.0**max_delta_exp
    sigmas = draw(st.lists(sigma_st, min_size=n, max_size=n))
    rgbs = draw(st.lists(st.tuples(*[st.floats(0.0, 1.0)] * 3), min_size=n, max_size=n))
    bg = draw(st.tuples(*[st.floats(0.0, 1.0)] * 3))
    start = draw(st.floats(0.0, 10.0))
    return start, deltas, sigmas, rgbs, bg


def as_case(drawn, dtype) -> Case:
    start, deltas, sigmas, rgbs, bg = drawn
    edges = start + torch.cat([torch.zeros(1, dtype=torch.float64), torch.tensor(deltas, dtype=torch.float64).cumsum(0)])
    t0, t1 = edges[:-1][None].to(dtype), edges[1:][None].to(dtype)
    return t0, t1, torch.tensor([sigmas], dtype=dtype), torch.tensor([rgbs], dtype=dtype), torch.tensor(bg, dtype=dtype)


@settings(deadline=None, max_examples=50)
@given(rays_st(max_delta_exp=0.0))
def test_property_weights_partition_and_rgb_is_a_convex_mix(drawn):
    # float64, σδ ≤ 1e8: opacity ∈ [0, 1], w ≥ 0, Σw ≤ 1, rgb between the sample colours and bg.
    # (The cumsum(τ) - τ cancellation leaves up to ulp(1e8) ≈ 1.5e-8 here.)
    case = as_case(drawn, torch.float64)
    comp, g_sig, g_rgb, g_bg = composite_with_grads(case)
    assert finite(comp.rgb, comp.depth, comp.opacity, g_sig, g_rgb, g_bg)
    assert (comp.weights >= 0).all()
    assert 0.0 <= comp.opacity.item() <= 1.0 + 1e-6
    assert comp.weights.sum().item() <= 1.0 + 1e-6
    colours_and_bg = torch.cat([case[3][0], case[4][None]])
    lo, hi = colours_and_bg.amin(0), colours_and_bg.amax(0)
    assert ((comp.rgb[0] >= lo - 1e-6) & (comp.rgb[0] <= hi + 1e-6)).all()


@settings(deadline=None, max_examples=50)
@given(rays_st(max_delta_exp=10.0))
def test_property_float32_full_range_stays_finite(drawn):
    # σ up to 1e8, δ up to 1 and a possible last interval of 1e10, in float32
    comp, g_sig, g_rgb, g_bg = composite_with_grads(as_case(drawn, torch.float32))
    assert finite(comp.rgb, comp.depth, comp.opacity, comp.weights, g_sig, g_rgb, g_bg)
    assert (comp.weights >= 0).all() and (comp.opacity >= 0).all()


# --- the renderer -----------------------------------------------------------------------------


def grid_field(dens_bias: float | None = None) -> ConditionalRadianceField:
    cfg = dataclasses.replace(
        Config(), code_dim=4, code_embed=4, width=16, rad_width=16, grid_res=4, grid_features=2, occ_res=16
    ).validated()
    torch.manual_seed(0)
    field = ConditionalRadianceField(cfg, 2)
    if dens_bias is not None:
        with torch.no_grad():
            field.F_dens.bias.fill_(dens_bias)
    return field


def hierarchical_field(n_coarse: int = 8, n_fine: int = 8) -> ConditionalRadianceField:
    cfg = dataclasses.replace(
        PRESETS["paper"], code_dim=4, code_embed=4, width=16, rad_width=16, share_layers=1, inst_layers=1,
        fuse_layers=1, n_coarse=n_coarse, n_fine=n_fine,
    ).validated()
    torch.manual_seed(0)
    return ConditionalRadianceField(cfg, 2)


HIT = Rays(torch.tensor([[0.05, -2.0, 0.1], [2.0, 0.1, -0.2], [0.3, 0.2, 2.0]]),
           torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
MISS = Rays(torch.tensor([[0.0, -2.0, 1.5], [3.0, 3.0, 3.0]]), torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
ONE = Rays(HIT.origins[:1], HIT.directions[:1])


def render_with_grads(field, rays: Rays, autocast: bool = False, **kwargs):
    """render_rays, then back-propagate rgb.sum() into the field; returns (out, max |∂param|)."""
    field.zero_grad()
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out = render_rays(field, rays, 1, **kwargs)
    grads = []
    if out.rgb.requires_grad:
        out.rgb.sum().backward()
        grads = [p.grad for p in field.parameters() if p.grad is not None]
    g_max = max((float(g.abs().max()) for g in grads), default=0.0)
    assert all(bool(g.isfinite().all()) for g in grads)
    return out, g_max


RENDER_CASES: dict[str, Callable[[], tuple]] = {
    "grid: rays that miss the box": lambda: render_with_grads(grid_field(), MISS),
    "grid: a batch of one ray": lambda: render_with_grads(grid_field(), ONE),
    "grid: σ at the e¹⁵ cap everywhere": lambda: render_with_grads(grid_field(dens_bias=30.0), HIT),
    "grid: bfloat16 autocast": lambda: render_with_grads(grid_field(dens_bias=1.0), HIT, autocast=True),
    "hierarchical: rays that miss the box": lambda: render_with_grads(hierarchical_field(), MISS),
    "hierarchical: a batch of one ray": lambda: render_with_grads(hierarchical_field(), ONE),
    "hierarchical: one sample per ray": lambda: render_with_grads(hierarchical_field(1, 0), HIT),
    "hierarchical: bfloat16 autocast": lambda: render_with_grads(hierarchical_field(), HIT, autocast=True),
}


@pytest.mark.parametrize("name", RENDER_CASES)
def test_render_edge_case_is_finite_with_finite_gradients(name):
    out, _ = RENDER_CASES[name]()
    assert finite(out.rgb, out.depth, out.opacity)
    assert ((out.opacity >= 0) & (out.opacity <= 1 + 1e-6)).all()
    assert ((out.rgb >= -1e-6) & (out.rgb <= 1 + 1e-6)).all()


@pytest.mark.parametrize("field_fn", [grid_field, hierarchical_field], ids=["grid", "hierarchical"])
def test_missed_rays_render_exactly_background_without_samples(field_fn):
    bg = torch.tensor([0.25, 0.5, 0.75])
    out = render_rays(field_fn(), MISS, 0, background=bg)
    assert out.n_samples == 0
    assert torch.equal(out.rgb, bg.expand(2, 3)) and torch.equal(out.opacity, torch.zeros(2))


def test_one_ray_renders_like_the_same_ray_in_a_batch():
    field = grid_field(dens_bias=1.0)
    torch.testing.assert_close(render_rays(field, ONE, 1).rgb, render_rays(field, HIT, 1).rgb[:1], rtol=0, atol=1e-6)


@pytest.mark.parametrize("field_fn", [lambda: grid_field(dens_bias=1.0), hierarchical_field], ids=["grid", "hierarchical"])
def test_bfloat16_autocast_stays_close_to_float32(field_fn):
    field = field_fn()
    full = render_rays(field, HIT, 1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        half = render_rays(field, HIT, 1)
    assert half.rgb.dtype == torch.float32 and finite(half.rgb, half.depth, half.opacity)
    assert (half.rgb - full.rgb).abs().max().item() < 0.05
    assert (half.opacity - full.opacity).abs().max().item() < 0.05


# --- the measured table of docs/robustness.md ---------------------------------------------------


def robustness_table() -> str:
    rows = ["| case | outputs finite | grads finite | max Σw | max \\|∂/∂σ\\| | max \\|∂/∂rgb\\| |", "|---|---|---|---|---|---|"]
    for name, make in COMPOSITE_CASES.items():
        comp, g_sig, g_rgb, g_bg = composite_with_grads(make())
        rows.append(
            f"| {name} | {finite(comp.rgb, comp.depth, comp.opacity)} | {finite(g_sig, g_rgb, g_bg)} "
            f"| {comp.weights.sum(-1).max().item():.4g} | {g_sig.abs().max().item():.3g} | {g_rgb.abs().max().item():.3g} |"
        )
    rows += ["", "| render case | outputs finite | grads finite | samples | max opacity | max \\|∂param\\| |",
             "|---|---|---|---|---|---|"]
    for name, make in RENDER_CASES.items():
        try:
            out, g_max = make()
            grads_ok = True
        except AssertionError:
            out, g_max, grads_ok = None, math.nan, False
        rows.append(
            f"| {name} | {finite(out.rgb, out.depth, out.opacity)} | {grads_ok} | {out.n_samples} "
            f"| {out.opacity.max().item():.4g} | {g_max:.3g} |"
        )
    return "\n".join(rows)


if __name__ == "__main__":
    torch.set_num_threads(1)
    print(robustness_table())
