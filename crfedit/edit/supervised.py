"""Edits supervised by a 3-D selection S (:mod:`.selection`): the edit is told where the part
is, in every view, instead of only along the scribbled view's rays.

Both edits are teacher–student fits of the paper's modules against the starting model (the
teacher, θ₀), with targets known in closed form:

* **remove** (trains F_fuse + F_dens): it empties S and S's skin (:func:`removal_cells`).  At
  points sampled in the instance's occupied cells, σ → 0 in the emptied cells and σ, bottleneck
  features held firmly (:data:`HOLD_WEIGHT`) at the teacher's elsewhere; along the rays of
  several views (the scribbled ones and the same cameras turned by 90°, 180°, 270° about the
  up axis) the target is the teacher's render *with the emptied cells' density zeroed*.  The
  occupancy grid then drops those cells, so the renderer never samples them.  S's junction
  cells, where S meets another part (:func:`removal_split`), stay in the grid and are split
  within the cell instead: σ → 0 on S's side, held on the other part's.
* **recolour** (trains F_rad + colour code; density is fixed, so every sample's compositing
  weight is a constant): a sample of colour c inside S targets c_appear · ⟨c, c̄⟩ / ⟨c̄, c̄⟩ —
  c_appear the colour the part should *appear* under the scribble, c̄ the mean rendered colour
  of the scribbled pixels — so it keeps its shading relative to the scribbled pixels (a darker
  pixel stays darker by the same factor) and takes the new colour (:class:`RecolorTarget`;
  ``EditOptions.recolor="ratio"`` is the per-channel c · c_appear / c̄ of before).  Samples
  near S whose ray's surface lies in S count as inside (:func:`surface_selected`); other
  samples and points take the new colour in proportion to S's share interpolated over the
  occupied cells (:func:`sample_share`), so samples away from S hold their starting colour.
  The loss is the weight-averaged per-sample error, the pixel error of the views' rays, and
  the error at 3-D points of the occupied cells seen from random directions
  (:class:`PointTargets`), which reach the faces no supervision ray saw.
"""

from __future__ import annotations

import json
import math
import time
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .. import occupancy
from ..cameras import Camera, Rays, rays_from_camera
from ..errors import CrfError
from ..model import CategoryModel
from ..names import RECOLOR_RULES
from ..rendering import composite_dense
from .cache import FEATURES, cache_stage, edit_passes
from .core import EditOptions, EditResult, InstanceEdit, camera_meta, finish, occupancy_after, optimize
from .losses import mse
from .selection import GROW_LOW, Selection
from .selection.classify import chroma_spread, chromaticity
from .selection.refine import surrounded_by

TURNS = (0.0, 90.0, 180.0, 270.0)
"""Supervision views: each scribbled camera turned about the world's up (Z) axis by these angles."""
MIN_MEAN_COLOR = 0.05
"""c̄ is floored per channel at this, so a near-black part still gets a finite ratio; every
sample is lifted by what the floor added to the mean (:class:`RecolorTarget`), so the scribbled
mean still maps to the colour asked.  Floored alone, a part recoloured black (rendering ~0.02)
and then white came out 0.46 grey: its samples read as shaded to 0.4 of a 0.05 mean."""
HOLD_WEIGHT = 10.0
"""Removal: weight of holding σ and the bottleneck at the teacher's values outside S, against
σ → 0 inside.  The network's drift outside S is what a removal damages; the occupancy grid
already skips S's cells, so holding the rest firmly costs the removal little."""
SKIN_LOW = GROW_LOW
"""A removal's skin takes only the cells of selection value at least this.  Measured (forty-
seventh session, gap closed, hybrid; docs/benchmarks.md): 0.2 instead of 0.3 helps the
procedural removals (0.825 → 0.850, 0.831 → 0.846, an H100 model 0.711 → 0.757: the faces of a
box-shaped part that its features miss) and costs the real ones (0.896 → 0.892, 0.911 → 0.894,
0.777 → 0.753: where S already reaches beyond the part, the skin takes more of the rest)."""
SKIN_SHARE = 0.4
"""A removal's skin (:func:`removal_cells`) takes a neighbour of S only where S is at least this
share of the neighbour's occupied 3×3×3 neighbourhood.  A flat face's outline cell has S on
one side and little else; a seat cell under a thin frame's rail has a third or less.  Measured
(docs/selection.md, hybrid, gap closed): real removals 0.420 → 0.484 (all four twins up),
procedural 0.780 → 0.776; a share of 0.25 gave 0.466 and 0.777, no share test (the skin of
before) 0.420 and 0.780, no skin 0.503 and 0.764."""
ADD_POINT_POOL = 8
"""Addition: each step fits a fresh batch of the usual size (``rays`` points in the pasted
cells, twice as many in the rest), drawn from a pool this many times as large whose targets
are computed once.  A fixed batch (the rule before 2026-11-26) was fitted point by point and
left the space between the points to chance.  On the four benchmark models, two edit seeds
each (`benchmarks/add.py`, 4 pairs): the rest of the chair +0.87 dB on average (−0.05 to
+1.87, better in 7 of 8), spill lower in 8 of 8, silhouette IoU −0.001 to +0.009, share added
−0.005 on average; about 0.15 s more (docs/benchmarks.md, forty-fifth session)."""
UNLIKE_FACTOR = 2.0
"""Recolour: outside S's interior (:func:`mixed_at`) a sample whose starting colour's
chromaticity lies farther than ``UNLIKE_FACTOR`` · r + :data:`UNLIKE_FLOOR` from the scribbled
pixels' median chromaticity (r: the 90th percentile of their own distances to it) keeps its
colour: its share of the new colour falls linearly from 1 there to 0 at twice that distance
(:meth:`RecolorTarget.likeness`; 0 turns the test off).  A 64³ cell where S meets another part
holds both surfaces, and a cell of S beside an unseen part (the cushion of an armchair
scribbled from behind) takes that part's rim with it.  Measured (forty-eighth session,
docs/benchmarks.md; gap closed and the rest of the chair against unedited, edits' seeds 0 / 1):
real recolours 0.875 → 0.883 and 0.867 → 0.881 (`r_nt`), 0.836 → 0.838 and 0.840 → 0.838
(`r_nt1`), outside +0.33 / +0.34 and +0.23 / +0.19 dB; procedural 0.912 → 0.908 and
0.905 → 0.902 (`p_nt`), 0.906 → 0.903 and 0.904 → 0.905 (`p_nt1`), outside +0.04 to +0.06 dB.
Where the selection is right it costs a little: `r_nt`'s edits with the oracle selection
0.845 → 0.831 (most likely a dark part's own shaded rim held).  Factor 1.5 gave 0.05–0.10 dB more outside
on the real models but 0.805 with the oracle selection; factor 3 or floor 0.03 kept less of
the real gain; applied to every sample (S's interior too) the test cost the procedural
recolours 0.016 (shaded faces of the part itself fall outside)."""
UNLIKE_FLOOR = 0.02
"""See :data:`UNLIKE_FACTOR`."""
BLEED_CHANGE = 0.1
"""Recolour: a held point (outside S, more than a cell from it) whose colour moved more than this
(largest channel, 0–1) has taken some of the new colour: :meth:`PointTargets.bleed`."""
BLEED_LIMIT = 0.01
"""Recolour with the paper's modules: when more than this share of the held points (weighted by
opacity) bled, F_rad could not tell them from the part (a back rail of the seat's brown reads
the same 8 bottleneck features), and the edit is fitted again training the bottleneck layer
too (:data:`WIDENED`), kept if it bleeds less.  On the quickstart's model (sixty-third session,
docs/benchmarks.md) recolours of parts unlike their neighbours bled 0.000–0.002; a seat whose
back rail has its brown 0.052 (0.021 widened), yellow legs beside teal rails 0.034 (0.021)."""
WIDENED = (FEATURES,)
"""What a recolour that bled trains besides F_rad and the colour code (:data:`BLEED_LIMIT`)."""
POINTS_PER_RAY = 0.5
"""Recolour: 3-D target points in S per supervision ray (twice as many outside S).  At 0.25
(before 2026-11-26) the recolours closed 0.900 / 0.900 / 0.867 / 0.834 of the gap on the four
benchmark models (procedural / real, training seeds 0 / 1; 0.903 / 0.902 / 0.865 / 0.840 with
the edits' seed 1); at 0.5 0.913 / 0.905 / 0.872 / 0.844 (0.904 / 0.904 / 0.865 / 0.845): a
face the views see at a grazing angle, such as the top of a chair's back, takes its new colour
from the points.  The optimization takes ~15 % longer.  Fewer points outside S (½× the inside
count instead of 2×) lose what the inside gains; 1× is mixed."""


def turned_about_z(camera: Camera, degrees: float) -> Camera:
    """``camera`` rotated about the world Z axis through the origin (the object's centre)."""
    a = math.radians(degrees)
    rz = np.eye(4)
    rz[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return Camera(rz @ np.asarray(camera.c2w), camera.focal, camera.width, camera.height)


def supervision_rays(cameras: Sequence[Camera], per_view: int, generator: torch.Generator, device) -> Rays:
    """``per_view`` seeded random rays of every camera turned by each of :data:`TURNS`."""
    origins, dirs = [], []
    for cam in cameras:
        for turn in TURNS:
            rays = rays_from_camera(turned_about_z(cam, turn), device)
            pick = torch.randperm(rays.origins.shape[0], generator=generator)[:per_view].to(device)
            origins.append(rays.origins[pick])
            dirs.append(rays.directions[pick])
    return Rays(torch.cat(origins), torch.cat(dirs))


def occupied_points(grid: Tensor, selected: Tensor, n_in: int, n_out: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """(normalized points [n, 3], inside-S flags [n]): up to ``n_in`` random points in selected
    occupied cells and ``n_out`` in the other occupied cells, half of those within two cells of S
    (where damage would show)."""
    res = grid.shape[-1]
    near = occupancy.dilate(selected, 2) & grid & ~selected
    far = grid & ~selected & ~near
    picks = []
    for cells, n in ((selected & grid, n_in), (near, n_out // 2), (far, n_out - n_out // 2)):
        idx = cells.reshape(-1).nonzero().squeeze(-1)
        if idx.numel() == 0 or n == 0:
            continue
        idx = idx[torch.randint(idx.numel(), (n,), generator=generator).to(idx.device)]
        jitter = torch.rand(n, 3, generator=generator).to(idx.device) - 0.5
        picks.append(occupancy.cell_centers(res, idx.device)[idx] + jitter * (2.0 / res))
    pts = torch.cat(picks)
    inside = occupancy.lookup(selected[None], torch.zeros(pts.shape[0], dtype=torch.long, device=pts.device), pts)
    return pts, inside


SHEET_OUTLINE = True
"""Whether a removal of sheets takes their outline (:func:`removal_cells`).  Measured (fifty-third
session, docs/benchmarks.md, hybrid, gap closed, edit seeds 0 / 1): the procedural removals
0.836 / 0.837 → 0.872 / 0.873 and 0.867 / 0.866 → 0.889 / 0.888 (every sheet twin up,
0.017–0.072); the real removals, whose scribbles all lie on lines (frames, tubes), do not
change.  Grown for every removal instead, the real ones lost 0.014–0.047 (a tube's outline
cells are the seat's and the pads')."""


def removal_cells(selection: Selection, grid: Tensor) -> Tensor:
    """The occupied cells [R, R, R] a removal empties: S, plus S's skin — the occupied cells next
    to S whose selection value is at least :data:`SKIN_LOW` and whose occupied 3×3×3
    neighbourhood is at least :data:`SKIN_SHARE` S.  A cell grid cut through at threshold 0.5
    leaves the part's outer faces in the cells just outside S, a faint outline where the part
    was; those cells lie against S with little else occupied around them.  A cell of another
    part that S merely touches (a seat under a thin frame) has mostly its own part around it.

    When the scribble lies on sheets (:attr:`Selection.reads_sheets`: a slab, a panel, a box's
    faces) the skin grows once more, by the same share test and whatever the cells' values:
    the cells along a slab's edges and corners have less of S around them than a face's
    outline cell, and stayed as a wire outline of the removed part (:data:`SHEET_OUTLINE`)."""
    sel = selection.mask.to(grid.device) & grid
    skin = occupancy.dilate(sel, 1) & surrounded_by(sel, grid, SKIN_SHARE) & (selection.values.to(grid.device) >= SKIN_LOW)
    sel = sel | skin
    if SHEET_OUTLINE and selection.reads_sheets:
        sel = sel | (occupancy.dilate(sel, 1) & surrounded_by(sel, grid, SKIN_SHARE))
    return sel


JUNCTION_SHARE = 0.2
"""A cell of S is a junction cell (:func:`removal_split`) where it touches an occupied cell
outside the emptied cells whose occupied 3×3×3 neighbourhood is less than this share emptied:
a cell of another part's body, not the fringe of S (an outline cell left beside S has S on
most of its sides).  Measured (docs/selection.md, hybrid, gap closed, seeds 0/1/2): procedural
removals 0.777/0.775/0.773 → 0.777/0.775/0.776, real (17 000 steps) 0.563/0.563/0.555 →
0.588/0.591/0.585, the weaker models 0.308 → 0.322 and 0.280 → 0.334, outside the part
+0.3–0.4 dB on all four; every S cell next to a kept cell (no share test): 0.603 and 0.606
(the part's outline stays); shares 0.15, 0.25 and 0.34: 0.783/0.582, 0.766/0.590,
0.736/0.613."""


def removal_split(selection: Selection, grid: Tensor) -> tuple[Tensor, Tensor]:
    """(core, junction) [R, R, R]: the cells a removal takes (:func:`removal_cells`) split into
    those it drops from the grid and its junction cells, which touch a kept cell of another
    part's body (:data:`JUNCTION_SHARE`).  A 64³ cell is coarser than the boundary between two
    parts: emptying a whole cell where a removed arm met a seat cut the seat's side face with
    it, so in a junction cell only the points on S's side (:func:`removed_at`) lose their
    density."""
    sel = removal_cells(selection, grid)
    body = grid & ~sel & ~surrounded_by(sel, grid, JUNCTION_SHARE)
    junction = sel & occupancy.dilate(body, 1)
    return sel & ~junction, junction


def removed_at(core: Tensor, junction: Tensor, grid: Tensor, xn: Tensor) -> Tensor:
    """[M] Whether a removal empties normalized points ``xn`` [M, 3]: all of the ``core``
    cells, and the points of ``junction`` cells nearer S than the rest — where the removed
    cells' share, trilinearly interpolated over the occupied cells, is at least a half."""
    zero = torch.zeros(xn.shape[0], dtype=torch.long, device=xn.device)
    removed = core | junction
    share = occupancy.masked_trilinear(removed.to(xn.dtype), grid, xn)
    return occupancy.lookup(core[None], zero, xn) | (occupancy.lookup(junction[None], zero, xn) & (share >= 0.5))


def remove_selected(
    model: CategoryModel, k: int, selection: Selection, cameras: Sequence[Camera], options: EditOptions
) -> EditResult:
    """Remove the selected part of instance ``k`` (see the module docstring)."""
    started = time.perf_counter()
    selection.check_for(model, k)
    generator = torch.Generator().manual_seed(options.seed)
    edit = InstanceEdit(model, k, "shape", options.strategy, options.penalty)
    field = edit.field
    device = model.device
    grid = field.occupancy[k].clone()
    core, junction = removal_split(selection, grid)
    pts, _ = occupied_points(grid, core | junction, options.rays, 2 * options.rays, generator)
    inside = removed_at(core, junction, grid, pts)
    shape_code, _ = field.codes(k)
    with torch.no_grad():
        inputs = field.fuse_inputs(pts, shape_code)
        inputs = type(inputs)(*(t.detach() if t is not None else None for t in inputs))
        raw0, feat0 = field.density_from_fuse_inputs(inputs)
        log0 = torch.log1p(field.sigma(raw0))
    rays = supervision_rays(cameras, max(8, options.rays // (2 * len(TURNS) * len(cameras))), generator, device)
    passes = edit_passes(field, rays, k, list(edit.params), density_changes=True, cache=options.cache)
    targets = []
    with torch.no_grad():
        for p in passes:
            out = p.forward()
            in_s = p.dense(removed_at(core, junction, grid, p.xn).to(out.sigmas.dtype))
            targets.append(composite_dense(p.t_starts, p.t_ends, out.sigmas * (1 - in_s), out.rgbs, p.background))

    outside = (~inside).nonzero().squeeze(-1)  # once: a mask index inside the loss is a host read per step
    holds = outside.numel() > 0  # a removal of the whole instance holds no point (a mean over none is NaN)

    def loss_fn():
        raw, feat = field.density_from_fuse_inputs(inputs)
        log_sigma = torch.log1p(field.sigma(raw))
        total = torch.where(inside, log_sigma**2, HOLD_WEIGHT * (log_sigma - log0) ** 2).mean()
        if holds:
            total = total + HOLD_WEIGHT * ((feat[outside] - feat0[outside]) ** 2).sum(dim=-1).mean()
        for p, target in zip(passes, targets):
            out = p.forward()
            total = total + mse(out.rgb, target.rgb) + mse(out.opacity, target.opacity)
        return total

    final = optimize(edit, loss_fn, options, "removal")
    extra, modules = edit.occupancy_delta(grid & ~core)
    hyper = {
        "method": "selection", "rays": int(rays.origins.shape[0]), "points": int(pts.shape[0]),
        "removed_cells": int((core | junction).sum()),  # the selection with its skin (removal_cells)
        "selected_cells": int((selection.mask.to(grid.device) & grid).sum()),
        "junction_cells": int(junction.sum()), "stage": passes[-1].stage,
        "cameras": [camera_meta(c) for c in cameras],
    }
    return finish(edit, "remove", options, hyper, final, started, extra, modules)


def surface_selected(sel: Tensor, ray: Tensor, xn: Tensor, w: Tensor, n_rays: int) -> Tensor:
    """[m] True for the samples within one cell of S whose ray's surface point (the weight-
    averaged sample position) lies in S: a surface's compositing weight spreads over the cells
    around it, and samples there must take the part's new colour too."""
    zero = torch.zeros_like(ray)
    wsum = torch.zeros(n_rays, device=w.device, dtype=w.dtype).index_add(0, ray, w).clamp_min(1e-12)
    surface = torch.zeros(n_rays, 3, device=w.device, dtype=w.dtype).index_add(0, ray, w[:, None] * xn) / wsum[:, None]
    hit = occupancy.lookup(sel[None], torch.zeros(n_rays, dtype=torch.long, device=ray.device), surface)
    return hit[ray] & occupancy.lookup(occupancy.dilate(sel, 1)[None], zero, xn)


def in_selection(sel: Tensor, ray: Tensor, xn: Tensor, w: Tensor, n_rays: int) -> Tensor:
    """[m] True for the samples in S's cells and the :func:`surface_selected` ones: the cell
    test, which takes the part's new colour fully."""
    return occupancy.lookup(sel[None], torch.zeros_like(ray), xn) | surface_selected(sel, ray, xn, w, n_rays)


def selection_share(sel: Tensor, grid: Tensor, xn: Tensor, full: Tensor) -> Tensor:
    """[m] How much of the part's new colour each point ``xn`` takes, in [0, 1]: 1 where
    ``full``, else S's share trilinearly interpolated over the instance's occupied cells
    ``grid`` (:func:`~crfedit.occupancy.masked_trilinear`).

    A cell-wise test alone leaves pixel-sized specks of a recoloured face in the old colour:
    the rendered surface of a face lying on a cell boundary falls now in the part's cell and
    now in the empty one beside it.  The interpolation reads the occupied neighbour instead,
    and blends across the boundary between two parts."""
    soft = occupancy.masked_trilinear((sel & grid).to(xn.dtype), grid, xn)
    return torch.maximum(full.to(soft.dtype), soft)


def mixed_at(sel: Tensor, grid: Tensor, xn: Tensor) -> Tensor:
    """[m] Whether normalized points ``xn`` [m, 3] lie outside S's interior, where a sample may
    show another part: in a cell of S next to an occupied cell outside S, or outside S.  The
    recolour's chromaticity test (:data:`UNLIKE_FACTOR`) applies there."""
    s = sel & grid
    interior = s & ~occupancy.dilate(grid & ~s, 1)
    return occupancy.lookup((~interior)[None], torch.zeros(xn.shape[0], dtype=torch.long, device=xn.device), xn)


def sample_share(sel: Tensor, grid: Tensor, ray: Tensor, xn: Tensor, w: Tensor, n_rays: int) -> Tensor:
    """[m] Each sample's :func:`selection_share`, full for the samples :func:`in_selection`."""
    return selection_share(sel, grid, xn, in_selection(sel, ray, xn, w, n_rays))


class PointTargets:
    """Teacher–student colour targets at 3-D points of the instance's occupied cells, seen
    from random directions: ``n`` points in S (target: ``recolor`` of the teacher's colour) and
    ``2n`` outside (target: the teacher's colour, blended towards ``recolor`` by S's
    interpolated share where S is less than a cell away, :func:`selection_share`), half of
    those within two cells of S.

    The views' rays reach only the surfaces those views see, from their directions; F_rad also
    reads the view direction, so without these points a face no supervision ray saw (a side
    face, a view from higher up) keeps its old colour.  Each point is weighted by its cell's
    opacity under the teacher, 1 − exp(−σ · cell side), so empty space inside an occupied cell
    does not count.
    """

    def __init__(self, edit: InstanceEdit, sel: Tensor, recolor, n: int, generator: torch.Generator):
        field, k = edit.field, edit.instance
        grid = field.occupancy[k]
        self.pts, inside = occupied_points(grid, sel, n, 2 * n, generator)
        d = torch.randn(self.pts.shape[0], 3, generator=generator).to(self.pts.device)
        self.dirs = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        self.edit = edit
        self.upstream = any(not (name.startswith(("F_rad.", FEATURES)) or name == "color_codes") for name in edit.params)
        features_train = any(name.startswith(FEATURES) for name in edit.params)
        cell = occupancy.step_size(field.aabb, grid.shape[-1], 1.0)
        with torch.no_grad():
            shape_code, _, idx = field.select(k)
            fused = field.fuse_activations(field.fuse_inputs(self.pts, shape_code, idx))  # one pass for both
            raw, feat = field.raw_density(fused), field.bottleneck(fused)
            self.inputs = field.F_rad.inputs(feat, self.dirs)  # constant unless upstream modules train
            self.fused = fused if features_train else None  # the trained bottleneck runs on it
            rgb0 = self.rgb()
            alpha = 1.0 - torch.exp(-field.sigma(raw) * cell)
            self.target = recolor.toward(rgb0, selection_share(sel, grid, self.pts, inside), mixed_at(sel, grid, self.pts))
            self.w = (alpha / alpha.sum().clamp_min(1e-12))[:, None]
            self.start = rgb0
            index = torch.zeros(self.pts.shape[0], dtype=torch.long, device=self.pts.device)
            self.held = ~occupancy.lookup(occupancy.dilate(sel, 1)[None], index, self.pts)

    def rad_inputs(self) -> Tensor:
        """F_rad's inputs [n, 8 + D] at the points now (no module upstream of the bottleneck trains)."""
        if self.fused is None:
            return self.inputs
        field = self.edit.field
        return torch.cat([field.bottleneck(self.fused), self.inputs[:, field.cfg.bottleneck:]], dim=-1)

    def rgb(self) -> Tensor:
        """The edited field's colour [n, 3] at the points, from their directions."""
        field, k = self.edit.field, self.edit.instance
        if self.upstream:
            return field.radiance(field.features(self.pts, k), self.dirs, k)
        _, code, idx = field.select(k)
        return field.F_rad(self.rad_inputs(), code, idx)

    def loss(self) -> Tensor:
        return (self.w * (self.rgb() - self.target) ** 2).sum()

    @torch.no_grad()
    def bleed(self) -> float:
        """The opacity-weighted share of the held points (outside S, more than a cell from it)
        whose colour now differs from the teacher's by more than :data:`BLEED_CHANGE`."""
        held = self.held
        if not bool(held.any()):
            return 0.0
        moved = (self.rgb()[held] - self.start[held]).abs().amax(dim=-1) > BLEED_CHANGE
        w = self.w[held, 0]
        return float((w * moved).sum() / w.sum().clamp_min(1e-12))


class RecolorTarget:
    """The colour a sample of the part should take: its starting colour ``rgb`` [m, 3] mapped so
    the scribbled pixels' mean c̄ (``rendered`` [n, 3]) becomes ``appear``.

    * ``ratio``: rgb ⊙ (c_appear / c̄), per channel.
    * ``shading`` (the default): c_appear · s with s = ⟨rgb, c̄⟩ / ⟨c̄, c̄⟩, the sample's
      shading relative to the scribbled mean.  For a white-lit Lambertian part (rgb = albedo · shade) both give
      c_appear · shade / mean shade; they differ on what is not shading: the per-channel ratio
      multiplies the model's colour noise by up to max(r) in one channel (a dark red part turned
      light green scales its green noise by ~9), the projection keeps only its component along c̄.

    Where the clamp at 1 bites (white on a part whose shading spreads), a gain per channel
    (:func:`clamped_gain`) brings the scribbled pixels' targets back to ``appear`` on average.

    ``unlike``: :data:`UNLIKE_FACTOR`, the chromaticity test of :meth:`likeness`.
    """

    def __init__(self, appear: Sequence[float], rendered: Tensor, rule: str = RECOLOR_RULES[0], unlike: float = UNLIKE_FACTOR):
        if rule not in RECOLOR_RULES:
            raise ValueError(f"RecolorTarget: rule={rule!r}, expected one of {RECOLOR_RULES}")
        self.rule = rule
        mean = rendered.mean(dim=0)
        self.mean = mean.clamp_min(MIN_MEAN_COLOR)
        self.lift = self.mean - mean  # what the floor added (0 on channels above it): added to every sample
        self.appear = torch.as_tensor(appear, dtype=self.mean.dtype, device=self.mean.device)
        self.gain = torch.ones_like(self.mean)  # the targets at gain 1 first, then the gain they need (clamped_gain)
        self.gain = clamped_gain(self(rendered), self.appear)
        self.unlike = unlike
        chroma = chromaticity(rendered)
        _, spread, self.chroma = chroma_spread(chroma, chroma)
        self.reach = unlike * float(spread) + UNLIKE_FLOOR

    def likeness(self, rgb: Tensor) -> Tensor:
        """[m] How much of the new colour a sample of colour ``rgb`` [m, 3] may take where it
        could show another part: 1 while its chromaticity lies within ``reach`` of the scribbled
        pixels' median, falling linearly to 0 at twice that (all 1 when ``unlike`` is 0)."""
        if self.unlike <= 0:
            return torch.ones(rgb.shape[0], dtype=rgb.dtype, device=rgb.device)
        distance = (chromaticity(rgb) - self.chroma).norm(dim=-1)
        return (2.0 - distance / self.reach).clamp(0.0, 1.0)

    def toward(self, rgb: Tensor, share: Tensor, mixed: Tensor | None = None) -> Tensor:
        """``rgb`` [m, 3] moved ``share`` [m] of the way to its target: rgb + share · (target − rgb);
        where ``mixed`` [m] (:func:`mixed_at`), ``share`` × :meth:`likeness` instead."""
        if mixed is not None:
            share = torch.where(mixed, share * self.likeness(rgb), share)
        return rgb + share[:, None] * (self(rgb) - rgb)

    def __call__(self, rgb: Tensor) -> Tensor:
        rgb = rgb + self.lift  # on a floored channel the mean itself maps to ``appear`` (not mean/floor of it)
        if self.rule == "ratio":
            return (rgb * (self.appear * self.gain / self.mean)).clamp(0, 1)
        shade = rgb @ self.mean / (self.mean @ self.mean)
        return (shade[:, None] * (self.appear * self.gain)).clamp(0, 1)


GAIN_MEAN_CAP = 0.97
""":func:`clamped_gain` aims the scribbled pixels' mean at most this high: a mean of 1 is flat
white, every pixel at 1 and the shading gone (a tester's navy seat asked #ffffff merged seat,
back and cushion edge into one patch, where #fcfcfc kept them: 25 levels apart held out)."""


def clamped_gain(targets: Tensor, appear: Tensor, rounds: int = 30) -> Tensor:
    """[3] The gain g ≥ 1 per channel for which the scribbled pixels' targets ``targets`` [n, 3]
    (their shading × ``appear``, clamped to 1) times g, clamped again, average ``appear``: the
    clamp takes from the bright pixels what nothing gives back, so a dark navy part recoloured
    white averaged 0.86 under its scribble, not the 1 asked.  The mean aimed at is capped at
    :data:`GAIN_MEAN_CAP`.  1 where nothing clamps (most colours); a bisection, at most 1 / the
    darkest target's value (every pixel at 1)."""
    gain = torch.ones_like(appear)
    for c in range(appear.shape[0]):
        t, want = targets[:, c], min(float(appear[c]), GAIN_MEAN_CAP)
        if t.numel() == 0 or want <= 0 or float(t.clamp(0, 1).mean()) >= want - 1e-4:
            continue
        low, high = 1.0, 1.0 / max(float(t.clamp_min(0).min()), 1e-3)
        for _ in range(rounds):
            mid = 0.5 * (low + high)
            low, high = (mid, high) if float((t * mid).clamp(0, 1).mean()) < want else (low, mid)
        gain[c] = high
    return gain


def recolor_selected(
    model: CategoryModel, k: int, selection: Selection, cameras: Sequence[Camera], scribbled_rgb: Tensor,
    appear: Sequence[float], options: EditOptions,
) -> EditResult:
    """Recolour the selected part of instance ``k`` so that it appears ``appear`` where the
    scribbled pixels (rendered colours ``scribbled_rgb`` [n, 3]) were."""
    started = time.perf_counter()
    selection.check_for(model, k)
    recolor = RecolorTarget(appear, scribbled_rgb.to(model.device), options.recolor)
    edit, final, hyper, bleed = _fit_recolor(model, k, selection, cameras, recolor, options)
    widened = None
    if options.strategy == "hybrid" and bleed > BLEED_LIMIT:
        wide = _fit_recolor(model, k, selection, cameras, recolor, options, WIDENED)
        widened = {"modules": [m.rstrip(".") for m in WIDENED], "bleed": round(wide[3], 4), "kept": wide[3] < bleed}
        if widened["kept"]:
            edit, final, hyper, _ = wide
    hyper.update(appear=[float(c) for c in appear], bleed=round(bleed, 4), **({"widened": widened} if widened else {}))
    return finish(edit, "color", options, hyper, final, started)


def _fit_recolor(
    model: CategoryModel, k: int, selection: Selection, cameras: Sequence[Camera], recolor: RecolorTarget,
    options: EditOptions, extra: tuple[str, ...] = (),
) -> tuple[InstanceEdit, float, dict, float]:
    """One fit of :func:`recolor_selected` training the strategy's modules and ``extra``:
    (the edit, its final loss, its hyper-parameters, :meth:`PointTargets.bleed` after it).
    Every fit draws the same rays and points (the generator is seeded afresh)."""
    generator = torch.Generator().manual_seed(options.seed)
    edit = InstanceEdit(model, k, "color", options.strategy, options.penalty, extra)
    device = model.device
    sel = selection.mask.to(device)
    rays = supervision_rays(cameras, max(8, options.rays // (len(TURNS) * len(cameras))), generator, device)
    (p,) = edit_passes(edit.field, rays, k, list(edit.params), density_changes=False, cache=options.cache)
    radiance = p.stage == "radiance"

    def current() -> tuple[Tensor, Tensor, Tensor]:
        """(sample colours [m, 3], their compositing weights [m], pixels [N, 3]) now."""
        _, code = edit.field.codes(k)
        if radiance:
            rgb_s = p.sample_rgb(p.net, code)
            return rgb_s, p.w, p.constant.index_add(0, p.ray, p.w[:, None] * rgb_s)
        out, s = p.forward(), p.samples
        return out.rgbs[s.ray, s.step], out.weights[s.ray, s.step], out.rgb

    with torch.no_grad():
        rgb0, w0, pixel0 = current()
        ray, xn = (p.ray, p.xn_kept) if radiance else (p.samples.ray, p.xn)
        grid = edit.field.occupancy[k]
        share = sample_share(sel, grid, ray, xn, w0, pixel0.shape[0])
        target_s = recolor.toward(rgb0, share, mixed_at(sel, grid, xn))
        # weights are fixed (density does not change), so a pixel is linear in its samples' colours
        target_px = pixel0.index_add(0, ray, w0[:, None] * (target_s - rgb0))
        w = w0[:, None] / w0.sum().clamp_min(1e-12)
    points = PointTargets(edit, sel, recolor, max(8, int(options.rays * POINTS_PER_RAY)), generator)

    if radiance and not points.upstream:
        # One F_rad pass for the views' kept samples and the 3-D points, and the pixel error as
        # the weighted sum of its samples' errors (pixel − target_px = Σ w₀ (c − target), the
        # constant part cancels): the same loss as below in a third of the small CPU ops.
        m = p.per_point.shape[0]
        target_all, w_all = torch.cat([target_s, points.target]), torch.cat([w, points.w])
        w_px = p.w[:, None]
        fixed = torch.cat([p.per_point, points.inputs]) if p.fused is None else None

        def loss_fn():
            _, code = edit.field.codes(k)
            inputs = fixed if fixed is not None else torch.cat([p.rad_inputs(p.net), points.rad_inputs()])
            err = p.net.F_rad(inputs, code) - target_all
            pixel_err = torch.zeros_like(pixel0).index_add(0, p.ray, w_px * err[:m])
            return (w_all * err**2).sum() + (pixel_err**2).mean()

    else:

        def loss_fn():
            rgb_s, _, pixel = current()
            return (w * (rgb_s - target_s) ** 2).sum() + mse(pixel, target_px) + points.loss()

    final = optimize(edit, loss_fn, options, "colour edit")
    hyper = {
        "method": "selection", "rays": int(rays.origins.shape[0]),
        "recolor_rule": recolor.rule, "unlike": recolor.unlike, "ratio": [round(float(r), 4) for r in recolor.appear / recolor.mean],
        "selected_samples": round(float(share.sum()), 1), "cached_samples": p.n_cached, "stage": p.stage, "cameras": [camera_meta(c) for c in cameras],
    }
    return edit, final, hyper, points.bleed()


def paste_translation(field, selection_mask: Tensor, camera: Camera, offset: tuple[int, int]) -> Tensor:
    """The world translation [3] that moves the selected donor cells ``offset`` = (dx, dy) pixels
    right and down in ``camera``'s image, at the depth of their centroid (a pinhole's pixel
    spans depth / focal world units there)."""
    res = selection_mask.shape[-1]
    cells = selection_mask.reshape(-1).nonzero().squeeze(-1)
    centroid = field.denormalize(occupancy.cell_centers(res, field.aabb.device)[cells]).mean(dim=0)
    c2w = torch.as_tensor(np.asarray(camera.c2w), dtype=centroid.dtype, device=centroid.device)
    right, up, back, eye = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
    depth = ((centroid - eye) * -back).sum()
    dx, dy = offset
    return (dx * right - dy * up) * depth / camera.focal


def percent_down(share: float) -> str:
    """``share`` as a whole percent rounded down: a part some of which stays is never "100%"."""
    return f"{math.floor(100.0 * share)}%"


def outside_box_note(meta: dict, moved: str) -> str | None:
    """The warning an addition's metadata ``meta`` calls for when its offset moved more than
    :data:`OUTSIDE_WARN` of the part out of the scene box (None otherwise); ``moved`` names the
    offset as the user gave it (``--offset 0,-16``, ``the paste``)."""
    lost = json.loads(meta.get("hyperparameters") or "{}").get("outside_box", 0.0)
    if lost <= OUTSIDE_WARN:
        return None
    return f"{moved} moves {percent_down(lost)} of the donor's part out of the scene box: that much of it is not added (paste it nearer the object)"


OUTSIDE_REFUSE = 0.5
"""``add`` refuses an offset that moves more than this share of the part's cells out of the scene
box (the page accepted a paste that kept 24 of 7 874 cells)."""
OUTSIDE_WARN = 0.02
"""``add`` warns when its offset moves more than this share of the donor part's cells out of the
scene box (those cells are not added: a part pushed off the box came out as slivers)."""


def shifted_cells(mask: Tensor, shift_n: Tensor) -> tuple[Tensor, float]:
    """(the cells ``mask`` [R, R, R] covers after a translation ``shift_n`` [3] in normalized
    units, dilated by one cell so that no part of a shifted cell is missed; the share of its
    cells the translation moves out of the scene box, which the paste loses)."""
    res = mask.shape[-1]
    cells = mask.reshape(-1).nonzero().squeeze(-1)
    ijk, inside = occupancy.cell_index(occupancy.cell_centers(res, mask.device)[cells] + shift_n, res)
    lost = 1.0 - float(inside.float().mean()) if inside.numel() else 0.0
    ijk = ijk[inside]
    out = torch.zeros_like(mask)
    out[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return occupancy.dilate(out, 1), lost


def add_selected(
    model: CategoryModel, k: int, donor: int, selection: Selection, camera: Camera, offset: tuple[int, int],
    options: EditOptions,
) -> EditResult:
    """Add the donor's selected part to instance ``k``, moved ``offset`` pixels in ``camera``'s
    view (trains F_fuse + F_dens).  A teacher–student fit at points in 3-D: in the pasted cells
    S′ = S + t, σ and the bottleneck features take the donor's values at x − t where x − t lies
    in S (the part's colour then follows instance ``k``'s colour code, as in the paper), and the
    instance's own elsewhere; in the instance's other occupied cells both are held.  Each step
    fits a batch drawn from a larger pool of points (:data:`ADD_POINT_POOL`).  The occupancy
    grid then gains the pasted cells where the fit put density."""
    started = time.perf_counter()
    selection.check_for(model, donor)
    generator = torch.Generator().manual_seed(options.seed)
    edit = InstanceEdit(model, k, "shape", options.strategy, options.penalty)
    field = edit.field
    donor_field = model.field_for(donor)
    device = model.device
    source = selection.mask.to(device) & donor_field.occupancy[donor]
    if not bool(source.any()):
        raise CrfError("the selection covers none of the donor's occupied cells")
    shift = paste_translation(field, source, camera, offset)
    lo, hi = field.aabb[:3], field.aabb[3:]
    shift_n = shift * 2.0 / (hi - lo)
    pasted, lost = shifted_cells(source, shift_n)
    if not bool(pasted.any()):
        raise CrfError(f"--offset {offset[0]},{offset[1]} moves the whole part out of the scene box")
    if lost > OUTSIDE_REFUSE:
        raise CrfError(f"--offset {offset[0]},{offset[1]} moves {percent_down(lost)} of the part out of the scene box, which holds "
                       "nothing outside it: paste it nearer the object")
    original = field.occupancy[k].clone()
    union = original | pasted
    pts, in_pasted = occupied_points(union, pasted, ADD_POINT_POOL * options.rays, ADD_POINT_POOL * 2 * options.rays, generator)
    pre = pts - shift_n
    inst_d = torch.full((pts.shape[0],), donor, dtype=torch.long, device=device)
    copied = in_pasted & occupancy.lookup(source[None], torch.zeros_like(inst_d), pre)
    copied &= occupancy.lookup(donor_field.occupancy, inst_d, pre)  # σ = 0 where the renderer never samples the donor
    cached = None
    if cache_stage(list(edit.params), density_changes=True) == "fuse":  # nothing upstream of F_fuse trains
        with torch.no_grad():
            cached = field.fuse_inputs(pts, field.codes(k)[0])
    def fuse_inputs(rows: Tensor | None = None):
        """F_fuse's inputs at the pool's points, or at its ``rows``."""
        if cached is None:
            return field.fuse_inputs(pts if rows is None else pts[rows], field.codes(k)[0])
        if rows is None:
            return cached
        return cached._replace(hidden=cached.hidden[rows], pe=cached.pe[rows])  # one instance: no per-point code rows

    with torch.no_grad():
        raw0, feat0 = field.density_from_fuse_inputs(fuse_inputs())
        sigma0 = field.sigma(raw0) * occupancy.lookup(original[None], torch.zeros_like(inst_d), pts)
        raw_d, feat_d = donor_field.density_from_fuse_inputs(donor_field.fuse_inputs(pre, donor_field.codes(donor)[0]))
        sigma_d = donor_field.sigma(raw_d)
        take = copied & (sigma_d > sigma0)  # where the pasted part is denser than what is there
        sigma_t = torch.where(take, sigma_d, sigma0)
        log_t = torch.log1p(sigma_t)
        feat_t = torch.where(take[:, None], feat_d, feat0)
        cell = float((hi - lo).max()) / original.shape[-1]
        # features matter where the target is opaque over a cell; held exactly outside S′
        w_feat = torch.where(in_pasted, 1.0 - torch.exp(-sigma_t * cell), torch.ones_like(sigma0))

    n_batch = pts.shape[0] // ADD_POINT_POOL  # the fixed batch's size before the pool

    def loss_fn():
        idx = torch.randint(pts.shape[0], (n_batch,), generator=generator).to(device)
        raw, feat = field.density_from_fuse_inputs(fuse_inputs(idx))
        log_sigma = torch.log1p(field.sigma(raw))
        total = ((log_sigma - log_t[idx]) ** 2).mean()
        return total + (w_feat[idx] * ((feat - feat_t[idx]) ** 2).sum(dim=-1)).mean()

    final = optimize(edit, loss_fn, options, "add edit")
    extra, modules = occupancy_after(edit, union, generator, kept=original)
    hyper = {
        "method": "selection", "points": int(pts.shape[0]), "donor": model.names[donor], "offset": list(offset),
        "translation": [round(float(v), 6) for v in shift],
        "selected_cells": int(source.sum()), "pasted_cells": int(pasted.sum()), "camera": camera_meta(camera),
        "outside_box": round(lost, 4),
    }
    return finish(edit, "add", options, hyper, final, started, extra, modules)
