"""``crfedit select``: scribbles → a 3-D selection file, with a tinted preview."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import CrfError
from ..masks import mask_digest
from ..names import SELECTION_FORMAT
from .common import DeviceChoice, DeviceOpt, JsonOpt, app, check_out_file, command_line, json_record, size_text, table_row, user_errors
from .edit import PREVIEW_VIEWS, JoinOpt, MirrorOpt, ModelArg, PreviewViewsOpt, PriorOpt, _load, _one_view, _preview_views, _view_render, is_none, previews_of


def echo_summaries(info: dict, skip: tuple[str, ...] = ()) -> None:
    """Print a fresh selection's summary lines (``label: line``), the ones that apply and are
    not labelled in ``skip``.  A scribble over the whole instance (``whole``) selects every
    occupied cell whatever the rules found: their lines (a shape gate's rim cells) would say
    what did not happen, so only the coverage and strokes lines are printed."""
    from ..edit.selection import SUMMARIES

    whole = info.get("whole") is not None
    for label, summary in SUMMARIES:
        line = None if label in skip or (whole and label not in ("coverage", "strokes")) else summary(info)
        if line is not None:
            typer.echo(f"{label}: {line}")


def _off_object_warning(field, k: int, spec: str, v, render) -> None:
    """Warn when a view's scribble or keep strokes lie on the background only: they lift no
    point, and the view adds nothing (strokes drawn for another view, say).  ``render``: the
    view's opacity render, which the selection reads too."""
    from ..edit.selection.pipeline import view_on_object

    on = view_on_object(field, k, v, render=render)
    for what, mask, adds in (("scribble lies", v.scribble, "it adds no scribbled point"), ("keep strokes lie", v.keep, "they add no keep point")):
        if mask is not None and mask.any() and not (mask & on).any():
            typer.echo(f"warning: --view {spec}: its {what} on the background only (no pixel shows the object there): {adds} "
                       "(the view still adds its other surface points as candidates); drawn for another view?", err=True)


def _mask(path: Path, model, instance: int, camera, what: str):
    """A mask image (read as drawn: one line says how), or strokes JSON when the name ends in
    .json (:func:`~crfedit.edit.scribble.load_mask`), at the view's size."""
    from ..edit.scribble import load_mask

    read = load_mask(path, None, camera.width, camera.height, what, _view_render(model, instance, camera))
    typer.echo(f"{what} {path}: {read.reading}, {int(read.mask.sum())} pixels")
    return read.mask


@app.command("select")
@user_errors
@json_record
def select_cmd(
    model: ModelArg,
    instance: Annotated[str, typer.Option("--instance", help="Instance whose part is selected: a name or an index.")],
    view: Annotated[list[str], typer.Option("--view", help="A view the scribbles belong to (repeatable: one --scribble per --view).")],
    scribble: Annotated[list[Path], typer.Option("--scribble", help="The part, on that view (repeatable): white on black, strokes on a transparent PNG, strokes painted over the view's render, or a strokes JSON; the word none for a further view that only holds keep strokes.")],
    out: Annotated[Path, typer.Option("--out", help="Selection file to write (.safetensors).")],
    keep: Annotated[Optional[list[Path]], typer.Option("--keep", help="What is not the part, per view: leave --keep out, or give one per --view in order (the word none for a view without keep strokes).")] = None,
    edit: PriorOpt = None,
    preview: Annotated[Optional[Path], typer.Option("--preview", help="Folder for PNG previews with the selection tinted.")] = None,
    views: PreviewViewsOpt = None,
    kind: Annotated[str, typer.Option("--for", help="The edit the selection is for: color (also takes the cells of the scribble's chromaticity), remove or add.")] = "color",
    mirror: MirrorOpt = None,
    join: JoinOpt = None,
    as_json: JsonOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Lift scribbles on one or more views to a 3-D selection of the instance's part (no weight changes)."""
    import numpy as np

    from ..edit.scribble import few_pixels_note, keep_outside, keep_overlap
    from ..edit.selection import ScribbleView, options_for, preview as tinted, save_selection, select
    from ..edit.selection.base import merge_views
    from ..edit.shape import same_camera
    from ..edit.selection.options import EDIT_KINDS
    from ..io import write_png
    from ..renderer import render_camera

    counted = lambda n, word: f"{n} {word}{'' if n == 1 else 's'}"
    if len(scribble) != len(view):
        raise CrfError(f"give one --scribble per --view ({counted(len(view), 'view')}, {counted(len(scribble), 'scribble')})")
    if keep and len(keep) != len(view):
        raise CrfError(f"give one --keep per --view, in order (none for a view without keep strokes), or no --keep "
                       f"({counted(len(view), 'view')}, {counted(len(keep), 'keep mask')})")
    if all(is_none(p) for p in scribble):
        raise CrfError("no view holds a scribble: keep strokes alone select nothing (scribble the part on at least one view)")
    kind = "color" if kind == "colour" else kind
    if kind not in EDIT_KINDS:  # named by its option here (options_for's line names no flag)
        raise CrfError(f"--for {kind}: expected one of {', '.join(EDIT_KINDS)}")
    options = options_for(kind, None if mirror is None else mirror.value, None if join is None else join.value)
    check_out_file(out, {"MODEL": model, "--edit": edit, "--scribble": scribble, "--keep": keep}, "selection", "sel.safetensors", SELECTION_FORMAT)
    m = _load(model, edit, device)
    k = m.instance_index(instance)
    shown = _preview_views(m, k, preview, views)
    scribbles, specs, renders = [], [], []
    field = m.field_for(k)
    for i, spec in enumerate(view):
        _, camera = _one_view(m, spec, k)
        bg = _mask(keep[i], m, k, camera, "keep") if keep and not is_none(keep[i]) else None
        if is_none(scribble[i]):  # a view that only holds back what it shows
            if bg is None:
                raise CrfError(f"--view {spec} --scribble none: a view without a scribble needs its --keep strokes")
            fg = np.zeros_like(bg)
        else:
            fg = _mask(scribble[i], m, k, camera, "scribble")
            if few := few_pixels_note(fg):
                typer.echo(f"note: {spec}: {few}", err=True)
        if bg is not None:  # refused as the edit commands refuse it (select took an empty keep PNG as none)
            try:
                keep_outside(fg, bg)
            except CrfError as e:
                raise CrfError(f"--view {spec}: {e}") from None
        overlap = keep_overlap(fg, bg)
        if overlap:
            typer.echo(f"warning: {spec}: {overlap}", err=True)
        given = ScribbleView(camera, fg, bg)
        render = render_camera(field, camera, k, colour=False)  # once: the warning's and the selection's
        if len(view) > 1:  # one view alone on the background is refused by select itself
            _off_object_warning(field, k, spec, given, render)
        same = next((j for j, v in enumerate(scribbles) if same_camera(v.camera, camera)), None)
        if same is None:
            scribbles.append(given)
            specs.append(spec)
            renders.append(render)
        else:  # the strokes of one view given twice join, as one view
            scribbles[same] = merge_views(scribbles[same], given)
            if scribbles[same].keep is not None:  # refused as one view's would be
                try:
                    keep_outside(scribbles[same].scribble, scribbles[same].keep)
                except CrfError as e:
                    raise CrfError(f"--view {spec} (with --view {specs[same]}, one view): {e}") from None
            again = "given again" if spec == specs[same] else f"is the camera of --view {specs[same]}"
            typer.echo(f"note: --view {spec} {again}: its strokes join that view's, as one view", err=True)
    sel = select(m, k, scribbles, options, renders=renders)
    sel.meta["for"] = kind
    sel.meta["made_from"] = [{"view": spec, "scribble": mask_digest(v.scribble) if v.scribble.any() else None, "keep": mask_digest(v.keep)}
                             for spec, v in zip(specs, scribbles)]
    sel.meta["command"] = command_line()
    if join is not None:
        sel.meta["colour_join"] = join.value  # the mode asked for, which join_summary names
    save_selection(out, sel)
    info = sel.meta
    typer.echo(
        f"wrote {out} ({size_text(out.stat().st_size)}): {info['selected_cells']} of {info['occupied_cells']} occupied cells of {m.names[k]} selected "
        f"({info['positives']} scribbled, {info['keep_points']} keep, {info['view_points']} other surface points; {info['seconds']:.2f} s)"
    )
    echo_summaries(info)
    if preview is not None:
        with previews_of(out, preview):
            preview.mkdir(parents=True, exist_ok=True)
            for i, (label, camera) in enumerate(shown):
                write_png(preview / f"{i:04d}.png", tinted(m, sel, camera))
        typer.echo(f"wrote previews of {views or PREVIEW_VIEWS} to {preview}/")


def print_selection(path: Path, as_json: bool, version: str) -> None:
    """`info` on a selection file of format ``version`` (from the header `info` read): its
    instance, model, cells and how it was made (table or JSON)."""
    import json

    from ..edit.selection import FORMAT, SUMMARIES, load_selection

    sel = load_selection(path)
    info = sel.meta if isinstance(sel.meta, dict) else {}
    res = sel.values.shape[0]
    selected, nonzero = int(sel.mask.sum()), int((sel.values > 0).sum())
    if as_json:
        typer.echo(json.dumps({
            "file": str(path), "bytes": path.stat().st_size, "format": FORMAT, "version": version, "instance": sel.instance_name,
            "instance_index": sel.instance, "model_fingerprint": sel.model_fingerprint, "grid": res,
            "threshold": sel.threshold, "selected_cells": selected, "nonzero_cells": nonzero, "info": info,
        }, indent=2))
        return
    counts = [f"{info[key]} {what}" for key, what in (("views", "view(s)"), ("positives", "scribbled points"), ("keep_points", "keep points"))
              if type(info.get(key)) is int]
    features = info.get("features")
    rows = [
        ("selection", f"{path} ({path.stat().st_size} bytes, format version {version})"),
        ("instance", f"{sel.instance_name} (index {sel.instance})"),
        ("model", sel.model_fingerprint or "(none)"),
        ("for", info.get("for", "unknown")),
        ("cells", (f"{selected} of the instance's {info['occupied_cells']} occupied cells" if type(info.get("occupied_cells")) is int
                   else f"{selected} of {res}^3 cells") + f" selected (value >= {sel.threshold:g}; a {res}^3 grid), {nonzero} with a value above 0"),
        ("made from", ", ".join(counts) or "unknown"),
    ]
    made = info.get("made_from")
    if isinstance(made, list) and all(isinstance(v, dict) for v in made):  # selections since the sixty-seventh session
        rows.append(("views", "; ".join(f"{v.get('view')} (scribble {v.get('scribble') or 'none'}, keep {v.get('keep') or 'none'})" for v in made)))
    if isinstance(info.get("command"), str):
        rows.append(("command", info["command"]))
    if isinstance(features, list):
        rows.append(("features", ", ".join(map(str, features))))
    for label, summary in SUMMARIES:
        try:
            line = summary(info)
        except (KeyError, TypeError, ValueError, IndexError):  # a hand-edited record: say nothing rather than guess
            line = None
        if line is not None:
            rows.append((label, line))
    for key, value in rows:
        typer.echo(table_row(key, value))
