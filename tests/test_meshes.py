"""``dataset from-meshes`` and the Sweet Home 3D chair extraction, on meshes made in the test."""

from __future__ import annotations

import json
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from crfedit.cameras import Camera, focal_from_angle, look_at  # noqa: E402
from crfedit.data.loading import load_category, load_twins, read_twin_specs  # noqa: E402
from crfedit.data.format import Frame  # noqa: E402
from crfedit.data.mesh_io import PartMesh, albedo_table, load_normalized, load_part_mesh, normalize_mesh, part_colors  # noqa: E402
from crfedit.data.meshes import (  # noqa: E402
    MAX_HIDDEN_SHARE,
    MeshDatasetConfig,
    RayScene,
    facing_normals,
    hidden_share,
    in_frame,
    instance_names_from,
    pick_twin_sources,
    removable_parts,
    render_view,
    stroke_view,
    separable_parts,
    write_mesh_category,
)
from crfedit.data.sh3f import extract_model, find_chairs, list_models, model_stem, read_properties  # noqa: E402
from crfedit.errors import CrfError, DataError  # noqa: E402

from cli_helpers import assert_user_error, invoke  # noqa: E402

L = np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85])
SEAT_KD, POST_KD = (0.8, 0.2, 0.1), (0.1, 0.3, 0.9)


def box_obj(lo, hi, offset: int) -> tuple[list[str], list[str]]:
    """OBJ ``v`` and ``f`` lines of an axis-aligned box, outward-facing, 1-based from ``offset``."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    corners = [(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]  # index = 4x + 2y + z
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    v = [f"v {x} {y} {z}" for x, y, z in corners]
    f = [f"f {a + offset} {b + offset} {c + offset}\nf {a + offset} {c + offset} {d + offset}" for a, b, c, d in quads]
    return v, f


def write_two_boxes(folder: Path, stem: str = "two_boxes") -> Path:
    """A wide "seat" slab under a thin "post", as two ``usemtl`` groups; Z-up, already unit size.

    seat: [-0.5, 0.5] × [-0.5, 0.5] × [-0.5, 0];  post: [-0.1, 0.1]² × [0, 0.5].
    """
    v1, f1 = box_obj((-0.5, -0.5, -0.5), (0.5, 0.5, 0.0), 1)
    v2, f2 = box_obj((-0.1, -0.1, 0.0), (0.1, 0.1, 0.5), 9)
    (folder / f"{stem}.mtl").write_text(
        f"newmtl seat\nKd {' '.join(map(str, SEAT_KD))}\n\nnewmtl post\nKd {' '.join(map(str, POST_KD))}\n"
    )
    obj = [f"mtllib {stem}.mtl", *v1, *v2, "usemtl seat", *f1, "usemtl post", *f2]
    path = folder / f"{stem}.obj"
    path.write_text("\n".join(obj) + "\n")
    return path


def camera(eye, target, res: int = 33) -> Camera:
    return Camera(look_at(eye, target), focal_from_angle(0.6911, res), res, res)


@pytest.fixture()
def boxes(tmp_path) -> Path:
    return write_two_boxes(tmp_path)


def test_parts_are_material_groups_with_their_kd(boxes):
    mesh = load_part_mesh(boxes)
    assert [(p.id, p.name) for p in mesh.parts] == [(1, "post"), (2, "seat")]  # by material name
    assert np.bincount(mesh.face_part).tolist() == [0, 12, 12]
    np.testing.assert_allclose(mesh.parts[0].material_color, POST_KD, atol=1 / 255)
    np.testing.assert_allclose(mesh.parts[1].material_color, SEAT_KD, atol=1 / 255)
    assert separable_parts(mesh) == [1, 2]
    assert removable_parts(mesh) == [1]  # the seat has the larger area: it is the body


def test_parts_of_glb_materials_and_ply_face_colors(tmp_path):
    import trimesh
    from trimesh.visual.material import PBRMaterial

    seat = trimesh.creation.box((1.0, 1.0, 0.5))
    post = trimesh.creation.box((0.2, 0.2, 0.5))
    seat.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="seat", baseColorFactor=[204, 51, 26, 255]))
    post.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(name="post", baseColorFactor=[26, 77, 230, 255]))
    trimesh.Scene({"a": seat, "b": post}).export(tmp_path / "boxes.glb")
    mesh = load_part_mesh(tmp_path / "boxes.glb")
    assert [p.name for p in mesh.parts] == ["post", "seat"]
    np.testing.assert_allclose(mesh.parts[1].material_color, np.array([204, 51, 26]) / 255)

    both = trimesh.util.concatenate([seat, post])
    colors = np.repeat([[200, 50, 20, 255], [20, 70, 230, 255]], 12, axis=0).astype(np.uint8)
    trimesh.Trimesh(both.vertices, both.faces, face_colors=colors, process=False).export(tmp_path / "boxes.ply")
    mesh = load_part_mesh(tmp_path / "boxes.ply")
    assert [p.name for p in mesh.parts] == ["color_1446e6", "color_c83214"]
    assert np.bincount(mesh.face_part).tolist() == [0, 12, 12]


def test_mtl_color_of_a_textured_material_is_the_texture_mean(tmp_path):
    from PIL import Image

    Image.fromarray(np.array([[[255, 0, 0], [0, 0, 255]]] * 2, np.uint8)).save(tmp_path / "tex.png")
    (tmp_path / "t.mtl").write_text("newmtl wood\nKd 0.64 0.64 0.64\nmap_Kd tex.png\n")
    obj = "mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl wood\nf 1/1 2/2 3/3\n"
    (tmp_path / "t.obj").write_text(obj)
    (part,) = load_part_mesh(tmp_path / "t.obj").parts
    np.testing.assert_allclose(part.material_color, [0.5, 0.0, 0.5])


def test_exact_depth_part_and_shade_head_on(boxes):
    mesh, _ = load_normalized(boxes, "z")
    np.testing.assert_allclose(mesh.vertices.min(0), [-0.5, -0.5, -0.5])
    np.testing.assert_allclose(mesh.vertices.max(0), [0.5, 0.5, 0.5])
    albedo = albedo_table(mesh, part_colors(mesh, "mtl", np.random.default_rng(0)))
    scene = RayScene(mesh)

    side = render_view(scene, camera((0.0, -2.0, -0.25), (0.0, 0.0, -0.25)), albedo)
    c = 16  # center pixel of 33×33: its ray is the optical axis
    assert side.depth[c, c] == pytest.approx(1.5, abs=1e-6)  # eye y=-2 to the seat's face y=-0.5
    assert side.parts[c, c] == 2 and side.rgba[c, c, 3] == 1.0
    expected = albedo[2] * (0.35 + 0.65 * max(0.0, np.dot([0.0, -1.0, 0.0], L)))
    np.testing.assert_allclose(side.rgba[c, c, :3], expected, atol=1e-6)
    assert side.parts[0, 0] == 0 and side.rgba[0, 0, 3] == 0.0 and np.isinf(side.depth[0, 0])
    np.testing.assert_array_equal(side.rgba[0, 0, :3], [1.0, 1.0, 1.0])

    top = render_view(scene, camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0)), albedo)
    assert top.depth[c, c] == pytest.approx(1.5, abs=1e-6)  # eye z=2 to the post's top z=0.5
    assert top.parts[c, c] == 1
    assert {1, 2} <= set(np.unique(top.parts).tolist())  # the seat shows around the post


def test_normals_face_the_camera():
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])  # looking at the front, at the back
    np.testing.assert_array_equal(facing_normals(n, d), [[0, 0, 1], [0, 0, -1]])


def test_y_up_and_sidecar_rotation(tmp_path):
    v, f = box_obj((0.0, 0.0, 0.0), (1.0, 4.0, 2.0), 1)  # tallest along the file's +Y
    path = tmp_path / "tall.obj"
    path.write_text("\n".join(v + f) + "\n")
    mesh, _ = load_normalized(path, "y")
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [0.25, 0.5, 1.0])
    np.testing.assert_allclose(mesh.vertices.min(0) + mesh.vertices.max(0), 0.0, atol=1e-12)
    # a file rotation first turns +X into +Y: x-extent 1 lands on y, then y-up puts 4 on z
    (tmp_path / "tall.meta.json").write_text(json.dumps({"rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]]}))
    mesh, _ = load_normalized(path, "y")
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [1.0, 0.5, 0.25])


def test_round_trip_through_load_category(boxes, tmp_path):
    out = tmp_path / "data"
    config = MeshDatasetConfig(views=5, res=16, seed=3, palette="mtl", twins=False)
    result = write_mesh_category(out, [boxes], config)
    assert result.names == ["two_boxes"] and result.parts == [2] and result.twins == []
    cat = load_category(out, with_depth=True, with_parts=True)
    assert cat.names == ["two_boxes"]
    inst = cat.instance(0)
    assert {s: len(v) for s, v in inst.splits.items()} == {"train": 3, "val": 1, "test": 1}
    parts = json.loads((out / "two_boxes" / "parts.json").read_text())
    assert [(p["id"], p["name"]) for p in parts] == [(1, "post"), (2, "seat")]
    assert parts[1]["color"] == "#cc331a"  # Kd 0.8 0.2 0.1
    mesh, _ = load_normalized(boxes, "z")
    scene, albedo = RayScene(mesh), albedo_table(mesh, [p["color"] for p in parts])
    for view in inst.splits["train"]:
        again = render_view(scene, view.camera, albedo, config.aa)
        np.testing.assert_array_equal(view.depth, again.depth)
        np.testing.assert_array_equal(view.parts, again.parts)
        np.testing.assert_allclose(view.alpha, again.rgba[..., 3], atol=0.5 / 255 + 1e-6)  # 8-bit PNG alpha
        assert view.camera.width == 16 and np.linalg.norm(view.camera.center) == pytest.approx(2.0)
    assert not (out / "ATTRIBUTION.txt").exists()


def test_twins_and_attribution(boxes, tmp_path):
    (boxes.parent / "two_boxes.meta.json").write_text(
        json.dumps({"name": "Box chair", "creator": "A. Maker", "license": "CC-BY 3.0", "source": "https://example.org/b"})
    )
    out = tmp_path / "data"
    result = write_mesh_category(out, [boxes], MeshDatasetConfig(views=20, res=32, seed=0))
    specs = {s.kind: s for s in read_twin_specs(out)}
    assert set(specs) == {"color", "remove"}
    assert specs["remove"].part == "post" and specs["color"].part == "seat"
    assert specs["color"].color.startswith("#") and specs["remove"].color is None
    twins = {spec.kind: inst for spec, inst in load_twins(out)}
    assert all(1 not in v.parts for v in twins["remove"].splits["test"])  # the post is gone
    source = load_category(out, with_parts=True).instance(0)
    for a, b in zip(source.splits["test"], twins["color"].splits["test"]):
        np.testing.assert_array_equal(a.alpha, b.alpha)  # same shape, other colors
    assert len(result.twins) == 2
    text = (out / "ATTRIBUTION.txt").read_text()
    assert "two_boxes (from two_boxes.obj)" in text and "A. Maker" in text and "CC-BY 3.0" in text
    assert "https://example.org/b" in text


def write_cushion_on_seat(folder: Path) -> Path:
    """A seat slab with a cushion lying on it: removing the cushion uncovers the seat's top,
    which no camera saw."""
    v1, f1 = box_obj((-0.5, -0.5, -0.5), (0.5, 0.5, 0.0), 1)
    v2, f2 = box_obj((-0.4, -0.4, 0.0), (0.4, 0.4, 0.1), 9)
    (folder / "cushion.mtl").write_text("newmtl seat\nKd 0.8 0.2 0.1\n\nnewmtl cushion\nKd 0.1 0.3 0.9\n")
    path = folder / "cushion.obj"
    path.write_text("\n".join(["mtllib cushion.mtl", *v1, *v2, "usemtl seat", *f1, "usemtl cushion", *f2]) + "\n")
    return path


def test_in_frame_closed_form():
    cam = camera([0.0, -2.0, 0.0], [0.0, 0.0, 0.0], res=33)
    points = np.array([[0, 0, 0], [0, -3, 0], [5, 0, 0], [0.3, 0, 0.3]], dtype=float)
    # the target, behind the camera, far off to the side (x/depth = 2.5 > tan(fov/2)), inside
    assert in_frame(cam, points).tolist() == [True, False, False, True]


def test_hidden_share_tells_a_cushion_from_a_post(boxes, tmp_path):
    from crfedit.data.synth import sample_cameras

    cams = sample_cameras(np.random.default_rng(0), 50, 32)
    post = load_part_mesh(boxes)
    # behind a post: background and seen seat, but for its footprint (the post's top in view)
    assert 0.1 < hidden_share(post, 1, cams["test"], cams["train"]) < MAX_HIDDEN_SHARE
    cushion = load_part_mesh(write_cushion_on_seat(tmp_path))
    assert [p.name for p in cushion.parts] == ["cushion", "seat"]
    # under it the unseen seat top; from low views, past its far edge, the background
    assert hidden_share(cushion, 1, cams["test"], cams["train"]) > 0.8
    assert hidden_share(cushion, 1, cams["test"], cams["train"] + cams["val"]) > 0.8  # however many views
    # a part no view shows counts as hidden: its removal twin would be its source, byte for byte
    away = [camera([0.0, 0.0, -40.0], [0.0, 0.0, -60.0], res=16)]  # looking away from the object
    assert hidden_share(post, 1, away, cams["train"]) == 1.0
    # a removal twin must not measure inpainting: the cushion gets a colour twin only
    out = tmp_path / "data"
    write_mesh_category(out, [tmp_path / "cushion.obj"], MeshDatasetConfig(views=10, res=32, seed=0))
    assert [s.kind for s in read_twin_specs(out)] == ["color"]


def test_thin_parts_get_strokes_along_them():
    from crfedit.data.synth import scribbles, stroke_region
    from crfedit.masks import erode

    parts = np.zeros((32, 32), dtype=np.uint8)
    parts[4:28, 10] = 1  # a 1-px leg, 24 px long
    parts[8:18, 16:26] = 2  # a 10×10 seat
    assert (stroke_region(parts == 2, 16) == erode(parts == 2, 2)).all()  # 6×6 = 36 ≥ 16
    assert (stroke_region(parts == 1, 16) == (parts == 1)).all()  # erosion would leave nothing
    fg, keep = scribbles(np.random.default_rng(0), parts, 1)
    assert fg.sum() >= 3 and (fg <= (parts == 1)).all()  # on the leg, not a speck beside it
    frames = [type("F", (), {"parts": parts})(), type("F", (), {"parts": np.where(parts == 1, 0, parts)})()]
    assert stroke_view(frames, 1, 16) == (0, 24)


def test_same_seed_same_files(boxes, tmp_path):
    config = MeshDatasetConfig(views=4, res=16, seed=7)
    write_mesh_category(tmp_path / "a", [boxes], config)
    write_mesh_category(tmp_path / "b", [boxes], config)
    for f in sorted((tmp_path / "a").rglob("*")):
        if f.is_file():
            assert f.read_bytes() == (tmp_path / "b" / f.relative_to(tmp_path / "a")).read_bytes(), f


def test_broken_and_empty_meshes_are_one_line_errors(tmp_path):
    broken = tmp_path / "broken.ply"
    broken.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01garbage")
    with pytest.raises(DataError, match="broken.ply"):
        load_part_mesh(broken)
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(DataError, match=r"empty\.obj: mesh has no triangles"):
        load_part_mesh(empty)
    flat = tmp_path / "flat.obj"  # a triangle with its corners in a line: accepted, it rendered empty views that train refused
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(DataError, match=r"flat\.obj: mesh has no area: every triangle is degenerate"):
        load_part_mesh(flat)
    with pytest.raises(DataError, match="notes.txt: not a mesh format"):
        (tmp_path / "notes.txt").write_text("hi")
        load_part_mesh(tmp_path / "notes.txt")

    assert_user_error(invoke("dataset", "from-meshes", tmp_path / "out", broken), "broken.ply")
    assert not (tmp_path / "out").exists()  # meshes are checked before anything is written
    noise = tmp_path / "noise.obj"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(DataError, match=r"noise\.obj: cannot read mesh"):
        load_part_mesh(noise)
    (tmp_path / "folder.obj").mkdir()
    with pytest.raises(DataError, match=r"folder\.obj: is a folder, not a mesh file"):
        load_part_mesh(tmp_path / "folder.obj")


def test_missing_embreex_is_a_data_error_with_the_install_hint(boxes, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "embreex", None)  # makes `import embreex` raise ImportError
    with pytest.raises(DataError, match=r"embreex is not installed: pip install 'crfedit\[meshes\]'"):
        write_mesh_category(tmp_path / "out", [boxes], MeshDatasetConfig(views=3, res=8))
    assert not (tmp_path / "out").exists()


def test_bad_options_and_foreign_output_folders_are_refused(boxes, tmp_path):
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(CrfError, match="not empty and not a dataset"):
        write_mesh_category(tmp_path / "busy", [boxes])
    with pytest.raises(CrfError, match="--palette"):
        write_mesh_category(tmp_path / "x", [boxes], MeshDatasetConfig(palette="pastel"))
    with pytest.raises(CrfError, match="twins need a test split"):
        write_mesh_category(tmp_path / "x", [boxes], MeshDatasetConfig(views=2))
    assert not (tmp_path / "x").exists()


def test_instance_names_are_sanitized_and_unique():
    paths = [Path("a/chair.obj"), Path("b/chair.obj"), Path("Ché z.ply"), Path("twins.obj"), Path("...obj")]
    assert instance_names_from(paths) == ["chair", "chair_2", "Ch_z", "twins_2", "mesh"]


def test_cli_from_meshes(boxes, tmp_path):
    out = tmp_path / "cli"
    args = ["dataset", "from-meshes", str(out), str(boxes), "--views", "4", "--res", "16", "--palette", "mtl", "--no-twins"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    assert "wrote 1 mesh (2 parts) x 4 views at 16x16 + 0 twins" in result.stdout and "replaced" not in result.stdout
    # written again over the first: said, and the user's notes and scribbles beside it are kept (they were deleted)
    (out / "NOTES.md").write_text("mine")
    (out / "my_scribbles").mkdir()
    (out / "my_scribbles" / "seat.png").write_bytes(b"x")
    again = invoke(*args)
    assert again.exit_code == 0 and "(it replaced the dataset that was there; kept what was not the dataset's: NOTES.md, my_scribbles)" in again.stdout, again.output
    assert (out / "NOTES.md").read_text() == "mine" and (out / "my_scribbles" / "seat.png").read_bytes() == b"x"
    assert (out / "instances.txt").read_text() == "two_boxes\n"


def test_normalize_rejects_a_mesh_collapsed_to_a_point(boxes):
    mesh = load_part_mesh(boxes)
    flat = type(mesh)(np.zeros_like(mesh.vertices), mesh.faces, mesh.face_part, mesh.parts)
    with pytest.raises(DataError, match="all its vertices coincide"):
        normalize_mesh(flat)


# ----------------------------------------------------------------------------- .sh3f catalogs


PROPERTIES = """# a catalog
id=Test#catalog
license=Creative Commons Attribution 3.0 license
name#1=Dining chair
category#1=Living room
creator#1=Jos\\u00e9 \\
  Maker
model#1=/test/diningChair/diningChair.obj
width#1=45
depth#1=50
height#1=90
modelRotation#1=1 0 0 0 0 1 0 -1 0
name#2=Deck chair
creator#2=Someone
model#2=/test/deck/deck.obj
width#2=70
depth#2=190
height#2=80
name#3=Wheelchair
model#3=/test/wheel/wheel.obj
width#3=60
depth#3=70
height#3=90
"""


def test_read_properties_escapes_and_continuations():
    props = read_properties("a=1\nb : two \\\n   words\n! c=3\nd=caf\\u00e9\ne\\=f=g\n")
    assert props == {"a": "1", "b": "two words", "d": "café", "e=f": "g"}


def test_sh3f_chairs_extract_with_attribution_and_rotation(boxes, tmp_path):
    catalog = tmp_path / "Test-CC-BY.sh3f"
    with zipfile.ZipFile(catalog, "w") as z:
        z.writestr("PluginFurnitureCatalog.properties", PROPERTIES.encode("latin-1"))
        z.writestr("LICENSE.TXT", "http://creativecommons.org/licenses/by/3.0/\n")
        z.writestr("test/diningChair/diningChair.obj", boxes.read_text())
        z.writestr("test/diningChair/two_boxes.mtl", (boxes.parent / "two_boxes.mtl").read_text())
        z.writestr(
            "test/diningChair/1 - LICENSE.html",
            '<h1><a href="http://www.blendswap.com/blends/view/1">Blend #1: Nice chair</a></h1>',
        )
    assert [m.name for m in list_models(catalog)] == ["Dining chair", "Deck chair", "Wheelchair"]
    chairs = find_chairs([catalog])
    assert [m.name for m in chairs] == ["Dining chair"]  # deck chair too flat, wheelchair not a chair
    assert chairs[0].creator == "José Maker"
    assert model_stem(chairs[0]) == "test_cc_by_dining_chair"

    obj = extract_model(chairs[0], tmp_path / "src")
    assert obj == tmp_path / "src" / "test_cc_by_dining_chair" / "test_cc_by_dining_chair.obj"
    meta = json.loads(obj.with_suffix(".meta.json").read_text())
    assert meta == {
        "name": "Dining chair",
        "title": "Nice chair",
        "creator": "José Maker",
        "license": "Creative Commons Attribution 3.0 license",
        "license_url": "http://creativecommons.org/licenses/by/3.0/",
        "source": "http://www.blendswap.com/blends/view/1",
        "rotation": [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]],
    }
    # the file is Z-up; modelRotation turns it Y-up and --up y back: the post stays on top
    mesh, _ = load_normalized(obj, "y")
    post = mesh.vertices[np.unique(mesh.faces[mesh.face_part == 1])]
    assert post[:, 2].min() == pytest.approx(0.0) and post[:, 2].max() == pytest.approx(0.5)

    out = tmp_path / "data"
    write_mesh_category(out, [obj], MeshDatasetConfig(views=3, res=8, up="y", twins=False))
    text = (out / "ATTRIBUTION.txt").read_text()
    assert "José Maker" in text and "Nice chair" in text and "blends/view/1" in text


def test_more_twin_sources_keep_the_default_ones():
    picks = [(1, None if i % 3 == 0 else 2) for i in range(20)]  # every 3rd mesh has nothing to remove
    base, more = pick_twin_sources(picks), pick_twin_sources(picks, 8)
    assert [len(base[k]) for k in ("color", "remove")] == [4, 4] and [len(more[k]) for k in ("color", "remove")] == [8, 8]
    for kind, pick in (("color", 0), ("remove", 1)):
        assert set(base[kind]) <= set(more[kind])
        assert all(picks[i][pick] is not None for i in more[kind])


def test_mesh_names_keep_clear_of_the_dataset_files_and_rotations_are_rotations(boxes, tmp_path):
    """A mesh named like a file of the dataset's root (instances.txt.obj) wrote its instance
    folders, then failed on its own folder; a sidecar "rotation" that scales, shears or mirrors
    reshaped the object without a word."""
    import shutil

    from crfedit.data.meshes import instance_names_from

    names = instance_names_from([Path(n) for n in ("instances.txt.obj", "twins.json.ply", "ATTRIBUTION.txt.obj", "twins.off")])
    assert names == ["instances.txt_2", "twins.json_2", "ATTRIBUTION.txt_2", "twins_2"]
    for bad in ([[-1, 0, 0], [0, 1, 0], [0, 0, 1]], [[5, 0, 0], [0, 1, 0], [0, 0, 1]], [[1, 1, 0], [0, 1, 0], [0, 0, 1]]):
        mesh = tmp_path / "m.obj"
        shutil.copy(boxes, mesh)
        (tmp_path / "m.meta.json").write_text(json.dumps({"rotation": bad}))
        with pytest.raises(DataError, match=r"rotation must be a rotation \(orthonormal rows, determinant \+1\)"):
            load_normalized(mesh)
    (tmp_path / "m.meta.json").write_text(json.dumps({"rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]]}))  # a quarter turn: fine
    load_normalized(tmp_path / "m.obj")
    (tmp_path / "m.meta.json").write_text(json.dumps({"rotation": [["1", 0, 0], [0, 1, 0], [0, 0, 1]]}))  # text is not a number
    with pytest.raises(DataError, match="rotation must be a 3x3 matrix of numbers"):
        load_normalized(tmp_path / "m.obj")
    (tmp_path / "m.meta.json").write_text(json.dumps({"licence": "CC0", "author": "me"}))  # misspelt: the credit was lost silently
    with pytest.raises(DataError, match=r"m\.meta\.json: unknown keys 'author', 'licence'; a sidecar holds name, title, creator, license"):
        load_normalized(tmp_path / "m.obj")


def test_mesh_notes_name_a_y_up_file_a_tiny_mesh_a_renamed_file_and_twins_of_every_mesh(boxes, tmp_path):
    """What looks wrong with a mesh dataset is said after the run (it wrote silently): a glTF
    read Z-up, an OBJ deeper along y than tall along z, a mesh that covers under 1 % of its
    views (a stray triangle far away), a file whose instance is not its stem, and twins whose
    sources are every mesh (training then gets no part head)."""
    import shutil

    from crfedit.data.meshes import mesh_notes

    square = lambda n: [Frame(None, np.zeros((8, 8, 4), np.float32), None, None) for _ in range(n)]
    seen = square(3)
    for f in seen:
        f.rgba[2:6, 2:6, 3] = 1.0
    flat, _ = load_normalized(boxes)  # two boxes, Z-up: wider than tall, no note for its axes
    assert mesh_notes(Path("two_boxes.obj"), "two_boxes", flat, "z", seen) == []
    assert mesh_notes(Path("two_boxes.glb"), "two_boxes", flat, "z", seen)[0].startswith("two_boxes.glb: glTF is Y-up by its specification")
    assert mesh_notes(Path("two_boxes.glb"), "two_boxes", flat, "y", seen) == []
    turned = PartMesh(flat.vertices * np.array([0.6, 1.0, 0.5]), flat.faces, flat.face_part, flat.parts)  # deep along y, low along z
    assert "deeper along y" in mesh_notes(Path("m.obj"), "m", turned, "z", seen)[0]
    assert mesh_notes(Path("m.obj"), "m", turned, "y", seen) == []
    tiny = mesh_notes(Path("two_boxes.obj"), "two_boxes", flat, "y", square(3))  # no pixel shows it
    assert tiny == ["two_boxes.obj: the mesh covers 0.00% of its views (median): its bounding box is far larger than the object "
                    "(a stray piece far away? each mesh is scaled to unit size by its box); remove the piece"]
    assert mesh_notes(Path("椅子.obj"), "mesh", flat, "y", seen) == ["椅子.obj is instance mesh (names keep letters, digits, _ . and -)"]
    # a clean name renamed says why: the dataset's root uses it, or another mesh took it
    assert mesh_notes(Path("twins.obj"), "twins_2", flat, "y", seen) == ["twins.obj is instance twins_2 (twins is a name the dataset's root uses)"]
    assert mesh_notes(Path("my_chair.obj"), "my_chair_2", flat, "y", seen) == ["my_chair.obj is instance my_chair_2 (another mesh is instance my_chair)"]
    other = tmp_path / "other.obj"
    shutil.copy(boxes, other)
    result = write_mesh_category(tmp_path / "d", [boxes, other], MeshDatasetConfig(views=4, res=16, twin_sources=4))
    assert result.twins and [n for n in result.notes if "twins" in n] == [
        "the twins' sources are all 2 meshes: training leaves their part maps out by default (part_labels=not-twins), so it gets no "
        "part head; fewer --twin-sources, --no-twins, or train with --set part_labels=all"]
    assert not write_mesh_category(tmp_path / "e", [boxes, other], MeshDatasetConfig(views=4, res=16, twins=False)).notes



def test_a_dataset_written_again_is_replaced_whole(boxes, tmp_path):
    """Writing a mesh dataset over an earlier one left the earlier instances' folders (and their
    renders, CC-BY ones among them, without the ATTRIBUTION.txt that went with them)."""
    out = tmp_path / "data"
    cushion = write_cushion_on_seat(tmp_path)
    write_mesh_category(out, [boxes, cushion], MeshDatasetConfig(views=4, res=16, seed=0, twins=False))
    assert (out / cushion.stem).is_dir()
    (out / "notes.txt").write_text("mine")  # not the dataset's: carried over
    result = write_mesh_category(out, [boxes], MeshDatasetConfig(views=4, res=16, seed=0, twins=False))
    assert sorted(p.name for p in out.iterdir()) == sorted([boxes.stem, "instances.txt", "notes.txt"]) and result.kept == ["notes.txt"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no hidden build folder left
