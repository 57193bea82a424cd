"""``crfedit fit-real``: a new instance fitted to one photo, written as a ``fit-real`` edit file."""

from __future__ import annotations

import enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import CrfError
from .common import DeviceChoice, DeviceOpt, JsonOpt, SeedOpt, app, check_out_file, command_line, instance_option, json_record, size_text, stderr_progress, user_errors


class JointWeights(str, enum.Enum):
    heads = "heads"
    all = "all"


class Start(str, enum.Enum):  # fit_real.STARTS, listed in --help as the other choices are
    nearest = "nearest"
    mean = "mean"
    nearest_codes = "nearest-codes"


class FitProgress:
    """A rich progress bar over both stages: stage, step/total, loss and PSNR of the batch, elapsed.

    Stage reports (a full render of the pose against the photo) are printed as they come.
    """

    def __init__(self, total: int):
        from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

        self.bar = stderr_progress(
            TextColumn("{task.description:<6}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("loss {task.fields[loss]}  PSNR {task.fields[psnr]}"),
            TimeElapsedColumn(),
        )
        self.task = self.bar.add_task("codes", total=max(total, 1), loss="-", psnr="-")

    def __enter__(self) -> "FitProgress":
        self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.stop()

    def note(self, line: str) -> None:
        """A line on stderr above the bar (a warning met while fitting)."""
        if self.bar.live.is_started:
            self.bar.console.print(line, highlight=False, markup=False)
        else:
            typer.echo(line, err=True)

    def on_step(self, stage: str, step: int, steps: int, loss: float, psnr: float) -> None:
        self.bar.update(self.task, advance=1, description=stage, loss=f"{loss:.4f}", psnr=f"{psnr:5.2f}")

    def on_stage(self, report) -> None:
        line = (
            f"{report.stage:<6} {report.steps:>5} steps  photo loss {report.loss:.5f}  "
            f"PSNR {report.psnr:5.2f} dB  ({report.seconds:.1f} s)"
        )
        if self.bar.live.is_started:
            self.bar.console.print(line, highlight=False, markup=False)
        else:
            typer.echo(line)


@app.command("fit-real")
@user_errors
@json_record
def fit_real_cmd(
    model: Annotated[Path, typer.Argument(help="Model file (.safetensors).")],
    photo: Annotated[Path, typer.Argument(help="Photo of an object of the category (PNG or JPEG; an alpha channel marks the object).")],
    pose: Annotated[str, typer.Option("--pose", help="Camera of the photo: one view of a training instance with a similar pose (train:5, orbit:36:5 …) or a camera JSON file.")],
    out: Annotated[Path, typer.Option("--out", help="Edit file to write (.safetensors); written atomically.")],
    mask: Annotated[Optional[Path], typer.Option("--mask", help="Object mask, the photo's size: alpha > 0, else non-black pixels are the object (replaces the photo's alpha).")] = None,
    name: Annotated[Optional[str], typer.Option("--name", help="Name of the new instance (default: the photo's file name without extension).")] = None,
    pose_instance: Annotated[str, typer.Option("--pose-instance", help="The training instance whose views --pose names (name or index).")] = "0",
    steps_codes: Annotated[int, typer.Option("--steps-codes", help="Stage 1: steps on the new instance's shape and colour codes only.")] = 200,
    steps_joint: Annotated[int, typer.Option("--steps-joint", help="Stage 2: steps on codes and an instance-scoped copy of the weights (0: codes only).")] = 200,
    weights: Annotated[JointWeights, typer.Option("--weights", help="Weights stage 2 fine-tunes: heads (F_fuse, F_dens, F_rad) or all (the whole network, as the paper).")] = JointWeights.heads,
    lr_codes: Annotated[float, typer.Option("--lr-codes", help="Adam learning rate of the codes.")] = 1e-2,
    lr_weights: Annotated[float, typer.Option("--lr-weights", help="Adam learning rate of the weights (stage 2).")] = 1e-3,
    rays: Annotated[int, typer.Option("--rays", help="Rays per step, drawn from the photo's pixels (all of them at 64x64 by default).")] = 4096,
    start: Annotated[Start, typer.Option("--start", help="Where the fit starts: nearest (the codes of the training instance whose render from --pose best matches the photo's outline, in its grid), mean (the mean code in every training grid, as the paper), nearest-codes (those codes, every grid).")] = Start.nearest,
    distortion: Annotated[float, typer.Option("--distortion", help="Stage 2: weight of the distortion loss that gathers each ray's density into one surface (one photo leaves depth free; 0: off).")] = 0.1,
    edit: Annotated[Optional[list[Path]], typer.Option("--edit", help="An earlier edit to apply first (repeatable, in the order they were made).")] = None,
    as_json: JsonOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
    seed: SeedOpt = 0,
) -> None:
    """Fit a new instance to a photo of a real object: its codes first, then codes and a copy of
    the weights; writes a fit-real edit that adds the instance (the model file is untouched)."""
    from ..delta import apply_edit_files
    from ..fit_real import FitOptions, check_new_name, fit_real, photo_warnings, prepare_photo, read_photo
    from ..model import load_model
    from ..runtime import resolve_device
    from ..views import SPLITS, one_view_hint, one_view_label, resolve_views

    options = FitOptions(
        steps_codes=steps_codes, steps_joint=steps_joint, weights=weights.value, lr_codes=lr_codes,
        lr_weights=lr_weights, rays=rays, distortion=distortion, seed=seed, start=start.value,
    ).validated()
    check_out_file(out, {"MODEL": model, "PHOTO": photo, "--mask": mask, "--edit": edit}, "edit", "real.safetensors")
    name_from = "--name" if name is not None else "instance name (the photo's file name)"
    name = photo.stem if name is None else name
    image, object_mask = read_photo(photo, mask)
    base, _ = load_model(model, resolve_device(device))
    m = apply_edit_files(base, list(edit or []))
    check_new_name(m, name, name_from)
    j = instance_option(m, pose_instance, "--pose-instance")
    train = m.views.get("train")
    views = resolve_views(pose, m, j)
    if len(views) != 1:
        raise CrfError(f"--pose {pose}: names {len(views)} views; the photo has exactly one ({one_view_hint(pose)})")
    label, camera = views[0]
    if train is not None and camera.width != train.width:  # a camera file's own size: the fit runs at the model's
        fitted = camera.resized(train.width)
        typer.echo(f"note: --pose {pose}: a {camera.width}x{camera.height} camera; fit-real fits at the model's training size, "
                   f"{fitted.width}x{fitted.height} (focal scaled with it), and the photo is area-resized to that", err=True)
        camera = fitted
    label = one_view_label(pose, label)
    prepared = prepare_photo(image, object_mask, camera.width, camera.height, str(mask or photo))
    for line in photo_warnings(image, object_mask, camera.width, camera.height):
        typer.echo(f"warning: {line}", err=True)
    if prepared.silhouette == "white background":
        typer.echo(f"note: no alpha channel and no --mask: the object is what the photo's white background surrounds "
                   f"({prepared.mask.mean():.0%} of the view); give --mask to outline it yourself", err=True)
    with FitProgress(options.steps_codes + options.steps_joint) as progress:
        result = fit_real(m, prepared, camera, name, options, progress.on_step, progress.on_stage,
                          lambda text: progress.note(f"warning: {text}"))
    split_view = label.partition(":")[0] in SPLITS  # a stored view is a view of one instance
    result.save(out, command=command_line(), photo=str(photo), pose=f"{label} of {m.names[j]}" if split_view else label,
                **({"mask": str(mask)} if mask else {}))
    typer.echo(
        f"wrote {out}: fit-real edit adding instance {name} ({len(result.tensors)} tensors, "
        f"{size_text(out.stat().st_size)}), photo PSNR {result.stages[-1].psnr:.2f} dB, {result.seconds:.2f} s"
    )
