""":func:`select`: the steps of the package docstring, from scribbled views to a
:class:`~.base.Selection`."""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ... import occupancy
from ...errors import CrfError
from ...model import CategoryModel
from ...names import MIRROR_MODES
from ...parts import labelled_names
from ...masks import dilate, erode
from ...renderer import RenderOutput, render_camera
from ...runtime import full_precision
from ..scribble import require_on_object
from ..symmetry import CONFLICT, Mirror, agreeing, conflict, find_mirror, mirror_camera, mirror_image
from .base import ScribbleView, Selection
from .classify import appearance_gate, chroma_spread, chromaticity, classifier, evenly, feature_stats, keep_wins, nearest_cosine, standardizer, within_spread
from .features import SHAPE_SOURCES, CellPoints, FrameTable, cell_opacity, cell_points, group_width, local_frames, local_shape, point_features, surface_points
from .options import CENTRE_SHARE, GROW_LOW, KEEP_GROUPS, MIN_OPACITY, STRAY_FLOOR, STRAY_SHARE, SelectOptions, WIDTHS, options_for
from .refine import bilateral_smooth, components, connected_to, fill_rims, large_pieces, neighbour_table, raised, smooth_over_occupied
from .shapes import BARS_RADIUS, JOIN_LINES, RIM_SHEETS, SHAPE_GATE_POINTS, SHAPE_GATE_RADIUS, gate_pieces, lines_of, odd_lines, rim_lines, sheets_of
from .store import quantized


def _strokes(v: ScribbleView, device) -> tuple[Tensor, Tensor]:
    """A view's scribbled and keep pixels [H·W] (a pixel both scribbled and kept is scribbled)."""
    scribbled = torch.from_numpy(v.scribble.reshape(-1)).to(device)
    kept = torch.zeros_like(scribbled) if v.keep is None else torch.from_numpy(v.keep.reshape(-1)).to(device) & ~scribbled
    return scribbled, kept


WHOLE_SCRIBBLE = 0.95
"""A view whose scribble covers at least this share of the pixels that show the instance, with
no keep stroke in any view, selects the whole instance: it was asked for all of it.  Taken part
by part, a scribble over a whole chair (removal) lay on sheets, so the sheet rules left its legs
and stretchers standing and half the chair stayed."""


def _on_object(field, k, v: ScribbleView, render: RenderOutput, min_opacity: float) -> np.ndarray:
    """[H, W] bool: the pixels of view ``v`` that show the object (and lift to a surface point)."""
    return surface_points(field, v.camera, k, min_opacity, render)[1].view(v.camera.height, v.camera.width).cpu().numpy()


def whole_share(views: Sequence[ScribbleView], on_object: Sequence[np.ndarray]) -> float | None:
    """The share of what a view shows of the instance its scribble covers, the largest over
    ``views`` (``on_object``: each view's :func:`_on_object`), when it reaches
    :data:`WHOLE_SCRIBBLE` and no keep stroke lies on the object in any view (keep strokes on the
    background hold nothing back); None otherwise."""
    if any(v.keep is not None and (v.keep & on).any() for v, on in zip(views, on_object)):
        return None
    share = max(float((v.scribble & on).sum()) / max(1, int(on.sum())) for v, on in zip(views, on_object))
    return round(share, 3) if share >= WHOLE_SCRIBBLE else None


def view_on_object(field, k, view: ScribbleView, min_opacity: float = MIN_OPACITY, render: RenderOutput | None = None) -> np.ndarray:
    """[H, W] bool: the pixels of ``view`` that show the object, from ``render`` (its opacity
    render, as :func:`select` takes them) or rendered here."""
    render = render_camera(field, view.camera, k, colour=False) if render is None else render
    return _on_object(field, k, view, render, min_opacity)


def _snapped_strokes(views: Sequence[ScribbleView], on_object: Sequence[np.ndarray], share: float) -> tuple[list[ScribbleView], int]:
    """(``views`` with each scribble that has less than ``share`` of its pixels on the object
    (``on_object``: each view's :func:`_on_object`) snapped onto it: the on-object pixels next
    to its off-object pixels, and not kept, are added; the pixels added),
    :attr:`SelectOptions.stroke_snap`."""
    out, added = [], 0
    for v, on in zip(views, on_object):
        if (v.scribble & on).sum() >= share * v.scribble.sum():
            out.append(v)
            continue
        near = dilate(v.scribble & ~on, 1) & on & ~v.scribble
        if v.keep is not None:
            near &= ~v.keep
        out.append(ScribbleView(v.camera, v.scribble | near, v.keep))
        added += int(near.sum())
    return out, added


def _stroke_centres(views: Sequence[ScribbleView], on_object: Sequence[np.ndarray]) -> tuple[list[ScribbleView], int, int, int]:
    """(``views`` with each scribble and each view's keep strokes cut to their centres
    (:func:`_centre`; ``on_object``: each view's :func:`_on_object`), the scribbled and the keep
    surface points left out, the views whose scribble was lifted whole),
    :attr:`SelectOptions.stroke_centres`."""
    out, dropped, dropped_keep, whole = [], 0, 0, 0
    for v, on in zip(views, on_object):
        scribble, n = _centre(v.scribble, on)
        keep, n_keep = (None, 0) if v.keep is None else _centre(v.keep & ~v.scribble, on)
        out.append(ScribbleView(v.camera, scribble, keep))
        dropped, dropped_keep = dropped + n, dropped_keep + n_keep
        whole += int(scribble is v.scribble and bool(v.scribble.any()))
    return out, dropped, dropped_keep, whole


def _centre(strokes: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, int]:
    """(``strokes`` [H, W] cut to their 1-px erosion where that keeps at least
    :data:`CENTRE_SHARE` of their surface points (``on``: the view's on-object mask) and 4,
    else the very array given; the surface points left out).

    The pieces of the strokes 1–2 px wide (:func:`thin_pieces`) stay whole beside the erosion,
    as a thin scribble alone does: a 2-px stroke along a seat's edge drawn on from a 5-px
    stroke on the back has no erosion, and cut to the centre it vanished (the seat stayed)."""
    centre = erode(strokes, 1)
    n_all, n_centre = int((strokes & on).sum()), int((centre & on).sum())
    if n_centre < max(4, CENTRE_SHARE * n_all):
        return strokes, 0
    centre = centre | thin_pieces(strokes, centre)
    return centre, n_all - int((centre & on).sum())


def thin_pieces(strokes: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """[H, W] The pixels of ``strokes`` farther than a pixel from every 3×3 square that fits
    inside them (``centre``: their erosion, whose dilation is those squares' union): a piece
    1–2 px wide.  A wide stroke's own edge lies within a pixel of such a square, so its
    strays stay out."""
    return strokes & ~dilate(dilate(centre, 1) & strokes, 1)


def _lift_views(field, k, views: Sequence[ScribbleView], min_opacity: float, renders: Sequence[RenderOutput] | None,
                strays: float = 0.0):
    """Positive and negative surface points of all views, plus each view's other surface points
    (negatives too, until self-training drops those that look like the part); each view's
    (surface points, on-object mask), which :func:`_lift_mirrors` reads; and how many
    scribbled points were left out as strays (:func:`_strays`, when ``strays`` > 0)."""
    pos, neg, implied, surfaces, dropped = [], [], [], [], 0
    for i, v in enumerate(views):
        pts, on = surface_points(field, v.camera, k, min_opacity, None if renders is None else renders[i])
        scribbled, kept = _strokes(v, on.device)
        p, n = pts[scribbled & on], pts[kept & on]
        if strays > 0 and n.shape[0] > 0 and p.shape[0] > 0:  # a view of keep strokes alone has no scribble to compare
            stray = _strays(field, k, p, n, v.camera, strays)
            p, dropped = p[~stray], dropped + int(stray.sum())
        pos.append(p)
        neg.append(n)
        implied.append(pts[on & ~scribbled & ~kept])
        surfaces.append((pts, on))
    return _cat_points(field, pos), _cat_points(field, neg), _cat_points(field, implied), surfaces, dropped


def _strays(field, k, pos: Tensor, keep: Tensor, camera, ratio: float) -> Tensor:
    """[n] bool: the scribbled points ``pos`` [n, 3] of one view that look like its keep
    strokes' points ``keep`` [m, 3], not like the rest of the scribble
    (:attr:`SelectOptions.keep_strays`): their chromaticity, seen from the camera, lies within
    ``ratio`` × its distance to the scribble's median chromaticity of some kept point's, and
    more than :data:`STRAY_FLOOR` from that median.  Chromaticity, not colour: the lit face of a
    grey back is as bright as the beige seat kept beside it, and is not a stray.  None are
    strays when more than :data:`STRAY_SHARE` of the scribble would be: it then means both."""
    eye = torch.as_tensor(np.asarray(camera.c2w)[:3, 3], dtype=torch.float32, device=pos.device)
    colour = chromaticity(point_features(field, k, torch.cat([pos, keep]), eye, ("color",)))
    c_pos, c_keep = colour[: pos.shape[0]], colour[pos.shape[0]:]
    to_median = (c_pos - c_pos.median(dim=0).values).norm(dim=-1)
    to_keep = torch.cdist(c_pos, c_keep).amin(dim=-1)
    stray = (to_keep < ratio * to_median) & (to_median > STRAY_FLOOR)
    if float(stray.float().mean()) > STRAY_SHARE:
        return torch.zeros_like(stray)
    return stray


def _cat_points(field, xs: Sequence[Tensor]) -> Tensor:
    return torch.cat(list(xs)) if xs else torch.zeros(0, 3, device=field.aabb.device)


def _lift_mirrors(field, k, views: Sequence[ScribbleView], surfaces, mirror: Mirror, min_opacity: float, render=None) -> tuple[Tensor, Tensor, Tensor]:
    """The three point sets of :func:`_lift_views` for the views' mirror images
    (:func:`_lift_mirrored`; ``surfaces``: what :func:`_lift_views` returned of each view;
    ``render``: a camera → its render without colour, None to render each here)."""
    mirrored = [_lift_mirrored(field, k, v, pts, on, mirror, min_opacity, render) for v, (pts, on) in zip(views, surfaces)]
    return tuple(_cat_points(field, list(x)) for x in zip(*mirrored))


def _lift_mirrored(field, k, v: ScribbleView, pts: Tensor, on: Tensor, mirror: Mirror, min_opacity: float, render=None):
    """The scribbles of view ``v`` (its surface points ``pts`` and on-object mask ``on``, [H·W])
    seen in a mirror: the view from the reflected camera, whose image is the original's flipped
    left–right where the instance is symmetric.  Its scribbled, keep and other surface points,
    kept where its surface agrees with the original's mirror image (:func:`.symmetry.agreeing`)."""
    h, w = v.camera.height, v.camera.width
    cam = mirror_camera(v.camera, mirror, field.aabb)
    m_pts, m_on = surface_points(field, cam, k, min_opacity, None if render is None else render(cam))
    expected = mirror.points(field.aabb, pts.view(h, w, 3).flip(1).reshape(-1, 3))
    agree = m_on & on.view(h, w).flip(1).reshape(-1) & agreeing(m_pts, expected, mirror.cell(field.aabb))
    scribbled, kept = _strokes(ScribbleView(cam, mirror_image(v.scribble), mirror_image(v.keep)), m_on.device)
    return m_pts[agree & scribbled], m_pts[agree & kept], m_pts[agree & ~scribbled & ~kept]


def _camera_key(camera) -> tuple:
    """A hashable key of a camera (its pose's bytes, focal and size)."""
    return (np.asarray(camera.c2w, dtype=np.float64).tobytes(), float(camera.focal), int(camera.width), int(camera.height))


def _cells_of(field, points: Tensor, res: int) -> Tensor:
    """[R, R, R] bool: the cells holding any of world ``points`` [M, 3]."""
    grid = torch.zeros(res, res, res, dtype=torch.bool, device=points.device)
    ijk, inside = occupancy.cell_index(field.normalize(points), res)
    ijk = ijk[inside]
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return grid


def _columns(groups: Sequence[str], widths: Sequence[int], device: torch.device) -> dict[str, Tensor]:
    """Each feature group's column indices in :func:`point_features`' output (``widths`` per
    group), on ``device``: ``index_select`` takes its index on the features' device."""
    return dict(zip(groups, torch.arange(sum(widths), device=device).split(widths)))


def _group_standardizer(groups: Sequence[str], widths: Sequence[int], f_cells: Tensor, options: SelectOptions, position_scale: float = 1.0,
                        stats: tuple[Tensor, Tensor] | None = None, columns: Tensor | None = None):
    """:func:`standardizer` over the cells' features with the groups weighted as ``options``
    say (position × ``position_scale``, for step 5b's distance)."""
    weight = {"position": options.position_weight * position_scale, "geometry": options.geometry_weight}
    return standardizer(f_cells, widths, [weight.get(g, 1.0) for g in groups], stats, columns)


def _classify(groups: Sequence[str], widths: Sequence[int], f_pos, f_keep, f_view, f_cells, options: SelectOptions,
              stats: tuple[Tensor, Tensor] | None = None, held: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Steps 3 and 5 on the columns of ``groups``: each occupied cell's probability [N] of
    being the part, from the features of the positives, keep points, the view's other surface
    points (those ``held`` marks stay negatives, :attr:`SelectOptions.line_negatives`) and the
    cells (unstandardized, ``widths`` columns per group); and the cells'
    standardized appearance [N, F] (every group but position and F_fuse's activations), which
    step 6 smooths along: the self-training's appearance fit reads F_fuse too, the bilateral
    smoothing's 26 neighbour distances do not (removals' gap closed within 0.01 of reading it
    on three of four models, and 0.13 s faster on a 37 000-cell grid with a 64-wide F_fuse)."""
    z = _group_standardizer(groups, widths, f_cells, options, stats=stats)
    columns = _columns(groups, widths, f_cells.device)
    looks = torch.cat([c for g, c in columns.items() if g != "position"]) if len(groups) > 1 and "position" in groups else None
    z_pos, z_cells = z(f_pos), z(f_cells)
    clf = classifier(z_pos, z(f_keep), z(f_view), options.self_training, options.keep_weight,
                     looks if options.appearance_self_training else None, held)
    pred = clf(z_cells)
    gated = [c for g, c in columns.items() if g in ("bottleneck", "chroma")]
    if options.appearance_gate > 0 and gated:
        gated = torch.cat(gated)
        pred = pred * appearance_gate(z_cells.index_select(1, gated), z_pos.index_select(1, gated), options.appearance_gate)
    smooth = [c for g, c in columns.items() if g not in ("position", "fuse")]
    return pred, (z_cells.index_select(1, torch.cat(smooth)) if smooth else z_cells)


def _keep_veto(groups: Sequence[str], widths: Sequence[int], f_pos, f_keep, f_cells, options: SelectOptions,
               stats: tuple[Tensor, Tensor] | None = None) -> Tensor | None:
    """Step 5b: the cells [N] a keep stroke wins (:attr:`SelectOptions.keep_ratio`), in the
    :data:`KEEP_GROUPS` columns standardized as the classifier's, position weighted
    ``keep_position_weight`` × the classifier's weight; None when off or without keep points."""
    use = [g for g in groups if g in KEEP_GROUPS]
    if options.keep_ratio <= 0 or len(f_keep) == 0 or not use:
        return None
    columns = _columns(groups, widths, f_cells.device)
    z = _group_standardizer(groups, widths, f_cells, options, options.keep_position_weight, stats, torch.cat([columns[g] for g in use]))
    return keep_wins(z(f_cells), z(f_pos), z(f_keep), options.keep_ratio)


def _refine(classified: tuple[Tensor, Tensor], cells: Tensor, neighbours: Tensor | None, occupied: Tensor, scribbled: Tensor,
            kept: Tensor, options: SelectOptions, veto: Tensor | None = None, free_pieces: float = 0.0, said: dict | None = None) -> Tensor:
    """Step 6: the cells' probabilities (``classified``: from :func:`_classify`, with their
    appearance; cells: flat indices of ``occupied``, ``neighbours`` their :func:`neighbour_table`,
    given when the smoothing is bilateral) as a grid [R, R, R], 0 where ``veto`` [N] (step 5b),
    smoothed, connected to the ``scribbled`` cells (or in a piece of at least ``free_pieces`` of
    their count, :attr:`SelectOptions.free_pieces`, which ``said`` is filled with), 0 in the
    ``kept`` cells."""
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
        selected = values >= options.threshold
        reached = connected_to(selected, occupancy.dilate(scribbled, 1))
        if free_pieces > 0:  # whole pieces of the selected cells: joined to the reached ones, they are reached as they are
            apart = selected & ~reached
            n_reached = int(reached.sum())
            large, n_large = large_pieces(apart, free_pieces * n_reached)
            reached = reached | large
            if said is not None:
                said.update(share=free_pieces, reached=n_reached, kept_pieces=n_large, kept_cells=int(large.sum()),
                            left_cells=int((apart & ~large).sum()), pieces=large)  # counted again at the end (_kept_pieces)
        values = raised(values, reached, options.threshold)  # hysteresis at one cut
    return torch.where(kept, torch.zeros_like(values), values)


def _kept_pieces(said: dict, selected: Tensor) -> dict:
    """:func:`_refine`'s record of the loose pieces it kept, with their cells and pieces counted
    in the final ``selected`` [R, R, R] (the vetoes after it drop some: the count before them
    said 167 cells kept of a selection of 127)."""
    pieces = said.pop("pieces")
    final = pieces & selected
    labels = components(pieces)[final]
    return {**said, "kept_cells": int(final.sum()), "kept_pieces": int(torch.unique(labels).numel())}


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


@full_precision
@torch.no_grad()
def select(
    model: CategoryModel, instance: int | str, views: Sequence[ScribbleView], options: SelectOptions = SelectOptions(),
    renders: Sequence[RenderOutput] | None = None, points: CellPoints | None = None,
) -> Selection:
    """The 3-D selection the scribbles of ``views`` mean (see the module docstring).
    ``renders`` are the views' renders of the instance when the caller has them already;
    ``points`` its :func:`~.features.cell_points` (computed here when None, or when they are
    not this instance's cells at ``options.cell_ascent``)."""
    started = time.perf_counter()
    k = model.instance_index(instance)
    if not views:
        raise CrfError("select: give at least one view with a scribble")
    if not any(v.scribble.any() for v in views) and any(v.keep is not None and v.keep.any() for v in views):
        raise CrfError("no view holds a scribble: keep strokes alone select nothing (scribble the part on at least one view)")
    for i, v in enumerate(views):  # a view with keep strokes alone holds back what it shows (a second view's fix)
        if not v.scribble.any() and (len(views) == 1 or v.keep is None or not v.keep.any()):
            raise CrfError("the scribble is empty: no pixel is set" if len(views) == 1 else  # one view: no number to name it by
                           f"the scribble of view {i + 1} is empty: no pixel is set (a view without a scribble needs keep strokes)")
    if options.shape_from not in SHAPE_SOURCES:
        raise CrfError(f"selection shape_from {options.shape_from!r}: expected one of {', '.join(SHAPE_SOURCES)}")
    if options.mirror not in MIRROR_MODES:
        raise CrfError(f"selection mirror mode {options.mirror!r}: expected one of {', '.join(MIRROR_MODES)}")
    field = model.field_for(k)
    occupied = field.occupancy[k]
    res = occupied.shape[-1]
    centre_meta = snap_meta = None
    if options.stroke_centres or options.stroke_snap > 0:  # both read each view's on-object pixels
        renders = [render_camera(field, v.camera, k, colour=False) for v in views] if renders is None else renders
        on_object = [_on_object(field, k, v, r, options.min_opacity) for v, r in zip(views, renders)]
    whole = whole_share(views, on_object) if options.stroke_centres or options.stroke_snap > 0 else None  # see WHOLE_SCRIBBLE
    if options.stroke_snap > 0:  # see SelectOptions.stroke_snap
        views, added = _snapped_strokes(views, on_object, options.stroke_snap)
        snap_meta = {"added_pixels": added}
    if options.stroke_centres:  # see SelectOptions.stroke_centres
        views, dropped, dropped_keep, lifted_whole = _stroke_centres(views, on_object)
        centre_meta = {"edge_points": dropped, "keep_edge_points": dropped_keep, "whole_views": lifted_whole}
    pos_pts, neg_pts, cand_pts, surfaces, strays = _lift_views(field, k, views, options.min_opacity, renders, options.keep_strays)
    require_on_object(pos_pts.shape[0])
    cells = occupied.reshape(-1).nonzero().squeeze(-1)
    if points is None or not points.fits(cells, options.cell_ascent):
        points = cell_points(field, k, options.cell_ascent)
    elif points.memo is None:
        points = points._replace(memo={})  # kept for this selection's own repeated steps
    centres, fused, sigma = points.points, points.fused, points.sigma
    remember = points.kept  # what depends on the instance alone, kept with its cell points for the next scribble
    mirror = remember(("mirror",), lambda: find_mirror(occupied)) if options.mirror != "off" else None
    mirror, mirror_meta = _mirror_use(field, mirror, options.mirror, pos_pts, neg_pts)
    if mirror is not None and options.mirror == "views":
        render = lambda cam: remember(("render", _camera_key(cam)), lambda: render_camera(field, cam, k, colour=False))
        mirrored = _lift_mirrors(field, k, views, surfaces, mirror, options.min_opacity, render)
        mirror_meta.update(positives=int(len(mirrored[0])), keep_points=int(len(mirrored[1])))
        pos_pts, neg_pts, cand_pts = (torch.cat([a, b]) for a, b in zip((pos_pts, neg_pts, cand_pts), mirrored))
    cell_pts = field.denormalize(centres)
    first = next(v for v in views if v.scribble.any())  # the features' view-dependent terms read its eye
    eye = torch.as_tensor(np.asarray(first.camera.c2w)[:3, 3], dtype=torch.float32, device=occupied.device)
    groups, part_meta, fused_pos, coherence = options.features, None, None, 0.0
    if options.part_head and field.F_part is not None and "part" not in groups:
        fused_pos = field.fuse_features(field.normalize(pos_pts), k)  # point_features reuses it
        coherence = float(field.part_embedding(fused_pos).mean(dim=0).norm())
        labelled = labelled_names(model.meta)  # whether the head learned this chair's maps: None when the file does not say
        part_meta = {"coherence": round(coherence, 3), "cut": options.part_coherence, "used": coherence >= options.part_coherence,
                     "learned": None if labelled is None else model.names[k] in labelled}
        if part_meta["used"]:
            groups = (*groups, "part")
    shape_grid = geometry = None
    bar_rules = options.join_lines > 0 or options.line_negatives or bool(options.on_bars)  # they ask whether the scribble lies on bars
    if "geometry" in groups or bar_rules:
        shape_grid = remember(("shape", options.shape_from), lambda: cell_opacity(field, k, occupied, sigma) if options.shape_from == "density" else occupied)
    scribbled_frames, gate_meta = None, {"dropped": 0}
    line_share = None  # the share of the scribbled points that lie on lines
    if shape_grid is not None and (options.shape_gate > 0 or options.rim_fill > 0 or options.sheet_veto > 0 or bar_rules):
        scribbled_xn = field.normalize(evenly(pos_pts, SHAPE_GATE_POINTS))
        scribbled_frames = local_frames(shape_grid, scribbled_xn, SHAPE_GATE_RADIUS)
        bar_frames = scribbled_frames if BARS_RADIUS == SHAPE_GATE_RADIUS else local_frames(shape_grid, scribbled_xn, BARS_RADIUS)
        line_share = float(lines_of(bar_frames).float().mean())
    on_bars = line_share is not None and line_share >= JOIN_LINES  # join_lines, line_negatives and on_bars run only then
    bars_meta = None
    if on_bars and options.on_bars:  # see SelectOptions.on_bars
        bars_meta = {"line_share": round(line_share, 3), "options": [name for name, _ in options.on_bars]}
        options = options.on_bars_options()
        groups = (*options.features, "part") if part_meta is not None and part_meta["used"] else options.features
    if "geometry" in groups:
        geometry = remember(("geometry", options.shape_from, options.shape_radius),
                        lambda: local_shape(shape_grid, field.normalize(cell_pts), options.shape_radius))  # the cells' (point_features')
    feats = lambda p, fused_p=None, geometry_p=None: point_features(field, k, p, eye, groups, fused_p, shape_grid, options.shape_radius,
                                                                    options.chroma_offset, geometry_p)
    shape_gate = options.shape_gate > 0 and shape_grid is not None

    def shape_test(where: Tensor, test) -> Tensor:
        """[R, R, R] bool: ``test`` (:class:`Frames` [M] → [M] bool) of the occupied cells of
        ``where`` [R, R, R], their frames read at those cells only; False elsewhere."""
        at_cells = where.reshape(-1)[cells]
        out = torch.zeros(res**3, dtype=torch.bool, device=occupied.device)
        if bool(at_cells.any()):  # each cell's frame computed once, when first asked for
            frames = remember(("frames", options.shape_from), lambda: FrameTable(shape_grid, centres, SHAPE_GATE_RADIUS))
            out[cells[at_cells]] = test(frames.at(at_cells))
        return out.view(res, res, res)

    def gated(added: Tensor) -> Tensor:
        """The cells of ``added`` [R, R, R] that :attr:`SelectOptions.shape_gate` leaves out
        (:func:`gate_pieces` of the :func:`odd_lines` among them)."""
        drop = gate_pieces(added, shape_test(added, lambda f: odd_lines(f, scribbled_frames)), options.shape_gate)
        gate_meta["dropped"] += int(drop.sum())
        return drop

    f_pos, f_keep, f_view, f_cells = feats(pos_pts, fused_pos), feats(neg_pts), feats(cand_pts), feats(cell_pts, fused, geometry)
    widths = [group_width(g, field.cfg) for g in groups]
    scribbled, kept = _cells_of(field, pos_pts, res), _cells_of(field, neg_pts, res)
    clash = [int((scribbled & kept).sum()), int(scribbled.sum())]  # cells both scribbled and kept: the keep strokes win (keep_summary)
    neighbours = remember(("neighbours",), lambda: neighbour_table(cells, res)) if options.smooth and options.smooth_bandwidth > 0 else None
    stats = feature_stats(f_cells)
    veto = _keep_veto(groups, widths, f_pos, f_keep, f_cells, options, stats)
    spared = kept.clone()  # keep-stroke cells and those a keep stroke wins: no join takes them
    if veto is not None:
        spared.view(-1)[cells[veto]] = True
    held = None  # see SelectOptions.line_negatives: the view's points off lines stay negatives under a scribble on lines
    if options.line_negatives and on_bars and len(cand_pts):
        off_lines = shape_test(_cells_of(field, cand_pts, res), lambda f: ~lines_of(f))
        held = occupancy.lookup(off_lines[None], torch.zeros(len(cand_pts), dtype=torch.long, device=occupied.device), field.normalize(cand_pts))
    pieces_meta = {} if options.free_pieces > 0 and options.connected else None
    values = _refine(_classify(groups, widths, f_pos, f_keep, f_view, f_cells, options, stats, held), cells, neighbours, occupied, scribbled,
                     kept, options, veto, options.free_pieces, pieces_meta)
    columns = _columns(groups, widths, f_cells.device)
    union, saturation, spread = None, 0.0, None
    if "chroma" in groups:  # the cells' chromaticity distances, once for every test below
        spread = chroma_spread(f_cells.index_select(1, columns["chroma"]), f_pos.index_select(1, columns["chroma"]))
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
            alone = _refine(_classify(("chroma",), [WIDTHS["chroma"]], *(f.index_select(1, c) for f in (f_pos, f_keep, f_view, f_cells)), options,
                                      (stats[0][c], stats[1][c])),
                            cells, neighbours, occupied, scribbled, kept, options, veto)
            if options.join_chroma > 0:  # see SelectOptions.join_chroma
                alone = torch.where(alike_grid(options.join_chroma), alone, torch.zeros_like(alone))
            if shape_gate:  # see SelectOptions.shape_gate
                alone = torch.where(gated((alone >= options.threshold) & (values < options.threshold)), torch.zeros_like(alone), alone)
            n_main, n_alone = int((values >= options.threshold).sum()), int((alone >= options.threshold).sum())
            cap = options.pale_union if options.pale_union > 0 and saturation < options.pale_saturation else options.chroma_union
            union.update(cells=n_alone, features_cells=n_main, cap=cap, joined=n_alone <= cap * max(n_main, 1))
            union["keeps_lines"] = options.join_lines > 0 and on_bars  # a join here keeps only pieces of lines (join_summary's advice)
            if union["joined"] and options.join_lines > 0 and on_bars:
                added = (alone >= options.threshold) & (values < options.threshold)  # see SelectOptions.join_lines
                drop = gate_pieces(added, shape_test(added, lambda f: ~lines_of(f)), options.join_lines)
                union["not_lines"] = int(drop.sum())
                alone = torch.where(drop, torch.zeros_like(alone), alone)
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
        alike[cells] = f_cells.index_select(1, c) @ F.normalize(f_pos.index_select(1, c).mean(dim=0), dim=0)
        alike = alike.view(res, res, res)
        if options.part_veto > 0:
            unlike = occupied & (alike < options.part_veto) & ~scribbled
            if options.part_veto_keep:  # see SelectOptions.part_veto_keep; only the cells below the cut are read
                rows = unlike.view(-1)[cells].nonzero().squeeze(-1)
                unlike = torch.zeros(res**3, dtype=torch.bool, device=occupied.device)
                if len(f_keep) and len(rows):
                    part = f_cells[:, int(c[0]):int(c[-1]) + 1]  # the group's columns are contiguous: a view, gathered row by row
                    unlike[cells[rows]] = nearest_cosine(part[rows], f_keep.index_select(1, c)) >= alike.view(-1)[cells[rows]]
                unlike = unlike.view(res, res, res)
            if part_meta is not None:  # the selected cells it leaves out
                part_meta.update(vetoed=int((unlike & (values >= at)).sum()), veto_by="keep strokes" if options.part_veto_keep else "cosine",
                                 keep_points=int(len(f_keep)))
            values = torch.where(unlike, values.clamp(max=GROW_LOW * 0.999), values)
        if options.part_join > 0:
            like = occupied & (alike >= options.part_join) & ~spared
            if 0 < options.part_join_hue <= saturation and options.veto_chroma > 0:  # see SelectOptions.part_join_hue
                like &= alike_grid(options.veto_chroma, options.veto_floor) | scribbled
            like &= connected_to(like | (values >= at), occupancy.dilate(scribbled, 1))
            sure = 0 < options.part_join_sure <= coherence  # see SelectOptions.part_join_sure
            if shape_gate and not sure:  # see SelectOptions.shape_gate
                like &= ~gated(like & (values < at))
            if shape_gate and part_meta is not None:
                part_meta.update(join_gated=not sure, sure_at=options.part_join_sure)
            values = torch.where(like, values.clamp_min(at), values)
    if options.sheet_veto > 0 and scribbled_frames is not None:  # see SelectOptions.sheet_veto
        sheet_meta = {"line_share": round(line_share, 3), "cells": 0}
        if sheet_meta["line_share"] >= options.sheet_veto:
            sheet = shape_test((values >= GROW_LOW) & ~scribbled, sheets_of)
            values = torch.where(sheet, values.clamp(max=GROW_LOW * 0.999), values)
            sheet_meta["cells"] = int(sheet.sum())
    if options.rim_fill > 0 and shape_grid is not None:  # see SelectOptions.rim_fill
        sheets = scribbled_frames.planar > scribbled_frames.linear
        sheet_share = float(sheets.float().mean())
        rim_meta = {"cells": 0, "sheet_share": round(sheet_share, 3)}  # a removal reads it: Selection.reads_sheets
        if sheet_share >= RIM_SHEETS:
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
    if whole is not None:
        values = torch.where(occupied, torch.ones_like(values), values)
    values = quantized(values, (at, options.threshold, GROW_LOW))
    meta = {
        "positives": int(pos_pts.shape[0]), "keep_points": int(neg_pts.shape[0]), "view_points": int(cand_pts.shape[0]),
        "views": len(views), "features": list(groups), "occupied_cells": int(cells.numel()),
        "selected_cells": int((values >= at).sum()), "seconds": round(time.perf_counter() - started, 4),
    }
    if whole is not None:
        meta["whole"] = whole
    meta["clash_cells"] = clash
    meta["correction_views"] = sum(v.keep is not None and bool(v.keep.any()) for v in views[1:])  # mirror_summary's hint
    if veto is not None:
        meta["keep_wins_cells"] = int(veto.sum())
    if bars_meta is not None:
        meta["on_bars"] = bars_meta
    if held is not None:
        meta["line_negatives"] = {"line_share": round(line_share, 3), "points": int(held.sum())}
    if centre_meta is not None:
        meta["stroke_centres"] = centre_meta
    if snap_meta is not None:
        meta["stroke_snap"] = snap_meta
    if options.keep_strays > 0:
        meta["keep_strays"] = strays
    if union is not None:
        meta["chroma_union"] = union
    if mirror_meta is not None:
        meta["mirror"] = mirror_meta
    if part_meta is not None:
        meta["part_head"] = part_meta
    if shape_gate:
        meta["shape_gate"] = gate_meta
    if pieces_meta:
        meta["free_pieces"] = _kept_pieces(pieces_meta, values >= at)
    if options.sheet_veto > 0 and scribbled_frames is not None:
        meta["sheet_veto"] = sheet_meta
    if options.rim_fill > 0 and shape_grid is not None:
        meta["rim_fill"] = rim_meta
    return Selection(values, k, model.names[k], model.fingerprint(), meta, at)


def select_for(
    model: CategoryModel, instance: int | str, camera, scribble: np.ndarray, keep: np.ndarray | None, kind: str,
    mirror: str | None = None, renders: Sequence[RenderOutput] | None = None, join: str | None = None,
) -> Selection:
    """The selection a ``kind`` edit makes from one view's scribbles (:func:`.options.options_for`
    with the ``mirror`` and ``join`` modes): what ``edit-color``, ``remove`` and ``add`` compute
    when not given one, and what the commands print before they edit."""
    sel = select(model, instance, [ScribbleView(camera, scribble, keep)], options_for(kind, mirror, join), renders=renders)
    sel.meta["for"] = kind  # as `crfedit select --for` records it: an edit of another kind given the file says so
    if join is not None:
        sel.meta["colour_join"] = join  # the mode asked for, which join_summary names
    return sel
