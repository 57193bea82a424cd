"""Configuration: one frozen dataclass, named presets, overrides from the command line.

``fast`` (default) is the small, grid-accelerated model that trains in minutes on a laptop
CPU; ``paper`` is the architecture and sampling of Liu et al. (ICCV 2021) for reproduction.
The resolved config is stored in every model file, so a model always renders the way it was
trained.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, fields

from .errors import CrfError

MAX_GRID_SIDE = 512
"""Largest occupancy grid side (``occ_res``) a model may have and a file may declare: a packed
grid is checked against its declared shape before it is unpacked, and this bounds what
unpacking allocates (a few bytes a cell, 0.4 GB at 512³)."""


@dataclass(frozen=True)
class Config:
    """Every knob of the field, the renderer and training.  Lengths are in world units."""

    preset: str = "fast"
    arch: str = "ours"
    """Ablation variant (paper Table 1): ours | separate (codes, no shared branch) | single (one
    latent code for shape and color) | nerf (no codes: one field for the whole category)."""
    # --- field -----------------------------------------------------------------------------
    code_dim: int = 32
    """Size of each per-instance shape code and color code."""
    code_embed: int = 32
    """Codes enter the network through Linear(code_dim, code_embed)+ReLU."""
    pe_x: int = 4
    """Positional-encoding frequencies for positions."""
    pe_d: int = 2
    """Positional-encoding frequencies for view directions."""
    grid_res: int = 48
    """Instance-agnostic dense feature grid inside F_share (0 = none)."""
    grid_features: int = 8
    density_act: str = "softplus"
    """σ from the raw output: exp (truncated at e¹⁵) or softplus (grows linearly, so density
    cannot saturate within a few hundred steps and trap the geometry)."""
    density_scale: float = 50.0
    """σ = density_scale · act(raw): puts raw outputs of order 1 at the density of an opaque
    surface (σ ≈ 100 over a 0.017-unit step), so the network need not first grow its output
    by orders of magnitude; scale 1 left surfaces semi-transparent for whole runs."""
    width: int = 64
    """Width of F_share, F_inst and F_fuse."""
    share_layers: int = 1
    inst_layers: int = 2
    fuse_layers: int = 1
    bottleneck: int = 8
    rad_width: int = 64
    rad_layers: int = 1
    part_dim: int = 16
    """Width of F_part, a linear part-embedding head on F_fuse's output that selections read
    (:mod:`crfedit.parts`).  Trained where the dataset has part maps and depth; 0 (also what
    training sets when it has none): no head."""
    # --- sampling --------------------------------------------------------------------------
    sampler: str = "grid"
    """grid: march a per-instance occupancy grid; hierarchical: the paper's coarse + fine."""
    occ_res: int = 64
    """Occupancy-grid cells per side (per instance)."""
    steps_per_cell: float = 1.0
    """Marching step = cell size / steps_per_cell.  One step per cell trained 2.5× more steps
    in the same time and scored 0.3 dB higher than two (docs/benchmarks.md)."""
    n_coarse: int = 64
    n_fine: int = 128
    early_stop: float = 1e-4
    """Stop marching a ray once its transmittance falls below this when rendering."""
    train_early_stop: float = 1e-3
    """The same during training (grid sampler): samples behind opaque surfaces are skipped."""
    # --- training --------------------------------------------------------------------------
    rays: int = 1024
    """Rays per training step (more, smaller steps won: 1024 beat 2048 and 4096 at equal time);
    under torchrun the total over all ranks, split between them."""
    steps: int = 30000
    """Length of the learning-rate schedule; ``train --minutes`` ends it on time instead."""
    lr: float = 1e-2
    lr_codes: float = 1e-2
    lr_final: float = 0.05
    """Final learning rate as a fraction of the initial one (cosine decay)."""
    hull_margin: int = 0
    """Cells of dilation around the visual hull that starts each occupancy grid (-1 = no hull:
    start all-occupied and let the density prune)."""
    occ_every: int = 16
    """Update occupancy grids from the density every this many steps."""
    occ_warmup: int = 256
    """Steps before the first occupancy update."""
    occ_threshold: float = 0.01
    """A cell stays occupied while its opacity over one step, 1-exp(-σ·step), exceeds this."""
    density_noise: float = 0.0
    """Std of noise added to raw density early in training (avoids the all-empty start)."""
    random_background: bool = True
    """Train over a random background colour per ray, not white (:func:`~crfedit.train.over_background`)."""
    distortion: float = 0.0
    """Weight of mip-NeRF 360's distortion loss (:func:`~crfedit.rendering.distortion_dense`),
    which pulls each ray's weight into one short stretch: sharper surfaces, fewer floaters
    (grid sampler only; 0: off)."""
    view_reg: float = 0.0
    """Weight of the paper's view-dependence regularizer (one view per instance)."""
    part_weight: float = 0.05
    """Weight of the part loss (:func:`~crfedit.parts.part_contrastive_loss`) against the MSE.
    At 0.2 the head judged held-out procedural chairs it never learned as well as learned ones,
    but removals and the reconstruction lost; 0.1 was no clear gain (docs/benchmarks.md,
    fifty-ninth session)."""
    part_labels: str = "not-twins"
    """Whose part maps train F_part: ``not-twins``, every instance but the sources of the
    dataset's ground-truth twins (``twins.json``; a dataset without twins: every instance), so
    that an edit benchmark scores selections of parts the model was never told about; ``all``;
    or ``not:NAME,…``, every instance but those named (the name ``twins``: the twins' sources),
    to hold out more chairs than the twins' (:func:`hidden_part_labels`)."""
    checkpoint_every: int = 500
    eval_views: int = 5
    """Held-out views per instance scored at the end of training."""

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "Config":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise CrfError(f"model config is not valid JSON ({e.msg})") from None
        if not isinstance(data, dict):
            raise CrfError("model config is not a JSON object")
        known = {f.name for f in fields(cls)}
        data.setdefault("density_scale", 1.0)  # files written before the key existed used σ = act(raw)
        data.setdefault("random_background", False)  # nor did they train over a random background
        data.setdefault("part_dim", 0)  # nor had they a part head
        unknown = sorted(set(data) - known)
        if unknown:
            raise CrfError(f"model config has unknown keys: {', '.join(unknown)}")
        return cls(**data).validated()

    def validated(self) -> "Config":
        """Raise a one-line CrfError for values that cannot work: a wrong type (a damaged model
        file), a non-finite number, a value out of its range, or a size no machine holds."""
        for f in fields(self):
            value, default = getattr(self, f.name), f.default
            kind = (int, float) if type(default) is float else type(default)
            if type(value) is bool and type(default) is not bool or not isinstance(value, kind):
                raise CrfError(f"{f.name} {value!r}: expected {type(default).__name__}")
            if isinstance(value, float) and not math.isfinite(value):
                raise CrfError(f"{f.name} {value}: must be a finite number")
        sizes = {"width": 4096, "rad_width": 4096, "code_dim": 4096, "code_embed": 4096, "bottleneck": 1024, "part_dim": 1024,
                 "grid_features": 256, "share_layers": 64, "inst_layers": 64, "fuse_layers": 64, "rad_layers": 64,
                 "n_coarse": 4096, "n_fine": 4096, "rays": 1 << 22, "pe_x": 20, "pe_d": 20, "grid_res": MAX_GRID_SIDE}
        for key, most in sizes.items():
            if getattr(self, key) > most:
                raise CrfError(f"{key} {getattr(self, key)}: at most {most}")
        checks = [
            (self.preset in PRESETS, f"preset {self.preset!r}: expected one of {', '.join(PRESETS)}"),
            (self.arch in ARCHS, f"arch {self.arch!r}: expected one of {', '.join(ARCHS)}"),
            (self.sampler in ("grid", "hierarchical"), f"sampler {self.sampler!r}: expected grid or hierarchical"),
            (self.density_act in ("exp", "softplus"), f"density_act {self.density_act!r}: expected exp or softplus"),
            (self.density_scale > 0, "density_scale must be > 0"),
            (self.code_dim > 0 and self.code_embed > 0, "code_dim and code_embed must be positive"),
            (self.width > 0 and self.rad_width > 0 and self.bottleneck > 0, "widths must be positive"),
            (min(self.share_layers, self.inst_layers, self.fuse_layers, self.rad_layers) >= 1, "layer counts must be ≥ 1"),
            (self.pe_x >= 0 and self.pe_d >= 0 and self.grid_res >= 0, "encoding sizes must be ≥ 0"),
            (2 <= self.occ_res <= MAX_GRID_SIDE, f"occ_res must be from 2 to {MAX_GRID_SIDE}"),
            (self.steps_per_cell > 0, "steps_per_cell must be > 0"),
            (self.grid_res == 0 or self.grid_features >= 1, "grid_features must be ≥ 1 (or grid_res 0: no grid)"),
            (0 < self.occ_threshold < 1, f"occ_threshold {self.occ_threshold:g}: must be between 0 and 1"),
            (0 <= self.early_stop < 1 and 0 <= self.train_early_stop < 1, "early_stop and train_early_stop must be from 0 to below 1"),
            (0 <= self.lr_final <= 1, f"lr_final {self.lr_final:g}: a fraction of the learning rate, from 0 to 1"),
            (self.density_noise >= 0 and self.view_reg >= 0, "density_noise and view_reg must be ≥ 0"),
            (self.hull_margin >= -1, f"hull_margin {self.hull_margin}: must be ≥ -1 (-1: no hull)"),
            (self.occ_warmup >= 0, "occ_warmup must be ≥ 0"),
            (self.eval_views >= 1, f"eval_views {self.eval_views}: must be ≥ 1"),
            (self.n_coarse >= 1 and self.n_fine >= 0, "n_coarse must be ≥ 1 and n_fine ≥ 0"),
            (self.rays >= 1, "rays must be ≥ 1"),
            (self.steps >= 1, "steps must be ≥ 1"),
            (self.lr > 0 and self.lr_codes > 0, f"lr {self.lr:g} and lr_codes {self.lr_codes:g}: learning rates must be > 0"),
            (self.occ_every >= 1 and self.checkpoint_every >= 1, "intervals must be ≥ 1"),
            (self.part_dim >= 0 and self.part_weight >= 0, "part_dim and part_weight must be ≥ 0"),
            (self.distortion >= 0 and math.isfinite(self.distortion), "distortion must be ≥ 0"),
            (self.distortion == 0 or self.sampler == "grid", "distortion needs sampler grid"),
            (hidden_part_labels(self.part_labels) is not None,
             f"part_labels {self.part_labels!r}: expected {', '.join(PART_LABELS)} or not:NAME[,NAME…]"),
        ]
        for ok, message in checks:
            if not ok:
                raise CrfError(message)
        return self


ARCHS = ("ours", "separate", "single", "nerf")
PART_LABELS = ("all", "not-twins")


def hidden_part_labels(labels: str) -> list[str] | None:
    """The instance names whose part maps ``part_labels`` hides from F_part (``twins``: the
    twins' sources): ``all`` none, ``not-twins`` ``["twins"]``, ``not:A,B`` ``["A", "B"]``;
    None when ``labels`` is none of these (an empty name, say)."""
    if labels == "all":
        return []
    if labels == "not-twins":
        return ["twins"]
    names = [n.strip() for n in labels.removeprefix("not:").split(",")] if labels.startswith("not:") else []
    return names if names and all(names) else None


PRESETS: dict[str, Config] = {
    "fast": Config(),
    "paper": Config(
        preset="paper",
        pe_x=10,
        pe_d=4,
        grid_res=0,
        width=256,
        share_layers=4,
        inst_layers=4,
        fuse_layers=4,
        rad_width=128,
        rad_layers=1,
        sampler="hierarchical",
        n_coarse=64,
        n_fine=128,
        rays=1024,
        steps=200_000,
        lr=1e-4,
        lr_codes=1e-4,
        lr_final=0.1,
        density_noise=1.0,
        density_act="exp",
        density_scale=1.0,
        random_background=False,
        part_dim=0,
    ),
}


def _coerce(name: str, value: str, current):
    try:
        if isinstance(current, bool):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError
        return type(current)(value)
    except ValueError:
        kind = {bool: "true or false", int: "an integer", float: "a number"}.get(type(current), f"a {type(current).__name__}")
        raise CrfError(f"--set {name}={value}: expected {kind}") from None


DEVICE_DEFAULTS: dict[tuple[str, str], dict[str, object]] = {
    # Provisional: issue 15's one-minute runs on one H100 (before the device-resident step) gave
    # 27.05 dB held-out at 1024 rays per step, 30.37 dB at 8192 and 30.24 dB at 65536.
    # benchmarks/gpu.py --rays sweeps it; replace this with what it measures on a GPU.
    ("fast", "cuda"): {"rays": 8192},
}
"""Per-device defaults of a preset, ``(preset, device type) → fields``: a GPU trains best on
bigger batches than two CPU cores.  Applied over the preset and under explicit overrides; the
resolved config is stored in the model file, so a model renders the same on any device."""


def make_config(
    preset: str = "fast", overrides: dict[str, object] | None = None, sets: list[str] = (), device_type: str = "cpu"
) -> Config:
    """The named preset with its defaults for ``device_type`` (:data:`DEVICE_DEFAULTS`), then
    typed ``overrides`` and ``key=value`` strings (``--set``) applied."""
    if preset not in PRESETS:
        raise CrfError(f"--preset {preset}: expected one of {', '.join(PRESETS)}")
    cfg = dataclasses.replace(PRESETS[preset], **DEVICE_DEFAULTS.get((preset, device_type), {}))
    known = {f.name: getattr(cfg, f.name) for f in fields(cfg)}
    changes = {k: v for k, v in (overrides or {}).items() if v is not None}
    for item in sets:
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if key == "preset":
            raise CrfError(f"--set {item}: the preset is chosen with --preset, before the --set changes")
        if not sep or key not in known:
            raise CrfError(f"--set {item}: expected KEY=VALUE with KEY one of {', '.join(sorted(k for k in known if k != 'preset'))}")
        changes[key] = _coerce(key, value.strip(), known[key])
    return dataclasses.replace(cfg, **changes).validated()
