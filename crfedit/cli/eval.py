"""``crfedit eval recon | edits | ablation`` and ``crfedit bench``.

Each command calls :mod:`crfedit.evaluation`, :mod:`crfedit.ablation` or :mod:`crfedit.bench`
(written out by :mod:`crfedit.report`) and prints a table
(``--json``: JSON only on stdout; progress and warnings go to stderr).
"""

from __future__ import annotations

import enum
import json
import math
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import CrfError
from ..io import check_folder_target, check_replaceable
from ..names import is_digits
from .common import DeviceChoice, DeviceOpt, SeedOpt, app, echo_notes, eval_app, user_errors
from .train import PresetChoice


class SplitChoice(str, enum.Enum):
    test = "test"
    val = "val"
    train = "train"


ModelArg = Annotated[Path, typer.Argument(help="Model file (.safetensors) written by crfedit train.")]
DataArg = Annotated[Path, typer.Argument(help="Dataset the model was trained on: a category folder (instances.txt), or one NeRF-synthetic or nerfstudio scene.")]
TwinsDataArg = Annotated[Path, typer.Argument(help="Category dataset folder (instances.txt, and twins.json with the twins) the model was trained on.")]
AblationDataArg = Annotated[Path, typer.Argument(help="Category dataset folder (instances.txt) the variants train and are scored on.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print JSON only (progress and warnings go to stderr).")]
LpipsOpt = Annotated[
    Optional[Path],
    typer.Option("--lpips-weights", help="LPIPS-AlexNet weights (.safetensors); default $CRFEDIT_LPIPS_WEIGHTS; without, LPIPS is skipped."),
]
StrictOpt = Annotated[bool, typer.Option("--strict", help="A dataset other than the model's training data (for eval edits also a part head trained on the twins' sources) is an error, not a warning.")]


def _json_safe(obj):
    """Non-finite floats become null, so the output is valid JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _echo_json(obj) -> None:
    typer.echo(json.dumps(_json_safe(obj), indent=2, allow_nan=False, ensure_ascii=False))


def _err(message: str) -> None:
    typer.echo(message, err=True)


def _num(value, fmt: str) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return format(value, fmt)


def _print_table(title: str, columns: list[str], rows: list[list[str]], footer: list[str] | None = None) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    for i, name in enumerate(columns):
        table.add_column(name, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*row)
    if footer is not None:
        table.add_section()
        table.add_row(*footer)
    console = Console(soft_wrap=True)
    need = console.measure(table, options=console.options.update_width(10_000)).maximum  # printed whole: a narrow terminal wraps its lines
    (console if need <= console.width else Console(soft_wrap=True, width=need)).print(table)


def _lpips_line(reported: bool, note: str | None) -> str:
    from ..evaluation import LPIPS_SKIPPED

    if reported:
        return "LPIPS: AlexNet v0.1 (lower is better)"
    if note and "no weights" in note:
        return LPIPS_SKIPPED
    return f"LPIPS: skipped ({note})" if note else LPIPS_SKIPPED


def _load(model: Path, data: Path, device: DeviceChoice, strict: bool, split: str = "test"):
    """(model, category at the model's resolution), after the fingerprint check."""
    from ..evaluation import fingerprint_warning, load_category_for
    from ..model import load_model
    from ..runtime import resolve_device

    m, _ = load_model(model, resolve_device(device))
    category = load_category_for(m, data, split)
    echo_notes(category)
    warning = fingerprint_warning(m, category)
    if warning is not None:
        if strict:
            raise CrfError(warning)
        _err(f"warning: {warning}")
    try:
        baked = json.loads(m.meta.get("baked_edits", "[]"))
    except json.JSONDecodeError:
        baked = []
    if isinstance(baked, list) and baked:  # scores of an edited chair against the unedited data read as a bad model
        _err(f"note: {model} has {len(baked)} edit{'s' * (len(baked) != 1)} baked in (crfedit info lists them): the instances "
             "they edit are scored as edited, against the dataset's unedited views (and eval edits' 'unedited' rows are this "
             "baked model)")
    return m, category


# ----------------------------------------------------------------------------- eval recon


@eval_app.command("recon")
@user_errors(ranked=True)
def recon_cmd(
    model: ModelArg,
    data: DataArg,
    split: Annotated[SplitChoice, typer.Option("--split", help="Split to score (test and val are held out).")] = SplitChoice.test,
    max_views: Annotated[Optional[int], typer.Option("--max-views", help="Score only the first N views of each instance.")] = None,
    lpips_weights: LpipsOpt = None,
    as_json: JsonOpt = False,
    strict: StrictOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Reconstruction quality of held-out views: PSNR, SSIM (and LPIPS with weights), per instance and mean.

    Under torchrun the instances are shared out over the ranks; rank 0 prints the gathered table.
    """
    from ..distributed import SINGLE, process_group, rank_device, ranks_from_env
    from ..evaluation import evaluate_recon

    if max_views is not None and max_views < 1:
        raise CrfError(f"--max-views {max_views}: must be at least 1")
    ranks = ranks_from_env()
    if ranks is not None:
        device = rank_device(device, ranks)
    ranks = ranks or SINGLE
    m, category = _load(model, data, device, strict, split.value)
    with process_group(ranks, m.device):
        score = evaluate_recon(m, category, split.value, max_views, lpips_weights, ranks, progress=_err)
    if not ranks.main:
        return
    if score["without_views"]:  # left out of the means: said, not silent
        names = score["without_views"]
        _err(f"note: {len(names)} instance{'s' * (len(names) != 1)} ({', '.join(names[:4])}{', …' if len(names) > 4 else ''}) "
             f"{'have' if len(names) != 1 else 'has'} no {split.value} views in {data}: left out of the scores")
    if as_json:
        _echo_json({"model": str(model), "data": str(data), **score})
        return
    with_lpips = score["lpips"] is not None
    columns = ["instance", "views", "PSNR (dB)", "SSIM"] + (["LPIPS"] if with_lpips else [])
    rows = [
        [name, str(s["n"]), _num(s["psnr"], ".2f"), _num(s["ssim"], ".4f")] + ([_num(s["lpips"], ".4f")] if with_lpips else [])
        for name, s in score["instances"].items()
    ]
    footer = ["mean", str(score["n"]), _num(score["psnr"], ".2f"), _num(score["ssim"], ".4f")]
    footer += [_num(score["lpips"], ".4f")] if with_lpips else []
    _print_table(f"{model.name} on {data} ({split.value} split)", columns, rows, footer)
    typer.echo(score["ssim_note"])
    typer.echo(_lpips_line(score["lpips"] is not None, score["lpips_note"]))


# ----------------------------------------------------------------------------- eval edits


def _strategies(text: str) -> tuple[str, ...]:
    from ..edit import STRATEGIES

    items = tuple(s.strip() for s in text.split(",") if s.strip())
    if not items:
        raise CrfError(f"--strategies {text!r}: give one or more of {', '.join(STRATEGIES)}, comma-separated")
    for s in items:
        if s not in STRATEGIES:
            raise CrfError(f"--strategies {text}: {s!r} is not one of {', '.join(STRATEGIES)}")
    return items


TABLE_TITLES = {"color": "Table 2 (colour edits)", "remove": "Table 3 (shape edits: removal)"}


@eval_app.command("edits")
@user_errors(ranked=True)
def edits_cmd(
    model: ModelArg,
    data: TwinsDataArg,
    strategies: Annotated[str, typer.Option("--strategies", help="Update strategies to compare, comma-separated: hybrid, codes, all.")] = "hybrid,codes,all",
    nerf_baseline: Annotated[bool, typer.Option("--nerf-baseline/--no-nerf-baseline", help="Also train a single-instance NeRF per source and fine-tune it (slow).")] = False,
    nerf_steps: Annotated[Optional[int], typer.Option("--nerf-steps", help="Training steps of each single-instance NeRF (with --nerf-baseline; default 1000).", show_default=False)] = None,
    nerf_minutes: Annotated[Optional[float], typer.Option("--nerf-minutes", help="Optional time budget of each single-instance NeRF.")] = None,
    steps: Annotated[int, typer.Option("--steps", help="Optimization steps of each edit.")] = 100,
    rays: Annotated[int, typer.Option("--rays", help="Most rays rendered per edit step.")] = 1024,
    lr: Annotated[float, typer.Option("--lr", help="Adam learning rate of the edits.")] = 1e-2,
    penalty: Annotated[str, typer.Option("--penalty", help="Weight penalty of the edits: element (every trained number weighed alike; default) or tensor (Σ per-tensor means, the earlier rule).")] = "element",
    recolor: Annotated[str, typer.Option("--recolor", "--recolour", help="Recolour target of the selection edits: shading (default) or ratio (the earlier rule; see crfedit edit-color --help).")] = "shading",
    lpips_weights: LpipsOpt = None,
    as_json: JsonOpt = False,
    strict: StrictOpt = False,
    seed: SeedOpt = 0,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """The paper's edit protocol on the dataset's ground-truth twins (Tables 2 and 3).

    Each colour and removal twin is edited from its scribbles with each strategy; every test
    view of the source is rendered with the edit and scored against the twin's test views.
    Rows: strategies (mean over twins), the unedited model as a reference, the paper's losses
    (hybrid, --method paper: one more edit per twin), and optionally a single-instance NeRF
    fine-tuned with the same edit.
    """
    from ..distributed import SINGLE, process_group, rank_device, ranks_from_env
    from ..edit import EditOptions
    from ..evaluation import NerfBaseline, evaluate_edits, load_twin_cases, part_labels_warning

    chosen = _strategies(strategies)
    options = EditOptions(steps=steps, rays=rays, lr=lr, seed=seed, penalty=penalty, recolor=recolor).validated()
    if not nerf_baseline and (nerf_steps is not None or nerf_minutes is not None):  # they set the baseline only
        raise CrfError("--nerf-steps and --nerf-minutes belong to --nerf-baseline (the single-instance NeRF is not trained without it)")
    nerf_steps = 1000 if nerf_steps is None else nerf_steps
    if nerf_steps < 1:
        raise CrfError(f"--nerf-steps {nerf_steps}: must be at least 1")
    if nerf_minutes is not None and not (nerf_minutes > 0 and math.isfinite(nerf_minutes)):
        raise CrfError(f"--nerf-minutes {nerf_minutes:g}: must be a finite positive number")
    ranks = ranks_from_env()
    if ranks is not None:
        device = rank_device(device, ranks)
    ranks = ranks or SINGLE
    m, category = _load(model, data, device, strict)
    cases = load_twin_cases(m, category)
    warning = part_labels_warning(m, cases)
    if warning is not None:
        if strict:
            raise CrfError(warning)
        _err(f"warning: {warning}")
    nerf = NerfBaseline(nerf_steps, nerf_minutes) if nerf_baseline else None
    with process_group(ranks, m.device):
        result = evaluate_edits(
            m, category, cases, chosen, options, nerf, lpips_weights, m.device, seed, progress=_err, ranks=ranks,
        )
    if not ranks.main:
        return
    if as_json:
        _echo_json({"model": str(model), "data": str(data), **result})
        return
    with_lpips = any(r["lpips"] is not None for rows in result["tables"].values() for r in rows)
    for kind, rows in result["tables"].items():
        columns = ["method", "twins", "PSNR (dB)", "SSIM"] + (["LPIPS"] if with_lpips else []) + [
            "gap closed", "below", "inside", "outside", "sel. IoU", "seconds"]
        body = [
            [r["method"], str(r["n"]), _num(r["psnr"], ".2f"), _num(r["ssim"], ".4f")]
            + ([_num(r["lpips"], ".4f")] if with_lpips else [])
            + [_num(r["gap_closed"], ".2f"), _num(r["below_unedited"], "d"), _num(r["psnr_inside"], ".2f"), _num(r["psnr_outside"], ".2f"),
               _num(r["selection_iou"], ".2f"), _num(r["seconds"], ".2f")]
            for r in rows
        ]
        _print_table(f"{TABLE_TITLES[kind]}: {model.name} on {data}", columns, body)
    for entry in result["skipped"]:
        typer.echo(f"skipped {entry['method']} for {entry['kind']} twins: {entry['reason']}")
    typer.echo("unedited: the model's renders of the source before editing, scored against the twin (reference)")
    typer.echo("gap closed: (PSNR − unedited) / (ceiling − unedited), ceiling = the source's reconstruction on the same poses; averaged over the twins whose ceiling lies above unedited (gap_closed_n in --json)")
    typer.echo("below: twins the edit left with a lower PSNR than no edit at all")
    typer.echo("inside / outside: PSNR (dB) on the pixels where the twin differs from the source / on the rest")
    typer.echo("sel. IoU: the 3-D selection of the scribbles against the part's pixels of the test views")
    typer.echo("seconds: edit optimization time, mean over twins")
    if result["nerf_train_seconds"]:
        train_s = sum(result["nerf_train_seconds"].values()) / len(result["nerf_train_seconds"])
        typer.echo(f"nerf (single instance): a NeRF trained {train_s:.1f} s on the source alone, then every weight fine-tuned")
    typer.echo(result["ssim_note"])
    typer.echo(_lpips_line(with_lpips, result["lpips_note"]))


# ----------------------------------------------------------------------------- eval ablation


@eval_app.command("ablation")
@user_errors
def ablation_cmd(
    data: AblationDataArg,
    minutes: Annotated[Optional[float], typer.Option("--minutes", help="Training time of each variant (this or --steps is required).")] = None,
    steps: Annotated[Optional[int], typer.Option("--steps", help="Training steps of each variant (this or --minutes is required; with both, whichever ends first).")] = None,
    preset: Annotated[PresetChoice, typer.Option("--preset", help="Preset the variants are built from.")] = PresetChoice.fast,
    sets: Annotated[Optional[list[str]], typer.Option("--set", help="Override a config field of every variant, KEY=VALUE (repeatable).")] = None,
    res: Annotated[Optional[int], typer.Option("--res", help="Train and score at this image width (default: as stored).")] = None,
    max_views: Annotated[Optional[int], typer.Option("--max-views", help="Score only the first N held-out views of each instance.")] = None,
    models: Annotated[Optional[Path], typer.Option("--models", help="Keep the trained variants in this folder (default: a temporary one).")] = None,
    as_json: JsonOpt = False,
    seed: SeedOpt = 0,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Table 1: the architecture variants at equal network parameters and an equal budget.

    nerf (no codes), single (one code for shape and colour), separate (shape and colour codes,
    no shared branch) and ours each train for --minutes (or --steps) with the width that brings
    their network parameters (codes and feature grid excluded) within 5 % of ours; held-out
    PSNR and SSIM are reported.
    """
    from ..config import make_config
    from ..data.loading import load_category
    from ..ablation import run_ablation
    from ..evaluation import SSIM_NOTE
    from ..runtime import resolve_device
    from ..views import parse_resolution

    if minutes is None and steps is None:
        raise CrfError("give a budget per variant: --minutes M and/or --steps N")
    if max_views is not None and max_views < 1:
        raise CrfError(f"--max-views {max_views}: must be at least 1")
    if models is not None:
        check_folder_target(models, "--models")
    base = make_config(preset.value, sets=sets or [])
    dev = resolve_device(device)
    category = load_category(data, res=parse_resolution(res))
    rows = run_ablation(
        category, minutes, steps, seed, dev, base=base, max_views=max_views, workdir=models, progress=_err,
    )
    lpips_note = "the ablation does not compute it; eval recon MODEL DATA --lpips-weights W scores a variant kept with --models"
    if as_json:
        _echo_json({"data": str(data), "preset": preset.value, "minutes": minutes, "steps": steps, "rows": rows, "lpips_note": lpips_note})
        return
    split = rows[0]["split"] if rows else "test"
    body = [
        [r["arch"], str(r["width"]), f"{r['params']:,}", f"{r['params_vs_ours']:.3f}", str(r["steps"]), f"{r['seconds']:.1f}",
         _num(r["psnr"], ".2f"), _num(r["ssim"], ".4f")]
        for r in rows
    ]
    budget = " and ".join(x for x in (f"{minutes:g} min" if minutes else "", f"{steps} steps" if steps else "") if x)
    _print_table(
        f"Table 1 (ablation): {data}, {budget} each, held-out {split}",
        ["arch", "width", "params", "vs ours", "steps", "seconds", "PSNR (dB)", "SSIM"], body,
    )
    typer.echo("params: network parameters without the per-instance codes and the shared feature grid")
    typer.echo(SSIM_NOTE)
    typer.echo(_lpips_line(False, lpips_note))  # skipped, said so, never another metric in its place


# ----------------------------------------------------------------------------- bench


def _floats(option: str, text: str | None) -> tuple[float, ...] | None:
    """``"0.5,1,2"`` → (0.5, 1.0, 2.0); ``"none"`` → () (leave that sweep out); None → None."""
    if text is None:
        return None
    if text.strip().lower() == "none":
        return ()
    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise CrfError(f"{option} {text}: expected numbers separated by commas, e.g. 0.5,1,2") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise CrfError(f"{option} {text}: expected positive numbers separated by commas")
    return values


def _ints(option: str, text: str | None) -> tuple[int, ...] | None:
    """``"10,30"`` → (10, 30); ``"none"`` → (); None → None."""
    if text is None:
        return None
    if text.strip().lower() == "none":
        return ()
    items = [x.strip() for x in text.split(",") if x.strip()]
    if not items or not all(is_digits(x) and int(x) > 0 for x in items):
        raise CrfError(f"{option} {text}: expected positive whole numbers separated by commas, e.g. 10,30,100")
    return tuple(int(x) for x in items)


@app.command("bench")
@user_errors
def bench_cmd(
    data: Annotated[Optional[Path], typer.Argument(help="Category dataset with twins (default with --tiny: a generated 2-chair one).")] = None,
    tiny: Annotated[bool, typer.Option("--tiny", help="A seconds-long sweep on tiny settings (a smoke test of the pipeline).")] = False,
    csv_path: Annotated[Path, typer.Option("--csv", metavar="CSV", help="CSV to write; the plots go beside it as <stem>_<group>.png. The repository's page uses --csv docs/benchmarks/bench.csv.")] = Path("runs/bench/bench.csv"),
    md_path: Annotated[Path, typer.Option("--md", metavar="MARKDOWN", help="Markdown page whose bench section (between the markers) is rewritten. The repository's page: --md docs/benchmarks.md.")] = Path("runs/bench/benchmarks.md"),
    presets: Annotated[Optional[str], typer.Option("--presets", help="Training curves, comma-separated (default fast,paper).")] = None,
    minutes: Annotated[Optional[float], typer.Option("--minutes", help="Training time per curve (default 5).")] = None,
    steps: Annotated[Optional[int], typer.Option("--steps", help="Step cap per training curve.")] = None,
    checkpoints: Annotated[Optional[int], typer.Option("--checkpoints", help="Points scored along each training run (default 6).")] = None,
    train_spc: Annotated[Optional[str], typer.Option("--train-samples-per-cell", help="Extra fast-preset training curves at these steps_per_cell (default 2; none: leave out).")] = None,
    render_spc: Annotated[Optional[str], typer.Option("--samples-per-cell", help="steps_per_cell values to render at (default 0.5,1,2,4,8; none: leave out).")] = None,
    edit_steps: Annotated[Optional[str], typer.Option("--edit-steps", help="Edit steps to sweep (default 10,30,100,300; none: no edit curves).")] = None,
    edit_rays: Annotated[Optional[str], typer.Option("--edit-rays", help="Edit rays to sweep, one curve each (default 256,1024,4096).")] = None,
    eval_instances: Annotated[Optional[int], typer.Option("--eval-instances", help="Instances scored at each point (default 4).")] = None,
    eval_views: Annotated[Optional[int], typer.Option("--eval-views", help="Held-out views per scored instance (default 2).")] = None,
    sets: Annotated[Optional[list[str]], typer.Option("--set", help="Override a config field of every training run, KEY=VALUE (repeatable).")] = None,
    work: Annotated[Optional[Path], typer.Option("--work", help="Keep the trained models in this folder (default: a temporary one).")] = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Speed against error: sweep presets, training time, samples per ray, edit steps and rays.

    Writes a CSV, one PNG plot of PSNR against seconds per group (training, rendering,
    editing) and markdown tables into the bench section of --md, stamped with the machine,
    date and git revision.
    """
    import dataclasses
    import tempfile

    from ..bench import TINY_LABEL, BenchSettings, run_bench, tiny_category
    from ..report import write_outputs
    from ..data.loading import load_category
    from ..runtime import resolve_device

    settings = BenchSettings.tiny() if tiny else BenchSettings()
    changes = {
        "presets": None if presets is None else tuple(p.strip() for p in presets.split(",") if p.strip()),
        "minutes": minutes, "steps": steps, "checkpoints": checkpoints,
        "train_steps_per_cell": _floats("--train-samples-per-cell", train_spc),
        "render_steps_per_cell": _floats("--samples-per-cell", render_spc),
        "edit_steps": _ints("--edit-steps", edit_steps), "edit_rays": _ints("--edit-rays", edit_rays),
        "eval_instances": eval_instances, "eval_views": eval_views,
        "sets": None if sets is None else tuple(settings.sets) + tuple(sets), "seed": seed,
    }
    settings = dataclasses.replace(settings, **{k: v for k, v in changes.items() if v is not None}).validated()
    for option, path, default, suffix in (("--csv", csv_path, "runs/bench/bench.csv", ".csv"), ("--md", md_path, "runs/bench/benchmarks.md", ".md")):
        if path.is_dir():
            raise CrfError(f"{option} {path}: is a folder; give a file name")
        if path == Path(default):
            check_folder_target(path.parent, option)  # the default folder is made
        else:
            check_replaceable(path, option, (suffix,))
        if suffix == ".csv":  # the plots go beside it: <stem>_<group>.png
            for plot in path.parent.glob(f"{path.stem}_*.png") if path.parent.is_dir() else []:
                check_replaceable(plot, f"{option} {path}: its plot", (".png",))
    dev = resolve_device(device)
    with tempfile.TemporaryDirectory(prefix="crfedit-tiny-") as tmp:
        if data is not None:
            category = load_category(data)
        elif tiny:
            category = tiny_category(Path(tmp) / "chairs")
        else:
            raise CrfError("give a DATA folder (a category with twins, e.g. from crfedit dataset synth), or --tiny")
        report = run_bench(category, settings, dev, workdir=work, progress=_err, data_label=None if data is not None else TINY_LABEL)
        written = write_outputs(report, csv_path, md_path)
    for path in written:
        typer.echo(f"wrote {path}")
    for note in report.notes:
        typer.echo(f"note: {note}", err=True)
