"""Views of one instance rendered to a folder: ``NNNN.png`` (+ depth EXR), ``views.json`` and a
video; what ``crfedit render`` and ``crfedit quickstart`` write."""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

from .errors import CrfError
from .io import check_replaceable, write_exr, write_json, write_png
from .preview import depth_preview
from .renderer import ray_distance, render_camera
from .video import check_fps, video_path, write_video
from .views import resolve_views


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


def _frame_files(i: int, depth: bool) -> list[str]:
    """The files of frame ``i`` of a render: ``NNNN.png`` (and its depth EXR and preview)."""
    return [f"{i:04d}.png", *([f"{i:04d}_depth.exr", f"{i:04d}_depth.png"] if depth else [])]


def _earlier_frames(out: Path) -> set[str]:
    """The frame files an earlier render wrote to ``out``, as its ``views.json`` lists them
    (with their depth files), that are there: a new render removes those it does not write
    again, so the folder holds one set of frames; files it did not write stay."""
    try:
        listed = json.loads((out / "views.json").read_text())["views"]
        names = {r["file"] for r in listed if isinstance(r, dict) and isinstance(r.get("file"), str)}
    except (OSError, ValueError, KeyError, TypeError):
        return set()
    frames = {n for f in names if re.fullmatch(r"\d{4}\.png", f) for n in _frame_files(int(f[:4]), True)}
    return {n for n in frames if (out / n).is_file()}


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
    folder is the same as a single process writes.  ``seconds`` is then the slowest rank's.
    A run that fails part way (a full disk, Ctrl-C) removes the files it wrote, so no partial
    set of frames is left to pass for a render."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from .distributed import SINGLE
    from .video import to_uint8

    ranks = ranks or SINGLE

    if chunk < 1:
        raise CrfError(f"--chunk {chunk}: must be at least 1")
    views = resolve_views(spec, model, instance, res)
    if video is not None:
        target = video_path(video)  # a bad suffix or frame rate fails before any rendering
        check_fps(fps)
        if target != video and target.exists():  # the GIF in place of an MP4 is a file the user did not name
            raise CrfError(f"--video {video}: without the [video] extra (pip install -e '.[video]') this writes {target.name}, "
                           f"which exists already; give --video {target} to replace it")
        if target.is_file():  # a video replaces a video, not notes or a photo that took a typo's name
            check_replaceable(target, "--video", (target.suffix.lower(),))
        made = [out.absolute(), *out.absolute().parents]  # the folders --out's creation makes or finds
        if video.is_dir() or not (video.parent.is_dir() or video.parent.absolute() in made):
            raise CrfError(f"--video {video}: needs a file name in an existing folder (or in --out's)")
    earlier: set[str] = set()
    if ranks.main:
        prepare_folder(out)
        earlier = _earlier_frames(out)
    ranks.barrier("waiting for rank 0 to create the output folder")
    field = model.field_for(instance)
    frames, records, seconds = {}, {}, 0.0
    columns = (TextColumn("{task.description:<12}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    console = Console(stderr=True)
    written: list[Path] = []  # this run's files: a run that fails (a full disk, Ctrl-C) removes them again
    try:
        with Progress(*columns, console=console, transient=True, disable=not console.is_terminal) as bar:
            task = bar.add_task("rendering", total=len(views))
            for i, (label, camera) in ranks.shard(list(enumerate(views))):
                t0 = time.perf_counter()
                output = render_camera(field, camera, instance, chunk=chunk)
                seconds += time.perf_counter() - t0
                rgb = output.rgb.clamp(0.0, 1.0).cpu().numpy()
                files = [out / name for name in _frame_files(i, depth)]
                written.append(files[0])
                write_png(files[0], rgb)
                if depth:
                    z = ray_distance(output).cpu().numpy()
                    written += files[1:]
                    write_exr(files[1], {"Z": z, "A": output.opacity.cpu().numpy()})
                    write_png(files[2], depth_preview(z, output.opacity.cpu().numpy()))
                if video is not None:
                    frames[i] = to_uint8(rgb)
                records[i] = {
                    "file": files[0].name, "view": label, "width": camera.width, "height": camera.height,
                    "camera_angle_x": camera.camera_angle_x, "transform_matrix": camera.c2w.tolist(),
                }
                bar.update(task, advance=1, description=label)
        if ranks.world > 1:
            parts = ranks.gather((records, frames, seconds), "gathering the rendered views")
            records = {i: r for part in parts for i, r in part[0].items()}
            frames = {i: f for part in parts for i, f in part[1].items()}
            seconds = max(part[2] for part in parts)
        video_written = None
        if ranks.main:
            write_json(out / "views.json", {"instance": model.names[instance], "spec": spec, "views": [records[i] for i in sorted(records)]})
            video_written = write_video(video, [frames[i] for i in sorted(frames)], fps) if video is not None else None
            now = {n for i in range(len(views)) for n in _frame_files(i, depth)}
            for name in sorted(earlier - now):  # an earlier render's frames this one did not write: not this set's
                (out / name).unlink(missing_ok=True)
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise
    first = views[0][1]
    return RenderResult(len(views), first.width, first.height, seconds, video_written)
