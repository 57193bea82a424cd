"""Pinhole cameras and their rays (OpenGL / NeRF-synthetic convention).

A camera is a 4×4 camera-to-world matrix ``c2w`` whose columns are the camera's x (right),
y (up) and z (backwards) axes and its center; the camera looks down its **-Z** axis with +Y up.
The world is Z-up, as in Blender's NeRF-synthetic scenes.  Rays go through pixel **centers**:
pixel (i, j) — column i, row j, row 0 at the top — has direction
``((i + 0.5 - cx) / f, -(j + 0.5 - cy) / f, -1)`` in camera space.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch

from .errors import CrfError
from .names import real_number


@dataclass(frozen=True)
class Camera:
    """A pinhole camera; ``c2w`` is a float64 [4, 4] array, ``focal`` in pixels."""

    c2w: np.ndarray  # [4, 4]
    focal: float
    width: int
    height: int

    def __post_init__(self):
        if not isinstance(self.c2w, np.ndarray):  # a nested list from a script: an array, as every reader makes
            _, problem = c2w_problem(self.c2w)
            if problem is None:
                object.__setattr__(self, "c2w", np.array(self.c2w, dtype=np.float64).reshape(4, 4))

    @property
    def camera_angle_x(self) -> float:
        """Horizontal field of view in radians (the NeRF-synthetic ``camera_angle_x``)."""
        return angle_from_focal(self.focal, self.width)

    @property
    def center(self) -> np.ndarray:
        return self.c2w[:3, 3]

    def resized(self, width: int, height: int | None = None) -> "Camera":
        """The same camera at another resolution (focal scaled with the width)."""
        for name, side in (("width", width), ("height", height), ("this camera's width", self.width)):
            if side is not None and (isinstance(side, bool) or not isinstance(side, (int, np.integer)) or side < 1):
                raise CrfError(f"camera: {name} {side!r} must be a whole number of pixels, at least 1")
        height = height if height is not None else max(1, round(self.height * width / self.width))
        return replace(self, focal=self.focal * width / self.width, width=width, height=height)


MIN_FIELD_OF_VIEW = 1e-5
"""Radians: a camera whose horizontal field of view is narrower sees too little to render or
train on (a dataset split with 10⁻³⁰ passed, and training blamed the camera axes for the empty
visual hull it carved); loading and rendering refuse it.  A camera framing the object from the
farthest a render allows (``renderer.MAX_CAMERA_REACH``, 10⁴ box diagonals) needs about 10⁻⁴."""


def angle_from_focal(focal: float, width: float) -> float:
    """The horizontal field of view ``2 atan(W / 2f)`` in radians: the inverse of
    :func:`focal_from_angle`."""
    return 2.0 * math.atan(0.5 * width / focal)


def narrow_view(angle: float) -> str | None:
    """None when a horizontal field of view of ``angle`` radians can see an object, else the
    phrase that says it cannot (each loader and the renderer prefix what they read)."""
    if angle >= MIN_FIELD_OF_VIEW:
        return None
    return (f"a {math.degrees(angle):.3g}° field of view, too narrow to see an object "
            f"(at least {math.degrees(MIN_FIELD_OF_VIEW):.2g}°)")


RIGID_TOLERANCE = 1e-3
"""Largest |RᵀR − I| entry a camera-to-world rotation may have: float32 storage and rounded
exports stay far below it, a scaled or sheared matrix does not."""


def _numbers(value):
    """Whether each leaf of nested lists is a number (bool is not), one flag per leaf."""
    for v in value:
        if isinstance(v, (list, tuple)):
            yield from _numbers(v)
        else:
            yield real_number(v) is not None


def c2w_problem(value) -> tuple[np.ndarray | None, str | None]:
    """``value`` (a 4×4 nested list, or 16 numbers row-major) as a float64 camera-to-world
    matrix, and what is wrong with it as a camera (``None`` if nothing): the rotation must be
    orthonormal and right-handed and the last row 0 0 0 1, or the rays come out skewed,
    stretched or mirrored without any error (a pinhole camera is a rigid motion)."""
    if isinstance(value, (list, tuple)) and not all(_numbers(value)):  # JSON: "0.5" is a string, not a number
        return None, "is not a 4x4 matrix (or 16 numbers, row-major): it holds something other than numbers"
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return None, "is not a 4x4 matrix (or 16 numbers, row-major)"
    if m.shape == (16,):
        m = m.reshape(4, 4)
    if m.shape != (4, 4):
        return None, "is not a 4x4 matrix (or 16 numbers, row-major)"
    if not np.isfinite(m).all():
        return None, "has non-finite values"
    r = m[:3, :3]
    if abs(np.linalg.det(r)) < 1e-8:
        return None, "is not invertible"
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > RIGID_TOLERANCE:
        return None, "has a last row other than 0 0 0 1"
    if np.abs(r.T @ r - np.eye(3)).max() > RIGID_TOLERANCE:
        return None, "is not a rigid camera-to-world matrix (its rotation is scaled or sheared)"
    if np.linalg.det(r) < 0:
        return None, "is not a rigid camera-to-world matrix (its rotation mirrors: the determinant is -1)"
    return m, None


def focal_from_angle(camera_angle_x: float, width: int) -> float:
    """``f = 0.5 W / tan(0.5 camera_angle_x)``; an angle so small that f overflows (5e-324) is
    a one-line error."""
    tangent = math.tan(0.5 * camera_angle_x)
    if not tangent > 0 or not math.isfinite(0.5 * width / tangent):
        raise CrfError(f"camera_angle_x {camera_angle_x!r}: no finite focal length (a field of view of 0)")
    return 0.5 * width / tangent


class Rays(NamedTuple):
    """A batch of rays; ``directions`` have unit length, so ``t`` is a distance."""

    origins: torch.Tensor  # [N, 3]
    directions: torch.Tensor  # [N, 3]


def ray_directions_camera(
    width: int, height: int, focal: float, offset: tuple[float, float] = (0.5, 0.5)
) -> torch.Tensor:
    """Unnormalized camera-space directions through pixel centers, row-major.  [H*W, 3]

    Example: a 2×2 image with focal 1 gives (-0.5, 0.5, -1), (0.5, 0.5, -1),
    (-0.5, -0.5, -1), (0.5, -0.5, -1).  ``offset`` (x right, y down, in pixels from the
    pixel's top-left corner) moves the sample inside each pixel, for supersampled datasets.
    """
    j, i = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    x = (i + offset[0] - 0.5 * width) / focal
    y = -(j + offset[1] - 0.5 * height) / focal
    return torch.stack([x, y, -torch.ones_like(x)], dim=-1).reshape(-1, 3)


def subpixel_offsets(n: int) -> list[tuple[float, float]]:
    """An n×n grid of sample positions per pixel (cell centers), center first when n is odd."""
    grid = [((i + 0.5) / n, (j + 0.5) / n) for j in range(n) for i in range(n)]
    return sorted(grid, key=lambda o: (o != (0.5, 0.5),))


def camera_problem(camera: Camera) -> str | None:
    """What makes ``camera`` unusable (``None`` if nothing): a matrix :func:`c2w_problem`
    refuses, a focal length that is not a positive number, a size that is not a whole number
    of pixels from 1 to 16384.  Cameras from files are checked where they are read; this
    catches one a script builds (a NaN pose rendered silently white)."""
    if not isinstance(camera, Camera):
        return f"expected a Camera, not {type(camera).__name__}"
    _, problem = c2w_problem(camera.c2w)
    if problem:
        return f"c2w {problem}"
    focal = camera.focal
    if real_number(focal) is None or not math.isfinite(focal) or focal <= 0:
        return f"focal {focal!r} must be a positive number of pixels"
    for name, side in (("width", camera.width), ("height", camera.height)):
        if isinstance(side, bool) or not isinstance(side, (int, np.integer)) or not 1 <= side <= 16384:
            return f"{name} {side!r} must be a whole number of pixels from 1 to 16384"
    return None


def require_camera(camera, what: str = "camera") -> Camera:
    """``camera``, or a one-line :class:`~crfedit.errors.CrfError` naming what
    :func:`camera_problem` refuses (a view spec string given for a Camera failed deep inside)."""
    problem = camera_problem(camera)
    if problem:
        raise CrfError(f"{what}: {problem}")
    return camera


def rays_from_camera(camera: Camera, device: torch.device | str = "cpu") -> Rays:
    """All rays of ``camera`` in row-major pixel order, float32 on ``device``; a camera
    :func:`camera_problem` refuses is a one-line :class:`~crfedit.errors.CrfError`."""
    require_camera(camera)
    d_cam = ray_directions_camera(camera.width, camera.height, camera.focal)
    c2w = torch.as_tensor(camera.c2w, dtype=torch.float64)
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3].expand_as(d)
    return Rays(o.to(device=device, dtype=torch.float32).contiguous(), d.to(device=device, dtype=torch.float32))


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world matrix of a camera at ``eye`` looking at ``target`` (OpenGL axes)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:  # looking straight along `up`
        right = np.cross(np.array([0.0, 1.0, 0.0]), back)
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, back, eye
    return c2w


def spherical_eye(azimuth_deg: float, elevation_deg: float, radius: float) -> np.ndarray:
    """Point on a Z-up sphere; azimuth from +X towards +Y, elevation above the XY plane."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def eye_angles(eye: np.ndarray) -> tuple[float, float]:
    """``(azimuth, elevation)`` in degrees of a point, the inverse of :func:`spherical_eye`:
    azimuth in [0, 360) from +X towards +Y, elevation above the XY plane (0 at the origin)."""
    x, y, z = (float(v) for v in np.asarray(eye, dtype=np.float64)[:3])
    flat = math.hypot(x, y)
    return math.degrees(math.atan2(y, x)) % 360.0, math.degrees(math.atan2(z, flat)) if flat or z else 0.0


def orbit_cameras(
    n: int, elevation_deg: float, radius: float, focal: float, width: int, height: int, target=(0.0, 0.0, 0.0)
) -> list[Camera]:
    """``n`` cameras evenly spaced in azimuth around the vertical through ``target`` (default
    the origin), all looking at it."""
    centre = np.asarray(target, dtype=np.float64)
    return [
        Camera(look_at(centre + spherical_eye(360.0 * k / n, elevation_deg, radius), centre), focal, width, height)
        for k in range(n)
    ]


def look_at_point(cameras) -> np.ndarray | None:
    """The point nearest every camera's optical axis (least squares); None when the axes are
    (nearly) parallel."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = -np.asarray(cam.c2w, np.float64)[:3, 2]
        d /= np.linalg.norm(d)
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ np.asarray(cam.center, np.float64)
    return np.linalg.solve(a, b) if np.linalg.cond(a) < 1e6 else None


OFF_CENTRE = 0.1
"""Cameras whose axes meet farther than this share of their nearest distance from the origin
look at an object off the origin: the scene box (training) and orbits (rendering) centre there."""


def off_centre_target(cameras) -> np.ndarray | None:
    """Where ``cameras`` look (:func:`look_at_point`) when that lies off the origin by more than
    :data:`OFF_CENTRE` of their nearest distance from it; None when they look at the origin (or
    their axes do not meet).  The one rule the scene box and the orbits follow."""
    target = look_at_point(cameras)
    nearest = min(float(np.linalg.norm(np.asarray(c.center, np.float64))) for c in cameras)
    return target if target is not None and np.linalg.norm(target) > OFF_CENTRE * nearest else None
