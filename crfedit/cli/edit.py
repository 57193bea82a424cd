"""``crfedit edit-color | remove | add | transfer`` and ``crfedit edits show | check | bake``.

Each edit command loads the model, applies the ``--edit`` files it builds on, edits one
instance as seen from one ``--view`` and writes the edit file ``--out`` (docs/edit-format.md).
"""

from __future__ import annotations

import contextlib
import enum
import json
from pathlib import Path
from typing import Annotated, Iterator, NamedTuple, Optional

import typer

from ..errors import CrfError
from ..names import ADD_METHODS, EDIT_METHODS, JOIN_MODES, MIRROR_MODES, MODEL_FORMAT, NO_MASK, PENALTIES, RECOLOR_RULES, STRATEGIES
from .common import printable, table_row, DeviceChoice, DeviceOpt, JsonOpt, SeedOpt, app, check_out_file, command_line, edits_app, instance_option, json_record, size_text, user_errors


Strategy = enum.Enum("Strategy", {s: s for s in STRATEGIES}, type=str)
AddMethod = enum.Enum("AddMethod", {m: m for m in ADD_METHODS}, type=str)
EditMethod = enum.Enum("EditMethod", {m: m for m in EDIT_METHODS}, type=str)
Penalty = enum.Enum("Penalty", {m: m for m in PENALTIES}, type=str)
Recolor = enum.Enum("Recolor", {m: m for m in RECOLOR_RULES}, type=str)
MirrorMode = enum.Enum("MirrorMode", {m: m for m in MIRROR_MODES}, type=str)
JoinMode = enum.Enum("JoinMode", {m: m for m in JOIN_MODES}, type=str)


ModelArg = Annotated[Path, typer.Argument(help="Model file (.safetensors).")]
InstanceOpt = Annotated[str, typer.Option("--instance", help="Instance to edit: a name or an index.")]
ViewOpt = Annotated[str, typer.Option("--view", help="The one view the scribbles belong to: train:5, test:0, orbit:36@30:5 (the sixth of 36 orbit views, frame 0005 of render --views orbit:36@30), or a camera JSON.")]
OutOpt = Annotated[Path, typer.Option("--out", help="Edit file to write (.safetensors); written atomically.")]
PriorOpt = Annotated[Optional[list[Path]], typer.Option("--edit", help="An earlier edit to apply first (repeatable, in the order they were made).")]
StrategyOpt = Annotated[Strategy, typer.Option("--strategy", help="What to train: hybrid (the paper's), codes (the instance's code only) or all (every weight).")]
PenaltyOpt = Annotated[Penalty, typer.Option("--penalty", help="Weight penalty: element (every trained number weighed alike, so strategies are penalised alike; default) or tensor (Σ per-tensor means, the earlier rule).")]
StepsOpt = Annotated[int, typer.Option("--steps", help="Optimization steps.")]
LrOpt = Annotated[float, typer.Option("--lr", help="Adam learning rate.")]
RaysOpt = Annotated[int, typer.Option("--rays", help="Most rays rendered per step (the supervising views' rays: scribbled, kept, turned views).")]
ScribbleOpt = Annotated[Optional[Path], typer.Option("--scribble", metavar="PNG", help="The part to edit, at the view's size: white on black, strokes on a transparent PNG, strokes painted over the view's render, or a strokes JSON (.json).")]
ScribbleJsonOpt = Annotated[Optional[Path], typer.Option("--scribble-json", help='Strokes JSON: {"strokes": [[[x, y], ...], ...], "radius": r} or a list of strokes.')]
KeepOpt = Annotated[Optional[Path], typer.Option("--keep", help="Mask PNG (or strokes .json) of what must not change (default: a random sample of the rest of the view).")]
KeepShapeOpt = Annotated[Optional[Path], typer.Option("--keep", help="Mask PNG (or strokes .json) of what must not change (a random sample of the rest of the view is kept as well).")]
MethodOpt = Annotated[EditMethod, typer.Option("--method", help="selection: lift the scribbles to a 3-D selection and supervise the edit with it in every view; paper: the paper's losses on the scribbled view's rays alone.")]
SelectionOpt = Annotated[Optional[Path], typer.Option("--selection", help="A selection file from `crfedit select` to edit (default: computed from the scribbles); remove takes it without a scribble, edit-color still reads the part's colour under its scribble.")]
JoinOpt = Annotated[Optional[JoinMode], typer.Option("--colour-join", "--color-join", help="Whether the selection computed from the scribbles also takes the cells of the scribbled colour: auto (unless that would be over 4.5× the cells the features chose, 3.5× for a recolour's pale part; additions never), always (a part that is most of the instance) or never.")]
MirrorOpt = Annotated[Optional[MirrorMode], typer.Option("--mirror", help="Mirror symmetry of the selection computed from the scribbles: views (the scribbled view's mirror image lends its strokes; removals' default), values (the selection takes its own mirror image; recolours' default) or off (one side only). Nothing is mirrored where the keep strokes cover the scribble's mirror image.")]
KeepJsonOpt = Annotated[Optional[Path], typer.Option("--keep-json", help="Strokes JSON of what must not change.")]
PreviewOpt = Annotated[Optional[Path], typer.Option("--preview", help="Folder for PNG renders of the edited instance from --views.")]
PREVIEW_VIEWS = "orbit:8"
"""The views of ``--preview`` when ``--views`` is not given."""
PreviewViewsOpt = Annotated[Optional[str], typer.Option("--views", help=f"Views of --preview (default {PREVIEW_VIEWS}), e.g. test.")]
ForceOpt = Annotated[bool, typer.Option("--force", help="Accept a scribble that covers more than half the view (and, for remove, a selection of nearly all the object).")]


def _scribbled_inputs(model: Path, edits, scribble, scribble_json, keep, keep_json, selection) -> dict[str, object]:
    """The files an edit command reads, for :func:`~.common.check_out_file`."""
    return {"MODEL": model, "--edit": edits, "--scribble": scribble, "--scribble-json": scribble_json, "--keep": keep,
            "--keep-json": keep_json, "--selection": selection}


def _load(model: Path, edits: list[Path] | None, device: DeviceChoice):
    from ..delta import apply_edit_files
    from ..model import load_model
    from ..runtime import resolve_device

    base, _ = load_model(model, resolve_device(device))
    return apply_edit_files(base, list(edits or []))


def _one_view(model, spec: str, instance: int, option: str = "--view"):
    from ..views import one_view_hint, one_view_label, resolve_views

    try:
        views = resolve_views(spec, model, instance)
    except CrfError as e:  # which option's spec it was: add reads --view and --donor-view
        raise CrfError(f"{option}: {e}") from None
    if len(views) != 1:
        raise CrfError(f"{option} {spec}: names {len(views)} views; an edit is drawn on exactly one ({one_view_hint(spec)})")
    label, camera = views[0]
    return one_view_label(spec, label), camera


def _require_scribble(scribble: Path | None, scribble_json: Path | None, what: str) -> None:
    if scribble is None and scribble_json is None:
        raise CrfError(f"give the {what} as --scribble MASK.png or --scribble-json STROKES.json")


def _view_render(model, instance: int, camera):
    """A callable rendering the view [H, W, 3]: what a scribble painted over the render is
    compared against (called only for that reading) and what a preview writes."""

    def render():
        from ..renderer import render_camera

        return render_camera(model.field_for(instance), camera, instance).rgb.cpu().numpy()

    return render


def is_none(path) -> bool:
    """Whether a mask option names ``none`` (a view without such strokes), not a file: the word,
    unless a file is called that."""
    return path is not None and str(path).lower() == NO_MASK and not Path(path).exists()


def _refuse_none(option: str, path, needs: str) -> None:
    """``none`` names `select`'s views without such strokes; given to an edit's mask (and no file
    is called that) it is one line saying so, not 'none: file not found'."""
    if is_none(path):
        raise CrfError(f"{option} none: `none` is for `crfedit select`'s views without such strokes; {needs}")


def _masks(scribble, scribble_json, keep, keep_json, model, instance: int, camera, force: bool):
    """(scribble mask, keep mask or None), each image read as drawn (one line says how)."""
    from ..edit.scribble import check_coverage, check_masks, few_pixels_note, keep_overlap, load_mask

    _refuse_none("--scribble", scribble, "an edit's one view needs its scribble")
    _refuse_none("--keep", keep, "an edit's one view takes no --keep when it has no keep strokes")
    render = _view_render(model, instance, camera)
    fg = load_mask(scribble, scribble_json, camera.width, camera.height, "scribble", render)
    fraction = check_coverage(fg.mask, force)
    typer.echo(f"scribble: {fg.reading}, {int(fg.mask.sum())} pixels ({100 * fraction:.1f} % of the view)")
    if few := few_pixels_note(fg.mask):
        typer.echo(f"note: {few}", err=True)
    bg = load_mask(keep, keep_json, camera.width, camera.height, "keep", render)
    if bg is not None:
        typer.echo(f"keep: {bg.reading}, {int(bg.mask.sum())} pixels")
        check_masks(fg.mask, bg.mask, camera.width, camera.height)  # a keep mask that is wrong is an error before any warning
        overlap = keep_overlap(fg.mask, bg.mask)
        if overlap:
            typer.echo(f"warning: {overlap}", err=True)
    return fg.mask, None if bg is None else bg.mask


def _mode(value, method, option: str) -> str | None:
    """A selection mode's value (``--mirror``, ``--colour-join``; None: the edit's default),
    refused with ``--method paper``."""
    if value is not None and method != EditMethod.selection:
        raise CrfError(f"{option} belongs to --method selection (the paper's losses select nothing)")
    return None if value is None else value.value


def _selection(path: Path | None, model, instance: int, kind: str, mirror: str | None = None, join: str | None = None):
    """The selection file at ``path`` checked against the model and instance (None: none
    given); a warning when it was made ``--for`` a kind of edit that selects differently."""
    from ..edit.selection import EDIT_KINDS, load_selection, options_for

    if path is None:
        return None
    for option, value in (("--mirror", mirror), ("--colour-join", join)):
        if value is not None:
            raise CrfError(f"{option} sets how the selection is computed from the scribbles; with --selection give it to `crfedit select`")

    sel = load_selection(path)
    sel.check_for(model, instance)
    made = sel.meta.get("for")
    if made in EDIT_KINDS and options_for(made) != options_for(kind):
        typer.echo(f"warning: {path} was made with crfedit select --for {made}; this {kind} edit's own selection would be --for {kind}", err=True)
    return sel


def _preview_views(model, instance: int, folder: Path | None, spec: str):
    """The preview's (label, camera) list, resolved before any work so that a bad ``--preview``
    or ``--views`` stops the command before it writes anything (None: no preview).  ``--views``
    without ``--preview`` is refused: it was ignored, so an edit asked for previews wrote none."""
    if folder is None:
        if spec is not None:
            raise CrfError(f"--views {spec}: sets the views of --preview; give --preview DIR too")
        return None
    if folder.exists() and not folder.is_dir():
        raise CrfError(f"--preview {folder}: is a file; give a folder for the preview PNGs")
    from ..io import check_folder_target
    from ..views import resolve_views

    check_folder_target(folder, "--preview")

    return resolve_views(spec or PREVIEW_VIEWS, model, instance)


@contextlib.contextmanager
def previews_of(out: Path, folder: Path) -> Iterator[None]:
    """Ctrl-C while the previews of ``out`` (written already) go to ``folder`` says so: the line
    names the file written and the previews left incomplete (exit 130)."""
    try:
        yield
    except KeyboardInterrupt as e:  # SIGTERM stays a Terminated: exit 143, not Ctrl-C's 130
        raise type(e)(f"{out} was written; the previews in {folder}/ are incomplete") from None
    except OSError as e:  # a disk that filled, a folder made read-only since the check
        from .common import os_error_message

        raise CrfError(f"{os_error_message(e)}: {out} was written, its previews in {folder}/ were not") from None


def _preview(model, instance: int, folder: Path | None, views, spec: str, out: Path) -> None:
    """Render the edited instance from ``views`` (:func:`_preview_views`) into ``folder``,
    after its edit file ``out`` was written."""
    if folder is None:
        return
    from ..io import write_png

    with previews_of(out, folder):
        folder.mkdir(parents=True, exist_ok=True)
        for i, (_, camera) in enumerate(views):
            write_png(folder / f"{i:04d}.png", _view_render(model, instance, camera)())
    typer.echo(f"wrote previews of the edited {model.names[instance]} ({spec or PREVIEW_VIEWS}) to {folder}/")


class _Scribbled(NamedTuple):
    """What `edit-color` and `remove` prepare before they edit (:func:`_scribbled`)."""

    model: object
    instance: int
    shown: list | None  # the preview's views (:func:`_preview_views`)
    label: str
    camera: object
    scribble: object  # [H, W] bool
    keep: object  # [H, W] bool or None
    mirror: str | None
    selection: object  # a checked Selection, or None
    join: str | None = None  # the --colour-join mode asked for

    def inputs(self) -> dict:
        """What the edit was made from, for its file (``inputs``): digests of the scribble, the
        keep strokes and the selection (:func:`~crfedit.masks.mask_digest`), and the modes asked for."""
        import hashlib

        from ..masks import mask_digest

        sel = None if self.selection is None else hashlib.sha256(self.selection.values.cpu().numpy().tobytes()).hexdigest()[:16]
        return {"scribble": mask_digest(self.scribble), "keep": mask_digest(self.keep), "selection": sel,
                "mirror": self.mirror, "colour_join": self.join}


def _scribbled(model: Path, edits, device: DeviceChoice, instance: str, view: str, masks: tuple, force: bool, method,
               mirror, selection: Path | None, kind: str, preview: Path | None, views: str, join=None) -> _Scribbled:
    """Load the model with its ``--edit`` files and read, in this order (so that the first bad
    option is the one named): the instance, the preview's views, the scribbled view, its masks
    (``masks``: scribble, scribble JSON, keep, keep JSON), the mirror and colour-join modes and
    the ``--selection`` file made for a ``kind`` edit; then, without one, make the selection
    (:func:`_lifted`)."""
    m = _load(model, edits, device)
    k = m.instance_index(instance)
    shown = _preview_views(m, k, preview, views)
    label, camera = _one_view(m, view, k)
    given = masks[0] is not None or masks[1] is not None
    if not given and (masks[2] is not None or masks[3] is not None):
        raise CrfError("--keep goes with a scribble; a --selection file alone already says what goes")
    fg, bg = _masks(*masks, m, k, camera, force) if given else (None, None)  # remove --selection alone
    mode, join_mode = _mode(mirror, method, "--mirror"), _mode(join, method, "--colour-join")
    sel = _selection(selection, m, k, kind, mode, join_mode)
    if kind == "remove" and method != EditMethod.selection and not force and fg is not None:
        _refuse_whole_paper_removal(m, k, camera, fg, bg, label)
    if sel is not None and kind == "remove" and not force:  # a saved selection of (nearly) the whole instance, as one lifted here
        from ..edit.selection.base import nearly_all

        occupied = m.field_for(k).occupancy[k]
        taken, total = int((sel.mask.to(occupied.device) & occupied).sum()), int(occupied.sum())
        if nearly_all(taken, total):
            raise CrfError(f"--selection {selection}: takes {taken} of the instance's {total} occupied cells, nearly all of it: "
                           "pass --force to remove that much")
    if sel is None and method == EditMethod.selection:
        sel = _lifted(m, k, camera, fg, bg, kind, mode, join_mode)
        from ..edit.selection import coverage_summary

        if kind == "remove" and not force and sel.meta.get("whole") is not None:  # asked for, not a slip of view
            raise _whole_removal(sel.meta["whole"], label)
        if kind == "remove" and not force and coverage_summary(sel.meta) is not None:
            raise CrfError(f"the removal's selection takes {sel.meta['selected_cells']} of the instance's {sel.meta['occupied_cells']} "
                           f"occupied cells, nearly all of it: check that the scribble was drawn on view {label} of this instance "
                           "(crfedit select --preview shows it), or pass --force to remove that much")
    return _Scribbled(m, k, shown, label, camera, fg, bg, mode, sel, join_mode)


def _refuse_whole_paper_removal(m, k: int, camera, fg, bg, label: str) -> None:
    """``remove --method paper`` of a scribble over the whole instance (the selection's own
    rule, :func:`~crfedit.edit.selection.pipeline.whole_share`) asks for --force, as the default
    method does: it emptied the chair without a word where the default refused."""
    from ..edit.selection import ScribbleView
    from ..edit.selection.pipeline import view_on_object, whole_share

    view = ScribbleView(camera, fg, bg)
    share = whole_share([view], [view_on_object(m.field_for(k), k, view)])
    if share is not None:
        raise _whole_removal(share, label)


def _whole_removal(share: float, label: str) -> CrfError:
    """The one line refusing a removal scribbled over the whole instance without --force."""
    return CrfError(f"the scribble covers {share:.0%} of what view {label} shows of the instance and no keep stroke holds "
                    "anything back, so the removal would take all of it: pass --force to remove the whole instance, or keep "
                    "strokes on what must stay")


def _lifted(m, k: int, camera, fg, bg, kind: str, mirror: str | None, join: str | None = None):
    """The selection a ``kind`` edit makes from its scribbles (what the edit would compute
    itself), made here so that the command says what it took, in `crfedit select`'s lines."""
    from ..edit.scribble import check_masks
    from ..edit.selection import select_for

    fg, keep = check_masks(fg, bg, camera.width, camera.height)
    sel = select_for(m, k, camera, fg, keep, kind, mirror, join=join)
    _echo_selection(sel)
    return sel


def _echo_selection(sel, whose: str = "", takes_keep: bool = True) -> None:
    """`crfedit select`'s lines for a selection an edit made (``whose``: e.g. "donor ";
    ``takes_keep`` False where the command takes no keep strokes for it, so that no line asks
    for them)."""
    from .select import echo_summaries

    info = sel.meta
    typer.echo(f"{whose}selection: {info['selected_cells']} of {info['occupied_cells']} occupied cells ({info['seconds']:.2f} s)")
    echo_summaries(info, () if takes_keep else ("keep strokes",))


SHOW_AFTER = 1.0
"""Seconds an edit runs before :func:`edit_progress` draws its bar: the default edits take a
fraction of a second, but ``--rays 4194304`` ran for minutes without a word."""


@contextlib.contextmanager
def edit_progress(options, what: str) -> Iterator:
    """``options`` with an ``on_step`` that draws a progress bar on stderr (a terminal's only,
    :func:`~crfedit.cli.common.stderr_progress`) once the edit has run :data:`SHOW_AFTER`
    seconds: its step of ``options.steps``, steps per second and the time left.  A recolour
    fitted a second time starts the count again, as "refit"."""
    import dataclasses
    import time

    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

    from .common import stderr_progress
    from .dataset import _rate_column

    started, state = time.perf_counter(), {"bar": None, "task": None, "last": 0}

    def on_step(step: int, _loss: float) -> None:
        bar = state["bar"]
        if bar is None:
            if time.perf_counter() - started < SHOW_AFTER:
                state["last"] = step
                return
            bar = stderr_progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), _rate_column(),
                                  TimeRemainingColumn())
            bar.start()
            state["bar"], state["task"] = bar, bar.add_task(what, total=options.steps, completed=step)
        if step < state["last"]:  # the fit began again
            bar.reset(state["task"], total=options.steps, description=f"{what} (refit)")
        state["last"] = step
        bar.update(state["task"], completed=step)

    try:
        yield dataclasses.replace(options, on_step=on_step)
    finally:
        if state["bar"] is not None:
            state["bar"].stop()


def _options(strategy: Strategy, steps: int, lr: float, rays: int, seed: int, penalty: Penalty, recolor: Recolor = Recolor.shading):
    from ..edit import EditOptions

    return EditOptions(strategy=strategy.value, steps=steps, lr=lr, rays=rays, seed=seed, penalty=penalty.value, recolor=recolor.value).validated()


def _write(result, out: Path, label: str, inputs: dict | None = None) -> None:
    extra = {"command": command_line(), **({"view": label} if label else {}), **({"inputs": json.dumps(inputs)} if inputs else {})}
    result.save(out, **extra)
    meta = result.meta
    size, n = out.stat().st_size, len(result.tensors)
    typer.echo(
        f"wrote {out}: {meta['kind']} edit of {meta['instance']}, {n} tensor{'s' * (n != 1)}, "
        f"{size_text(size)}, final loss {result.final_loss:.4g}, {result.seconds:.2f} s"
    )
    note = little_moved_note(meta)
    if note:
        typer.echo(f"note: {note}", err=True)


LITTLE_MOVED = 0.98
""":func:`little_moved_note` speaks when an edit's final loss is at least this share of its first:
``--lr 1e-6`` wrote a recolour to red that moved the seat by 1/255 (0.4538 against 0.455)."""


def little_moved_note(meta: dict) -> str | None:
    """A line when an edit's loss barely fell (:data:`LITTLE_MOVED`), else None: the first step's
    loss against the mean of the last tenth of the steps' without the weight penalty
    (``fit_loss``; ``final_loss`` adds the penalty, the larger part of an addition's).  Edits of
    fewer than 10 steps record neither (one step's random batch can cost more than the first's)."""
    try:
        first, final = float(meta["first_loss"]), float(meta["fit_loss"])
    except (KeyError, TypeError, ValueError):
        return None
    if not (first > 0 and final >= LITTLE_MOVED * first):
        return None
    moved = f"fell only from {first:.4g} to {final:.4g}" if final < first else f"rose from {first:.4g} to {final:.4g}"
    try:
        hyper = json.loads(meta.get("hyperparameters") or "{}")
    except json.JSONDecodeError:
        hyper = {}
    from ..edit import EditOptions

    defaults = EditOptions()
    if isinstance(hyper, dict) and (hyper.get("lr"), hyper.get("steps")) == (defaults.lr, defaults.steps):
        why = "the view may show little of what the scribble marks"
    else:
        why = f"a learning rate too small or too few steps? the defaults are --lr {defaults.lr:g}, --steps {defaults.steps}"
    return f"the loss {moved}: the edit changed little ({why}); render it to check"


@app.command("edit-color")
@user_errors
@json_record
def edit_color_cmd(
    model: ModelArg,
    instance: InstanceOpt,
    view: ViewOpt,
    out: OutOpt,
    color: Annotated[str, typer.Option("--color", "--colour", help="Target colour: #rgb, #rrggbb, rgb(R, G, B) or a CSS colour name such as red, navy, darkred; with --method selection, the colour the part should appear under the scribble.")],
    scribble: ScribbleOpt = None,
    scribble_json: ScribbleJsonOpt = None,
    keep: KeepOpt = None,
    keep_json: KeepJsonOpt = None,
    method: MethodOpt = EditMethod.selection,
    selection: SelectionOpt = None,
    mirror: MirrorOpt = None,
    join: JoinOpt = None,
    force: ForceOpt = False,
    preview: PreviewOpt = None,
    views: PreviewViewsOpt = None,
    edit: PriorOpt = None,
    strategy: StrategyOpt = Strategy.hybrid,
    penalty: PenaltyOpt = Penalty.element,
    recolor: Annotated[Recolor, typer.Option("--recolor", "--recolour", help="--method selection: the part's new colour × each point's shading along the scribbled pixels' mean colour (shading; default), or each point's colour × new/old per channel (ratio, which also scales the model's colour noise).")] = Recolor.shading,
    steps: StepsOpt = 100,
    lr: LrOpt = 1e-2,
    rays: RaysOpt = 1024,
    as_json: JsonOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
    seed: SeedOpt = 0,
) -> None:
    """Recolour the scribbled part of one instance (trains F_rad and its colour code)."""
    from ..edit import edit_color
    from ..edit.scribble import parse_color

    rgb = parse_color(color, "--color")
    _require_scribble(scribble, scribble_json, "part to recolour")
    options = _options(strategy, steps, lr, rays, seed, penalty, recolor)
    check_out_file(out, _scribbled_inputs(model, edit, scribble, scribble_json, keep, keep_json, selection))
    p = _scribbled(model, edit, device, instance, view, (scribble, scribble_json, keep, keep_json), force, method, mirror, selection, "color", preview, views,
                   join)
    with edit_progress(options, "colour edit") as shown_options:
        result = edit_color(p.model, p.instance, p.camera, p.scribble, rgb, p.keep, shown_options, method.value, p.selection, p.mirror)
    hyper = json.loads(result.meta.get("hyperparameters", "{}"))
    widened = hyper.get("widened")
    if widened:  # the held points that F_rad alone could not tell from the part
        how = "kept that fit" if widened["kept"] else "kept the first fit"
        typer.echo(f"colour hold: with F_rad alone {100 * hyper['bleed']:.1f} % of the 3-D points held outside the selection "
                   "(opacity-weighted, hidden faces too, so more than a view shows) changed colour by over 0.1 "
                   f"(they look like the part to it); fitted again training the bottleneck layer too: {100 * widened['bleed']:.1f} %, {how}")
    _write(result, out, p.label, p.inputs())
    _preview(result.model, p.instance, preview, p.shown, views, out)


@app.command("remove")
@user_errors
@json_record
def remove_cmd(
    model: ModelArg,
    instance: InstanceOpt,
    view: ViewOpt,
    out: OutOpt,
    scribble: ScribbleOpt = None,
    scribble_json: ScribbleJsonOpt = None,
    keep: KeepShapeOpt = None,
    keep_json: KeepJsonOpt = None,
    occluded: Annotated[bool, typer.Option("--occluded", help="With --method paper: remove only the first surface along each scribbled ray (a part in front of others); a selection already says which surfaces go.")] = False,
    method: MethodOpt = EditMethod.selection,
    selection: SelectionOpt = None,
    mirror: MirrorOpt = None,
    join: JoinOpt = None,
    force: ForceOpt = False,
    preview: PreviewOpt = None,
    views: PreviewViewsOpt = None,
    edit: PriorOpt = None,
    strategy: StrategyOpt = Strategy.hybrid,
    penalty: PenaltyOpt = Penalty.element,
    steps: StepsOpt = 100,
    lr: LrOpt = 1e-2,
    rays: RaysOpt = 1024,
    as_json: JsonOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
    seed: SeedOpt = 0,
) -> None:
    """Remove the scribbled part of one instance (trains F_fuse and F_dens, updates its occupancy grid)."""
    from ..edit import remove
    from ..edit.shape import check_occluded

    check_occluded(occluded, method.value)  # before the selection is lifted and said, not after
    if selection is None:  # a selection file says what goes by itself
        _require_scribble(scribble, scribble_json, "part to remove (or a --selection file)")
    options = _options(strategy, steps, lr, rays, seed, penalty)
    check_out_file(out, _scribbled_inputs(model, edit, scribble, scribble_json, keep, keep_json, selection))
    p = _scribbled(model, edit, device, instance, view, (scribble, scribble_json, keep, keep_json), force, method, mirror, selection, "remove", preview, views,
                   join)
    with edit_progress(options, "removal") as shown_options:
        result = remove(p.model, p.instance, p.camera, p.scribble, p.keep, occluded, shown_options, method.value, p.selection, p.mirror)
    hyper = json.loads(result.meta.get("hyperparameters", "{}"))
    if "removed_cells" in hyper:  # why the grid loses another count of cells than the selection holds
        taken, junction = hyper["removed_cells"], hyper["junction_cells"]
        typer.echo(f"removal: {taken} cells, {_skin_text(taken, hyper.get('selected_cells'), p.selection)}; {junction} of them touch "
                   f"a kept part and lose only their side toward the selection, so {taken - junction} leave the occupancy grid")
    _write(result, out, p.label, p.inputs())
    _preview(result.model, p.instance, preview, p.shown, views, out)


def _skin_text(taken: int, selected: int | None, given) -> str:
    """What a removal took besides its selection (``selected`` cells; ``given``: a --selection
    file's, or None): a skin of cells around it, or none, and why when the file was made for
    another kind of edit."""
    if selected is None:  # an edit file before the count was recorded
        return "the selection with the skin around it"
    if taken > selected:
        return f"the selection's {selected} and a skin of {taken - selected} around it"
    made_for = given.meta.get("for", "remove") if given is not None else "remove"
    if made_for != "remove":
        return f"the selection's {selected}, no skin (made --for {made_for}, it holds no cell of a removal's lower values)"
    return f"the selection's {selected}, no skin"


@app.command("add")
@user_errors
@json_record
def add_cmd(
    model: ModelArg,
    instance: InstanceOpt,
    view: Annotated[str, typer.Option("--view", help="The target's view the part is pasted on (--offset is in its pixels): train:5, test:0, orbit:36@30:5, or a camera JSON.")],
    out: OutOpt,
    donor: Annotated[str, typer.Option("--donor", help="Instance to copy a part from: a name or an index.")],
    copy_mask: Annotated[Path, typer.Option("--copy", help="The part to copy, drawn on the donor view: read like --scribble (white on black, strokes on a transparent PNG or over the donor view's render, or strokes JSON when the name ends in .json).")],
    offset: Annotated[str, typer.Option("--offset", help="Where to paste: DX,DY pixels right and down, e.g. 6,0 or -4,2.")],
    donor_view: Annotated[Optional[str], typer.Option("--donor-view", help="The donor's view the copy mask is drawn on (default: --view's spec, of the donor: train:5 is the donor's train:5).")] = None,
    method: Annotated[AddMethod, typer.Option("--method", help="composite: fit the pasted image; density: match the donor's density along the pasted rays; selection (default): lift the copy mask to a 3-D selection of the donor's part and copy its density and features, moved into place, at points in 3-D.")] = AddMethod.selection,
    selection: Annotated[Optional[Path], typer.Option("--selection", help="With --method selection: a selection file of the DONOR's part from `crfedit select` (default: computed from --copy).")] = None,
    keep: Annotated[Optional[Path], typer.Option("--keep", help="With --method composite or density: mask PNG (or strokes .json) on --view of what must not change (a random sample of the rest of the view is kept as well).")] = None,
    keep_json: Annotated[Optional[Path], typer.Option("--keep-json", help="With --method composite or density: strokes JSON of what must not change.")] = None,
    preview: PreviewOpt = None,
    views: PreviewViewsOpt = None,
    edit: PriorOpt = None,
    strategy: StrategyOpt = Strategy.hybrid,
    penalty: PenaltyOpt = Penalty.element,
    steps: StepsOpt = 100,
    lr: LrOpt = 1e-2,
    rays: RaysOpt = 1024,
    as_json: JsonOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
    seed: SeedOpt = 0,
) -> None:
    """Add a part copied from another instance (trains F_fuse and F_dens, grows its occupancy grid)."""
    from ..edit import add
    from ..edit.scribble import load_mask
    from ..edit.shape import parse_offset
    from ..edit.supervised import outside_box_note

    dxdy = parse_offset(offset)
    options = _options(strategy, steps, lr, rays, seed, penalty)
    check_out_file(out, {**_scribbled_inputs(model, edit, None, None, keep, keep_json, selection), "--copy": copy_mask})
    m = _load(model, edit, device)
    k, j = instance_option(m, instance, "--instance"), instance_option(m, donor, "--donor")  # named: it takes two
    if "occupancy" in m.overrides.get(j, {}):  # a removal (or addition) of the donor earlier in the stack
        typer.echo(f"note: an earlier --edit changed {m.names[j]}'s shape: the part is copied from the donor as edited "
                   "(a part it removed is not there to copy; check the preview)", err=True)
    shown = _preview_views(m, k, preview, views)
    label, camera = _one_view(m, view, k)
    # the copy mask is drawn on the donor's own view: --view's spec read on the donor by default
    donor_camera = _one_view(m, view if donor_view is None else donor_view, j, "--view" if donor_view is None else "--donor-view")[1]
    _refuse_none("--copy", copy_mask, "an addition needs the donor's part drawn on --copy")
    copied = load_mask(copy_mask, None, donor_camera.width, donor_camera.height, "copy", _view_render(m, j, donor_camera))
    mask = copied.mask
    typer.echo(f"copy: {copied.reading}, {int(mask.sum())} pixels")
    bg = load_mask(keep, keep_json, camera.width, camera.height, "keep")
    bg = None if bg is None else bg.mask
    if selection is not None and method != AddMethod.selection:
        raise CrfError("--selection belongs to --method selection")
    sel = _selection(selection, m, j, "add")
    with edit_progress(options, "addition") as shown_options:
        result = add(m, k, camera, j, mask, dxdy, donor_camera, method.value, bg, shown_options, sel,
                     on_selection=lambda made: _echo_selection(made, "donor ", takes_keep=False))
    note = outside_box_note(result.meta, f"--offset {offset}")
    if note:
        typer.echo(f"warning: {note}", err=True)
    from ..masks import mask_digest

    _write(result, out, label, {"copy": mask_digest(mask), "keep": mask_digest(bg), "donor_view": donor_view or view})
    _preview(result.model, k, preview, shown, views, out)


@app.command("transfer")
@user_errors
@json_record
def transfer_cmd(
    model: ModelArg,
    instance: InstanceOpt,
    out: OutOpt,
    shape_from: Annotated[Optional[str], typer.Option("--shape-from", help="Take the shape code (and occupancy grid) of this instance.")] = None,
    color_from: Annotated[Optional[str], typer.Option("--color-from", "--colour-from", help="Take the colour code of this instance.")] = None,
    preview: PreviewOpt = None,
    views: PreviewViewsOpt = None,
    edit: PriorOpt = None,
    as_json: JsonOpt = False,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Give one instance another instance's shape or colour code (no optimization)."""
    from ..edit import transfer
    from ..edit.transfer import weights_not_carried

    if shape_from is None and color_from is None:
        raise CrfError("transfer: give --shape-from or --color-from (or both)")
    check_out_file(out, {"MODEL": model, "--edit": edit})
    m = _load(model, edit, device)
    k = instance_option(m, instance, "--instance")  # named: the command takes two or three instances
    shown = _preview_views(m, k, preview, views)
    sources = {key: None if name is None else instance_option(m, name, option)
               for key, name, option in (("shape_from", shape_from, "--shape-from"), ("color_from", color_from, "--color-from"))}
    result = transfer(m, k, **sources)
    for note in weights_not_carried(m, k, **sources):
        typer.echo(printable(f"note: {note}"), err=True)
    _write(result, out, "")
    _preview(result.model, k, preview, shown, views, out)


# ----------------------------------------------------------------------------- edits …


def _short(value) -> str:
    """A hyperparameter for the table: floats to 4 significant digits, a list of records (the
    cameras) as its length; ``--json`` prints them whole."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        return f"[{len(value)} record{'s' * (len(value) != 1)}]"
    if isinstance(value, list):
        return "[" + ", ".join(_short(v) for v in value) + "]"
    if isinstance(value, dict):  # a small record (a recolour's widened refit: the fit it kept)
        return "{" + ", ".join(f"{k}={_short(v)}" for k, v in value.items()) + "}"
    return str(value)


JSON_META = ("modules", "hyperparameters", "first_loss", "fit_loss", "final_loss", "seconds", "inputs", "stages", "photo_psnr")
"""An edit's metadata values that hold JSON (a list, a table, a number): ``--json`` shows them parsed."""


def _parsed(key: str, value: str):
    """``value`` parsed where ``key`` is one of :data:`JSON_META` (as it was, if it is not JSON
    or is NaN or infinite, which JSON cannot print)."""
    if key not in JSON_META:
        return value
    def refuse(constant: str):
        raise ValueError(constant)

    try:
        return json.loads(value, parse_constant=refuse)
    except ValueError:
        return value


IDENTITY_ROWS = ("kind", "instance", "adds_instance", "modules", "base", "parent", "fingerprint")
RECORD_ROWS = ("first_loss", "fit_loss", "final_loss", "seconds", "view", "command", "rebased")
FIT_REAL_ROWS = ("photo", "mask", "pose", "photo_psnr")
SHOWN_KEYS = frozenset({*IDENTITY_ROWS, *RECORD_ROWS, *FIT_REAL_ROWS, "hyperparameters", "inputs", "stages", "version", "format",
                        "occupancy_shape", "made_by"})
"""The metadata keys ``edits show`` prints in rows of their own (the three tuples, the hyper,
inputs and stage rows), or as the file's size line and format, or not at all (the quickstart's
mark); any other (``EditResult.save(path, note=...)`` from a script) gets a row after them."""


def _show_rows(delta, size: int) -> list[tuple[str, str]]:
    meta = delta.meta
    rows = [(key, meta.get(key, "")) for key in IDENTITY_ROWS]
    rows = [(k, v if v else "(none)" if k == "parent" else v) for k, v in rows if v or k == "parent"]
    rows += [(key, meta[key]) for key in RECORD_ROWS if meta.get(key)]
    if meta.get("hyperparameters"):
        try:
            hyper = json.loads(meta["hyperparameters"])
        except json.JSONDecodeError:
            hyper = None
        if isinstance(hyper, dict):
            rows.append(("hyper", ", ".join(f"{k}={_short(v)}" for k, v in hyper.items())))
    if meta.get("inputs"):  # digests of what it was made from (and the modes asked for; null: the default)
        inputs = _parsed("inputs", meta["inputs"])
        if isinstance(inputs, dict):
            rows.append(("inputs", ", ".join(f"{k}={'default' if v is None else v}" for k, v in inputs.items()) or "(none recorded)"))
    rows += [(key, meta[key]) for key in FIT_REAL_ROWS if meta.get(key)]  # fit-real's record
    rows += [(key, meta[key]) for key in sorted(meta) if key and key not in SHOWN_KEYS and isinstance(meta[key], str)]  # a script's own provenance (table_row keeps it on one line)
    stages = _parsed("stages", meta["stages"]) if meta.get("stages") else None
    if isinstance(stages, list):
        for st in stages:
            if isinstance(st, dict):
                rows.append(("stage", ", ".join(f"{k}={_short(v)}" for k, v in st.items())))
    n = len(delta.tensors)
    rows.append(("size", f"{size} bytes, {n} tensor{'s' * (n != 1)}, edit format version {meta['version']}"))
    grid = delta.tensors.get("occupancy")
    if grid is not None and delta.meta["version"] != "1":  # version 1 stored the grid itself
        rows.append(("occupancy", f"{int((grid < 0).sum())} cells emptied, {int((grid > 0).sum())} occupied"))
    for name, t in sorted(delta.tensors.items()):
        stored = _packed_bytes(delta) if name == "occupancy" else None
        how = "" if stored is None else f", stored bit-packed in {stored} bytes"
        rows.append(("tensor", f"{name} {list(t.shape)} {str(t.dtype).replace('torch.', '')}{how}"))
    return rows


def _packed_bytes(delta) -> int | None:
    """Bytes of the file's grid change, where it is stored bit-packed (version 3 on); else None."""
    from ..delta import GRID, grid_packed, pack_grid_change

    if GRID not in delta.tensors or not grid_packed(delta.meta["version"]):
        return None
    return sum(t.numel() for t in pack_grid_change(delta.tensors[GRID])[0].values())


@edits_app.command("show")
@user_errors
def show_cmd(
    edit: Annotated[Path, typer.Argument(help="Edit file (.safetensors).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """Print an edit file's metadata and tensors."""
    print_edit(edit, as_json)


def print_edit(edit: Path, as_json: bool) -> None:
    """`edits show` (and `info` on an edit file): the file's metadata and tensors, as a table or JSON."""
    from ..delta import read_delta

    delta = read_delta(edit)
    size = edit.stat().st_size
    if as_json:
        tensors = {n: {"shape": list(t.shape), "dtype": str(t.dtype).replace("torch.", "")} for n, t in sorted(delta.tensors.items())}
        stored = _packed_bytes(delta)
        if stored is not None:
            tensors["occupancy"]["stored_bytes"] = stored  # bit-packed on disk
        typer.echo(json.dumps({"file": str(edit), "bytes": size, "metadata": {k: _parsed(k, v) for k, v in delta.meta.items()}, "tensors": tensors}, indent=2))
        return
    for key, value in _show_rows(delta, size):
        typer.echo(table_row(key, value))


@edits_app.command("check")
@user_errors
def check_cmd(
    model: ModelArg,
    edit: Annotated[list[Path], typer.Option("--edit", help="Edit file (repeatable, in the order they apply).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print {ok, model, base, edits: [{file, kind, instance, fingerprint}]} as JSON on stdout; a stack that does not apply prints nothing there.")] = False,
) -> None:
    """Check that a stack of edits applies to a model (files, order, instances, shapes)."""
    from ..delta import check_stack, read_delta, stack_of
    from ..model import load_model

    m, _ = load_model(model, "cpu")
    deltas = [read_delta(p) for p in edit]
    check_stack(m, deltas)
    if as_json:  # a failing stack prints its one line on stderr and nothing here (exit 2), as every --json command
        typer.echo(json.dumps({"ok": True, "model": str(model), "base": stack_of(m)[0], "edits": [
            {"file": str(p), "kind": d.kind, "instance": d.instance, "fingerprint": d.fingerprint} for p, d in zip(edit, deltas)]}, indent=2))
        return
    typer.echo(f"ok: {len(deltas)} edit(s) apply to {model} in this order")
    for i, d in enumerate(deltas, 1):
        typer.echo(printable(f"  {i}. {d.path}: {d.kind} edit of {d.instance} ({d.fingerprint})"))


@edits_app.command("rebase")
@user_errors
def rebase_cmd(
    model: ModelArg,
    edit: Annotated[list[Path], typer.Option("--edit", help="Edit file (repeatable), in the new order; leave out the ones to drop.")],
    out_dir: Annotated[Path, typer.Option("--out-dir", help="Folder for the re-pinned files (made if missing, in a folder that exists), named as the inputs; never an input's own folder.")],
) -> None:
    """Re-pin edits to a new stack: drop one from the middle, reorder them, or share one alone.

    Each file keeps its change (the same tensors; a transfer takes its source's code again at its
    new place); base, parent and fingerprint are recomputed for its new place, so the written
    files pass `crfedit edits check` in the order given. An edit made after one that is now left
    out applies its change without it, not optimized again.
    """
    from ..delta import apply_deltas, made_on_files, made_on_stack, made_where_it_stands, read_delta, restack, save_delta
    from ..edit.transfer import weights_not_carried
    from ..model import load_model

    names = [p.name for p in edit]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise CrfError(f"--edit: {twice[0]} is given twice (or two files share the name); --out-dir names the outputs after the inputs")
    if out_dir.exists() and not out_dir.is_dir():
        raise CrfError(f"--out-dir {out_dir}: is a file, not a folder")
    parent = out_dir.parent if str(out_dir.parent) else Path(".")
    if not out_dir.exists() and not parent.is_dir():  # the folder itself is made; a typo above it is an error
        raise CrfError(f"--out-dir {out_dir}: folder {parent} does not exist")
    for p in edit:
        if p.parent.resolve() == out_dir.resolve():
            raise CrfError(f"--out-dir {out_dir}: holds the input {p} itself; write the re-pinned files to another folder")
    there = [out_dir / p.name for p in edit if (out_dir / p.name).exists()]
    for target in there:  # an edit may replace an edit, never another kind of file
        check_out_file(target, {"--edit": edit}, "re-pinned edit", label=f"--out-dir {out_dir}: {target.name}", instead="pick another folder")
    m, _ = load_model(model, "cpu")
    deltas = [read_delta(p) for p in edit]
    _, pinned = restack(m, deltas)  # everything checked before anything is written
    out_dir.mkdir(parents=True, exist_ok=True)
    for p, before, after in zip(edit, deltas, pinned):
        # a re-pinned file's `command` still names the stack it was made on: say where it went since
        earlier = after.meta.get("rebased")  # a file re-pinned before keeps that record too, oldest first
        meta = after.meta if after is before else {**after.meta, "rebased": f"{earlier}; then {command_line()}" if earlier else command_line()}
        save_delta(out_dir / p.name, after.tensors, meta)
        how = "unchanged (already in this place)" if after is before else "re-pinned"
        if after is not before and after.kind == "transfer":
            how += f" (a transfer: it takes {_transfer_sources(after)}'s code again here)"
        old_grid = " (format version 1: its grid replaces the instance's)" if after.meta["version"] == "1" and "occupancy" in after.tensors else ""
        replaced = ", replacing the edit file there" if out_dir / p.name in there else ""
        typer.echo(printable(f"wrote {out_dir / p.name}: {after.kind} edit of {after.instance}, {how}{old_grid}{replaced}"))
    typer.echo(f"ok: {len(pinned)} edit(s) apply to {model} in this order")
    stale = sorted(p.name for p in out_dir.glob("*.safetensors") if p.name not in names and _is_edit_file(p))
    if stale:  # an earlier rebase's files: not in this stack, and `edits check` with them fails
        typer.echo(printable(f"note: {out_dir} also holds {', '.join(stale)} from before, which this stack does not include"), err=True)
    for p, before, after in zip(edit, deltas, pinned):  # an old transfer's source lies outside its fingerprint
        if (after is not before and before.kind == "transfer" and before.meta["version"] in ("1", "2", "3")
                and not made_where_it_stands(before, m)):  # else restack checked it against its stored change
            typer.echo(printable(f"note: {p.name} is a format-version-{before.meta['version']} transfer: the source it names "
                                 f"({_transfer_sources(before)}) lies outside its fingerprint and could not be checked against "
                                 "its stored change here (made after other edits); make it again if in doubt"), err=True)
    for i, (p, before, after) in enumerate(zip(edit, deltas, pinned)):  # as transfer says it where the transfer is made
        if after is not before and after.kind == "transfer":
            hyper = json.loads(after.meta.get("hyperparameters") or "{}")
            for note in weights_not_carried(apply_deltas(m, pinned[:i]), after.instance, hyper.get("shape_from"), hyper.get("color_from")):
                typer.echo(printable(f"note: {p.name} here: {note}"), err=True)
    given, named = {p.name for p in edit}, False
    for p, before, after in zip(edit, deltas, pinned):  # the edits each re-pinned one was optimized on that this stack leaves out
        if after is before or after.kind == "transfer":
            continue
        stack = made_on_stack(before)  # the files its record names, read, when they are still those edits
        made_on = stack if stack is not None else [None] * len(made_on_files(before))
        gone = [_left_out(path, d, after.instance) for path, d in zip(made_on_files(before), made_on) if Path(path).name not in given]
        if gone:
            named = True
            why = (" (a part the left-out removal took comes back as it was learnt beside it: a recolour made after it may have "
                   "spread onto it)" if after.kind == "color" and any(kind == "remove" for _, kind in gone) else "")
            typer.echo(printable(f"note: {p.name} was optimized on top of {', '.join(text for text, _ in gone)}, which this stack "
                                 f"leaves out; it keeps the change it learnt there{why}: render the new stack to check it "
                                 "(crfedit render --edit ...)"), err=True)
    if not named and any(after is not before and after.kind != "transfer" for before, after in zip(deltas, pinned)):
        typer.echo("note: a re-pinned edit keeps the change it was optimized for on its old stack; where an edit of the same "
                   "instance was left out or moved before it, render the new stack to check it (crfedit render --edit ...)", err=True)


def _left_out(path: str, delta, instance: str) -> tuple[str, str | None]:
    """(an edit file an edit was made on, for a line: its name, and its kind when ``delta`` is
    that edit, read and verified (:func:`~crfedit.delta.made_on_stack`), and edits the same
    instance, ``e3.safetensors (a remove edit of chair_003)``; that kind or None).  Without it,
    the recorded name alone, marked so: a file of that name here may be another edit."""
    if delta is None:
        return f"{Path(path).name} (as recorded)", None
    if delta.instance != instance:
        return Path(path).name, None
    return f"{Path(path).name} (a {delta.kind} edit of {delta.instance})", delta.kind


def _transfer_sources(delta) -> str:
    """The instances a transfer takes its codes from, for a line: ``chair_001`` or ``chair_001 and
    chair_002``; only for the code rows it stores (an old file's record may name more)."""
    hyper = json.loads(delta.meta.get("hyperparameters") or "{}")
    rows = {"shape_from": "shape_code", "color_from": "color_code"}
    names = dict.fromkeys(str(hyper[k]) for k, row in rows.items() if hyper.get(k) and row in delta.tensors)
    return " and ".join(names) or "its source"


def _is_edit_file(path: Path) -> bool:
    """Whether ``path`` is an edit file, by its header alone (anything unreadable is not)."""
    from ..names import EDIT_FORMAT
    from ..safefile import read_header

    try:
        return read_header(path)[1].get("format") == EDIT_FORMAT
    except Exception:  # noqa: BLE001 - a damaged or foreign file is simply not one of ours
        return False


@edits_app.command("bake")
@user_errors
def bake_cmd(
    model: ModelArg,
    edit: Annotated[list[Path], typer.Option("--edit", help="Edit file to fold in (repeatable, in the order they apply).")],
    out: Annotated[Path, typer.Option("--out", help="Model file to write (atomically).")],
    training_state: Annotated[bool, typer.Option("--training-state", help="Also copy the input's training state (default: the baked model is stripped).")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --out model instead of refusing.")] = False,
) -> None:
    """Fold a stack of edits into a new model file (renders like the model with the stack applied).

    The new model holds no training state (crfedit model strip), unless --training-state.
    """
    from ..delta import bake
    from ..model import load_model, save_model

    check_out_file(out, {"MODEL": model, "--edit": edit}, "baked model", "baked.safetensors", MODEL_FORMAT, overwrite)
    m, state = load_model(model, "cpu")
    baked = bake(m, edit)
    save_model(out, baked, state if training_state else None, extra_meta={"command": command_line()})
    kept = "with" if training_state and state else "without"
    typer.echo(
        f"wrote {out} ({size_text(out.stat().st_size)}, {kept} training state): the model {model} "
        f"with {len(edit)} edit(s) baked in; {model} is unchanged"
    )
