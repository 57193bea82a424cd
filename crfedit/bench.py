"""Speed against error: how much accuracy each knob that saves time costs.

Three groups of measurements, each a set of curves of PSNR against seconds:

* ``train`` — held-out PSNR against training time, one curve per preset (and per marching
  density ``steps_per_cell`` of the fast preset).  The points of a curve are checkpoints of
  *one* run: training writes its model file every ``checkpoint_every`` steps, and the
  ``on_step`` callback copies the file aside each time the run's progress (the larger of
  step/steps and elapsed/budget, as the learning-rate schedule reads it) passes the next of
  ``checkpoints`` equal fractions; the copies are scored after training, so scoring never
  eats into the training clock.  The copies' own cost is subtracted from the reported times.
  The checkpoint interval comes from a short probe run's step rate.
* ``render`` — PSNR of a trained model against seconds per rendered view, varying the samples
  per ray: ``steps_per_cell`` (grid sampler) or coarse + fine samples (hierarchical sampler).
* ``edit`` — PSNR against a ground-truth twin (the dataset's ``twins.json``) against the edit's
  time (its selection made once per twin beforehand and not timed, as ``crfedit eval edits``
  times it), one curve per number of edit rays (and one with feature caching off), points
  over the number of edit steps.

:func:`run_bench` measures and returns a :class:`BenchReport` stamped with the machine
(:func:`crfedit.machine.machine_info`); :func:`crfedit.report.write_outputs` writes it as CSV,
plots and markdown.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import torch

from .config import PRESETS, Config, make_config
from .data.loading import Category, load_category
from .data.synth import SynthConfig, write_synth_category
from .edit import EditOptions
from .errors import CrfError
from .ablation import warm_up_training
from .evaluation import (
    apply_twin_edit, held_out_split, load_twin_cases, render_views, score_instance, score_model, twin_appearance, twin_selection,
)
from .machine import machine_info
from .metrics import score_images
from .model import CategoryModel, load_model
from .train import train

UNBOUNDED_STEPS = 10**9
"""The step cap of a time-budgeted run: the budget alone ends it and drives the schedule."""

Progress = Callable[[str], None]


@dataclass(frozen=True)
class BenchSettings:
    """What :func:`run_bench` sweeps.  The defaults take about 25 minutes on 2 CPU cores."""

    presets: tuple[str, ...] = ("fast", "paper")
    """One training curve per preset."""
    minutes: float = 5.0
    """Training time of each curve."""
    steps: int | None = None
    """Optional step cap of each training curve (whichever of steps and minutes ends first)."""
    checkpoints: int = 6
    """Points scored along each training curve, at equal fractions of it, the last at its end."""
    train_steps_per_cell: tuple[float, ...] = (2.0,)
    """Extra fast-preset training curves at these marching densities (the preset has 1)."""
    render_steps_per_cell: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0, 8.0)
    """Marching densities a grid-sampler model is rendered at."""
    render_samples: tuple[tuple[int, int], ...] = ((16, 32), (32, 64), (64, 128))
    """(coarse, fine) samples per ray a hierarchical-sampler model is rendered at."""
    edit_steps: tuple[int, ...] = (10, 30, 100, 300)
    edit_rays: tuple[int, ...] = (256, 1024, 4096)
    edit_uncached: bool = True
    """Also an edit curve with feature caching off (at 1024 rays, or the first of edit_rays)."""
    eval_instances: int = 4
    """Held-out scores use the first this many instances …"""
    eval_views: int = 2
    """… and this many held-out views of each."""
    sets: tuple[str, ...] = ()
    """``KEY=VALUE`` config overrides applied to every training run (as ``--set``)."""
    seed: int = 0

    @classmethod
    def tiny(cls) -> "BenchSettings":
        """A sweep of seconds on a 2-chair, 16-pixel category (used by the tests)."""
        return cls(
            presets=("fast",), minutes=0.5, steps=24, checkpoints=2, train_steps_per_cell=(),
            render_steps_per_cell=(1.0, 2.0), render_samples=(), edit_steps=(2, 4), edit_rays=(64,),
            eval_instances=2, eval_views=1, sets=("rays=128", "occ_res=16", "grid_res=16"),
        )

    def validated(self) -> "BenchSettings":
        checks = [
            (len(self.presets) > 0, "--presets: give at least one preset"),
            (self.minutes > 0 and math.isfinite(self.minutes), f"--minutes {self.minutes:g}: must be a finite positive number"),
            (self.steps is None or self.steps >= 1, f"--steps {self.steps}: must be at least 1"),
            (self.checkpoints >= 1, f"--checkpoints {self.checkpoints}: must be at least 1"),
            (all(v > 0 for v in (*self.train_steps_per_cell, *self.render_steps_per_cell)), "samples per cell must be > 0"),
            (all(c >= 1 and f >= 0 for c, f in self.render_samples), "render samples: coarse ≥ 1 and fine ≥ 0"),
            (all(s >= 1 for s in self.edit_steps), "--edit-steps: each must be at least 1"),
            (all(r >= 2 for r in self.edit_rays), "--edit-rays: each must be at least 2"),
            (self.eval_instances >= 1 and self.eval_views >= 1, "--eval-instances and --eval-views must be at least 1"),
        ]
        for ok, message in checks:
            if not ok:
                raise CrfError(message)
        for preset in self.presets:
            if preset not in PRESETS:  # named as bench's option is spelt (make_config's line says --preset)
                raise CrfError(f"--presets {','.join(self.presets)}: {preset} is not a preset (expected {', '.join(PRESETS)})")
            make_config(preset, sets=list(self.sets))  # unknown keys fail here, before any work
        return self


@dataclass(frozen=True)
class BenchRow:
    """One measured point."""

    group: str  # train | render | edit
    curve: str  # the plotted curve it belongs to, e.g. "fast", "paper", "color, 1024 rays"
    knob: str  # what varies along the curve: step | steps_per_cell | samples | edit_steps
    value: str  # the knob's value at this point
    seconds: float  # training time so far | seconds per rendered view | edit time (its selection made beforehand)
    psnr: float
    ssim: float
    views: int  # images scored


@dataclass
class BenchReport:
    rows: list[BenchRow]
    machine: dict[str, str]
    settings: BenchSettings
    data: str
    notes: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- training curves


def _score(model: CategoryModel, category: Category, settings: BenchSettings) -> dict:
    instances = range(min(settings.eval_instances, len(model.names)))
    return score_model(model, category, held_out_split(category, "test"), settings.eval_views, instances)


def probe_steps_per_second(category: Category, cfg: Config, device, seconds: float, folder: Path, seed: int) -> float:
    """Training steps per second of ``cfg`` measured by a short throwaway run."""

    probe = dataclasses.replace(cfg, steps=UNBOUNDED_STEPS, checkpoint_every=UNBOUNDED_STEPS)
    path = folder / "probe.safetensors"
    _, result = train(category, probe, path, device, seed=seed, minutes=seconds / 60.0)
    path.unlink(missing_ok=True)
    return result.steps / max(result.seconds, 1e-9)


def train_curve(
    category: Category, cfg: Config, label: str, settings: BenchSettings, device, folder: Path, progress: Progress
) -> tuple[list[BenchRow], CategoryModel]:
    """Train ``cfg`` once for the settings' budget; score ``checkpoints`` points along the run
    and its end (see the module docstring).  Returns (rows, the trained model)."""

    budget = 60.0 * settings.minutes
    n = settings.checkpoints
    if settings.steps is not None:
        interval = max(1, settings.steps // (2 * n))
    else:
        rate = probe_steps_per_second(category, cfg, device, min(30.0, max(2.0, 0.03 * budget)), folder, settings.seed)
        interval = max(1, int(rate * budget / (3 * n)))
    cfg = dataclasses.replace(cfg, steps=settings.steps or UNBOUNDED_STEPS, checkpoint_every=interval)
    slug = "".join(c if c.isalnum() else "_" for c in label)
    out = folder / f"{slug}.safetensors"
    snapshots: list[tuple[int, float, Path]] = []
    state = {"next": 1, "pending": None, "overhead": 0.0}

    def on_step(step: int, _loss: float, _psnr: float, rays_per_s: float) -> None:
        elapsed = cfg.rays * step / rays_per_s if rays_per_s > 0 else 0.0
        if state["pending"] is not None:  # the previous step's checkpoint is on disk now
            t0 = time.perf_counter()
            s, seconds = state["pending"]
            path = folder / f"{slug}.step{s}.safetensors"
            shutil.copyfile(out, path)
            snapshots.append((s, seconds, path))
            state["pending"] = None
            state["overhead"] += time.perf_counter() - t0
        if step % cfg.checkpoint_every == 0:
            done = max(step / cfg.steps, elapsed / budget)
            if done * n >= state["next"]:
                state["pending"] = (step, elapsed - state["overhead"])
                state["next"] = math.floor(done * n) + 1

    progress(f"train {label}: {settings.minutes:g} min" + (f" or {settings.steps} steps" if settings.steps else "")
             + f", checkpoint every {interval} steps")
    model, result = train(category, cfg, out, device, seed=settings.seed, minutes=settings.minutes, on_step=on_step)
    points = []
    for s, sec, p in snapshots:
        if s < result.steps:
            m = load_model(p, device)[0]
            if m.meta.get("step") != str(s):  # train() writes step s's checkpoint right after on_step(s)
                raise RuntimeError(f"checkpoint copied after step {s} holds step {m.meta.get('step')}")
            points.append((s, sec, m))
    points.append((result.steps, result.seconds - state["overhead"], model))
    rows = []
    for step, seconds, m in points:
        score = _score(m, category, settings)
        rows.append(BenchRow("train", label, "step", str(step), seconds, score["psnr"], score["ssim"], score["n"]))
        progress(f"  {label} step {step} ({seconds:.1f} s): PSNR {score['psnr']:.2f} dB")
    for _, _, p in snapshots:
        p.unlink(missing_ok=True)
    return rows, model


# ----------------------------------------------------------------------------- render curves


def with_sampling(model: CategoryModel, **changes) -> CategoryModel:
    """The model rendering with other sampling settings (``steps_per_cell``, ``n_coarse``,
    ``n_fine``); weights and grids are shared, not copied."""
    f = copy.copy(model.field)  # a shallow copy shares parameters and buffers
    f.cfg = dataclasses.replace(model.field.cfg, **changes).validated()
    return dataclasses.replace(model, field=f)


def render_curve(
    model: CategoryModel, category: Category, label: str, knob: str, variants: Sequence[tuple[str, dict]],
    settings: BenchSettings, progress: Progress,
) -> list[BenchRow]:
    """Seconds per view and PSNR of held-out views rendered with each sampling variant."""
    split = held_out_split(category, "test")
    pairs = [
        (k, view)
        for k in range(min(settings.eval_instances, len(model.names)))
        if model.names[k] in category.names
        for view in category.instance(model.names[k]).splits.get(split, [])[: settings.eval_views]
    ]
    if not pairs:
        return []
    render_views(model, pairs[0][0], [pairs[0][1].camera])  # warm-up: first calls pay one-off costs
    rows = []
    for value, changes in variants:
        m = with_sampling(model, **changes)
        t0 = time.perf_counter()
        preds = [render_views(m, k, [v.camera])[0].rgb.clamp(0, 1).cpu().numpy() for k, v in pairs]
        seconds = (time.perf_counter() - t0) / len(pairs)
        score = score_images(preds, [v.rgb for _, v in pairs])
        rows.append(BenchRow("render", label, knob, value, seconds, score["psnr"], score["ssim"], score["n"]))
        progress(f"render {label} {knob}={value}: {seconds * 1000:.1f} ms/view, PSNR {score['psnr']:.2f} dB")
    return rows


def render_variants(cfg: Config, settings: BenchSettings) -> tuple[str, list[tuple[str, dict]]]:
    """(knob, variants) that change the samples per ray of a model of ``cfg``."""
    if cfg.sampler == "grid":
        return "steps_per_cell", [(f"{v:g}", {"steps_per_cell": float(v)}) for v in settings.render_steps_per_cell]
    return "samples", [(f"{c}+{f}", {"n_coarse": c, "n_fine": f}) for c, f in settings.render_samples]


# ----------------------------------------------------------------------------- edit curves


def edit_curves(model: CategoryModel, category: Category, settings: BenchSettings, progress: Progress,
                notes: list[str] | None = None) -> list[BenchRow]:
    """PSNR against the first colour twin and the first removal twin over edit steps × rays.

    Each twin's edit is made as ``crfedit eval edits`` makes it: from its selection, made once
    and not timed (the curves show what steps and rays cost), a recolour targeting the colour
    the part should appear (:func:`~crfedit.evaluation.twin_appearance`).  A point whose edit
    diverges or is refused is left out, with a line in ``notes``, and the sweep goes on."""

    if not settings.edit_steps or not settings.edit_rays:
        return []
    cases = load_twin_cases(model, category)
    firsts = [next((c for c in cases if c.spec.kind == kind), None) for kind in ("color", "remove")]
    chosen = [c for c in firsts if c is not None]
    rows = []
    if chosen:  # the first edit of a process pays one-off costs; keep them out of the timings
        try:
            apply_twin_edit(model, chosen[0], EditOptions(steps=1, rays=settings.edit_rays[0], seed=settings.seed))
        except CrfError:  # refused (a collapsed model): each point below says so for itself
            pass
    def leave_out(what: str, why: str) -> None:
        if notes is not None:
            notes.append(f"{what} left out: {why}")
        progress(f"{what}: left out ({why})")

    plain = 1024 if 1024 in settings.edit_rays else settings.edit_rays[0]
    runs = [(rays, True) for rays in settings.edit_rays] + ([(plain, False)] if settings.edit_uncached else [])
    for case in chosen:
        try:
            appear, selection = twin_appearance(category, case), twin_selection(model, case)
        except CrfError as e:  # e.g. a collapsed model no longer shows the scribbled part
            why = f"{e}" + ("; does the model render the chair? its training may have collapsed (see the train curve)"
                            if "background only" in str(e) else "")
            leave_out(f"edit curves of {case.spec.name}", why)
            continue
        for rays, cache in runs:
            label = f"{case.spec.kind}, {rays} rays" + ("" if cache else ", no cache")
            for steps in settings.edit_steps:
                options = EditOptions(strategy="hybrid", steps=steps, rays=rays, seed=settings.seed, cache=cache)
                try:
                    result = apply_twin_edit(model, case, options, appear=appear, selection=selection)
                except CrfError as e:  # diverged, or refused (a scribble a collapsed model no longer shows): that point only
                    leave_out(f"edit {label}, {steps} steps", str(e))
                    continue
                score = score_instance(result.model, case.instance, case.views)
                rows.append(BenchRow("edit", label, "edit_steps", str(steps), result.seconds, score["psnr"], score["ssim"], score["n"]))
                progress(f"edit {label} {steps} steps: {result.seconds:.2f} s, PSNR {score['psnr']:.2f} dB")
    return rows


# ----------------------------------------------------------------------------- the sweep


TINY_LABEL = "the `--tiny` category, made in a temporary folder"
"""How the page names the ``--tiny`` category (:func:`run_bench`'s ``data_label``)."""


def run_bench(
    category: Category,
    settings: BenchSettings = BenchSettings(),
    device: torch.device | str = "cpu",
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    data_label: str | None = None,
) -> BenchReport:
    """Measure every curve of ``settings`` on ``category`` (see the module docstring).
    ``data_label`` names the data on the page (default: its folder; the ``--tiny`` category's
    is a temporary one, gone once the command ends).

    Model files go to ``workdir`` (kept) or a temporary folder (deleted).  The first preset's
    final model is edited (when the dataset has twins); the first final model of each sampler
    (grid, hierarchical) is rendered with other samples per ray.
    """
    settings = settings.validated()
    device = torch.device(device)
    say = progress or (lambda _msg: None)
    rows: list[BenchRow] = []
    notes: list[str] = []
    with tempfile.TemporaryDirectory(prefix="crfedit-bench-") as tmp:
        folder = Path(workdir) if workdir is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        finals: dict[str, CategoryModel] = {}
        warm_up_training(category, make_config(settings.presets[0], sets=list(settings.sets)), device, folder)
        for preset in settings.presets:
            base = make_config(preset, sets=list(settings.sets))
            curves = [(preset, base)]
            if base.sampler == "grid":
                curves += [
                    (f"{preset}, {v:g} samples/cell", dataclasses.replace(base, steps_per_cell=float(v)))
                    for v in settings.train_steps_per_cell if float(v) != base.steps_per_cell
                ]
            for label, cfg in curves:
                curve_rows, model = train_curve(category, cfg, label, settings, device, folder, say)
                rows += curve_rows
                if label == preset:
                    finals[preset] = model
        rendered = set()
        for preset, model in finals.items():
            if model.cfg.sampler in rendered:
                continue
            rendered.add(model.cfg.sampler)
            knob, variants = render_variants(model.cfg, settings)
            rows += render_curve(model, category, f"{preset}: samples per ray", knob, variants, settings, say)
        first = finals[settings.presets[0]]
        if (category.root / "twins.json").is_file():
            rows += edit_curves(first, category, settings, say, notes)
        else:
            notes.append(f"no edit curves: {category.root} has no ground-truth twins (twins.json)")
    resolution = category.instances[0].splits["train"][0].camera.width if "train" in category.instances[0].splits else 0
    data = f"{data_label or f'`{category.root}`'} ({len(category.instances)} instances, {resolution} px)"
    return BenchReport(rows, machine_info(device), settings, data, notes)


def tiny_category(folder: str | Path) -> Category:
    """The procedural 2-chair, 6-view, 16-pixel category with twins that ``--tiny`` runs on."""
    folder = Path(folder)
    if not (folder / "instances.txt").is_file():
        write_synth_category(folder, SynthConfig(instances=2, views=6, res=16))
    return load_category(folder)


def benchmark_category(data: str | Path | None, tiny: bool, scratch: str | Path, default: str | Path,
                       say: Progress | None = None) -> Category:
    """The category a benchmark script runs on: ``data`` when given, else the ``--tiny`` one in
    ``scratch``, else the default procedural category (24 chairs at 64²) at ``default``,
    generated there once (``say`` is told) and reused afterwards."""
    if data is not None:
        return load_category(data)
    if tiny:
        return tiny_category(Path(scratch) / "chairs")
    default = Path(default)
    if not (default / "instances.txt").is_file():
        if say is not None:
            say(f"generating the benchmark category into {default}")
        write_synth_category(default, SynthConfig())
    return load_category(default)
