"""``crfedit render``: views of one instance, optionally edited, to PNG (+ depth EXR, video)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import DeviceChoice, DeviceOpt, app, instance_option, printable, user_errors


@app.command("render")
@user_errors(ranked=True)
def render_cmd(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="Model file (.safetensors).")],
    instance: Annotated[str, typer.Option("--instance", help="Instance to render: a name or an index.")],
    views: Annotated[str, typer.Option("--views", help="Views: test, test:0-9, train:1,4,7, orbit:36, orbit:36@45, a camera JSON file, or photo (the camera of the photo the --edit fit-real edit fitted this instance to).")],
    out: Annotated[Path, typer.Option("--out", help="Folder for NNNN.png (created if missing).")],
    res: Annotated[Optional[int], typer.Option("--res", help="Render at this width (height keeps the aspect ratio).")] = None,
    depth: Annotated[bool, typer.Option("--depth", help="Also write NNNN_depth.exr (Z = ray distance, +inf on background; A = opacity) and a colour-mapped NNNN_depth.png (near red, far blue).")] = False,
    video: Annotated[Optional[Path], typer.Option("--video", help="Also write the frames as a video: MP4 with the [video] extra, else GIF (a .gif name always gives GIF).")] = None,
    fps: Annotated[float, typer.Option("--fps", help="Frames per second of --video.")] = 12.0,
    shape_from: Annotated[Optional[str], typer.Option("--shape-from", help="Render with the shape code of this instance (name or index).")] = None,
    color_from: Annotated[Optional[str], typer.Option("--color-from", "--colour-from", help="Render with the colour code of this instance (name or index).")] = None,
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
    from ..render_files import render_to_folder
    from ..video import gif_frame_rate
    from ..runtime import resolve_device
    from ..views import parse_resolution

    res = parse_resolution(res)
    ranks = ranks_from_env()
    dev = resolve_device(device) if ranks is None else rank_device(device, ranks)
    ranks = ranks or SINGLE
    m, _ = load_model(model, dev)
    deltas = []
    if edit:  # before the instance lookup: an edit may add the instance (fit-real)
        from ..delta import apply_deltas, read_delta

        deltas = [read_delta(p) for p in edit]
        m = apply_deltas(m, deltas)
    k = m.instance_index(instance)
    # an instance's own code is what it renders with already: nothing to swap in
    picked = (None if j is None else instance_option(m, j, option) for j, option in ((shape_from, "--shape-from"), (color_from, "--color-from")))
    shape_from, color_from = (None if j == k else j for j in picked)
    if shape_from is not None or color_from is not None:
        from ..edit.transfer import swap_codes, weights_not_carried

        for note in weights_not_carried(m, k, shape_from, color_from):
            typer.echo(printable(f"note: {note}"), err=True)
        m = swap_codes(m, k, shape_from=shape_from, color_from=color_from)
    with process_group(ranks, dev):
        source = {"model": str(model), "edits": [str(p) for p in edit or []], "res": res,  # what these views are of
                  "shape_from": None if shape_from is None else m.names[shape_from],
                  "color_from": None if color_from is None else m.names[color_from]}
        result = render_to_folder(m, k, views, out, res, depth, video, chunk, fps, ranks, source)
    if not ranks.main:
        return
    trained = m.views.get("train")
    widest = None if trained is None else max(trained.widths)
    drawn = max(w for w, _ in (result.sizes or ((result.width, result.height),)))
    if widest is not None and drawn > widest:  # --res, or a camera file's size
        typer.echo(f"note: views {drawn} pixels wide are wider than the {widest}-pixel views the model was trained on: "
                   "the rays are denser, but the field holds no finer detail than it learned", err=True)
    if result.blank:  # a camera looking away, inside the object, or so wide the object is a speck
        shown = ", ".join(result.blank[:3]) + (f" and {len(result.blank) - 3} more" if len(result.blank) > 3 else "")
        grid = m.field_for(k).occupancy
        why = ("its edits leave no occupied cell (it was removed whole)" if m.cfg.sampler == "grid" and not bool(grid[k].any()) else
               "a camera looking away from it, inside it, too far from it, or with so wide a field of view that it covers no pixel")
        typer.echo(f"note: {len(result.blank)} of the {result.count} views show nothing of {m.names[k]} ({shown}): {why}", err=True)
    per_view = result.seconds / max(result.count, 1)
    typer.echo(
        f"rendered {result.count} view{'s' if result.count != 1 else ''} of {m.names[k]} at {result.size_text} "
        f"in {result.seconds:.2f} s ({per_view:.3f} s per view) -> {out}"
    )
    if result.video is not None:
        kind = "MP4" if result.video.suffix.lower() == ".mp4" else "GIF"
        note = ""
        if video is not None and result.video != video:
            note = " (imageio-ffmpeg is not installed, so a GIF instead of MP4: pip install -e '.[video]')"
        if kind == "GIF" and abs(gif_frame_rate(fps) - fps) > 1e-6 * fps:
            note += f" at {gif_frame_rate(fps):g} fps (a GIF's frame time is whole hundredths of a second; --fps {fps:g} asked)"
        typer.echo(f"wrote {kind} {result.video}{note}")
    # the instances this render reads: its own, and those whose codes (and grid) --shape-from/--color-from take
    read = {m.names[k], *(m.names[m.instance_index(i)] for i in (shape_from, color_from) if i is not None)}
    others = [(p, d.instance) for p, d in zip(edit or [], deltas) if d.instance not in read]
    if deltas and len(others) == len(deltas):  # a stack of other instances' edits alone: likely a slip
        for p, whose in others:
            typer.echo(printable(f"note: {p.name} edits {whose}, not {' or '.join(sorted(read))}: it leaves this render unchanged"), err=True)
