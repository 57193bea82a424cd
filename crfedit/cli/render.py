"""``crfedit render``: views of one instance, optionally edited, to PNG (+ depth EXR, video)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import CrfError
from .common import DeviceChoice, DeviceOpt, app, user_errors


@dataclass
class RenderResult:
    count: int
    width: int
    height: int
    seconds: float  # rendering only, file writes excluded
    video: Path | None


def prepare_folder(out: Path) -> None:
    """``mkdir -p out``; an existing file there is a user error."""
    if out.exists() and not out.is_dir():
        raise CrfError(f"--out {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CrfError(f"--out {out}: cannot create the folder ({e.strerror or e.__class__.__name__})") from None


def render_to_folder(
    model, instance: int, spec: str, out: Path, res: int | None = None, depth: bool = False,
    video: Path | None = None, chunk: int = 16384, fps: float = 12.0, ranks=None,
) -> RenderResult:
    """Render the views ``spec`` names and write ``out/NNNN.png`` (+ ``NNNN_depth.exr`` with float32
    channels Z = ray distance, +inf where opacity ≤ 1e-3, and A = opacity, and a colour-mapped
    ``NNNN_depth.png`` preview), ``out/views.json``
    (label and camera of each NNNN) and, with ``video``, an MP4 or GIF of the frames.

    Under torchrun (``ranks``) each rank renders and writes every ``world``-th view; rank 0
    gathers the camera records (and frames) and writes ``views.json`` and the video, so the
    folder is the same as a single process writes.  ``seconds`` is then the slowest rank's."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from ..distributed import SINGLE
    from ..io import write_exr, write_json, write_png
    from ..preview import depth_preview
    from ..renderer import ray_distance, render_camera
    from ..video import to_uint8, video_path, write_video
    from ..views import resolve_views

    ranks = ranks or SINGLE

    if chunk < 1:
        raise CrfError(f"--chunk {chunk}: must be at least 1")
    views = resolve_views(spec, model, instance, res)
    if video is not None:
        video_path(video)  # a bad suffix fails before any rendering
        if video.is_dir() or not video.parent.is_dir():
            raise CrfError(f"--video {video}: needs a file name in an existing folder")
    if ranks.main:
        prepare_folder(out)
    ranks.barrier("waiting for rank 0 to create the output folder")
    field = model.field_for(instance)
    frames, records, seconds = {}, {}, 0.0
    columns = (TextColumn("{task.description:<12}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    console = Console()
    with Progress(*columns, console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task("rendering", total=len(views))
        for i, (label, camera) in ranks.shard(list(enumerate(views))):
            t0 = time.perf_counter()
            output = render_camera(field, camera, instance, chunk=chunk)
            seconds += time.perf_counter() - t0
            rgb = output.rgb.clamp(0.0, 1.0).cpu().numpy()
            write_png(out / f"{i:04d}.png", rgb)
            if depth:
                z = ray_distance(output).cpu().numpy()
                write_exr(out / f"{i:04d}_depth.exr", {"Z": z, "A": output.opacity.cpu().numpy()})
                write_png(out / f"{i:04d}_depth.png", depth_preview(z, output.opacity.cpu().numpy()))
            if video is not None:
                frames[i] = to_uint8(rgb)
            records[i] = {
                "file": f"{i:04d}.png", "view": label, "width": camera.width, "height": camera.height,
                "camera_angle_x": camera.camera_angle_x, "transform_matrix": camera.c2w.tolist(),
            }
            bar.update(task, advance=1, description=label)
    if ranks.world > 1:
        parts = ranks.gather((records, frames, seconds), "gathering the rendered views")
        records = {i: r for part in parts for i, r in part[0].items()}
        frames = {i: f for part in parts for i, f in part[1].items()}
        seconds = max(part[2] for part in parts)
    written = None
    if ranks.main:
        write_json(out / "views.json", {"instance": model.names[instance], "spec": spec, "views": [records[i] for i in sorted(records)]})
        written = write_video(video, [frames[i] for i in sorted(frames)], fps) if video is not None else None
    first = views[0][1]
    return RenderResult(len(views), first.width, first.height, seconds, written)


@app.command("render")
@user_errors
def render_cmd(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="Model file (.safetensors).")],
    instance: Annotated[str, typer.Option("--instance", help="Instance to render: a name or an index.")],
    views: Annotated[str, typer.Option("--views", help="Views: test, test:0-9, train:1,4,7, orbit:36, orbit:36@45, or a camera JSON file.")],
    out: Annotated[Path, typer.Option("--out", help="Folder for NNNN.png (created if missing).")],
    res: Annotated[Optional[int], typer.Option("--res", help="Render at this width (height keeps the aspect ratio).")] = None,
    depth: Annotated[bool, typer.Option("--depth", help="Also write NNNN_depth.exr (Z = ray distance, +inf on background; A = opacity) and a colour-mapped NNNN_depth.png (near red, far blue).")] = False,
    video: Annotated[Optional[Path], typer.Option("--video", help="Also write the frames as a video: MP4 with the [video] extra, else GIF (a .gif name always gives GIF).")] = None,
    fps: Annotated[float, typer.Option("--fps", help="Frames per second of --video.")] = 12.0,
    shape_from: Annotated[Optional[str], typer.Option("--shape-from", help="Render with the shape code of this instance (name or index).")] = None,
    color_from: Annotated[Optional[str], typer.Option("--color-from", help="Render with the color code of this instance (name or index).")] = None,
    edit: Annotated[Optional[list[Path]], typer.Option("--edit", metavar="EDIT", help="Apply this edit file first (repeatable, applied in order).")] = None,
    chunk: Annotated[int, typer.Option("--chunk", help="Rays rendered at once; lower it to save memory.")] = 16384,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Render views of one instance, optionally with edits applied or codes swapped in.

    Under torchrun (torchrun --nproc-per-node N -m crfedit render ...) the views are shared out
    over the ranks; the output folder is the same as one process writes.
    """
    from ..distributed import SINGLE, process_group, rank_device, ranks_from_env
    from ..model import load_model
    from ..runtime import resolve_device
    from ..views import parse_resolution

    res = parse_resolution(res)
    ranks = ranks_from_env()
    dev = resolve_device(device) if ranks is None else rank_device(device, ranks)
    ranks = ranks or SINGLE
    m, _ = load_model(model, dev)
    if edit:  # before the instance lookup: an edit may add the instance (fit-real)
        from ..delta import apply_edit_files

        m = apply_edit_files(m, list(edit))
    k = m.instance_index(instance)
    if shape_from is not None or color_from is not None:
        from ..edit.transfer import swap_codes

        m = swap_codes(
            m, k,
            shape_from=None if shape_from is None else m.instance_index(shape_from),
            color_from=None if color_from is None else m.instance_index(color_from),
        )
    with process_group(ranks, dev):
        result = render_to_folder(m, k, views, out, res, depth, video, chunk, fps, ranks)
    if not ranks.main:
        return
    per_view = result.seconds / max(result.count, 1)
    typer.echo(
        f"rendered {result.count} view{'s' if result.count != 1 else ''} of {m.names[k]} at {result.width}x{result.height} "
        f"in {result.seconds:.2f} s ({per_view:.3f} s per view) -> {out}"
    )
    if result.video is not None:
        kind = "MP4" if result.video.suffix.lower() == ".mp4" else "GIF"
        note = ""
        if video is not None and result.video != video:
            note = " (imageio-ffmpeg is not installed, so a GIF instead of MP4: pip install -e '.[video]')"
        typer.echo(f"wrote {kind} {result.video}{note}")
