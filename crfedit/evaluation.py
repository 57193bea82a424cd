"""The paper's evaluation protocols on top of :mod:`crfedit.evaluate`.

* :func:`evaluate_recon` — reconstruction of held-out views, per instance and overall.
* :func:`evaluate_edits` — Tables 2 (colour) and 3 (shape / removal) of Liu et al.: every
  ground-truth twin of the dataset (``twins.json``) is edited from its scribbles with each
  update strategy (and, optionally, the single-instance NeRF baseline), every test view of the
  source instance is rendered with the edit applied and scored against the twin's test views.
* :func:`run_ablation` — Table 1: the architecture variants (``Config.arch``) trained at an
  equal number of network parameters (:func:`matched_width`) and an equal time or step budget,
  scored on held-out views.

Scores are PSNR (dB, averaged per image), SSIM (:data:`SSIM_NOTE`) and LPIPS-AlexNet when a
weights file is configured (:mod:`crfedit.metrics`).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .cameras import Camera
from .config import ARCHS, Config, make_config
from .data.format import Category, TwinSpec, View, load_category, load_twins, read_mask
from .distributed import SINGLE, Ranks
from .edit import STRATEGIES, EditOptions, EditResult, edit_color, remove
from .edit.params import GROUP, trained_prefixes
from .errors import CrfError
from .evaluate import render_views, score_model
from .edit.selection import ScribbleView, select
from .twin_scores import appearance, changed_regions, gap_closed, region_scores, selection_iou
from .field import ConditionalRadianceField
from .metrics import lpips_unavailable_reason, score_images
from .model import CategoryModel
from .names import CODE_TABLES
from .train import train

SSIM_NOTE = "SSIM: 11×11 Gaussian window, σ=1.5, on RGB"
LPIPS_SKIPPED = "LPIPS: skipped (no weights)"
UNEDITED = "unedited"
NERF_BASELINE = "nerf (single instance)"
PAPER_METHOD = "hybrid, --method paper"
"""The paper's own losses (scribbled view's rays only) with its hybrid update, for comparison."""
ABLATION_ARCHS = ("nerf", "single", "separate", "ours")
"""Table 1's rows, weakest first."""
PARAM_TOLERANCE = 0.05
"""Ablation variants' network parameters lie within ±5 % of ``ours``."""

Progress = Callable[[str], None]


# ----------------------------------------------------------------------------- datasets


def fingerprint_warning(model: CategoryModel, category: Category) -> str | None:
    """A one-line warning when ``category`` is not the dataset the model was trained on, else None."""
    if model.dataset_fingerprint == category.fingerprint:
        return None
    trained = model.dataset_fingerprint or "unknown"
    return (
        f"the dataset {category.root} (fingerprint {category.fingerprint}) is not the one the model "
        f"was trained on (fingerprint {trained}); scores compare against other images"
    )


def model_width(model: CategoryModel, split: str = "test") -> int | None:
    """The image width the model's views of ``split`` were stored at (else its training width)."""
    table = model.views.get(split) or model.views.get("train") or next(iter(model.views.values()), None)
    return None if table is None else table.width


def load_category_for(model: CategoryModel, data: str | Path, split: str = "test") -> Category:
    """The dataset at ``data`` loaded at the resolution the model was trained and stored at."""
    return load_category(Path(data), res=model_width(model, split))


# ----------------------------------------------------------------------------- reconstruction


def score_instance(
    model: CategoryModel, instance: int, views: Sequence[View], lpips_weights: str | Path | None = None
) -> dict:
    """Render ``instance`` at ``views``' cameras and score against their images (score_images)."""
    outs = render_views(model, instance, [v.camera for v in views])
    preds = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in outs]
    return score_images(preds, [v.rgb for v in views], lpips_weights)


def evaluate_recon(
    model: CategoryModel,
    category: Category,
    split: str = "test",
    max_views: int | None = None,
    lpips_weights: str | Path | None = None,
    ranks: Ranks = SINGLE,
) -> dict:
    """Held-out reconstruction scores of every model instance that ``category`` holds.

    Each instance's first ``max_views`` views of ``split`` (default: all) are rendered with the
    dataset's cameras and scored against its images.  Returns::

        {"split", "n": views scored, "psnr", "ssim", "lpips" (None without weights),
         "lpips_note", "ssim_note", "dataset_match": bool,
         "instances": {name: {"n", "psnr", "ssim", "lpips"}}}

    Means are over views (each view counts once, as in :func:`crfedit.evaluate.score_model`).
    ``lpips_weights`` (or ``$CRFEDIT_LPIPS_WEIGHTS``) enables LPIPS; a configured file that is
    missing or invalid is an error, never a silent skip.  Under torchrun (``ranks``) each rank
    scores every ``world``-th instance and every rank returns the gathered result.
    """
    if split not in ("train", "val", "test"):
        raise CrfError(f"--split {split}: expected train, val or test")
    if max_views is not None and max_views < 1:
        raise CrfError(f"--max-views {max_views}: must be at least 1")
    per_instance, note = {}, lpips_unavailable_reason(lpips_weights)
    for k, name in ranks.shard(list(enumerate(model.names))):
        if name not in category.names:
            continue
        views = category.instance(name).splits.get(split, [])[:max_views]
        if views:
            score = score_instance(model, k, views, lpips_weights)
            note = score["lpips_note"]
            per_instance[name] = {key: score[key] for key in ("n", "psnr", "ssim", "lpips")}
    if ranks.world > 1:
        parts = ranks.gather((per_instance, note), "gathering the scores")
        scored = {name: row for part, _ in parts for name, row in part.items()}
        per_instance = {name: scored[name] for name in model.names if name in scored}
        note = next((n for part, n in parts if part), note)
    if not per_instance:
        raise CrfError(f"{category.root}: none of the model's instances has {split} views in this dataset")
    rows = list(per_instance.values())
    n = np.array([r["n"] for r in rows], dtype=np.float64)

    def mean(key: str) -> float | None:
        values = [r[key] for r in rows]
        return None if any(v is None for v in values) else float(np.sum(n * np.array(values)) / n.sum())

    return {
        "split": split, "n": int(n.sum()), "psnr": mean("psnr"), "ssim": mean("ssim"), "lpips": mean("lpips"),
        "lpips_note": note, "ssim_note": SSIM_NOTE, "dataset_match": fingerprint_warning(model, category) is None,
        "instances": per_instance,
    }


# ----------------------------------------------------------------------------- edits (Tables 2, 3)


@dataclass(frozen=True, eq=False)
class TwinCase:
    """One ground-truth twin, ready to be edited: what the user scribbled and what it should give."""

    spec: TwinSpec
    instance: int  # the source's index in the model
    camera: Camera  # the scribbled view of the source
    scribble: np.ndarray  # [H, W] bool, the part to edit
    keep: np.ndarray  # [H, W] bool, what must not change
    views: list[View]  # the twin's test views: the source's test poses, rendered edited


def twin_cases(model: CategoryModel, category: Category, twins: Sequence[tuple[TwinSpec, object]]) -> list[TwinCase]:
    """:func:`~crfedit.data.format.load_twins` output resolved against the model and dataset.

    The scribbled view is the source's view ``spec.view`` in ``category`` (so the masks, read at
    that view's width, line up with its camera).
    """
    cases = []
    for spec, data in twins:
        if spec.source not in model.names:
            raise CrfError(f"twin {spec.name}: source instance {spec.source!r} is not in the model")
        view = category.instance(spec.source).view(spec.view)
        cam = view.camera
        masks = [read_mask(category.root / rel, width=cam.width) for rel in (spec.scribble, spec.keep)]
        for rel, mask in zip((spec.scribble, spec.keep), masks):
            if mask.shape != (cam.height, cam.width):
                raise CrfError(f"twin {spec.name}: mask {rel} is {mask.shape[1]}x{mask.shape[0]}, view {spec.view} is {cam.width}x{cam.height}")
        views = data.splits.get("test", [])
        if not views:
            raise CrfError(f"twin {spec.name}: no test views in {category.root / spec.folder}")
        cases.append(TwinCase(spec, model.instance_index(spec.source), cam, masks[0], masks[1], views))
    return cases


def load_twin_cases(model: CategoryModel, category: Category) -> list[TwinCase]:
    """The dataset's twins (``twins.json``), loaded at the model's resolution, as :class:`TwinCase`."""
    return twin_cases(model, category, load_twins(category.root, res=model_width(model, "test")))


def apply_twin_edit(
    model: CategoryModel, case: TwinCase, options: EditOptions, instance: int | None = None, method: str = "selection",
    appear: tuple[float, ...] | None = None, selection=None,
) -> EditResult:
    """Make the twin's edit of ``case`` (colour or removal) from its scribbles; an EditResult.

    ``instance`` overrides the edited index (the single-instance baseline edits its index 0).
    ``method`` is the edits' (selection or paper); a selection-supervised recolour targets the
    colour the part should *appear* (``appear``, see :func:`~crfedit.twin_scores.appearance`),
    the paper's the twin's albedo as given.
    """

    k = case.instance if instance is None else instance
    if case.spec.kind == "color":
        color = appear if method == "selection" and appear is not None else case.spec.color
        return edit_color(model, k, case.camera, case.scribble, color, case.keep, options, method, selection)
    return remove(model, k, case.camera, case.scribble, case.keep, options=options, method=method, selection=selection)


def strategy_problem(model: CategoryModel, kind: str, strategy: str) -> str | None:
    """Why ``strategy`` cannot edit this model for a ``kind`` twin (e.g. ``codes`` on arch nerf), else None."""

    try:
        trained_prefixes(model.field, GROUP[kind], strategy)
    except CrfError as e:
        return str(e)
    return None


@dataclass(frozen=True)
class NerfBaseline:
    """The paper's single-instance NeRF baseline: a NeRF (``arch=nerf``) trained on the source
    instance alone, then fine-tuned with the edit, every weight trained (strategy ``all``)."""

    steps: int = 1000
    """Training steps (a short, fixed budget)."""
    minutes: float | None = None
    """Optional time budget; training stops at whichever limit comes first."""


def single_instance(category: Category, name: str) -> Category:
    """``category`` restricted to one instance (its own fingerprint, derived from the category's)."""
    return Category(category.root, [category.instance(name)], f"{category.fingerprint}:{name}")


def train_single_instance_nerf(
    category: Category, name: str, base: Config, baseline: NerfBaseline, out: str | Path, device, seed: int = 0
) -> tuple[CategoryModel, float]:
    """(model, training seconds) of a NeRF trained on instance ``name`` of ``category`` alone."""

    cfg = dataclasses.replace(base, arch="nerf", steps=baseline.steps).validated()
    model, result = train(single_instance(category, name), cfg, out, device, seed=seed, minutes=baseline.minutes)
    return model, result.seconds


def _finite(x):
    return x if x is None or math.isfinite(x) else None


def _mean(rows: list[dict], key: str) -> float | None:
    values = [r.get(key) for r in rows]
    if not values or any(v is None for v in values):
        return None
    return float(np.mean(values))


TABLE_KEYS = (
    "psnr", "ssim", "lpips", "seconds", "psnr_before", "psnr_ceiling", "gap_closed", "psnr_inside", "psnr_outside",
    "selection_iou",
)
"""Per-twin numbers that the edit tables average (a key no run of a method has is None)."""


def edit_tables(runs: list[dict], methods: Sequence[str]) -> dict[str, list[dict]]:
    """Tables 2 and 3 from per-twin ``runs``: per kind, one row per method (in ``methods``'
    order) with PSNR, SSIM, LPIPS and seconds averaged over that kind's twins."""
    tables: dict[str, list[dict]] = {}
    for kind in ("color", "remove"):
        rows = []
        for method in methods:
            sel = [r for r in runs if r["kind"] == kind and r["method"] == method]
            if sel:
                rows.append({"method": method, "n": len(sel), **{key: _mean(sel, key) for key in TABLE_KEYS}})
        if rows:
            tables[kind] = rows
    return tables


def evaluate_edits(
    model: CategoryModel,
    category: Category,
    cases: Sequence[TwinCase],
    strategies: Sequence[str] = ("hybrid", "codes", "all"),
    options: EditOptions | None = None,
    nerf: NerfBaseline | None = None,
    lpips_weights: str | Path | None = None,
    device: torch.device | str = "cpu",
    seed: int = 0,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    paper: bool = True,
) -> dict:
    """The paper's edit protocol on ground-truth twins (Tables 2 and 3).

    For each twin in ``cases``: the unedited model's renders of the source's test views are
    scored against the twin (the reference row ``unedited``); then for each strategy the edit is
    made from the twin's scribbles with ``options`` (an :class:`~crfedit.edit.EditOptions`; its
    ``strategy`` is replaced) and scored the same way; with ``nerf`` a single-instance NeRF of
    the source is trained once per source (model files under ``workdir``, a temporary folder by
    default) and fine-tuned with the same edit, strategy ``all``.  Returns::

        {"runs": [{"twin", "kind", "source", "method", "n", "psnr", "ssim", "lpips", "seconds"}],
         "tables": {"color": [rows], "remove": [rows]}, "skipped": [{"method", "kind", "reason"}],
         "nerf_train_seconds": {source: s}, "ssim_note", "lpips_note"}

    ``seconds`` is the edit's optimization time (0 for ``unedited``), measured after a one-step
    warm-up edit that absorbs the process's one-off costs.  A strategy the model's
    architecture cannot use for a kind of twin (``codes`` without a separate code of that kind)
    is listed under ``skipped``.
    """

    options = options or EditOptions()
    unknown = [s for s in strategies if s not in STRATEGIES]
    if unknown:
        raise CrfError(f"--strategies {','.join(strategies)}: {unknown[0]!r} is not one of {', '.join(STRATEGIES)}")
    if not cases:
        raise CrfError(f"{category.root}: the dataset has no ground-truth twins (twins.json) to evaluate edits on")
    say = progress or (lambda _msg: None)
    runs: list[dict] = []
    skipped: list[dict] = []
    note = lpips_unavailable_reason(lpips_weights)

    def record(case: TwinCase, method: str, result: CategoryModel, seconds: float, instance: int | None = None, extra=None) -> None:
        nonlocal note
        k = case.instance if instance is None else instance
        preds = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in render_views(result, k, [v.camera for v in case.views])]
        score = score_images(preds, [v.rgb for v in case.views], lpips_weights)
        note = score["lpips_note"]
        ref = context[case.spec.name]
        row = {
            "twin": case.spec.name, "kind": case.spec.kind, "source": case.spec.source, "method": method,
            "n": score["n"], "psnr": _finite(score["psnr"]), "ssim": score["ssim"], "lpips": score["lpips"],
            "seconds": seconds, **region_scores(preds, case.views, ref["regions"]),
            "psnr_before": ref.get("psnr_before"), "psnr_ceiling": ref["psnr_ceiling"], **(extra or {}),
        }
        row["gap_closed"] = gap_closed(row["psnr"], row["psnr_before"], row["psnr_ceiling"])
        runs.append(row)
        psnr = "inf" if row["psnr"] is None else f"{row['psnr']:.2f}"
        say(f"{case.spec.name}: {method:<22} PSNR {psnr} dB  SSIM {row['ssim']:.3f}  {seconds:.2f} s")

    warm = next((s for s in strategies if strategy_problem(model, cases[0].spec.kind, s) is None), None)
    if warm is not None:  # the first edit of a process pays one-off costs; keep them out of the timings
        apply_twin_edit(model, cases[0], dataclasses.replace(options, strategy=warm, steps=1))
    context: dict[str, dict] = {}
    for case in cases:
        source_dir = category.instance(case.spec.source).path
        source_views = category.instance(case.spec.source).splits.get("test", [])[: len(case.views)]
        unedited = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in render_views(model, case.instance, [v.camera for v in source_views])]
        context[case.spec.name] = {
            "regions": changed_regions(source_views, case.views),
            "psnr_ceiling": _finite(score_images(unedited, [v.rgb for v in source_views])["psnr"]),
        }
        record(case, UNEDITED, model, 0.0)
        context[case.spec.name]["psnr_before"] = runs[-1]["psnr"]
        runs[-1]["psnr_before"] = runs[-1]["psnr"]
        runs[-1]["gap_closed"] = 0.0
        appear = None
        if case.spec.kind == "color":
            scribbled = category.instance(case.spec.source).view(case.spec.view)
            appear = appearance(source_dir, scribbled, case.scribble, case.spec.part, case.spec.color)
        sel = select(model, case.instance, [ScribbleView(case.camera, case.scribble, case.keep)])
        iou = {"selection_iou": selection_iou(model, sel, source_dir, source_views, case.spec.part)}
        for strategy in strategies:
            problem = strategy_problem(model, case.spec.kind, strategy)
            if problem is not None:
                entry = {"method": strategy, "kind": case.spec.kind, "reason": problem}
                if entry not in skipped:
                    skipped.append(entry)
                continue
            result = apply_twin_edit(model, case, dataclasses.replace(options, strategy=strategy), appear=appear, selection=sel)
            record(case, strategy, result.model, result.seconds, extra=iou)
        if paper:
            result = apply_twin_edit(model, case, dataclasses.replace(options, strategy="hybrid"), method="paper")
            record(case, PAPER_METHOD, result.model, result.seconds)

    train_seconds: dict[str, float] = {}
    if nerf is not None:
        with tempfile.TemporaryDirectory(prefix="crfedit-nerf-") as tmp:
            folder = Path(workdir) if workdir is not None else Path(tmp)
            folder.mkdir(parents=True, exist_ok=True)
            baselines: dict[str, CategoryModel] = {}
            for case in cases:
                source = case.spec.source
                if source not in baselines:
                    budget = f"{nerf.steps} steps" + (f" or {nerf.minutes:g} min" if nerf.minutes else "")
                    say(f"{source}: training a single-instance NeRF ({budget})")
                    path = folder / f"nerf_{source}.safetensors"
                    baselines[source], train_seconds[source] = train_single_instance_nerf(
                        category, source, model.cfg, nerf, path, device, seed
                    )
                result = apply_twin_edit(baselines[source], case, dataclasses.replace(options, strategy="all"), instance=0, method="paper")
                record(case, NERF_BASELINE, result.model, result.seconds, instance=0)

    methods = [UNEDITED, *strategies, *([PAPER_METHOD] if paper else []), *([NERF_BASELINE] if nerf else [])]
    return {
        "runs": runs,
        "tables": edit_tables(runs, methods),
        "skipped": skipped,
        "nerf_train_seconds": train_seconds,
        "ssim_note": SSIM_NOTE,
        "lpips_note": note,
    }


# ----------------------------------------------------------------------------- ablation (Table 1)


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


def held_out_split(category: Category) -> str:
    """``test`` when every instance has test views, else ``val``."""
    return "test" if all("test" in inst.splits for inst in category.instances) else "val"


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
        raise CrfError(f"--minutes {minutes:g}: must be a positive number")
    if steps is not None and steps < 1:
        raise CrfError(f"--steps {steps}: must be at least 1")
    base = base or make_config("fast")
    if steps is not None:
        base = dataclasses.replace(base, steps=steps)
    elif minutes is not None:
        base = dataclasses.replace(base, steps=max(base.steps, 10**9))  # the time budget ends every run
    split = split or held_out_split(category)
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
                "psnr": _finite(score["psnr"]), "ssim": score["ssim"], "lpips": score["lpips"],
            })
            say(f"{arch}: {result.steps} steps in {result.seconds:.1f} s, PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.3f}")
    return rows
