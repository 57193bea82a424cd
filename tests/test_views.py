"""The view SPEC grammar: splits, index lists and ranges, orbits, camera files, resizing, errors."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from crfedit.cameras import focal_from_angle, look_at, rays_from_camera, spherical_eye
from crfedit.config import make_config
from crfedit.errors import CrfError
from crfedit.field import ConditionalRadianceField
from crfedit.model import CategoryModel, ViewTable
from crfedit.views import parse_indices, parse_resolution, resolve_views

W, H, FOCAL = 32, 24, 40.0


def table(views_per_instance: int, radii: list[float]) -> ViewTable:
    """Two instances; view i of instance k sits at azimuth 30°·i, radius radii[i % len(radii)]."""
    c2w, inst = [], []
    for k in range(2):
        for i in range(views_per_instance):
            c2w.append(look_at(spherical_eye(30.0 * i, 20.0, radii[i % len(radii)])))
            inst.append(k)
    n = len(inst)
    return ViewTable(torch.tensor(np.stack(c2w)), torch.full((n,), FOCAL, dtype=torch.float64), torch.tensor(inst), W, H)


@pytest.fixture(scope="module")
def model() -> CategoryModel:
    cfg = make_config("fast", sets=["grid_res=0", "occ_res=2", "width=8", "rad_width=8"])
    views = {"train": table(6, [2.0, 3.0, 4.0]), "test": table(3, [2.5])}
    return CategoryModel(ConditionalRadianceField(cfg, 2), ["chair_a", "chair_b"], views=views)


def labels(views) -> list[str]:
    return [label for label, _ in views]


def test_whole_split_and_its_cameras(model):
    views = resolve_views("train", model, 1)
    assert labels(views) == [f"train:{i}" for i in range(6)]
    stored = model.views["train"].cameras(1)
    for (_, cam), ref in zip(views, stored):
        np.testing.assert_array_equal(cam.c2w, ref.c2w)
        assert (cam.focal, cam.width, cam.height) == (FOCAL, W, H)


@pytest.mark.parametrize(
    "spec, expected",
    [
        ("test:2", ["test:2"]),
        ("test:0-2", ["test:0", "test:1", "test:2"]),
        ("train:1,4,5", ["train:1", "train:4", "train:5"]),
        ("train:0-1,4", ["train:0", "train:1", "train:4"]),
        ("train:3-3", ["train:3"]),
        (" test ", ["test:0", "test:1", "test:2"]),
    ],
)
def test_indices_and_ranges(model, spec, expected):
    assert labels(resolve_views(spec, model, 0)) == expected


@given(st.lists(st.tuples(st.integers(0, 19), st.integers(0, 5)), min_size=1, max_size=6))
def test_parse_indices_expands_ranges_in_order(items):
    text = ",".join(f"{a}-{min(a + n, 19)}" if n else str(a) for a, n in items)
    expected = [i for a, n in items for i in range(a, min(a + n, 19) + 1)]
    assert parse_indices("spec", text, 20) == expected


@pytest.mark.parametrize(
    "spec, message",
    [
        ("val", "stores no val views"),
        ("bogus", "expected train, val or test"),
        ("bogus:3", "expected train, val or test"),
        ("test:3", "index 3 out of range (0-2)"),
        ("test:1-7", "index 7 out of range"),
        ("test:2-1", "runs backwards"),
        ("test:x", "'x' is not an index"),
        ("test:", "'' is not an index"),
        ("test:-1", "is not an index"),
        ("orbit", "expected orbit:N"),
        ("orbit:0", "between 1 and"),
        ("orbit:4@90", "strictly between -90 and 90"),
        ("orbit:4@x", "expected orbit:N"),
        ("orbit:4:4", "index 4 out of range (0-3)"),
        ("orbit:4@20:x", "'x' is not an index"),
        ("", "view spec is empty"),
    ],
)
def test_bad_specs_are_one_line_errors_naming_the_spec(model, spec, message):
    with pytest.raises(CrfError) as e:
        resolve_views(spec, model, 0)
    assert message in str(e.value) and "\n" not in str(e.value)
    if spec.strip():
        assert repr(spec.strip()) in str(e.value)


def test_orbit_radius_focal_elevation(model):
    views = resolve_views("orbit:4", model, 0)
    assert labels(views) == ["orbit:4@30:0", "orbit:4@30:1", "orbit:4@30:2", "orbit:4@30:3"]
    for k, (_, cam) in enumerate(views):
        center = cam.center
        assert math.isclose(np.linalg.norm(center), 3.0)  # median of train radii 2, 3, 4, 2, 3, 4
        assert math.isclose(center[2], 3.0 * math.sin(math.radians(30.0)), abs_tol=1e-12)
        assert math.isclose(math.degrees(math.atan2(center[1], center[0])) % 360.0, 90.0 * k, abs_tol=1e-9)
        forward = -cam.c2w[:3, 2]  # the camera looks down -Z, at the origin
        np.testing.assert_allclose(forward, -center / np.linalg.norm(center), atol=1e-12)
        assert (cam.focal, cam.width, cam.height) == (FOCAL, W, H)
    _, cam = resolve_views("orbit:3@45", model, 0)[0]
    assert math.isclose(cam.center[2], 3.0 * math.sin(math.radians(45.0)), abs_tol=1e-12)
    _, cam = resolve_views("orbit:2@-10.5", model, 0)[0]
    assert cam.center[2] < 0
    # some of an orbit's views by index: the same cameras and labels as in the whole orbit
    whole = resolve_views("orbit:36@20", model, 0)
    some = resolve_views("orbit:36@20:5,30-31", model, 0)
    assert labels(some) == ["orbit:36@20:5", "orbit:36@20:30", "orbit:36@20:31"]
    # each label is a spec of its own view (not orbit:5, which would be an orbit of 5 views)
    assert all(np.array_equal(cam.c2w, resolve_views(label, model, 0)[0][1].c2w) for label, cam in whole[::7] + some)
    assert all(np.array_equal(cam.c2w, whole[int(label.rsplit(":", 1)[1])][1].c2w) for label, cam in some)


def test_res_resizes_width_and_focal_keeps_aspect(model):
    (_, cam), = resolve_views("test:1", model, 0, res=64)
    assert (cam.width, cam.height) == (64, 48)
    assert math.isclose(cam.focal, FOCAL * 2)
    assert all(c.width == 16 for _, c in resolve_views("orbit:3", model, 0, res=16))


def test_nerfstudio_camera_path(model, tmp_path):
    c2w = look_at(spherical_eye(10.0, 25.0, 2.5))
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps({
        "render_width": 40, "render_height": 20, "fps": 24,
        "camera_path": [
            {"camera_to_world": c2w.reshape(-1).tolist(), "fov": 50.0, "aspect": 2.0},
            {"camera_to_world": c2w.tolist(), "fov": 30.0, "aspect": 2.0},
        ],
    }))
    views = resolve_views(str(path), model, 0)
    assert labels(views) == ["camera_path.json:0", "camera_path.json:1"]
    for (_, cam), fov in zip(views, (50.0, 30.0)):
        np.testing.assert_array_equal(cam.c2w, c2w)  # 16 floats are row-major: same as the 4x4
        assert (cam.width, cam.height) == (40, 20)
        assert math.isclose(cam.focal, 10.0 / math.tan(math.radians(fov) / 2))  # vertical fov


def test_single_camera_file_and_transforms_file(model, tmp_path):
    c2w = look_at(spherical_eye(0.0, 0.0, 3.0))
    one = tmp_path / "cam.json"
    one.write_text(json.dumps({"transform_matrix": c2w.tolist(), "camera_angle_x": 0.7, "width": 50, "height": 30}))
    (_, cam), = resolve_views(str(one), model, 0)
    assert (cam.width, cam.height) == (50, 30) and math.isclose(cam.focal, focal_from_angle(0.7, 50))
    np.testing.assert_array_equal(cam.c2w, c2w)
    no_size = tmp_path / "nosize.json"
    no_size.write_text(json.dumps({"transform_matrix": c2w.tolist(), "camera_angle_x": 0.7}))
    (_, cam), = resolve_views(str(no_size), model, 0)
    assert (cam.width, cam.height) == (W, H)  # the stored views' size
    frames = tmp_path / "transforms_test.json"
    frames.write_text(json.dumps({"camera_angle_x": 0.7, "frames": [{"transform_matrix": c2w.tolist()}] * 3}))
    assert labels(resolve_views(str(frames), model, 0)) == [f"transforms_test.json:{i}" for i in range(3)]


def test_an_orbit_view_is_recorded_as_its_spec():
    """An edit records the spec of an orbit view, not its label: ``orbit:5`` alone is another camera."""
    from crfedit.views import one_view_label

    assert one_view_label(" orbit:36@30:5 ", "orbit:5") == "orbit:36@30:5"
    assert one_view_label("train:5", "train:5") == "train:5" and one_view_label("cam.json", "cam.json:0") == "cam.json:0"


def test_strings_are_not_numbers_in_a_camera_matrix(model, tmp_path):
    path = tmp_path / "cams.json"
    path.write_text(json.dumps({"transform_matrix": [[str(v) for v in row] for row in np.eye(4).tolist()], "camera_angle_x": 0.5}))
    with pytest.raises(CrfError, match="holds something other than numbers"):
        resolve_views(str(path), model, 0)


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "malformed JSON"),
        ("[1, 2]", "expected a JSON object"),
        ('{"camera_path": []}', "non-empty list"),
        ('{"camera_path": [{"camera_to_world": [1, 2, 3], "fov": 50}]}', "not a 4x4 matrix"),
        ('{"camera_path": [{"camera_to_world": ' + json.dumps(np.eye(4).tolist()) + "}]}", "fov must be a number"),
        ('{"camera_path": [{"camera_to_world": ' + json.dumps(np.zeros((4, 4)).tolist()) + ', "fov": 40}]}', "invertible"),
        ('{"transform_matrix": ' + json.dumps(np.diag([2.0, 2.0, 2.0, 1.0]).tolist()) + ', "camera_angle_x": 0.5}', "scaled or sheared"),
        ('{"transform_matrix": ' + json.dumps([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) + ', "camera_angle_x": 0.5}',
         "scaled or sheared"),
        ('{"transform_matrix": ' + json.dumps(np.diag([-1.0, 1.0, 1.0, 1.0]).tolist()) + ', "camera_angle_x": 0.5}', "mirrors"),
        ('{"transform_matrix": ' + json.dumps([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]) + ', "camera_angle_x": 0.5}',
         "last row other than 0 0 0 1"),
        ('{"transform_matrix": ' + json.dumps(np.eye(4).tolist()) + "}", "camera_angle_x must be a number"),
        ('{"transform_matrix": ' + json.dumps(np.eye(4).tolist()) + ', "camera_angle_x": 0.5, "width": 0}', "width must be"),
        ('{"frames": [{}], "camera_angle_x": 0.5}', "frames[0].transform_matrix"),
        ('{"something": 1}', "expected a camera_path list"),
    ],
)
def test_bad_camera_files(model, tmp_path, content, message):
    path = tmp_path / "cams.json"
    path.write_text(content)
    with pytest.raises(CrfError) as e:
        resolve_views(str(path), model, 0)
    assert message in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value)


def test_missing_camera_file(model, tmp_path):
    with pytest.raises(CrfError, match="camera file not found"):
        resolve_views(str(tmp_path / "nope.json"), model, 0)
    os.mkfifo(tmp_path / "pipe.json")  # a named pipe nothing writes to: read as empty, not waited on for ever
    with pytest.raises(CrfError, match=r"pipe\.json: the pipe gave nothing \(nothing wrote to it\)$"):
        resolve_views(str(tmp_path / "pipe.json"), model, 0)


def test_parse_resolution():
    assert parse_resolution(None) is None
    assert parse_resolution("64") == 64 and parse_resolution(7) == 7
    for bad in ("0", "-3", "big", "1.5", 20000):
        with pytest.raises(CrfError, match="--res"):
            parse_resolution(bad)


def test_orbit_without_stored_views_of_the_instance_uses_any_instance():
    cfg = make_config("fast", sets=["grid_res=0", "occ_res=2", "width=8", "rad_width=8"])
    t = table(3, [2.0])
    only_first = ViewTable(t.c2w[:3], t.focal[:3], t.instance[:3], W, H)
    m = CategoryModel(ConditionalRadianceField(cfg, 2), ["a", "b"], views={"train": only_first})
    assert len(resolve_views("orbit:5", m, 1)) == 5
    with pytest.raises(CrfError, match="no cameras"):
        resolve_views("orbit:5", CategoryModel(ConditionalRadianceField(cfg, 2), ["a", "b"]), 0)


def test_orbit_cameras_are_rigid_upright_and_look_at_the_origin(model):
    """Each orbit pose is a rotation (orthonormal, det +1) plus the eye; the camera looks along
    −z (OpenGL axes) straight at the origin, its image up is world-up, and its rays start at the eye."""
    for _, cam in resolve_views("orbit:5@20", model, 0):
        rot, eye = cam.c2w[:3, :3], cam.c2w[:3, 3]
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_array_equal(cam.c2w[3], [0.0, 0.0, 0.0, 1.0])
        np.testing.assert_allclose(-rot[:, 2], -eye / np.linalg.norm(eye), atol=1e-12)
        assert rot[2, 0] == pytest.approx(0.0, abs=1e-12) and rot[2, 1] > 0  # no roll, upright
        rays = rays_from_camera(cam)
        np.testing.assert_allclose(rays.origins.numpy(), np.broadcast_to(eye, (cam.width * cam.height, 3)), atol=1e-6)


def test_an_orbit_circles_where_the_cameras_look_when_that_is_off_the_origin():
    """Cameras that look at an object off the origin (a tester's dataset moved by (0.9, −0.6,
    0.3)) had their turntable orbit the origin, the chair sliding out of frame; the orbit now
    circles the point their axes meet at, at their distance from it.  Cameras aimed at the origin
    (within OFF_CENTRE of their distance) keep the origin exactly."""
    from crfedit.cameras import look_at_point

    shift = np.array([0.9, -0.6, 0.3])
    c2w = []
    for i in range(6):
        eye = spherical_eye(60.0 * i, 20.0, 3.0) + shift
        c2w.append(look_at(eye, shift))
    tables = {"train": ViewTable(torch.tensor(np.stack(c2w)), torch.full((6,), FOCAL, dtype=torch.float64), torch.zeros(6, dtype=torch.long), W, H)}
    cfg = make_config("fast", sets=["grid_res=0", "occ_res=2", "width=8", "rad_width=8"])
    moved = CategoryModel(ConditionalRadianceField(cfg, 1), ["chair_a"], views=tables)
    cams = [cam for _, cam in resolve_views("orbit:8", moved, 0)]
    np.testing.assert_allclose(look_at_point(cams), shift, atol=1e-9)
    assert all(np.linalg.norm(cam.center - shift) == pytest.approx(3.0) for cam in cams)
    # a look-at point a hair off the origin (float noise) is the origin: the usual orbit, unchanged
    hair = np.full(3, 1e-3)
    c2w = np.stack([look_at(spherical_eye(60.0 * i, 20.0, 3.0) + hair, hair) for i in range(6)])
    tables = {"train": ViewTable(torch.tensor(c2w), torch.full((6,), FOCAL, dtype=torch.float64), torch.zeros(6, dtype=torch.long), W, H)}
    nearly = CategoryModel(ConditionalRadianceField(cfg, 1), ["chair_a"], views=tables)
    for _, cam in resolve_views("orbit:4", nearly, 0):
        np.testing.assert_allclose(-cam.c2w[:3, 2], -cam.center / np.linalg.norm(cam.center), atol=1e-12)
