"""How scribbles become a selection: :class:`SelectOptions`, each edit kind's options
(:func:`options_for`) and the measured constants behind them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ...errors import CrfError
from ...names import JOIN_MODES, MIRROR_MODES

MIN_OPACITY = 0.5
"""A pixel shows the object (and has a surface point) where its rendered opacity is at least this."""
CENTRE_SHARE = 0.2
""":attr:`SelectOptions.stroke_centres` keeps a view's whole scribble (or keep strokes) when
its 1-px erosion holds less than this share of their surface points (or fewer than 4): strokes
one or two pixels wide have no centre to trust.  A thin piece of wider strokes is lifted whole
beside their erosion (:func:`.pipeline.thin_pieces`)."""
STROKE_CENTRES = True
"""Every edit kind's :attr:`SelectOptions.stroke_centres`.  On the benchmark twins'
scribbles, which lie inside their parts, the four models' mean IoUs move by at most 0.004;
drawn 1 px wider, the removals keep 0.689–0.907 where every pixel gave 0.621–0.853, and the
procedural recolours drawn 2 px wider keep 0.904–0.910 where they fell to 0.834–0.844
(docs/benchmarks.md, forty-third session, `benchmarks/sloppy_scribbles.py`).  The keep
strokes' centres: as drawn no mean IoU moves by more than 0.001; drawn 4 px wider, onto the
part, the removals keep 0.724–0.908 where every kept pixel gave 0.590–0.794.  Additions
(`benchmarks/add.py`, the two procedural models): copy strokes 1 px wider than the donor's
part spill 0.14 / 0.16 where every pixel spilled 0.21 / 0.18, and the rest of the chair is
34.59 / 35.28 dB where it was 31.24 / 32.99 dB (forty-fourth session)."""
STROKE_SNAP = 0.7
"""Recolours' and removals' :attr:`SelectOptions.stroke_snap`.  Each twin's scribble moved 1 px
(`benchmarks/sloppy_scribbles.py --brush shift1`): the real removals' mean IoU 0.481 → 0.726
and 0.536 → 0.699 (a tube's stroke a pixel beside it lies on the background, and lifts to a
point or two); every other brush change and the procedural twins within 0.003
(docs/benchmarks.md, forty-fourth session).  Additions keep 0: moved 2 px off a thin armrest,
their copy strokes snapped onto the chair beside it, and the addition copied that too (the
rest of the target 1.5–3.1 dB worse on three of four runs; forty-fifth session)."""
KEEP_STRAYS = 0.5
"""Recolours' and removals' :attr:`SelectOptions.keep_strays`: a scribbled point is a stray when
its chromaticity lies within this × its distance to the scribble's median of a kept point's.
A tester's 1-px stroke on a navy sofa's seat strayed 1 px onto the white pillow above it (9
of its 70 pixels) and the pillow under a keep stroke turned pink (PSNR 11.7 dB on held-out
views); without those 9 pixels it stayed white (31.5 dB) (docs/benchmarks.md, sixty-sixth
session)."""
STRAY_FLOOR = 0.08
"""A stray's chromaticity lies farther than this from the scribble's median."""
STRAY_SHARE = 1 / 3
"""No stray is dropped when more than this share of a view's scribble would be."""
FEATURES = ("bottleneck", "color", "chroma", "position")
"""The feature groups a selection uses by default."""
GROW_LOW = 0.3
""":meth:`Selection.grown` also takes the cells of value ≥ this connected to the selection
(a measured diagnostic; no edit uses it, see the module docstring); a removal also empties the
cells next to S of value ≥ this."""
VETO_FLOOR = 0.08
"""Chromaticity distance added to the veto's spread term: the scribbled points of a uniformly
coloured part spread by 0.005–0.02, less than the part's own shading edges differ; with the
spread alone (factor 3, floor 0.01) the veto cut those edges from the procedural removals'
parts (gap closed 0.778 → 0.735).  Removals' :attr:`SelectOptions.veto_floor`; recolours use
:data:`COLOR_VETO_FLOOR`."""
FEATURE_GROUPS = (*FEATURES, "fuse", "geometry", "part")
"""Per-point feature groups :func:`point_features` can build: ``fuse`` (F_fuse's activations,
the model's width) and ``geometry`` (:func:`local_shape`), which removals read
(:data:`REMOVE_FEATURES`), and ``part`` (the part head's unit embedding,
:attr:`SelectOptions.part_head`)."""
WIDTHS = {"color": 3, "chroma": 3, "position": 9, "geometry": 11}
"""Feature widths per group (the bottleneck's and F_fuse's are the model's: :func:`group_width`)."""
CHROMA_OFFSET = 0.05
"""The :attr:`SelectOptions.chroma_offset` removals use: rgb / (r + g + b + 0.05)."""
GEOMETRY_RADIUS = 1
""":func:`local_shape`'s block: the (2r+1)³ cells around the point's cell."""

REMOVE_SMOOTH_BANDWIDTH = 0.7
"""A removal's :attr:`SelectOptions.smooth_bandwidth` (:func:`options_for`), with two rounds.
Measured (docs/selection.md) against the plain mean, on the removal twins: selection IoU
procedural 0.884 → 0.891, real 0.394 → 0.405; gap closed 0.744 → 0.743 and −0.174 → −0.106
(h 0.5 – 1.0 and three rounds within 0.01 and 0.03 of these).  Recolours keep the plain mean:
their IoU rose too (0.812 → 0.819, 0.588 → 0.602) but their gap closed fell (0.748 → 0.729,
0.586 → 0.570)."""


JOIN_CHROMA = 4.0
""":attr:`SelectOptions.join_chroma`.  The chromaticity-only classifier is one hyperplane
against the view's other points, so its side can reach a neighbour of a different hue that
no negative stood for: on a model trained over random backgrounds (``train``'s default since
the twenty-third session) `scopia_armchair2`'s recolour took a whole armchair (24 722 cells,
gap closed −0.04).  Measured on the 16-twin benchmark (docs/benchmarks.md, "Training over a
random background"), recolours' gap closed, procedural / real, first and second model pair:
models trained over white 0.845 / 0.644 / 0.860 / 0.582 → 0.845 / 0.642 / 0.860 / 0.582;
over random backgrounds 0.660 / 0.486 / 0.866 / 0.506 → 0.660 / 0.580 / 0.867 / 0.509
(that armchair 0.72); removals within 0.001 on all eight models.  At 2: 0.842 / 0.635 /
0.866 / 0.579 and 0.658 / 0.576 (first pair); at 1, 0.657 / 0.553."""

CELL_ASCENT = 1.0
""":attr:`SelectOptions.cell_ascent`.  A thin part fills a fraction of its cells, and at a
cell's centre, in empty space beside it, the field's features describe little: the lifted
points the classifier is fitted on all lie on surfaces.  Measured (docs/selection.md), mean
selection IoU colour / removal twins: procedural 0.812 / 0.891 → 0.830 / 0.905, real (17 000
steps) 0.539 / 0.383 → 0.615 / 0.485, real (9 500 steps) 0.588 / 0.405 → 0.714 / 0.411."""


PART_COHERENCE = 0.9
""":attr:`SelectOptions.part_coherence`.  The part head learns each instance's parts from other
instances' part maps; where a category's part vocabulary is shared (procedural chairs: seat,
back, legs, arms …) it recognises the parts of a chair it was never told about, and the
scribbled points' embeddings agree (coherence 0.90–1.00 on the procedural benchmark twins of
two models).  Where parts are whatever a mesh's materials are (real chairs) it often does not
(0.50–0.98; 9 of 32 twins pass),
and reading it there cost a white shell's recolour (selection IoU 0.58 → 0.40).  Measured in
docs/selection.md ("The part head F_part")."""
PART_VETO = 0.5
""":attr:`SelectOptions.part_veto`.  With :data:`PART_JOIN`, on the procedural benchmark twins
(docs/selection.md), recolours' gap closed 0.883 → 0.904 and 0.887 → 0.905 over reading the
head as a feature alone, removals 0.620 → 0.632 and 0.617 → 0.647 (two models)."""
PART_VETO_KEEP = True
""":attr:`SelectOptions.part_veto_keep`.  The head's parts are what its training maps call parts:
a procedural chair's seat, back and legs, a real mesh's materials.  So where the scribbled part
meets another of its colour, the head's veto is right on one kind of chair and wrong on the
other, and a scribble alone cannot tell which is meant: `chair_015`'s seat scribbled, its back
posts (the seat's grey) vetoed, as the twin wants; `scopia_chair4`'s wooden back scribbled, its
wooden legs vetoed, which the twin (the wood recoloured) does not want.  The keep strokes can:
`chair_015`'s keep stroke lies on the back, `scopia_chair4`'s none on the chair.  Measured on
six models (four H200, two CPU; docs/benchmarks.md, fifty-first session), recolours' gap closed,
edit seed 0 / 1: real 0.802 / 0.794 → 0.860 / 0.852, 0.837 / 0.835 → 0.855 / 0.856, 0.629 /
0.641 → 0.707 / 0.698, 0.828 / 0.825 → 0.848 / 0.841 (`scopia_chair4` 0.588 → 1.062 and 0.866
→ 1.035 on the H200 models, `katorlegaz_cafe_chair`'s 12 scribbled points 0.258 → 0.723);
procedural 0.933 / 0.932 → 0.927 / 0.922 and 0.700 / 0.694 → 0.680 / 0.685 (an orange seat
under an orange back, kept strokes on the pedestal only: 0.994 → 0.956 on one model); removals
within 0.01.  The cost: a procedural scribble with no keep stroke gets no veto; without their keep
strokes the colour twins' selection IoU falls 0.917 → 0.868 and 0.859 → 0.817
(`benchmarks/sloppy_scribbles.py --brush nokeep`; real 0.867 → 0.899 and 0.892 → 0.914)."""
PART_JOIN = 0.8
""":attr:`SelectOptions.part_join`.  A part's far side or hidden face that the scribbled view
could not show (a black shell's seat scribbled from behind: recolour 0.36 → 0.80 and
0.41 → 0.93 on two real models).  At 0.7: procedural recolours 0.910 and removals 0.636, real
recolours 0.765 (seed-0 models)."""
PART_JOIN_SURE = 0.97
""":attr:`SelectOptions.part_join_sure` of recolours.  A procedural back frame is a top rail and
two posts.  Scribbled on the rail, the shape gate left the posts out of the head's join as
lines square to the scribble: `chair_023`'s back recoloured at 0.414 / 0.480 selection IoU
(gap closed 0.45 / 0.53) on `g_p0` / `g_p1`, 0.355 (0.41) on a model whose head never saw that
chair's part labels; trusted, 0.917 / 0.935 (0.80 / 0.81) and 0.766 (0.68).  Those heads
put the scribble in one part at coherence 0.97–0.996; `chair_015`'s legs, whose join the head
floods with the stretchers (a legs recolour 0.88 → 0.65 ungated), at 0.93, so the gate still
holds them.  Removals leave it off: on the model whose head never saw the labels, it is sure
(0.971) that `chair_023`'s stretchers and legs are one part, and their removal took the legs
(IoU 0.588 → 0.459, gap closed 0.73 → 0.28, −3.9 dB outside), while its gains were an arm's
posts (`chair_001`, 0.73 → 0.79).  Measured on twins the rules were not tuned on
(``benchmarks/heldout_twins.py``; docs/benchmarks.md, fifty-seventh session): the benchmark's
own twins move by at most 0.003."""
PALE_SATURATION = 0.3
"""The saturation below which :attr:`SelectOptions.pale_union` caps the chromaticity join, and
the default :attr:`SelectOptions.chroma_saturation` (removals never join below it)."""


@dataclass(frozen=True)
class SelectOptions:
    """How scribbles become a selection."""

    features: tuple[str, ...] = FEATURES
    """Feature groups describing a point (from :data:`FEATURE_GROUPS`)."""
    part_head: bool = True
    """Also describe points by the model's part head F_part (the ``part`` group,
    :mod:`crfedit.parts`) when it has one and it sees the scribbled points as one part
    (``part_coherence``)."""
    part_coherence: float = PART_COHERENCE
    """The part head is read only when the scribbled points' unit part embeddings agree: the
    length of their mean, 1 when all are one vector, is at least this (:data:`PART_COHERENCE`)."""
    part_veto: float = PART_VETO
    """When the part head is read: an occupied cell, the scribbled cells aside, whose part
    embedding's cosine with the scribbled points' mean embedding is below this is capped below
    :data:`GROW_LOW` (neither selected nor a removal's skin); 0: no veto."""
    part_veto_keep: bool = PART_VETO_KEEP
    """The veto takes only the cells whose part embedding is at least as near (cosine) some
    keep point's as the scribbled points' mean: the parts the keep strokes mark, wherever the
    head finds them; without a keep stroke on the object, none.  False: every cell below
    ``part_veto`` (:data:`PART_VETO_KEEP`)."""
    part_join: float = PART_JOIN
    """When the part head is read: an occupied cell whose cosine (as ``part_veto``'s) is at
    least this joins the selection where it connects (26-neighbourhood, through such cells and
    selected ones) to a scribbled cell, keep-stroke cells and those a keep stroke wins aside: the
    part's far side, or its hidden face, that the scribbled view could not show; 0: no join."""
    part_join_sure: float = 0.0
    """When > 0 and the part head is at least this sure of the scribbled part (its
    ``coherence``, as :attr:`part_coherence` reads it): :attr:`shape_gate` leaves the head's join
    alone.  The gate stops joins from taking bars square to the scribbled ones (the legs of a
    stretchers' colour); a head that puts every scribbled point in one part knows whether the
    bars square to them are that part (an arm's post under its rail, a back's posts under its
    top rail).  Recolours use :data:`PART_JOIN_SURE`; removals, whose joins remove, do not."""
    part_join_hue: float = 0.0
    """When > 0, and the scribbled points' saturation (as ``chroma_saturation``'s) is at least
    this: the part head's join leaves out the cells whose chromaticity ``veto_chroma`` (with
    ``veto_floor``) calls unlike the scribbled points'.  The head's part may hold another
    material; below the saturation a part's hue is mostly the model's colour noise.  Recolours
    use :data:`COLOR_PART_JOIN_HUE`."""
    position_weight: float = 1.0
    """Scale of the standardized position group against the others."""
    geometry_weight: float = 1.0
    """Scale of the standardized ``geometry`` group (when in ``features``) against the others."""
    shape_from: str = "density"
    """What the ``geometry`` group's :func:`local_shape` weighs a cell by: ``density`` (its
    :func:`cell_opacity`) or ``occupancy`` (the dilated sampling grid)."""
    shape_radius: int = GEOMETRY_RADIUS
    """The ``geometry`` group's block: the (2r+1)³ cells around a point's cell."""
    shape_gate: float = 0.0
    join_lines: float = 0.0
    """When > 0, and at least :data:`~.shapes.JOIN_LINES` of the scribbled points lie on lines
    (:func:`~.shapes.lines_of`: a frame's bars, legs): a chromaticity join (:attr:`chroma_union`)
    that its cap lets through leaves out each connected piece it would add at least this share
    of whose cells are not lines (a seat or panel of the bars' colour).  A scribble on bars
    means bars.  The shape is read from the density (:func:`~.features.cell_opacity`) whether
    or not the ``geometry`` group is.  Recolours and removals use :data:`JOIN_LINES_SHARE`."""
    line_negatives: bool = False
    """When set, and at least :data:`~.shapes.JOIN_LINES` of the scribbled points lie on lines:
    the scribbled views' other surface points whose cells are not lines stay negatives through
    the self-training (:func:`~.classify.classifier`), however much they look like the part.
    Self-training drops the view's points that look like the part, so that the unscribbled rest
    of it does not stay a negative; under a scribble on bars the rest of the part is bars, and a
    slab or block of the bars' colour is another part.  Recolours and removals set it
    (:data:`LINE_NEGATIVES`)."""
    on_bars: tuple = ()
    """Overrides ``((field name, value), …)`` of these options that apply when at least
    :data:`~.shapes.JOIN_LINES` of the scribbled points lie on lines, decided before any
    feature is read (:meth:`on_bars_options`).  A scribble on a frame's bars means bars,
    whatever the edit: recolours then select as removals, which are all scribbled on frames,
    read a frame (:data:`COLOR_ON_BARS`).  (): none."""
    sheet_veto: float = 0.0
    """When > 0 (and the ``geometry`` group is read), and at least this share of the scribbled
    points lie on lines (:func:`lines_of`: a frame's tubes, legs): the cells that lie on sheets
    (:func:`sheets_of`), the scribbled cells aside, are capped below :data:`GROW_LOW`, neither
    selected nor a removal's skin.  A scribble on a tube means the tube, not the seat it
    carries, however alike the two look.  Removals use :data:`REMOVE_SHEET_VETO`."""
    rim_fill: float = 0.0
    """When > 0 (and the ``geometry`` group is read), and at least :data:`RIM_SHEETS` of the
    scribbled points lie on sheets (a panel, not a frame's tubes): the selection also takes the
    occupied cells next to it, keep-stroke cells and those a keep stroke wins aside, that are
    lines lying in the plane of at least this share of those sheet points
    (:func:`rim_lines`): a panel's rims and edges, lit unlike its scribbled faces, which a
    removal otherwise leaves standing as a thin frame.  Removals use :data:`REMOVE_RIM_FILL`."""
    """When > 0 (and the ``geometry`` group is read): of the cells that the chromaticity join
    or the part head's join would add, a connected piece (26-neighbourhood) is left out when
    at least this share of its cells are lines at odds with the scribble
    (:func:`odd_lines`): the legs of a chair whose stretchers, of the legs' colour, are
    scribbled.  A joined piece of another orientation that is no line (a box's top face, or its
    rim lying in the scribbled face) stays.  Removals use :data:`REMOVE_SHAPE_GATE`."""
    self_training: int = 3
    """Rounds that drop from the negatives the view points the classifier calls positive."""
    keep_weight: float = 3.0
    """Weight of a keep-stroke point against one of the view's other surface points."""
    appearance_self_training: bool = True
    """Self-training also drops the view points an appearance-only fit calls positive."""
    appearance_gate: float = 8.0
    """Cells farther in appearance from every positive than this × the positives' spacing are
    not selected (0: no gate)."""
    skin_chroma: float = 2.0
    """Unselected cells whose chromaticity is unlike the scribbled points' (:func:`chroma_alike`
    with this factor) are capped below :data:`GROW_LOW`, so neither a removal's skin nor
    :meth:`Selection.grown` takes a neighbour of another colour, such as the seat under a
    removed cushion (0: no cap; the selection itself never changes)."""
    chroma_union: float = 0.0
    """Also select what chromaticity alone selects — steps 3–6 on the chromaticity group only,
    joined by a cell-wise max — when that selects at most this × as many cells as the full
    features do (0: never).  Recolours and removals use :data:`CHROMA_UNION`
    (:func:`options_for`)."""
    join_chroma: float = JOIN_CHROMA
    """The join takes only cells whose chromaticity lies within this × the scribbled points'
    spread (+ 0.01) of theirs (:func:`chroma_alike`; 0: any cell the chromaticity-only
    selection selects).  See :data:`JOIN_CHROMA`."""
    chroma_saturation: float = PALE_SATURATION
    """Nor does it join (nor run) unless the scribbled points' median chromaticity has at least
    this HSV saturation (max − min) / max, a colour's, which shading does not change: the
    chromaticity of a near-grey part is mostly the model's colour noise.  Measured on the
    colour twins: a white chair 0.07 (joining cost its recolour 1.6 dB outside the part), the
    tests' weakly trained beige seat 0.24 (joining tinted the other parts 7 levels more),
    procedural parts 0.22–0.26 (joining changed their gap closed by < 0.03) and 0.70, real
    wooden and orange parts 0.49–0.82.  Was 0.4; on the 16-twin benchmark (``--twin-sources
    8``, retrained models) the scribbled parts lie at 0.01–0.28 or 0.35–0.92, and 0.3 joins
    for five more twins: real recolours 0.562 → 0.655 of the gap (edit seed 1: 0.580 →
    0.657; a pink shell 0.24 stays below, its recolour 0.25), procedural 0.615 → 0.619,
    removals 0.479 → 0.550 (procedural) and 0.644 → 0.624 (real); 0.2 flooded a procedural
    back (recolours 0.511).  Recolours join at every saturation (0): their chromaticity
    vetoes keep other hues out (:data:`COLOR_VETO_CHROMA`)."""
    pale_union: float = 0.0
    """When > 0, a part less saturated than ``pale_saturation`` (and at least
    ``chroma_saturation``) joins only when the chromaticity-only selection holds at most this ×
    the full features' cells, not ``chroma_union`` ×: its chromaticity is nearer the model's
    colour noise and the hue of the chair's other parts (0: ``chroma_union`` at any
    saturation, every kind's default).  Recolours used 2.0 until their chromaticity vetoes
    (:data:`COLOR_VETO_CHROMA`): a procedural back of saturation 0.25 whose arms share its
    brown held 2.18 × the full features' cells and took the arms (gap closed 0.75 → −0.06 at
    :data:`CHROMA_UNION`).  With the vetoes the cap at 2.0 only held back what should join
    (a pink café shell's shadowed outside, a dark armchair shell's other side: real
    recolours 0.845 / 0.752 → 0.845 / 0.832); at 2.25, 2.5 and 3 as without it."""
    pale_saturation: float = PALE_SATURATION
    """See ``pale_union``."""
    smooth: bool = True
    """Blend each cell's value half-and-half with its occupied 3×3×3 neighbourhood's mean."""
    smooth_bandwidth: float = 0.0
    """When > 0 the neighbourhood mean is bilateral (:func:`bilateral_smooth`): a neighbour
    weighs exp(−d²/2h²), d its distance in standardized appearance from the cell, h this, so
    the values of a part do not average across into a different-looking part it touches.
    0: the plain mean (:func:`smooth_over_occupied`)."""
    smooth_rounds: int = 2
    """Rounds of the bilateral blend (the plain mean blends once)."""
    connected: bool = True
    """Keep only selected cells connected to a scribbled cell."""
    free_pieces: float = 0.0
    """With :attr:`connected`: a piece of the classifier's selection (after smoothing) that no
    scribbled cell reaches is kept too when it holds at least this share of the cells the
    scribbles reach; 0 keeps none.  A part in pieces that touch only through other parts (the
    bar along the top of a slung back) is one part to the classifier and several to the
    connectivity test; a stray fragment beside the part (a leg's stub between stretchers of
    its colour) is small.  Only the features' selection reads it, not
    the chromaticity join's."""
    threshold: float = 0.5
    """A cell is selected when its value is at least this; it also decides which cells seed
    the connectivity test and the chromaticity join's counts."""
    select_threshold: float | None = None
    """When set, the selection selects at this value instead (its ``threshold``), after the
    refinement above: recolours use :data:`COLOR_THRESHOLD`."""
    band_chroma: float = 0.5
    """A cell selected only through a lower ``select_threshold`` (its value below
    ``threshold``) must also have the scribbled points' chromaticity (:func:`chroma_alike`
    with this factor, stricter than ``skin_chroma``); others are capped below it (0: no test).
    Nor does the lower threshold apply to a near-grey part (``chroma_saturation``, as for the
    join): the selection then selects at ``threshold``."""
    min_opacity: float = MIN_OPACITY
    """A pixel counts as on the object when its rendered opacity is at least this."""
    stroke_centres: bool = False
    """Lift each scribble's centre only: its 1-px erosion, where that keeps at least
    :data:`CENTRE_SHARE` of the scribbled surface points (:func:`.pipeline._stroke_centres`);
    each view's keep strokes the same way.  A brush wider than a thin part strays onto the
    parts beside it and the background, and a few positives on a neighbouring part pull the
    classifier there; a keep stroke drawn up to the part's edge strays onto the part, and
    negatives on it cut the part in two.  The user aims the stroke's centre.  Every edit kind
    uses it (:data:`STROKE_CENTRES`); off, as here by default, every scribbled and kept pixel is
    lifted."""
    stroke_snap: float = 0.0
    """Snap a view's scribble onto the object when less than this share of its pixels show the
    object (0: never): the on-object pixels next to its off-object pixels, and not kept, are
    scribbled too (:func:`.pipeline._snapped_strokes`), before :attr:`stroke_centres`.  A
    stroke aimed a pixel beside a 1-px tube lies on the background, which is not lifted, and
    leaves the selection a point or two to grow from.  Recolours and removals use it
    (:data:`STROKE_SNAP`)."""
    keep_strays: float = 0.0
    """When > 0, a view's scribbled points whose colour looks like its keep strokes' and not
    like the rest of the scribble are left out (:func:`.pipeline._strays`; this is its ratio):
    a stroke drawn up to a part's edge strays onto the neighbour the user kept, and a few
    positives there pull the classifier onto it.  The scribble's centres
    (:attr:`stroke_centres`) cannot tell them apart where the strokes are one or two pixels
    wide.  Recolours and removals use it (:data:`KEEP_STRAYS`)."""
    cell_ascent: float = CELL_ASCENT
    """A cell is described at its centre moved this many half cells up the density gradient,
    where the density is higher there (:func:`denser_points`; 0: at the centre)."""
    veto_chroma: float = 0.0
    """When > 0, each cell of value ≥ :data:`GROW_LOW`, the scribbled cells aside, whose
    chromaticity lies farther from the scribbled points' median than this × their spread +
    ``veto_floor`` (:func:`chroma_alike`) is capped below :data:`GROW_LOW`: neither
    selected nor taken into a removal's skin.  Only for a saturated part
    (``chroma_saturation``, as for the join).  Removals use :data:`REMOVE_VETO_CHROMA`,
    recolours :data:`COLOR_VETO_CHROMA`."""
    veto_floor: float = VETO_FLOOR
    """See ``veto_chroma``; recolours use :data:`COLOR_VETO_FLOOR`."""
    pale_veto: float = 0.0
    """``veto_chroma`` for a near-grey part (saturation below ``pale_veto_saturation``), with
    this factor and ``pale_veto_floor``: a grey material has no hue, so a cell of a clear hue
    is another part (0: off; recolours use :data:`COLOR_PALE_VETO`)."""
    pale_veto_floor: float = 0.02
    """See ``pale_veto``."""
    pale_veto_saturation: float = 0.2
    """See ``pale_veto``."""
    chroma_offset: float = CHROMA_OFFSET
    """The ``chroma`` feature is rgb / (r + g + b + this): the offset keeps a black point's
    chromaticity finite but pulls a shaded point's towards 0 (recolours use
    :data:`COLOR_CHROMA_OFFSET`)."""
    keep_ratio: float = 0.0
    """When > 0, a keep stroke wins near it: a cell whose nearest keep-stroke point is nearer
    than this × its nearest positive, in the standardized appearance and position
    (:data:`KEEP_GROUPS`, :func:`keep_wins`), scores 0 before the refinement, in the full
    features' selection and in the chromaticity join alike.  The classifier is one hyperplane:
    a keep stroke on a part that looks like the scribbled one (legs the colour of the
    stretchers scribbled) cannot pull that part to its side, and the stroke went unheeded.
    Recolours and removals use :data:`COLOR_KEEP_RATIO` and :data:`REMOVE_KEEP_RATIO` (0: off,
    the default and additions')."""
    keep_position_weight: float = 1.0
    """Position's weight in :attr:`keep_ratio`'s distance, relative to its weight in the
    classifier (:attr:`position_weight`); recolours use :data:`COLOR_KEEP_POSITION_WEIGHT`."""
    mirror: str = "off"
    """Mirror symmetry (:mod:`.symmetry`), for an instance whose occupancy grid has a mirror
    plane: ``views`` — each scribbled view's mirror image (the camera reflected, the strokes
    flipped left–right) lends its strokes as a second, virtual view; ``values`` — the finished
    selection also takes its own mirror image (cell-wise max, keep-stroke cells aside);
    ``off``.  Either way nothing is mirrored when the keep strokes cover the scribble's mirror
    image (:data:`.symmetry.CONFLICT`: the user means one side).  Removals use
    :data:`REMOVE_MIRROR`, recolours :data:`COLOR_MIRROR`."""
    fill_share: float = 0.0
    """When > 0, the selection finally also takes each occupied cell, keep-stroke cells aside,
    at least this share of whose occupied 3×3×3 neighbourhood (itself included) it selects
    (:func:`fill_rims`); recolours use :data:`COLOR_FILL_SHARE`, removals :data:`REMOVE_FILL_SHARE`."""

    def on_bars_options(self) -> "SelectOptions":
        """These options with :attr:`on_bars`'s overrides applied (and none left to apply)."""
        try:
            return dataclasses.replace(self, on_bars=(), **dict(self.on_bars))
        except TypeError as e:  # a name that is not a field
            raise CrfError(f"selection on_bars {self.on_bars!r}: {e}") from None


CHROMA_UNION = 4.5
"""Recolours' and removals' :attr:`SelectOptions.chroma_union`.  The full features miss parts
of one material that look different elsewhere: a wooden frame's legs when its back is
scribbled, a lit top face.  Chromaticity alone takes them (a Lambertian shading factor cancels in it) but on its own
floods parts of a shared hue.  Before the saturation test existed, the 8 colour twins' selections held
0.7–1.9× the full features' cells on 7 and 3.7× on one (a near-grey back, IoU 0.36 against the
full features' 0.82).  With the test, the saturated parts of the benchmark twins (colour and
removal, four models) hold 0.51–1.99×, and 2.19–2.68× for a wooden frame scribbled on its back,
whose legs the join rightly adds (IoU 0.59 → 0.93, gap closed 0.48 → 1.00 on the 17 000-step
real model; at 2.5 it was refused there).  It was 3.5, below the one flood measured (that
near-grey back, before the saturation test).  At 4.5 since the fifty-sixth session: on
`c_r2` the dark blue shell of `scopia_armchair2` (saturation 0.34), scribbled on its back,
joins its sides at 3.9× (selection IoU 0.48 → 0.92, gap closed 0.24 → 0.76), and no other of the
158 selections of the benchmark's colour, frame, legs and removal twins on the six models
moves (the next refused join, `chair_009`'s orange frame on `g_p0`, lies at 4.9×, where
joining costs 0.011 of IoU).  One twin is thin evidence, so pale parts, whose chromaticity
lies nearer the colour noise and where the 3.7× flood was, keep 3.5 (:data:`COLOR_PALE_UNION`;
removals do not join below saturation 0.3)."""
COLOR_PALE_UNION = 3.5
"""A recolour's :attr:`SelectOptions.pale_union` (below :data:`PALE_SATURATION`): the cap
:data:`CHROMA_UNION` had before the fifty-sixth session."""
JOIN_LINES_SHARE = 0.5
"""Recolours' and removals' :attr:`SelectOptions.join_lines`: a piece the join would add is left
out once half its cells are not lines.  `chair_009`'s orange back frame, scribbled on its bars
(two thirds of the scribbled points lie on lines), joined the orange seat on `g_p1`: 8 662
cells by chromaticity, 2.6× the features' 3 347, under the cap.  The seat's 5 306 cells are
not lines; with them left out the recolour's selection IoU went 0.331 → 0.618 and its gap closed
−0.99 → 0.36.  The 46 removal twins of the six benchmark models, whose scribbles lie on legs
and frames, selected with the recolour's options: mean IoU per model unchanged to ±0.001 (each
twin within 0.008); with a removal's: +0.000 to +0.003 (the pale plastic chair's frame +0.013 to
+0.035, a piece of its seat left out of the join).  Removals' gap closed on the real models
0.887 / 0.872 / 0.852 / 0.904 → 0.926 / 0.868 / 0.853 / 0.900 (docs/benchmarks.md, fifty-fourth
session)."""
LINE_NEGATIVES = True
"""Recolours' and removals' :attr:`SelectOptions.line_negatives`.  `chair_009`'s orange back
frame, scribbled on its bars over an orange seat: the seat's points in the scribbled view looked
like the frame, self-training dropped them from the negatives, and the features took a quarter
of the seat (selection IoU 0.618 on `g_p1` after :data:`JOIN_LINES_SHARE`).  Held as negatives,
0.814, and the recolour's gap closed 0.36 → 0.83 (`g_p0`: 0.843 → 0.860).  Hybrid, seed 0,
recolours' gap closed `g_p0` 0.925 → 0.927, `g_p1` 0.849 → 0.908; removals 0.871 / 0.889 (procedural)
and 0.926 / 0.868 / 0.853 / 0.900 (real) → 0.875 / 0.889 and 0.911 / 0.876 / 0.875 / 0.930
(docs/benchmarks.md, fifty-fourth session)."""
COLOR_SATURATION = 0.2
"""A recolour's :attr:`SelectOptions.pale_veto_saturation`: below it the pale veto
(:data:`COLOR_PALE_VETO`) runs too.  Until the vetoes (2026-11-26) it was a recolour's
:attr:`SelectOptions.chroma_saturation`: the chromaticity join and lower cut
(:data:`COLOR_THRESHOLD`) ran for parts from this saturation, joining at most 2 × the full
features' cells below :data:`PALE_SATURATION`; now they run at every saturation.  A pink shell
(0.24–0.26), scribbled on its lit inside, had its shadowed outside left out: the full
features' classifier leans on the predicted colour, and the view's unscribbled shadowed
inside stayed a negative.  Measured on the 16-twin benchmark over the four model pairs
(white-trained and random-background, procedural / real, training seeds 0 and 1;
docs/benchmarks.md), recolours' gap closed, white 0.845 / 0.642 / 0.860 / 0.582 → 0.860 /
0.695 / 0.862 / 0.633, random background 0.660 / 0.580 / 0.867 / 0.509 → 0.664 / 0.651 /
0.884 / 0.578 (the shell 0.31 / 0.40 / 0.31 / 0.31 → 0.74 / 0.81 / 0.87 / 0.87); no twin lost
more than 0.02.  The cut sits between the black and white shells (≤ 0.14) and the palest
procedural back (0.21).  Only the join: 0.727 and 0.690 mean; only the lower cut:
0.746 and 0.666.  Removals keep 0.3: at 0.2 (join capped as here) their gap closed moved
0.620 → 0.624 and 0.758 → 0.767, four twins up and three down by 0.03–0.13."""
EDIT_KINDS = ("color", "remove", "add")
"""What a selection can be made for (:func:`options_for`)."""


COLOR_THRESHOLD = GROW_LOW
"""A recolour's selection of a saturated part takes cells of value ≥ 0.3, not 0.5, when their
chromaticity is the scribbled points' (:attr:`SelectOptions.band_chroma`).  The classifier is
fitted against the view's other surface points, which still hold some unscribbled part, so
the part far from the scribble can score between 0.3 and 0.5 (a café chair's seat slats under
its scribbled backrest's: gap closed 0.15 → 0.76).  Measured (docs/selection.md), recolours'
gap closed: procedural 0.749 → 0.748, real 0.435 → 0.586 (previous real twins 0.701 → 0.694),
outside the part unchanged.  Without the saturation and chromaticity tests: 0.793, 0.714,
0.736, but the rest of the tests' weakly trained chair moved 0.43× as much as the part
(0.17× at 0.5).  Removals stay at 0.5: thin frames bled into their seats at 0.3 (real IoU
0.39 → 0.29)."""


COLOR_APPEARANCE_GATE = 6.0
"""A recolour's :attr:`SelectOptions.appearance_gate` (8 for the others).  The chromaticity
join of a saturated part reaches a neighbour of its colour the scribble did not mean: a
procedural back took the seat of the same orange (recolour −1.05, outside 22.8 dB).  A
tighter gate keeps such a neighbour, lit otherwise and unlike the scribbled points in its
bottleneck features, out.  Measured on the 16-twin benchmark over two model pairs (procedural /
real, training seeds 0 and 1; docs/benchmarks.md), recolours' gap closed: 0.619 / 0.655 /
0.847 / 0.451 → 0.847 / 0.634 / 0.856 / 0.528 (that back 0.76, outside 32.5 dB); edit seed
1: 0.615 / 0.657 / 0.828 / 0.450 → 0.846 / 0.632 / 0.856 / 0.524.  At 4: 0.858 / 0.623 /
0.863 / 0.540; at 5: 0.851 / 0.620 / 0.859 / 0.532; at 7: 0.854 / 0.631 / 0.858 / 0.450."""

COLOR_FILL_SHARE = 0.4
"""A recolour's :attr:`SelectOptions.fill_share`.  The rims of a selected slab (its top and
side faces, lit unlike the scribbled front) score low although the occupied cells around them
are the slab: half of a free rim cell's occupied neighbourhood is selected.  A part lying
face-on against the selection has a third of its touching cells' neighbourhood selected, so
any share above a third leaves it out.  Measured (docs/selection.md), recolours' gap closed:
procedural 0.783 → 0.811 (`chair_006`'s back 0.53 → 0.63), real 0.509 → 0.512, outside the
part unchanged; at 0.3 (which takes a touching part's first layer), 0.826 and 0.510 with 0.14
dB lost outside on the procedural chairs; at 0.5, 0.791 and 0.521.  Removals fill at
:data:`REMOVE_FILL_SHARE`."""

REMOVE_FILL_SHARE = 0.5
"""A removal's :attr:`SelectOptions.fill_share`.  A boxy armrest's edges score low (their
cells are half empty, their look the panel's edge) and stayed standing as a frame around the
removed panel.  Measured on ``p63`` / ``r63`` (hybrid, seed 0, docs/benchmarks.md, sixty-eighth
session): selection IoU 0.893 / 0.737 → 0.908 / 0.756, up on all fifteen removal twins
(`chair_018`'s arms 0.781 → 0.843), gap closed 0.836 / 0.973 → 0.848 / 0.979, outside the
part −0.01 / −0.03 dB; the quickstart model's removal 0.674 → 0.704 (IoU 0.880 → 0.917).  At
0.4: 0.913 / 0.749 IoU but 0.863 / 0.961 gap and 0.14 / 0.30 dB lost outside (the lower share
takes a touching part's first layer); at 0.6: 0.900 / 0.751, 0.829 / 0.963.  Measured in an
earlier pipeline (before the vetoes and the keep strokes' win), filling had cost the real
removals 0.11 of the gap (a café chair's aluminium frame took the seat slats it touches); that
chair now gains 0.006."""

REMOVE_FEATURES = (*FEATURES, "fuse", "geometry")
"""A removal's :attr:`SelectOptions.features`: the default groups plus F_fuse's activations,
what the density head reads (and what a removal retrains).  A dark-grey tube frame and the
black shell it carries have nearly one predicted colour (0.17 against 0.11) and bottleneck;
with the 8-d bottleneck alone the classifier took a third of the shell's seat with the frame
and the removal emptied all of it.  Measured (docs/selection.md), removals' gap closed:
procedural 0.776 → 0.777, real (17 000 steps) 0.484 → 0.563 (the armchair's frame −0.56 →
−0.20), the weaker models 0.288 → 0.308 (procedural, 2 948 steps) and 0.220 → 0.280 (real,
9 500 steps).  Recolours keep :data:`FEATURES`: with F_fuse the procedural recolours fell
0.811 → 0.739 and the real ones 0.641 → 0.619.  And the grid's local shape
(:func:`local_shape`, weighted :data:`REMOVE_GEOMETRY_WEIGHT`): a frame's tube is a line of
cells, the seat it carries a sheet, the two alike in colour and features."""

REMOVE_GEOMETRY_WEIGHT = 2.0
"""A removal's :attr:`SelectOptions.geometry_weight`, with the shape read from the density
(:func:`cell_opacity`) and its orientation (:func:`local_shape`).  Measured on the 16-twin
benchmark (hybrid, gap closed, one view, the 17 000-step models of docs/benchmarks.md, seed 0
/ seed 1), with :data:`REMOVE_SHAPE_GATE`: procedural removals 0.631 / 0.652 → 0.812 / 0.820
(`chair_015`'s stretchers −0.46 / −0.33 → 0.93 / 0.95), real 0.799 / 0.776 → 0.885 / 0.820;
at weight 1 (the block 5³): 0.807 / 0.758 and 0.875 / 0.873; at 0.5 (seed 0) 0.631 and
0.813, `chair_015` still below unedited.  Read from the occupancy grid instead (weight 2, the
gate): 0.623 and 0.791 (seed 0): the grid is dilated for sampling, so a two-cell leg reads as
a solid (sphericity 0.8–0.9) and its orientation is lost."""
REMOVE_SHAPE_GATE = 0.3
"""A removal's :attr:`SelectOptions.shape_gate`.  Without it the weighted shape alone does not
save `chair_015` (0.365 selection IoU): the chromaticity join floods the legs of the
stretchers' colour.  Per-cell gates (each odd cell left out) kept the legs out too but
broke a box's rims and faces out of the joins (`chair_021`'s arms 0.78 → 0.42–0.66); the gate
by pieces keeps them (0.77).  Also measured, not adopted: joining what a second classifier
with the shape weighted 0.25 or 0.5 selects, through the same gate: procedural removals
+0.01 (and `chair_000` on a model without the part head 0.42 → 0.73), real −0.01 to −0.08."""
REMOVE_SHEET_VETO = 0.5
"""A removal's :attr:`SelectOptions.sheet_veto`: the veto runs once at least half the scribbled
points lie on lines.  `scopia_plastic_chair` is a pale tube frame under a pale seat, scribbled on a leg
and on the bar under the seat's edge.  On the thirty-first session's seed-1 model the
classifier took the seat with the frame (3 651 of 5 500 cells; gap closed 0.17, −9.1 dB
outside), and the veto from a line share of 0.7 made it 0.65; that model read 88 % of the
scribbled points as lines.  The H200 model `g_r0` reads 57 %: at 0.7 the seat's speckles went
with the frame (gap 0.44, −4.9 dB outside), at 0.5 the gap is 0.61 (−3.3 dB).

Measured on the 16-twin benchmark (hybrid removals, gap closed, one view):
* at 0.7, over no veto (the thirty-first session's models, seed 0 / seed 1): real
  0.882 / 0.842 → 0.895 / 0.912, procedural 0.822 / 0.837 → 0.827 / 0.833, real selection IoU
  0.735 / 0.699 → 0.736 / 0.716; at 0.8 real 0.885 / 0.904;
* from 0.7 to 0.5 (the fiftieth session's four H200 models, edits' seeds 0 and 1): `g_r0`
  0.858 → 0.885 and 0.864 → 0.886 (outside −0.63 → −0.42 dB, IoU 0.722 → 0.730), `g_r1`
  0.868 → 0.870 and 0.881 → 0.879, procedural identical; two fresh 17 000-step CPU models of
  the real chairs 0.854 → 0.854 and 0.910 → 0.904.  0.4 gives what 0.5 gives; 0.6 leaves the
  plastic chair as it was.
The real removals' scribbles read 0.57–1.0 of lines, the procedural ones 0–0.05 or
0.75–0.94.  Removals made from the colour twins' scribbles (a back's frame among them, at 0.70)
reach the same selection IoU at 0.5 as at 0.7."""
REMOVE_FREE_PIECES = 0.04
"""A removal's :attr:`SelectOptions.free_pieces`.  Measured on the six benchmark models
(selection IoU on held-out views, one view's scribbles; docs/selection.md, fifty-sixth
session): real removals 0.732 / 0.714 / 0.715 / 0.730 → 0.753 / 0.714 / 0.734 / 0.777 (the
modern armchair's top bar: 0.71 → 0.88 on `g_r0`), the procedural ones unchanged (0.916 /
0.915).  Keeping every piece cost `chair_015`'s stretchers 0.04 for leg stubs of their
colour, 2–3 % of the selection each; the bar holds 9–10 % of it where it is one piece (on
`g_r1` it is in pieces of 1–2 % and stays out).  On the recolours it moved nothing or
±0.005, so they leave it off."""
REMOVE_RIM_FILL = 0.5
"""A removal's :attr:`SelectOptions.rim_fill`.  Measured (hybrid, gap closed, one view, the
17 000-step models, seed 0 / seed 1): procedural removals 0.812 / 0.820 → 0.823 / 0.830 and
their selection IoU 0.894 / 0.899 → 0.907 / 0.906 (`chair_018`'s arm panels 0.54 / 0.47 →
0.58 / 0.53), the model without the part head 0.732 → 0.765; real removals unchanged (0.885 /
0.820, 0.915 without the head: their scribbled parts are tubes, so it does not run).  At 0.3
and 0.7 the same within 0.001.  Filling every ring cell whose orientation agrees with the
scribble, sheets too, took real removals to 0.790 / 0.771."""
REMOVE_POSITION_WEIGHT = 0.5
"""A removal's :attr:`SelectOptions.position_weight`.  Measured on the 16-twin benchmark
(``--twin-sources 8``; docs/selection.md, hybrid, gap closed, edit seeds 0 / 1, retrained
17 000-step models): real removals 0.542 / 0.547 → 0.644 / 0.642 (`katorlegaz_cafe_chair`
0.35 → 0.89: the quadratic position terms took a band of its back with the frame), procedural
0.481 / 0.479 → 0.479 / 0.477 (outside the part −0.4 dB; `chair_000`'s arms 0.40 → 0.30);
0.75: 0.582 and 0.481; 0.25: 0.655 and 0.479."""

REMOVE_VETO_CHROMA = 1.5
"""A removal's :attr:`SelectOptions.veto_chroma`.  The classifier scores small parts touching
the target above the target itself when they share its bottleneck features (a desk chair's
casters 0.98–0.99 against its legs' 0.91), and the removal empties them; yet a caster is
brown and the legs are violet-grey.  Measured (docs/selection.md), removals'
gap closed: procedural 0.778 → 0.780, real (17 000 steps) 0.216 → 0.420 (the desk chair 0.03
→ 0.83), real (9 500 steps) −0.080 → 0.072; factor 1.5–3 with floor 0.05–0.12 within 0.04 of
these on the 17 000-step models.  Recolours select no differently (their lower cut already tests the chromaticity).
Was 2.0; 1.5 on the 16-twin benchmark over two model pairs (procedural / real, training seeds
0 and 1, edit seed 0): 0.550 / 0.624 / 0.475 / 0.565 → 0.550 / 0.630 / 0.477 / 0.630 (the
desk chair on the seed-1 model 0.07 → 0.56); edit seed 1: 0.549 / 0.622 / 0.476 / 0.570 →
0.548 / 0.625 / 0.479 / 0.624; 1.25 and 1.0 gained more on one model and lost on another."""
REMOVE_PALE_VETO = 1.0
"""A removal's :attr:`SelectOptions.pale_veto` (floor 0.02), below the saturation its
chromaticity veto starts at (0.3), so a removal vetoes unlike hues beside a part of any
saturation.  Measured as :data:`COLOR_VETO_CHROMA`, removals' gap closed 0.823 / 0.830 / 0.885
/ 0.820 → 0.822 / 0.837 / 0.882 / 0.842 (the real armchair's grey tube frame on the seed-1
model 0.22 → 0.45); the removals' own veto at floor 0.05 instead of 0.08: 0.821 / 0.829 /
0.880 / 0.817."""
KEEP_GROUPS = ("bottleneck", "color", "chroma", "position")
"""The feature groups of :attr:`SelectOptions.keep_ratio`'s distance: appearance and position
(not F_fuse's activations nor the grid's local shape, which removals' classifier also reads)."""
REMOVE_KEEP_RATIO = 1.0
"""A removal's :attr:`SelectOptions.keep_ratio`: a cell nearer a keep-stroke point than every
positive is not selected.  Measured on the 16-twin benchmark over two model pairs
(procedural / real, training seeds 0 and 1; docs/benchmarks.md), removals' gap closed: 0.550
/ 0.630 / 0.477 / 0.630 → 0.563 / 0.671 / 0.487 / 0.657 (edit seed 1: 0.548 / 0.625 / 0.479 /
0.624 → 0.557 / 0.672 / 0.476 / 0.657); after two simulated corrections from other views
(``benchmarks/correction.py``) 0.612 / 0.748 / 0.549 / 0.714 → 0.682 / 0.832 / 0.675 / 0.818.
At 0.7: 0.550 / 0.657 / 0.478 / 0.653; 1.3: 0.558 / 0.642 / 0.464 / 0.625; position at half
or twice the weight: 0.549 / 0.682 / 0.474 / 0.665 and 0.559 / 0.667 / 0.486 / 0.653."""
COLOR_KEEP_RATIO = 0.7
"""A recolour's :attr:`SelectOptions.keep_ratio`, with position at
:data:`COLOR_KEEP_POSITION_WEIGHT`: the keep stroke wins only where it is clearly nearer,
closer to where it was drawn.  Measured as :data:`REMOVE_KEEP_RATIO`, recolours' gap closed
from one view 0.847 / 0.634 / 0.856 / 0.528 → 0.846 / 0.628 / 0.860 / 0.527 (edit seed 1:
0.846 / 0.632 / 0.856 / 0.524 → 0.845 / 0.628 / 0.859 / 0.529), after two corrections 0.795 /
0.714 / 0.851 / 0.656 → 0.886 / 0.720 / 0.888 / 0.668 (`chair_015`'s recolour, whose first
correction took its legs: 0.89 → 0.30 before, 0.88 → 0.73 now, 0.90 after the second).  As
the removals' (1.0, position at 1): 0.839 /
0.585 / 0.858 / 0.524 from one view (`scopia_armchair2` 0.56 → 0.21); 0.5: 0.841 / 0.641 /
0.859 / 0.528."""
COLOR_KEEP_POSITION_WEIGHT = 2.0
""":data:`COLOR_KEEP_RATIO`'s :attr:`SelectOptions.keep_position_weight`."""
REMOVE_MIRROR = "views"
"""A removal's :attr:`SelectOptions.mirror`: the scribbled view's mirror image lends its
strokes, so the far arm or the far legs a view hides are labelled as the near ones are.
Measured on the 16-twin benchmark over two model pairs (procedural / real, training seeds 0
and 1; docs/selection.md, step 11), removals' gap closed: 0.563 / 0.671 / 0.487 / 0.657 →
0.580 / 0.713 / 0.471 / 0.718 (edit seed 1: 0.557 / 0.672 / 0.476 / 0.657 → 0.578 / 0.712 /
0.468 / 0.715); ``values``: 0.566 / 0.699 / 0.473 / 0.654 (cell-wise max) and 0.562 / 0.718
/ 0.486 / 0.676 (mean).  The one loss: a grey armrest lit brighter on the far side brought
a light seat into `chair_018`'s selection on one model (0.42 → 0.17)."""
COLOR_MIRROR = "values"
"""A recolour's :attr:`SelectOptions.mirror`: the selection takes its own mirror image.
Measured as :data:`REMOVE_MIRROR`, recolours' gap closed: 0.846 / 0.628 / 0.860 / 0.527 →
0.845 / 0.644 / 0.860 / 0.582 (edit seed 1: 0.845 / 0.628 / 0.859 / 0.529 → 0.843 / 0.646
/ 0.844 / 0.586), outside the part 31.35 → 31.32 dB on the first procedural model; ``views``
lost: 0.859 / 0.553 / 0.862 / 0.528 (the real `armchair` 0.63 → 0.24, measured without the
mirrored view's other surface points).  A recolour's classifier leans on the predicted
colour, and the mirrored view brings the far side's other lighting into its positives."""


COLOR_CHROMA_OFFSET = 0.01
"""A recolour's :attr:`SelectOptions.chroma_offset`.  At 0.05 a shell's shaded underside
(rgb 0.36 / 0.28 / 0.28, chromaticity 0.373 / 0.285 / 0.292) was no longer the scribbled lit
inside's chromaticity (rgb 0.84 / 0.64 / 0.66, 0.383 / 0.292 / 0.301) to the classifiers: the
unscribbled, shaded inside stayed a negative through self-training and both classifiers drew
their line between bright and dark pink (the underside's cells 0.03 and 0.15).  Measured on
the 16-twin benchmark (hybrid, one view, procedural / real models, training seeds 0 and 1;
docs/benchmarks.md), recolours' selection IoU 0.908 / 0.904 / 0.897 / 0.887 → 0.909 / 0.905
/ 0.919 / 0.899 (the café chair's shell 0.86 → 0.98), gap closed 0.906 / 0.908 / 0.845 /
0.832 → 0.900 / 0.900 / 0.867 / 0.834, with the edits' seed 1 0.895 / 0.905 / 0.834 / 0.827
→ 0.903 / 0.902 / 0.865 / 0.840; 0.02: 0.905 / 0.895 / 0.864 / 0.832.  Removals keep 0.05:
at 0.01 their gap closed 0.827 / 0.833 / 0.895 / 0.912 → 0.825 / 0.829 / 0.902 / 0.891."""
COLOR_VETO_CHROMA = 1.0
"""A recolour's :attr:`SelectOptions.veto_chroma`, with :data:`COLOR_VETO_FLOOR`, at every
saturation (a recolour's ``chroma_saturation`` is 0; a near-grey part also gets
:data:`COLOR_PALE_VETO`).  A dark blue armchair shell scribbled on its back took the light
grey cushions inside it, lit alike in the bottleneck features (chromaticity distance from the
scribbled points: shell 0.017–0.024, cushions 0.076–0.079; the removals' floor 0.08 let them
through).  Measured on the 16-twin benchmark (hybrid, one view, the 17 000-step models,
procedural / real, training seeds 0 and 1; docs/benchmarks.md), recolours' gap closed:

- before: 0.904 / 0.906 / 0.790 / 0.673;
- this veto for saturated parts only (the join and lower cut from 0.2 as before): 0.906 /
  0.908 / 0.803 / 0.717;
- with the join and lower cut at every saturation and the pale veto: 0.906 / 0.908 / 0.845 /
  0.752 (the shell 0.68 / −0.10 → 0.78 / 0.26; outside the part 29.93 / 29.24 → 30.75 /
  30.39 dB on the real models);
- and no pale cap on the join (``pale_union`` 0, the default): 0.906 / 0.908 / 0.845 / 0.832
  (the shell on the seed-1 model 0.64, the café chair's pink shell 0.53 → 0.79).

Factor 1.5: 0.908 / 0.907 / 0.846 / 0.739; floor 0.05: 0.900 / 0.904 / 0.839 / 0.724; one
veto at floor 0.03 for every saturation without the pale one: 0.901 / 0.900 / 0.835 / 0.751;
at floor 0.02: 0.901 / 0.900 / 0.843 / 0.744 (all with the cap)."""
COLOR_VETO_FLOOR = 0.03
""":data:`COLOR_VETO_CHROMA`'s :attr:`SelectOptions.veto_floor`.  It takes a few cells at a
part's shading edges too: a brown procedural back (saturation 0.23) 0.85 → 0.79 with the
edits' seed 1 (0.82 → 0.85 at seed 0), the same selection IoU.  At 0.04: 0.901 / 0.908 /
0.843 / 0.818 at seed 0 (the blue shell 0.53 on the seed-1 real model), 0.898 / 0.902 on the
procedural models at seed 1, against 0.895 / 0.905 here."""

COLOR_PART_JOIN_HUE = PALE_SATURATION
"""A recolour's :attr:`SelectOptions.part_join_hue`.  `scopia_chair4`'s wooden back scribbled
(saturation 0.69): on one model the part head saw its teal seat cushion as the back's part
and joined it, 2 954 cells the hue veto had just left out (gap closed 0.747, −5.22 dB outside
the part; with the test 1.073, +1.61 dB).  Measured on six models (docs/benchmarks.md,
fifty-first session), recolours' gap closed, edit seeds 0 / 1: real 0.860 / 0.852 → 0.860 /
0.852, 0.855 / 0.856 → 0.854 / 0.851, 0.707 / 0.698 → 0.750 / 0.754, 0.848 / 0.841 → 0.847 /
0.843 (a folding chair's seat, its tubes no longer joined: selection IoU 0.927 → 0.986);
procedural 0.927 / 0.922 → 0.925 / 0.922, 0.680 / 0.685 → 0.680 / 0.683.  At every
saturation (and the pale veto's cells too) it cost a black shell scribbled from behind the
hidden seat the head had joined (0.907 → 0.775), and removals 0.022 on one model: removals
keep 0."""
COLOR_PALE_VETO = 1.0
"""A recolour's :attr:`SelectOptions.pale_veto` (floor 0.02, below :data:`COLOR_SATURATION`).
A white shell's selection took blotches of the beige seat cushion it holds (chromaticity
distance 0.05 against the shell's 0.017), and the recolour darkened them.  Measured as
:data:`COLOR_VETO_CHROMA`, with the join and the lower cut at every saturation: real
recolours' gap closed 0.790 / 0.673 → 0.833 / 0.707 (the shell 0.31 / 0.39 → 0.63 / 0.70),
procedural unchanged (their scribbled parts are saturated); the pale veto alone, the join
from 0.2 as before: 0.819 / 0.673 (the shell 0.54 / 0.39: on the seed-1 model the shell's
lit inside was missing, which only the join takes)."""


JOIN_ALWAYS = 1e9
""":attr:`SelectOptions.chroma_union` for ``join="always"`` (:func:`options_for`): a cap no
chromaticity-only selection reaches (finite, so that a selection file's metadata stays JSON)."""


COLOR_BARS_THRESHOLD = 0.4
"""A recolour's :attr:`SelectOptions.select_threshold` under a scribble on bars
(:data:`COLOR_ON_BARS`): between the sheets' 0.3 (:data:`COLOR_THRESHOLD`) and a removal's 0.5.
The lower cut grows a thin part along itself, and also into what it meets: purple legs from
purple stretchers, a pale shell from its legs.  On the frame recolours, gap closed at 0.3 →
0.4, edit seed 0: procedural 0.864 / 0.877 → 0.870 / 0.891, real 0.435 / 0.204 / 0.445 /
0.368 → 0.523 / 0.223 / 0.533 / 0.460 (seed 1 alike); at 0.5 the real modern armchair's frame,
whose tube bends, lost 0.17 of IoU.  The one colour twin of the 16-twin benchmark scribbled on
bars, `chair_009`'s back frame, closes 0.849 → 0.994 (`g_p0`) and 0.864 → 0.934 (`g_p1`)."""
COLOR_ON_BARS = (("features", REMOVE_FEATURES), ("geometry_weight", REMOVE_GEOMETRY_WEIGHT),
                 ("position_weight", REMOVE_POSITION_WEIGHT), ("shape_gate", REMOVE_SHAPE_GATE), ("sheet_veto", REMOVE_SHEET_VETO),
                 ("select_threshold", COLOR_BARS_THRESHOLD))
"""Recolours' :attr:`SelectOptions.on_bars`: scribbled on bars, a recolour reads the matter's
shape and F_fuse's activations (:data:`REMOVE_FEATURES`, :data:`REMOVE_GEOMETRY_WEIGHT`),
weighs position at :data:`REMOVE_POSITION_WEIGHT`, leaves lines square to the scribble out of
its joins (:data:`REMOVE_SHAPE_GATE`) and vetoes sheets (:data:`REMOVE_SHEET_VETO`), as a
removal does, and cuts at :data:`COLOR_BARS_THRESHOLD`; it keeps its own smoothing, vetoes
and rims.  Measured on the 46 colour twins of ``benchmarks/frame_recolours.py`` (each removal
twin's part recoloured, from its scribbles): docs/benchmarks.md, fifty-fifth session."""


def options_for(kind: str, mirror: str | None = None, join: str | None = None) -> SelectOptions:
    """The selection options an edit of ``kind`` uses: recolours and removals join the
    chromaticity-only selection (:data:`CHROMA_UNION`), additions (a donor's part) do not: it
    doubled the damage of an added part to the rest of the chair (docs/selection.md).
    Removals also describe points by F_fuse's activations and the grid's local shape
    (:data:`REMOVE_FEATURES`), weigh position at :data:`REMOVE_POSITION_WEIGHT`, smooth
    bilaterally (:data:`REMOVE_SMOOTH_BANDWIDTH`) and veto cells of another
    chromaticity (:data:`REMOVE_VETO_CHROMA`); recolours select at a lower
    cut (:data:`COLOR_THRESHOLD`), read chromaticity with a smaller offset
    (:data:`COLOR_CHROMA_OFFSET`), fill the rims (:data:`COLOR_FILL_SHARE`; removals
    :data:`REMOVE_FILL_SHARE`), gate
    appearance tighter (:data:`COLOR_APPEARANCE_GATE`), join at every saturation and veto
    unlike hues (:data:`COLOR_VETO_CHROMA`, :data:`COLOR_PALE_VETO`; removals
    :data:`REMOVE_PALE_VETO` below their join's saturation).  Both let keep strokes win near them
    (:data:`REMOVE_KEEP_RATIO`, :data:`COLOR_KEEP_RATIO`), snap a scribble that lies mostly off
    the object onto it (:data:`STROKE_SNAP`), and read the instance's mirror symmetry
    (:data:`REMOVE_MIRROR`, :data:`COLOR_MIRROR`) unless ``mirror`` says otherwise; ``off``
    (the scribbled side only) also keeps a removal from taking loose pieces of its part
    (:attr:`SelectOptions.free_pieces`), which would be the other side's.
    All three lift their strokes' centres (:data:`STROKE_CENTRES`).  ``join`` (``auto``, the
    default; ``always``; ``never``) overrides the chromaticity join's cap: a part that is most
    of the instance can hold more of its colour than the cap lets the join take."""
    if kind not in EDIT_KINDS:
        raise CrfError(f"a selection for {kind!r}: expected one of {', '.join(EDIT_KINDS)}")
    if mirror is not None and mirror not in MIRROR_MODES:
        raise CrfError(f"--mirror {mirror}: expected one of {', '.join(MIRROR_MODES)}")
    if join is not None and join not in JOIN_MODES:
        raise CrfError(f"--colour-join {join}: expected one of {', '.join(JOIN_MODES)}")
    options = _kind_options(kind)
    if mirror is not None:
        options = dataclasses.replace(options, mirror=mirror)
    if mirror == "off":  # the scribbled side only: a removal's loose pieces would take the other side's arm back
        options = dataclasses.replace(options, free_pieces=0.0)
    if join == "always":
        options = dataclasses.replace(options, chroma_union=JOIN_ALWAYS, pale_union=0.0)
    elif join == "never":
        options = dataclasses.replace(options, chroma_union=0.0)
    return options


def _kind_options(kind: str) -> SelectOptions:
    if kind == "color":
        return SelectOptions(chroma_union=CHROMA_UNION, chroma_saturation=0.0,
                             veto_chroma=COLOR_VETO_CHROMA, veto_floor=COLOR_VETO_FLOOR, chroma_offset=COLOR_CHROMA_OFFSET,
                             pale_veto=COLOR_PALE_VETO, pale_veto_saturation=COLOR_SATURATION, part_join_hue=COLOR_PART_JOIN_HUE,
                             select_threshold=COLOR_THRESHOLD, fill_share=COLOR_FILL_SHARE,
                             appearance_gate=COLOR_APPEARANCE_GATE, keep_ratio=COLOR_KEEP_RATIO,
                             keep_position_weight=COLOR_KEEP_POSITION_WEIGHT, mirror=COLOR_MIRROR, stroke_centres=STROKE_CENTRES,
                             stroke_snap=STROKE_SNAP, keep_strays=KEEP_STRAYS, join_lines=JOIN_LINES_SHARE, line_negatives=LINE_NEGATIVES,
                             on_bars=COLOR_ON_BARS, pale_union=COLOR_PALE_UNION, part_join_sure=PART_JOIN_SURE)
    if kind == "remove":
        return SelectOptions(features=REMOVE_FEATURES, geometry_weight=REMOVE_GEOMETRY_WEIGHT, position_weight=REMOVE_POSITION_WEIGHT,
                             shape_gate=REMOVE_SHAPE_GATE, sheet_veto=REMOVE_SHEET_VETO, rim_fill=REMOVE_RIM_FILL,
                             chroma_union=CHROMA_UNION,
                             smooth_bandwidth=REMOVE_SMOOTH_BANDWIDTH, veto_chroma=REMOVE_VETO_CHROMA,
                             pale_veto=REMOVE_PALE_VETO, pale_veto_saturation=PALE_SATURATION,
                             keep_ratio=REMOVE_KEEP_RATIO, mirror=REMOVE_MIRROR, stroke_centres=STROKE_CENTRES,
                             stroke_snap=STROKE_SNAP, keep_strays=KEEP_STRAYS, join_lines=JOIN_LINES_SHARE, line_negatives=LINE_NEGATIVES,
                             free_pieces=REMOVE_FREE_PIECES, fill_share=REMOVE_FILL_SHARE)
    return SelectOptions(stroke_centres=STROKE_CENTRES)
