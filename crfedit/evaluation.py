"""Rendering views of a trained model and scoring them: the paper's evaluation protocols.

* :func:`score_model` — the one scoring loop: each instance's views of a split rendered with
  the dataset's cameras and scored against its images (:func:`score_instance`).
* :func:`evaluate_recon` — reconstruction of held-out views, per instance and overall.
* :func:`evaluate_edits` — Tables 2 (colour) and 3 (shape / removal) of Liu et al.: every
  ground-truth twin of the dataset (``twins.json``) is edited from its scribbles with each
  update strategy (and, optionally, the single-instance NeRF baseline), every test view of the
  source instance is rendered with the edit applied and scored against the twin's test views.

Table 1 (the architecture ablation) is :mod:`crfedit.ablation`.  Scores are PSNR (dB,
averaged per image), SSIM (:data:`SSIM_NOTE`) and LPIPS-AlexNet when a weights file is
configured (:mod:`crfedit.metrics`).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .cameras import Camera
from .config import Config
from .data.format import TwinSpec, read_mask
from .data.loading import Category, View, load_category, load_twins
from .distributed import SINGLE, Ranks
from .edit import STRATEGIES, EditOptions, EditResult, edit_color, remove
from .edit.params import GROUP, trained_prefixes
from .edit.selection import Selection, select_for
from .errors import CrfError
from .metrics import lpips_unavailable_reason, score_images
from .model import CategoryModel
from .parts import labelled_names
from .renderer import RenderOutput, render_camera
from .runtime import resolve_device
from .train import train
from .twin_scores import appearance, changed_regions, gap_closed, region_scores, selection_iou

SSIM_NOTE = "SSIM: 11×11 Gaussian window, σ=1.5, on RGB"
LPIPS_SKIPPED = "LPIPS: skipped (no weights)"
UNEDITED = "unedited"
NERF_BASELINE = "nerf (single instance)"
PAPER_METHOD = "hybrid, --method paper"
"""The paper's own losses (scribbled view's rays only) with its hybrid update, for comparison."""
DEFAULT_CHUNK = 16384
HELD_OUT = ("test", "val")

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


def part_labels_seen(model: CategoryModel, cases: Sequence["TwinCase"]) -> list[str] | None:
    """The twins' sources whose part maps trained the model's F_part, as the file records them
    (:func:`~crfedit.parts.labelled_names`); None without a head or without the record (a file
    written before it)."""
    labelled = None if model.field.F_part is None else labelled_names(model.meta)
    return None if labelled is None else sorted({c.spec.source for c in cases} & set(labelled))


def part_labels_warning(model: CategoryModel, cases: Sequence["TwinCase"]) -> str | None:
    """A one-line warning when the model's part head was trained on the part maps of a twin's
    source: its selections then read the answer the twin scores.  Read from the file's record
    (:func:`part_labels_seen`), so that twins of another dataset of the same chairs
    (``dataset synth --twin-sources``) are caught too; a file written before the record warns
    only for ``part_labels=all``."""
    if not cases or model.field.F_part is None:
        return None
    seen = part_labels_seen(model, cases)
    if seen is None:
        if model.cfg.part_labels != "all":
            return None
        return ("the model's part head F_part was trained on the part maps of every instance, the twins' sources "
                "among them (part_labels=all): its selections read the answer; train with --set part_labels=not-twins "
                "to benchmark edits")
    if not seen:
        return None
    named = ", ".join(seen[:3]) + (f" and {len(seen) - 3} more" if len(seen) > 3 else "")
    return (f"the model's part head F_part was trained on the part maps of {len(seen)} of the twins' sources ({named}): "
            f"their selections read the answer; train with --set part_labels=not:twins,NAME,… to hold them out")


def model_width(model: CategoryModel, split: str = "test") -> int | None:
    """The image width the model's views of ``split`` were stored at (else its training width);
    None (each view at its own size) for views of several widths."""
    table = model.views.get(split) or model.views.get("train") or next(iter(model.views.values()), None)
    if table is None or len(table.widths) > 1:
        return None
    return table.width


def load_category_for(model: CategoryModel, data: str | Path, split: str = "test") -> Category:
    """The dataset at ``data`` loaded at the resolution the model was trained and stored at."""
    return load_category(Path(data), res=model_width(model, split))


def held_out_split(category: Category, prefer: str = "test") -> str:
    """``prefer`` (``test`` or ``val``) when any instance has views of it, else the other one.

    Training's end-of-run score prefers ``val`` (it keeps ``test`` unseen); the ablation and
    the benchmarks prefer ``test``.
    """
    if prefer not in HELD_OUT:
        raise CrfError(f"held-out split {prefer!r}: expected test or val")
    other = HELD_OUT[1 - HELD_OUT.index(prefer)]
    return prefer if any(prefer in inst.splits for inst in category.instances) else other


# ----------------------------------------------------------------------------- reconstruction


def render_views(
    model: CategoryModel, instance: int, cameras: Sequence[Camera], chunk: int = DEFAULT_CHUNK
) -> list[RenderOutput]:
    """Render ``cameras`` of ``instance`` (on white), with the instance's baked overrides if any.

    Deterministic: the same model and cameras give bit-identical images.
    """
    field = model.field_for(instance)
    return [render_camera(field, cam, instance, chunk=chunk) for cam in cameras]


def score_instance(
    model: CategoryModel, instance: int, views: Sequence[View], lpips_weights: str | Path | None = None,
    chunk: int = DEFAULT_CHUNK,
) -> dict:
    """Render ``instance`` at ``views``' cameras and score against their images (score_images)."""
    outs = render_views(model, instance, [v.camera for v in views], chunk)
    preds = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in outs]
    return score_images(preds, [v.rgb for v in views], lpips_weights)


def score_model(
    model: CategoryModel,
    category: Category,
    split: str = "test",
    max_views: int | None = None,
    instances: Sequence[int] | None = None,
    lpips_weights: str | Path | None = None,
    chunk: int = DEFAULT_CHUNK,
    ranks: Ranks = SINGLE,
    progress: Progress | None = None,
) -> dict:
    """PSNR / SSIM (and LPIPS when weights are configured) of the model's renders of ``split``.

    ``instances`` are model indices or names (default: every model instance that ``category`` holds; a
    given one that it lacks is an error); each is matched to the dataset's instance of the same
    name, and its first ``max_views`` views of ``split`` (default: all) are rendered with the
    dataset's cameras and scored against its images (:func:`score_instance`).  Returns::

        {"split": "test", "n": total views, "psnr": mean dB, "ssim": mean, "lpips": mean or None,
         "lpips_note": why LPIPS was skipped or None,
         "instances": {name: {"n", "psnr", "ssim", "lpips"}},
         "without_views": [names of the instances with no view of the split, not in the means]}

    Means are over all scored views (each view counts once, whatever its instance).
    Under torchrun (``ranks``) each rank scores every ``world``-th instance and every rank
    returns the gathered result.  ``progress`` gets a line per instance scored (rank 0's).
    """
    if max_views is not None and max_views < 1:
        raise CrfError(f"--max-views {max_views}: must be at least 1")
    if instances is None:
        indices = [k for k, name in enumerate(model.names) if name in category.names]
        if not indices:
            shown = ", ".join(model.names[:4]) + (", …" if len(model.names) > 4 else "")
            raise CrfError(f"none of the model's instances ({shown}) is in {category.root}")
    else:
        if isinstance(instances, (str, bytes)) or not hasattr(instances, "__len__") or not len(instances):  # a bare name iterates its letters
            raise CrfError(f"instances {instances!r}: give a list of instance names or indices (or None for all)")
        indices = [model.instance_index(k) for k in instances]  # names too; an unknown one is one line
        missing = [model.names[k] for k in indices if model.names[k] not in category.names]
        if missing:
            raise CrfError(f"instance {missing[0]!r} of the model is not in the dataset {category.root}")
    per_instance, note = {}, None
    say = progress if progress is not None and ranks.main else (lambda _msg: None)
    mine = ranks.shard(indices)
    started = time.perf_counter()
    for i, k in enumerate(mine):
        name = model.names[k]
        views = category.instance(name).splits.get(split, [])[:max_views]
        if views:
            score = score_instance(model, k, views, lpips_weights, chunk)
            note = score["lpips_note"]
            per_instance[name] = {key: score[key] for key in ("n", "psnr", "ssim", "lpips")}
            elapsed = time.perf_counter() - started
            say(f"{name} ({i + 1}/{len(mine)}{'' if ranks.world == 1 else ' on rank 0'}): {len(views)} view{'s' * (len(views) != 1)}, "
                f"PSNR {score['psnr']:.2f} dB, {elapsed / (i + 1):.2f} s per instance, ~{elapsed / (i + 1) * (len(mine) - i - 1):.0f} s left")
    if ranks.world > 1:
        parts = ranks.gather((per_instance, note), "gathering the scores")
        scored = {name: row for part, _ in parts for name, row in part.items()}
        per_instance = {name: scored[name] for name in model.names if name in scored}
        note = next((n for part, n in parts if part), note)
    if not per_instance:
        has = sorted({s for k in indices for s, views in category.instance(model.names[k]).splits.items() if views})
        raise CrfError(f"{category.root}: none of the model's instances has {split} views in this dataset"
                       + (f" (only {', '.join(has)})" if has else ""))
    rows = list(per_instance.values())
    n = np.array([r["n"] for r in rows], dtype=np.float64)

    def mean(key: str) -> float | None:
        values = [r[key] for r in rows]
        return None if any(v is None for v in values) else float(np.sum(n * np.array(values)) / n.sum())

    unscored = [model.names[k] for k in indices if model.names[k] not in per_instance]  # no views of the split
    return {
        "split": split, "n": int(n.sum()), "psnr": mean("psnr"), "ssim": mean("ssim"), "lpips": mean("lpips"),
        "lpips_note": note, "instances": per_instance, "without_views": unscored,
    }


def evaluate_recon(
    model: CategoryModel,
    category: Category,
    split: str = "test",
    max_views: int | None = None,
    lpips_weights: str | Path | None = None,
    ranks: Ranks = SINGLE,
    progress: Progress | None = None,
) -> dict:
    """Held-out reconstruction scores of every model instance that ``category`` holds.

    :func:`score_model`'s result plus ``"ssim_note"`` and ``"dataset_match"`` (whether
    ``category`` is the dataset the model was trained on).  ``lpips_weights`` (or
    ``$CRFEDIT_LPIPS_WEIGHTS``) enables LPIPS; a configured file that is missing or invalid is
    an error, never a silent skip.
    """
    if split not in ("train", "val", "test"):
        raise CrfError(f"--split {split}: expected train, val or test")
    score = score_model(model, category, split, max_views, lpips_weights=lpips_weights, ranks=ranks, progress=progress)
    instances = score.pop("instances")
    match = fingerprint_warning(model, category) is None
    return {**score, "ssim_note": SSIM_NOTE, "dataset_match": match, "instances": instances}


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
    """:func:`~crfedit.data.loading.load_twins` output resolved against the model and dataset.

    The scribbled view is the source's view ``spec.view`` in ``category`` (so the masks, read at
    that view's width, line up with its camera).
    """
    cases = []
    for spec, data in twins:
        if spec.source not in model.names:
            raise CrfError(f"twin {spec.name}: source instance {spec.source!r} is not in the model")
        try:
            view = category.instance(spec.source).view(spec.view)
        except CrfError as e:  # a twin scribbled on a view the source does not have: name the twin and its file
            raise CrfError(f"twin {spec.name} ({category.root / 'twins.json'}): {e}") from None
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


def twin_selection(model: CategoryModel, case: TwinCase) -> Selection:
    """The selection the twin's edit makes from its scribbles (the edit kind's options)."""
    return select_for(model, case.instance, case.camera, case.scribble, case.keep, case.spec.kind)


def twin_appearance(category: Category, case: TwinCase) -> tuple[float, ...] | None:
    """The colour a colour twin's part should *appear* under its scribble
    (:func:`~crfedit.twin_scores.appearance`); None for other twins or without part maps."""
    if case.spec.kind != "color":
        return None
    source = category.instance(case.spec.source)
    return appearance(source.path, source.view(case.spec.view), case.scribble, case.spec.part, case.spec.color)


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


def below_unedited(rows: list[dict]) -> int | None:
    """How many of ``rows`` (one method's per-twin runs) end with a lower PSNR than the
    unedited render's (``psnr_before``): edits that did harm.  #14's removals must have none.
    None when a run lacks either number."""
    if any(r.get("psnr") is None or r.get("psnr_before") is None for r in rows):
        return None
    return sum(r["psnr"] < r["psnr_before"] for r in rows)


def edit_tables(runs: list[dict], methods: Sequence[str]) -> dict[str, list[dict]]:
    """Tables 2 and 3 from per-twin ``runs``: per kind, one row per method (in ``methods``'
    order) with PSNR, SSIM, LPIPS and seconds averaged over that kind's twins, and the count of
    twins that end below unedited (:func:`below_unedited`).  ``gap_closed`` averages the twins
    whose gap is defined (ceiling above unedited), ``gap_closed_n`` of them."""
    tables: dict[str, list[dict]] = {}
    for kind in ("color", "remove"):
        rows = []
        for method in methods:
            sel = [r for r in runs if r["kind"] == kind and r["method"] == method]
            if sel:
                row = {"method": method, "n": len(sel), **{key: _mean(sel, key) for key in TABLE_KEYS}, "below_unedited": below_unedited(sel)}
                # a twin whose model reconstructs it no better than unedited has no gap to close: left out of the mean, counted
                defined = [r for r in sel if r.get("gap_closed") is not None]
                row["gap_closed"] = _mean(defined, "gap_closed") if defined else None
                row["gap_closed_n"] = len(defined)
                rows.append(row)
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
    ranks: Ranks = SINGLE,
    on_edit: Callable[[TwinCase, str, EditResult], None] | None = None,
) -> dict:
    """The paper's edit protocol on ground-truth twins (Tables 2 and 3).

    Under torchrun (``ranks``) each rank edits every ``world``-th twin and every rank returns
    the gathered result, in the twins' order (the same as one process gives).

    For each twin in ``cases``: the unedited model's renders of the source's test views are
    scored against the twin (the reference row ``unedited``); then for each strategy the edit is
    made from the twin's scribbles with ``options`` (an :class:`~crfedit.edit.EditOptions`; its
    ``strategy`` is replaced) and scored the same way; with ``nerf`` a single-instance NeRF of
    the source is trained once per source (model files under ``workdir``, a temporary folder by
    default) and fine-tuned with the same edit, strategy ``all``; its rows' ``psnr_before`` and
    ``psnr_ceiling`` (so its gap closed) are the NeRF's own: its unedited render against the
    twin, its reconstruction of the source.  Returns::

        {"runs": [{"twin", "kind", "source", "method", "n", "psnr", "ssim", "lpips", "seconds"}],
         "tables": {"color": [rows], "remove": [rows]}, "skipped": [{"method", "kind", "reason"}],
         "nerf_train_seconds": {source: s}, "ssim_note", "lpips_note",
         "part_labels_seen": the twins' sources whose part maps trained F_part (None: unknown),
         "settings": the seed and the edits' options the scores depend on}

    The edits run where ``model`` is (move it with ``model.to``); ``device`` (checked: cuda
    without one is an error) is where the single-instance NeRFs train.

    ``seconds`` is the edit's optimization time (0 for ``unedited``), measured after a one-step
    warm-up edit that absorbs the process's one-off costs.  A strategy the model's
    architecture cannot use for a kind of twin (``codes`` without a separate code of that kind)
    is listed under ``skipped``.  ``on_edit(case, strategy, result)`` is handed each strategy's
    edit (:class:`~crfedit.edit.EditResult`) after it is scored: the quickstart saves its deltas.
    """

    options = options or EditOptions()
    device = resolve_device(device)
    unknown = [s for s in strategies if s not in STRATEGIES]
    if unknown:
        raise CrfError(f"--strategies {','.join(strategies)}: {unknown[0]!r} is not one of {', '.join(STRATEGIES)}")
    twice = sorted({s for s in strategies if list(strategies).count(s) > 1})
    if twice:
        raise CrfError(f"--strategies {','.join(strategies)}: {twice[0]!r} is named twice (each row would count its twins twice)")
    if not cases:
        raise CrfError(f"{category.root}: the dataset has no ground-truth twins (twins.json) to evaluate edits on")
    say = progress if progress is not None and ranks.main else (lambda _msg: None)  # rank 0's lines, as eval recon's
    runs: list[dict] = []
    skipped: list[dict] = []
    note = lpips_unavailable_reason(lpips_weights)

    def record(case: TwinCase, method: str, result: CategoryModel, seconds: float, instance: int | None = None, extra=None,
               reference: dict | None = None) -> None:
        """Score ``result``'s render of the twin's views; ``reference`` replaces the twin's
        psnr_before and psnr_ceiling (the NeRF baseline's own: its unedited render and its
        reconstruction, not the conditional model's)."""
        nonlocal note
        k = case.instance if instance is None else instance
        preds = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in render_views(result, k, [v.camera for v in case.views])]
        score = score_images(preds, [v.rgb for v in case.views], lpips_weights)
        note = score["lpips_note"]
        ref = {**context[case.spec.name], **(reference or {})}
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
    if nerf is None:
        mine = ranks.shard(cases)
    else:  # by source chair: each single-instance NeRF is trained on one rank (its twins shared out, it trained on each)
        sources = list(dict.fromkeys(case.spec.source for case in cases))
        taken = set(ranks.shard(sources))
        mine = [case for case in cases if case.spec.source in taken]
    for case in mine:
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
        runs[-1]["gap_closed"] = gap_closed(runs[-1]["psnr"], runs[-1]["psnr"], context[case.spec.name]["psnr_ceiling"])  # 0, or None with no gap
        appear = twin_appearance(category, case)
        sel = twin_selection(model, case)
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
            if on_edit is not None:
                on_edit(case, strategy, result)
        if paper:
            result = apply_twin_edit(model, case, dataclasses.replace(options, strategy="hybrid"), method="paper")
            record(case, PAPER_METHOD, result.model, result.seconds)

    train_seconds: dict[str, float] = {}
    if nerf is not None:
        with tempfile.TemporaryDirectory(prefix="crfedit-nerf-") as tmp:
            folder = Path(workdir) if workdir is not None else Path(tmp)
            folder.mkdir(parents=True, exist_ok=True)
            baselines: dict[str, CategoryModel] = {}
            for case in mine:
                source = case.spec.source
                if source not in baselines:
                    budget = f"{nerf.steps} steps" + (f" or {nerf.minutes:g} min" if nerf.minutes else "")
                    say(f"{source}: training a single-instance NeRF ({budget})")
                    path = folder / f"nerf_{source}.safetensors"
                    baselines[source], train_seconds[source] = train_single_instance_nerf(
                        category, source, model.cfg, nerf, path, device, seed
                    )
                # the NeRF's own gap: its unedited render against the twin, and (the twin's views are the
                # source's test poses: one render) its reconstruction of the source
                source_views = category.instance(source).splits.get("test", [])[: len(case.views)]
                unedited = [o.rgb.clamp(0.0, 1.0).cpu().numpy() for o in render_views(baselines[source], 0, [v.camera for v in case.views])]
                reference = {"psnr_before": _finite(score_images(unedited, [v.rgb for v in case.views])["psnr"]),
                             "psnr_ceiling": _finite(score_images(unedited[: len(source_views)], [v.rgb for v in source_views])["psnr"])}
                result = apply_twin_edit(baselines[source], case, dataclasses.replace(options, strategy="all"), instance=0, method="paper")
                record(case, NERF_BASELINE, result.model, result.seconds, instance=0, reference=reference)

    if ranks.world > 1:  # every rank edited its share of the twins: gather them in the twins' order
        parts = ranks.gather((runs, skipped, train_seconds, note), "gathering the edit scores")
        order = {case.spec.name: i for i, case in enumerate(cases)}
        # as one process lists them: every twin's runs in the twins' order, then the NeRF baseline's
        runs = sorted((r for part in parts for r in part[0]), key=lambda r: (r["method"] == NERF_BASELINE, order[r["twin"]]))
        skipped = [e for i, part in enumerate(parts) for e in part[1] if e not in [x for p in parts[:i] for x in p[1]]]
        train_seconds = {k: v for part in parts for k, v in part[2].items()}
        note = next((part[3] for part in parts if part[0]), note)
    methods = [UNEDITED, *strategies, *([PAPER_METHOD] if paper else []), *([NERF_BASELINE] if nerf else [])]
    return {
        "runs": runs,
        "tables": edit_tables(runs, methods),
        "skipped": skipped,
        "nerf_train_seconds": train_seconds,
        "ssim_note": SSIM_NOTE,
        "lpips_note": note,
        "part_labels_seen": part_labels_seen(model, cases),
        "settings": {"seed": seed, "strategies": list(strategies), **{k: getattr(options, k) for k in ("steps", "lr", "rays", "penalty", "recolor")},
                     "nerf_baseline": dataclasses.asdict(nerf) if nerf else None, "device": str(model.device),
                     "threads": torch.get_num_threads(), "world_size": ranks.world, "lpips": lpips_weights is not None},
    }
