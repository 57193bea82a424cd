"""Mirror symmetry (edit/symmetry.py) and how a selection reads it (edit/selection.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from crfedit import occupancy
from crfedit.cameras import Camera, look_at, rays_from_camera
from crfedit.cli import app
from crfedit.edit.selection import pipeline as S
from crfedit.edit.selection import ScribbleView, SelectOptions, load_selection, options_for, select, surface_points
from crfedit.edit.symmetry import Mirror, conflict, find_mirror, mirror_camera, mirror_image, mirror_overlaps
from crfedit.errors import CrfError

from cli_helpers import assert_user_error


def _rolled(grid: torch.Tensor, axis: int, shift: int) -> torch.Tensor:
    """The grid flipped along ``axis`` and shifted by ``shift`` cells the slow way."""
    res = grid.shape[axis]
    out = torch.zeros_like(grid)
    for i in range(res):
        j = res - 1 - i + shift
        if 0 <= j < res:
            out.select(axis, j).copy_(grid.select(axis, i))
    return out


def test_mirror_overlaps_match_a_brute_force_count():
    g = torch.Generator().manual_seed(0)
    grid = torch.rand(12, 12, 12, generator=g) < 0.3
    for axis in range(3):
        counts = mirror_overlaps(grid, axis, 4)
        brute = [int((_rolled(grid, axis, s) & grid).sum()) for s in range(-4, 5)]
        assert counts.long().tolist() == brute


def test_find_mirror_recovers_an_off_centre_plane_and_refuses_an_asymmetric_grid():
    res = 32
    grid = torch.zeros(res, res, res, dtype=torch.bool)
    grid[4:9, 3:20, 5:12] = True  # a box, its mirror across the plane y = 3 cells off centre
    grid |= _rolled(grid, 1, 3)
    m = find_mirror(grid)
    assert (m.axis, m.shift, m.res) == (1, 3, res) and m.overlap == pytest.approx(1.0)
    assert torch.equal(m.grid(grid), grid)
    assert torch.equal(m.grid(m.grid(grid.float())), grid.float())
    lone = torch.zeros(res, res, res, dtype=torch.bool)
    lone[2:6, 2:6, 2:30] = True  # an L: no axis plane maps it onto itself
    lone[2:30, 2:6, 2:6] = True
    lone[2:6, 2:30, 2:6] = True
    assert find_mirror(lone) is None and find_mirror(torch.zeros(8, 8, 8, dtype=torch.bool)) is None


def test_mirror_maps_cells_points_and_world_alike():
    m = Mirror(axis=0, shift=-2, res=16, overlap=1.0)
    aabb = torch.tensor([-1.0, -2.0, 0.0, 3.0, 2.0, 1.5])
    centres = occupancy.cell_centers(16)
    ijk, _ = occupancy.cell_index(m.normalized(centres), 16)
    one = torch.zeros(16**3)
    one[1234] = 1.0
    moved = m.grid(one.view(16, 16, 16)).reshape(-1)
    i = int(moved.nonzero())
    assert ijk[1234].tolist() == [i // 256, i // 16 % 16, i % 16]
    x = torch.tensor([[0.3, -1.1, 0.7], [2.9, 1.9, 0.1]])
    lo, hi = aabb[:3], aabb[3:]
    normalize = lambda p: (p - lo) / (hi - lo) * 2 - 1
    torch.testing.assert_close(normalize(m.points(aabb, x)), m.normalized(normalize(x)))
    torch.testing.assert_close(m.points(aabb, m.points(aabb, x)), x)
    assert m.cell(aabb) == 4.0 / 16  # the box's largest side (x: 4) over the grid's 16 cells


def test_the_mirrored_camera_sees_the_mirror_image_flipped_left_right():
    m = Mirror(axis=0, shift=3, res=32, overlap=1.0)
    aabb = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    cam = Camera(look_at((2.0, -1.5, 1.0), target=(0.2, 0.1, 0.0)), focal=40.0, width=7, height=5)
    mc = mirror_camera(cam, m, aabb)
    r = mc.c2w[:3, :3]
    torch.testing.assert_close(torch.from_numpy(r.T @ r), torch.eye(3, dtype=torch.float64))
    assert np.linalg.det(r) == pytest.approx(1.0)  # still a rotation: right-handed
    a, b = rays_from_camera(cam), rays_from_camera(mc)
    flip = lambda t: t.view(5, 7, 3).flip(1).reshape(-1, 3)
    mat = torch.from_numpy(m.matrix(aabb)).to(a.origins.dtype)
    torch.testing.assert_close(b.origins, flip(a.origins) @ mat[:3, :3].T + mat[:3, 3])
    torch.testing.assert_close(b.directions, flip(a.directions) @ mat[:3, :3].T)
    img = np.arange(10).reshape(2, 5)
    assert mirror_image(img)[0].tolist() == [4, 3, 2, 1, 0] and mirror_image(None) is None


def test_conflict_closed_form():
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0], [9.0, 0, 0]])
    others = torch.tensor([[0.0, 0.5, 0], [9.0, 0.7, 0]])  # [1, 0, 0] is 1.12 from the first
    assert conflict(pts, others, cell=0.5) == pytest.approx(0.5)  # tolerance 1.5 cells = 0.75
    assert conflict(pts, others[:0], cell=0.5) == 0.0 and conflict(pts[:0], others, cell=0.5) == 0.0


def _halves(model, category, k: int, mirror: Mirror):
    """A view of instance k's seat from above, and its seat pixels on either side of the plane."""
    inst = category.instances[k]
    pid = next(p["id"] for p in json.loads((inst.path / "parts.json").read_text()) if p["name"] == "seat")
    field = model.field_for(k)
    view = max(inst.splits["train"], key=lambda v: int((v.parts == pid).sum()))
    pts, on = surface_points(field, view.camera, k)
    side = mirror.normalized(field.normalize(pts))[:, mirror.axis] - field.normalize(pts)[:, mirror.axis]
    seat = torch.from_numpy(view.parts.reshape(-1) == pid) & on
    one = (seat & (side < -4.0 / mirror.res)).view(view.parts.shape).numpy()
    other = (seat & (side > 4.0 / mirror.res)).view(view.parts.shape).numpy()
    return view, one, other


def test_a_selection_reads_the_mirror_and_one_sided_strokes_turn_it_off(edit_category, monkeypatch):
    """views: the mirrored strokes lie on the mirror image of the scribbled ones; keep strokes on
    the scribble's mirror image switch mirroring off (the same selection as without it);
    values: the selection is the cell-wise max with its own mirror image."""
    _, model, category = edit_category
    k, res = 2, model.cfg.occ_res
    mirror = Mirror(axis=1, shift=0, res=res, overlap=1.0)
    monkeypatch.setattr(S, "find_mirror", lambda occupied: mirror)
    view, one, other = _halves(model, category, k, mirror)
    assert one.sum() > 10 and other.sum() > 10
    field = model.field_for(k)
    cell = float((field.aabb[3:] - field.aabb[:3]).max()) / res
    pos, neg, cand, surfaces, _ = S._lift_views(field, k, [ScribbleView(view.camera, one, None)], 0.5, None)
    mirrored = S._lift_mirrors(field, k, [ScribbleView(view.camera, one, None)], surfaces, mirror, 0.5)
    assert len(mirrored[0]) >= 0.3 * len(pos)
    assert conflict(mirror.points(field.aabb, mirrored[0]), pos, cell) == 1.0

    base = SelectOptions(features=("bottleneck", "chroma", "position"))
    off = select(model, k, [ScribbleView(view.camera, one, None)], base)
    views = select(model, k, [ScribbleView(view.camera, one, None)], SelectOptions(**{**base.__dict__, "mirror": "views"}))
    assert "mirror" not in off.meta and views.meta["mirror"]["used"] and views.meta["mirror"]["positives"] == len(mirrored[0])
    assert views.meta["positives"] == off.meta["positives"] + len(mirrored[0])

    def no_render(*args, **kwargs):
        raise AssertionError("the mirrored view was rendered although the keep strokes turn mirroring off")

    with monkeypatch.context() as m:  # the conflict is decided before any mirrored view is rendered
        m.setattr(S, "_lift_mirrored", no_render)
        one_sided = select(model, k, [ScribbleView(view.camera, one, other)], SelectOptions(**{**base.__dict__, "mirror": "views"}))
    assert not one_sided.meta["mirror"]["used"] and "mirror image" in one_sided.meta["mirror"]["why"]
    plain = select(model, k, [ScribbleView(view.camera, one, other)], base)
    assert torch.equal(one_sided.values, plain.values)

    values = select(model, k, [ScribbleView(view.camera, one, None)], SelectOptions(**{**base.__dict__, "mirror": "values"}))
    occ = field.occupancy[k]
    both = occ & mirror.grid(occ)
    expected = torch.where(both, torch.maximum(off.values, mirror.grid(off.values)), off.values)
    assert torch.equal(values.values, expected) and values.meta["mirror"]["used"]
    assert int(values.mask.sum()) > int(off.mask.sum())


def test_mirror_options_and_commands(edit_category, tmp_path):
    path, model, category = edit_category
    assert options_for("remove").mirror == "views" and options_for("color").mirror == "values" and options_for("add").mirror == "off"
    assert options_for("remove", "off").mirror == "off"
    with pytest.raises(CrfError, match="--mirror sideways"):
        options_for("color", "sideways")
    with pytest.raises(CrfError, match="mirror mode 'sideways'"):
        select(model, 0, [ScribbleView(category.instances[0].splits["train"][0].camera, np.ones((32, 32), bool), None)],
               SelectOptions(mirror="sideways"))
    from PIL import Image

    view = category.instances[1].splits["train"][0]
    Image.fromarray(((view.parts > 0) * 255).astype(np.uint8)).save(tmp_path / "fg.png")
    runner = CliRunner()
    base = ["--instance", model.names[1], "--view", "train:0", "--scribble", str(tmp_path / "fg.png")]
    r = runner.invoke(app, ["select", str(path), *base, "--mirror", "off", "--out", str(tmp_path / "s.safetensors")])
    assert r.exit_code == 0, r.output
    assert "mirror" not in load_selection(tmp_path / "s.safetensors").meta
    r = runner.invoke(app, ["select", str(path), *base, "--for", "remove", "--out", str(tmp_path / "r.safetensors")])
    assert r.exit_code == 0 and "mirror: " in r.output, r.output
    assert load_selection(tmp_path / "r.safetensors").meta["mirror"]["mode"] == "views"
    r = runner.invoke(app, ["remove", str(path), *base, "--method", "paper", "--mirror", "off", "--force", "--out", str(tmp_path / "e.safetensors")])
    assert_user_error(r, "--mirror belongs to --method selection")
    assert not (tmp_path / "e.safetensors").exists()
    r = runner.invoke(app, ["remove", str(path), *base, "--selection", str(tmp_path / "r.safetensors"), "--mirror", "off", "--force",
                            "--out", str(tmp_path / "e.safetensors")])
    assert_user_error(r, "give it to `crfedit select`")
    assert not (tmp_path / "e.safetensors").exists()


def test_mirror_off_keeps_a_removal_to_the_scribbled_side():
    """--mirror off is one side only: a removal's loose pieces (the other arm is one) are not taken."""
    from crfedit.edit.selection import options_for

    assert options_for("remove").free_pieces > 0 and options_for("remove", "views").free_pieces > 0
    assert options_for("remove", "off").free_pieces == 0.0 and options_for("remove", "off").mirror == "off"
