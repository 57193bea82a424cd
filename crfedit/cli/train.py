"""``crfedit train``, ``crfedit info`` and ``crfedit quickstart``."""

from __future__ import annotations

import enum
import json
import math
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..io import check_folder_target, writer_lock
from ..config import ARCHS, PRESETS
from ..errors import CrfError
from ..names import MODEL_FORMAT
from .common import echo_notes, printable, table_row, DeviceChoice, DeviceOpt, Session, SeedOpt, app, check_kind_suffix, command_line, seed_in_range, size_text, user_errors


PresetChoice = enum.Enum("PresetChoice", {p: p for p in PRESETS}, type=str)


ArchChoice = enum.Enum("ArchChoice", {a: a for a in ARCHS}, type=str)


class MarchChoice(str, enum.Enum):
    auto = "auto"
    fixed = "fixed"
    exact = "exact"


# ----------------------------------------------------------------------------- progress


class TrainProgress:
    """A rich progress bar fed by :func:`crfedit.train.train`'s ``on_step``.

    Columns: step/total, loss, PSNR (of the training batch), rays/s, elapsed, ETA.  With a time
    budget the bar tracks whichever limit comes first, steps or minutes.  Written to a file or a
    pipe (``> train.log``, ``nohup``, CI), where a bar shows only its last state when training
    ends, the same fields also go out as a plain line every :attr:`LINE_SECONDS`.
    """

    LINE_SECONDS = 30.0
    """Seconds between the plain progress lines printed when the output is not a terminal."""

    def __init__(self, cfg, minutes: float | None, first_step: int = 0):
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.cfg, self.budget, self.first_step = cfg, None if minutes is None else 60.0 * minutes, first_step
        self.t0 = time.perf_counter()
        console = Console(stderr=True)  # progress on stderr, as every command's: stdout keeps the results
        self.bar = Progress(
            TextColumn("{task.fields[step]:>6}/{task.fields[steps]}"),
            BarColumn(),
            TextColumn("loss {task.fields[loss]}  PSNR {task.fields[psnr]}  {task.fields[rate]} rays/s"),
            TimeElapsedColumn(),
            TextColumn("ETA {task.fields[eta]}"),
            console=console,
            disable=not console.is_terminal,  # a log gets plain lines instead (on_step), and no last frame before an error line
        )
        self.task = self.bar.add_task("train", total=1.0, step=first_step, steps=cfg.steps, loss="-", psnr="-", rate="-", eta="-")
        self.lines = not console.is_terminal
        self.last_line = self.t0

    def __enter__(self) -> "TrainProgress":
        self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.stop()

    def on_step(self, step: int, loss: float, psnr: float, rays_per_s: float) -> None:
        # train() reports rays/s as rays so far over the run's total elapsed time, which gives
        # that elapsed time back (it includes the time before a --resume).
        elapsed = self.cfg.rays * step / rays_per_s if rays_per_s > 0 else 0.0
        done = step / self.cfg.steps
        if self.budget is not None:
            done = max(done, elapsed / self.budget)
        steps_per_s = (step - self.first_step) / max(time.perf_counter() - self.t0, 1e-9)
        remaining = (self.cfg.steps - step) / steps_per_s if steps_per_s > 0 else math.inf
        if self.budget is not None:
            remaining = min(remaining, self.budget - elapsed)
        fields = {"step": step, "loss": _number(loss, "{:.4f}"), "psnr": _number(psnr, "{:5.2f}"), "rate": _si(rays_per_s),
                  "eta": _clock(max(remaining, 0.0))}  # loss and PSNR are NaN until training's first read-out
        self.bar.update(self.task, completed=min(done, 1.0), **fields)
        now = time.perf_counter()
        if self.lines and now - self.last_line >= self.LINE_SECONDS:
            self.last_line = now
            self.bar.console.print(
                f"{step:>6}/{self.cfg.steps}  loss {fields['loss']}  PSNR {fields['psnr']}  {fields['rate']} rays/s  "
                f"{_clock(now - self.t0)}  ETA {fields['eta']}", highlight=False, soft_wrap=True)


def _number(x: float, form: str) -> str:
    return form.format(x) if math.isfinite(x) else "-"


def _si(x: float) -> str:
    return f"{x / 1e6:.2f}M" if x >= 1e6 else f"{x / 1e3:.1f}k" if x >= 1e3 else f"{x:.0f}"


def _remove_partials(out: Path) -> None:
    """Remove the half-written temporaries of ``out`` and its run record a killed run left
    (held under the writer lock, so none is being written), saying so."""
    from ..io import stale_partials
    from ..runlog import record_paths

    for target in (out, record_paths(out)["run"]):
        for p in stale_partials(target):
            size = p.stat().st_size
            p.unlink(missing_ok=True)
            typer.echo(printable(f"note: removed {p.name} ({size_text(size)}), a copy of {target.name} a killed run left half-written"), err=True)


def _clock(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "-:--:--"
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


# ----------------------------------------------------------------------------- helpers


def check_output_file(out: Path, resume: bool = False, overwrite: bool = False, what: str = "--out") -> None:
    """``out`` is a file name whose folder may be missing (:func:`~crfedit.io.writer_lock`
    creates it for the run); an existing model there is only continued (``resume``) or
    replaced (``overwrite``), never replaced silently."""
    from ..safefile import file_format

    if out.is_dir():
        raise CrfError(f"{what} {out}: is a folder; give a file name such as {out / 'model.safetensors'}")
    if not (out.exists() and file_format(out) == MODEL_FORMAT):  # an existing model is resumed by whatever name it has
        check_kind_suffix(out, "model", "model.safetensors", f"{what} {out}")
    if out.exists() and file_format(out) != MODEL_FORMAT:  # first: --resume and --overwrite would not help
        raise CrfError(f"{what} {out}: exists and is not a crfedit model; --resume and --overwrite take only models (pick another name)")
    if out.exists() and not (resume or overwrite):
        raise CrfError(f"{what} {out}: exists; continue its training with --resume, or replace it with --overwrite")
    for folder in out.parents:  # the first that exists must be a folder
        if folder.exists():
            if not folder.is_dir():
                raise CrfError(f"{what} {out}: {folder} is a file, not a folder")
            break


def format_score(score: dict) -> str:
    text = f"PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.3f}"
    return text + (f", LPIPS {score['lpips']:.3f}" if score["lpips"] is not None else "")


def run_training(
    category, out: Path, cfg, device, seed: int, minutes: float | None, resume: bool, log_every: int | None = None, ranks=None,
    compile: bool = False,
    march: str = "auto",
    given: frozenset[str] | None = None,
):
    """Train on a loaded category with a progress bar and run records (crfedit.runlog), both on
    rank 0 only under torchrun; return (model, TrainResult).  Training reads its loss back every
    gcd(``log_every``, READ_EVERY) steps, so every logged row holds that step's own loss."""
    import torch

    from ..distributed import SINGLE
    from ..modelfile import stored_training
    from ..parts import has_labels, part_config
    from ..runlog import LOG_EVERY, RunLog, config_block, record_paths, started_with, stored_log_every
    from ..train import READ_EVERY, train

    if log_every is None:  # a resumed run keeps its cadence
        log_every = stored_log_every(out) if resume else LOG_EVERY
    fixed = {"auto": None, "fixed": True, "exact": False}[march]
    options = {"read_every": math.gcd(log_every, READ_EVERY), "compile": compile, "fixed_shapes": fixed}

    ranks = ranks or SINGLE
    first_step = 0
    if resume and out.is_file():
        stored = stored_training(out)
        stored_cfg, first_step = stored.cfg, stored.step
        ignored = _ignored_seed(ignored_flags(part_config(category, cfg), stored_cfg, given), given, seed, stored.seed)
        seed = seed if stored.seed is None else stored.seed  # what train() goes on with, for the run record too
        if ignored and ranks.main:
            typer.echo(f"resuming {out} with its stored config (preset {stored_cfg.preset}, {stored_cfg.steps} steps); {ignored}", err=True)
        cfg = stored_cfg
    else:
        asked = cfg.part_dim
        cfg = part_config(category, cfg)  # what train() will store, for the records
        if asked and not cfg.part_dim and ranks.main and has_labels(category, range(len(category.instances))):
            why = (" (the twins' sources, so that an edit benchmark scores parts the model was never told about)"
                   if cfg.part_labels == "not-twins" else "")  # a list of the user's own says nothing of twins
            typer.echo(f"note: no part head: every instance with part maps is left out by part_labels={cfg.part_labels}{why}; "
                       "--set part_labels=all learns them", err=True)
    if not ranks.main:
        return train(category, cfg, out, device, seed=seed, minutes=minutes, resume=resume, ranks=ranks, **options)
    threads = torch.get_num_threads()  # what this process computes with (the CLI set it at start, :class:`Session`)
    run = {"command": command_line(), "dataset": str(category.root), "dataset_fingerprint": category.fingerprint,
           "seed": seed, "device": str(device), "threads": threads, "minutes": minutes, "resumed_at": first_step,
           "world_size": ranks.world, "log_every": log_every}  # torchrun's processes (1: one process)
    paths = record_paths(out)
    # on stdout with the results: what the run computes with belongs in a log of it (`> run.txt`);
    # an error during training is then still the one line on stderr
    typer.echo(f"config (also in {paths['run']}; log every {log_every} steps in {paths['log']}):\n{config_block(cfg)}")
    typer.echo(f"CPU threads: {threads}" + (f" ({Session.threads_why})" if Session.threads == threads and Session.threads_why else ""))
    before = sorted(set(started_with(out, "threads"))) if resume and torch.device(device).type == "cpu" else []
    if before and before != [threads]:  # the sums split otherwise: same seed, another model
        counts = " and ".join(map(str, before))
        typer.echo(f"note: this run trained with {counts} CPU thread{'s' * (before != [1])} and goes on with {threads}: the same seed "
                   f"gives the same model only at one thread count throughout" + (f" (CRFEDIT_THREADS={before[0]} keeps it)" if len(before) == 1 else ""),
                   err=True)
    # a run that fails before its first checkpoint takes its records back (RunLog.take_back)
    stamp = lambda: (out.stat().st_mtime_ns, out.stat().st_size) if out.is_file() else None
    model_before, finished = stamp(), False
    log = RunLog(out, cfg, log_every, minutes, resume, run)
    try:
        with TrainProgress(cfg, minutes, first_step) as progress:
            def on_step(*args):
                progress.on_step(*args)
                log.on_step(*args)

            result = train(
                category, cfg, out, device, seed=seed, minutes=minutes, resume=resume,
                on_step=on_step, extra_meta={"command": command_line()}, ranks=ranks, **options,
                on_note=lambda text: progress.bar.console.print(f"warning: {text}", highlight=False, soft_wrap=True, markup=False),
            )
            finished = True
            stats = result[1]  # train() returns (model, TrainResult)
            log.end((stats.steps, stats.final_loss, stats.train_psnr))  # the last checkpoint's read-out, its own step
            return result
    finally:
        if not finished and stamp() != model_before:  # stopped (Ctrl-C, SIGTERM) with a checkpoint written: its step is a row
            log.end()
        log.close()
        if not finished and stamp() == model_before:
            log.take_back()


def ignored_flags(asked, stored, given: frozenset[str] | None = None) -> str:
    """What ``--resume`` ignores: the settings the command line gave (``given``: their config
    keys, :func:`given_settings`; None: every setting) that differ from the stored run's ("" when
    none do).  A default the user never typed is not "ignored"."""
    keys = [k for k in vars(asked) if given is None or k in given]
    differ = [f"{k} {getattr(asked, k)} (stored {getattr(stored, k)})" for k in keys if getattr(asked, k) != getattr(stored, k)]
    return f"ignored: {', '.join(differ)}" if differ else ""


def given_settings(preset: str, overrides: dict, sets: list[str]) -> frozenset[str]:
    """The config keys a train command line set: its options (``overrides``, None where not
    given), its ``--set KEY=VALUE`` keys and, for a preset other than the default, every key
    that preset sets."""
    from ..config import PRESETS

    keys = {k for k, v in overrides.items() if v is not None}
    keys |= {item.partition("=")[0].strip().replace("-", "_") for item in sets}
    if preset != "fast":
        base, chosen = PRESETS["fast"], PRESETS[preset]
        keys |= {k for k in vars(chosen) if getattr(chosen, k) != getattr(base, k)}
    return frozenset(keys)


def _ignored_seed(ignored: str, given, seed: int, stored_seed: int | None) -> str:
    """``ignored`` (:func:`ignored_flags`' line) with a --seed the stored run overrides added."""
    if given is not None and "seed" in given and stored_seed is not None and seed != stored_seed:
        return f"{ignored or 'ignored:'}{',' if ignored else ''} seed {seed} (stored {stored_seed})"
    return ignored


def _resumed(out: Path, res: int | None, minutes: float | None, ranks):
    """``--resume``'s reading of the stored run, before the dataset loads or any run record is
    written: (the stored run, the resolution, the time budget, why nothing is left to train or
    "").  A stripped or baked model, or another resolution, is a one-line error."""
    from ..modelfile import stored_training

    if not out.is_file():
        raise CrfError(f"--resume: {out} does not exist (start without --resume)")
    stored = stored_training(out)
    if not stored.resumable:
        raise CrfError(f"--resume: {out} holds no training state (it was baked or stripped)")
    stored_width = (stored.sizes.get("train") or [None])[0]
    several = (stored.widths or {}).get("train")
    if several and len(several) > 1:  # trained with each view at its own size: resumed alike
        if res is not None:
            raise CrfError(f"--resume --res {res}: {out} was trained with each view at its own width "
                           f"({', '.join(map(str, several))}); resume without --res")
    elif res is None:
        res = stored_width
    elif stored_width is not None and res != stored_width:
        raise CrfError(f"--resume --res {res}: {out} was trained at width {stored_width}")
    if minutes is None and stored.minutes is not None:  # the run's schedule ends on its own clock
        minutes = stored.minutes
        if ranks.main:
            typer.echo(f"resuming {out} with its time budget, --minutes {minutes:g} (pass --minutes to change it)", err=True)
    return stored, res, minutes, _finished(stored.step, stored.cfg.steps, stored.elapsed, minutes)


def _finished(step: int, steps: int, elapsed: float | None, minutes: float | None) -> str:
    """The line that says a stored run has nothing left to train ("" when it has): its last
    step reached, or its time budget spent."""
    if step >= steps:
        return f"is trained to step {step} of {steps}: nothing to resume (the file is unchanged)"
    if minutes is not None and elapsed is not None and elapsed >= 60.0 * minutes:
        return (f"has trained its --minutes {minutes:g} ({elapsed:.0f} s, step {step} of {steps}): nothing to resume "
                "(the file is unchanged; a larger --minutes trains on)")
    return ""


# ----------------------------------------------------------------------------- train


@app.command("train")
@user_errors(ranked=True)
def train_cmd(
    data: Annotated[Path, typer.Argument(help="Category dataset folder (instances.txt), a NeRF-synthetic scene, or nerfstudio transforms.json scene(s).")],
    out: Annotated[Path, typer.Option("--out", metavar="MODEL", help="Model file to write, e.g. model.safetensors (its folder is created if missing).")],
    preset: Annotated[PresetChoice, typer.Option("--preset", help="fast: minutes on a CPU; paper: the paper's networks and sampling.")] = PresetChoice.fast,
    arch: Annotated[Optional[ArchChoice], typer.Option("--arch", help="Ablation variant (paper Table 1); default ours.")] = None,
    steps: Annotated[Optional[int], typer.Option("--steps", help="Training steps (default: the preset's).")] = None,
    minutes: Annotated[Optional[float], typer.Option("--minutes", help="Stop after this much training time; the learning-rate schedule ends there.")] = None,
    res: Annotated[Optional[int], typer.Option("--res", help="Train at this image width (images are area-resized); default: as stored.")] = None,
    seed: Annotated[Optional[int], typer.Option("--seed", callback=seed_in_range, show_default=False, help="Random seed from 0 (default 0); the same seed gives the same result (--resume goes on with the run's own).")] = None,
    device: DeviceOpt = DeviceChoice.auto,
    resume: Annotated[bool, typer.Option("--resume", help="Continue the run stored in --out from its last checkpoint (stored config and resolution).")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --out model instead of refusing.")] = False,
    view_reg: Annotated[Optional[float], typer.Option("--view-reg", help="Weight of the view-dependence regularizer (one-view-per-instance data).")] = None,
    sets: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE", help="Override any config field, KEY=VALUE (repeatable), e.g. --set rays=1024.")] = None,
    log_every: Annotated[Optional[int], typer.Option("--log-every", help="Write a row of the CSV log (and TensorBoard, when installed) every N steps (default 100; --resume: the run's own).", show_default=False)] = None,
    compile: Annotated[bool, typer.Option("--compile", help="Run the fixed-shape march's networks through torch.compile (needs a C++ compiler; the first steps compile for seconds).")] = False,
    march: Annotated[MarchChoice, typer.Option("--march", help="fixed: fixed-capacity sample buffers, no host read in a step (auto on a GPU); exact: buffers sized by nonzero (auto on a CPU).")] = MarchChoice.auto,
) -> None:
    """Train one model over a category: shared networks plus a shape and a color code per instance.

    Writes the model (with a checkpoint every checkpoint_every steps), then prints held-out
    PSNR/SSIM on a few validation views per instance (test views when there is no val split).

    Launched by torchrun (torchrun --nproc-per-node N -m crfedit train ...), it trains data
    parallel: each rank samples from its share of the instances and gradients are averaged
    (gloo on CPU, nccl on cuda:LOCAL_RANK).  rays (--set rays=R) is the number of rays per step
    in total, split over the ranks, so a run's settings mean the same at any world size.  Rank 0
    prints and writes the model, in the single-process format.
    """
    from ..config import make_config
    from ..data.loading import load_category
    from ..distributed import SINGLE, process_group, rank_device, ranks_from_env
    from ..evaluation import held_out_split, score_model
    from ..runtime import resolve_device, seed_everything
    from ..train import check_trainable
    from ..views import parse_resolution

    if steps is not None and steps < 1:
        raise CrfError(f"--steps {steps}: must be at least 1")
    if log_every is not None and log_every < 1:
        raise CrfError(f"--log-every {log_every}: must be at least 1")
    if minutes is not None and not (minutes > 0 and math.isfinite(minutes)):
        raise CrfError(f"--minutes {minutes:g}: must be a finite positive number")
    if view_reg is not None and not (view_reg >= 0 and math.isfinite(view_reg)):
        raise CrfError(f"--view-reg {view_reg:g}: must be 0 or more")
    res = parse_resolution(res)
    check_output_file(out, resume, overwrite)
    ranks = ranks_from_env()
    dev = resolve_device(device) if ranks is None else rank_device(device, ranks)
    overrides = {"arch": arch.value if arch else None, "steps": steps, "view_reg": view_reg}
    cfg = make_config(preset.value, overrides, sets or [], dev.type)
    given = given_settings(preset.value, overrides, sets or [])
    if seed is None:
        seed = 0
    else:
        given |= {"seed"}  # typed: a resume that goes on with the stored seed says so
    ranks = ranks or SINGLE
    with writer_lock(out, ranks.main):
        check_output_file(out, resume, overwrite)  # again, now that no other run can write it: one may have finished meanwhile
        if ranks.main:
            _remove_partials(out)
        if resume:  # read under the lock: a run still writing the file is named as such
            stored, res, minutes, finished = _resumed(out, res, minutes, ranks)
        # the data and the run checked before the ranks join: a problem every rank finds is rank 0's one line
        labels = (stored.cfg if resume else cfg).part_dim > 0  # F_part trains from part maps and depth
        category = load_category(data, res=res, with_depth=labels, with_parts=labels)
        if ranks.main:
            echo_notes(category)
        if resume and stored.dataset != category.fingerprint:  # before any record, bar or set-up
            raise CrfError(f"--resume: {out} was trained on another dataset (fingerprint {stored.dataset})")
        if resume and finished:  # rewriting it would only replace its records
            from ..parts import part_config

            ignored = _ignored_seed(ignored_flags(part_config(category, cfg), stored.cfg, given), given, seed, stored.seed)
            if ranks.main:
                typer.echo(f"{out} {finished}" + (f"; {ignored}" if ignored else ""))
            return
        check_trainable(category, ranks.world, (stored.cfg if resume else cfg).rays)
        with process_group(ranks, dev):
            seed_everything(seed)  # train() draws the initial weights from torch's global generator
            model, result = run_training(category, out, cfg, dev, seed, minutes, resume, log_every, ranks, compile, march.value, given)
    if not ranks.main:
        return
    split = held_out_split(category, "val")
    if any(inst.splits.get(split) for inst in category.instances):
        n = sum(min(model.cfg.eval_views, len(inst.splits.get(split, []))) for inst in category.instances)
        # said first: at the paper preset on a CPU each 64x64 view takes ~20 s, and the run looked hung after its last step
        typer.echo(f"scoring {n} held-out {split} view{'s' * (n != 1)} (--set eval_views=N scores fewer)", err=True)
        score = score_model(model, category, split, max_views=model.cfg.eval_views)
        typer.echo(f"held-out {score['split']} ({score['n']} view{'s' * (score['n'] != 1)}): {format_score(score)}")
    else:
        typer.echo(f"note: no held-out score: {data} has no val or test views", err=True)
    rate = model.cfg.rays * result.steps / max(result.seconds, 1e-9)
    psnr = f"train PSNR {result.train_psnr:.2f} dB" if math.isfinite(result.train_psnr) else "no step run in this call"
    typer.echo(
        f"trained {len(model.names)} instance{'s' * (len(model.names) != 1)} for {result.steps} steps in {result.seconds:.1f} s "
        f"({_si(rate)} rays/s, {psnr}) -> {out}"
    )


# ----------------------------------------------------------------------------- info


def _baked(meta: dict) -> str:
    """What ``edits bake`` folded in: the instances, how many edits, onto which base model."""
    if not meta["baked_instances"]:
        return "none"
    text = ", ".join(meta["baked_instances"])
    edits = meta["baked_edits"]
    if edits is not None:
        text += f" ({len(edits)} edit{'s' * (len(edits) != 1)}"
        text += f" onto {meta['baked_from']})" if meta["baked_from"] else ")"
        text += "".join(f"\n{'':<15}{fp}" for fp in edits)  # the edit fingerprints, in order (edits show prints each file's)
    return text



@app.command("info")
@user_errors
def info_cmd(
    model: Annotated[Path, typer.Argument(help="A crfedit file (.safetensors): a model, an edit file or a selection.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Summarize a crfedit file: a model (preset, instances, parameters and bytes per module,
    occupancy, fingerprints), an edit file (as `crfedit edits show`) or a selection (its
    instance, model, cells and how it was made)."""
    from ..modelfile import model_info
    from ..safefile import EDIT_FORMAT, MODEL_FORMAT, SELECTION_FORMAT, read_header

    if model.is_dir():
        raise CrfError(f"{model}: is a folder; info reads model, edit and selection files (a dataset: crfedit dataset info {model})")
    header = read_header(model)[1]
    kind = header.get("format")
    if kind == EDIT_FORMAT:
        from .edit import print_edit

        return print_edit(model, as_json)
    if kind == SELECTION_FORMAT:
        from .select import print_selection

        return print_selection(model, as_json, header.get("version"))
    if kind != MODEL_FORMAT:  # one line for every kind `info` reads, not a model's alone
        raise CrfError(f"{model}: not a crfedit model, edit or selection file (format {kind or 'unknown'!r})")
    meta = model_info(model)
    if as_json:
        typer.echo(json.dumps(meta, indent=2))
        return
    names = meta["names"]
    shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
    occ = meta["occupancy"]
    fills = list(occ["fill"].values())
    occupancy = (
        f"{100 * occ['mean_fill']:.1f} % of {occ['res']}^3 cells per instance on average "
        f"(min {100 * min(fills):.1f} %, max {100 * max(fills):.1f} %)"
        if occ["used"] else f"not used ({meta['sampler']} sampler)"
    )
    lo, hi = meta["scene_box"]["min"], meta["scene_box"]["max"]
    step = "unknown" if meta["step"] is None else f"{meta['step']} of {meta['steps']}"
    if meta["train_seconds"] is not None:
        step += f" ({meta['train_seconds']:.0f} s of training)"
    rows = [
        ("model", f"{meta['path']} ({size_text(meta['file_bytes'])})"),
        ("  size", ", ".join(f"{kind} {size_text(n)}" for kind, n in meta["sizes"].items() if n)
         + ("" if meta["resumable"] else " (no training state: stripped or baked)")
         + (" (crfedit model strip drops the training state)" if meta["sizes"]["training state"] else "")),
        ("preset", f"{meta['preset']}, arch {meta['arch']}, sampler {meta['sampler']}"),
        ("instances", f"{meta['instances']}: {shown}"),
        ("parameters", f"{meta['parameters']:,}"),
    ]
    rows += [(f"  {name}", f"{m['params']:>10,}  {size_text(m['bytes']):>9}") for name, m in meta["modules"].items()]
    rows += [
        ("occupancy", occupancy),
        ("scene box", "[" + ", ".join(f"{x:.3f}" for x in lo) + "] .. [" + ", ".join(f"{x:.3f}" for x in hi) + "]"),
        ("views", ", ".join(f"{s} {v['count']} at {' / '.join(f'{w}x{h}' for w, h in v.get('sizes', [v['size']]))}"
                   for s, v in meta["views"].items()) or "none stored"),
        ("step", step),
        ("baked edits", _baked(meta)),
        ("dataset", meta["dataset_fingerprint"] or "unknown"),
        ("fingerprint", meta["fingerprint"]),
    ]
    if "F_part" in meta["modules"]:
        seen = meta["part_labelled"]
        rows.insert(-2, ("part labels", f"part_labels={meta['config']['part_labels']}; " + (
            "whose part maps F_part learned: not recorded (a file written before the record)" if seen is None
            else f"F_part learned the part maps of {len(seen)} of {meta['instances']} instances")))
    for key, value in rows:
        typer.echo(table_row(key, value, 14))


# ----------------------------------------------------------------------------- quickstart


def _db(psnr: float | None) -> str:
    return "inf" if psnr is None else f"{psnr:.2f}"


@app.command("quickstart")
@user_errors
def quickstart_cmd(
    out: Annotated[Path, typer.Option("--out", help="Folder for the dataset, model, renders and score.")] = Path("runs/quickstart"),
    minutes: Annotated[float, typer.Option("--minutes", help="Training time.")] = 3.0,
    instances: Annotated[int, typer.Option("--instances", help="Procedural chairs in the category.")] = 8,
    res: Annotated[int, typer.Option("--res", help="Image width and height in pixels.")] = 64,
    seed: SeedOpt = 0,
    device: DeviceOpt = DeviceChoice.auto,
    edits: Annotated[bool, typer.Option("--edits/--no-edits", help="Also edit chair 0 from the dataset's scribbles (a recolour and a removal) and score the edits against its ground-truth twins.")] = True,
) -> None:
    """Generate procedural chairs, train the fast preset, render a turntable, score held-out views, edit chair 0.

    Everything goes under --out: data/ (the category, with chair 0's ground-truth twins),
    model.safetensors, turntable/ (24 PNGs of chair 0 and turntable.gif), edits/ (the
    recolour's and the removal's deltas and edits.png: the scribbles, and held-out views
    before, after and of the twin) and score.json (test-split PSNR/SSIM per chair, and each
    edit's PSNR against its twin and the share of the gap it closed).
    """
    from ..config import make_config
    from ..data.loading import load_category
    from ..data.synth import SynthConfig, check_synth_args, write_synth_category
    from ..demo import clear_stale_demo, demo_edits
    from ..evaluation import score_model
    from ..io import write_json
    from ..render_files import render_to_folder
    from ..runtime import resolve_device, seed_everything

    if not (minutes > 0 and math.isfinite(minutes)):
        raise CrfError(f"--minutes {minutes:g}: must be a finite positive number")
    check_folder_target(out, "--out")
    synth = SynthConfig(instances=instances, views=50, res=res, seed=seed, twins=edits, twin_sources=1)
    check_synth_args(out / "data", synth)
    dev = resolve_device(device)
    start = time.perf_counter()

    out.mkdir(parents=True, exist_ok=True)
    steps = 5 if edits else 4
    typer.echo(f"1/{steps} generating {instances} procedural chairs x 50 views at {res}x{res} -> {out / 'data'}")
    write_synth_category(out / "data", synth)

    typer.echo(f"2/{steps} training the fast preset for {minutes:g} min on {dev.type}")
    model_path = out / "model.safetensors"
    cfg = make_config("fast", device_type=dev.type)
    category = load_category(out / "data", with_depth=cfg.part_dim > 0, with_parts=cfg.part_dim > 0)
    seed_everything(seed)
    model, result = run_training(category, model_path, cfg, dev, seed, minutes, False)

    typer.echo(f"3/{steps} rendering a turntable of chair 0 (orbit:24)")
    frames_dir = out / "turntable"
    turntable = render_to_folder(model, 0, "orbit:24", frames_dir, video=out / "turntable.gif")

    typer.echo(f"4/{steps} scoring every held-out test view")
    score = score_model(model, category, "test")
    typer.echo(f"held-out test ({score['n']} view{'s' * (score['n'] != 1)}): {format_score(score)}")  # under its own step, not the next one's
    stale = clear_stale_demo(out / "edits", model)  # an earlier run's, made for another model
    if stale:
        typer.echo(f"note: removed {', '.join(stale)} from {out / 'edits'}: an earlier quickstart's, made for another model", err=True)
    demo, skipped = None, None
    if edits:
        typer.echo(f"5/{steps} editing chair 0 from the dataset's scribbles: a recolour and a removal")
        try:
            demo = demo_edits(model, category, out / "edits", seed, command=command_line())
        except CrfError as e:  # e.g. a model trained too briefly to show the scribbled part
            skipped = str(e)
    if demo and demo["skipped"]:
        skipped = "; ".join(f"{twin}: {why}" for twin, why in demo["skipped"].items())
    write_json(out / "score.json", {**score, "steps": result.steps, "train_seconds": result.seconds,
                                    **({"edits": demo["edits"]} if demo else {}), **({"edits_skipped": skipped} if skipped else {})})

    typer.echo(f"dataset    {out / 'data'}")
    typer.echo(f"model      {model_path} ({result.steps} steps in {result.seconds:.0f} s; crfedit info {model_path})")
    typer.echo(f"turntable  {frames_dir}/0000.png .. {turntable.count - 1:04d}.png and {turntable.video}")
    typer.echo(f"score      {out / 'score.json'}")
    if skipped:
        typer.echo(printable(f"edits      skipped: {skipped}"))
    for row in demo["edits"] if demo else []:
        what = "recolour" if row["kind"] == "color" else "removal "
        gap = "n/a" if row["gap_closed"] is None else f"{row['gap_closed']:.2f}"
        worse = row["gap_closed"] is not None and row["gap_closed"] < 0  # a model too rough to edit: said, not left to the number
        typer.echo(printable(f"{what}   {row['source']}'s {row['part']}: closes {gap} of the PSNR gap to its twin "
                             f"({_db(row['psnr_before'])} -> {_db(row['psnr'])} dB) in {row['seconds']:.2f} s; delta {row['delta']}"
                             + (f"\n           worse than no edit: a model of {score['psnr']:.1f} dB held-out is too rough to edit "
                                "well (train longer: --minutes)" if worse else "")))
    if demo:
        first = demo["edits"][0]
        typer.echo(f"picture    {demo['picture']}")
        typer.echo(printable(f"next       crfedit render {model_path} --instance {first['source']} --edit {first['delta']} --views orbit:24 --out {out / 'edited'}"))
        import importlib.util

        extra = "" if importlib.util.find_spec("aiohttp") else "; needs pip install -e '.[ui]'"
        typer.echo(printable(f"           crfedit ui {model_path} --data {out / 'data'} --edit {first['delta']}  (scribble your own{extra})"))
    typer.echo(f"done in {time.perf_counter() - start:.0f} s")
