"""The conditional radiance field: the paper's module names, parameter shapes, where the codes
enter (σ never sees the view direction or the colour code), ablation variants, the activation."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from torch import nn

from crfedit.cameras import Rays
from crfedit.config import ARCHS, PRESETS, Config
from crfedit.field import (
    ConditionalRadianceField,
    FieldNet,
    density_activation,
    linear_with_codes,
    positional_encoding,
    run_mlp,
)
from crfedit.renderer import field_at_samples, render_rays
from crfedit.sampling import PackedSamples

PAPER_MODULES = {"F_share", "F_inst", "F_fuse", "F_dens", "bottleneck", "F_rad"}


def tiny(arch: str = "ours", **overrides) -> Config:
    small = dict(arch=arch, code_dim=4, code_embed=5, width=16, rad_width=12, grid_res=4, grid_features=2, occ_res=8)
    return dataclasses.replace(Config(), **{**small, **overrides}).validated()


def make_field(cfg: Config, n: int = 3, seed: int = 0) -> ConditionalRadianceField:
    torch.manual_seed(seed)
    field = ConditionalRadianceField(cfg, n)
    with torch.no_grad():  # distinct codes and a non-trivial feature grid
        field.shape_codes.normal_()
        field.color_codes.normal_()
        for net in (field, field.coarse):
            if net is not None and net.F_share.grid is not None:
                net.F_share.grid.normal_()
    return field


def points(m: int = 40, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(m, 3, generator=g) * 2 - 1
    d = torch.randn(m, 3, generator=g)
    return x, d / d.norm(dim=-1, keepdim=True), torch.randint(0, 3, (m,), generator=g)


# --- names and shapes -----------------------------------------------------------------------


def fieldnet_shapes(pos: int, grid: tuple | None, d_enc: int, w: int, layers: dict, rad_w: int) -> dict:
    """Expected parameter shapes of one FieldNet, with code_dim = code_embed = 32, bottleneck 8."""
    def mlp(prefix, n_in, width, n):
        out = {}
        for i in range(n):
            out[f"{prefix}.{2 * i}.weight"] = (width, n_in if i == 0 else width)
            out[f"{prefix}.{2 * i}.bias"] = (width,)
        return out

    enc = pos + (grid[1] if grid else 0)
    shapes = {**({"F_share.grid": grid} if grid else {})}
    shapes |= mlp("F_share.mlp", enc, w, layers["share"])
    shapes |= {"F_inst.code.linear.weight": (32, 32), "F_inst.code.linear.bias": (32,)}
    shapes |= mlp("F_inst.mlp", enc + 32, w, layers["inst"])
    shapes |= mlp("F_fuse", w + pos + 32, w, layers["fuse"])
    shapes |= {"F_dens.weight": (1, w), "F_dens.bias": (1,), "bottleneck.weight": (8, w), "bottleneck.bias": (8,)}
    shapes |= {"F_rad.code.linear.weight": (32, 32), "F_rad.code.linear.bias": (32,)}
    shapes |= mlp("F_rad.mlp", 8 + d_enc + 32, rad_w, 1)
    shapes |= {"F_rad.out.weight": (3, rad_w), "F_rad.out.bias": (3,)}
    return shapes


def test_fast_preset_names_and_shapes():
    field = ConditionalRadianceField(PRESETS["fast"], 3)
    assert {name for name, _ in field.named_children()} == PAPER_MODULES | {"F_part"}
    # pe_x = 4 → 3·9 = 27, feature grid 8 × 48³; pe_d = 2 → 3·5 = 15; the part head 64 → 16
    expected = fieldnet_shapes(27, (1, 8, 48, 48, 48), 15, 64, {"share": 1, "inst": 2, "fuse": 1}, 64)
    expected |= {"shape_codes": (3, 32), "color_codes": (3, 32), "F_part.weight": (16, 64), "F_part.bias": (16,)}
    assert {n: tuple(p.shape) for n, p in field.named_parameters()} == expected
    assert {n: tuple(b.shape) for n, b in field.named_buffers()} == {"aabb": (6,), "occupancy": (3, 64, 64, 64)}
    assert field.occupancy.dtype == torch.bool and field.coarse is None


def test_paper_preset_names_and_shapes():
    field = ConditionalRadianceField(PRESETS["paper"], 3)
    assert {name for name, _ in field.named_children()} == PAPER_MODULES | {"coarse"}
    assert {name for name, _ in field.coarse.named_children()} == PAPER_MODULES
    # pe_x = 10 → 63, no grid; pe_d = 4 → 27; 4 + 4 + 4 layers of 256, F_rad one layer of 128
    net = fieldnet_shapes(63, None, 27, 256, {"share": 4, "inst": 4, "fuse": 4}, 128)
    expected = net | {f"coarse.{n}": s for n, s in net.items()} | {"shape_codes": (3, 32), "color_codes": (3, 32)}
    assert {n: tuple(p.shape) for n, p in field.named_parameters()} == expected


# --- where the codes and the direction enter ----------------------------------------------


def packed(x: torch.Tensor, idx: torch.Tensor) -> PackedSamples:
    m = len(x)
    return PackedSamples(torch.arange(m), torch.zeros(m, dtype=torch.long), torch.zeros(m), torch.ones(m), x, m, 1)


def test_sigma_ignores_view_direction_and_color_code():
    field = make_field(tiny())
    x, d, idx = points()
    world = (x + 1) / 2 * (field.aabb[3:] - field.aabb[:3]) + field.aabb[:3]
    sig, rgb = field_at_samples(field, field, packed(world, idx), Rays(torch.zeros_like(x), d), idx)
    other_d = torch.roll(d, 1, dims=0)
    sig_d, rgb_d = field_at_samples(field, field, packed(world, idx), Rays(torch.zeros_like(x), other_d), idx)
    with torch.no_grad():
        field.color_codes.mul_(-3.0)
    sig_c, rgb_c = field_at_samples(field, field, packed(world, idx), Rays(torch.zeros_like(x), d), idx)
    assert torch.equal(sig_d, sig) and torch.equal(sig_c, sig)
    assert not torch.allclose(rgb_d, rgb) and not torch.allclose(rgb_c, rgb)


def test_shape_code_reaches_rgb_only_through_the_bottleneck():
    field = make_field(tiny())
    x, d, idx = points()
    s, c = field.code_tables()
    raw, feat = field.density_and_features(x, s, idx)
    rgb = field.radiance_from_codes(feat, d, c, idx)
    s2 = s.flip(0).detach() * 2.0
    raw2, feat2 = field.density_and_features(x, s2, idx)
    assert not torch.allclose(raw2, raw) and not torch.allclose(field.radiance_from_codes(feat2, d, c, idx), rgb)
    # freeze the bottleneck's output: the shape code then has no way left into rgb
    handle = field.bottleneck.register_forward_hook(lambda mod, inp, out: feat)
    try:
        _, frozen = field.density_and_features(x, s2, idx)
        assert torch.equal(field.radiance_from_codes(frozen, d, c, idx), rgb)
    finally:
        handle.remove()
    assert field.F_rad.mlp[0].in_features == 8 + 3 * (1 + 2 * field.cfg.pe_d) + field.cfg.code_embed


def test_color_code_selects_each_instance_rgb():
    field = make_field(tiny())
    x, d, _ = points()
    zero = torch.zeros(len(x), dtype=torch.long)
    s, c = field.code_tables()
    _, feat = field.density_and_features(x, s, zero)
    rgb = field.radiance_from_codes(feat, d, c, zero)
    swapped = c.detach().clone()
    swapped[0] = c[2]  # instance 0 takes instance 2's colour code: its rgb becomes instance 2's
    torch.testing.assert_close(field.radiance_from_codes(feat, d, swapped, zero), field.radiance_from_codes(feat, d, c, zero + 2))
    assert not torch.allclose(field.radiance_from_codes(feat, d, swapped, zero), rgb)
    # a single code row (idx None) is the same as that row selected for every point
    torch.testing.assert_close(field.radiance_from_codes(feat, d, c[:1], None), rgb, rtol=0, atol=1e-6)


def test_linear_with_codes_equals_the_concatenated_layer():
    g = torch.Generator().manual_seed(0)
    layer = nn.Linear(5 + 3, 7)
    x, codes = torch.randn(10, 5, generator=g), torch.randn(4, 3, generator=g)
    idx = torch.randint(0, 4, (10,), generator=g)
    expected = layer(torch.cat([x, codes[idx]], dim=-1))
    torch.testing.assert_close(linear_with_codes(layer, x, codes, idx), expected, rtol=0, atol=1e-6)
    single = layer(torch.cat([x, codes[2:3].expand(10, 3)], dim=-1))
    torch.testing.assert_close(linear_with_codes(layer, x, codes[2:3], None), single, rtol=0, atol=1e-6)
    plain = nn.Linear(5, 7)
    assert torch.equal(linear_with_codes(plain, x, None, None), plain(x))


def test_run_mlp_equals_the_sequential_on_concatenated_input():
    torch.manual_seed(0)
    seq = nn.Sequential(nn.Linear(5 + 3, 6), nn.ReLU(), nn.Linear(6, 6), nn.ReLU())
    x, codes, idx = torch.randn(9, 5), torch.randn(2, 3), torch.tensor([0, 1] * 4 + [1])
    torch.testing.assert_close(run_mlp(seq, x, codes, idx), seq(torch.cat([x, codes[idx]], -1)), rtol=0, atol=1e-6)


# --- encodings -------------------------------------------------------------------------------


def test_positional_encoding_hand_values():
    enc = positional_encoding(torch.tensor([[0.25, 0.5]], dtype=torch.float64), 2)
    s, c = math.sin, math.cos
    pi = math.pi
    expected = [0.25, 0.5, s(pi / 4), s(pi / 2), s(pi / 2), s(pi), c(pi / 4), c(pi / 2), c(pi / 2), c(pi)]
    torch.testing.assert_close(enc, torch.tensor([expected], dtype=torch.float64), rtol=0, atol=1e-15)
    x = torch.rand(4, 3)
    assert torch.equal(positional_encoding(x, 0), x)


def test_feature_grid_axes_are_x_width_y_height_z_depth():
    field = ConditionalRadianceField(tiny(grid_res=3, grid_features=1, pe_x=0), 1)
    d, h, w = torch.meshgrid(torch.arange(3.0), torch.arange(3.0), torch.arange(3.0), indexing="ij")
    with torch.no_grad():
        field.F_share.grid.copy_((100 * d + 10 * h + w)[None, None])
    x = torch.tensor([[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0], [0.0, 0.0, 0.0]])
    enc = field.F_share.encode(x)
    assert torch.equal(enc[:, :3], x)
    torch.testing.assert_close(enc[:, 3], torch.tensor([0.0, 2.0, 20.0, 200.0, 111.0]))


# --- ablations -------------------------------------------------------------------------------


@pytest.mark.parametrize("arch", ARCHS)
def test_every_ablation_builds_and_renders(arch):
    field = make_field(tiny(arch))
    x, d, idx = points()
    s, c = field.code_tables()
    raw, feat = field.density_and_features(x, s, idx)
    rgb = field.radiance_from_codes(feat, d, c, idx)
    assert raw.shape == (40,) and feat.shape == (40, 8) and rgb.shape == (40, 3)
    assert raw.isfinite().all() and ((rgb >= 0) & (rgb <= 1)).all()
    rays = Rays(torch.tensor([[0.0, -2.0, 0.1], [2.0, 0.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
    out = render_rays(field, rays, torch.tensor([0, 2]))
    assert out.rgb.shape == (2, 3) and out.rgb.isfinite().all() and out.n_samples > 0
    names = {n for n, _ in field.named_children()} - {"F_part"}  # the part head: not the paper's, every arch has it
    assert names == (PAPER_MODULES - {"F_inst"} if arch == "nerf" else PAPER_MODULES)
    assert (field.F_part is None) == (field.cfg.part_dim == 0)
    assert (field.F_share.mlp is None) == (arch in ("separate", "single"))


def test_nerf_ablation_ignores_codes():
    field = make_field(tiny("nerf"))
    x, d, idx = points()
    assert field.code_tables() == (None, None)
    raw, feat = field.density_and_features(x, None, idx)
    rgb = field.radiance_from_codes(feat, d, None, idx)
    raw0, feat0 = field.density_and_features(x, None, torch.zeros_like(idx))
    assert torch.equal(raw, raw0) and torch.equal(field.radiance_from_codes(feat0, d, None, None), rgb)


def test_single_ablation_uses_the_shape_code_for_color():
    field = make_field(tiny("single"))
    s, c = field.code_tables()
    assert c is s is field.shape_codes
    x, d, idx = points()
    raw, feat = field.density_and_features(x, s, idx)
    rgb = field.radiance_from_codes(feat, d, c, idx)
    with torch.no_grad():
        field.color_codes.mul_(5.0)  # unused by this variant
    s2, c2 = field.code_tables()
    assert torch.equal(field.radiance_from_codes(*field.density_and_features(x, s2, idx)[1:], d, c2, idx), rgb)


def test_separate_ablation_has_no_shared_branch():
    field = make_field(tiny("separate"))
    assert field.F_share.mlp is None and not any(n.startswith("F_share.mlp") for n, _ in field.named_parameters())
    assert field.code_tables()[1] is field.color_codes


def test_coarse_net_is_a_twin_sharing_the_codes():
    cfg = dataclasses.replace(PRESETS["paper"], code_dim=4, code_embed=5, width=16, rad_width=12,
                              share_layers=1, inst_layers=1, fuse_layers=1)
    field = ConditionalRadianceField(cfg, 2)
    assert isinstance(field.coarse, FieldNet) and not isinstance(field.coarse, ConditionalRadianceField)
    fine = {n: p.shape for n, p in field.named_parameters() if not n.startswith("coarse.") and "codes" not in n}
    assert {n: p.shape for n, p in field.coarse.named_parameters()} == fine


# --- density activation ------------------------------------------------------------------------


def test_density_activation_values_and_gradient_above_the_cap():
    raw = torch.tensor([0.0, 1.0, 15.0, 20.0, 1e4, -1e4], requires_grad=True)
    sigma = density_activation(raw)
    cap = math.exp(15.0)
    torch.testing.assert_close(sigma, torch.tensor([1.0, math.e, cap, cap, cap, 0.0]))
    sigma.sum().backward()
    # d/dx exp(min(x, 15)) would be 0 above the cap; the truncated exp passes exp(min(x, 15))
    torch.testing.assert_close(raw.grad, torch.tensor([1.0, math.e, cap, cap, cap, 0.0]))
    assert raw.grad.isfinite().all() and (raw.grad[3:5] > 0).all()


def test_density_activation_gradcheck_below_the_cap():
    raw = torch.linspace(-5.0, 14.0, 11, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(density_activation, (raw,))


def test_density_scale_multiplies_sigma_and_old_files_keep_scale_one():
    cfg = tiny()
    field = make_field(cfg)
    raw = torch.linspace(-5, 5, 11)
    assert cfg.density_scale == 50.0
    torch.testing.assert_close(field.sigma(raw), 50.0 * torch.nn.functional.softplus(raw))
    stored = json.loads(cfg.to_json())
    del stored["density_scale"]  # a model file written before the key existed
    assert Config.from_json(json.dumps(stored)).density_scale == 1.0
    assert Config.from_json(cfg.to_json()).density_scale == 50.0


def test_single_instance_path_equals_per_point_selection():
    """A rendered view passes its instance as an int (codes enter as biases); batches of mixed
    instances select code rows per point.  Both give the same σ and rgb."""
    field = make_field(tiny())
    g = torch.Generator().manual_seed(1)
    rays = Rays(torch.zeros(64, 3) - 1.5, torch.nn.functional.normalize(torch.ones(64, 3) + 0.1 * torch.randn(64, 3, generator=g), dim=-1))
    for k in range(field.n_instances):
        a = render_rays(field, rays, k)
        b = render_rays(field, rays, torch.full((64,), k))
        torch.testing.assert_close(a.rgb, b.rgb, atol=1e-6, rtol=0)
        torch.testing.assert_close(a.opacity, b.opacity, atol=1e-6, rtol=0)
    assert float(render_rays(field, rays, 0).opacity.detach().max()) > 0.01  # the rays do cross the field


# --- the instance-level interface and old model files ---------------------------------------


@pytest.mark.parametrize("arch", ARCHS)
def test_density_features_radiance_forward_equal_the_stages(arch):
    """``density``/``features``/``radiance``/``forward`` take an instance (an int, or one per
    point) and give bit for bit what the table-level stages give with that instance's codes."""
    field = make_field(tiny(arch, sampler="hierarchical", n_coarse=4, n_fine=4))
    x, d, idx = points()
    s, c = field.code_tables()
    for net in (field, field.coarse):
        raw, feat = net.density_and_features(x, s, idx)
        sigma, rgb = net.sigma(raw), net.radiance_from_codes(feat, d, c, idx)
        torch.testing.assert_close(field.density(x, idx, net), sigma, rtol=0, atol=1e-6)
        torch.testing.assert_close(field.features(x, idx, net), feat, rtol=0, atol=1e-6)
        torch.testing.assert_close(field.radiance(feat, d, idx, net), rgb, rtol=0, atol=1e-6)
        for k in range(field.n_instances):
            rows = idx == k
            sigma_k, rgb_k = field(x[rows], d[rows], k, net)
            torch.testing.assert_close(sigma_k, sigma[rows], rtol=0, atol=1e-5)
            torch.testing.assert_close(rgb_k, rgb[rows], rtol=0, atol=1e-6)
            assert torch.equal(field.density(x[rows], k, net), sigma_k)
    # forward is the renderer's evaluation at the same points
    world = (x + 1) / 2 * (field.aabb[3:] - field.aabb[:3]) + field.aabb[:3]
    sig_r, rgb_r = field_at_samples(field, field, packed(world, idx), Rays(torch.zeros_like(x), d), idx)
    sig_f, rgb_f = field(field.normalize(world), d, idx)
    assert torch.equal(sig_f, sig_r) and torch.equal(rgb_f, rgb_r)


def test_f_inst_and_f_rad_are_named_parts():
    field = make_field(tiny())
    assert [n for n, _ in field.F_inst.named_children()] == ["code", "mlp"]
    assert [n for n, _ in field.F_rad.named_children()] == ["code", "mlp", "out"]
    assert field.F_rad.mlp[0].in_features == 8 + 3 * (1 + 2 * field.cfg.pe_d) + field.cfg.code_embed


OLD_FORMAT_KEYS = [
    "F_dens.bias", "F_dens.weight", "F_fuse.0.bias", "F_fuse.0.weight", "F_inst.code.linear.bias",
    "F_inst.code.linear.weight", "F_inst.mlp.0.bias", "F_inst.mlp.0.weight", "F_rad.code.linear.bias",
    "F_rad.code.linear.weight", "F_rad.mlp.0.bias", "F_rad.mlp.0.weight", "F_rad.out.bias", "F_rad.out.weight",
    "F_share.mlp.0.bias", "F_share.mlp.0.weight", "aabb", "bottleneck.bias", "bottleneck.weight",
]


def test_old_format_model_file_loads_and_renders_as_it_did():
    """tests/data/old_format_model.safetensors was written by the code before F_inst/F_rad became
    named classes (ModuleDicts then), with its render of instance 1: the names still load, and
    the render is the stored one to 1e-5 (bit-identical on the AMD EPYC it was written on; an
    Intel Xeon's float kernels differ from it by up to 4e-6, 1/1000 of an 8-bit level)."""
    from pathlib import Path

    from crfedit.cameras import Camera
    from crfedit.model import load_model
    from crfedit.renderer import render_camera
    from crfedit.safefile import read_safetensors

    data = Path(__file__).parent / "data"
    model, _ = load_model(data / "old_format_model.safetensors")
    names = sorted(model.field.state_dict())
    expected = OLD_FORMAT_KEYS + [f"coarse.{k}" for k in OLD_FORMAT_KEYS if k != "aabb"]
    assert names == sorted(expected + ["color_codes", "occupancy", "shape_codes"])
    stored, _ = read_safetensors(data / "old_format_render.safetensors")
    camera = Camera(stored["c2w"].numpy(), 8.0, 6, 6)
    with torch.no_grad():
        rgb = render_camera(model.field, camera, 1).rgb
    torch.testing.assert_close(rgb, stored["rgb"], rtol=0, atol=1e-5)
    assert float(stored["rgb"].std()) > 0.01  # the view does show the field
