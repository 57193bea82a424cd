"""Scribbles lifted to an explicit 3-D part selection over an instance's occupancy grid.

The paper's edits constrain only the scribbled view's rays; nothing says where the part is in
3-D, so density drops wherever features resemble the scribble.  Here the scribbles first become
a selection S (one soft value per occupancy cell), which the edits then supervise with
(:mod:`.supervised`) and which a user can preview before any weight moves.

1. **Lift.**  Each scribbled pixel on the object becomes a surface point at the rendered
   expected depth (a *positive*); each keep-stroke pixel on the object a *negative*.
2. **Describe.**  Every point — the lifted ones and every occupied cell — is described by the
   field's own per-point features (:func:`point_features`): the 8-d bottleneck, the predicted
   colour, its chromaticity and the position, each group standardized; a removal also reads
   F_fuse's activations and the local shape and orientation of the matter around the point,
   the density's (:data:`REMOVE_FEATURES`, :func:`local_shape`, :func:`cell_opacity`),
   weighted above the other groups (:data:`REMOVE_GEOMETRY_WEIGHT`); a model trained with part maps adds its
   part head's embedding (:mod:`crfedit.parts`) when the scribbled points agree in it
   (:data:`PART_COHERENCE`).  A cell is described
   at its centre moved a half cell up the density gradient when that is denser
   (:func:`denser_points`): the lifted points lie on surfaces, and the centre of a cell that a
   thin part only crosses lies in empty space beside it.
3. **Classify.**  A class-balanced logistic regression over these features (position with
   its second-order terms, so that "both arms but not the seat between them" is a linear cut;
   fitted by Newton's method, :func:`fit_logistic`) separates the positives from the keep
   points and the view's other surface points; each cell's value is its predicted
   probability.  Measured alternatives (a soft nearest-neighbour
   rule, fewer feature groups) did worse: docs/editing.md.
4. **Negatives without keep strokes.**  The view's other surface points are negatives, but
   the unscribbled rest of the scribbled part must not stay one: each of
   ``self_training`` rounds refits without the view points that the last fit — or a fit on
   appearance alone (every group but position) — calls positive.  The appearance fit is what
   lets a part far from the scribble in space but made of the same material (the legs of a
   frame scribbled on its backrest) leave the negatives.
5. **Appearance gate.**  A linear classifier extrapolates: a part the scribbled view never
   showed (a seat hidden behind the scribbled arms) can land on the positive side merely by
   being unlike the negatives.  A cell whose appearance (bottleneck + chromaticity) is farther
   from every positive than ``appearance_gate`` × the positives' own spacing (95th percentile
   of their nearest-neighbour distances) is not selected.
   **5b. Keep strokes win near them** (recolours and removals, :attr:`SelectOptions.keep_ratio`):
   a cell nearer a keep-stroke point than every positive (:func:`keep_wins`, in appearance and
   position) scores 0.  One hyperplane cannot put a part that looks like the scribbled one on
   the other side, however many keep strokes cover it; near the strokes, this does.
6. **Refine.**  Values are blended half-and-half with the mean over each cell's occupied
   3×3×3 neighbourhood (a smoothing that respects the grid's empty space, mild enough that a
   one-cell-thick part survives it; a removal's mean is bilateral, twice: neighbours of unlike
   appearance weigh less, :func:`bilateral_smooth`); only selected cells connected
   (26-neighbourhood, through selected cells) to a scribbled cell stay selected, and a cell
   holding a keep-stroke point scores 0.
7. **Recolours and removals: chromaticity alone.**  Steps 3–6 on the chromaticity group alone select parts
   of the scribbled material that look different elsewhere (a frame's legs, a lit top face);
   for a recolour or a removal (:func:`options_for`) that selection is joined cell by cell,
   unless the part is near-grey or it floods the instance (:attr:`SelectOptions.chroma_union`),
   and only where the chromaticity is the scribbled points' (:attr:`SelectOptions.join_chroma`).

8. **Recolours of saturated parts: a lower cut.**  A recolour's selection of a part that
   passes step 7's saturation test also takes the cells of value :data:`COLOR_THRESHOLD`–0.5
   whose chromaticity is the scribbled points' (:attr:`SelectOptions.select_threshold`,
   :attr:`SelectOptions.band_chroma`).
9. **Recolours: fill the rims.**  A recolour's selection also takes each occupied cell at least
   :data:`COLOR_FILL_SHARE` of whose occupied 3×3×3 neighbourhood is selected
   (:attr:`SelectOptions.fill_share`, :func:`fill_rims`): a slab's lit top face and side
   faces shade unlike its scribbled front and score low, but every occupied cell around them
   is the slab.
10. **Removals: veto other colours.**  A removal's cells of value ≥ :data:`GROW_LOW` whose
    chromaticity is far from the scribbled points' are capped below it, so neither the
    selection nor the removal's skin takes a small touching part of another colour that the
    classifier scored as the target (:attr:`SelectOptions.veto_chroma`; saturated parts only).
10b. **Removals: no odd lines through the joins.**  Of what the chromaticity join (step 7)
    and the part head's join would add, a connected piece mostly made of lines square to the
    scribbled points' orientation is left out (:attr:`SelectOptions.shape_gate`,
    :func:`odd_lines`): the legs of a chair whose stretchers, of the legs' colour, are
    scribbled.  And a scribbled panel's selection takes the lines beside it lying in its
    plane, its rims (:attr:`SelectOptions.rim_fill`, :func:`rim_lines`).
11. **Mirror symmetry.**  When the instance's occupancy grid has a mirror plane
    (:mod:`.symmetry`), a removal's scribbled views lend their mirror images as virtual views
    to steps 1–5 (the camera reflected, the strokes flipped left–right, kept where the mirrored
    surface agrees), and a recolour's finished selection takes its own mirror image
    (:attr:`SelectOptions.mirror`).  Keep strokes on the scribble's mirror image turn this off:
    the user means one side.

``Selection.grown`` (hysteresis: cells of value ≥ :data:`GROW_LOW` connected to the selection
join it) is measured in docs/selection.md but not used by the edits: it raised the procedural
recolours' gap closed by 0.10 and tinted other parts of a weakly trained model.  A removal
empties only the one-cell skin of S at that value (:func:`~.supervised.removal_cells`), and
an unselected cell of another chromaticity than the scribbled points is capped below it.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .. import occupancy
from ..cameras import Camera, rays_from_camera
from ..config import MAX_GRID_SIDE
from ..errors import CrfError
from ..field import ConditionalRadianceField
from ..model import CategoryModel
from ..names import MIRROR_MODES
from ..renderer import RenderOutput, render_camera
from ..safefile import grid_shape, other_kind, pack_bits, read_safetensors, unpack_bits, write_safetensors
from .symmetry import CONFLICT, Mirror, agreeing, conflict, find_mirror, mirror_camera, mirror_image

FORMAT = "crfedit-selection"
VERSION = "2"
READ_VERSIONS = ("1", "2")
"""Version 1 stored ``values`` as uint8 [R, R, R]; version 2 stores only the cells with a value
(``nonzero`` bit-packed, ``levels`` uint8): 39–50 KB against 263 KB for the benchmark twins'
64³ selections.  Both read."""
SPARSE = ("nonzero", "levels")
MIN_OPACITY = 0.5
"""A pixel shows the object (and has a surface point) where its rendered opacity is at least this."""
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


def group_width(group: str, cfg) -> int:
    """Columns of feature ``group`` in :func:`point_features` for a model of config ``cfg``."""
    return WIDTHS.get(group, {"fuse": cfg.width, "part": cfg.part_dim}.get(group, cfg.bottleneck))


@dataclass(frozen=True)
class ScribbleView:
    """One view's scribbles: the part to edit (``scribble``) and what must not change (``keep``)."""

    camera: Camera
    scribble: np.ndarray  # [H, W] bool
    keep: np.ndarray | None = None  # [H, W] bool


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
PART_JOIN = 0.8
""":attr:`SelectOptions.part_join`.  A part's far side or hidden face that the scribbled view
could not show (a black shell's seat scribbled from behind: recolour 0.36 → 0.80 and
0.41 → 0.93 on two real models).  At 0.7: procedural recolours 0.910 and removals 0.636, real
recolours 0.765 (seed-0 models)."""
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
    part_join: float = PART_JOIN
    """When the part head is read: an occupied cell whose cosine (as ``part_veto``'s) is at
    least this joins the selection where it connects (26-neighbourhood, through such cells and
    selected ones) to a scribbled cell, keep-stroke cells and those a keep stroke wins aside: the
    part's far side, or its hidden face, that the scribbled view could not show; 0: no join."""
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
    (:func:`fill_rims`); recolours use :data:`COLOR_FILL_SHARE`."""


CHROMA_UNION = 3.5
"""Recolours' and removals' :attr:`SelectOptions.chroma_union`.  The full features miss parts
of one material that look different elsewhere: a wooden frame's legs when its back is
scribbled, a lit top face.  Chromaticity alone takes them (a Lambertian shading factor cancels in it) but on its own
floods parts of a shared hue.  Before the saturation test existed, the 8 colour twins' selections held
0.7–1.9× the full features' cells on 7 and 3.7× on one (a near-grey back, IoU 0.36 against the
full features' 0.82).  With the test, the saturated parts of the benchmark twins (colour and
removal, four models) hold 0.51–1.99×, and 2.19–2.68× for a wooden frame scribbled on its back,
whose legs the join rightly adds (IoU 0.59 → 0.93, gap closed 0.48 → 1.00 on the 17 000-step
real model; at 2.5 it was refused there).  The factor sits below the one flood measured."""
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
dB lost outside on the procedural chairs; at 0.5, 0.791 and 0.521.  Removals do not fill:
procedural 0.778 → 0.784 but real 0.216 → 0.110 (at 0.4; a café chair's aluminium frame took
the seat slats it touches)."""

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
REMOVE_SHEET_VETO = 0.7
"""A removal's :attr:`SelectOptions.sheet_veto`.  `scopia_plastic_chair`'s pale tube frame
under a pale seat, scribbled on one leg (88 % of the scribbled points on lines): on the
seed-1 model the classifier took the seat with it (3 651 of 5 500 cells; gap closed 0.17,
−9.1 dB outside), with the veto 0.65.  Measured on the 16-twin benchmark (hybrid, gap closed,
one view, the 17 000-step models, seed 0 / seed 1): real removals 0.882 / 0.842 → 0.895 /
0.912, procedural 0.822 / 0.837 → 0.827 / 0.833, selection IoU 0.735 / 0.699 → 0.736 / 0.716
(real) and the same on the procedural chairs.  At a line share of 0.8 the real removals
closed 0.885 / 0.904, at 0.9 the plastic chair's scribble (0.875) is left as it was."""
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
COLOR_PALE_VETO = 1.0
"""A recolour's :attr:`SelectOptions.pale_veto` (floor 0.02, below :data:`COLOR_SATURATION`).
A white shell's selection took blotches of the beige seat cushion it holds (chromaticity
distance 0.05 against the shell's 0.017), and the recolour darkened them.  Measured as
:data:`COLOR_VETO_CHROMA`, with the join and the lower cut at every saturation: real
recolours' gap closed 0.790 / 0.673 → 0.833 / 0.707 (the shell 0.31 / 0.39 → 0.63 / 0.70),
procedural unchanged (their scribbled parts are saturated); the pale veto alone, the join
from 0.2 as before: 0.819 / 0.673 (the shell 0.54 / 0.39: on the seed-1 model the shell's
lit inside was missing, which only the join takes)."""


def options_for(kind: str, mirror: str | None = None) -> SelectOptions:
    """The selection options an edit of ``kind`` uses: recolours and removals join the
    chromaticity-only selection (:data:`CHROMA_UNION`), additions (a donor's part) do not: it
    doubled the damage of an added part to the rest of the chair (docs/selection.md).
    Removals also describe points by F_fuse's activations and the grid's local shape
    (:data:`REMOVE_FEATURES`), weigh position at :data:`REMOVE_POSITION_WEIGHT`, smooth
    bilaterally (:data:`REMOVE_SMOOTH_BANDWIDTH`) and veto cells of another
    chromaticity (:data:`REMOVE_VETO_CHROMA`); recolours select at a lower
    cut (:data:`COLOR_THRESHOLD`), read chromaticity with a smaller offset
    (:data:`COLOR_CHROMA_OFFSET`), fill the rims (:data:`COLOR_FILL_SHARE`), gate
    appearance tighter (:data:`COLOR_APPEARANCE_GATE`), join at every saturation and veto
    unlike hues (:data:`COLOR_VETO_CHROMA`, :data:`COLOR_PALE_VETO`; removals
    :data:`REMOVE_PALE_VETO` below their join's saturation).  Both let keep strokes win near them
    (:data:`REMOVE_KEEP_RATIO`, :data:`COLOR_KEEP_RATIO`), and read the instance's mirror
    symmetry (:data:`REMOVE_MIRROR`, :data:`COLOR_MIRROR`) unless ``mirror`` says otherwise."""
    if kind not in EDIT_KINDS:
        raise CrfError(f"a selection for {kind!r}: expected one of {', '.join(EDIT_KINDS)}")
    if mirror is not None and mirror not in MIRROR_MODES:
        raise CrfError(f"--mirror {mirror}: expected one of {', '.join(MIRROR_MODES)}")
    options = _kind_options(kind)
    return options if mirror is None else dataclasses.replace(options, mirror=mirror)


def _kind_options(kind: str) -> SelectOptions:
    if kind == "color":
        return SelectOptions(chroma_union=CHROMA_UNION, chroma_saturation=0.0,
                             veto_chroma=COLOR_VETO_CHROMA, veto_floor=COLOR_VETO_FLOOR, chroma_offset=COLOR_CHROMA_OFFSET,
                             pale_veto=COLOR_PALE_VETO, pale_veto_saturation=COLOR_SATURATION,
                             select_threshold=COLOR_THRESHOLD, fill_share=COLOR_FILL_SHARE,
                             appearance_gate=COLOR_APPEARANCE_GATE, keep_ratio=COLOR_KEEP_RATIO,
                             keep_position_weight=COLOR_KEEP_POSITION_WEIGHT, mirror=COLOR_MIRROR)
    if kind == "remove":
        return SelectOptions(features=REMOVE_FEATURES, geometry_weight=REMOVE_GEOMETRY_WEIGHT, position_weight=REMOVE_POSITION_WEIGHT,
                             shape_gate=REMOVE_SHAPE_GATE, sheet_veto=REMOVE_SHEET_VETO, rim_fill=REMOVE_RIM_FILL,
                             chroma_union=CHROMA_UNION,
                             smooth_bandwidth=REMOVE_SMOOTH_BANDWIDTH, veto_chroma=REMOVE_VETO_CHROMA,
                             pale_veto=REMOVE_PALE_VETO, pale_veto_saturation=PALE_SATURATION,
                             keep_ratio=REMOVE_KEEP_RATIO, mirror=REMOVE_MIRROR)
    return SelectOptions()


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

    def grown(self, low: float = GROW_LOW) -> "Selection":
        """This selection plus every cell of value ≥ ``low`` connected to it (26-neighbourhood):
        hysteresis.  Measured for recolours and not used by them (see the module docstring)."""
        values = hysteresis(self.values, self.mask, self.threshold, low)
        return Selection(values, self.instance, self.instance_name, self.model_fingerprint, self.meta, self.threshold)

    def check_for(self, model: CategoryModel, instance: int) -> None:
        """A one-line error unless this selection was made for ``model``'s ``instance``."""
        if self.model_fingerprint != model.fingerprint():
            raise CrfError(f"the selection was made for another model (fingerprint {self.model_fingerprint[:12]}…, this model {model.fingerprint()[:12]}…)")
        if self.instance_name != model.names[instance]:
            raise CrfError(f"the selection is of instance {self.instance_name!r}, not {model.names[instance]!r}")
        if tuple(self.values.shape) != (model.cfg.occ_res,) * 3:
            raise CrfError(f"the selection grid is {self.values.shape[0]}³ but the model's occupancy grid is {model.cfg.occ_res}³")
        if not bool(self.mask.any()):
            raise CrfError("the selection is empty: no cell is selected")


# ----------------------------------------------------------------------------- lifting


@torch.no_grad()
def surface_points(
    field: ConditionalRadianceField, camera: Camera, instance: int, min_opacity: float = MIN_OPACITY,
    out: RenderOutput | None = None,
) -> tuple[Tensor, Tensor]:
    """(world points [H·W, 3], on-object mask [H·W]) at each pixel's expected surface depth,
    from ``out`` (the view's render; rendered here when None, depth and opacity only)."""
    out = render_camera(field, camera, instance, colour=False) if out is None else out
    rays = rays_from_camera(camera, field.aabb.device)
    opacity = out.opacity.reshape(-1)
    t = out.depth.reshape(-1) / opacity.clamp_min(1e-6)
    return rays.origins + t[:, None] * rays.directions, opacity >= min_opacity


@torch.no_grad()
def point_features(
    field: ConditionalRadianceField, instance: int, points: Tensor, view_from: Tensor, groups: Sequence[str], fused: Tensor | None = None,
    shape_grid: Tensor | None = None, shape_radius: int = GEOMETRY_RADIUS, chroma_offset: float = CHROMA_OFFSET,
) -> Tensor:
    """The field's own description of world ``points`` [M, 3]: the chosen :data:`FEATURE_GROUPS`
    groups concatenated, unstandardized.  Colour is F_rad's output looking from ``view_from`` [3];
    position is the normalized point and its second-order terms (so that a linear classifier
    can select e.g. both arms but not the seat between them); ``fuse`` is F_fuse's output, of
    which the bottleneck is a linear map; ``geometry`` the matter's local shape
    (:func:`local_shape` of ``shape_grid``, the instance's :func:`cell_opacity` when None).
    ``fused``: F_fuse's output at the points, when the caller has it; ``chroma``'s offset:
    :attr:`SelectOptions.chroma_offset`."""
    xn = field.normalize(points)
    fused = field.fuse_features(xn, instance) if fused is None else fused
    feat = field.bottleneck(fused)
    rgb = None
    if "color" in groups or "chroma" in groups:  # F_rad once for both colour groups
        rgb = field.radiance(feat, F.normalize(points - view_from, dim=-1), instance)
    out = []
    for group in groups:
        if group == "bottleneck":
            out.append(feat)
        elif group == "fuse":
            out.append(fused)
        elif group == "color":
            out.append(rgb)
        elif group == "chroma":  # rgb / (r + g + b): a Lambertian shading factor cancels
            out.append(rgb / (rgb.sum(dim=-1, keepdim=True) + chroma_offset))
        elif group == "position":
            x, y, z = xn.unbind(-1)
            out.append(torch.stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], dim=-1))
        elif group == "geometry":
            grid = cell_opacity(field, instance, field.occupancy[instance]) if shape_grid is None else shape_grid
            out.append(local_shape(grid, xn, shape_radius))
        elif group == "part":
            if field.F_part is None:
                raise CrfError("selection feature 'part': this model has no part head (its dataset had no part maps)")
            out.append(field.part_embedding(fused))
        else:
            raise CrfError(f"selection feature {group!r}: expected one of {', '.join(FEATURE_GROUPS)}")
    return torch.cat(out, dim=-1)


class Frames(NamedTuple):
    """The local shape of the matter around points (:func:`local_frames`), per point."""

    linear: Tensor
    """(λ₁ − λ₂)/λ₁: 1 on a line of cells.  [M]"""
    planar: Tensor
    """(λ₂ − λ₃)/λ₁: 1 on a sheet.  [M]"""
    spherical: Tensor
    """λ₃/λ₁: 1 in a solid.  [M]"""
    share: Tensor
    """The block's mean weight.  [M]"""
    spread: Tensor
    """√λ₁ / r.  [M]"""
    direction: Tensor
    """v₁, a line's direction (unit; its sign arbitrary).  [M, 3]"""
    normal: Tensor
    """v₃, a sheet's normal (unit; its sign arbitrary).  [M, 3]"""


def local_frames(grid: Tensor, xn: Tensor, radius: int = GEOMETRY_RADIUS) -> Frames:
    """The shape of the matter in the (2r+1)³ block of cells around the cell of each normalized
    point ``xn`` [M, 3], each cell weighing ``grid`` [R, R, R] (a cell's opacity, or a bool
    occupancy grid): the eigenvalues λ₁ ≥ λ₂ ≥ λ₃ and eigenvectors v₁, v₂, v₃ of the weighted
    covariance of the cells' offsets (+ 10⁻³ I), as :class:`Frames`."""
    res, side = grid.shape[-1], grid.shape[-1] + 2 * radius
    padded = F.pad(grid.to(xn.dtype), (radius,) * 6).reshape(-1)  # the box's outside is empty
    ijk, _ = occupancy.cell_index(xn, res)
    ijk = ijk.clamp(0, res - 1) + radius
    r = torch.arange(-radius, radius + 1, device=xn.device)
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)  # [K, 3]
    flat = (ijk[:, 0] * side + ijk[:, 1]) * side + ijk[:, 2]
    w = padded[flat[:, None] + ((offsets[:, 0] * side + offsets[:, 1]) * side + offsets[:, 2])[None]]  # [M, K]
    n = w.sum(dim=1).clamp_min(1e-6)
    d = offsets.to(xn.dtype)
    mean = w @ d / n[:, None]
    second = (w @ (d[:, :, None] * d[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3) / n[:, None, None]
    cov = second - mean[:, :, None] * mean[:, None, :] + 1e-3 * torch.eye(3, dtype=xn.dtype, device=xn.device)
    lam, v1, v3 = sym3_eigen(cov)  # ascending
    l3, l2, l1 = lam.clamp_min(1e-6).unbind(-1)
    return Frames((l1 - l2) / l1, (l2 - l3) / l1, l3 / l1, w.mean(dim=1), l1.sqrt() / radius, v1, v3)


def sym3_eigen(a: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The eigenvalues (ascending) [M, 3] of symmetric 3×3 matrices ``a`` [M, 3, 3], and the
    unit eigenvectors of the largest [M, 3] and of the smallest [M, 3], in closed form (in
    float64 inside; returned in ``a``'s dtype).

    The eigenvalues by the trigonometric solution of the characteristic cubic (Smith 1961),
    each eigenvector as the longest cross product of two rows of a − λI.  Where an eigenvalue
    is repeated its eigenvectors are any of a plane and it is a line's normal or a sheet's
    direction, which :func:`local_shape` weighs by 0; where all three are equal (a solid
    block) the vectors are z and x, as LAPACK returns for a multiple of I.
    ``torch.linalg.eigh`` loops over the matrices: 2.5× the time on a 37 000-cell grid."""
    m = a.reshape(-1, 9).T.double().contiguous()
    a00, a01, a02, _, a11, a12, _, _, a22 = m
    q = (a00 + a11 + a22) / 3
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    p2 = (d0 * d0 + d1 * d1 + d2 * d2 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6
    p = p2.sqrt()
    det = d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
    phi = torch.acos(torch.where(p2 > 0, det / (2 * p2 * p).clamp_min(1e-300), torch.zeros_like(det)).clamp_(-1, 1)) / 3
    l1 = q + 2 * p * torch.cos(phi)
    l3 = q + 2 * p * torch.cos(phi + 2 * math.pi / 3)
    l2 = 3 * q - l1 - l3

    def vector(lam: Tensor, fallback: tuple[float, float, float]) -> Tensor:
        b0, b1, b2 = a00 - lam, a11 - lam, a22 - lam
        crosses = [(a01 * a12 - a02 * b1, a02 * a01 - b0 * a12, b0 * b1 - a01 * a01),
                   (a01 * b2 - a02 * a12, a02 * a02 - b0 * b2, b0 * a12 - a01 * a02),
                   (b1 * b2 - a12 * a12, a12 * a02 - a01 * b2, a01 * a12 - b1 * a02)]
        best, best_n = crosses[0], sum(c * c for c in crosses[0])
        for c in crosses[1:]:
            n = sum(ci * ci for ci in c)
            longer = n > best_n
            best, best_n = tuple(torch.where(longer, ci, bi) for ci, bi in zip(c, best)), torch.where(longer, n, best_n)
        ok = best_n > 1e-24 * (1 + p2) ** 2
        inv = torch.where(ok, best_n.clamp_min(1e-300).rsqrt(), torch.zeros_like(best_n))
        return torch.stack([torch.where(ok, c * inv, torch.full_like(c, f)) for c, f in zip(best, fallback)], dim=-1)

    return torch.stack([l3, l2, l1], dim=-1).to(a.dtype), vector(l1, (0.0, 0.0, 1.0)).to(a.dtype), vector(l3, (1.0, 0.0, 0.0)).to(a.dtype)


def local_shape(grid: Tensor, xn: Tensor, radius: int = GEOMETRY_RADIUS) -> Tensor:
    """:func:`local_frames` as features: linearity ℓ, planarity p, sphericity, the block's mean
    weight, √λ₁ / r, and the orientation ℓ·v₁² (a line's direction) and p·v₃² (a sheet's
    normal), per axis (squared: the eigenvectors' signs are arbitrary).  [M, 11]

    The classic point-cloud descriptors, on the grid: a tube is a line of cells, a seat or a
    shell a sheet, a cushion a solid, and a chair's legs are vertical lines where the
    stretchers between them are horizontal ones.  A part's colour and the field's features
    do not tell a dark frame from the dark seat it carries, nor legs from stretchers of their
    colour; its shape does."""
    f = local_frames(grid, xn, radius)
    return torch.cat([torch.stack([f.linear, f.planar, f.spherical, f.share, f.spread], dim=-1),
                      f.linear[:, None] * f.direction**2, f.planar[:, None] * f.normal**2], dim=-1)


SHAPE_CLASH = 0.25
""":func:`odd_lines`: a cell and a scribbled point agree in orientation where their clash (the
squared sine of the angle between them) is at most this: within 30°."""
SHAPE_AGREE = 0.25
""":func:`odd_lines`: a line is at odds with the scribble where it agrees with fewer than this
share of the scribbled points."""
SHAPE_LINE = 0.5
""":func:`odd_lines`: a cell is a line where its linearity is at least this and its planarity."""
RIM_SHEETS = 0.5
""":attr:`SelectOptions.rim_fill` runs when at least this share of the scribbled points lie on sheets."""
SHAPE_GATE_POINTS = 512
""":attr:`SelectOptions.shape_gate` compares the cells with at most this many scribbled points,
evenly spaced (the comparison is cells × points)."""
SHAPE_GATE_RADIUS = 2
"""The block :func:`odd_lines` reads the orientation in: at 3³ cells half a chair's legs
(two cells thick) read as lines, at 5³ nine in ten do."""


def shape_agreement(cells: Frames, points: Frames, chunk: int = 8192) -> Tensor:
    """Each cell's share of ``points`` whose orientation it agrees with, their clash at most
    :data:`SHAPE_CLASH`.  Each counts as a line or a sheet, whichever of its linearity and
    planarity is larger, and the clash is the squared sine of the angle between the two lines
    or the two normals, or the squared cosine between the line and the normal: 0 where they
    agree (a line along a line, a sheet parallel to a sheet, a line lying in a sheet such as a
    panel's rim), 1 where they are square (a leg under a stretcher, under a seat).  [N]"""
    p_line = (points.linear >= points.planar)[None]
    c_line = cells.linear >= cells.planar
    out = []
    for lo in range(0, len(c_line), chunk):
        cu, cn = cells.direction[lo : lo + chunk], cells.normal[lo : lo + chunk]
        line_vs = torch.where(p_line, 1 - (cu @ points.direction.T) ** 2, (cu @ points.normal.T) ** 2)
        sheet_vs = torch.where(p_line, (cn @ points.direction.T) ** 2, 1 - (cn @ points.normal.T) ** 2)
        clash = torch.where(c_line[lo : lo + chunk, None], line_vs, sheet_vs)
        out.append((clash <= SHAPE_CLASH).float().mean(dim=1))
    return torch.cat(out) if out else cells.linear.new_zeros(0)


def lines_of(frames: Frames) -> Tensor:
    """[N] bool: the points on a line, linearity at least :data:`SHAPE_LINE` and the planarity."""
    return (frames.linear >= frames.planar) & (frames.linear >= SHAPE_LINE)


def odd_lines(cells: Frames, points: Frames) -> Tensor:
    """[N] bool: the cells that are lines (:func:`lines_of`) and agree in orientation with
    fewer than :data:`SHAPE_AGREE` of the scribbled ``points`` (:func:`shape_agreement`)."""
    line = lines_of(cells)
    odd = torch.zeros_like(line)
    odd[line] = shape_agreement(Frames(*(f[line] for f in cells)), points) < SHAPE_AGREE  # the lines' agreement only
    return odd


SHEET_PLANAR = 0.7
""":func:`sheets_of`: a cell is a sheet where its planarity is at least this and its linearity
(at 0.5 a tube running along a panel's edge read as a sheet: the real `modern_armchair`'s
frame removal 0.77 → 0.68, at 0.6 0.70)."""


def sheets_of(frames: Frames) -> Tensor:
    """[N] bool: the points on a sheet, planarity at least :data:`SHEET_PLANAR` and above the linearity."""
    return (frames.planar > frames.linear) & (frames.planar >= SHEET_PLANAR)


def rim_lines(cells: Frames, points: Frames, share: float) -> Tensor:
    """[N] bool: the cells that are lines (:func:`lines_of`) lying in the plane (within 30°,
    :data:`SHAPE_CLASH`) of at least ``share`` of the ``points`` that are sheets
    (:attr:`SelectOptions.rim_fill`); none when no point is a sheet."""
    sheets = points.planar > points.linear
    line = lines_of(cells)
    if not bool(sheets.any()):
        return torch.zeros_like(line)
    inplane = ((cells.direction @ points.normal[sheets].T) ** 2 <= SHAPE_CLASH).float().mean(dim=1)
    return line & (inplane >= share)


def gate_pieces(added: Tensor, odd: Tensor, share: float) -> Tensor:
    """[R, R, R] bool: the cells of the connected pieces of ``added`` (26-neighbourhood) at least
    ``share`` of whose cells are ``odd`` [R, R, R] (:attr:`SelectOptions.shape_gate`)."""
    at = added.reshape(-1).nonzero().squeeze(-1)
    _, piece = torch.unique(components(added).reshape(-1)[at], return_inverse=True)  # 0, 1, … per piece
    n = torch.bincount(piece).float()
    bad = torch.bincount(piece, weights=odd.reshape(-1)[at].float(), minlength=len(n))
    out = torch.zeros(added.numel(), dtype=torch.bool, device=added.device)
    out[at] = (bad / n >= share)[piece]
    return out.view(added.shape)


SHAPE_SOURCES = ("density", "occupancy")
"""What :attr:`SelectOptions.shape_from` may name."""
SHAPE_FRACTION = 1 / 32
""":func:`cell_opacity` measures a cell's opacity across this fraction of its side."""


@torch.no_grad()
def cell_opacity(field: ConditionalRadianceField, instance: int, occupied: Tensor, sigma: Tensor | None = None) -> Tensor:
    """Each occupied cell's opacity across :data:`SHAPE_FRACTION` of its side, 1 − exp(−σ·h·f)
    with σ the density at its centre (``sigma`` [C], in the order of the occupied cells, when
    the caller has it) and h the cell's side, 0 in the empty cells.  [R, R, R]

    What :func:`local_shape` weighs.  The occupancy grid is dilated for sampling (a thin leg is
    a solid block of occupied cells, sphericity 0.8–0.9); the density is not, but an opacity
    across a whole cell saturates to 1 in the leg's halo as in its core: across 1/32 of it
    the weight is nearly the density itself, up to where a surface is."""
    res = occupied.shape[-1]
    cells = occupied.reshape(-1).nonzero().squeeze(-1)
    if sigma is None:
        xn = occupancy.cell_centers(res, occupied.device)[cells]
        sigma = field.sigma(field.raw_density(field.fuse_features(xn, instance))).reshape(-1)
    h = float((field.aabb[3:] - field.aabb[:3]).max()) / res
    out = torch.zeros(res**3, device=occupied.device)
    out[cells] = 1.0 - torch.exp(-sigma * h * SHAPE_FRACTION)
    return out.view(res, res, res)


ASCENT_CHUNK = 8192
""":func:`denser_points` takes the cells this many at a time: each piece's activations stay in
the cache (37 000 cells on one core: 126 → 114 ms, the same bits)."""


def denser_points(field: ConditionalRadianceField, instance: int, xn: Tensor, distance: float) -> tuple[Tensor, Tensor, Tensor]:
    """Normalized points ``xn`` [N, 3], each moved ``distance`` along its density gradient where
    the density is higher there, else left where it is; F_fuse's output at the points
    returned [N, width], which :func:`point_features` takes instead of computing it again; and
    the density at ``xn`` [N], which :func:`cell_opacity` takes.

    One gradient step (a forward and backward pass, and one forward pass to check it): a cell
    centre beside a thin part moves onto it, one inside a solid part stays put or moves within
    it.  Every point's step is its own, so the points go :data:`ASCENT_CHUNK` at a time."""
    if len(xn) > ASCENT_CHUNK:
        pieces = [denser_points(field, instance, piece, distance) for piece in xn.split(ASCENT_CHUNK)]
        return tuple(torch.cat(parts) for parts in zip(*pieces))
    density = lambda fused: field.sigma(field.raw_density(fused))
    with torch.enable_grad():
        x = xn.detach().requires_grad_(True)
        fused = field.fuse_features(x, instance)
        sigma = density(fused)
        (grad,) = torch.autograd.grad(sigma.sum(), x)
    moved = xn + F.normalize(grad, dim=-1) * distance
    fused_moved = field.fuse_features(moved, instance)
    denser = (density(fused_moved) > sigma.detach())[:, None]
    return torch.where(denser, moved, xn), torch.where(denser, fused_moved, fused.detach()), sigma.detach().reshape(-1)


def _standardizer(all_feats: Tensor, widths: Sequence[int], weights: Sequence[float], stats: tuple[Tensor, Tensor] | None = None,
                  columns: Tensor | None = None):
    """Per-dimension z-scores, each group scaled by weight/√(its width) so groups weigh alike
    (``stats``: :func:`_feature_stats` of ``all_feats``, when the caller has them), of the
    ``columns`` only when given."""
    mean, std = _feature_stats(all_feats) if stats is None else stats
    scale = torch.cat([torch.full((w,), g / w**0.5) for w, g in zip(widths, weights)]).to(all_feats)
    if columns is not None:
        mean, std, scale = mean[columns], std[columns], scale[columns]
        return lambda f: (f[:, columns] - mean).div_(std).mul_(scale)
    return lambda f: (f - mean).div_(std).mul_(scale)


def _feature_stats(feats: Tensor) -> tuple[Tensor, Tensor]:
    """Per-dimension mean and standard deviation (at least 10⁻⁶) of ``feats`` [N, F].

    Two passes, the second in place: ``Tensor.std(dim=0)`` takes six times as long on a
    37 000 × 140 grid of cells' features, for the same values to a unit in the last place."""
    mean = feats.mean(dim=0)
    var = (feats - mean).square_().sum(dim=0) / max(len(feats) - 1, 1)
    return mean, var.sqrt_().clamp_min(1e-6)


NEWTON_STEPS = 50
"""At most this many Newton steps per logistic fit (they converge in fewer than 10)."""
NEWTON_TOL = 1e-4
"""A logistic fit stops once a step moves no weight by more than this.  Past it the fits
creep (steps of 10⁻⁵ for a dozen more iterations, the loss changing in its seventh digit
on a 115-feature removal): a cell's logit would move by about 10⁻³."""


class Logistic(NamedTuple):
    """A fitted logistic regression: x ↦ P(positive) = σ(x·w + b) for rows of x."""

    w: Tensor
    b: Tensor

    def __call__(self, x: Tensor) -> Tensor:
        return torch.sigmoid(x @ self.w + self.b)


def fit_logistic(pos: Tensor, neg: Tensor, neg_weight: Tensor, l2: float = 1e-2, start: Logistic | None = None) -> Logistic:
    """A class-balanced logistic regression pos [P, F] vs neg [N, F] (negatives weighted by
    ``neg_weight`` [N]), L2 penalty ``l2``·|w|², fitted by Newton's method from ``start``
    (zeros when None), in float64 (the curvature in float32).  The loss is strictly convex, so the start changes only how
    many steps the fit takes; with F + 1 ≈ 25 unknowns a step is one small linear solve."""
    x = torch.cat([pos, neg]).double()
    x = torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype, device=x.device)], dim=1)
    y = torch.cat([torch.ones(len(pos)), torch.zeros(len(neg))]).to(x)
    wt = torch.cat([torch.full((len(pos),), 0.5 / len(pos)).to(x), 0.5 * neg_weight.to(x) / neg_weight.sum()])
    ridge = torch.full((x.shape[1],), 2.0 * l2, dtype=x.dtype, device=x.device)
    ridge[-1] = 0.0  # the bias is not penalised
    theta = torch.zeros(x.shape[1], dtype=x.dtype, device=x.device) if start is None else torch.cat([start.w, start.b]).to(x)
    loss = lambda z, t: (wt * F.binary_cross_entropy_with_logits(z, y, reduction="none")).sum() + 0.5 * (ridge * t * t).sum()
    x32, xt32 = x.float(), x.T.float().contiguous()  # the curvature in float32 (below)
    logits = x @ theta
    current = loss(logits, theta)
    for _ in range(NEWTON_STEPS):
        p = torch.sigmoid(logits)
        grad = x.T @ (wt * (p - y)) + ridge * theta
        # float32 curvature, float64 gradient and loss: the steps head for the same minimum and
        # the line search still guards them; the product is most of a step's time, 2.7× faster
        hess = ((xt32 * (wt * p * (1 - p)).float()) @ x32).double() + torch.diag(ridge)
        step = torch.linalg.solve(hess, grad)
        scale = 1.0
        while True:  # backtrack if a full step overshoots
            trial_theta = theta - scale * step
            trial_logits = x @ trial_theta
            trial = loss(trial_logits, trial_theta)
            if trial <= current or scale < 1e-4:
                break
            scale *= 0.5
        if trial > current:  # no step lowers the loss: converged to float64 precision
            break
        theta, logits, current = trial_theta, trial_logits, trial
        if float(step.abs().max()) * scale < NEWTON_TOL:
            break
    theta = theta.to(pos.dtype)
    return Logistic(theta[:-1], theta[-1:])


def classifier(pos: Tensor, keep: Tensor, others: Tensor, rounds: int, keep_weight: float, appearance: Tensor | None = None):
    """Positives against the keep strokes' points (each weighing ``keep_weight``) and the view's
    other surface points; each of ``rounds`` self-training rounds drops the other points the last
    fit calls positive (the unscribbled rest of the part must not stay a negative), or that a fit
    on the ``appearance`` columns alone calls positive.  With no negative at all (the scribbles
    cover the whole object) everything is selected.  Each round's fits start from the last
    round's."""
    active = torch.ones(len(others), dtype=torch.bool, device=others.device)
    clf = looks = None
    for _ in range(rounds + 1):
        neg = torch.cat([keep, others[active]])
        if len(neg) == 0:  # the scribble covers all of the object in every view: it means all of it
            return lambda q: torch.ones(q.shape[0], dtype=q.dtype, device=q.device)
        weight = torch.cat([torch.full((len(keep),), keep_weight), torch.ones(int(active.sum()))]).to(pos)
        clf = fit_logistic(pos, neg, weight, start=clf)
        if len(others):
            active = clf(others) < 0.5
            if appearance is not None:
                looks = fit_logistic(pos[:, appearance], neg[:, appearance], weight, start=looks)
                active &= looks(others[:, appearance]) < 0.5
    return clf


def chroma_alike(cells: Tensor, pos: Tensor, factor: float, floor: float = 0.01) -> Tensor:
    """Whether each cell's chromaticity [N, 3] lies within ``factor`` · r + ``floor`` of the
    positives' [P, 3] median chromaticity, r the 90th percentile of the positives' own
    distances to it."""
    return within_spread(chroma_spread(cells, pos), factor, floor)


def within_spread(spread: tuple[Tensor, Tensor, Tensor], factor: float, floor: float) -> Tensor:
    """:func:`chroma_alike`'s test on :func:`chroma_spread`'s terms: distance ≤ ``factor`` · r + ``floor``.  [N] bool"""
    distance, r, _ = spread
    return distance <= factor * r + floor


def chroma_spread(cells: Tensor, pos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`chroma_alike`'s terms: each cell's distance [N] to the positives' median
    chromaticity, r (the 90th percentile of the positives' own distances to it) and the median
    [3], so that one selection tests several factors without computing them again."""
    med = pos.median(dim=0).values
    r = torch.quantile((pos - med).norm(dim=-1), 0.9) if len(pos) > 1 else torch.zeros((), device=pos.device)
    return (cells - med).norm(dim=-1), r, med


def evenly(rows: Tensor, most: int) -> Tensor:
    """``rows`` [P, ...], or ``most`` of them evenly spaced when there are more."""
    return rows if len(rows) <= most else rows[torch.linspace(0, len(rows) - 1, most).long()]


def appearance_gate(cells: Tensor, pos: Tensor, factor: float, max_positives: int = 2000) -> Tensor:
    """Whether each cell's appearance [N, F] lies within ``factor`` × the positives' spacing of
    some positive [P, F] (the spacing: 95th percentile of the positives' nearest-neighbour
    distances, over at most ``max_positives`` evenly spaced positives)."""
    pos = evenly(pos, max_positives)
    if len(pos) < 2:
        return torch.ones(len(cells), dtype=torch.bool, device=cells.device)
    d = torch.cdist(pos, pos)
    d.fill_diagonal_(float("inf"))
    spacing = torch.quantile(d.amin(dim=1), 0.95)
    return nearest_distance(cells, pos, max_positives) <= factor * spacing


def nearest_distance(cells: Tensor, points: Tensor, max_points: int = 2000, chunk: int = 8192) -> Tensor:
    """Each cell's [N, F] distance to its nearest point [P, F], over at most ``max_points``
    evenly spaced points, ``chunk`` cells at a time (bounded memory on a 64³ grid).  [N]

    ``torch.cdist(c, points).min(dim=1)`` to the bit, without the square root of every pair:
    past 25 rows cdist computes its squared distances as one product of padded rows, |a|²
    − 2a·b + |b|² (:func:`_squared_distances` repeats it), then the root of each, and the
    root is monotonic, so the root of the least square is the least root.  The least square
    by ``amin`` (values only: half the time of ``min``'s values and indices)."""
    points = evenly(points, max_points)
    if not len(cells):
        return cells.new_zeros(0)
    p_norm = points.pow(2).sum(-1, keepdim=True)
    p_ = torch.cat([points, torch.ones_like(p_norm), p_norm], dim=-1).mT
    out = []
    for c in cells.split(chunk):
        if len(c) <= 25 and len(points) <= 25:  # cdist's direct path
            out.append(torch.cdist(c, points).amin(dim=1))
        else:
            out.append(_squared_distances(c, p_).amin(dim=1).clamp_min_(1e-30).sqrt_())
    return torch.cat(out)


def _squared_distances(cells: Tensor, padded_points_t: Tensor) -> Tensor:
    """cdist's squared Euclidean distances [N, P] past 25 rows (ATen's ``_euclidean_dist``):
    the rows [−2a, |a|², 1] times the columns [b, 1, |b|²] (``padded_points_t`` [F + 2, P])."""
    c_norm = cells.pow(2).sum(-1, keepdim=True)
    return torch.cat([cells.mul(-2), c_norm, torch.ones_like(c_norm)], dim=-1).matmul(padded_points_t)


def keep_wins(cells: Tensor, pos: Tensor, keep: Tensor, ratio: float) -> Tensor:
    """Whether each cell [N, F] lies nearer some keep point [K, F] than ``ratio`` × its nearest
    positive [P, F] (:attr:`SelectOptions.keep_ratio`): a Voronoi split between the two kinds
    of stroke, in whatever space the columns span.  [N] bool; all False without keep points."""
    if len(keep) == 0 or len(pos) == 0:
        return torch.zeros(len(cells), dtype=torch.bool, device=cells.device)
    return nearest_distance(cells, keep) < ratio * nearest_distance(cells, pos)


# ----------------------------------------------------------------------------- refinement


def smooth_over_occupied(values: Tensor, occupied: Tensor) -> Tensor:
    """Mean of ``values`` [R, R, R] over each occupied cell's occupied 3×3×3 neighbourhood."""
    occ = occupied.float()[None, None]
    num = F.avg_pool3d((values * occupied)[None, None], 3, stride=1, padding=1, count_include_pad=False)
    den = F.avg_pool3d(occ, 3, stride=1, padding=1, count_include_pad=False)
    return torch.where(occupied, (num / den.clamp_min(1e-12))[0, 0], torch.zeros_like(values))


def neighbour_table(cells: Tensor, res: int | Sequence[int], half: bool = False) -> Tensor:
    """For each of the flat cell indices ``cells`` [N] (ascending) of an [R, R, R] grid (or a
    grid of shape ``res``), the positions in ``cells`` of its 26 neighbours, −1 where a
    neighbour is not among them.  [N, 26]; with ``half`` the first 13 columns only, whose
    opposites are the other 13 (each pair of neighbours once).  [N, 13]

    The cells' positions written into a grid padded by one empty cell on each side, and read
    back at each cell's flat index plus the 26 offsets' flat steps: no neighbour falls off the
    grid, so none needs a bounds test."""
    shape = (res,) * 3 if isinstance(res, int) else tuple(res)
    d, h, w = (n + 2 for n in shape)
    index = torch.full((d * h * w,), -1, dtype=torch.long, device=cells.device)
    padded = ((cells // (shape[1] * shape[2]) + 1) * h + cells // shape[2] % shape[1] + 1) * w + cells % shape[2] + 1
    index[padded] = torch.arange(cells.numel(), device=cells.device)
    steps = torch.tensor([(a * h + b) * w + c for a, b, c in NEIGHBOUR_OFFSETS[: 13 if half else 26]], device=cells.device)
    return index[steps[:, None] + padded[None]].T  # laid out offset by offset: bilateral_smooth reads it so


NEIGHBOUR_OFFSETS = [o for o in itertools.product((-1, 0, 1), repeat=3) if any(o)]
"""The 26 neighbour offsets in :func:`neighbour_table`'s column order; column j's opposite is
column 25 − j."""


def bilateral_smooth(values: Tensor, features: Tensor, neighbours: Tensor, bandwidth: float, rounds: int) -> Tensor:
    """``rounds`` times, each cell's value [N] blended half-and-half with the mean over itself and
    its occupied neighbours (``neighbours`` from :func:`neighbour_table`), a neighbour weighing
    exp(−d²/2h²) for d the distance between the two cells' ``features`` [N, F] and h
    ``bandwidth`` (the cell itself weighs 1).  With h → ∞ one round is
    :func:`smooth_over_occupied`'s blend."""
    columns = neighbours.T  # [26, N]: contiguous as neighbour_table makes it, one row per offset
    valid = columns >= 0
    columns = columns.clamp_min(0)
    # d² is symmetric: the distance to the neighbour in row 25 − j is that neighbour's distance
    # in row j, so half the rows are computed and the others gathered
    w = features.new_empty(columns.shape)
    for j in range(13):
        torch.sum(features.index_select(0, columns[j]).sub_(features).square_(), dim=-1, out=w[j])
    w[13:] = w[:13].flip(0).gather(1, columns[13:])
    # exp(−60) ≈ 10⁻²⁶ weighs nothing beside the cell's own 1, and the clamp keeps exp off
    # float32's subnormal range, where it is ten times slower
    w.div_(-2.0 * bandwidth**2).clamp_min_(-60.0).exp_().mul_(valid)
    total = 1.0 + w.sum(dim=0)
    flat = columns.reshape(-1)
    for _ in range(rounds):
        values = 0.5 * (values + (values + (w * values.index_select(0, flat).view_as(w)).sum(dim=0)) / total)
    return values


def fill_rims(values: Tensor, at: float, occupied: Tensor, kept: Tensor, share: float) -> Tensor:
    """``values`` [R, R, R] with every occupied cell outside ``kept`` raised to ``at`` where at
    least ``share`` of its occupied 3×3×3 neighbourhood (itself included) has value ≥ ``at``.

    One pass, so the selection grows by at most one cell, and only where it surrounds a cell:
    the rim of a selected slab (a cell whose occupied neighbours are the slab) joins it, a cell
    of a bulky part that the slab merely touches (most of its occupied neighbours its own
    part's) does not."""
    sel = (values >= at) & occupied
    fill = surrounded_by(sel, occupied, share) & ~sel & ~kept
    return torch.where(fill, values.clamp_min(at), values)


def surrounded_by(selected: Tensor, occupied: Tensor, share: float) -> Tensor:
    """[R, R, R] bool: the occupied cells at least ``share`` of whose occupied 3×3×3
    neighbourhood (itself included) is ``selected`` (a cell's share among the cells around it:
    :func:`fill_rims` and a removal's skin, ``supervised.removal_cells``)."""
    return occupied & (smooth_over_occupied(selected.float(), occupied) >= share - 1e-6)


def hysteresis(values: Tensor, seeds: Tensor, high: float, low: float) -> Tensor:
    """``values`` [R, R, R] with the cells reached from ``seeds`` through cells of value ≥
    ``low`` raised to at least ``high`` and every other cell capped just below ``high``."""
    reached = connected_to(values >= low, seeds)
    return torch.where(reached, values.clamp_min(high), values.clamp(max=high * 0.999))


def components(selected: Tensor) -> Tensor:
    """The connected pieces (26-neighbourhood) of ``selected`` [D, H, W]: each selected cell
    labelled with 1 + the largest flat index in its piece, every other cell with 0.  [D, H, W]
    long

    Over the selected cells only (their :func:`neighbour_table`), each cell pointing at a cell
    of its piece (a larger one, or itself: a root).  Each round hooks every root onto the
    largest root beside any cell pointing at it, then follows the pointers to their roots
    (pointer jumping), so a piece of n cells settles in about log₂ n rounds, not its diameter."""
    out = torch.zeros(selected.shape, dtype=torch.long, device=selected.device)
    cells = selected.reshape(-1).nonzero().squeeze(-1)
    if cells.numel() == 0:
        return out
    nb = neighbour_table(cells, selected.shape, half=True)
    one, column = (nb >= 0).nonzero(as_tuple=True)  # each pair of neighbouring selected cells once
    other = nb[one, column]
    src, dst = torch.cat([one, other]), torch.cat([other, one])
    label = torch.arange(cells.numel(), device=cells.device)  # positions in cells, ascending as the flat indices
    while True:
        beside = label.scatter_reduce(0, src, label[dst], "amax")  # the largest label beside a cell, or its own
        grown = label.scatter_reduce(0, label, beside, "amax")  # hook: a root takes the largest root beside its cells
        while True:
            jumped = grown[grown]
            if torch.equal(jumped, grown):
                break
            grown = jumped
        if torch.equal(grown, label):
            break
        label = grown
    out.view(-1)[cells] = cells[label] + 1
    return out


def connected_to(selected: Tensor, seeds: Tensor) -> Tensor:
    """Cells of ``selected`` [R, R, R] reachable from ``seeds`` through selected cells
    (26-neighbourhood), grown within the selected cells' bounding box."""
    out = torch.zeros_like(selected, dtype=torch.bool)
    nz = selected.nonzero()
    if len(nz) == 0:
        return out
    lo, hi = nz.min(dim=0).values.tolist(), (nz.max(dim=0).values + 1).tolist()
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    inside = selected[box]
    reached = seeds[box] & inside
    while True:
        grown = occupancy.dilate(reached, 1) & inside
        if torch.equal(grown, reached):
            break
        reached = grown
    out[box] = reached
    return out


# ----------------------------------------------------------------------------- select


def _strokes(v: ScribbleView, device) -> tuple[Tensor, Tensor]:
    """A view's scribbled and keep pixels [H·W] (a pixel both scribbled and kept is scribbled)."""
    scribbled = torch.from_numpy(v.scribble.reshape(-1)).to(device)
    kept = torch.zeros_like(scribbled) if v.keep is None else torch.from_numpy(v.keep.reshape(-1)).to(device) & ~scribbled
    return scribbled, kept


def _lift_views(field, k, views: Sequence[ScribbleView], min_opacity: float, renders: Sequence[RenderOutput] | None):
    """Positive and negative surface points of all views, plus each view's other surface points
    (negatives too, until self-training drops those that look like the part); and each view's
    (surface points, on-object mask), which :func:`_lift_mirrors` reads."""
    pos, neg, implied, surfaces = [], [], [], []
    for i, v in enumerate(views):
        pts, on = surface_points(field, v.camera, k, min_opacity, None if renders is None else renders[i])
        scribbled, kept = _strokes(v, on.device)
        pos.append(pts[scribbled & on])
        neg.append(pts[kept & on])
        implied.append(pts[on & ~scribbled & ~kept])
        surfaces.append((pts, on))
    return _cat_points(field, pos), _cat_points(field, neg), _cat_points(field, implied), surfaces


def _cat_points(field, xs: Sequence[Tensor]) -> Tensor:
    return torch.cat(list(xs)) if xs else torch.zeros(0, 3, device=field.aabb.device)


def _lift_mirrors(field, k, views: Sequence[ScribbleView], surfaces, mirror: Mirror, min_opacity: float) -> tuple[Tensor, Tensor, Tensor]:
    """The three point sets of :func:`_lift_views` for the views' mirror images
    (:func:`_lift_mirrored`; ``surfaces``: what :func:`_lift_views` returned of each view)."""
    mirrored = [_lift_mirrored(field, k, v, pts, on, mirror, min_opacity) for v, (pts, on) in zip(views, surfaces)]
    return tuple(_cat_points(field, list(x)) for x in zip(*mirrored))


def _lift_mirrored(field, k, v: ScribbleView, pts: Tensor, on: Tensor, mirror: Mirror, min_opacity: float):
    """The scribbles of view ``v`` (its surface points ``pts`` and on-object mask ``on``, [H·W])
    seen in a mirror: the view from the reflected camera, whose image is the original's flipped
    left–right where the instance is symmetric.  Its scribbled, keep and other surface points,
    kept where its surface agrees with the original's mirror image (:func:`.symmetry.agreeing`)."""
    h, w = v.camera.height, v.camera.width
    cam = mirror_camera(v.camera, mirror, field.aabb)
    m_pts, m_on = surface_points(field, cam, k, min_opacity)
    expected = mirror.points(field.aabb, pts.view(h, w, 3).flip(1).reshape(-1, 3))
    agree = m_on & on.view(h, w).flip(1).reshape(-1) & agreeing(m_pts, expected, mirror.cell(field.aabb))
    scribbled, kept = _strokes(ScribbleView(cam, mirror_image(v.scribble), mirror_image(v.keep)), m_on.device)
    return m_pts[agree & scribbled], m_pts[agree & kept], m_pts[agree & ~scribbled & ~kept]


def _cells_of(field, points: Tensor, res: int) -> Tensor:
    """[R, R, R] bool: the cells holding any of world ``points`` [M, 3]."""
    grid = torch.zeros(res, res, res, dtype=torch.bool, device=points.device)
    ijk, inside = occupancy.cell_index(field.normalize(points), res)
    ijk = ijk[inside]
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return grid


def _columns(groups: Sequence[str], widths: Sequence[int]) -> dict[str, Tensor]:
    """Each feature group's column indices in :func:`point_features`' output (``widths`` per group)."""
    return dict(zip(groups, torch.arange(sum(widths)).split(widths)))


def _group_standardizer(groups: Sequence[str], widths: Sequence[int], f_cells: Tensor, options: SelectOptions, position_scale: float = 1.0,
                        stats: tuple[Tensor, Tensor] | None = None, columns: Tensor | None = None):
    """:func:`_standardizer` over the cells' features with the groups weighted as ``options``
    say (position × ``position_scale``, for step 5b's distance)."""
    weight = {"position": options.position_weight * position_scale, "geometry": options.geometry_weight}
    return _standardizer(f_cells, widths, [weight.get(g, 1.0) for g in groups], stats, columns)


def _classify(groups: Sequence[str], widths: Sequence[int], f_pos, f_keep, f_view, f_cells, options: SelectOptions,
              stats: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Steps 3 and 5 on the columns of ``groups``: each occupied cell's probability [N] of
    being the part, from the features of the positives, keep points, the view's other surface
    points and the cells (unstandardized, ``widths`` columns per group); and the cells'
    standardized appearance [N, F] (every group but position and F_fuse's activations), which
    step 6 smooths along: the self-training's appearance fit reads F_fuse too, the bilateral
    smoothing's 26 neighbour distances do not (removals' gap closed within 0.01 of reading it
    on three of four models, and 0.13 s faster on a 37 000-cell grid with a 64-wide F_fuse)."""
    z = _group_standardizer(groups, widths, f_cells, options, stats=stats)
    columns = _columns(groups, widths)
    looks = torch.cat([c for g, c in columns.items() if g != "position"]) if len(groups) > 1 and "position" in groups else None
    z_pos, z_cells = z(f_pos), z(f_cells)
    clf = classifier(z_pos, z(f_keep), z(f_view), options.self_training, options.keep_weight,
                     looks if options.appearance_self_training else None)
    pred = clf(z_cells)
    gated = [c for g, c in columns.items() if g in ("bottleneck", "chroma")]
    if options.appearance_gate > 0 and gated:
        gated = torch.cat(gated)
        pred = pred * appearance_gate(z_cells[:, gated], z_pos[:, gated], options.appearance_gate)
    smooth = [c for g, c in columns.items() if g not in ("position", "fuse")]
    return pred, (z_cells[:, torch.cat(smooth)] if smooth else z_cells)


def _keep_veto(groups: Sequence[str], widths: Sequence[int], f_pos, f_keep, f_cells, options: SelectOptions,
               stats: tuple[Tensor, Tensor] | None = None) -> Tensor | None:
    """Step 5b: the cells [N] a keep stroke wins (:attr:`SelectOptions.keep_ratio`), in the
    :data:`KEEP_GROUPS` columns standardized as the classifier's, position weighted
    ``keep_position_weight`` × the classifier's weight; None when off or without keep points."""
    use = [g for g in groups if g in KEEP_GROUPS]
    if options.keep_ratio <= 0 or len(f_keep) == 0 or not use:
        return None
    columns = _columns(groups, widths)
    z = _group_standardizer(groups, widths, f_cells, options, options.keep_position_weight, stats, torch.cat([columns[g] for g in use]))
    return keep_wins(z(f_cells), z(f_pos), z(f_keep), options.keep_ratio)


def _refine(classified: tuple[Tensor, Tensor], cells: Tensor, neighbours: Tensor | None, occupied: Tensor, scribbled: Tensor,
            kept: Tensor, options: SelectOptions, veto: Tensor | None = None) -> Tensor:
    """Step 6: the cells' probabilities (``classified``: from :func:`_classify`, with their
    appearance; cells: flat indices of ``occupied``, ``neighbours`` their :func:`neighbour_table`,
    given when the smoothing is bilateral) as a grid [R, R, R], 0 where ``veto`` [N] (step 5b),
    smoothed, connected to the ``scribbled`` cells, 0 in the ``kept`` cells."""
    pred, looks = classified
    if veto is not None:
        pred = torch.where(veto, torch.zeros_like(pred), pred)
    if neighbours is not None:  # half the cell's own value: a thin part must survive its neighbours
        pred = bilateral_smooth(pred, looks, neighbours, options.smooth_bandwidth, options.smooth_rounds)
    values = torch.zeros(occupied.numel(), device=occupied.device)
    values[cells] = pred
    values = values.view(occupied.shape)
    if options.smooth and neighbours is None:
        values = 0.5 * (values + smooth_over_occupied(values, occupied))
    if options.connected:
        values = hysteresis(values, occupancy.dilate(scribbled, 1), options.threshold, options.threshold)
    return torch.where(kept, torch.zeros_like(values), values)


def _mirror_use(field, mirror: Mirror | None, mode: str, pos: Tensor, keep: Tensor):
    """(``mirror``, or None when the scribbles mean one side only, :func:`.symmetry.conflict`;
    what the selection's metadata says of it, None when ``mode`` is off).  Decided on the
    original views' points alone, before any mirrored view is rendered."""
    if mode == "off":
        return None, None
    if mirror is None:
        return None, {"mode": mode, "used": False, "why": "the instance is not mirror-symmetric"}
    meta = {"mode": mode, "axis": mirror.axis, "shift": mirror.shift, "overlap": round(mirror.overlap, 3)}
    cell = mirror.cell(field.aabb)
    clash = max(conflict(mirror.points(field.aabb, pos), keep, cell), conflict(mirror.points(field.aabb, keep), pos, cell))
    if clash > CONFLICT:
        return None, {**meta, "used": False, "why": f"the keep strokes cover {clash:.0%} of the scribble's mirror image"}
    return mirror, {**meta, "used": True}


def part_summary(meta: dict) -> str | None:
    """What a selection's metadata says of the part head, in a line (None: the model has none,
    or the selection was told not to read it)."""
    info = meta.get("part_head")
    if info is None:
        return None
    if info["used"]:
        return f"read (the scribbled points' part embeddings agree: coherence {info['coherence']:.2f})"
    return f"not read (coherence {info['coherence']:.2f} < {info['cut']:g}: it does not see the scribbled points as one part)"


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
                    else f"left {cells(gate['dropped'], '')} out of the joins (pieces of lines square to the scribble)")
    sheets = meta.get("sheet_veto")
    if sheets is not None and sheets["cells"] > 0:
        said.append(f"left {cells(sheets['cells'], 'sheet ')} out (the scribble lies on lines: {sheets['line_share']:.0%})")
    if rims is not None and rims["cells"] > 0:
        said.append(f"took {cells(rims['cells'], 'rim ')} (lines lying in the scribbled panel's plane)")
    return "; ".join(said) if said else "no rim taken"


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
    return f"{plane}; the selection took its mirror image"


@torch.no_grad()
def select(
    model: CategoryModel, instance: int | str, views: Sequence[ScribbleView], options: SelectOptions = SelectOptions(),
    renders: Sequence[RenderOutput] | None = None,
) -> Selection:
    """The 3-D selection the scribbles of ``views`` mean (see the module docstring).
    ``renders`` are the views' renders of the instance when the caller has them already."""
    started = time.perf_counter()
    k = model.instance_index(instance)
    if not views:
        raise CrfError("select: give at least one view with a scribble")
    for i, v in enumerate(views):
        if not v.scribble.any():
            raise CrfError(f"the scribble of view {i + 1} is empty: no pixel is set")
    if options.shape_from not in SHAPE_SOURCES:
        raise CrfError(f"selection shape_from {options.shape_from!r}: expected one of {', '.join(SHAPE_SOURCES)}")
    if options.mirror not in MIRROR_MODES:
        raise CrfError(f"selection mirror mode {options.mirror!r}: expected one of {', '.join(MIRROR_MODES)}")
    field = model.field_for(k)
    occupied = field.occupancy[k]
    res = occupied.shape[-1]
    pos_pts, neg_pts, cand_pts, surfaces = _lift_views(field, k, views, options.min_opacity, renders)
    if pos_pts.shape[0] == 0:
        raise CrfError("the scribble lies on the background only: no scribbled pixel covers the object in its view")
    mirror = find_mirror(occupied) if options.mirror != "off" else None
    mirror, mirror_meta = _mirror_use(field, mirror, options.mirror, pos_pts, neg_pts)
    if mirror is not None and options.mirror == "views":
        mirrored = _lift_mirrors(field, k, views, surfaces, mirror, options.min_opacity)
        mirror_meta.update(positives=int(len(mirrored[0])), keep_points=int(len(mirrored[1])))
        pos_pts, neg_pts, cand_pts = (torch.cat([a, b]) for a, b in zip((pos_pts, neg_pts, cand_pts), mirrored))
    cells = occupied.reshape(-1).nonzero().squeeze(-1)
    centres, fused, sigma = occupancy.cell_centers(res, occupied.device)[cells], None, None
    if options.cell_ascent > 0:  # a half cell is 1/res in normalized units
        centres, fused, sigma = denser_points(field, k, centres, options.cell_ascent / res)
    cell_pts = field.denormalize(centres)
    eye = torch.as_tensor(np.asarray(views[0].camera.c2w)[:3, 3], dtype=torch.float32, device=occupied.device)
    groups, part_meta, fused_pos = options.features, None, None
    if options.part_head and field.F_part is not None and "part" not in groups:
        fused_pos = field.fuse_features(field.normalize(pos_pts), k)  # point_features reuses it
        coherence = float(field.part_embedding(fused_pos).mean(dim=0).norm())
        part_meta = {"coherence": round(coherence, 3), "cut": options.part_coherence, "used": coherence >= options.part_coherence}
        if part_meta["used"]:
            groups = (*groups, "part")
    shape_grid = None
    if "geometry" in groups:
        shape_grid = cell_opacity(field, k, occupied, sigma) if options.shape_from == "density" else occupied
    feats = lambda p, fused_p=None: point_features(field, k, p, eye, groups, fused_p, shape_grid, options.shape_radius, options.chroma_offset)
    scribbled_frames, shape_gate, gate_meta = None, options.shape_gate > 0 and shape_grid is not None, {"dropped": 0}
    if shape_grid is not None and (options.shape_gate > 0 or options.rim_fill > 0 or options.sheet_veto > 0):
        scribbled_frames = local_frames(shape_grid, field.normalize(evenly(pos_pts, SHAPE_GATE_POINTS)), SHAPE_GATE_RADIUS)

    def shape_test(where: Tensor, test) -> Tensor:
        """[R, R, R] bool: ``test`` (:class:`Frames` [M] → [M] bool) of the occupied cells of
        ``where`` [R, R, R], their frames read at those cells only; False elsewhere."""
        at_cells = where.reshape(-1)[cells]
        out = torch.zeros(res**3, dtype=torch.bool, device=occupied.device)
        if bool(at_cells.any()):
            out[cells[at_cells]] = test(local_frames(shape_grid, centres[at_cells], SHAPE_GATE_RADIUS))
        return out.view(res, res, res)

    def gated(added: Tensor) -> Tensor:
        """The cells of ``added`` [R, R, R] that :attr:`SelectOptions.shape_gate` leaves out
        (:func:`gate_pieces` of the :func:`odd_lines` among them)."""
        drop = gate_pieces(added, shape_test(added, lambda f: odd_lines(f, scribbled_frames)), options.shape_gate)
        gate_meta["dropped"] += int(drop.sum())
        return drop

    f_pos, f_keep, f_view, f_cells = feats(pos_pts, fused_pos), feats(neg_pts), feats(cand_pts), feats(cell_pts, fused)
    widths = [group_width(g, field.cfg) for g in groups]
    scribbled, kept = _cells_of(field, pos_pts, res), _cells_of(field, neg_pts, res)
    neighbours = neighbour_table(cells, res) if options.smooth and options.smooth_bandwidth > 0 else None
    stats = _feature_stats(f_cells)
    veto = _keep_veto(groups, widths, f_pos, f_keep, f_cells, options, stats)
    spared = kept.clone()  # keep-stroke cells and those a keep stroke wins: no join takes them
    if veto is not None:
        spared.view(-1)[cells[veto]] = True
    values = _refine(_classify(groups, widths, f_pos, f_keep, f_view, f_cells, options, stats), cells, neighbours, occupied, scribbled, kept, options, veto)
    columns = _columns(groups, widths)
    union, saturation, spread = None, 0.0, None
    if "chroma" in groups:  # the cells' chromaticity distances, once for every test below
        spread = chroma_spread(f_cells[:, columns["chroma"]], f_pos[:, columns["chroma"]])
        med = spread[2]  # HSV saturation of the scribbled points' median chromaticity
        saturation = float((med.max() - med.min()) / med.max().clamp_min(1e-6))

    def alike_grid(factor: float, floor: float = 0.01) -> Tensor:
        """[R, R, R] bool: the occupied cells whose chromaticity is the scribbled points'
        (:func:`chroma_alike` with ``factor`` and ``floor``, from ``spread``)."""
        alike = torch.zeros(res**3, dtype=torch.bool, device=occupied.device)
        alike[cells] = within_spread(spread, factor, floor)
        return alike.view(res, res, res)

    if options.chroma_union > 0 and "chroma" in groups and len(groups) > 1:  # see SelectOptions.chroma_union
        c = columns["chroma"]
        union = {"saturation": round(saturation, 3), "cells": None, "joined": False}
        if saturation >= options.chroma_saturation:
            alone = _refine(_classify(("chroma",), [WIDTHS["chroma"]], f_pos[:, c], f_keep[:, c], f_view[:, c], f_cells[:, c], options,
                                      (stats[0][c], stats[1][c])),
                            cells, neighbours, occupied, scribbled, kept, options, veto)
            if options.join_chroma > 0:  # see SelectOptions.join_chroma
                alone = torch.where(alike_grid(options.join_chroma), alone, torch.zeros_like(alone))
            if shape_gate:  # see SelectOptions.shape_gate
                alone = torch.where(gated((alone >= options.threshold) & (values < options.threshold)), torch.zeros_like(alone), alone)
            n_main, n_alone = int((values >= options.threshold).sum()), int((alone >= options.threshold).sum())
            cap = options.pale_union if options.pale_union > 0 and saturation < options.pale_saturation else options.chroma_union
            union.update(cells=n_alone, joined=n_alone <= cap * max(n_main, 1))
            if union["joined"]:
                values = torch.maximum(values, alone)
    def cap_unlike(values: Tensor, factor: float, below: float, low: float = 0.0, high: float = options.threshold,
                   floor: float = 0.01, spare: Tensor | None = None) -> Tensor:
        """``values`` with each cell of value in [``low``, ``high``) whose chromaticity is
        unlike the scribbled points' (:func:`chroma_alike` with ``factor`` and ``floor``)
        capped just below ``below``; the cells of ``spare`` [R, R, R] are left as they are."""
        unlike = (values < high) & (values >= low) & ~alike_grid(factor, floor)
        if spare is not None:
            unlike &= ~spare
        return torch.where(unlike, values.clamp(max=below * 0.999), values)

    if options.skin_chroma > 0 and "chroma" in groups:  # see SelectOptions.skin_chroma
        values = cap_unlike(values, options.skin_chroma, GROW_LOW)
    at = options.threshold if options.select_threshold is None else options.select_threshold
    if at < options.threshold and saturation < options.chroma_saturation:  # see SelectOptions.band_chroma
        at = options.threshold
    elif at < options.threshold and options.band_chroma > 0 and "chroma" in groups:
        values = cap_unlike(values, options.band_chroma, at, low=at)
    if options.veto_chroma > 0 and "chroma" in groups and saturation >= options.chroma_saturation:  # see SelectOptions.veto_chroma
        values = cap_unlike(values, options.veto_chroma, GROW_LOW, low=GROW_LOW, high=float("inf"), floor=options.veto_floor, spare=scribbled)
    if options.pale_veto > 0 and "chroma" in groups and saturation < options.pale_veto_saturation:  # see SelectOptions.pale_veto
        values = cap_unlike(values, options.pale_veto, GROW_LOW, low=GROW_LOW, high=float("inf"), floor=options.pale_veto_floor, spare=scribbled)
    if "part" in groups:  # see SelectOptions.part_veto and part_join
        c = columns["part"]
        alike = torch.full((res**3,), -1.0, device=occupied.device)
        alike[cells] = f_cells[:, c] @ F.normalize(f_pos[:, c].mean(dim=0), dim=0)
        alike = alike.view(res, res, res)
        if options.part_veto > 0:
            unlike = occupied & (alike < options.part_veto) & ~scribbled
            values = torch.where(unlike, values.clamp(max=GROW_LOW * 0.999), values)
        if options.part_join > 0:
            like = occupied & (alike >= options.part_join) & ~spared
            like &= connected_to(like | (values >= at), occupancy.dilate(scribbled, 1))
            if shape_gate:  # see SelectOptions.shape_gate
                like &= ~gated(like & (values < at))
            values = torch.where(like, values.clamp_min(at), values)
    if options.sheet_veto > 0 and scribbled_frames is not None:  # see SelectOptions.sheet_veto
        sheet_meta = {"line_share": round(float(lines_of(scribbled_frames).float().mean()), 3), "cells": 0}
        if sheet_meta["line_share"] >= options.sheet_veto:
            sheet = shape_test((values >= GROW_LOW) & ~scribbled, sheets_of)
            values = torch.where(sheet, values.clamp(max=GROW_LOW * 0.999), values)
            sheet_meta["cells"] = int(sheet.sum())
    if options.rim_fill > 0 and shape_grid is not None:  # see SelectOptions.rim_fill
        rim_meta = {"cells": 0}
        sheets = scribbled_frames.planar > scribbled_frames.linear
        if float(sheets.float().mean()) >= RIM_SHEETS:
            sel_now = values >= at
            ring = occupancy.dilate(sel_now, 1) & occupied & ~sel_now & ~spared
            rim = shape_test(ring, lambda f: rim_lines(f, scribbled_frames, options.rim_fill))
            values = torch.where(rim, values.clamp_min(at), values)
            rim_meta["cells"] = int(rim.sum())
    if options.fill_share > 0:  # see SelectOptions.fill_share
        values = fill_rims(values, at, occupied, kept, options.fill_share)
    if mirror is not None and options.mirror == "values":  # see SelectOptions.mirror
        both = occupied & mirror.grid(occupied)
        values = torch.where(both & ~kept, torch.maximum(values, mirror.grid(values)), values)
    values = quantized(values, (at, options.threshold, GROW_LOW))
    meta = {
        "positives": int(pos_pts.shape[0]), "keep_points": int(neg_pts.shape[0]), "view_points": int(cand_pts.shape[0]),
        "views": len(views), "features": list(groups), "occupied_cells": int(cells.numel()),
        "selected_cells": int((values >= at).sum()), "seconds": round(time.perf_counter() - started, 4),
    }
    if veto is not None:
        meta["keep_wins_cells"] = int(veto.sum())
    if union is not None:
        meta["chroma_union"] = union
    if mirror_meta is not None:
        meta["mirror"] = mirror_meta
    if part_meta is not None:
        meta["part_head"] = part_meta
    if shape_gate:
        meta["shape_gate"] = gate_meta
    if options.sheet_veto > 0 and scribbled_frames is not None:
        meta["sheet_veto"] = sheet_meta
    if options.rim_fill > 0 and shape_grid is not None:
        meta["rim_fill"] = rim_meta
    return Selection(values, k, model.names[k], model.fingerprint(), meta, at)


def quantized(values: Tensor, cuts: Sequence[float]) -> Tensor:
    """``values`` [R, R, R] clamped to [0, 1] and rounded to the 256 levels k/255 a selection
    file stores, each cell kept on its side of every cut in ``cuts``.

    A selection is used as computed (the page, one-step edits) and as read back from its file
    (``--selection``): the two must be the same tensor.  Plain rounding is not enough at a cut:
    filling the rims sets cells to exactly the recolour's cut 0.3, which rounds to 76/255 =
    0.298, below it, so a file dropped every filled cell."""
    v = values.clamp(0, 1)
    q = (v * 255).round()
    levels = torch.arange(256, dtype=q.dtype, device=q.device)
    for cut in cuts:
        up = float(levels[levels / 255.0 >= cut][0]) if cut <= 1 else 256.0  # the lowest level on or above the cut, read
        down = up - 1  # back as the file's reader does (float32), and the one below it
        q = torch.where((v >= cut) & (q / 255.0 < cut), torch.full_like(q, up), q)
        q = torch.where((v < cut) & (q / 255.0 >= cut), torch.full_like(q, down), q)
    return q / 255.0


# ----------------------------------------------------------------------------- file


def save_selection(path: str | Path, sel: Selection) -> None:
    """Write ``sel`` atomically as safetensors (version 2), sparse: ``nonzero`` uint8, one bit per
    cell of the [R, R, R] grid in C order (most significant first, as ``numpy.packbits``), set
    where the value is above 0; ``levels`` uint8, value·255 of each such cell in the same order;
    and string metadata, ``shape`` the grid's JSON shape.  A 64³ grid's mask is 32 KiB plus a
    byte per cell with a value, against 256 KiB for the whole grid as uint8 (version 1)."""
    q = (sel.values * 255).round().to(torch.uint8).cpu().contiguous().numpy()
    nonzero = q.reshape(-1) != 0
    meta = {
        "format": FORMAT, "version": VERSION, "model_fingerprint": sel.model_fingerprint,
        "instance": sel.instance_name, "instance_index": str(sel.instance), "threshold": repr(sel.threshold),
        "shape": json.dumps(list(q.shape)), "info": json.dumps(sel.meta, sort_keys=True),
    }
    tensors = {SPARSE[0]: pack_bits(nonzero), SPARSE[1]: torch.from_numpy(q.reshape(-1)[nonzero])}
    write_safetensors(Path(path), tensors, meta)


def grid_values(path: str | Path, tensors: dict[str, Tensor], meta: dict[str, str]) -> Tensor:
    """The uint8 [R, R, R] grid a selection file holds, in either version; every shape, length
    and padding bit is checked (a declared shape the file does not fill allocates nothing)."""
    def bad(why: str) -> CrfError:
        return CrfError(f"{path}: bad selection grid ({why})")

    if meta.get("version") == "1":
        values = tensors.get("values")
        if values is None or values.dtype != torch.uint8 or values.dim() != 3 or len(set(values.shape)) != 1:
            raise CrfError(f"{path}: 'values' must be a uint8 [R, R, R] grid")
        if values.shape[0] > MAX_GRID_SIDE:
            raise bad(f"its side is {values.shape[0]}, at most {MAX_GRID_SIDE}")
        return values
    if set(tensors) != set(SPARSE) or "shape" not in meta:
        raise bad(f"a version-2 file holds the tensors {' and '.join(SPARSE)} and the metadata key shape")
    dims = grid_shape(meta["shape"], bad)
    if len(set(dims)) != 1:
        raise bad(f"the grid must be a cube, not {dims}")
    nonzero = unpack_bits(tensors[SPARSE[0]], dims[0] ** 3, SPARSE[0], bad, "cells")
    levels = tensors[SPARSE[1]]
    if levels.dtype != torch.uint8 or levels.dim() != 1 or levels.numel() != int(nonzero.sum()):
        raise bad(f"{SPARSE[1]} must be {int(nonzero.sum())} uint8 values, one per set bit of {SPARSE[0]}, not {list(levels.shape)} {str(levels.dtype).replace('torch.', '')}")
    if levels.numel() and int(levels.min()) == 0:
        raise bad(f"{SPARSE[1]} holds a 0 where {SPARSE[0]} says the cell has a value")
    out = np.zeros(dims[0] ** 3, dtype=np.uint8)
    out[nonzero] = levels.numpy()
    return torch.from_numpy(out.reshape(dims))


def load_selection(path: str | Path) -> Selection:
    """Read a selection file, version 1 or 2 (safetensors only; nothing in it is executed)."""
    tensors, meta = read_safetensors(Path(path))
    if meta.get("format") != FORMAT:
        raise CrfError(f"{path}: not a crfedit selection file (format {meta.get('format')!r}){other_kind(meta.get('format'))}")
    if meta.get("version") not in READ_VERSIONS:
        raise CrfError(f"{path}: selection format version {meta.get('version')!r} is not supported (expected {' or '.join(READ_VERSIONS)})")
    values = grid_values(path, tensors, meta)
    try:
        info = json.loads(meta.get("info", "{}"))
        threshold = float(meta.get("threshold", "0.5"))
        index = int(meta.get("instance_index", "-1"))
    except ValueError as e:
        raise CrfError(f"{path}: corrupt selection metadata ({e})") from None
    return Selection(values.float() / 255.0, index, meta.get("instance", ""), meta.get("model_fingerprint", ""), info, threshold)


# ----------------------------------------------------------------------------- preview

TINT = (1.0, 0.15, 0.1)
"""Colour blended over the selected surface in a preview."""


@torch.no_grad()
def preview(model: CategoryModel, sel: Selection, camera: Camera, strength: float = 0.6) -> np.ndarray:
    """The instance's render from ``camera`` [H, W, 3] with the selected surface tinted, so the
    user sees what an edit will change before any weight moves."""
    field = model.field_for(sel.instance)
    out = render_camera(field, camera, sel.instance)
    pts, on = surface_points(field, camera, sel.instance, out=out)
    hit = (sel.at(field.normalize(pts)) & on).reshape(camera.height, camera.width, 1)
    tint = torch.tensor(TINT, device=out.rgb.device)
    rgb = torch.where(hit, (1 - strength) * out.rgb + strength * tint, out.rgb)
    return rgb.clamp(0, 1).cpu().numpy()
