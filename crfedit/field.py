"""The conditional radiance field of Liu et al. (ICCV 2021), built from the paper's named parts.

    x ─┬─ encode ─┬─ F_share ──────────────┐
       │          └─ F_inst(· , shape code)─┴─(+)─ F_fuse(· , x, shape code) ─┬─ F_dens → σ
       │                                                                      ├─ bottleneck (8-d)
       │                                                                      └─ F_part → part embedding (selections only)
    d ─┴─ encode ──────────────────────────────── F_rad(bottleneck, d, color code) → rgb

Parameter names start with the module names (``F_rad.``, ``F_fuse.`` …): edits select what they
train, and deltas what they store, by these prefixes.  σ depends on position and shape code
only; colour adds the view direction and the colour code.  Callers ask the field for
``density(x, instance)``, ``features(x, instance)``, ``radiance(features, dirs, instance)`` or
``forward(x, dirs, instance)``; the stages below them are separate methods of :class:`FieldNet`
so that an edit can cache the inputs of the stage it trains (``fuse_inputs`` for shape edits,
the bottleneck features for colour edits).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import Config
from .names import CODE_TABLES, COLOR_CODES, MODULES, SHAPE_CODES  # noqa: F401  (re-exported)


def positional_encoding(x: Tensor, n_freqs: int) -> Tensor:
    """[x, sin(2ᵏπx), cos(2ᵏπx)] for k < n_freqs.  [..., D] → [..., D(1 + 2·n_freqs)]"""
    if n_freqs == 0:
        return x
    freqs = torch.pi * 2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)
    xf = (x[..., None, :] * freqs[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(xf), torch.cos(xf)], dim=-1)


def mlp(n_in: int, width: int, n_layers: int) -> nn.Sequential:
    """``n_layers`` of Linear + ReLU, ``width`` wide.  The ReLUs work in place: each one's
    input is its Linear's fresh output, which nothing else reads (the Linear's backward needs
    its input, not its output), so the values and gradients are the same bits with one
    allocation and one pass over memory fewer per layer (``select``'s density ascent over
    37 000 cells: 120 → 106 ms on one core)."""
    layers: list[nn.Module] = []
    for i in range(n_layers):
        layers += [nn.Linear(n_in if i == 0 else width, width), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class CodeEmbed(nn.Module):
    """A latent code enters the network through Linear + ReLU (as in the paper)."""

    def __init__(self, code_dim: int, out: int):
        super().__init__()
        self.linear = nn.Linear(code_dim, out)

    def forward(self, code: Tensor) -> Tensor:
        return F.relu(self.linear(code))


class SharedBranch(nn.Module):
    """F_share: instance-agnostic.  Owns the position encoding (an optional dense feature grid
    plus sinusoids), which F_inst reads too."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.pe_x = cfg.pe_x
        self.grid = nn.Parameter(torch.zeros(1, cfg.grid_features, *(cfg.grid_res,) * 3)) if cfg.grid_res else None
        self.encoded_dim = 3 * (1 + 2 * cfg.pe_x) + (cfg.grid_features if cfg.grid_res else 0)
        self.mlp = mlp(self.encoded_dim, cfg.width, cfg.share_layers) if cfg.arch in ("ours", "nerf") else None

    def encode(self, x: Tensor) -> Tensor:
        """``x`` in [-1, 1]³ (the normalized scene box) → encoded position.  [M, 3] → [M, E]"""
        enc = positional_encoding(x, self.pe_x)
        if self.grid is None:
            return enc
        # grid_sample wants (x, y, z) ↔ (W, H, D); trilinear with align_corners → cell corners.
        g = F.grid_sample(self.grid, x.view(1, 1, 1, -1, 3), mode="bilinear", align_corners=True)
        return torch.cat([enc, g.view(self.grid.shape[1], -1).T], dim=-1)


def linear_with_codes(layer: nn.Linear, per_point: Tensor, per_code: Tensor | None, idx: Tensor | None) -> Tensor:
    """``layer(cat([per_point, per_code[idx]]))`` without repeating the code part per point.

    The code columns of the weight act on each code row once ([K, out]) and are then gathered.
    ``idx`` picks a row per point: [M] int64, or a one-hot [M, K] float selector (a matmul,
    whose backward is fast and accumulates in a fixed order), or None for a single code row,
    which then enters as the layer's bias (one fused multiply-add, no per-point gather).
    """
    if per_code is None:
        return layer(per_point)
    n = per_point.shape[-1]
    code_part = F.linear(per_code, layer.weight[:, n:], layer.bias)  # [K, out]
    if idx is None:
        if code_part.shape[0] != 1:
            raise ValueError("idx=None needs a single code row")
        return F.linear(per_point, layer.weight[:, :n], code_part[0])
    if idx.is_floating_point():
        return torch.addmm(idx @ code_part, per_point, layer.weight[:, :n].T)
    return torch.addmm(torch.index_select(code_part, 0, idx), per_point, layer.weight[:, :n].T)


def code_selector(idx: Tensor, n_codes: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """One-hot [M, K] selector for :func:`linear_with_codes` (deterministic, fast backward).

    Built by comparison rather than ``F.one_hot``, which reads ``idx``'s range back to the host
    (a GPU synchronization) to check it."""
    return (idx[:, None] == torch.arange(n_codes, device=idx.device)).to(dtype)


def run_mlp(seq: nn.Sequential, per_point: Tensor, per_code: Tensor | None = None, idx: Tensor | None = None) -> Tensor:
    """An :func:`mlp` whose first layer also sees a per-instance input (see :func:`linear_with_codes`)."""
    h = linear_with_codes(seq[0], per_point, per_code, idx).relu_()  # a fresh tensor: see mlp
    for layer in list(seq)[2:]:
        h = layer(h)
    return h


class InstanceBranch(nn.Module):
    """F_inst: the instance-specific branch, an MLP on the encoded position and the embedded
    shape code.  Its output is added to F_share's; the embedded code also skips into F_fuse."""

    def __init__(self, cfg: Config, encoded_dim: int):
        super().__init__()
        self.code = CodeEmbed(cfg.code_dim, cfg.code_embed)
        self.mlp = mlp(encoded_dim + cfg.code_embed, cfg.width, cfg.inst_layers)

    def forward(self, encoded: Tensor, shape_codes: Tensor, idx: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(hidden [M, W], embedded shape codes [K, E]) from the encoded position [M, E_x]."""
        s = self.code(shape_codes)
        return run_mlp(self.mlp, encoded, s, idx), s


class RadianceBranch(nn.Module):
    """F_rad: RGB in [0, 1] from the bottleneck features, the encoded view direction and the
    embedded colour code (none in the ``nerf`` ablation).

    Its per-point input (:meth:`inputs`) is separate from the network (:meth:`forward`): a
    colour edit builds the input once and runs only the network at every step.
    """

    def __init__(self, cfg: Config):
        super().__init__()
        e = cfg.code_embed if cfg.arch != "nerf" else 0
        self.pe_d = cfg.pe_d
        self.code = CodeEmbed(cfg.code_dim, e) if cfg.arch != "nerf" else nn.Identity()
        self.mlp = mlp(cfg.bottleneck + 3 * (1 + 2 * cfg.pe_d) + e, cfg.rad_width, cfg.rad_layers)
        self.out = nn.Linear(cfg.rad_width, 3)

    def inputs(self, features: Tensor, directions: Tensor) -> Tensor:
        """[bottleneck features, encoded direction].  [M, 8], [M, 3] → [M, 8 + D]"""
        return torch.cat([features, positional_encoding(directions, self.pe_d)], dim=-1)

    def forward(self, per_point: Tensor, color_codes: Tensor | None, idx: Tensor | None = None) -> Tensor:
        """RGB [M, 3] from :meth:`inputs` and colour code rows [K, D] (``idx`` as in
        :func:`linear_with_codes`)."""
        code = self.code(color_codes) if color_codes is not None else None
        return torch.sigmoid(self.out(run_mlp(self.mlp, per_point, code, idx)))


class FieldNet(nn.Module):
    """One network of the field (the fine one; the paper preset adds a coarse twin).

    Codes are passed as tables ``[K, code_dim]`` with ``idx`` choosing a row per point (see
    :func:`linear_with_codes`; None: a single row for all points).  Callers that think in
    instances use :class:`ConditionalRadianceField`'s ``density``/``features``/``radiance``.
    """

    def __init__(self, cfg: Config):
        super().__init__()
        w = cfg.width
        self.arch = cfg.arch
        self.density_act = cfg.density_act
        self.density_scale = cfg.density_scale
        self.F_share = SharedBranch(cfg)
        enc = self.F_share.encoded_dim
        self.uses_shape_code = cfg.arch != "nerf"
        self.uses_color_code = cfg.arch in ("ours", "separate")
        if self.uses_shape_code:
            self.F_inst = InstanceBranch(cfg, enc)
        skip = 3 * (1 + 2 * cfg.pe_x) + (cfg.code_embed if self.uses_shape_code else 0)
        self.F_fuse = mlp(w + skip, w, cfg.fuse_layers)
        self.F_dens = nn.Linear(w, 1)
        self.bottleneck = nn.Linear(w, cfg.bottleneck)
        self.F_rad = RadianceBranch(cfg)
        with torch.no_grad():  # start slightly transparent
            self.F_dens.bias.fill_(-1.0)

    def fuse_inputs(self, x: Tensor, shape_codes: Tensor | None, idx: Tensor | None = None) -> "FuseInputs":
        """Everything upstream of F_fuse: the cache of a shape edit.  x [M, 3] in [-1, 1]."""
        enc = self.F_share.encode(x)
        pe = enc[:, : 3 * (1 + 2 * self.F_share.pe_x)]
        h = self.F_share.mlp(enc) if self.F_share.mlp is not None else 0.0
        s = None
        if self.uses_shape_code:
            h_inst, s = self.F_inst(enc, shape_codes, idx)
            h = h + h_inst
        return FuseInputs(h, pe, s, idx)

    def fuse_activations(self, inputs: "FuseInputs") -> Tensor:
        """F_fuse's output [M, width]: what F_dens and the bottleneck both read."""
        return run_mlp(self.F_fuse, torch.cat([inputs.hidden, inputs.pe], dim=-1), inputs.code, inputs.idx)

    def raw_density(self, fused: Tensor) -> Tensor:
        """F_dens: the raw density [M] from F_fuse's output [M, width] (:meth:`sigma` makes it σ)."""
        return self.F_dens(fused).squeeze(-1)

    def density_from_fuse_inputs(self, inputs: "FuseInputs") -> tuple[Tensor, Tensor]:
        """F_fuse → (raw density [M], bottleneck features [M, 8])."""
        h = self.fuse_activations(inputs)
        return self.raw_density(h), self.bottleneck(h)

    def density_and_features(self, x: Tensor, shape_codes: Tensor | None, idx: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(raw density [M], bottleneck features [M, 8]): the cache of a colour edit."""
        return self.density_from_fuse_inputs(self.fuse_inputs(x, shape_codes, idx))

    def sigma(self, raw: Tensor) -> Tensor:
        """Density σ ≥ 0 from the raw F_dens output (see :func:`density_activation`)."""
        sigma = density_activation(raw, self.density_act)
        return sigma if self.density_scale == 1.0 else sigma * self.density_scale

    def radiance_from_codes(
        self, features: Tensor, directions: Tensor, color_codes: Tensor | None, idx: Tensor | None = None
    ) -> Tensor:
        """F_rad: RGB in [0, 1] from bottleneck features [M, 8], unit directions [M, 3], colour codes."""
        return self.F_rad(self.F_rad.inputs(features, directions), color_codes, idx)


class FuseInputs(NamedTuple):
    hidden: Tensor  # [M, W]  F_share + F_inst
    pe: Tensor  # [M, P]  encoded position (the skip into F_fuse)
    code: Tensor | None  # [K, E]  embedded shape codes (the other skip)
    idx: Tensor | None  # [M]  row of ``code`` per point


class _TruncExp(torch.autograd.Function):
    """exp(min(x, 15)) forward; the gradient of exp at min(x, 15) backward, so a saturated
    density still receives gradient and can come back down (a plain clamp would freeze it)."""

    @staticmethod
    def forward(ctx, x):
        y = torch.exp(x.clamp(max=15.0))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad):
        (y,) = ctx.saved_tensors
        return grad * y


def density_activation(raw: Tensor, kind: str = "exp") -> Tensor:
    """σ = exp(raw), capped at e¹⁵ ≈ 3.3e6 with a gradient that never vanishes at the cap;
    or σ = softplus(raw), which grows linearly and keeps compositing gradients alive."""
    if kind == "softplus":
        return F.softplus(raw)
    return _TruncExp.apply(raw)


class ConditionalRadianceField(FieldNet):
    """The category model: the fine network, per-instance codes, occupancy grids, scene box.

    ``shape_codes``/``color_codes`` are [K, code_dim]; ``occupancy`` [K, R, R, R] (bool) marks
    the cells of each instance worth sampling; ``aabb`` is the scene box.  With the paper's
    hierarchical sampler a ``coarse`` network of the same design shares the codes.
    """

    def __init__(self, cfg: Config, n_instances: int, aabb: Tensor | None = None):
        super().__init__(cfg)
        self.cfg = cfg
        self.shape_codes = nn.Parameter(torch.randn(n_instances, cfg.code_dim) * 0.01)
        self.color_codes = nn.Parameter(torch.randn(n_instances, cfg.code_dim) * 0.01)
        self.coarse = FieldNet(cfg) if cfg.sampler == "hierarchical" else None
        default_box = torch.tensor([-0.6, -0.6, -0.6, 0.6, 0.6, 0.6])
        self.register_buffer("aabb", (aabb if aabb is not None else default_box).float().clone())
        self.register_buffer("occupancy", torch.ones(n_instances, *(cfg.occ_res,) * 3, dtype=torch.bool))
        # not the paper's: a part embedding for selections, trained from part maps (crfedit.parts)
        self.F_part = nn.Linear(cfg.width, cfg.part_dim) if cfg.part_dim else None

    @classmethod
    def to_load(cls, cfg: Config, n_instances: int, aabb: Tensor | None = None) -> "ConditionalRadianceField":
        """A field whose tensors are about to be loaded (a model file, a grown model): built
        without drawing from torch's global random stream, so loading leaves a script's
        ``torch.manual_seed`` stream where it was (the random initial weights are overwritten)."""
        with torch.random.fork_rng(devices=[]):
            return cls(cfg, n_instances, aabb)

    @property
    def n_instances(self) -> int:
        return self.shape_codes.shape[0]

    def normalize(self, points: Tensor) -> Tensor:
        """World points → [-1, 1]³ over the scene box."""
        lo, hi = self.aabb[:3], self.aabb[3:]
        return (points - lo) / (hi - lo) * 2.0 - 1.0

    def denormalize(self, xn: Tensor) -> Tensor:
        """Normalized points in [-1, 1]³ → world (the inverse of :meth:`normalize`)."""
        lo, hi = self.aabb[:3], self.aabb[3:]
        return lo + (xn + 1.0) * 0.5 * (hi - lo)

    def code_tables(self) -> tuple[Tensor | None, Tensor | None]:
        """(shape codes, colour codes) [K, D] as the architecture uses them (None = unused)."""
        s = self.shape_codes if self.uses_shape_code else None
        if self.arch == "single":
            return s, s
        return s, (self.color_codes if self.uses_color_code else None)

    def codes(self, instance: int) -> tuple[Tensor | None, Tensor | None]:
        """The code rows [1, D] of one instance."""
        s, c = self.code_tables()
        return (None if s is None else s[instance : instance + 1]), (None if c is None else c[instance : instance + 1])

    def select(self, instance: int | Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        """(shape codes, colour codes, idx) for :class:`FieldNet`'s table-level methods.

        ``instance`` is an int (every point shows that instance: its code rows [1, D], which
        enter as biases, and idx None) or a [M] int64 tensor of one instance per point (the
        full tables and a one-hot selector, see :func:`linear_with_codes`).
        """
        if isinstance(instance, int):
            return (*self.codes(instance), None)
        return (*self.code_tables(), code_selector(instance, self.n_instances))

    def density(self, x: Tensor, instance: int | Tensor, net: FieldNet | None = None) -> Tensor:
        """σ ≥ 0 [M] at normalized points ``x`` [M, 3] in [-1, 1]³ (see :meth:`normalize`).

        ``instance`` as in :meth:`select`; ``net`` is the network to run: this one (default)
        or the paper preset's ``coarse`` twin.  Also for :meth:`features`, :meth:`radiance`
        and :meth:`forward`.
        """
        net = self if net is None else net
        s, _, idx = self.select(instance)
        return net.sigma(net.density_and_features(x, s, idx)[0])

    def fuse_features(self, x: Tensor, instance: int | Tensor, net: FieldNet | None = None) -> Tensor:
        """F_fuse's output [M, width] at ``x`` [M, 3]: what F_dens and the bottleneck read."""
        net = self if net is None else net
        s, _, idx = self.select(instance)
        return net.fuse_activations(net.fuse_inputs(x, s, idx))

    def part_embedding(self, fused: Tensor) -> Tensor:
        """F_part: the unit part embedding [M, part_dim] of F_fuse's output [M, width]."""
        return F.normalize(self.F_part(fused), dim=-1)

    def features(self, x: Tensor, instance: int | Tensor, net: FieldNet | None = None) -> Tensor:
        """The bottleneck features [M, 8] at ``x`` [M, 3]: all that F_rad sees of the position,
        so a colour edit caches them."""
        net = self if net is None else net
        return net.bottleneck(self.fuse_features(x, instance, net))

    def radiance(self, features: Tensor, directions: Tensor, instance: int | Tensor, net: FieldNet | None = None) -> Tensor:
        """RGB [M, 3] in [0, 1] from :meth:`features` [M, 8] and unit view directions [M, 3]."""
        net = self if net is None else net
        _, c, idx = self.select(instance)
        return net.radiance_from_codes(features, directions, c, idx)

    def forward(
        self, x: Tensor, directions: Tensor, instance: int | Tensor, net: FieldNet | None = None
    ) -> tuple[Tensor, Tensor]:
        """(σ [M], RGB [M, 3]) at ``x`` [M, 3] seen along ``directions`` [M, 3]."""
        net = self if net is None else net
        s, c, idx = self.select(instance)
        raw, feat = net.density_and_features(x, s, idx)
        return net.sigma(raw), net.radiance_from_codes(feat, directions, c, idx)
