"""Occupancy grids: cell indexing, lookups, dilation, visual-hull carving, density refresh."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from crfedit.cameras import orbit_cameras, rays_from_camera
from crfedit.occupancy import (
    carve_visual_hull,
    cell_centers,
    cell_index,
    dilate,
    lookup,
    masked_trilinear,
    occupied_box,
    step_size,
    update_from_density,
)
from crfedit.sampling import ray_aabb_intersect

AABB = torch.tensor([-0.6, -0.6, -0.6, 0.6, 0.6, 0.6])


def test_cell_index_hand_cases():
    xn = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [-0.49, 0.0, 0.51], [1.01, 0.0, 0.0], [0.0, -1.5, 0.0]])
    ijk, inside = cell_index(xn, 4)
    # floor((x + 1) · 2): -1 → 0, the closed upper face 1 → cell 3, (0.51, 1, 1.51) → (1, 2, 3)
    assert ijk[:3].tolist() == [[0, 0, 0], [3, 3, 3], [1, 2, 3]]
    assert inside.tolist() == [True, True, True, False, False]
    assert ((ijk >= 0) & (ijk < 4)).all()  # outside points are clamped, never out of range


def test_lookup_single_occupied_cell():
    grids = torch.zeros(2, 4, 4, 4, dtype=torch.bool)
    grids[1, 1, 2, 3] = True  # cell [-0.5, 0) × [0, 0.5) × [0.5, 1]
    inside = torch.tensor([[-0.25, 0.25, 0.75], [-0.49, 0.01, 0.99], [-0.01, 0.49, 0.51]])
    assert lookup(grids, torch.tensor([1, 1, 1]), inside).tolist() == [True, True, True]
    assert lookup(grids, torch.tensor([0, 0, 0]), inside).tolist() == [False, False, False]  # other instance
    neighbours = torch.tensor([[0.25, 0.25, 0.75], [-0.25, -0.25, 0.75], [-0.25, 0.25, 0.25]])
    assert not lookup(grids, torch.tensor([1, 1, 1]), neighbours).any()
    # outside the box but clamped into the occupied cell's index → still False
    outside = torch.tensor([[-0.25, 0.25, 1.2], [-0.25, 0.25, 7.0]])
    assert cell_index(outside, 4)[0].tolist() == [[1, 2, 3], [1, 2, 3]]
    assert lookup(grids, torch.tensor([1, 1]), outside).tolist() == [False, False]


def test_masked_trilinear_closed_form():
    """Trilinear over the known cells only, renormalized; the axes are the grid's [ix, iy, iz]."""
    res = 4
    c = lambda i, j, k: [(i + 0.5) / res * 2 - 1, (j + 0.5) / res * 2 - 1, (k + 0.5) / res * 2 - 1]
    values = torch.full((res, res, res), 7.0)  # unknown cells' values must not count
    known = torch.zeros(res, res, res, dtype=torch.bool)
    for ijk, v in (((1, 1, 1), 1.0), ((2, 1, 1), 0.25), ((1, 1, 2), 0.0)):
        values[ijk], known[ijk] = v, True
    mid = lambda a, b, t=0.5: [x + t * (y - x) for x, y in zip(c(*a), c(*b))]
    pts = torch.tensor([
        c(1, 1, 1),                       # a known centre: its value
        mid((1, 1, 1), (2, 1, 1)),        # halfway along x: (1 + 0.25) / 2
        mid((1, 1, 1), (1, 1, 2), 0.25),  # a quarter along z: 0.75 · 1 + 0.25 · 0
        mid((1, 1, 1), (1, 2, 1), 0.75),  # towards an unknown cell: only the known one counts
        c(3, 3, 3),                       # no known cell among the eight: 0
    ])
    got = masked_trilinear(values, known, pts)
    assert torch.allclose(got, torch.tensor([1.0, 0.625, 0.75, 1.0, 0.0]), atol=1e-6), got


def test_cell_centers_follow_the_flat_grid_order():
    c = cell_centers(2)
    assert c.tolist() == [
        [-0.5, -0.5, -0.5], [-0.5, -0.5, 0.5], [-0.5, 0.5, -0.5], [-0.5, 0.5, 0.5],
        [0.5, -0.5, -0.5], [0.5, -0.5, 0.5], [0.5, 0.5, -0.5], [0.5, 0.5, 0.5],
    ]
    grid = torch.rand(5, 5, 5, generator=torch.Generator().manual_seed(0)) > 0.5
    back = lookup(grid[None], torch.zeros(125, dtype=torch.long), cell_centers(5))
    assert torch.equal(back, grid.reshape(-1))


def test_dilate_single_cell():
    grid = torch.zeros(7, 7, 7, dtype=torch.bool)
    grid[3, 3, 3] = True
    assert torch.equal(dilate(grid, 0), grid)
    one = dilate(grid, 1)
    assert one.sum().item() == 27 and one[2:5, 2:5, 2:5].all()
    assert dilate(grid, 2).sum().item() == 125
    corner = torch.zeros(7, 7, 7, dtype=torch.bool)
    corner[0, 0, 0] = True
    assert dilate(corner, 2).sum().item() == 27 and dilate(corner, 2)[:3, :3, :3].all()  # clipped at the border
    assert dilate(grid, 1).dtype == torch.bool


def sphere_masks(cams, radius):
    masks = []
    for cam in cams:
        o, d = (v.double() for v in rays_from_camera(cam))
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - radius**2)
        masks.append((disc > 0).view(cam.height, cam.width).numpy())
    return masks


def box_masks(cams, box):
    masks = []
    for cam in cams:
        o, d = rays_from_camera(cam)
        masks.append(ray_aabb_intersect(o, d, box)[2].view(cam.height, cam.width).numpy())
    return masks


RING = orbit_cameras(8, 25.0, 3.0, 40.0, 32, 32) + orbit_cameras(8, -25.0, 3.0, 40.0, 32, 32)[::2]
RES = 16
CENTERS = AABB[:3].double() + (cell_centers(RES).double() + 1.0) * 0.5 * (AABB[3:] - AABB[:3]).double()


def test_visual_hull_of_a_sphere_contains_it_and_excludes_far_space():
    r = 0.3
    hull = carve_visual_hull(RING, sphere_masks(RING, r), AABB, RES).reshape(-1)
    dist = CENTERS.norm(dim=-1)
    assert hull[dist < r].all()  # the object is never carved
    # 8 views around + 4 below: the hull (dilated by one 0.075 cell) stays within two cells of the sphere
    assert not hull[dist > r + 0.15].any()
    assert not hull.view(RES, RES, RES)[[0, -1]][:, [0, -1]][:, :, [0, -1]].any()  # the 8 corners
    assert hull.sum().item() < 0.2 * RES**3


def test_visual_hull_of_a_box_contains_it_and_excludes_far_space():
    box = torch.tensor([-0.2, -0.1, -0.25, 0.3, 0.1, 0.2])
    hull = carve_visual_hull(RING, box_masks(RING, box), AABB, RES).reshape(-1)
    inside = ((CENTERS >= box[:3]) & (CENTERS <= box[3:])).all(-1)
    assert inside.any() and hull[inside].all()
    gap = torch.maximum(box[:3].double() - CENTERS, CENTERS - box[3:].double()).clamp_min(0).norm(dim=-1)
    assert not hull[gap > 0.15].any()


def test_visual_hull_keeps_only_cells_seen_by_half_the_views():
    # all-True masks carve nothing: only the "seen by at least half the views" rule applies.
    # Cameras on ±X and ±Y at distance 3, W = H = 8, f = 30: a point is in view iff its lateral
    # offsets are below (4/30)·depth, with depth = 3 - (its coordinate along the camera's axis).
    cams = orbit_cameras(4, 0.0, 3.0, 30.0, 8, 8)
    hull = carve_visual_hull(cams, [np.ones((8, 8), dtype=bool)] * 4, AABB, 8, margin=0).reshape(-1)
    p = AABB[:3].double() + (cell_centers(8).double() + 1.0) * 0.6
    x, y, z = p.unbind(-1)
    seen = torch.zeros(len(p), dtype=torch.int32)
    for along, lateral in ((x, y), (y, x), (-x, y), (-y, x)):
        depth = 3.0 - along
        seen += ((lateral.abs() < 4 / 30 * depth) & (z.abs() < 4 / 30 * depth)).int()
    assert (seen == 1).any() and (seen >= 2).any() and (seen == 0).any()
    assert torch.equal(hull, seen >= 2)


def test_occupied_box_and_step_size():
    grid = torch.zeros(8, 8, 8, dtype=torch.bool)
    grid[2, 3, 4] = True  # cell [-0.3, -0.15] × [-0.15, 0] × [0, 0.15]
    torch.testing.assert_close(occupied_box(grid, AABB, 0), torch.tensor([-0.3, -0.15, 0.0, -0.15, 0.0, 0.15]))
    # margin 3: cells (2,3,4)-3 … (2,3,4)+1+3, clamped to [0, 8]
    torch.testing.assert_close(occupied_box(grid, AABB, 3), torch.tensor([-0.6, -0.6, -0.45, 0.3, 0.45, 0.6]))
    assert torch.equal(occupied_box(torch.zeros_like(grid), AABB), AABB)
    assert step_size(AABB, 64, 2.0) == pytest.approx(1.2 / 128)
    assert step_size(torch.tensor([0.0, 0.0, 0.0, 1.0, 3.0, 2.0]), 10, 4.0) == pytest.approx(0.075)


def test_update_from_density_prunes_thin_cells_and_keeps_dense_ones():
    res, step, threshold = 4, 0.01, 0.01  # σ_min = -ln(0.99)/0.01 ≈ 1.005
    candidates = torch.ones(res**3, dtype=torch.bool)
    candidates[0] = False  # cell (0, 0, 0): not in the visual hull
    probes = []

    def density(xn):
        probes.append(xn)
        return torch.where(xn[:, 0] < 0, 1e3, 1e-3)  # dense in the x < 0 half

    ema = torch.zeros(res**3)
    ema[63] = 10.0  # cell (3, 3, 3) was dense before; it now reads 1e-3 and decays to 9.5
    grid = update_from_density(ema, candidates, density, step, threshold, decay=0.95,
                               generator=torch.Generator().manual_seed(0))
    x_neg = cell_centers(res)[:, 0] < 0
    assert torch.equal(grid, (x_neg & candidates) | (torch.arange(res**3) == 63))
    assert not grid[0]  # dense, but not a candidate
    assert ema[63].item() == pytest.approx(9.5)
    assert torch.equal(ema[x_neg & candidates], torch.full((31,), 1e3))
    # every candidate was probed once, inside its own cell
    ijk, inside = cell_index(probes[0], res)
    flat = (ijk[:, 0] * res + ijk[:, 1]) * res + ijk[:, 2]
    assert inside.all() and torch.equal(flat, candidates.nonzero().squeeze(-1))
    # the next refresh, with the density gone: the max-decay forgets slowly, then prunes
    for _ in range(int(math.log(1.005 / 1e3) / math.log(0.95)) + 1):
        grid = update_from_density(ema, candidates, lambda xn: torch.zeros(len(xn)), step, threshold)
    assert not grid[x_neg & candidates].any()


def test_the_scene_box_follows_an_object_off_the_origin_and_warns_when_the_hull_is_cut(tiny_chairs, tmp_path):
    import json

    from crfedit.data.loading import load_category
    from crfedit.data.synth import SynthConfig, write_synth_category
    from crfedit.train import scene_box

    root = tmp_path / "c"
    write_synth_category(root, SynthConfig(instances=1, views=16, res=16, seed=0, twins=False))
    notes = []
    box = scene_box(load_category(root), on_note=notes.append)
    shift = torch.tensor([1.5, 0.0, 0.5])
    for f in (root / "chair_000").glob("transforms_*.json"):
        doc = json.loads(f.read_text())
        for frame in doc["frames"]:
            frame["transform_matrix"] = (np.array(frame["transform_matrix"]) + np.pad(shift.numpy()[:, None], ((0, 1), (3, 0)))).tolist()
        f.write_text(json.dumps(doc))
    moved = scene_box(load_category(root), on_note=notes.append)  # the origin's cube holds none of it
    torch.testing.assert_close(moved, box + shift.repeat(2), atol=1e-4, rtol=0)
    assert notes == []
    scene_box(load_category(tiny_chairs), on_note=notes.append)  # 6 views: a loose hull, but inside the cube
    assert notes == []
    for f in (root / "chair_000").glob("transforms_*.json"):  # back at the origin, with 3x the field of view:
        doc = json.loads(f.read_text())  # the same silhouettes now span a chair too large for the cube
        for frame in doc["frames"]:
            m = np.array(frame["transform_matrix"])
            m[:3, 3] -= shift.numpy()
            frame["transform_matrix"] = m.tolist()
        doc["camera_angle_x"] = min(3 * doc["camera_angle_x"], 3.0)
        f.write_text(json.dumps(doc))
    scene_box(load_category(root), on_note=notes.append)
    assert len(notes) == 1 and "beyond the scene box" in notes[0] and "will be cut off" in notes[0]
