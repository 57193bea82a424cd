"""Category datasets from real meshes: load, split into parts, normalize, ray-cast, write.

A mesh file (OBJ + MTL, PLY, GLB/glTF — whatever trimesh reads) becomes one instance:

1. **Parts** are the file's material groups: the faces of each material (OBJ ``usemtl``, glTF
   material, or per-geometry when a scene node has none) form one part, numbered 1..P in order
   of material name; a single PLY/OFF-style mesh with a handful of distinct face colors gets
   one part per color.
2. **Normalization**: an optional sidecar rotation (``<stem>.meta.json``), then ``up="y"`` maps
   Y-up files to the world's Z-up (``(x, y, z) → (x, -z, y)``); the bounding box is centered on
   the origin and scaled so its largest side is 1 — the object fits ``[-0.5, 0.5]^3``.
3. **Colors**: ``palette="random"`` gives every part a distinct, slightly jittered color of
   ``dataset synth``'s woods/fabrics/metals palette; ``palette="mtl"`` takes the material's own
   color — the mean of its diffuse / base-color texture when it has one, else its ``Kd`` / base
   color factor, or the mean face color of a colored mesh; a part with none gets
   :data:`.mesh_io.FALLBACK_GRAY`.
4. **Rendering**: one ray per pixel center, first hit by Embree (``embreex``), the hit distance
   recomputed in float64 against the hit triangle's plane; the shading normal is the face normal
   flipped toward the camera, ``rgb = albedo · (0.35 + 0.65 · max(0, n·L))`` — the same
   view-independent shading as ``dataset synth``.

The sidecar ``<mesh stem>.meta.json`` beside a mesh may hold ``name``, ``title``, ``creator``,
``license``, ``license_url``, ``source`` (written to the dataset's ``ATTRIBUTION.txt``) and
``rotation`` (row-major 3×3, applied to the file's coordinates before ``up``).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..cameras import Camera
from ..errors import CrfError, DataError
from ..io import atomic_folder, atomic_write_text, write_png
from ..masks import erode
from .format import SMALL_COVER, Frame, TwinSpec, carry_extras, median_cover, supersampled_frame, write_instances_txt, write_parts, write_split, write_twins_json
from .mesh_io import INSTALL_HINT, PartMesh, _trimesh, albedo_table, load_normalized, part_colors
from .raycast import camera_rays, shade
from .synth import (
    SynthConfig,
    check_synth_args,
    contrasting_color,
    best_view,
    min_scribble_pixels,
    sample_cameras,
    scribbles,
    stroke_region,
    TWIN_SOURCES,
    twin_sources,
)


# ----------------------------------------------------------------------------- rendering


class RayScene:
    """A :class:`PartMesh` ready for ray casting with Embree (``embreex``)."""

    def __init__(self, mesh: PartMesh):
        trimesh = _trimesh()
        try:
            import embreex  # noqa: F401  (trimesh's wrapper imports it; fail here, with the hint)
            from trimesh.ray.ray_pyembree import RayMeshIntersector
        except ImportError:
            raise DataError(f"embreex is not installed: {INSTALL_HINT}") from None
        if len(mesh.faces) == 0:
            raise DataError("mesh has no faces left to render")
        self.mesh = mesh
        self._intersector = RayMeshIntersector(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False))
        tri = mesh.vertices[mesh.faces]  # [F, 3, 3]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.face_normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)  # [F, 3]
        self.face_points = tri[:, 0]  # [F, 3]
        self.face_centers = tri.mean(axis=1)  # [F, 3]

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face index (−1 = miss) and float64 distance (+inf = miss) of each ray's first hit.

        ``origins, directions: [N, 3]`` float64, unit directions.  Embree finds the face in
        float32; the distance is recomputed as ``t = ((p₀ − o)·n) / (d·n)`` against its plane
        (the face center's projection for a ray grazing the plane).
        """
        face = np.asarray(self._intersector.intersects_first(origins, directions), dtype=np.int64)
        t = np.full(len(face), np.inf)
        hit = face >= 0
        f, o, d = face[hit], origins[hit], directions[hit]
        n = self.face_normals[f]
        dn = (d * n).sum(axis=1)
        grazing = np.abs(dn) <= 1e-12
        plane = ((self.face_points[f] - o) * n).sum(axis=1) / np.where(grazing, 1.0, dn)
        t[hit] = np.where(grazing, ((self.face_centers[f] - o) * d).sum(axis=1), plane)
        return face, t


def facing_normals(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Flip each normal that points away from the viewer: ``n·d > 0 → −n``.  [N, 3]

    Real meshes mix windings and have open, single-sided surfaces; shading the side the camera
    sees makes both sides of a sheet look alike.
    """
    away = (normals * directions).sum(axis=1, keepdims=True) > 0
    return np.where(away, -normals, normals)


def render_view(scene: RayScene, camera: Camera, albedo: np.ndarray, aa: int = 1) -> Frame:
    """Ray-cast one view: rgba (white, alpha 0 on background), ray depth (+inf) and part ids.

    ``albedo: [P + 1, 3]`` rgb per part id (:func:`albedo_table`); shading is synth's
    ``albedo · (0.35 + 0.65 · max(0, n·L))`` with the normal facing the camera.  ``aa`` > 1
    supersamples aa×aa rays per pixel and box-filters them (alpha = coverage); depth and part
    ids come from the pixel-center ray.
    """

    def cast(offset: tuple[float, float]):
        origins, directions = camera_rays(camera, offset)
        face, t = scene.first_hits(np.ascontiguousarray(origins), directions)
        hit = face >= 0
        part = np.zeros(len(face), dtype=np.uint8)
        part[hit] = scene.mesh.face_part[face[hit]]
        rgb = np.ones((len(face), 3))
        rgb[hit] = shade(facing_normals(scene.face_normals[face[hit]], directions[hit]), albedo[part[hit]])
        return t, part, rgb, hit

    return supersampled_frame(camera, aa, cast)


# ----------------------------------------------------------------------------- parts for twins


def separable_parts(mesh: PartMesh, decimals: int = 6) -> list[int]:
    """Ids of the parts that share no vertex position with any other part.

    Removing such a part leaves every other part's surface intact (it may have rested on or
    passed through them, but it was not stitched to them).  Positions are compared rounded to
    ``decimals`` places of the normalized mesh.
    """
    corners = mesh.faces.reshape(-1)  # [3F]
    owner = np.repeat(mesh.face_part, 3)  # part of each corner
    keys = np.round(mesh.vertices[corners], decimals)
    _, position = np.unique(keys, axis=0, return_inverse=True)
    position = position.reshape(-1)
    pairs = np.unique(np.stack([position, owner.astype(np.int64)], axis=1), axis=0)
    shared = np.bincount(pairs[:, 0]) > 1  # positions used by two or more parts
    stitched = set(np.unique(pairs[shared[pairs[:, 0]], 1]).tolist())
    present = set(np.unique(mesh.face_part).tolist())
    return [p.id for p in mesh.parts if p.id in present and p.id not in stitched]


def part_areas(mesh: PartMesh) -> np.ndarray:
    """Surface area per part id.  [P + 1]"""
    tri = mesh.vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(mesh.face_part, weights=area, minlength=len(mesh.parts) + 1)


def scribble_view(frames: list[Frame], part_id: int) -> tuple[int, int]:
    """(index, pixel count) of the frame where the part's interior — its mask eroded by 2 px,
    where synth's :func:`scribbles` puts the strokes — is largest.  Thin parts (tubes, frames,
    slats) score near zero: a stroke cannot stay on them.
    """
    return best_view(frames, part_id, lambda mask: erode(mask, 2))


def stroke_view(frames: list[Frame], part_id: int, need: int) -> tuple[int, int]:
    """(index, pixel count) of the frame where synth's :func:`scribbles` have the most room on
    the part: its :func:`stroke_region`, which falls back to the uneroded part for thin parts
    (legs, tubes) that :func:`scribble_view` scores near zero."""
    return best_view(frames, part_id, lambda mask: stroke_region(mask, need))


def in_frame(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Which world ``points [N, 3]`` project inside the image, in front of the camera.  [N]"""
    local = (points - camera.c2w[:3, 3]) @ camera.c2w[:3, :3]  # camera axes: x right, y up, −z ahead
    ahead = -local[:, 2]
    safe = np.where(ahead > 0, ahead, 1.0)
    u = local[:, 0] / safe * camera.focal + 0.5 * camera.width
    v = -local[:, 1] / safe * camera.focal + 0.5 * camera.height
    return (ahead > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def seen_from(scene: RayScene, cameras: list[Camera], points: np.ndarray, tolerance: float = 2e-3) -> np.ndarray:
    """Which surface ``points [N, 3]`` some camera sees: in its frame, and its ray's first hit is
    no nearer than the point (less ``tolerance``, in the normalized object's units).  [N]"""
    seen = np.zeros(len(points), dtype=bool)
    for cam in cameras:
        todo = ~seen & in_frame(cam, points)
        if not todo.any():
            continue
        origin = cam.c2w[:3, 3]
        ray = points[todo] - origin
        dist = np.linalg.norm(ray, axis=1)
        _, t = scene.first_hits(np.ascontiguousarray(np.broadcast_to(origin, ray.shape)), ray / dist[:, None])
        seen[np.flatnonzero(todo)[t >= dist - tolerance]] = True
    return seen


def hidden_share(mesh: PartMesh, part_id: int, views: list[Camera], seen_by: list[Camera]) -> float:
    """Share of the part's pixels in ``views`` where removing it uncovers a surface no camera of
    ``seen_by`` saw: 0 for a part that hides only background and seen faces (arms, legs), near 1
    for a cushion on a seat.

    A removal twin shows what lay behind the part.  What no training view saw (a seat's top
    under its cushion) no edit can recover from the model, so a twin that uncovers it measures
    inpainting, not removal; :func:`twin_parts` avoids such parts.
    """
    scene, without = RayScene(mesh), RayScene(mesh.without_part(part_id))
    pixels = hidden = 0
    for cam in views:
        origins, directions = camera_rays(cam)
        face, _ = scene.first_hits(np.ascontiguousarray(origins), directions)
        on_part = (face >= 0) & (mesh.face_part[np.maximum(face, 0)] == part_id)
        o, d = np.ascontiguousarray(origins[on_part]), directions[on_part]
        behind, t = without.first_hits(o, d) if len(o) else (np.zeros(0, dtype=np.int64), np.zeros(0))
        uncovered = behind >= 0
        points = o[uncovered] + d[uncovered] * (t[uncovered, None] - 1e-3)  # just in front of the face
        pixels += int(on_part.sum())
        hidden += int((~seen_from(scene, seen_by, points)).sum()) if len(points) else 0
    return hidden / pixels if pixels else 1.0  # a part no view shows: its twin would equal its source


MAX_HIDDEN_SHARE = 0.25
"""The most :func:`hidden_share` a removal twin's part may have.  On the 24 real chairs of
``examples/real-chairs.sh``: legs, frames, feet and an armrest 0.00–0.14 (a post standing on a
seat, its footprint: about 0.17); small glides and caps, a wooden frame, a leather pad
0.24–0.53; cushions and seat pads 0.63–0.94."""


def removable_parts(mesh: PartMesh) -> list[int]:
    """Separable parts other than the one with the largest surface area (the chair's body)."""
    if len(mesh.parts) < 2:
        return []
    body = int(np.argmax(part_areas(mesh)[1:])) + 1
    return [p for p in separable_parts(mesh) if p != body]


# ----------------------------------------------------------------------------- the dataset


@dataclass(frozen=True)
class MeshDatasetConfig:
    views: int = 50
    """Views per mesh, split 80/10/10 into train/val/test (as ``dataset synth``)."""
    res: int = 64
    """Image width and height in pixels."""
    seed: int = 0
    """Same seed and meshes → byte-identical files."""
    palette: str = "random"
    """``random``: synth's palette per part; ``mtl``: the material's own diffuse color."""
    up: str = "z"
    """The file's up axis: ``z``, or ``y`` (most OBJ and every glTF file)."""
    twins: bool = True
    """Also write ground-truth color and removal twins."""
    twin_sources: int = TWIN_SOURCES
    """Meshes per twin kind that get a twin (:func:`pick_twin_sources`)."""
    aa: int = 3
    """Supersamples per pixel side (aa×aa rays, box-filtered); 1 = one ray per pixel center."""


@dataclass(frozen=True)
class MeshDatasetResult:
    names: list[str]
    twins: list[TwinSpec]
    parts: list[int]  # parts per instance
    seconds: float
    kept: list[str] = field(default_factory=list)  # the user's entries of the dataset it replaced, carried over
    notes: list[str] = field(default_factory=list)  # what looks wrong with a mesh or the set (mesh_notes), one line each


Y_TALLER = 1.25
""":func:`mesh_notes` names a mesh read with ``--up z`` whose extent along y is the largest and at
least this × its height (z): a Y-up file read as Z-up lies on its back."""
GLTF = (".glb", ".gltf")
"""glTF files are Y-up by the format's specification."""


def mesh_notes(path: Path, name: str, mesh: PartMesh, up: str, train: list[Frame]) -> list[str]:
    """What looks wrong with one mesh of a dataset, one line each ([] when nothing does): the
    instance's name when it is not the file's stem, a Y-up file read Z-up, a mesh that covers
    almost none of its views."""
    notes = []
    if name != path.stem:  # why: its characters, a name the dataset root uses, or another mesh's name
        base = folder_safe(path.stem)
        why = ("names keep letters, digits, _ . and -" if base != path.stem else
               f"{base} is a name the dataset's root uses" if base in ROOT_NAMES else f"another mesh is instance {base}")
        notes.append(f"{path.name} is instance {name} ({why})")
    if up == "z":
        ext = np.ptp(mesh.vertices[np.unique(mesh.faces)], axis=0)
        if path.suffix.lower() in GLTF:
            notes.append(f"{path.name}: glTF is Y-up by its specification, and --up z lays it on its back; give --up y "
                         "(or a sidecar rotation for this file alone)")
        elif ext[1] >= ext[0] and ext[1] >= Y_TALLER * ext[2]:
            notes.append(f"{path.name}: deeper along y ({ext[1]:.2f}) than tall along z ({ext[2]:.2f}); if it lies on its back, "
                         "the file is Y-up: give --up y (or a sidecar rotation for this file alone)")
    cover = median_cover([f.rgba[..., 3] for f in train])
    if cover < SMALL_COVER:  # (only `dataset info` spoke, of camera axes)
        notes.append(f"{path.name}: the mesh covers {cover:.2%} of its views (median): its bounding box is far larger than the "
                     "object (a stray piece far away? each mesh is scaled to unit size by its box); remove the piece")
    return notes


ROOT_NAMES = ("twins", "instances.txt", "twins.json", "ATTRIBUTION.txt")
"""What a dataset's root holds besides its instances: no instance takes these names."""


def folder_safe(stem: str) -> str:
    """A file stem with every run of characters other than ``[A-Za-z0-9_.-]`` made one ``_``."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).strip("._-") or "mesh"


def instance_names_from(paths: list[Path]) -> list[str]:
    """File stems made folder-safe (``[A-Za-z0-9_.-]``) and unique (``_2``, ``_3``, … on clashes).

    >>> instance_names_from([Path("a/chair.obj"), Path("b/chair.obj"), Path("Ché z.ply"), Path("twins.obj"), Path("twins.json.obj")])
    ['chair', 'chair_2', 'Ch_z', 'twins_2', 'twins.json_2']
    """
    names: list[str] = []
    taken = set(ROOT_NAMES)
    for path in paths:
        base = folder_safe(Path(path).stem)
        name, k = base, 2
        while name in taken:
            name, k = f"{base}_{k}", k + 1
        taken.add(name)
        names.append(name)
    return names


def mesh_steps(meshes: int, config: MeshDatasetConfig) -> int:
    """Progress steps :func:`write_mesh_category` reports at most: one per mesh, one per twin
    source (up to ``config.twin_sources`` per twin kind; fewer when few meshes have parts fit
    for twins)."""
    return meshes + (min(meshes, 2 * len(twin_sources(meshes, config.twin_sources))) if config.twins else 0)


def _check(out: Path, paths: list[Path], config: MeshDatasetConfig) -> None:
    """One-line CrfError for bad options or an output folder we must not write into (synth's
    rules: a new folder, an empty one, or a previous dataset)."""
    if not paths:
        raise CrfError("no mesh files given")
    if config.palette not in ("random", "mtl"):
        raise CrfError(f"--palette {config.palette}: expected random or mtl")
    if config.up not in ("y", "z"):
        raise CrfError(f"--up {config.up}: expected y or z")
    synth_like = SynthConfig(instances=len(paths), views=config.views, res=config.res, seed=config.seed, twins=config.twins, aa=config.aa,
                             twin_sources=config.twin_sources)
    check_synth_args(out, synth_like)


@dataclass(frozen=True, eq=False)
class _Instance:
    """What twin picking needs of a written instance."""

    name: str
    mesh: PartMesh
    colors: list[str]
    cams: dict[str, list[Camera]]
    room: dict[int, tuple[int, int]]  # part id → scribble_view(train frames, id)
    reach: dict[int, tuple[int, int]]  # removable part id → stroke_view(train frames, id, need)
    hidden: dict[int, float]  # removable part id → hidden_share on the test views


def _write_instance(
    folder: Path, mesh: PartMesh, colors: list[str], cams: dict[str, list[Camera]], aa: int = 1
) -> dict[str, list[Frame]]:
    scene, albedo = RayScene(mesh), albedo_table(mesh, colors)
    frames = {split: [render_view(scene, cam, albedo, aa) for cam in cams_] for split, cams_ in cams.items()}
    for split, fs in frames.items():
        write_split(folder, split, fs)
    present = set(np.unique(mesh.face_part).tolist())
    write_parts(folder, [{"id": p.id, "name": p.name, "color": c} for p, c in zip(mesh.parts, colors) if p.id in present])
    return frames


def twin_parts(inst: _Instance, res: int) -> tuple[int | None, int | None]:
    """(part to recolor, part to remove) of an instance, None where there is none.

    Remove the :func:`removable_parts` one with the most stroke room (:func:`stroke_view`, thin
    parts allowed) among those whose removal uncovers at most :data:`MAX_HIDDEN_SHARE` of
    never-seen surface (:func:`hidden_share`); recolor the part with the most scribble room
    (:func:`scribble_view`) among the others (the removed one if it is the only candidate).
    Each needs :func:`min_scribble_pixels`.
    """
    need = min_scribble_pixels(res)
    room = {pid: count for pid, (_, count) in inst.room.items() if count >= need}
    reach = {pid: count for pid, (_, count) in inst.reach.items() if count >= need and inst.hidden[pid] <= MAX_HIDDEN_SHARE}
    remove = max(reach, key=reach.get) if reach else None
    others = {pid: count for pid, count in room.items() if pid != remove} or room
    return (max(others, key=others.get) if others else None), remove


def pick_twin_sources(picks: list[tuple[int | None, int | None]], count: int = TWIN_SOURCES) -> dict[str, list[int]]:
    """Per twin kind, up to ``count`` instances spread over those that have a part for it
    (``picks``: :func:`twin_parts` of each instance; the default count's are always among
    them, :func:`~.synth.twin_sources`).  The kinds draw from their own pools: which chairs
    get a removal twin (few parts uncover nothing unseen) does not move the colour twins."""
    pools = {kind: [i for i, pick in enumerate(picks) if pick[k] is not None] for k, kind in enumerate(("color", "remove"))}
    return {kind: [pool[k] for k in twin_sources(len(pool), count)] for kind, pool in pools.items()}


def _write_twin(
    out: Path, inst: _Instance, index: int, kind: str, part_id: int, config: MeshDatasetConfig
) -> TwinSpec:
    part = next(p for p in inst.mesh.parts if p.id == part_id)
    name, folder = f"{inst.name}_{kind}", Path("twins") / f"{inst.name}_{kind}"
    if kind == "color":
        color = contrasting_color(inst.colors)
        twin_mesh, twin_colors = inst.mesh, [color if p.id == part_id else c for p, c in zip(inst.mesh.parts, inst.colors)]
    else:
        color = None
        twin_mesh, twin_colors = inst.mesh.without_part(part_id), inst.colors
    _write_instance(out / folder, twin_mesh, twin_colors, {"test": inst.cams["test"]}, config.aa)
    view = (inst.room if kind == "color" else inst.reach)[part_id][0]
    source_view = render_view(RayScene(inst.mesh), inst.cams["train"][view], albedo_table(inst.mesh, inst.colors))
    rng = np.random.default_rng([config.seed, index, 2 if kind == "color" else 3])
    fg, keep = scribbles(rng, source_view.parts, part_id)
    write_png(out / folder / "scribble.png", fg.astype(np.uint8) * 255)
    write_png(out / folder / "keep.png", keep.astype(np.uint8) * 255)
    scribble_path, keep_path = str(folder / "scribble.png"), str(folder / "keep.png")
    return TwinSpec(name, kind, inst.name, f"train:{view}", part.name, color, scribble_path, keep_path, str(folder))


def attribution_text(names: list[str], paths: list[Path], metas: list[dict]) -> str | None:
    """``ATTRIBUTION.txt``: model name, creator, license and source per instance; None when no
    mesh came with attribution."""
    keys = ("name", "title", "creator", "license", "license_url", "source")
    if not any(any(m.get(k) for k in keys) for m in metas):
        return None
    lines = [
        "The images of this dataset are renders of the 3D models below, by their creators.",
        "Changes were made: each model was re-oriented, centered, scaled to unit size and recolored;",
        "the twins under twins/ are further recolored or have a part removed.",
        "",
    ]
    for name, path, meta in zip(names, paths, metas):
        lines.append(f"{name} (from {Path(path).name})")
        if not any(meta.get(k) for k in keys):
            lines.append("  no attribution given")
        for key in keys:
            if meta.get(key):
                lines.append(f"  {key + ':':<12} {' '.join(str(meta[key]).split())}")
        lines.append("")
    return "\n".join(lines)


def write_mesh_category(
    out: Path, paths: list[Path], config: MeshDatasetConfig = MeshDatasetConfig(),
    progress: Callable[[str], None] | None = None,
) -> MeshDatasetResult:
    """Render each mesh in ``paths`` as one instance of a category written to ``out``.

    Every mesh is loaded and checked before anything is written.  Twins are picked once all
    instances are rendered (:func:`pick_twin_sources`).  ``progress(label)`` is called after
    each instance and each twin source.
    """
    start = time.perf_counter()
    paths, out = [Path(p) for p in paths], Path(out)
    _check(out, paths, config)
    loaded = [load_normalized(p, config.up) for p in paths]
    meshes, metas = [m for m, _ in loaded], [meta for _, meta in loaded]
    RayScene(meshes[0])  # fail on a missing embreex before touching `out`
    names = instance_names_from(paths)
    # built in a hidden folder that replaces `out` whole: an earlier dataset's instances (and their
    # renders, whose attribution went with it) do not stay behind, and a failure leaves `out` as it was
    with atomic_folder(out) as root:
        instances, need, notes = [], min_scribble_pixels(config.res), []
        for index, (name, mesh) in enumerate(zip(names, meshes)):
            colors = part_colors(mesh, config.palette, np.random.default_rng([config.seed, index, 0]))
            cams = sample_cameras(np.random.default_rng([config.seed, index, 1]), config.views, config.res)
            frames = _write_instance(root / name, mesh, colors, cams, config.aa)
            notes += mesh_notes(paths[index], name, mesh, config.up, frames["train"])
            room = {p.id: scribble_view(frames["train"], p.id) for p in mesh.parts}
            reach = {pid: stroke_view(frames["train"], pid, need) for pid in removable_parts(mesh)} if config.twins else {}
            hidden = {pid: hidden_share(mesh, pid, cams["test"], cams["train"]) for pid, (_, n) in reach.items() if n >= need}
            instances.append(_Instance(name, mesh, colors, cams, room, reach, hidden))
            if progress:
                progress(name)
        twins: list[TwinSpec] = []
        picks = [twin_parts(inst, config.res) for inst in instances] if config.twins else []
        sources = pick_twin_sources(picks, config.twin_sources) if config.twins else {}
        if config.twins and len(set(sum(sources.values(), []))) == len(names) and len(names) > 1:
            notes.append(f"the twins' sources are all {len(names)} meshes: training leaves their part maps out by default "
                         "(part_labels=not-twins), so it gets no part head; fewer --twin-sources, --no-twins, or train with "
                         "--set part_labels=all")
        for index in sorted(set(sum(sources.values(), []))):
            for part_id, kind in zip(picks[index], ("color", "remove")):
                if index in sources[kind]:
                    twins.append(_write_twin(root, instances[index], index, kind, part_id, config))
            if progress:
                progress(f"{names[index]} twins")
        write_instances_txt(root, names)
        if twins:
            write_twins_json(root, twins)
        text = attribution_text(names, paths, metas)
        if text is not None:
            atomic_write_text(root / "ATTRIBUTION.txt", text)
        kept = carry_extras(out, root)  # a user's notes and scribbles in an earlier build: not lost with it
    return MeshDatasetResult(names, twins, [len(m.parts) for m in meshes], time.perf_counter() - start, kept, notes)
