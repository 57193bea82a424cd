"""The matter's local shape and the shape gate of removals' joins (edit/selection.py):
closed-form orientation, agreement and connected pieces, and a frame whose legs are kept out
of a join that its stretchers' colour would make."""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import pytest
import torch

from crfedit import occupancy
from crfedit.edit.selection import classify, options as S, pipeline
from crfedit.edit.selection import options_for, pieces_summary
from crfedit.edit.selection.features import Frames, SHAPE_FRACTION, cell_opacity, local_frames, local_shape, sym3_eigen
from crfedit.edit.selection.refine import NEIGHBOUR_OFFSETS, components, connected_to, large_pieces, neighbour_table
from crfedit.edit.selection.shapes import SHAPE_GATE_RADIUS, gate_pieces, odd_lines, rim_lines, shape_agreement, sheets_of

RES = 16


def centre_of(i: int, j: int, k: int, res: int = RES) -> torch.Tensor:
    """The normalized centre of cell (i, j, k).  [1, 3]"""
    return (torch.tensor([[i, j, k]], dtype=torch.float32) + 0.5) / res * 2 - 1


def frames_of(line: list[bool], direction: list[list[float]], normal: list[list[float]]) -> Frames:
    """Frames of pure lines (ℓ = 1, p = 0) or pure sheets (ℓ = 0, p = 1)."""
    lin = torch.tensor([1.0 if x else 0.0 for x in line])
    one = torch.ones(len(line))
    return Frames(lin, 1 - lin, 0 * one, one, one, torch.nn.functional.normalize(torch.tensor(direction), dim=-1),
                  torch.nn.functional.normalize(torch.tensor(normal), dim=-1))


def test_local_shape_reads_orientation_from_weights():
    """A line of cells along z weighs its direction on the z axis (ℓ·v₁² = (0, 0, ℓ)); a sheet in
    the x–y plane its normal (p·v₃² = (0, 0, p)); a line along x weighted by opacities that fall
    off across it (0.2 beside the core) is still a line along x."""
    line = torch.zeros(RES, RES, RES)
    line[5, 5, 3:8] = 1.0
    f = local_shape(line, centre_of(5, 5, 5))[0]
    assert f.shape == (11,)
    assert torch.allclose(f[5:8], torch.tensor([0.0, 0.0, float(f[0])]), atol=1e-5) and f[0] > 0.99
    sheet = torch.zeros(RES, RES, RES)
    sheet[3:8, 3:8, 5] = 1.0
    f = local_shape(sheet, centre_of(5, 5, 5))[0]
    assert f[1] > 0.99 and torch.allclose(f[8:11], torch.tensor([0.0, 0.0, float(f[1])]), atol=1e-5)
    soft = torch.zeros(RES, RES, RES)
    soft[3:8, 5, 5] = 1.0
    soft[3:8, 4, 5] = soft[3:8, 6, 5] = 0.2
    fr = local_frames(soft, centre_of(5, 5, 5), radius=2)
    assert float(fr.linear[0]) > float(fr.planar[0]) and abs(float(fr.direction[0, 0])) > 0.99


def test_shape_agreement_closed_form():
    """A line agrees with a line along it, not with one square to it; a line lying in a sheet
    agrees with it (a panel's rim), a line along the sheet's normal does not; sheets agree when
    parallel.  The clash of a 30° tilt (sin² = 1/4) is at the bar; 45° is past it."""
    x, y, z = [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]
    stretcher = frames_of([True], [x], [y])  # a line along x
    panel = frames_of([False], [y], [x])  # a sheet with normal x
    cells = frames_of([True, True, True, True, False, False], [x, z, y, x, x, y], [y, x, z, y, z, y])
    # line x, line z, line y, line x (normal y), sheet normal z, sheet normal y: the two sheets hold the line x
    assert shape_agreement(cells, stretcher).tolist() == [1.0, 0.0, 0.0, 1.0, 1.0, 1.0]
    # vs the panel (normal x): line x square to it (along the normal), lines z and y lie in it; sheets z, y are square
    assert shape_agreement(cells, panel).tolist() == [0.0, 1.0, 1.0, 0.0, 0.0, 0.0]
    tilt = lambda deg: [float(np.cos(np.radians(deg))), 0.0, float(np.sin(np.radians(deg)))]
    tilted = frames_of([True, True], [tilt(29.9), tilt(45.0)], [y, y])
    assert shape_agreement(tilted, stretcher).tolist() == [1.0, 0.0]
    both = frames_of([True, True], [x, z], [y, x])
    assert shape_agreement(frames_of([True], [z], [x]), both).tolist() == [0.5]  # agrees with half the points


def test_rim_lines_closed_form():
    """Scribbled on a panel (sheets with normal x): a line along y or z lies in its plane and
    is a rim, a line along x (square to it) and a sheet are not; with half the points on a
    sheet of normal z, a line along y lies in both planes, one along z in one (a share of 1/2);
    scribbled on lines only, nothing is a rim."""
    x, y, z = [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]
    panel = frames_of([False, False], [y, z], [x, x])
    cells = frames_of([True, True, True, False], [y, z, x, y], [x, x, y, x])
    assert rim_lines(cells, panel, 0.5).tolist() == [True, True, False, False]
    mixed = frames_of([False, False], [y, y], [x, z])
    assert rim_lines(cells, mixed, 0.5).tolist() == [True, True, True, False]
    assert rim_lines(cells, mixed, 0.75).tolist() == [True, False, False, False]
    tubes = frames_of([True, True], [x, y], [y, x])
    assert not rim_lines(cells, tubes, 0.1).any()


def bfs_labels(grid: np.ndarray) -> np.ndarray:
    """Reference: each cell of a 26-connected piece labelled 1 + the piece's largest flat index."""
    out = np.zeros(grid.shape, dtype=np.int64)
    seen = np.zeros(grid.shape, dtype=bool)
    for start in zip(*np.nonzero(grid)):
        if seen[start]:
            continue
        piece, queue = [], deque([start])
        seen[start] = True
        while queue:
            c = queue.popleft()
            piece.append(c)
            for d in np.ndindex(3, 3, 3):
                n = tuple(c[i] + d[i] - 1 for i in range(3))
                if all(0 <= n[i] < grid.shape[i] for i in range(3)) and grid[n] and not seen[n]:
                    seen[n] = True
                    queue.append(n)
        label = max(np.ravel_multi_index(c, grid.shape) for c in piece) + 1
        for c in piece:
            out[c] = label
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_components_match_breadth_first_search(seed):
    """Connected pieces (26-neighbourhood) as a breadth-first search labels them, on a random
    grid that is not a cube; an empty grid has none."""
    g = torch.from_numpy(np.random.default_rng(seed).random((9, 12, 10)) < 0.3)
    assert torch.equal(components(g), torch.from_numpy(bfs_labels(g.numpy())))
    assert not components(torch.zeros(4, 4, 4, dtype=torch.bool)).any()


@pytest.mark.parametrize("seed", [0, 1])
def test_connected_to_is_the_pieces_holding_a_seed(seed):
    """The cells reached from the seeds are exactly those of the breadth-first pieces that hold
    a seed (the growth runs in the selection's bounding box, which must not cut a piece)."""
    rng = np.random.default_rng(seed)
    g = torch.from_numpy(rng.random((9, 12, 10)) < 0.3)
    g[0, 0, 0] = g[8, 11, 9] = True  # the box is the whole grid: a piece may touch any face
    seeds = torch.from_numpy(rng.random((9, 12, 10)) < 0.02)
    labels = torch.from_numpy(bfs_labels(g.numpy()))
    held = labels[seeds & g].unique()
    assert torch.equal(connected_to(g, seeds), g & torch.isin(labels, held))
    small = torch.zeros(9, 12, 10, dtype=torch.bool)
    small[3:5, 4, 6] = small[7, 9, 2] = True  # two pieces in a corner of the grid, one seeded
    seed = torch.zeros_like(small)
    seed[3, 4, 6] = True
    reached = connected_to(small, seed)
    assert reached[3:5, 4, 6].all() and int(reached.sum()) == 2
    assert not connected_to(torch.zeros_like(small), seed).any()


@pytest.mark.parametrize("seed", [0, 1])
def test_large_pieces_are_the_breadth_first_pieces_of_that_size(seed):
    """The cells of exactly the breadth-first pieces of at least ``least`` cells; none of an
    empty grid."""
    g = torch.from_numpy(np.random.default_rng(seed).random((9, 12, 10)) < 0.25)
    labels = torch.from_numpy(bfs_labels(g.numpy()))
    ids, counts = labels[g].unique(return_counts=True)
    for least in (1, 3, int(counts.max()), int(counts.max()) + 1, int(g.sum()) + 1):
        large, n_large = large_pieces(g, least)
        assert torch.equal(large, g & torch.isin(labels, ids[counts >= least])) and n_large == int((counts >= least).sum())
    large, n_large = large_pieces(torch.zeros(4, 4, 4, dtype=torch.bool), 0.0)
    assert not large.any() and n_large == 0


def _bar_and_loose_pieces() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A selection's values on a 16³ grid: a scribbled bar of 20 cells, a piece of 10 cells and
    one of 2 cells that the bar does not touch (all at 0.9), and the scribbled cell."""
    values = torch.zeros(RES, RES, RES)
    values[2, 2, 2:16] = 0.9  # the bar: 14 cells in one row, 6 beside them
    values[3, 2, 2:8] = 0.9
    values[10, 10, 2:12] = 0.9  # 10 cells apart
    values[13, 3, 3:5] = 0.9  # 2 cells apart
    scribbled = torch.zeros(RES, RES, RES, dtype=torch.bool)
    scribbled[2, 2, 5] = True
    return values, scribbled, values > 0


@pytest.mark.parametrize("free, kept_apart, pieces", [(0.0, 0, None), (0.05, 12, (2, 0)), (0.4, 10, (1, 1)), (0.6, 0, (0, 2))])
def test_free_pieces_keep_the_loose_pieces_of_their_share(free, kept_apart, pieces):
    """With ``free_pieces`` f a piece that the scribble does not reach stays selected when it
    holds at least f × the 20 cells the scribble reaches: 1, 8 and 12 cells for f = 0.05, 0.4
    and 0.6, so both pieces, the 10-cell one, neither.  The reached bar stays whatever f is,
    and every other cell ends below the cut.  What it did is said: the pieces kept and left
    out, and their cells."""
    values, scribbled, occupied = _bar_and_loose_pieces()
    cells = occupied.reshape(-1).nonzero().squeeze(-1)
    options = dataclasses.replace(options_for("remove"), free_pieces=free)
    said = {}
    out = pipeline._refine((values.reshape(-1)[cells], None), cells, None, occupied, scribbled, torch.zeros_like(occupied),
                           dataclasses.replace(options, smooth=False), free_pieces=free, said=said)
    chosen = out >= options.threshold
    assert int(chosen[:4].sum()) == 20 and int(chosen.sum()) == 20 + kept_apart
    assert bool((out[occupied & ~chosen] < options.threshold).all())
    if pieces is None:
        assert said == {}
        return
    kept_grid = chosen.clone()
    kept_grid[:4] = False  # the bar (x = 2, 3) is reached, not a kept piece
    assert torch.equal(said["pieces"], kept_grid)
    said = pipeline._kept_pieces(said, chosen)  # counted in the final selection
    assert said == {"share": free, "reached": 20, "kept_pieces": pieces[0], "kept_cells": kept_apart, "left_cells": 12 - kept_apart}
    if kept_apart:  # a later veto drops the 10-cell piece (x = 10): the line counts what is left (it said the count before)
        vetoed = chosen.clone()
        vetoed[10] = False
        fewer = pipeline._kept_pieces({**said, "pieces": kept_grid}, vetoed)
        assert fewer["kept_cells"] == kept_apart - 10 and fewer["kept_pieces"] == pieces[0] - 1
    line = pieces_summary({"free_pieces": said})
    assert ("kept" in line) == (pieces[0] > 0) and ("left" in line) == (pieces[1] > 0)
    if free == 0.4:
        then = "40% of the 20 cells the scribble reached at that step, before the vetoes"
        assert line == (f"kept 1 piece that the scribble does not reach (10 cells; each at least {then}); "
                        "left 2 cells out: pieces it does not reach, each under that share")
    assert pieces_summary({"free_pieces": {**said, "kept_pieces": 0, "kept_cells": 0, "left_cells": 0}}) is None and pieces_summary({}) is None
    # pieces that outnumber what the scribble reached (a 22-px scribble on a chair's wheels kept 1421 cells to its 1367,
    # the base's spoke ends among them): the line says to check the preview
    many = pieces_summary({"free_pieces": {**said, "kept_pieces": 2, "kept_cells": 30, "reached": 20}})
    assert ("(30 cells; each at least" in many and ": more than the scribble reached itself, so check the preview; keep strokes on "
            "the parts around them hold them back (or --mirror off for one side)" in many)


def test_neighbour_table_halves_and_non_cubic_grids():
    """On a grid that is not a cube, each row lists the positions of the 26 neighbours in
    NEIGHBOUR_OFFSETS' order (−1 off the cells), and the half table is its first 13 columns,
    whose opposites are the last 13 reversed."""
    shape = (5, 7, 6)
    occ = torch.from_numpy(np.random.default_rng(2).random(shape) < 0.5)
    cells = occ.reshape(-1).nonzero().squeeze(-1)
    pos = {int(c): i for i, c in enumerate(cells)}
    table = neighbour_table(cells, shape)
    for row, c in zip(table.tolist(), cells.tolist()):
        i, j, k = np.unravel_index(c, shape)
        for x, (a, b, d) in zip(row, NEIGHBOUR_OFFSETS):
            n = (i + a, j + b, k + d)
            inside = all(0 <= n[t] < shape[t] for t in range(3))
            assert x == (pos.get(int(np.ravel_multi_index(n, shape)), -1) if inside else -1)
    assert torch.equal(neighbour_table(cells, shape, half=True), table[:, :13])
    assert all(tuple(-v for v in NEIGHBOUR_OFFSETS[j]) == NEIGHBOUR_OFFSETS[25 - j] for j in range(26))


def test_feature_stats_are_the_sample_mean_and_deviation():
    """The two-pass statistics the selection standardizes with are torch's (unbiased) mean and
    standard deviation, to float32 rounding, on columns of very different offsets and scales;
    a constant column's deviation is floored at 10⁻⁶, not 0."""
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(5000, 6, generator=g) * torch.tensor([1e-3, 1.0, 30.0, 1.0, 5.0, 0.0]) + torch.tensor([0.0, 100.0, -4.0, 0.5, 0.0, 2.0])
    mean, std = classify.feature_stats(feats)
    torch.testing.assert_close(mean, feats.mean(dim=0))
    torch.testing.assert_close(std[:5], feats.std(dim=0)[:5], rtol=1e-5, atol=0)
    assert float(std[5]) == pytest.approx(1e-6)


def test_sym3_eigen_matches_lapack():
    """The closed-form eigenvalues agree with torch.linalg.eigh, and the eigenvectors of the
    largest and smallest with its (up to sign) wherever those eigenvalues are apart from the
    middle one; a multiple of I gives z and x, a line's and a sheet's frames their axis."""
    g = torch.Generator().manual_seed(0)
    a = torch.randn(2000, 3, 3, generator=g, dtype=torch.float64)
    spd = a @ a.transpose(1, 2) + 1e-3 * torch.eye(3, dtype=torch.float64)
    lam, v1, v3 = sym3_eigen(spd)
    want, vec = torch.linalg.eigh(spd)
    torch.testing.assert_close(lam, want, rtol=1e-9, atol=1e-9)
    apart1 = (want[:, 2] - want[:, 1]) > 1e-3 * want[:, 2]
    apart3 = (want[:, 1] - want[:, 0]) > 1e-3 * want[:, 2]
    assert float((1 - (v1 * vec[:, :, 2]).sum(-1).abs())[apart1].max()) < 1e-8
    assert float((1 - (v3 * vec[:, :, 0]).sum(-1).abs())[apart3].max()) < 1e-8
    special = torch.stack([2.0 * torch.eye(3), torch.diag(torch.tensor([1e-3, 0.7, 1e-3])), torch.diag(torch.tensor([0.6, 0.6, 1e-3]))])
    lam, v1, v3 = sym3_eigen(special)
    assert lam.dtype == torch.float32
    torch.testing.assert_close(lam, torch.tensor([[2.0, 2.0, 2.0], [1e-3, 1e-3, 0.7], [1e-3, 0.6, 0.6]]))
    torch.testing.assert_close(v1[0], torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(v3[0], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(v1[1].abs(), torch.tensor([0.0, 1.0, 0.0]))  # a line along y
    torch.testing.assert_close(v3[2].abs(), torch.tensor([0.0, 0.0, 1.0]))  # a sheet normal to z


def test_gate_pieces_drops_the_pieces_mostly_odd():
    """Two pieces: the one 2/3 of whose cells are odd is dropped at share 0.5, the one with 1/3
    is kept; at share 0.3 both go."""
    added = torch.zeros(8, 8, 8, dtype=torch.bool)
    odd = torch.zeros_like(added)
    added[1, 1, 0:3] = True
    odd[1, 1, 0:2] = True
    added[5, 5, 0:3] = True
    odd[5, 5, 0] = True
    dropped = gate_pieces(added, odd, 0.5)
    assert dropped[1, 1, 0:3].all() and not dropped[5, 5].any()
    assert torch.equal(gate_pieces(added, odd, 0.3), added)


def frame_grid() -> torch.Tensor:
    """Opacities of a stool's frame: four legs along z (cells x, y ∈ {3, 12}, z 0–12) joined by
    four stretchers along x or y at z = 5, and a seat slab at z = 13; each bar one cell thick,
    a faint halo (0.05) around it as a trained density has."""
    g = torch.zeros(RES, RES, RES)
    for i in (3, 12):
        for j in (3, 12):
            g[i, j, 0:13] = 1.0
        g[i, 3:13, 5] = 1.0  # stretchers along y
        g[3:13, i, 5] = 1.0  # stretchers along x
    g[3:13, 3:13, 13] = 1.0
    halo = occupancy.dilate(g > 0, 1) & (g == 0)
    return torch.where(halo, torch.full_like(g, 0.05), g)


def test_shape_gate_keeps_legs_out_of_a_stretcher_join():
    """Stretchers scribbled, the legs of their colour joined: the legs are lines square to
    every scribbled point, so the gate drops them; a join of the seat's rim (lines lying in
    the seat, as scribbled on its top) stays."""
    g = frame_grid()
    pos = torch.cat([centre_of(i, 3, 5) for i in (6, 7, 8)] + [centre_of(3, j, 5) for j in (6, 7, 8, 9)])
    legs = torch.zeros(RES, RES, RES, dtype=torch.bool)
    for i in (3, 12):
        for j in (3, 12):
            legs[i, j, 0:5] = True
            legs[i, j, 6:13] = True
    cells = legs.reshape(-1).nonzero().squeeze(-1)
    xn = occupancy.centers_of_cells(cells, RES)
    odd = torch.zeros(RES**3, dtype=torch.bool)
    odd[cells] = odd_lines(local_frames(g, xn, 2), local_frames(g, pos, 2))
    odd = odd.view(RES, RES, RES)
    assert float(odd[legs].float().mean()) > 0.6
    assert torch.equal(gate_pieces(legs, odd, options_for("remove").shape_gate), legs)
    # the seat's top scribbled: its rim (lines along x and y in the seat's plane) is no odd line
    seat_pos = torch.cat([centre_of(i, j, 13) for i in (6, 8) for j in (6, 8)])
    rim = torch.zeros(RES, RES, RES, dtype=torch.bool)
    rim[3:13, 3, 13] = rim[3:13, 12, 13] = True
    rc = rim.reshape(-1).nonzero().squeeze(-1)
    rim_odd = odd_lines(local_frames(g, occupancy.centers_of_cells(rc, RES), 2), local_frames(g, seat_pos, 2))
    assert not rim_odd.any()


class _Uniform:
    """A field-like stand-in of constant density σ over the box [−1, 1]³."""

    def __init__(self, sigma: float):
        self.aabb = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
        self.s = sigma
        self.raw_density = lambda fused: fused.squeeze(-1)
        self.sigma = lambda raw: raw

    def fuse_features(self, x, instance):
        return torch.full((x.shape[0], 1), self.s)


def test_cell_opacity_closed_form():
    """1 − exp(−σ·h/32) in the occupied cells (h = 2/R, the box's side over R), 0 elsewhere; a
    density passed in is used as given."""
    occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    occupied[2:4, 2:4, 2:4] = True
    field = _Uniform(40.0)
    got = cell_opacity(field, 0, occupied)
    want = 1 - np.exp(-40.0 * (2 / 8) * SHAPE_FRACTION)
    assert torch.allclose(got[occupied], torch.tensor(want, dtype=torch.float32)) and not got[~occupied].any()
    given = cell_opacity(field, 0, occupied, torch.full((8,), 4.0))
    assert torch.allclose(given[occupied], torch.tensor(1 - np.exp(-4.0 * 0.25 * SHAPE_FRACTION), dtype=torch.float32))


def test_removal_options_read_the_shape():
    """Removals read the density's shape with a weight above the others' and gate their joins;
    recolours and additions read no shape."""
    o = options_for("remove")
    assert o.shape_from == "density" and o.geometry_weight == S.REMOVE_GEOMETRY_WEIGHT > 1
    assert o.shape_gate == S.REMOVE_SHAPE_GATE > 0 and o.rim_fill == S.REMOVE_RIM_FILL > 0 and o.sheet_veto == S.REMOVE_SHEET_VETO > 0
    assert options_for("color").rim_fill == options_for("color").shape_gate == options_for("color").sheet_veto == 0
    assert options_for("add").sheet_veto == 0
    assert "geometry" not in options_for("color").features and "geometry" not in options_for("add").features


def seat_scribble(edit_category):
    """(model, instance 2, the train view showing most of its seat, a scribble on the seat
    eroded by a pixel, keep strokes on the other parts) of the shared edit fixture
    (test_selection's :func:`part_view`)."""
    from test_selection import part_view

    _, model, category = edit_category
    view, fg, keep, _ = part_view(category, 2, "seat")
    return model, 2, view, fg, keep


def test_removal_selection_reports_the_gate_and_refuses_an_unknown_shape_source(edit_category):
    """A removal's selection on a trained model reads the density's shape and says how many
    joined cells the gate left out; the occupancy grid's shape is the other source, any other
    name a one-line error."""
    import dataclasses

    from crfedit.edit.selection import ScribbleView, select
    from crfedit.errors import CrfError

    model, k, view, fg, keep = seat_scribble(edit_category)
    views = [ScribbleView(view.camera, fg, keep)]
    sel = select(model, k, views, options_for("remove"))
    assert "geometry" in sel.meta["features"] and isinstance(sel.meta["shape_gate"]["dropped"], int)
    assert isinstance(sel.meta["rim_fill"]["cells"], int)
    assert sel.reads_sheets and sel.meta["rim_fill"]["sheet_share"] >= 0.5  # a seat panel: its removal takes its outline
    assert sel.meta["selected_cells"] > 0
    occ = select(model, k, views, dataclasses.replace(options_for("remove"), shape_from="occupancy"))
    assert occ.meta["selected_cells"] > 0
    with pytest.raises(CrfError, match="shape_from 'voxels'"):
        select(model, k, views, dataclasses.replace(options_for("remove"), shape_from="voxels"))


def test_shape_summary_lines():
    """One line for `select` and the page: nothing said when the gate did not run."""
    from crfedit.edit.selection import shape_summary

    assert shape_summary({}) is None
    assert shape_summary({"shape_gate": {"dropped": 0}}) == "nothing left out of the joins"
    assert shape_summary({"shape_gate": {"dropped": 412}}).startswith("left 412 cells out of the joins")
    assert shape_summary({"shape_gate": {"dropped": 1}, "rim_fill": {"cells": 1}}) == ("left 1 cell out of the joins (pieces of lines square to the scribble, such as legs under scribbled "
                                                                                           "stretchers; if they belong to the part, scribble them too, here or from a second view); "
                                                                           "took 1 rim cell (lines lying in the scribbled panel's plane)")
    both = shape_summary({"shape_gate": {"dropped": 0}, "rim_fill": {"cells": 37}})
    assert both.startswith("nothing left out of the joins; took 37 rim cells")
    assert shape_summary({"rim_fill": {"cells": 0}}) == "no rim taken"
    assert shape_summary({"rim_fill": {"cells": 0, "sheet_share": 0.3}}) == "no rim taken"
    assert shape_summary({"rim_fill": {"cells": 5, "sheet_share": 0.96}}) == ("took 5 rim cells (lines lying in the scribbled panel's plane); "
                                                                            "the scribble lies on sheets (96%): a removal also empties their outline")
    sheets = shape_summary({"shape_gate": {"dropped": 0}, "sheet_veto": {"line_share": 0.875, "cells": 1963}})
    assert sheets == "nothing left out of the joins; left 1963 sheet cells out (the scribble lies on lines: 88%)"
    assert shape_summary({"shape_gate": {"dropped": 0}, "sheet_veto": {"line_share": 0.2, "cells": 0}}) == "nothing left out of the joins"


@pytest.mark.parametrize("n, p, f", [(20000, 90, 11), (300, 2500, 11), (20, 20, 5), (8200, 20, 4), (30, 10, 130), (1, 1, 3)])
def test_nearest_distance_is_cdist_min_to_the_bit(n, p, f):
    """Without a root per pair, ``cdist(...).min(dim=1)`` on both of cdist's paths (past 25 rows
    a padded product, below them the direct one; 8200 cells make a last chunk of 8), over at
    most 2000 evenly spaced points: the same bits where the BLAS computes a dot product alike in
    both orientations of the product (the Intel Xeon of earlier sessions, every case), else
    within a few ulp (an AMD EPYC's BLAS, 130 features: 5 of 30 values an ulp off)."""
    from crfedit.edit.selection.classify import nearest_distance

    g = torch.Generator().manual_seed(n + p)
    cells, points = torch.randn(n, f, generator=g), 1.5 * torch.randn(p, f, generator=g)
    used = points[torch.linspace(0, p - 1, 2000).long()] if p > 2000 else points
    ref = torch.cat([torch.cdist(c, used).min(dim=1).values for c in cells.split(8192)])
    got = nearest_distance(cells, points)
    torch.testing.assert_close(got, ref, rtol=4 * torch.finfo(torch.float32).eps, atol=0.0)


def test_sheet_veto_leaves_no_sheet_but_the_scribbled_cells(edit_category):
    """With the scribble read as lines (``sheet_veto`` tiny, so any share of lines is enough),
    no selected cell is a sheet but the scribbled cells themselves; without the veto the same
    scribble selects sheet cells (the seat), so the test can fail."""
    import dataclasses

    from crfedit.edit.selection import ScribbleView, select, shape_summary, surface_points

    model, k, view, fg, keep = seat_scribble(edit_category)
    views = [ScribbleView(view.camera, fg, keep)]
    field = model.field_for(k)
    occupied = field.occupancy[k]
    res = occupied.shape[-1]
    pts, on = surface_points(field, view.camera, k)
    scribbled = pipeline._cells_of(field, pts[torch.from_numpy(fg.reshape(-1)) & on], res)
    grid = cell_opacity(field, k, occupied)

    def sheet_cells(sel) -> torch.Tensor:
        chosen = sel.values >= sel.threshold
        cells = chosen.reshape(-1).nonzero().squeeze(-1)
        out = torch.zeros(res**3, dtype=torch.bool)
        out[cells] = sheets_of(local_frames(grid, occupancy.cell_centers(res)[cells], SHAPE_GATE_RADIUS))
        return out.view(res, res, res)

    # every scribbled pixel, as `scribbled` above; no rim fill, the later step that may take a sheet's first cells beside the selection
    base = dataclasses.replace(options_for("remove"), mirror="off", stroke_centres=False, fill_share=0.0)
    off = select(model, k, views, dataclasses.replace(base, sheet_veto=0.0))
    on_ = select(model, k, views, dataclasses.replace(base, sheet_veto=1e-6))
    assert "sheet_veto" not in off.meta and on_.meta["sheet_veto"]["cells"] > 0
    assert (sheet_cells(off) & ~scribbled).any()
    assert not (sheet_cells(on_) & ~scribbled).any()
    assert 0 < on_.meta["selected_cells"] < off.meta["selected_cells"]
    assert shape_summary(on_.meta).startswith(("nothing left out of the joins; left ", "left "))


def test_a_join_under_a_scribble_on_bars_leaves_the_slab_out():
    """The stool's stretchers scribbled (lines), the legs and the seat joined by their shared
    colour: the pieces mostly not lines (the seat slab) are left out at the options' share, the
    legs (lines) stay; scribbled on the seat's top instead, the scribble does not read as
    lines and the rule does not run."""
    from crfedit.edit.selection.shapes import JOIN_LINES, lines_of

    g = frame_grid()
    bars = torch.cat([centre_of(i, 3, 5) for i in (6, 7, 8)] + [centre_of(3, j, 5) for j in (6, 7, 8, 9)])
    assert float(lines_of(local_frames(g, bars, SHAPE_GATE_RADIUS)).float().mean()) >= JOIN_LINES
    top = torch.cat([centre_of(i, j, 13) for i in (6, 8) for j in (6, 8)])
    assert float(lines_of(local_frames(g, top, SHAPE_GATE_RADIUS)).float().mean()) < JOIN_LINES
    legs, seat = torch.zeros(RES, RES, RES, dtype=torch.bool), torch.zeros(RES, RES, RES, dtype=torch.bool)
    for i in (3, 12):
        for j in (3, 12):
            legs[i, j, 0:5] = True
    seat[3:13, 3:13, 13] = True
    added = legs | seat
    cells = added.reshape(-1).nonzero().squeeze(-1)
    not_line = torch.zeros(RES**3, dtype=torch.bool)
    not_line[cells] = ~lines_of(local_frames(g, occupancy.centers_of_cells(cells, RES), SHAPE_GATE_RADIUS))
    dropped = gate_pieces(added, not_line.view(RES, RES, RES), S.JOIN_LINES_SHARE)
    assert torch.equal(dropped, seat)
    assert options_for("color").join_lines == options_for("remove").join_lines == S.JOIN_LINES_SHARE > 0
    assert options_for("add").join_lines == 0


def test_join_lines_only_takes_cells_out_of_a_join_and_says_so(edit_category, monkeypatch):
    """With the rule made to run on any scribble (``JOIN_LINES`` 0) and to leave out any piece
    with a cell that is not a line, a forced join keeps only pieces of lines: the selection is
    a subset of the one without the rule, its metadata counts what was left out, and the
    summary line names it; without the rule nothing is left out."""
    from test_selection import part_view

    from crfedit.edit.selection import ScribbleView, SelectOptions, join_summary, select

    _, model, category = edit_category
    k = 1
    view, fg, keep, _ = part_view(category, k, "back")
    views = [ScribbleView(view.camera, fg, keep)]
    base = SelectOptions(chroma_union=1e6, chroma_saturation=0.0)
    monkeypatch.setattr(pipeline, "JOIN_LINES", 0.0)
    plain = select(model, k, views, base)
    gated = select(model, k, views, dataclasses.replace(base, join_lines=1e-6))
    assert "not_lines" not in plain.meta["chroma_union"]
    left = gated.meta["chroma_union"]["not_lines"]
    assert left > 0 and gated.meta["chroma_union"]["joined"]
    assert bool((plain.mask | ~gated.mask).all())  # every cell the rule keeps, the join without it took
    assert int(gated.mask.sum()) < int(plain.mask.sum())
    assert f"; left out {left} of them, in pieces that are not lines (the scribble lies on lines)" in join_summary(gated.meta)
    assert "not lines" not in join_summary(plain.meta)
    # a join the cap refuses says a forced one would keep to lines, with line_negatives off
    refused = select(model, k, views, dataclasses.replace(base, chroma_union=1e-6, join_lines=1e-6, line_negatives=False))
    assert not refused.meta["chroma_union"]["joined"] and refused.meta["chroma_union"]["keeps_lines"]
    assert "line_negatives" not in refused.meta
    assert join_summary(refused.meta).endswith("--colour-join always would join only the pieces of bars)")
    assert not plain.meta["chroma_union"]["keeps_lines"]


def test_line_negatives_hold_the_view_s_points_off_lines(edit_category, monkeypatch):
    """With the rule made to run on any scribble (``JOIN_LINES`` 0), the scribbled view's other
    surface points whose cells are not lines stay negatives: the metadata counts them (some,
    not all of the view's points), the summary says so, and the selection changes; off, or
    with a scribble read as not on lines, neither the metadata nor the line appear."""
    from test_selection import part_view

    from crfedit.edit.selection import ScribbleView, SelectOptions, join_summary, lines_summary, select

    _, model, category = edit_category
    k = 1
    view, fg, keep, _ = part_view(category, k, "back")
    views = [ScribbleView(view.camera, fg, keep)]
    on = SelectOptions(line_negatives=True)
    assert "line_negatives" not in select(model, k, views, on).meta  # the back is a panel: its scribble does not lie on lines
    monkeypatch.setattr(pipeline, "JOIN_LINES", 0.0)
    plain = select(model, k, views, SelectOptions())
    held = select(model, k, views, on)
    info = held.meta["line_negatives"]
    assert 0 < info["points"] < held.meta["view_points"]
    assert lines_summary(held.meta) == (f"the scribble lies on lines ({info['line_share']:.0%}): {info['points']} of the view's other "
                                        "surface points, off lines, held as not the part")
    assert "line_negatives" not in plain.meta and lines_summary(plain.meta) is None
    refused = {**held.meta, "chroma_union": {"saturation": 0.9, "cells": 900, "joined": False, "features_cells": 100, "cap": 3.5}}
    assert join_summary(refused).endswith("(the scribble lies on bars: --colour-join always would join only the pieces of bars)")
    not_on_bars = {key: value for key, value in refused.items() if key != "line_negatives"}
    general = "(if the part is that large: --colour-join always, or scribble more of it or from a second view)"
    assert join_summary(not_on_bars).endswith(general)
    # since the fifty-fifth session the join says itself whether it would keep to bars: join_lines on, line_negatives off or on
    keeps = {"chroma_union": {**refused["chroma_union"], "keeps_lines": True}}
    assert join_summary(keeps).endswith("(the scribble lies on bars: --colour-join always would join only the pieces of bars)")
    assert join_summary({**refused, "chroma_union": {**refused["chroma_union"], "keeps_lines": False}}).endswith(general)
    assert not torch.equal(held.values, plain.values)
    assert options_for("color").line_negatives and options_for("remove").line_negatives and not options_for("add").line_negatives


def test_on_bars_overrides_apply_only_under_a_scribble_on_lines(edit_category, monkeypatch):
    """``SelectOptions.on_bars``: with every scribble read as lying on lines (``JOIN_LINES``
    0) the overrides apply before any feature is read, so the selection is the one the
    overridden options make, to the bit, and its metadata and summary line say so; with no
    scribble on lines (``JOIN_LINES`` above 1) they do not apply; a name that is not an
    option is a one-line error."""
    from test_selection import part_view

    from crfedit.edit.selection import ScribbleView, SelectOptions, lines_summary, select
    from crfedit.errors import CrfError

    _, model, category = edit_category
    k = 1
    view, fg, keep, _ = part_view(category, k, "back")
    views = [ScribbleView(view.camera, fg, keep)]
    bars = SelectOptions(on_bars=(("features", ("bottleneck", "position")), ("position_weight", 0.5)))
    direct = SelectOptions(features=("bottleneck", "position"), position_weight=0.5)
    monkeypatch.setattr(pipeline, "JOIN_LINES", 0.0)
    got, want = select(model, k, views, bars), select(model, k, views, direct)
    assert torch.equal(got.values, want.values)
    assert got.meta["on_bars"]["options"] == ["features", "position_weight"] and "on_bars" not in want.meta
    assert got.meta["features"] == want.meta["features"]
    assert lines_summary(got.meta) == (f"the scribble lies on lines ({got.meta['on_bars']['line_share']:.0%}): "
                                       "selected as on bars (features, position_weight)")
    monkeypatch.setattr(pipeline, "JOIN_LINES", 1.01)
    off = select(model, k, views, bars)
    assert "on_bars" not in off.meta and torch.equal(off.values, select(model, k, views, SelectOptions()).values)
    assert options_for("color").on_bars and not options_for("remove").on_bars and not options_for("add").on_bars
    with pytest.raises(CrfError, match="on_bars"):
        SelectOptions(on_bars=(("no_such_option", 1.0),)).on_bars_options()


def test_a_thick_post_reads_as_a_bar_in_the_wider_block():
    """A square post 4 cells thick (a procedural leg at 64³): its middle cells' shape in the
    gates' 5³ block is a blob, not a line; in ``BARS_RADIUS``'s 7³ block it is a line along the
    post.  A slab 4 cells thick reads as no line in either."""
    from crfedit.edit.selection.shapes import BARS_RADIUS, lines_of

    res = 24
    post = torch.zeros(res, res, res)
    post[10:14, 10:14, 2:22] = 1.0
    pts = torch.cat([centre_of(i, j, k, res) for i in (11, 12) for j in (11, 12) for k in (8, 12, 16)])
    assert BARS_RADIUS > SHAPE_GATE_RADIUS
    assert not lines_of(local_frames(post, pts, SHAPE_GATE_RADIUS)).any()
    wide = local_frames(post, pts, BARS_RADIUS)
    assert lines_of(wide).all()
    assert torch.allclose(wide.direction.abs()[:, 2], torch.ones(len(pts)), atol=1e-3)  # along z
    slab = torch.zeros(res, res, res)
    slab[2:22, 2:22, 10:14] = 1.0
    assert not lines_of(local_frames(slab, pts, BARS_RADIUS)).any()
    assert not lines_of(local_frames(slab, pts, SHAPE_GATE_RADIUS)).any()
