"""Exact analytic ray casting of primitive unions (oriented boxes and cylinders), for the procedural chairs.

Rays are intersected exactly (slab test for boxes, quadratic + caps for cylinders), the nearest
hit wins, and the hit is shaded view-independently, ``albedo * (0.35 + 0.65 max(0, n·L))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..cameras import Camera, ray_directions_camera

LIGHT = np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85])
AMBIENT, DIFFUSE = 0.35, 0.65


# ----------------------------------------------------------------------------- primitives


@dataclass(frozen=True, eq=False)
class Primitive:
    """A box or cylinder in world space; local axes are the columns of ``rotation``."""

    kind: str  # "box" | "cylinder"
    center: np.ndarray  # [3]
    rotation: np.ndarray  # [3, 3] local → world
    size: np.ndarray  # [3] box: half extents; cylinder: (radius, radius, half length along local z)
    part: int


def rotation_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def box(center, half, part: int, yaw: float = 0.0) -> Primitive:
    """A box with half extents ``half``, rotated by ``yaw`` radians about Z."""
    return Primitive("box", np.asarray(center, float), rotation_z(yaw), np.asarray(half, float), part)


def cylinder(center, radius: float, half_length: float, part: int, horizontal_yaw: float | None = None) -> Primitive:
    """A vertical cylinder, or a horizontal one whose axis points at ``horizontal_yaw`` in the XY plane."""
    rot = np.eye(3)
    if horizontal_yaw is not None:  # local z → (cos yaw, sin yaw, 0)
        rot = rotation_z(horizontal_yaw) @ np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    return Primitive("cylinder", np.asarray(center, float), rot, np.array([radius, radius, half_length]), part)


def primitive_bounds(p: Primitive) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned bounding box (min, max) of a primitive."""
    if p.kind == "box":
        ext = np.abs(p.rotation) @ p.size
    else:
        axis = p.rotation[:, 2]
        ext = np.abs(axis) * p.size[2] + p.size[0] * np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0))
    return p.center - ext, p.center + ext


# ----------------------------------------------------------------------------- ray casting


@dataclass(frozen=True, eq=False)
class Hits:
    t: np.ndarray  # [N] float64 distance along the unit ray, inf = miss
    part: np.ndarray  # [N] int64, 0 = miss
    normal: np.ndarray  # [N, 3] world unit normal, 0 on a miss


def _local(o: np.ndarray, d: np.ndarray, prims: list[Primitive]) -> tuple[np.ndarray, np.ndarray]:
    """Rays in each primitive's frame, ``R^T (o - c)`` and ``R^T d``, component-major.  [3, P, N] each."""
    P, N = len(prims), len(o)
    centers = np.stack([p.center for p in prims])  # [P, 3]
    rots = np.stack([p.rotation for p in prims])  # [P, 3, 3]
    stacked = rots.transpose(2, 0, 1).reshape(3 * P, 3)  # row k*P + p is column k of R_p: one GEMM
    shift = np.einsum("pj,pjk->kp", centers, rots)[..., None]  # [3, P, 1]
    return (stacked @ o.T).reshape(3, P, N) - shift, (stacked @ d.T).reshape(3, P, N)


def box_distances(o: np.ndarray, d: np.ndarray, prims: list[Primitive]) -> np.ndarray:
    """Entry distance of each ray into each box (slab test), inf on a miss.  [P, N]

    ``t = max_k min(t1_k, t2_k)`` over the three slabs ``|x_k| <= h_k``; a hit needs
    ``t <= min_k max(t1_k, t2_k)`` and ``t > 0`` (cameras are outside every primitive).
    A ray parallel to a slab gets ±inf there (a NaN, for a ray exactly on a face plane, misses).
    """
    o_l, d_l = _local(o, d, prims)
    half = np.stack([p.size for p in prims]).T[..., None]  # [3, P, 1]
    t_near = t_far = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            inv = 1.0 / d_l[k]
            t1, t2 = (-half[k] - o_l[k]) * inv, (half[k] - o_l[k]) * inv
            lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
            t_near = lo if t_near is None else np.maximum(t_near, lo)
            t_far = hi if t_far is None else np.minimum(t_far, hi)
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def cylinder_distances(o: np.ndarray, d: np.ndarray, prims: list[Primitive]) -> np.ndarray:
    """Entry distance of each ray into each capped cylinder, inf on a miss.  [P, N]

    Side: nearer root of ``(ox + t dx)² + (oy + t dy)² = r²`` with ``|oz + t dz| <= h``;
    caps: ``t = (±h - oz) / dz`` with ``x² + y² <= r²``.  The smallest positive one is the entry.
    """
    (ox, oy, oz), (dx, dy, dz) = _local(o, d, prims)
    r = np.array([p.size[0] for p in prims])[:, None]
    h = np.array([p.size[2] for p in prims])[:, None]
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r * r
    disc = b * b - 4.0 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        side = (disc >= 0) & (a > 1e-18) & (t_side > 0) & (np.abs(oz + t_side * dz) <= h)
        best = np.where(side, t_side, np.inf)
        for cap in (h, -h):
            t_cap = (cap - oz) / dz
            x, y = ox + t_cap * dx, oy + t_cap * dy
            hit = (t_cap > 0) & (x * x + y * y <= r * r)
            best = np.minimum(best, np.where(hit, t_cap, np.inf))
    return best


def aabb_hit(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which rays ([N, 3] each) hit the world box [lo, hi] in front of their origin.  [N] bool"""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    t_near, t_far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    return ~(t_near > t_far) & ~(t_far < 0)


def _normal_local(p: Primitive, x: np.ndarray) -> np.ndarray:
    """Outward unit normal at local surface points ``x``.  [M, 3]"""
    n = np.zeros_like(x)
    rows = np.arange(len(x))
    if p.kind == "box":
        axis = np.argmax(np.abs(x) / p.size, axis=-1)
        n[rows, axis] = np.sign(x[rows, axis])
        return n
    rho = np.hypot(x[:, 0], x[:, 1])
    on_cap = (np.abs(x[:, 2]) - p.size[2]) > (rho - p.size[0])
    n[:, 2] = np.where(on_cap, np.sign(x[:, 2]), 0.0)
    safe = np.where(rho > 0, rho, 1.0)
    n[:, 0] = np.where(on_cap, 0.0, x[:, 0] / safe)
    n[:, 1] = np.where(on_cap, 0.0, x[:, 1] / safe)
    return n


def cast_rays(prims: list[Primitive], origins: np.ndarray, directions: np.ndarray) -> Hits:
    """Nearest hit of each ray (``origins``, unit ``directions``: [N, 3] float64) among ``prims``."""
    origins = np.asarray(origins, np.float64)
    directions = np.asarray(directions, np.float64)
    n = len(origins)
    t, part, normal = np.full(n, np.inf), np.zeros(n, np.int64), np.zeros((n, 3))
    boxes = [p for p in prims if p.kind == "box"]
    cyls = [p for p in prims if p.kind == "cylinder"]
    ordered = boxes + cyls
    if not ordered:
        return Hits(t, part, normal)
    bounds = [primitive_bounds(p) for p in ordered]
    near = np.nonzero(aabb_hit(origins, directions, np.min([b[0] for b in bounds], 0), np.max([b[1] for b in bounds], 0)))[0]
    o, d = origins[near], directions[near]
    dist = np.concatenate(
        ([box_distances(o, d, boxes)] if boxes else []) + ([cylinder_distances(o, d, cyls)] if cyls else [])
    )  # [P, M]
    winner = np.argmin(dist, axis=0)
    t_near = dist[winner, np.arange(len(near))]
    hit = np.isfinite(t_near)
    t[near] = t_near
    points = o + d * np.where(hit, t_near, 0.0)[:, None]
    for k, p in enumerate(ordered):
        sel = hit & (winner == k)
        if sel.any():
            part[near[sel]] = p.part
            normal[near[sel]] = _normal_local(p, (points[sel] - p.center) @ p.rotation) @ p.rotation.T
    return Hits(t, part, normal)


def camera_rays(camera: Camera, offset: tuple[float, float] = (0.5, 0.5)) -> tuple[np.ndarray, np.ndarray]:
    """float64 origins and unit directions of every pixel center (or ``offset`` inside each
    pixel), row-major (as rays_from_camera)."""
    d = ray_directions_camera(camera.width, camera.height, camera.focal, offset).numpy() @ camera.c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(camera.c2w[:3, 3], d.shape), d


def shade(normal: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """View-independent Lambert: ``albedo * (0.35 + 0.65 max(0, n·L))``.  [N, 3]"""
    return albedo * (AMBIENT + DIFFUSE * np.maximum(0.0, normal @ LIGHT))[:, None]
