"""``crfedit export mesh`` on a small trained model (issue 18): a closed-ish surface inside the
scene box whose vertex colours match the rendered colours where the vertices are visible."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfedit.config import make_config
from crfedit.data import load_category
from crfedit.renderer import ray_distance
from crfedit.export import extract_mesh, vertex_colors
from crfedit.model import load_model
from crfedit.renderer import render_camera
from crfedit.train import train

from cli_helpers import assert_user_error, invoke

pytest.importorskip("mcubes", reason="mesh export needs PyMCubes (pip install -e '.[export]')")
trimesh = pytest.importorskip("trimesh", reason="mesh export writes with trimesh (pip install -e '.[export]')")


@pytest.fixture(scope="module")
def model_path(tiny_chairs, tmp_path_factory):
    """The tiny category trained long enough to have opaque surfaces (~10 s on one core)."""
    path = tmp_path_factory.mktemp("export") / "model.safetensors"
    cfg = make_config("fast", overrides=dict(
        steps=300, rays=512, lr=1e-2, lr_codes=1e-2, grid_res=16, occ_res=32, width=32, rad_width=32,
        occ_warmup=100, occ_every=8, checkpoint_every=10**9,
    ))
    train(load_category(tiny_chairs), cfg, path, torch.device("cpu"), seed=0)
    return path


def visible_vertex_colours(model, mesh, camera, instance: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertex colours, the same vertices coloured looking from the camera, rendered colours at
    their pixels) [N, 3] for the vertices lying on the
    rendered surface of a view, where it is mostly opaque; rendered colours un-blended from the background."""
    out = render_camera(model.field_for(instance), camera, instance, background=0.0)
    opacity = out.opacity.numpy()
    depth, rgb, opaque = ray_distance(out).numpy(), out.rgb.numpy() / np.maximum(opacity, 1e-6)[..., None], opacity > 0.5
    w2c = np.linalg.inv(camera.c2w)
    p = mesh.vertices @ w2c[:3, :3].T + w2c[:3, 3]  # camera frame: looks down −z, y up (OpenGL)
    z = -p[:, 2]
    u = camera.focal * p[:, 0] / z + camera.width / 2
    v = -camera.focal * p[:, 1] / z + camera.height / 2
    inside = (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    ui, vi = u[inside].astype(int), v[inside].astype(int)
    on_surface = (np.abs(np.linalg.norm(p[inside], axis=1) - depth[vi, ui]) < 0.03) & opaque[vi, ui]
    points = mesh.vertices[inside][on_surface]
    towards_camera = camera.c2w[:3, 3] - points
    towards_camera /= np.linalg.norm(towards_camera, axis=1, keepdims=True)
    seen = vertex_colors(model.field_for(instance), instance, torch.as_tensor(points), torch.as_tensor(towards_camera, dtype=torch.float32))
    return mesh.colors[inside][on_surface], seen.numpy(), rgb[vi, ui][on_surface]


def test_mesh_is_bounded_closed_and_coloured_like_the_render(model_path):
    model, _ = load_model(model_path)
    mesh = extract_mesh(model, 0, res=48)
    lo, hi = model.field.aabb[:3].numpy(), model.field.aabb[3:].numpy()
    assert len(mesh.faces) > 200
    assert (mesh.vertices >= lo - 1e-5).all() and (mesh.vertices <= hi + 1e-5).all()
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    edges = np.sort(tm.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).mean() > 0.97  # watertight-ish: nearly every edge joins exactly two faces
    ours, seen, rendered = map(np.concatenate, zip(*(visible_vertex_colours(model, mesh, cam, 0) for cam in model.views["test"].cameras(0))))
    assert len(ours) > 50
    # the colouring ray, aimed from the camera, sees what the render sees at the vertex's pixel
    assert np.median(np.abs(seen - rendered).max(axis=1)) < 0.08, np.median(np.abs(seen - rendered).max(axis=1))
    # along the normal it sees the same surface; a 6-view 16x16 model's colour is view-dependent, so loosely
    assert np.abs(ours.mean(axis=0) - rendered.mean(axis=0)).max() < 0.3 and ours.max() < 0.99, (ours.mean(0), rendered.mean(0))


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_export_mesh_command_writes_vertex_colours(model_path, tmp_path, suffix):
    out = tmp_path / f"chair{suffix}"
    r = invoke("export", "mesh", model_path, "--instance", "chair_000", "--out", out, "--res", "32", "--device", "cpu")
    assert r.exit_code == 0 and "vertices" in r.stdout, r.output
    loaded = trimesh.load(out, process=False)
    assert len(loaded.faces) > 50 and loaded.visual.vertex_colors.shape[0] == len(loaded.vertices)
    assert_user_error(invoke("export", "mesh", model_path, "--instance", "0", "--out", tmp_path / "c.txt"), ".ply")
    assert not (tmp_path / "c.txt").exists()
    # a mesh replaces a mesh of its kind (the same command again), never notes that took its name
    again = invoke("export", "mesh", model_path, "--instance", "chair_000", "--out", out, "--res", "32", "--device", "cpu")
    assert again.exit_code == 0, again.output
    notes = tmp_path / f"notes{suffix}"
    notes.write_text("my notes")
    assert_user_error(invoke("export", "mesh", model_path, "--instance", "0", "--out", notes), "is not a")
    assert notes.read_text() == "my notes"


def test_glb_is_y_up_and_the_other_formats_keep_z_up(model_path, tmp_path):
    """glTF is Y-up: the .glb's vertices are the .ply's turned (x, y, z) → (x, z, −y), faces
    and colours alike, so the chair stands in a glTF viewer."""
    meshes = {}
    for suffix in (".ply", ".glb"):
        r = invoke("export", "mesh", model_path, "--instance", "chair_000", "--out", tmp_path / f"c{suffix}", "--res", "32", "--device", "cpu")
        assert r.exit_code == 0, r.output
        loaded = trimesh.load(tmp_path / f"c{suffix}", process=False, force="mesh")
        meshes[suffix] = loaded
    ply, glb = meshes[".ply"], meshes[".glb"]
    turned = np.stack([ply.vertices[:, 0], ply.vertices[:, 2], -ply.vertices[:, 1]], axis=1)
    assert np.allclose(glb.vertices, turned, atol=1e-6) and np.array_equal(glb.faces, ply.faces)
    assert np.allclose(glb.volume, ply.volume, rtol=1e-5) and glb.volume > 0  # a rotation: the winding still faces out


def test_the_lattice_built_in_slabs_is_the_lattice_built_at_once(model_path):
    """density_lattice builds a slab of planes at a time (the whole lattice's points were 12.9 GB
    at --res 1024): slabs of one plane and one slab of all planes give the same volume (to float
    rounding: the density batches differ), and it holds σ at its lattice points, 0 outside the
    occupied cells."""
    from crfedit import occupancy
    from crfedit.export import density_lattice

    model, _ = load_model(model_path)
    field, res = model.field_for(0), 20
    thin, whole = density_lattice(field, 0, res, chunk=1), density_lattice(field, 0, res, chunk=10**6)
    assert np.allclose(thin, whole, rtol=1e-5, atol=1e-5) and np.array_equal(thin > 0, whole > 0) and (whole > 0).any()
    axis = torch.linspace(-1.0, 1.0, res)
    xn = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    inside = occupancy.lookup_in_box(occupancy.dilate(field.occupancy[0], 1)[None], torch.zeros((), dtype=torch.long), xn)
    with torch.no_grad():
        expected = torch.where(inside, field.density(xn, 0), torch.zeros(()))
    assert np.allclose(whole.reshape(-1), expected.numpy(), rtol=1e-5, atol=1e-5)


def test_floaters_are_dropped_by_their_share_of_the_largest_piece():
    """Two pieces joined through a shared vertex count as one; a lone triangle far from them is a
    floater below a share of 0.5 of the largest piece's faces and stays at 0."""
    from crfedit.export import Mesh, drop_small_pieces, face_components

    tet = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    faces = np.concatenate([tet, tet + 3, [[7, 8, 9]]])  # the second tetrahedron shares vertex 3
    vertices = np.random.default_rng(0).random((10, 3)).astype(np.float32)
    assert face_components(faces, 10).tolist() == [0] * 8 + [7]
    mesh = Mesh(vertices, faces, vertices.copy(), 1.0)
    kept, dropped = drop_small_pieces(mesh, 0.5)
    assert dropped == 1 and kept.faces.tolist() == (np.concatenate([tet, tet + 3])).tolist()
    np.testing.assert_array_equal(kept.vertices, vertices[:7])
    assert drop_small_pieces(mesh, 0.0) == (mesh, 0) and drop_small_pieces(mesh, 0.1)[1] == 0
    long_chain = np.array([[i, i + 1, i + 2] for i in range(300)])  # labels reach along a long strip
    assert set(face_components(long_chain[::-1], 302).tolist()) == {0}


def test_export_mesh_min_piece_is_checked(model_path, tmp_path):
    assert_user_error(invoke("export", "mesh", model_path, "--instance", 0, "--out", tmp_path / "m.ply", "--min-piece", 1.5), "--min-piece 1.5")
    assert not (tmp_path / "m.ply").exists()
