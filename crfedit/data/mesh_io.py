"""Part-labelled meshes: loading (trimesh, optional), normalizing to the unit cube Z-up, part colors.

Used by :mod:`.meshes` to render categories from mesh files; see that module for the format notes.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CrfError, DataError
from ..io import read_json
from .synth import PALETTE, _jitter, hex_to_rgb, rgb_to_hex

INSTALL_HINT = "pip install 'crfedit[meshes]'"
MAX_COLOR_PARTS = 32  # a colored mesh with more distinct face colors is painted, not parted
FALLBACK_GRAY = (0.7, 0.7, 0.7)


@dataclass(frozen=True, eq=False)
class Part:
    id: int  # 1..P, the value in the part map
    name: str
    material_color: tuple[float, float, float] | None  # rgb in [0, 1] from the file, if any


@dataclass(frozen=True, eq=False)
class PartMesh:
    """A triangle soup whose faces are labeled with part ids."""

    vertices: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64
    face_part: np.ndarray  # [F] uint8, 1..P
    parts: list[Part] = field(default_factory=list)

    def without_part(self, part_id: int) -> "PartMesh":
        """The same mesh with part ``part_id``'s faces removed (vertices and ids kept)."""
        keep = self.face_part != part_id
        return PartMesh(self.vertices, self.faces[keep], self.face_part[keep], self.parts)


# ----------------------------------------------------------------------------- loading


def _trimesh():
    try:
        import trimesh
    except ImportError:
        raise DataError(f"trimesh is not installed: {INSTALL_HINT}") from None
    return trimesh


def read_meta(path: Path) -> dict:
    """The sidecar ``<stem>.meta.json`` of mesh ``path``, or ``{}`` when there is none."""
    sidecar = Path(path).with_suffix(".meta.json")
    if not sidecar.is_file():
        return {}
    try:
        meta = read_json(sidecar)
    except CrfError as e:
        raise DataError(str(e)) from None
    if not isinstance(meta, dict):
        raise DataError(f"{sidecar}: expected a JSON object")
    unknown = sorted(set(meta) - set(SIDECAR_KEYS))
    if unknown:  # a misspelt "licence" or "author" lost a CC-BY credit without a word
        raise DataError(f"{sidecar}: unknown key{'s' * (len(unknown) != 1)} {', '.join(map(repr, unknown))}; a sidecar holds "
                        f"{', '.join(SIDECAR_KEYS)}")
    return meta


SIDECAR_KEYS = ("name", "title", "creator", "license", "license_url", "source", "rotation")
"""The keys a mesh's sidecar ``<stem>.meta.json`` may hold: attribution (ATTRIBUTION.txt) and a rotation."""


def _material_color(visual, material, trimesh) -> tuple[float, float, float] | None:
    """The diffuse color of a trimesh visual: texture mean, else Kd / base color factor."""
    if material is None:
        if isinstance(visual, trimesh.visual.ColorVisuals) and visual.defined:
            rgb = np.asarray(visual.face_colors, dtype=np.float64)[:, :3] / 255.0
            return tuple(float(c) for c in rgb.mean(axis=0))
        return None
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    factor = None
    if hasattr(material, "baseColorFactor") and material.baseColorFactor is not None:
        factor = np.asarray(material.baseColorFactor, dtype=np.float64)[:3]
        factor = factor / 255.0 if factor.max() > 1.0 else factor
    if image is not None:
        arr = np.asarray(image.convert("RGBA"), dtype=np.float64) / 255.0
        weight = arr[..., 3:4]
        mean = (arr[..., :3] * weight).sum(axis=(0, 1)) / max(float(weight.sum()), 1e-9)
        if factor is not None:
            mean = mean * factor
        return tuple(float(c) for c in mean)
    if factor is not None:
        return tuple(float(c) for c in factor)
    diffuse = getattr(material, "diffuse", None)
    if diffuse is not None:
        rgb = np.asarray(diffuse, dtype=np.float64).reshape(-1)[:3]
        return tuple(float(c) for c in (rgb / 255.0 if rgb.max() > 1.0 else rgb))
    return None


def _part_name(raw: str | None, fallback: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(raw or "")).strip("_.")
    return name or fallback


def load_part_mesh(path: str | Path) -> PartMesh:
    """Read a mesh file and label its faces by material group (in the file's coordinates).

    Broken, unreadable or empty files raise a one-line :class:`DataError` naming the file.
    """
    path = Path(path)
    trimesh = _trimesh()
    if not path.is_file():
        raise DataError(f"{path}: is a folder, not a mesh file" if path.is_dir() else f"{path}: mesh file not found")
    if path.suffix.lower().lstrip(".") not in trimesh.available_formats():
        raise DataError(f"{path}: not a mesh format trimesh reads (use .obj, .ply, .glb, .gltf, .off or .stl)")
    try:
        scene = trimesh.load(path, force="scene")
    except ImportError:  # trimesh reaches for an optional text-encoding detector on bytes that are no text
        raise DataError(f"{path}: cannot read mesh (not {path.suffix.lstrip('.').upper()} text in a known encoding)") from None
    except Exception as e:  # trimesh's loaders raise anything from ValueError to IndexError
        raise DataError(f"{path}: cannot read mesh ({e.__class__.__name__}: {str(e)[:120]})") from None

    groups: dict[str, list] = {}  # part key → [(vertices, faces, color)]
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        vertices = trimesh.transform_points(np.asarray(geom.vertices, dtype=np.float64), transform)
        faces = np.asarray(geom.faces, dtype=np.int64)
        visual = geom.visual
        material = getattr(visual, "material", None)
        if material is None and isinstance(visual, trimesh.visual.ColorVisuals) and visual.defined:
            face_colors = np.asarray(visual.face_colors)[:, :3]
            unique, inverse = np.unique(face_colors, axis=0, return_inverse=True)
            if 1 < len(unique) <= MAX_COLOR_PARTS:
                for k, color in enumerate(unique):
                    key = "color_{:02x}{:02x}{:02x}".format(*color)
                    rgb = tuple(float(c) / 255.0 for c in color)
                    groups.setdefault(key, []).append((vertices, faces[inverse.reshape(-1) == k], rgb))
                continue
        name = getattr(material, "name", None) or geom_name
        groups.setdefault(str(name), []).append((vertices, faces, _material_color(visual, material, trimesh)))

    if not groups:  # (trimesh drops the faces of NaN vertices as it reads: such a file ends here too)
        raise DataError(f"{path}: mesh has no triangles (or only ones with NaN or infinite corners)")
    if len(groups) > 255:
        raise DataError(f"{path}: {len(groups)} material groups; at most 255 parts fit a part map")

    all_v, all_f, all_p, parts, offset = [], [], [], [], 0
    used_names: set[str] = set()
    for part_id, (key, pieces) in enumerate(sorted(groups.items()), start=1):  # trimesh's order varies
        colors = [c for _, _, c in pieces if c is not None]
        name = _part_name(key, f"part{part_id}")
        while name in used_names:
            name += "_"
        used_names.add(name)
        color = tuple(float(x) for x in np.mean(colors, axis=0)) if colors else None
        parts.append(Part(part_id, name, color))
        for vertices, faces, _ in pieces:
            all_v.append(vertices)
            all_f.append(faces + offset)
            all_p.append(np.full(len(faces), part_id, dtype=np.uint8))
            offset += len(vertices)
    vertices = np.concatenate(all_v)
    if not np.isfinite(vertices).all():
        raise DataError(f"{path}: mesh has NaN or infinite vertex coordinates")
    faces = np.concatenate(all_f)
    corners = vertices[faces]
    if not bool((np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=-1) > 0).any()):
        raise DataError(f"{path}: mesh has no area: every triangle is degenerate (its corners in a line), so no view would show it")
    return PartMesh(vertices, faces, np.concatenate(all_p), parts)


# ----------------------------------------------------------------------------- normalizing


Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""``(x, y, z) → (x, -z, y)``: a +90° turn about X; a Y-up file's front (+Z) ends up facing -Y."""


def normalize_mesh(mesh: PartMesh, up: str = "z", rotation: np.ndarray | None = None) -> PartMesh:
    """Turn ``mesh`` Z-up, center its bounding box on the origin and scale its largest side to 1.

    ``v' = s · (U R v − c)`` with ``R`` the optional file rotation, ``U`` the identity for
    ``up="z"`` or :data:`Y_UP_TO_Z_UP` for ``up="y"``.  Only faces in use count for the box.
    Example: a Y-up box spanning x∈[0,4], y∈[0,2], z∈[0,1] becomes x∈[-0.5,0.5],
    y∈[-0.125,0.125], z∈[-0.25,0.25].
    """
    if up not in ("y", "z"):
        raise DataError(f"--up {up}: expected y or z")
    m = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    if up == "y":
        m = Y_UP_TO_Z_UP @ m
    v = mesh.vertices @ m.T
    used = v[np.unique(mesh.faces)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    extent = float((hi - lo).max())
    if not extent > 0:
        raise DataError("mesh is degenerate: all its vertices coincide")
    v = (v - 0.5 * (lo + hi)) / extent
    return PartMesh(v, mesh.faces, mesh.face_part, mesh.parts)


def load_normalized(path: str | Path, up: str = "z") -> tuple[PartMesh, dict]:
    """:func:`load_part_mesh` + sidecar rotation + :func:`normalize_mesh`; also returns the sidecar."""
    path = Path(path)
    meta = read_meta(path)
    rotation = meta.get("rotation")
    if rotation is not None:
        numbers = isinstance(rotation, list) and all(
            isinstance(row, list) and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in row) for row in rotation)
        try:
            rotation = np.array(rotation, dtype=np.float64) if numbers else None  # "1" is text, not a number
        except (TypeError, ValueError, OverflowError):
            rotation = None
        if rotation is None or rotation.shape != (3, 3) or not np.isfinite(rotation).all():
            raise DataError(f"{path.with_suffix('.meta.json')}: rotation must be a 3x3 matrix of numbers")
        if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
            raise DataError(f"{path.with_suffix('.meta.json')}: rotation must be a rotation (orthonormal rows, determinant +1), "
                            "not a scale, shear or mirror, which would reshape the object")
    with warnings.catch_warnings():  # trimesh's own arithmetic on coordinates near 1e300 warns; the result is checked
        warnings.simplefilter("ignore", RuntimeWarning)
        mesh = load_part_mesh(path)
    try:
        return normalize_mesh(mesh, up, rotation), meta
    except DataError as e:
        raise DataError(f"{path}: {e}") from None


# ----------------------------------------------------------------------------- colors


def part_colors(mesh: PartMesh, palette: str, rng: np.random.Generator) -> list[str]:
    """``#rrggbb`` per part, in part order.

    ``random``: synth's palette in a random order, each color jittered (repeats only past 16
    parts); ``mtl``: the material colors, :data:`FALLBACK_GRAY` where a part has none.
    """
    if palette == "random":
        order = [_jitter(rng, PALETTE[i]) for i in rng.permutation(len(PALETTE))]
        return [order[k % len(order)] for k in range(len(mesh.parts))]
    if palette == "mtl":
        return [rgb_to_hex(p.material_color if p.material_color is not None else FALLBACK_GRAY) for p in mesh.parts]
    raise DataError(f"--palette {palette}: expected random or mtl")


def albedo_table(mesh: PartMesh, colors: list[str]) -> np.ndarray:
    """rgb in [0, 1] per part id, row 0 (background) unused.  [P + 1, 3]"""
    table = np.ones((len(mesh.parts) + 1, 3))
    for part, color in zip(mesh.parts, colors):
        table[part.id] = hex_to_rgb(color)
    return table
