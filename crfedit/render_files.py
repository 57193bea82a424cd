"""Views of one instance rendered to a folder: ``NNNN.png`` (+ depth EXR), ``views.json`` and a
video; what ``crfedit render`` and ``crfedit quickstart`` write."""

from __future__ import annotations

import contextlib
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

from .errors import CrfError
from .io import atomic_folder, carry_into, check_folder_target, check_replaceable, write_exr, write_json, write_png
from .preview import depth_preview
from .renderer import camera_problem, ray_distance, render_camera
from .video import check_fps, video_path, write_video
from .views import resolve_views


@dataclass
class RenderResult:
    count: int
    width: int
    height: int
    seconds: float  # rendering only, file writes excluded
    video: Path | None
    sizes: tuple[tuple[int, int], ...] = ()  # every (width, height) the views come in, in order
    blank: tuple[str, ...] = ()  # the views that show nothing of the instance (no pixel half opaque)

    @property
    def size_text(self) -> str:
        """``64x64``, or ``64x64 / 48x48`` for views of several sizes."""
        return " / ".join(f"{w}x{h}" for w, h in (self.sizes or ((self.width, self.height),)))


def check_out_folder(out: Path, writes: set[str] = frozenset()) -> list[Path]:
    """The files of ``out`` a render into it keeps: all but an earlier render's (its
    ``views.json`` and the frames that lists), carried into the new folder that replaces ``out``
    whole.  ``out``'s parent is created; an existing file at ``out``, a folder in it (a render
    carries files, not folders), a file no earlier render listed that this one writes over
    (``writes``, its frame files, and ``views.json``: a user's photo named ``0000.png`` was
    replaced) or the current folder (or one that holds it) is a user error."""
    check_folder_target(out, "--out")  # not a file, nor under one
    if out.is_dir() and out.resolve() in (Path.cwd().resolve(), *Path.cwd().resolve().parents):
        raise CrfError(f"--out {out}: is the current folder or holds it, which a render replaces whole; name a folder for the frames")
    try:
        out.absolute().parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CrfError(f"--out {out}: cannot create the folder ({e.strerror or e.__class__.__name__})") from None
    if not out.is_dir():
        return []
    listed = _listed_views(out)
    earlier = _earlier_frames(out, listed)
    if listed is not None:  # an earlier render's record: it goes with its frames
        earlier |= {"views.json"}
    keep = [p for p in out.iterdir() if p.name not in earlier]
    if folders := [p.name for p in keep if p.is_dir() and not p.is_symlink()]:
        raise CrfError(f"--out {out}: holds a folder ({folders[0]}), which a render would lose as it replaces the folder whole; "
                       "pick a new folder or move it out")
    if clash := sorted(p.name for p in keep if p.name in writes or p.name == "views.json"):
        raise CrfError(f"--out {out}: holds {clash[0]}, which no earlier render listed and this one would write over (a file of "
                       "yours there was replaced); pick a new folder or move it out")
    return keep


def _listed_views(out: Path) -> list | None:
    """The view records of the ``views.json`` an earlier render wrote to ``out`` (an object with
    a ``views`` list); None when there is none, or the file is not such a record."""
    try:
        record = json.loads((out / "views.json").read_text())
    except (OSError, ValueError):
        return None
    return record["views"] if isinstance(record, dict) and isinstance(record.get("views"), list) else None


def _frame_files(i: int, depth: bool) -> list[str]:
    """The files of frame ``i`` of a render: ``NNNN.png`` (and its depth EXR and preview)."""
    return [f"{i:04d}.png", *([f"{i:04d}_depth.exr", f"{i:04d}_depth.png"] if depth else [])]


def _earlier_frames(out: Path, listed: list | None) -> set[str]:
    """The frame files an earlier render wrote to ``out``, as its ``views.json`` lists them
    (``listed``: :func:`_listed_views`) with their depth files, that are there: a new render
    replaces them with its own set."""
    if listed is None:
        return set()
    names = {r["file"] for r in listed if isinstance(r, dict) and isinstance(r.get("file"), str)}
    frames = {n for f in names if re.fullmatch(r"\d{4}\.png", f) for n in _frame_files(int(f[:4]), True)}
    return {n for n in frames if (out / n).is_file()}


def render_to_folder(
    model, instance: int, spec: str, out: Path, res: int | None = None, depth: bool = False,
    video: Path | None = None, chunk: int = 16384, fps: float = 12.0, ranks=None, source: dict | None = None,
) -> RenderResult:
    """Render the views ``spec`` names and write ``out/NNNN.png`` (+ ``NNNN_depth.exr`` with float32
    channels Z = ray distance, +inf where opacity ≤ 1e-3, and A = opacity, and a colour-mapped
    ``NNNN_depth.png`` preview), ``out/views.json``
    (label and camera of each NNNN; ``source``'s keys beside them: what the render was of, e.g.
    the model file, its ``--edit`` stack, swapped codes) and, with ``video``, an MP4 or GIF of the frames.

    Under torchrun (``ranks``) each rank renders and writes every ``world``-th view; rank 0
    gathers the camera records (and frames) and writes ``views.json`` and the video, so the
    folder is the same as a single process writes.  ``seconds`` is then the slowest rank's.
    The set is written to a hidden folder beside ``out`` that replaces ``out`` whole at the end
    (keeping the files of ``out`` that are not an earlier render's), so a run that fails part way
    (a full disk, Ctrl-C) leaves ``out`` as it was, and of two runs at once the later's set."""
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
    keep = check_out_folder(out, {n for i in range(len(views)) for n in _frame_files(i, depth)}) if ranks.main else []
    field = model.field_for(instance)
    for label, camera in views:  # before the first view is rendered, naming the view (render_camera's line names none)
        if problem := camera_problem(camera, field.aabb):
            raise CrfError(f"view {label}: {problem}")
    frames, records, seconds = {}, {}, 0.0
    columns = (TextColumn("{task.description:<12}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    console = Console(stderr=True)
    # the set is written to a hidden folder beside out and swapped in whole at the end (atomic_folder)
    with atomic_folder(out) if ranks.main else contextlib.nullcontext() as tmp:
        tmp = Path(ranks.gather(str(tmp), "sharing the output folder")[0])
        with Progress(*columns, console=console, transient=True, disable=not console.is_terminal) as bar:
            task = bar.add_task("rendering", total=len(views))
            for i, (label, camera) in ranks.shard(list(enumerate(views))):
                t0 = time.perf_counter()
                output = render_camera(field, camera, instance, chunk=chunk)
                seconds += time.perf_counter() - t0
                rgb = output.rgb.clamp(0.0, 1.0).cpu().numpy()
                files = [tmp / name for name in _frame_files(i, depth)]
                write_png(files[0], rgb)
                if depth:
                    z = ray_distance(output).cpu().numpy()
                    write_exr(files[1], {"Z": z, "A": output.opacity.clamp(0.0, 1.0).cpu().numpy()})  # Σw can round past 1
                    write_png(files[2], depth_preview(z, output.opacity.cpu().numpy()))
                if video is not None:
                    frames[i] = to_uint8(rgb)
                records[i] = {
                    "file": files[0].name, "view": label, "width": camera.width, "height": camera.height,
                    "camera_angle_x": camera.camera_angle_x, "transform_matrix": camera.c2w.tolist(),
                    "blank": bool(output.opacity.max() < 0.5),
                }
                bar.update(task, advance=1, description=label)
        if ranks.world > 1:
            parts = ranks.gather((records, frames, seconds), "gathering the rendered views")
            records = {i: r for part in parts for i, r in part[0].items()}
            frames = {i: f for part in parts for i, f in part[1].items()}
            seconds = max(part[2] for part in parts)
        video_written = None
        if ranks.main:
            write_json(tmp / "views.json", {"instance": model.names[instance], "spec": spec, **(source or {}),
                                            "views": [{k: v for k, v in records[i].items() if k != "blank"} for i in sorted(records)]})
            if video is not None:  # one in --out goes into the new folder with the frames
                inside = video.absolute().parent == out.absolute()
                video_written = write_video(tmp / video.name if inside else video, [frames[i] for i in sorted(frames)], fps)
                video_written = out / video_written.name if inside else video_written
            carry_into(keep, tmp)
    first = views[0][1]
    sizes = tuple(dict.fromkeys((c.width, c.height) for _, c in views))
    blank = tuple(records[i]["view"] for i in sorted(records) if records[i]["blank"])
    return RenderResult(len(views), first.width, first.height, seconds, video_written, sizes, blank)
