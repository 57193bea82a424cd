"""Cameras and rays: pixel centers, OpenGL axes (-Z forward, +Y up), row 0 at the top, Z-up world."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from crfedit.cameras import (
    Camera,
    focal_from_angle,
    look_at,
    orbit_cameras,
    ray_directions_camera,
    rays_from_camera,
    eye_angles,
    spherical_eye,
)
from crfedit.errors import CrfError


def test_ray_directions_docstring_example():
    d = ray_directions_camera(2, 2, 1.0)
    expected = [[-0.5, 0.5, -1.0], [0.5, 0.5, -1.0], [-0.5, -0.5, -1.0], [0.5, -0.5, -1.0]]
    assert d.tolist() == expected


def test_ray_directions_hand_camera():
    # W=3, H=2, f=2: cx = 1.5, cy = 1; pixel (i, j) → ((i + .5 - 1.5)/2, -(j + .5 - 1)/2, -1), row-major
    d = ray_directions_camera(3, 2, 2.0)
    expected = [
        [-0.5, 0.25, -1.0], [0.0, 0.25, -1.0], [0.5, 0.25, -1.0],  # row 0: the top, +Y
        [-0.5, -0.25, -1.0], [0.0, -0.25, -1.0], [0.5, -0.25, -1.0],
    ]
    assert d.shape == (6, 3) and d.dtype == torch.float64
    assert d.tolist() == expected


def test_rays_from_identity_camera_look_down_minus_z():
    c2w = np.eye(4)
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    rays = rays_from_camera(Camera(c2w, 1.0, 3, 3))
    assert rays.origins.dtype == torch.float32 and rays.directions.dtype == torch.float32
    assert torch.equal(rays.origins, torch.tensor([[1.0, 2.0, 3.0]]).expand(9, 3))
    torch.testing.assert_close(rays.directions.norm(dim=-1), torch.ones(9))
    torch.testing.assert_close(rays.directions[4], torch.tensor([0.0, 0.0, -1.0]))  # the center pixel
    # top-left pixel (0, 0): camera-space (-1, 1, -1) normalized
    torch.testing.assert_close(rays.directions[0], torch.tensor([-1.0, 1.0, -1.0]) / math.sqrt(3.0))


def test_rays_from_a_camera_on_plus_x_follow_the_z_up_world():
    # at +X looking at the origin with world Z up: right is +Y, up is +Z
    cam = Camera(look_at((2.0, 0.0, 0.0)), 4.0, 5, 5)
    d = rays_from_camera(cam).directions.view(5, 5, 3)  # [row, column, xyz]
    torch.testing.assert_close(d[2, 2], torch.tensor([-1.0, 0.0, 0.0]))
    assert d[0, 2, 2] > 0 and d[4, 2, 2] < 0  # row 0 looks up
    assert d[2, 0, 1] < 0 and d[2, 4, 1] > 0  # column 0 looks left (-Y)


def test_look_at_is_orthonormal_right_handed_and_level():
    g = np.random.default_rng(0)
    for eye in g.normal(size=(20, 3)) * 3.0:
        target = g.normal(size=3) * 0.2
        c2w = look_at(eye, target)
        r = c2w[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(c2w[:3, 3], eye)
        back = (eye - target) / np.linalg.norm(eye - target)
        np.testing.assert_allclose(r[:, 2], back, atol=1e-12)  # camera -Z points at the target
        assert abs(r[2, 0]) < 1e-12  # no roll: the camera's right axis is horizontal
        assert r[2, 1] >= 0  # and its up axis points up
        np.testing.assert_array_equal(c2w[3], [0.0, 0.0, 0.0, 1.0])


def test_look_at_straight_down_is_still_a_rotation():
    c2w = look_at((0.0, 0.0, 2.0))
    r = c2w[:3, :3]
    assert np.isfinite(c2w).all()
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[:, 2], [0.0, 0.0, 1.0])


def test_eye_angles_invert_spherical_eye():
    for az, el in [(0.0, 0.0), (45.0, 30.0), (200.0, -70.0), (359.5, 89.0), (90.0, 10.0)]:
        got = eye_angles(spherical_eye(az, el, 3.7))
        assert got == pytest.approx((az, el), abs=1e-9)
    assert eye_angles(np.zeros(3)) == (0.0, 0.0) and eye_angles(np.array([0.0, 0.0, -2.0])) == (0.0, -90.0)


def test_spherical_eye_hand_values():
    np.testing.assert_allclose(spherical_eye(0.0, 0.0, 2.0), [2.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(spherical_eye(90.0, 0.0, 2.0), [0.0, 2.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(spherical_eye(0.0, 90.0, 2.0), [0.0, 0.0, 2.0], atol=1e-15)


def test_orbit_cameras_look_at_the_origin():
    cams = orbit_cameras(6, 30.0, 2.5, 20.0, 9, 7)
    assert len(cams) == 6
    for k, cam in enumerate(cams):
        center = cam.center
        assert np.linalg.norm(center) == pytest.approx(2.5)
        assert center[2] == pytest.approx(2.5 * math.sin(math.radians(30.0)))
        assert math.degrees(math.atan2(center[1], center[0])) % 360.0 == pytest.approx(60.0 * k, abs=1e-9)
        # the optical axis (-Z) points at the origin, and the center pixel's ray passes through it
        np.testing.assert_allclose(-cam.c2w[:3, 2], -center / np.linalg.norm(center), atol=1e-12)
        rays = rays_from_camera(cam)
        o, d = rays.origins[3 * 9 + 4].double(), rays.directions[3 * 9 + 4].double()
        closest = o - (o @ d) * d
        assert closest.norm().item() < 1e-6
        assert (cam.focal, cam.width, cam.height) == (20.0, 9, 7)


def test_camera_resized_scales_focal_and_keeps_the_field_of_view():
    cam = Camera(look_at((0.0, -2.0, 0.5)), 100.0, 200, 150)
    half = cam.resized(100)
    assert (half.focal, half.width, half.height) == (50.0, 100, 75)
    assert half.camera_angle_x == pytest.approx(cam.camera_angle_x)
    np.testing.assert_array_equal(half.c2w, cam.c2w)
    other = cam.resized(64, 32)
    assert (other.focal, other.width, other.height) == (32.0, 64, 32)
    assert Camera(cam.c2w, 50.0, 96, 48).resized(1).height == 1  # --res 1 of a wide view: one pixel, not 0


def test_focal_from_angle_round_trips_camera_angle_x():
    f = focal_from_angle(0.6911112070083618, 800)
    assert f == pytest.approx(1111.1110311937682)
    assert Camera(np.eye(4), f, 800, 800).camera_angle_x == pytest.approx(0.6911112070083618)


@pytest.mark.parametrize(
    "camera, message",
    [
        (Camera(np.full((4, 4), np.nan), 50.0, 8, 8), "c2w has non-finite values"),
        (Camera(np.diag([2.0, 2.0, 2.0, 1.0]), 50.0, 8, 8), "scaled or sheared"),
        (Camera(np.eye(3), 50.0, 8, 8), "not a 4x4 matrix"),
        (Camera(np.eye(4), float("nan"), 8, 8), "focal nan must be a positive number"),
        (Camera(np.eye(4), -3.0, 8, 8), "focal -3.0 must be a positive number"),
        (Camera(np.eye(4), 50.0, 0, 8), "width 0 must be a whole number of pixels"),
        (Camera(np.eye(4), 50.0, 8, 2.5), "height 2.5 must be a whole number of pixels"),
    ],
)
def test_a_camera_a_script_builds_is_checked_before_its_rays(camera, message):
    """A NaN pose used to render all white, a zero width to fail inside torch.cat."""
    with pytest.raises(CrfError) as e:
        rays_from_camera(camera)
    assert str(e.value).startswith("camera: ") and message in str(e.value) and "\n" not in str(e.value)


def test_resizing_a_camera_of_no_pixels_is_one_line():
    with pytest.raises(CrfError, match="this camera's width 0 must be a whole number"):
        Camera(np.eye(4), 50.0, 0, 8).resized(32)
    with pytest.raises(CrfError, match="height -2 must be a whole number"):
        Camera(np.eye(4), 50.0, 8, 8).resized(32, -2)
    assert Camera(np.eye(4), 50.0, 8, 4).resized(16).focal == 100.0


def test_a_numpy_integer_focal_is_a_number_of_pixels():
    """`Camera(focal=np.int64(100))` was refused as not "a positive number of pixels" while
    np.float16 passed; numpy integers are numbers too, and a bool or 0 is still refused."""
    from crfedit.cameras import camera_problem

    c2w = look_at(np.array([0.0, -3.0, 1.0]), np.zeros(3))
    assert camera_problem(Camera(c2w, np.int64(100), 8, 8)) is None
    assert "focal" in camera_problem(Camera(c2w, np.int64(0), 8, 8)) and "focal" in camera_problem(Camera(c2w, True, 8, 8))
