"""Scribbles lifted to an explicit 3-D part selection over an instance's occupancy grid.

The paper's edits constrain only the scribbled view's rays; nothing says where the part is in
3-D, so density drops wherever features resemble the scribble.  Here the scribbles first become
a selection S (one soft value per occupancy cell), which the edits then supervise with
(:mod:`.supervised`) and which a user can preview before any weight moves.

1. **Lift.**  Each scribbled pixel on the object becomes a surface point at the rendered
   expected depth (a *positive*); each keep-stroke pixel on the object a *negative*.
   Every edit kind lifts each scribble's and keep stroke's centre, its 1-px erosion, when
   that keeps a fifth of it (:data:`STROKE_CENTRES`): a brush wider than a thin part strays
   off it.  Recolours and removals first snap a scribble that lies mostly off the object onto
   the object pixels beside it (:data:`STROKE_SNAP`): a stroke a pixel beside a tube.
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
   frame scribbled on its backrest) leave the negatives.  Under a scribble on bars, the view
   points whose cells are not lines never leave them (:attr:`SelectOptions.line_negatives`).
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
   and only where the chromaticity is the scribbled points' (:attr:`SelectOptions.join_chroma`);
   under a scribble on bars, without the pieces that are not lines (:attr:`SelectOptions.join_lines`).

8. **Recolours of saturated parts: a lower cut.**  A recolour's selection of a part that
   passes step 7's saturation test also takes the cells of value :data:`COLOR_THRESHOLD`–0.5
   whose chromaticity is the scribbled points' (:attr:`SelectOptions.select_threshold`,
   :attr:`SelectOptions.band_chroma`).
9. **Fill the rims.**  A recolour's selection also takes each occupied cell at least
   :data:`COLOR_FILL_SHARE` of whose occupied 3×3×3 neighbourhood is selected, a removal's at
   least :data:`REMOVE_FILL_SHARE` (:attr:`SelectOptions.fill_share`, :func:`fill_rims`): a
   slab's lit top face and side faces shade unlike its scribbled front and score low, but
   every occupied cell around them is the slab.
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

The package follows these steps, one concept per module:

- :mod:`.options`: :class:`SelectOptions`, each edit kind's options (:func:`options_for`) and
  the measured constants behind them;
- :mod:`.base`: the input and the result, :class:`ScribbleView` and :class:`Selection`;
- :mod:`.features`: lifting (step 1) and the per-point features (step 2);
- :mod:`.classify`: the logistic regression, self-training and distance gates (steps 3–5b);
- :mod:`.refine`: smoothing, rims and connectivity over the occupancy grid (step 6);
- :mod:`.shapes`: the shape gate's orientation tests (step 10b);
- :mod:`.pipeline`: :func:`select`, which runs the steps in order (7–11 live there);
- :mod:`.store`: the selection file; :mod:`.tint`: the tinted preview.
"""

from .base import SUMMARIES, ScribbleView, Selection, coverage_summary, join_summary, keep_summary, lines_summary, mirror_summary, part_summary, pieces_summary, shape_summary, stroke_summary
from .features import CellPoints, cell_points, point_features, surface_points
from .options import EDIT_KINDS, FEATURES, GROW_LOW, MIN_OPACITY, SelectOptions, options_for
from .pipeline import select, select_for
from .store import FORMAT, load_selection, save_selection
from .tint import preview

__all__ = [
    "CellPoints", "EDIT_KINDS", "FEATURES", "FORMAT", "GROW_LOW", "MIN_OPACITY", "SUMMARIES", "ScribbleView", "SelectOptions", "Selection", "load_selection",
    "coverage_summary", "join_summary", "keep_summary", "lines_summary", "mirror_summary", "options_for", "part_summary", "pieces_summary", "cell_points", "point_features", "preview", "save_selection", "select", "select_for", "shape_summary", "stroke_summary",
    "surface_points",
]
