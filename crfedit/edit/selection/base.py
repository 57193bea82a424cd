"""A selection's input and result: one view's scribbles (:class:`ScribbleView`) and the soft
per-cell selection (:class:`Selection`), with one-line summaries of what its metadata says."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ... import occupancy
from ...cameras import Camera
from ...errors import CrfError
from ...masks import as_mask
from ...names import real_number
from ...model import CategoryModel
from .options import GROW_LOW
from .refine import hysteresis
from .shapes import RIM_SHEETS


@dataclass(frozen=True)
class ScribbleView:
    """One view's scribbles: the part to edit (``scribble``) and what must not change (``keep``)."""

    camera: Camera
    scribble: np.ndarray  # [H, W] bool
    keep: np.ndarray | None = None  # [H, W] bool

    def __post_init__(self):  # any mask as_mask takes (a torch tensor, 0/1 numbers) becomes a bool ndarray
        object.__setattr__(self, "scribble", as_mask(self.scribble, "scribble"))
        if self.keep is not None:
            object.__setattr__(self, "keep", as_mask(self.keep, "keep"))


@dataclass
class Selection:
    """A soft per-cell selection of one instance: ``values`` [R, R, R] in [0, 1]."""

    values: Tensor
    instance: int
    instance_name: str
    model_fingerprint: str
    meta: dict
    threshold: float = 0.5

    @property
    def mask(self) -> Tensor:
        """Selected cells [R, R, R] bool."""
        return self.values >= self.threshold

    def at(self, xn: Tensor) -> Tensor:
        """Whether normalized points [..., 3] lie in a selected cell (outside the box: False)."""
        inst = torch.zeros(xn.shape[:-1], dtype=torch.long, device=xn.device)
        return occupancy.lookup(self.mask[None].to(xn.device), inst, xn)

    @property
    def reads_sheets(self) -> bool:
        """Whether the scribbled points lie mostly on sheets (planar rather than linear local
        shape, :data:`~.shapes.RIM_SHEETS`), as the selection's rim fill measured them
        (``meta["rim_fill"]["sheet_share"]``); False when its metadata does not say."""
        share = (self.meta.get("rim_fill") or {}).get("sheet_share")
        return share is not None and share >= RIM_SHEETS

    def grown(self, low: float = GROW_LOW) -> "Selection":
        """This selection plus every cell of value ≥ ``low`` connected to it (26-neighbourhood):
        hysteresis.  Measured for recolours and not used by them (see the module docstring)."""
        values = hysteresis(self.values, self.mask, self.threshold, low)
        return Selection(values, self.instance, self.instance_name, self.model_fingerprint, self.meta, self.threshold)

    def check_for(self, model: CategoryModel, instance: int) -> None:
        """A one-line error unless this selection was made for ``model``'s ``instance``."""
        if self.model_fingerprint != model.fingerprint():
            from ...delta import stack_of

            base, stack = stack_of(model)
            if stack and self.model_fingerprint == base:
                raise CrfError(f"the selection was made on the model without the {len(stack)} earlier edit(s) applied here; "
                               "make it with the same --edit files as the edit (crfedit select ... --edit ...)")
            raise CrfError(f"the selection was made for another model, or the same one with other --edit files (fingerprint "
                           f"{self.model_fingerprint[:12]}…, this model{' with its edits' if stack else ''} {model.fingerprint()[:12]}…); "
                           "make it with the same model and --edit files as the edit")
        if self.instance_name != model.names[instance]:
            raise CrfError(f"the selection is of instance {self.instance_name!r}, not {model.names[instance]!r}")
        if tuple(self.values.shape) != (model.cfg.occ_res,) * 3:
            raise CrfError(f"the selection grid is {self.values.shape[0]}³ but the model's occupancy grid is {model.cfg.occ_res}³")
        self.check_values()
        if not bool(self.mask.any()):
            raise CrfError("the selection is empty: no cell is selected")

    def check_values(self) -> None:
        """A one-line error unless the values lie in [0, 1] (NaN refused) and the threshold in
        (0, 1]: a NaN grid or threshold read as "empty", and values of 1.5 or -0.5 were saved
        wrapped around uint8 (1.5 read back as 0.494, -0.5 as 0.502)."""
        t = self.threshold
        if real_number(t) is None or not 0.0 < real_number(t) <= 1.0:
            raise CrfError(f"the selection's threshold {t!r}: expected a number in (0, 1]")  # NaN fails the range test too
        v = self.values
        if not v.is_floating_point():
            raise CrfError(f"the selection's values must be a floating-point grid of numbers from 0 to 1, not {str(v.dtype)[6:]}")
        if bool(v.isnan().any()) or bool((v < 0).any()) or bool((v > 1).any()):
            raise CrfError(f"the selection's values must be numbers from 0 to 1 (its grid holds "
                           f"{'NaN' if bool(v.isnan().any()) else 'values outside [0, 1]'})")


def part_summary(meta: dict) -> str | None:
    """What a selection's metadata says of the part head, in a line (None: the model has none,
    or the selection was told not to read it)."""
    info = meta.get("part_head")
    if info is None:
        return None
    if info["used"]:
        line = f"read (the scribbled points' part embeddings agree: coherence {info['coherence']:.2f})"
        if info.get("veto_by") == "keep strokes" and info["keep_points"]:  # without keep points: keep_summary says so
            line += f"; {info['vetoed']} selected cells left out as parts the keep strokes mark"
        if info.get("join_gated") is False:
            line += f"; sure of the part (coherence ≥ {info['sure_at']:g}), so the shape gate leaves its join alone"
        if info.get("learned") is False:  # held-out chairs: 0.85 of the gap against 0.93 (docs/benchmarks.md, fifty-eighth session)
            line += "; it never learned this chair's part maps and judges it by other chairs' (check the preview)"
        return line
    return f"not read (coherence {info['coherence']:.2f} < {info['cut']:g}: it does not see the scribbled points as one part)"


JOIN_WARN = 2.0
""":func:`join_summary` says what to do when a join takes at least this × the features' cells.
Such a join is as often right as wrong: on the colour twins of four models (docs/benchmarks.md,
forty-ninth session) the joins of 2× or more mostly took what the features had missed of the
scribbled material (a wooden frame's legs, the rest of an armchair's shell), and once an
orange seat along with the orange back that was scribbled (2.6×)."""


def join_summary(meta: dict) -> str | None:
    """What a selection's metadata says of the chromaticity join
    (:attr:`~.options.SelectOptions.chroma_union`), in a line (None: not asked).  A refused
    join is what leaves a large part half selected; the line says what to do about it.
    ``meta["colour_join"]``: the ``--colour-join`` mode asked for, when one was."""
    mode = meta.get("colour_join")
    if mode == "never":
        return "off (--colour-join never)"
    info = meta.get("chroma_union")
    if info is None:
        return None
    if mode == "always" and info.get("joined"):
        return f"took the cells of the scribbled colour ({info['cells']} by chromaticity alone, as --colour-join always asks)"
    if info["cells"] is None:
        return f"not tried (the scribbled colour is near-grey: saturation {info['saturation']:.2f})"
    if info["joined"]:
        said = f"took the cells of the scribbled colour ({info['cells']} by chromaticity alone"
        features = info.get("features_cells")  # not recorded before 2026-11-26
        if not features:
            return said + ")"
        said += f", {info['cells'] / features:.1f}× the {features} the features select)"
        left = info.get("not_lines", 0)  # SelectOptions.join_lines, since 2026-11-27
        if left:
            said += f"; left out {left} of them, in pieces that are not lines (the scribble lies on lines)"
        if info["cells"] - left >= JOIN_WARN * features:
            said += ("; if the preview shows another part of this colour taken with it: --colour-join never,"
                     " or a keep stroke on that part")
        return said
    said = f"refused: chromaticity alone selects {info['cells']} cells"
    if "features_cells" in info:  # not recorded before 2026-11-26
        said += f", over {info['cap']:g}× the {info['features_cells']} the features select"
    if info.get("keeps_lines", "line_negatives" in meta):  # under a scribble on bars a join keeps to bars (SelectOptions.join_lines);
        # selections made before the fifty-fifth session (2026-11-27) say so only through line_negatives
        return said + " (the scribble lies on bars: --colour-join always would join only the pieces of bars)"
    return said + " (if the part is that large: --colour-join always, or scribble more of it or from a second view)"


def shape_summary(meta: dict) -> str | None:
    """What a selection's metadata says of the shape gate and the rims, in a line (None: neither ran)."""
    gate, rims = meta.get("shape_gate"), meta.get("rim_fill")
    if gate is None and rims is None:
        return None

    def cells(n: int, what: str) -> str:
        return f"{n} {what}cell{'' if n == 1 else 's'}"

    said = []
    if gate is not None:
        said.append("nothing left out of the joins" if gate["dropped"] == 0
                    else f"left {cells(gate['dropped'], '')} out of the joins (pieces of lines square to the scribble, "
                         "such as legs under scribbled stretchers; if they belong to the part, scribble them too, "
                         "here or from a second view)")
    sheets = meta.get("sheet_veto")
    if sheets is not None and sheets["cells"] > 0:
        said.append(f"left {cells(sheets['cells'], 'sheet ')} out (the scribble lies on lines: {sheets['line_share']:.0%})")
    if rims is not None and rims["cells"] > 0:
        said.append(f"took {cells(rims['cells'], 'rim ')} (lines lying in the scribbled panel's plane)")
    if rims is not None and rims.get("sheet_share", 0.0) >= RIM_SHEETS:
        said.append(f"the scribble lies on sheets ({rims['sheet_share']:.0%}): a removal also empties their outline")
    return "; ".join(said) if said else "no rim taken"


def stroke_summary(meta: dict) -> str | None:
    """What a selection's metadata says of :attr:`~.options.SelectOptions.stroke_snap` and
    :attr:`~.options.SelectOptions.stroke_centres`, in a line (None: it lifted every scribbled
    pixel, as asked)."""
    info, snap, strays = meta.get("stroke_centres"), meta.get("stroke_snap"), meta.get("keep_strays") or 0
    n = snap["added_pixels"] if snap else 0
    said = [f"{n} pixel{'' if n == 1 else 's'} beside the scribble snapped onto the object (it lay mostly off it)"] if n else []
    if info is not None:
        said.append(_centres_summary(info))
    if strays:
        said.append(f"{strays} scribbled point{' that looks' if strays == 1 else 's that look'} like the keep strokes, "
                    "not like the rest of the scribble, left out (a stroke straying onto a kept part looks so, and so may the "
                    "part's own points; the classifier may still take their cells)")
    return "; ".join(said) if said else None


def _centres_summary(info: dict) -> str:
    n, n_keep = info["edge_points"], info.get("keep_edge_points", 0)  # selections before 2026-11-26 cut only the scribble
    points = lambda m: f"{m} edge point{'' if m == 1 else 's'}"
    keep = f"; {points(n_keep)} of the keep strokes left out" if n_keep else ""
    if n == 0 and info.get("whole_views", 1) == 0:  # centres lifted, and every scribbled point on the object lay in one
        return f"their centres lifted (the strokes' edges lie off the object: no scribbled point left out){keep}"
    if n == 0:  # (a selection file before the sixty-sixth session does not say which)
        return f"lifted whole (strokes one or two pixels wide: every scribbled pixel is lifted){keep}"
    return f"their centres lifted ({points(n)} left out: a stroke's edge strays off its part){keep}"


NEARLY_ALL = 0.97
"""A selection holding this share of the instance's occupied cells or more gets a
"coverage" line.  The benchmark's 175 selections of seven models hold at most 0.90 (a real
chair of one material); a scribble drawn on another view than the one named held 0.99."""


def nearly_all(selected: int, occupied: int) -> bool:
    """Whether ``selected`` cells are nearly all (:data:`NEARLY_ALL`) of the ``occupied`` ones."""
    return selected >= NEARLY_ALL * occupied


def coverage_summary(meta: dict) -> str | None:
    """A line when the selection takes nearly every occupied cell of the instance (None
    otherwise): usually a scribble that belongs to another view or instance."""
    selected, occupied = meta.get("selected_cells"), meta.get("occupied_cells")
    if isinstance(meta.get("whole"), float):  # pipeline.WHOLE_SCRIBBLE
        return (f"the scribble covers {meta['whole']:.0%} of what the view shows of the instance, and no keep stroke "
                "holds anything back: the whole instance is selected")
    if type(selected) is not int or type(occupied) is not int or occupied <= 0 or not nearly_all(selected, occupied):
        return None
    return (f"{selected} of the instance's {occupied} occupied cells, nearly all of it: unless the part is most of "
            "the object, check that the scribble was drawn on this view of this instance (and the preview)")


CLASH_SHARE = 0.1
""":func:`keep_summary` warns when at least this share of the scribbled cells (and
:data:`CLASH_LEAST`) also hold keep points: a keep stroke of one view drawn on the part another
view scribbles cut a tester's selection from 3913 cells to 562 without a word.  A scribble and
its keep strokes meet in a cell or two along the part's edge anyway."""
CLASH_LEAST = 5


def merge_views(first: "ScribbleView", more: "ScribbleView") -> "ScribbleView":
    """``first``'s view with the strokes of ``more`` (drawn on the same view) added to its own:
    one view given twice is one view (lifted twice, its points counted twice, a tester's
    selection fell from 10 574 cells to 8 407)."""
    keeps = [k for k in (first.keep, more.keep) if k is not None]
    return ScribbleView(first.camera, first.scribble | more.scribble, np.logical_or.reduce(keeps) if keeps else None)


def keep_summary(meta: dict) -> str | None:
    """A line when many scribbled cells also hold keep points (:data:`CLASH_SHARE`), or when no
    keep stroke lies on the object (None otherwise, or when the record does not say).  Keep strokes on the background lift to no point, so the selection then has no
    example of what to leave: on the procedural twins with their keep strokes dropped,
    recolours' selection IoU fell 0.046 on the benchmark's and 0.067 / 0.083 on held-out chairs
    (docs/benchmarks.md, fifty-ninth session), most where a neighbour has the scribble's colour;
    on the real chairs' twins it did not move."""
    if meta.get("whole") is not None:  # the whole instance is selected: nothing was there to hold back
        return None
    clash = meta.get("clash_cells")
    if isinstance(clash, list) and len(clash) == 2 and clash[0] >= max(CLASH_LEAST, CLASH_SHARE * clash[1]):
        return (f"{clash[0]} of the {clash[1]} scribbled cells also hold keep points (strokes of another view on the part?); "
                "the keep strokes win there, so the part may be cut (check the preview)")
    if meta.get("keep_points") != 0 or type(meta.get("positives")) is not int:
        return None
    line = "none on the object, so nothing marks what to leave: a neighbouring part of the scribble's colour may be taken with it"
    head = meta.get("part_head") or {}
    if head.get("used") and head.get("veto_by") == "keep strokes":
        line += ", and the part head leaves no other part out"
    return line + " (check the preview; a keep stroke on that part holds it)"


def mirror_summary(meta: dict) -> str | None:
    """What a selection's metadata says of its mirror symmetry, in a line (None: not asked)."""
    info = meta.get("mirror")
    if info is None:
        return None
    if not info.get("used"):
        return f"not used ({info['why']})"
    plane = f"the plane normal to {'xyz'[info['axis']]} ({info['overlap']:.0%} of the cells mirror onto cells)"
    if info["mode"] == "views":
        return f"{plane}; the view's mirror image added {info['positives']} scribbled and {info['keep_points']} keep points"
    took = f"{plane}; the selection took its mirror image"
    held = meta.get("keep_wins_cells", 0) or (meta.get("part_head") or {}).get("vetoed", 0)
    if meta.get("correction_views", 0) > 0 and held:  # keep strokes on a view besides the first: a correction
        took += (" (a cell the keep strokes hold back comes back where its mirror image is selected: if a correction's keep "
                 "strokes mark one side only, --mirror off keeps to them)")
    return took


def lines_summary(meta: dict) -> str | None:
    """What a selection's metadata says of :attr:`~.options.SelectOptions.line_negatives` and
    :attr:`~.options.SelectOptions.on_bars`, in a line (None: the scribble does not lie on
    lines, or neither option is on)."""
    info, bars = meta.get("line_negatives"), meta.get("on_bars")
    if info is None and bars is None:
        return None
    said = f"the scribble lies on lines ({(info or bars)['line_share']:.0%})"
    if info is not None:
        n = info["points"]
        said += f": {n} of the view's other surface point{'' if n == 1 else 's'}, off lines, held as not the part"
    if bars is not None:
        said += ("; " if info is not None else ": ") + f"selected as on bars ({', '.join(bars['options'])})"
    return said


def pieces_summary(meta: dict) -> str | None:
    """What a selection's metadata says of :attr:`~.options.SelectOptions.free_pieces`, in a
    line (None: not on, or every selected cell connected to the scribble)."""
    info = meta.get("free_pieces")
    if not info or info["kept_cells"] + info["left_cells"] == 0 or meta.get("whole") is not None:  # whole: none was left out
        return None
    cells = lambda n: f"{n} cell{'' if n == 1 else 's'}"
    least = f"{info['share']:.0%} of the {cells(info['reached'])} the scribble reached at that step, before the vetoes"
    said = []
    if info["kept_pieces"]:
        n = info["kept_pieces"]
        said.append(f"kept {n} piece{'' if n == 1 else 's'} that the scribble does not reach ({cells(info['kept_cells'])}; each at least {least})"
                    + (": more than the scribble reached itself, so check the preview; keep strokes on the parts around them hold "
                       "them back (or --mirror off for one side)" if info["kept_cells"] > info["reached"] else ""))
    if info["left_cells"]:
        said.append(f"left {cells(info['left_cells'])} out: pieces it does not reach, each under "
                    + ("that share" if info["kept_pieces"] else least))
    return "; ".join(said)


SUMMARIES = (("coverage", coverage_summary), ("strokes", stroke_summary), ("keep strokes", keep_summary), ("mirror", mirror_summary), ("part head", part_summary), ("on lines", lines_summary),
             ("colour join", join_summary), ("shape gate", shape_summary), ("loose pieces", pieces_summary))
"""(label, summary function) of each part of a selection's metadata that ``select``, ``info``,
the edit commands and the page say, in that order (the page's field: the label, ``_`` for spaces)."""
