"""Mesh export: the density level set of one instance as a vertex-coloured triangle mesh.

1. σ is evaluated on a ``res``³ lattice over the scene box, but only at lattice points whose
   occupancy cell (dilated by one) is occupied; elsewhere σ = 0, so marching cubes (PyMCubes,
   or scikit-image) only finds surfaces the renderer can see.  σ is 0 on the box's faces too,
   so the surface is closed and inside the box.
2. The default level is the σ at which one render step is half opaque:
   1 − exp(−σ·step) = ½  →  σ = ln 2 / step.
3. Each vertex is coloured by what a ray looking at it along minus its outward normal
   (n = −∇σ / |∇σ|) renders: the radiance composited where that ray meets the surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from . import occupancy
from .cameras import Rays
from .errors import CrfError
from .model import CategoryModel
from .renderer import render_rays

MESH_SUFFIXES = (".ply", ".obj", ".glb", ".off", ".stl")


@dataclass
class Mesh:
    vertices: np.ndarray  # [V, 3] float32, world units
    faces: np.ndarray  # [F, 3] int64
    colors: np.ndarray  # [V, 3] float32 in [0, 1]
    level: float  # the σ of the level set


def default_level(field) -> float:
    """σ where one render step is half opaque: ln 2 / step."""
    return math.log(2.0) / occupancy.step_size(field.aabb, field.cfg.occ_res, field.cfg.steps_per_cell)


def _marching_cubes(volume: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices in lattice coordinates [V, 3], faces [F, 3] wound outward) with PyMCubes, else
    scikit-image."""
    try:
        import mcubes

        verts, faces = mcubes.marching_cubes(volume, level)
    except ImportError:
        try:
            from skimage.measure import marching_cubes
        except ImportError:
            raise CrfError("mesh export needs PyMCubes or scikit-image: pip install -e '.[export]'") from None
        verts, faces, _, _ = marching_cubes(volume, level, gradient_direction="ascent")
    return verts, outward(verts, faces.astype(np.int64))


def outward(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` wound so that the closed surface encloses a positive volume (normals out, as
    viewers with back-face culling need): the libraries' windings differ between versions
    (PyMCubes 0.1.6 winds outward, where an earlier release was read as inward)."""
    v0, v1, v2 = (verts[faces[:, i]] for i in range(3))
    signed = float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum())
    return faces if signed >= 0 else np.ascontiguousarray(faces[:, ::-1])


def density_lattice(field, instance: int, res: int, chunk: int = 65536, on_planes: Callable[[int], None] | None = None) -> np.ndarray:
    """σ [res, res, res] at the lattice points (corners included) of the scene box, 0 outside
    the instance's occupied cells.  Built a slab of x-planes at a time, so that only the
    volume itself is res³ (the points of the whole lattice were 12 bytes each: 12.9 GB at
    ``--res 1024``, refused by the allocator before any density was read).  ``on_planes(n)``
    after each slab: n planes of ``res`` done (a progress bar)."""
    device = field.aabb.device
    axis = torch.linspace(-1.0, 1.0, res, device=device)
    grid = occupancy.dilate(field.occupancy[instance], 1)[None]
    zero = torch.zeros((), dtype=torch.long, device=device)
    volume = np.zeros((res, res, res), np.float32)
    planes = max(1, (4 * chunk) // (res * res))
    with torch.no_grad():
        for x0 in range(0, res, planes):
            xn = torch.stack(torch.meshgrid(axis[x0 : x0 + planes], axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
            keep = occupancy.lookup_in_box(grid, zero, xn).nonzero().squeeze(-1)
            sigma = torch.zeros(xn.shape[0], device=device)
            for i in range(0, keep.numel(), chunk):
                idx = keep[i : i + chunk]
                sigma[idx] = field.density(xn[idx], instance)
            volume[x0 : x0 + planes] = sigma.view(-1, res, res).cpu().numpy()
            if on_planes is not None:
                on_planes(min(planes, res - x0))
    return volume


def vertex_normals(field, instance: int, xn: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
    """Outward unit normals [V, 3] (world frame) at normalized points: −∇σ / |∇σ|."""
    scale = 2.0 / (field.aabb[3:] - field.aabb[:3])  # d(xn)/dx: gradients in world units
    out = []
    for i in range(0, xn.shape[0], chunk):
        x = xn[i : i + chunk].clone().requires_grad_(True)
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(field.density(x, instance).sum(), x)
        out.append(torch.nn.functional.normalize(-grad * scale, dim=-1, eps=1e-12))
    return torch.cat(out) if out else torch.zeros(0, 3)


def vertex_colors(field, instance: int, points: torch.Tensor, normals: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
    """RGB [V, 3] that a ray looking at each world point along minus its normal sees: rendered
    from two occupancy cells outside the surface, un-blended from the background."""
    offset = 2.0 * float((field.aabb[3:] - field.aabb[:3]).max()) / field.cfg.occ_res
    out = []
    with torch.no_grad():
        for i in range(0, points.shape[0], chunk):
            p, n = points[i : i + chunk], normals[i : i + chunk]
            r = render_rays(field, Rays(p + offset * n, -n), instance, background=0.0)
            out.append((r.rgb / r.opacity.clamp_min(1e-6)[:, None]).clamp(0.0, 1.0))
    return torch.cat(out) if out else torch.zeros(0, 3)


def face_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """[F] the connected component of each face (faces sharing a vertex are connected), labelled
    by the smallest vertex index in it: label propagation with pointer jumping."""
    label = np.arange(n_vertices)
    while True:
        low = label[faces].min(axis=1)  # [F] the smallest label a face's vertices carry
        new = label.copy()
        for corner in range(3):
            np.minimum.at(new, faces[:, corner], low)
        new = new[new]  # pointer jumping: follow labels to their labels' labels
        if np.array_equal(new, label):
            return label[faces[:, 0]]
        label = new


def drop_small_pieces(mesh: Mesh, share: float) -> tuple[Mesh, int]:
    """(``mesh`` without the pieces of fewer faces than ``share`` × the largest piece's, the
    number of pieces dropped); vertices no face uses go too."""
    if share <= 0 or len(mesh.faces) == 0:
        return mesh, 0
    piece = face_components(mesh.faces, len(mesh.vertices))
    names, sizes = np.unique(piece, return_counts=True)
    small = names[sizes < share * sizes.max()]
    if small.size == 0:
        return mesh, 0
    faces = mesh.faces[~np.isin(piece, small)]
    used = np.unique(faces)
    index = np.full(len(mesh.vertices), -1, dtype=np.int64)
    index[used] = np.arange(used.size)
    return Mesh(mesh.vertices[used], index[faces], mesh.colors[used], mesh.level), int(small.size)


def extract_mesh(model: CategoryModel, instance: int, res: int = 256, level: float | None = None,
                 on_planes: Callable[[int], None] | None = None) -> Mesh:
    """The ``level`` set of σ of ``instance`` (edits included) on a ``res``³ lattice, coloured;
    ``on_planes`` as :func:`density_lattice` takes it."""
    if not 8 <= res <= 1024:
        raise CrfError(f"--res {res}: must be between 8 and 1024")
    field = model.field_for(instance)
    level = default_level(field) if level is None else float(level)
    if not (level > 0 and math.isfinite(level)):
        raise CrfError(f"--level {level:g}: must be a positive density")
    volume = density_lattice(field, instance, res, on_planes=on_planes)
    for axis in range(3):  # σ = 0 on the box's faces: the surface closes inside the box
        np.moveaxis(volume, axis, 0)[[0, -1]] = 0.0
    if not (volume > level).any():
        raise CrfError(f"the density of {model.names[instance]} never reaches the level {level:.4g} (try a lower --level)")
    verts, faces = _marching_cubes(volume, level)
    xn = torch.as_tensor(verts / (res - 1) * 2.0 - 1.0, dtype=torch.float32, device=field.aabb.device)
    world = field.aabb[:3] + (xn + 1.0) * 0.5 * (field.aabb[3:] - field.aabb[:3])
    colors = vertex_colors(field, instance, world, vertex_normals(field, instance, xn))
    return Mesh(world.cpu().numpy().astype(np.float32), faces, colors.cpu().numpy().astype(np.float32), level)


def write_mesh(mesh: Mesh, path: str | Path) -> None:
    """Write ``mesh`` with trimesh (format from the suffix), atomically.  crfedit's world is
    Z-up; glTF (``.glb``) is Y-up by its specification, so there the vertices are turned
    (x, y, z) → (x, z, −y) and the chair stands in a glTF viewer; the other formats keep Z-up."""
    from .io import atomic_path

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise CrfError(f"--out {path}: expected a mesh file name ending in {', '.join(MESH_SUFFIXES)}")
    try:
        import trimesh
    except ImportError:
        raise CrfError("mesh export needs trimesh: pip install -e '.[export]'") from None
    rgba = np.concatenate([np.clip(np.round(mesh.colors * 255), 0, 255), np.full((len(mesh.colors), 1), 255)], axis=1)
    vertices = np.asarray(mesh.vertices)
    if path.suffix.lower() == ".glb":
        vertices = np.stack([vertices[:, 0], vertices[:, 2], -vertices[:, 1]], axis=1)  # a proper rotation: faces keep their winding
    tm = trimesh.Trimesh(vertices, mesh.faces, vertex_colors=rgba.astype(np.uint8), process=False)
    with atomic_path(path) as tmp:
        tm.export(tmp, file_type=path.suffix.lower().lstrip("."))
