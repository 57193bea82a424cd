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
  optimization time, one curve per number of edit rays (and one with feature caching off),
  points over the number of edit steps.

:func:`run_bench` measures; :func:`write_outputs` writes the CSV, one PNG per group (drawn with
Pillow) and the markdown tables between ``<!-- bench:begin -->`` and ``<!-- bench:end -->`` of
a docs page, stamped with the machine, the date and the git revision.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import io
import math
import os
import platform
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Sequence

import torch

from .config import Config, make_config
from .data.format import Category, load_category
from .data.synth import SynthConfig, write_synth_category
from .edit import EditOptions
from .errors import CrfError
from .ablation import warm_up_training
from .evaluation import apply_twin_edit, held_out_split, load_twin_cases, render_views, score_instance, score_model
from .io import atomic_path, atomic_write_text
from .metrics import score_images
from .model import CategoryModel, load_model
from .train import train

BEGIN = "<!-- bench:begin -->"
END = "<!-- bench:end -->"
CSV_COLUMNS = ("group", "curve", "knob", "value", "seconds", "psnr", "ssim", "views")
GROUPS = {
    "train": ("Training: held-out PSNR against training time", "training time (s)", "held-out PSNR (dB)"),
    "render": ("Rendering: PSNR against time per view, by samples per ray", "seconds per view", "held-out PSNR (dB)"),
    "edit": ("Editing: PSNR against the ground-truth twin, by edit steps and rays", "edit time (s)", "PSNR vs twin (dB)"),
}
"""group → (title, x label, y label)."""
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
    """Points scored along each training curve (plus the end of training)."""
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
            (self.minutes > 0 and math.isfinite(self.minutes), f"--minutes {self.minutes:g}: must be a positive number"),
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
            make_config(preset, sets=list(self.sets))  # unknown presets or keys fail here, before any work
        return self


@dataclass(frozen=True)
class BenchRow:
    """One measured point."""

    group: str  # train | render | edit
    curve: str  # the plotted curve it belongs to, e.g. "fast", "paper", "color, 1024 rays"
    knob: str  # what varies along the curve: step | steps_per_cell | samples | edit_steps
    value: str  # the knob's value at this point
    seconds: float  # training time so far | seconds per rendered view | edit optimization time
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


# ----------------------------------------------------------------------------- machine


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what :mod:`platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware", "cpu model") and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_revision(folder: Path | None = None) -> str:
    """Short commit of the checkout holding crfedit (``+dirty`` with uncommitted changes), or ``unknown``."""
    folder = folder or Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=folder, capture_output=True, text=True, timeout=10)
        if rev.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=folder, capture_output=True, text=True, timeout=10
        )
        return rev.stdout.strip() + ("+dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine_info(device: torch.device | str = "cpu") -> dict[str, str]:
    """CPU model, cores (usable / total), torch version and threads, device, date (UTC), git revision."""
    device = torch.device(device)
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    info = {
        "cpu": cpu_model(),
        "cores": f"{usable} usable of {os.cpu_count()}",
        "torch": torch.__version__,
        "threads": str(torch.get_num_threads()),
        "device": device.type,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "revision": git_revision(),
        "python": platform.python_version(),
    }
    if device.type == "cuda":
        info["device"] = f"cuda ({torch.cuda.get_device_name(device)})"
    return info


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


def edit_curves(model: CategoryModel, category: Category, settings: BenchSettings, progress: Progress) -> list[BenchRow]:
    """PSNR against the first colour twin and the first removal twin over edit steps × rays."""

    if not settings.edit_steps or not settings.edit_rays:
        return []
    cases = load_twin_cases(model, category)
    firsts = [next((c for c in cases if c.spec.kind == kind), None) for kind in ("color", "remove")]
    chosen = [c for c in firsts if c is not None]
    rows = []
    if chosen:  # the first edit of a process pays one-off costs; keep them out of the timings
        apply_twin_edit(model, chosen[0], EditOptions(steps=1, rays=settings.edit_rays[0], seed=settings.seed))
    plain = 1024 if 1024 in settings.edit_rays else settings.edit_rays[0]
    runs = [(rays, True) for rays in settings.edit_rays] + ([(plain, False)] if settings.edit_uncached else [])
    for case in chosen:
        for rays, cache in runs:
            label = f"{case.spec.kind}, {rays} rays" + ("" if cache else ", no cache")
            for steps in settings.edit_steps:
                options = EditOptions(strategy="hybrid", steps=steps, rays=rays, seed=settings.seed, cache=cache)
                result = apply_twin_edit(model, case, options)
                score = score_instance(result.model, case.instance, case.views)
                rows.append(BenchRow("edit", label, "edit_steps", str(steps), result.seconds, score["psnr"], score["ssim"], score["n"]))
                progress(f"edit {label} {steps} steps: {result.seconds:.2f} s, PSNR {score['psnr']:.2f} dB")
    return rows


# ----------------------------------------------------------------------------- the sweep


def run_bench(
    category: Category,
    settings: BenchSettings = BenchSettings(),
    device: torch.device | str = "cpu",
    workdir: str | Path | None = None,
    progress: Progress | None = None,
) -> BenchReport:
    """Measure every curve of ``settings`` on ``category`` (see the module docstring).

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
            rows += edit_curves(first, category, settings, say)
        else:
            notes.append(f"no edit curves: {category.root} has no ground-truth twins (twins.json)")
    resolution = category.instances[0].splits["train"][0].camera.width if "train" in category.instances[0].splits else 0
    data = f"{category.root} ({len(category.instances)} instances, {resolution} px)"
    return BenchReport(rows, machine_info(device), settings, data, notes)


# ----------------------------------------------------------------------------- CSV


def write_csv(rows: Sequence[BenchRow], path: str | Path) -> Path:
    """One line per point, columns :data:`CSV_COLUMNS`; written atomically."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for r in rows:
        writer.writerow([r.group, r.curve, r.knob, r.value, f"{r.seconds:.6g}", f"{r.psnr:.4f}", f"{r.ssim:.4f}", r.views])
    path = Path(path)
    atomic_write_text(path, buf.getvalue())
    return path


# ----------------------------------------------------------------------------- plots (Pillow)

PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
PLOT_SIZE = (900, 600)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, AttributeError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round tick values (steps of 1, 2, 2.5 or 5 × 10ᵏ) covering [lo, hi]: the first tick ≤ lo,
    the last ≥ hi.  ``nice_ticks(11.3, 23.8)`` → [10, 12.5, 15, 17.5, 20, 22.5, 25]."""
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / count
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw * (1 - 1e-9))
    first, last = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
    return [round(k * step, 12) for k in range(first, last + 1)]


def log_ticks(lo: float, hi: float) -> list[float]:
    """Ticks of a log axis over [lo, hi] (lo > 0): decades, plus 2× and 5× when few decades show."""
    d0, d1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    mults = (1.0,) if d1 - d0 > 4 else (1.0, 2.0, 5.0)
    ticks = [m * 10.0**d for d in range(d0, d1 + 1) for m in mults]
    inside = [t for t in ticks if lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9)]
    return inside if len(inside) >= 2 else [10.0**d0, 10.0**d1]


def _tick_label(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.0e}".replace("e+0", "e").replace("e-0", "e-")
    return f"{v:g}"


def plot_curves(
    curves: dict[str, list[tuple[float, float]]], path: str | Path, title: str, xlabel: str, ylabel: str,
    size: tuple[int, int] = PLOT_SIZE,
) -> Path:
    """A line plot, one polyline with markers per curve, legend on the right; PNG written atomically.

    Drawn at twice the size and downsampled (anti-aliased lines and text).  The x axis is
    logarithmic when the positive x values span more than a factor of 30.  Non-finite points
    are left out.
    """
    from PIL import Image, ImageDraw

    curves = {k: sorted((x, y) for x, y in pts if math.isfinite(x) and math.isfinite(y)) for k, pts in curves.items()}
    curves = {k: v for k, v in curves.items() if v}
    if not curves:
        raise CrfError(f"{path}: nothing to plot (no finite points)")
    s = 2  # supersampling
    width, height = size[0] * s, size[1] * s
    img = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(img)
    font, small, big = _font(14 * s), _font(12 * s), _font(17 * s)
    left, right, top, bottom = 78 * s, width - 230 * s, 48 * s, height - 62 * s

    xs = [x for pts in curves.values() for x, _ in pts]
    ys = [y for pts in curves.values() for _, y in pts]
    log_x = min(xs) > 0 and max(xs) / min(xs) > 30
    if log_x:
        lo, hi = min(xs) / 1.25, max(xs) * 1.25
        xt = log_ticks(lo, hi)
        lo, hi = min(lo, xt[0]), max(hi, xt[-1])
        fx = lambda x: left + (math.log10(x) - math.log10(lo)) / (math.log10(hi) - math.log10(lo)) * (right - left)
    else:
        xt = nice_ticks(min(0.0, min(xs)), max(xs))
        lo, hi = xt[0], xt[-1]
        fx = lambda x: left + (x - lo) / (hi - lo) * (right - left)
    pad = 0.03 * (max(ys) - min(ys))
    yt = nice_ticks(min(ys) - pad, max(ys) + pad)
    ylo, yhi = yt[0], yt[-1]
    fy = lambda y: bottom - (y - ylo) / (yhi - ylo) * (bottom - top)

    for t in xt:
        x = fx(t)
        draw.line([(x, top), (x, bottom)], fill="#e6e6e6", width=s)
        draw.line([(x, bottom), (x, bottom + 5 * s)], fill="black", width=s)
        draw.text((x, bottom + 8 * s), _tick_label(t), fill="black", font=small, anchor="ma")
    for t in yt:
        y = fy(t)
        draw.line([(left, y), (right, y)], fill="#e6e6e6", width=s)
        draw.line([(left - 5 * s, y), (left, y)], fill="black", width=s)
        draw.text((left - 8 * s, y), _tick_label(t), fill="black", font=small, anchor="rm")
    draw.rectangle([left, top, right, bottom], outline="black", width=s)
    draw.text(((left + right) / 2, 16 * s), title, fill="black", font=big, anchor="ma")
    draw.text(((left + right) / 2, height - 24 * s), xlabel + (" (log scale)" if log_x else ""), fill="black", font=font, anchor="ma")
    label = Image.new("RGB", (bottom - top, 22 * s), "white")
    ImageDraw.Draw(label).text(((bottom - top) / 2, 2 * s), ylabel, fill="black", font=font, anchor="ma")
    img.paste(label.rotate(90, expand=True), (8 * s, top))

    ly, r = top + 6 * s, 3.5 * s
    for i, (name, pts) in enumerate(curves.items()):
        color = PALETTE[i % len(PALETTE)]
        xy = [(fx(x), fy(y)) for x, y in pts]
        for a, b in zip(xy, xy[1:]):
            draw.line([a, b], fill=color, width=2 * s)
        for px, py in xy:
            draw.ellipse([px - r, py - r, px + r, py + r], fill=color)
        mid = ly + 8 * s
        draw.line([(right + 14 * s, mid), (right + 40 * s, mid)], fill=color, width=2 * s)
        draw.ellipse([right + 27 * s - r, mid - r, right + 27 * s + r, mid + r], fill=color)
        text = name if len(name) <= 28 else name[:27] + "…"
        draw.text((right + 48 * s, mid), text, fill="black", font=small, anchor="lm")
        ly += 22 * s
    img = img.resize(size, Image.LANCZOS)
    path = Path(path)
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG")
    return path


def write_plots(rows: Sequence[BenchRow], stem: str | Path) -> dict[str, Path]:
    """One PNG per group present in ``rows``: ``<stem>_<group>.png``."""
    stem = Path(stem)
    out = {}
    for group, (title, xlabel, ylabel) in GROUPS.items():
        curves: dict[str, list[tuple[float, float]]] = {}
        for r in rows:
            if r.group == group:
                curves.setdefault(r.curve, []).append((r.seconds, r.psnr))
        if any(math.isfinite(x) and math.isfinite(y) for pts in curves.values() for x, y in pts):
            out[group] = plot_curves(curves, stem.with_name(f"{stem.name}_{group}.png"), title, xlabel, ylabel)
    return out


# ----------------------------------------------------------------------------- markdown


def _settings_line(s: BenchSettings) -> str:
    parts = [
        f"presets {', '.join(s.presets)}", f"{s.minutes:g} min per training curve" + (f" (at most {s.steps} steps)" if s.steps else ""),
        f"{s.checkpoints} checkpoints + end", f"held-out scores on {s.eval_views} view(s) of the first {s.eval_instances} instance(s)",
        f"seed {s.seed}",
    ]
    if s.sets:
        parts.append("overrides " + ", ".join(f"`{x}`" for x in s.sets))
    return "; ".join(parts)


def _table(rows: Sequence[BenchRow], knob_header: str) -> list[str]:
    lines = [f"| curve | {knob_header} | seconds | PSNR (dB) | SSIM |", "|---|---|---:|---:|---:|"]
    for r in rows:
        seconds = f"{r.seconds:.3g}" if r.seconds < 100 else f"{r.seconds:.0f}"
        lines.append(f"| {r.curve} | {r.knob} = {r.value} | {seconds} | {r.psnr:.2f} | {r.ssim:.3f} |")
    return lines


def markdown_section(report: BenchReport, csv_path: Path, plots: dict[str, Path], md_path: Path) -> str:
    """The text between the markers: stamp, settings, then per group a plot and a table."""
    m = report.machine
    rel = lambda p: os.path.relpath(Path(p).resolve(), Path(md_path).resolve().parent).replace(os.sep, "/")
    lines = [
        BEGIN,
        "## Speed against error",
        "",
        f"Measured {m['date']} on {m['cpu']} ({m['cores']} cores, {m['threads']} torch threads, device {m['device']}), "
        f"torch {m['torch']}, Python {m['python']}, crfedit revision `{m['revision']}`.",
        "",
        f"Data: `{report.data}`. Settings: {_settings_line(report.settings)}. Raw numbers: [{csv_path.name}]({rel(csv_path)}).",
        "",
    ]
    lines += [f"- {note}" for note in report.notes] + ([""] if report.notes else [])
    what = {
        "train": "Points along one run per curve (checkpoints; scoring is not counted in the time).",
        "render": "The same trained model rendered with fewer or more samples per ray.",
        "edit": "Hybrid-strategy edits of a twin's source instance, scored on all of the twin's test views.",
    }
    knob_header = {"train": "point", "render": "sampling", "edit": "edit"}
    for group, (title, _, _) in GROUPS.items():
        rows = [r for r in report.rows if r.group == group]
        if not rows:
            continue
        lines += [f"### {title}", "", what[group], ""]
        if group in plots:
            lines += [f"![{title}]({rel(plots[group])})", ""]
        lines += _table(rows, knob_header[group]) + [""]
    lines.append(END)
    return "\n".join(lines)


def update_markdown(path: str | Path, section: str, begin: str = BEGIN, end: str = END) -> Path:
    """Put ``section`` (markers included) between the markers of ``path``, keeping everything
    else; a page without markers gets it appended, a missing page is created."""
    path = Path(path)
    if path.is_file():
        text = path.read_text(encoding="utf-8")
        if begin in text and end in text and text.index(begin) < text.index(end):
            text = text[: text.index(begin)] + section + text[text.index(end) + len(end) :]
        else:
            text = text.rstrip("\n") + "\n\n" + section + "\n"
    else:
        text = "# Benchmarks\n\nWritten by `crfedit bench` (or `python benchmarks/run.py`).\n\n" + section + "\n"
    atomic_write_text(path, text)
    return path


def write_outputs(report: BenchReport, csv_path: str | Path, md_path: str | Path) -> list[Path]:
    """Write the CSV, the PNGs beside it (``<csv stem>_<group>.png``) and the markdown section.
    Folders are created as needed.  Returns the paths written."""
    csv_path, md_path = Path(csv_path), Path(md_path)
    for folder in {csv_path.parent, md_path.parent}:
        folder.mkdir(parents=True, exist_ok=True)
    written = [write_csv(report.rows, csv_path)]
    plots = write_plots(report.rows, csv_path.with_suffix(""))
    written += list(plots.values())
    written.append(update_markdown(md_path, markdown_section(report, csv_path, plots, md_path)))
    return written


def tiny_category(folder: str | Path) -> Category:
    """The procedural 2-chair, 6-view, 16-pixel category with twins that ``--tiny`` runs on."""
    folder = Path(folder)
    if not (folder / "instances.txt").is_file():
        write_synth_category(folder, SynthConfig(instances=2, views=6, res=16))
    return load_category(folder)
