"""Table 1 of Liu et al.: the architecture variants (``Config.arch``) trained at an equal number
of network parameters (:func:`matched_width`) and an equal time or step budget, scored on
held-out views (:func:`crfedit.evaluation.score_model`)."""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path
from typing import Sequence

import torch

from .config import ARCHS, Config, make_config
from .data.loading import Category
from .errors import CrfError
from .evaluation import Progress, held_out_split, score_model
from .field import ConditionalRadianceField
from .names import CODE_TABLES
from .train import train

ABLATION_ARCHS = ("nerf", "single", "separate", "ours")
"""Table 1's rows, weakest first."""
PARAM_TOLERANCE = 0.05
"""Ablation variants' network parameters lie within ±5 % of ``ours``."""


def network_parameters(cfg: Config) -> int:
    """Trainable parameters of a field built from ``cfg``, without the per-instance codes and the
    instance-agnostic feature grid (the same size in every arch).  Count of one instance's field."""
    field = ConditionalRadianceField(cfg, 1)
    return sum(
        p.numel() for name, p in field.named_parameters()
        if name not in CODE_TABLES and not name.endswith(".grid")
    )


def matched_width(cfg: Config, arch: str, target: int | None = None) -> int:
    """The ``width`` (of F_share, F_inst, F_fuse) that brings ``arch``'s network parameters
    closest to ``target`` (default: those of ``cfg`` with arch ``ours``).

    The count grows with the width, so a bisection finds the first width at or above the
    target and the closer of it and its predecessor wins.  Example (fast preset, width 64):
    ``separate`` and ``single`` drop the F_share MLP and need a wider trunk; ``nerf`` also
    drops F_inst and the code embeddings.
    """
    if arch not in ARCHS:
        raise CrfError(f"arch {arch!r}: expected one of {', '.join(ARCHS)}")
    if target is None:
        target = network_parameters(dataclasses.replace(cfg, arch="ours"))

    def count(width: int) -> int:
        return network_parameters(dataclasses.replace(cfg, arch=arch, width=width))

    lo, hi = 1, max(2, cfg.width)
    while count(hi) < target:
        lo, hi = hi, hi * 2
        if hi > 1 << 16:
            raise CrfError(f"arch {arch}: no width reaches {target} parameters")
    while lo < hi:
        mid = (lo + hi) // 2
        if count(mid) < target:
            lo = mid + 1
        else:
            hi = mid
    if lo > 1 and abs(count(lo - 1) - target) <= abs(count(lo) - target):
        return lo - 1
    return lo


def ablation_configs(base: Config, archs: Sequence[str] = ABLATION_ARCHS) -> dict[str, Config]:
    """One config per arch, widths matched to ``base`` as arch ``ours`` (:func:`matched_width`)."""
    target = network_parameters(dataclasses.replace(base, arch="ours"))
    out = {}
    for arch in archs:
        width = base.width if arch == "ours" else matched_width(base, arch, target)
        out[arch] = dataclasses.replace(base, arch=arch, width=width).validated()
    return out


def warm_up_training(category: Category, cfg: Config, device, folder: Path) -> None:
    """Two throwaway training steps: the first training of a process pays one-off costs (kernel
    and allocator warm-up, seconds on a CPU) that must not come out of a timed budget."""

    path = Path(folder) / "warm-up.safetensors"
    train(category, dataclasses.replace(cfg, steps=2, checkpoint_every=2), path, device)
    path.unlink(missing_ok=True)


def run_ablation(
    category: Category,
    minutes: float | None = None,
    steps: int | None = None,
    seed: int = 0,
    device: torch.device | str = "cpu",
    base: Config | None = None,
    archs: Sequence[str] = ABLATION_ARCHS,
    split: str | None = None,
    max_views: int | None = None,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
) -> list[dict]:
    """Table 1: train each arch at equal network parameters and an equal budget, score held out.

    Every arch gets ``minutes`` of training time and/or ``steps`` steps (at least one is
    needed; with both, whichever ends first), the same ``seed`` and data.  ``base`` is the
    config to vary (default: the ``fast`` preset).  Returns one dict per arch::

        {"arch", "width", "params", "params_vs_ours", "steps", "seconds", "split", "n",
         "psnr", "ssim", "lpips"}

    ``params_vs_ours`` is the ratio of network parameters (codes and feature grid excluded) to
    ``ours``; :func:`matched_width` keeps it within ``1 ± PARAM_TOLERANCE``.  Model files go to
    ``workdir`` (kept) or a temporary folder (deleted).
    """

    if minutes is None and steps is None:
        raise CrfError("ablation: give a time budget (--minutes) or a step budget (--steps)")
    if minutes is not None and not (minutes > 0 and math.isfinite(minutes)):
        raise CrfError(f"--minutes {minutes:g}: must be a finite positive number")
    if steps is not None and steps < 1:
        raise CrfError(f"--steps {steps}: must be at least 1")
    base = base or make_config("fast")
    if steps is not None:
        base = dataclasses.replace(base, steps=steps)
    elif minutes is not None:
        base = dataclasses.replace(base, steps=max(base.steps, 10**9))  # the time budget ends every run
    split = split or held_out_split(category, "test")
    from .parts import part_config

    base = part_config(category, base)  # widths matched (and parameters counted) with the part head training keeps
    configs = ablation_configs(base, archs)
    target = network_parameters(configs["ours"]) if "ours" in configs else network_parameters(dataclasses.replace(base, arch="ours"))
    say = progress or (lambda _msg: None)
    rows = []
    with tempfile.TemporaryDirectory(prefix="crfedit-ablation-") as tmp:
        folder = Path(workdir) if workdir is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        warm_up_training(category, next(iter(configs.values())), device, folder)
        for arch, cfg in configs.items():
            params = network_parameters(cfg)
            budget = f"{minutes:g} min" if minutes is not None else f"{steps} steps"
            say(f"{arch}: width {cfg.width}, {params:,} network parameters, training for {budget}")
            model, result = train(category, cfg, folder / f"{arch}.safetensors", device, seed=seed, minutes=minutes)
            score = score_model(model, category, split, max_views)
            rows.append({
                "arch": arch, "width": cfg.width, "params": params, "params_vs_ours": params / target,
                "steps": result.steps, "seconds": result.seconds, "split": split, "n": score["n"],
                "psnr": score["psnr"] if math.isfinite(score["psnr"]) else None, "ssim": score["ssim"], "lpips": score["lpips"],
            })
            say(f"{arch}: {result.steps} steps in {result.seconds:.1f} s, PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.3f}")
    return rows
