"""Dataset format: write → load round trips, Blender scenes, area resizing, one-line DataErrors."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from crfedit.cameras import Camera, focal_from_angle, look_at, rays_from_camera, spherical_eye
from crfedit.data import (
    Frame,
    TwinSpec,
    dataset_info,
    load_category,
    load_twins,
    training_rays,
    write_instances_txt,
    write_parts,
    write_split,
    write_twins_json,
)
from crfedit.errors import CrfError, DataError
from crfedit.io import write_exr

from cli_helpers import assert_user_error, invoke

RES = 8


def camera(k: int, res: int = RES) -> Camera:
    return Camera(look_at(spherical_eye(40.0 * k + 3.0, 20.0 + 5 * k, 2.0)), focal_from_angle(0.6911, res), res, res)


def random_frame(rng: np.random.Generator, k: int, res: int = RES) -> Frame:
    rgba = rng.integers(0, 256, (res, res, 4)).astype(np.float32) / 255.0
    depth = rng.uniform(1.0, 3.0, (res, res)).astype(np.float32)
    depth[0, :] = np.inf
    parts = rng.integers(0, 4, (res, res)).astype(np.uint8)
    return Frame(camera(k, res), rgba, depth, parts)


def make_category(root: Path, names=("a", "b"), views=3, res=RES, seed=0) -> dict[str, list[Frame]]:
    rng = np.random.default_rng(seed)
    frames = {}
    for name in names:
        frames[name] = [random_frame(rng, k, res) for k in range(views)]
        write_split(root / name, "train", frames[name])
        write_split(root / name, "test", frames[name][:1])
        write_parts(root / name, [{"id": 1, "name": "seat", "color": "#aa0000"}])
    write_instances_txt(root, list(names))
    return frames


def test_round_trip_poses_pixels_depth_parts(tmp_path):
    frames = make_category(tmp_path)
    cat = load_category(tmp_path, with_depth=True, with_parts=True)
    assert cat.names == ["a", "b"] and set(cat.instances[0].splits) == {"train", "test"}
    for inst in cat.instances:
        for frame, view in zip(frames[inst.name], inst.splits["train"]):
            np.testing.assert_allclose(view.camera.c2w, frame.camera.c2w, atol=1e-6)
            assert math.isclose(view.camera.focal, frame.camera.focal, rel_tol=1e-9)
            png = np.asarray(Image.open(inst.path / (view.file_path + ".png")))
            np.testing.assert_array_equal(png, np.round(frame.rgba * 255).astype(np.uint8))
            a = frame.rgba[..., 3]
            np.testing.assert_array_equal(view.alpha, a)
            np.testing.assert_allclose(view.rgb, frame.rgba[..., :3] * a[..., None] + 1 - a[..., None], atol=1e-7)
            np.testing.assert_array_equal(view.depth, frame.depth)  # inf included
            np.testing.assert_array_equal(view.parts, frame.parts)
    assert cat.instance("b") is cat.instances[1] and cat.instance(0) is cat.instances[0]
    assert cat.instance("1") is cat.instances[1]
    assert cat.instance("b").view("test:0").file_path == "./test/r_000"


def test_fingerprint_stable_and_sensitive(tmp_path):
    make_category(tmp_path / "x")
    make_category(tmp_path / "y")
    fx, fy = load_category(tmp_path / "x").fingerprint, load_category(tmp_path / "y").fingerprint
    assert fx == fy and len(fx) == 16
    path = tmp_path / "y" / "a" / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][0]["transform_matrix"][0][3] += 0.5
    path.write_text(json.dumps(meta))
    assert load_category(tmp_path / "y").fingerprint != fx


def blender_scene(folder: Path, res: int = 32, n: int = 2, angle: float = 0.6911) -> np.ndarray:
    """A NeRF-synthetic scene as Blender writes it: RGBA PNGs, camera_angle_x, extra keys."""
    rng = np.random.default_rng(1)
    (folder / "train").mkdir(parents=True)
    images = rng.integers(0, 256, (n, res, res, 4), dtype=np.uint8)
    frames = []
    for k in range(n):
        Image.fromarray(images[k], "RGBA").save(folder / "train" / f"r_{k}.png")
        frames.append({"file_path": f"./train/r_{k}", "rotation": 0.0125, "transform_matrix": camera(k).c2w.tolist()})
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}, indent=4))
    return images


def test_single_blender_scene_loads_as_one_instance(tmp_path):
    images = blender_scene(tmp_path / "lego")
    cat = load_category(tmp_path / "lego")
    assert cat.names == ["lego"] and list(cat.instances[0].splits) == ["train"]
    view = cat.instances[0].splits["train"][1]
    assert (view.camera.width, view.camera.height) == (32, 32)
    assert math.isclose(view.camera.focal, 16.0 / math.tan(0.5 * 0.6911))
    np.testing.assert_array_equal(view.alpha, images[1, ..., 3] / np.float32(255))
    info = dataset_info(cat)
    assert info["instances"] == 1 and info["views"] == {"train": 2} and info["bbox"]["source"] == "cameras"
    assert info["resolutions"] == ["32x32"] and info["twins"] == 0


def test_windows_separators_in_file_paths_load(tmp_path, tiny_chairs):
    """``train\\r_0`` (written on Windows) names the same image as ``train/r_0``, in both formats."""
    blender_scene(tmp_path / "lego")
    _edit_json(tmp_path / "lego" / "transforms_train.json",
               lambda m: [f.update(file_path=f["file_path"].replace("/", "\\")) for f in m["frames"]])
    assert "\\" in json.loads((tmp_path / "lego" / "transforms_train.json").read_text())["frames"][0]["file_path"]
    assert len(load_category(tmp_path / "lego").instances[0].splits["train"]) == 2
    from test_nerfstudio import to_nerfstudio

    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "scene", with_mask=True, listed=True)
    plain = load_category(tmp_path / "scene")
    _edit_json(tmp_path / "scene" / "transforms.json", lambda m: [
        *[f.update(file_path=f["file_path"].replace("/", "\\"), mask_path=f["mask_path"].replace("/", "\\")) for f in m["frames"]],
        *[m.update({key: [n.replace("/", "\\") for n in m[key]]}) for key in ("train_filenames", "test_filenames")]])
    windows = load_category(tmp_path / "scene")
    for split in ("train", "test"):
        a, b = plain.instances[0].splits[split], windows.instances[0].splits[split]
        assert len(a) == len(b) and all(np.array_equal(x.rgb, y.rgb) for x, y in zip(a, b))


def test_focal_in_pixels_and_16bit_png(tmp_path):
    blender_scene(tmp_path / "s")
    path = tmp_path / "s" / "transforms_train.json"
    meta = json.loads(path.read_text())
    del meta["camera_angle_x"]
    meta["fl_x"] = 40.0
    path.write_text(json.dumps(meta))
    Image.fromarray(np.full((32, 32), 65535, np.uint16)).save(tmp_path / "s" / "train" / "r_0.png")
    view = load_category(tmp_path / "s").instances[0].splits["train"][0]
    assert view.camera.focal == 40.0
    np.testing.assert_allclose(view.rgb, 1.0)


def test_resize_is_a_2x2_area_average(tmp_path):
    images = blender_scene(tmp_path / "s").astype(np.float64) / 255.0
    write_exr(tmp_path / "s" / "train" / "r_0_depth.exr", {"Z": np.arange(32 * 32, dtype=np.float32).reshape(32, 32)})
    view = load_category(tmp_path / "s", res=16, with_depth=True).instances[0].splits["train"][0]
    a = images[0, ..., 3:]
    composite = images[0, ..., :3] * a + (1 - a)
    block = lambda x: x.reshape(16, 2, 16, 2, -1).mean((1, 3))  # noqa: E731
    np.testing.assert_allclose(view.rgb, block(composite), atol=1e-6)
    np.testing.assert_allclose(view.alpha, block(a)[..., 0], atol=1e-6)
    assert (view.camera.width, view.camera.height) == (16, 16)
    assert math.isclose(view.camera.focal, 8.0 / math.tan(0.5 * 0.6911))
    depth = np.arange(32 * 32, dtype=np.float32).reshape(32, 32)
    assert set(view.depth.ravel()) <= set(depth.ravel())  # nearest: values copied, not blended


def test_training_rays(tmp_path):
    make_category(tmp_path)
    cat = load_category(tmp_path)
    rays = training_rays(cat)
    n = 2 * 3 * RES * RES
    assert rays.origins.shape == rays.directions.shape == rays.rgb.shape == (n, 3)
    assert rays.alpha.shape == rays.instance.shape == (n,)
    assert rays.origins.dtype == rays.rgb.dtype == torch.float32 and rays.instance.dtype == torch.int64
    assert rays.instance[0] == 0 and rays.instance[-1] == 1
    view = cat.instances[0].splits["train"][0]
    ref = rays_from_camera(view.camera)
    assert torch.equal(rays.origins[0], ref.origins[0]) and torch.equal(rays.directions[0], ref.directions[0])
    assert torch.equal(rays.rgb[0], torch.from_numpy(view.rgb[0, 0]))
    assert len(training_rays(cat, "test").alpha) == 2 * RES * RES


def test_twins_json_round_trip(tmp_path):
    make_category(tmp_path)
    (tmp_path / "twins").mkdir()
    write_split(tmp_path / "twins" / "a_color", "test", [random_frame(np.random.default_rng(3), 0)])
    Image.fromarray(np.zeros((RES, RES), np.uint8)).save(tmp_path / "twins" / "fg.png")
    spec = TwinSpec("a_color", "color", "a", "train:1", "seat", "#00ff00", "twins/fg.png", "twins/fg.png", "twins/a_color")
    write_twins_json(tmp_path, [spec])
    [(loaded, inst)] = load_twins(tmp_path)
    assert loaded == spec and list(inst.splits) == ["test"] and inst.splits["test"][0].depth is not None
    assert load_twins(tmp_path / "a") == []


# ----------------------------------------------------------------------------- bad input


def _edit_json(path: Path, fn) -> None:
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


def _set_matrix(value):
    return lambda m: m["frames"][1].__setitem__("transform_matrix", value)


def _cmyk(root: Path) -> None:
    Image.new("CMYK", (RES, RES)).save(root / "a" / "train" / "r_001.jpg")
    _edit_json(root / "a" / "transforms_train.json", lambda m: m["frames"][1].__setitem__("file_path", "./train/r_001.jpg"))


def _nan_depth(root: Path) -> None:
    depth = np.ones((RES, RES), np.float32)
    depth[2, 3] = np.nan
    write_exr(root / "a" / "train" / "r_001_depth.exr", {"Z": depth})


TRAIN = "a/transforms_train.json"
BAD_INPUTS = {
    "missing instances.txt": (lambda r: (r / "instances.txt").unlink(), "instances.txt", "not found"),
    "missing instance folder": (lambda r: shutil.rmtree(r / "b"), "instances.txt", "instance folder b"),
    "missing transforms": (lambda r: [(r / "b" / f"transforms_{s}.json").unlink() for s in ("train", "test")], "b", "no transforms"),
    "missing image": (lambda r: (r / "a" / "train" / "r_001.png").unlink(), "a/train/r_001.png", "not found"),
    "malformed json": (lambda r: (r / TRAIN).write_text('{"frames": [}'), TRAIN, "malformed JSON"),
    "matrix not 4x4": (lambda r: _edit_json(r / TRAIN, _set_matrix([[1, 0, 0], [0, 1, 0], [0, 0, 1]])), TRAIN, "4x4"),
    "matrix non-finite": (lambda r: _edit_json(r / TRAIN, _set_matrix([[1, 0, 0, 0]] * 3 + [[0, 0, 0, 1e999]])), TRAIN, "non-finite"),
    "matrix singular": (lambda r: _edit_json(r / TRAIN, _set_matrix([[1, 0, 0, 0]] * 3 + [[0, 0, 0, 1]])), TRAIN, "not invertible"),
    "no camera angle": (lambda r: _edit_json(r / TRAIN, lambda m: m.pop("camera_angle_x")), TRAIN, "camera_angle_x"),
    "camera angle too narrow": (lambda r: _edit_json(r / TRAIN, lambda m: m.__setitem__("camera_angle_x", 1e-30)), TRAIN,
                                "field of view, too narrow to see an object"),
    "wrong mode": (_cmyk, "a/train/r_001.jpg", "mode CMYK"),
    "inconsistent sizes": (
        lambda r: Image.new("RGBA", (RES // 2, RES // 2)).save(r / "a" / "train" / "r_001.png"),
        "a/train/r_001.png",
        "differs",
    ),
    "nan depth": (_nan_depth, "a/train/r_001_depth.exr", "NaN"),
    "empty split": (lambda r: _edit_json(r / TRAIN, lambda m: m.__setitem__("frames", [])), TRAIN, "empty split"),
    "corrupt image": (lambda r: (r / "a" / "train" / "r_001.png").write_bytes(b"not a png"), "a/train/r_001.png", "not a readable image"),
}


def test_instances_txt_saved_with_a_bom_reads_its_names(tmp_path):
    """Windows Notepad's UTF-8 starts the file with a byte-order mark, which was read as part of
    the first name ("instance folder \\ufeffa not found")."""
    make_category(tmp_path)
    (tmp_path / "instances.txt").write_text("a\nb\n", encoding="utf-8-sig")
    assert [i.name for i in load_category(tmp_path).instances] == ["a", "b"]


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_one_line_data_error_naming_the_file(tmp_path, case):
    make_category(tmp_path)
    breaker, file, words = BAD_INPUTS[case]
    breaker(tmp_path)
    with pytest.raises(DataError) as e:
        load_category(tmp_path, with_depth=True, with_parts=True)
    msg = str(e.value)
    assert "\n" not in msg and str(tmp_path / file) in msg and words in msg


def test_unknown_instance_lists_valid_names(tmp_path):
    make_category(tmp_path)
    cat = load_category(tmp_path)
    with pytest.raises(DataError, match=r"unknown instance 'zzz' \(valid: a, b; 2 in all\)"):
        cat.instance("zzz")
    with pytest.raises(DataError, match="out of range"):
        cat.instance(5)
    with pytest.raises(DataError, match="SPLIT:INDEX"):
        cat.instances[0].view("train7")


@pytest.mark.parametrize("case", ["missing instances.txt", "malformed json"])
def test_cli_bad_dataset_exits_2_with_one_line(tmp_path, case):
    make_category(tmp_path)
    BAD_INPUTS[case][0](tmp_path)
    assert_user_error(invoke("dataset", "info", tmp_path), str(tmp_path))


def test_cli_info_json(tmp_path):
    make_category(tmp_path)
    result = invoke("dataset", "info", tmp_path, "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info["instances"] == 2 and info["views"] == {"train": 6, "test": 2} and info["bbox"]["source"] == "depth"
    assert info["fingerprint"] == load_category(tmp_path).fingerprint and info["without_train_views"] == []
    # an instance without train views: counted as 0 per instance, named, and warned about
    name = load_category(tmp_path).names[1]
    (tmp_path / name / "transforms_train.json").unlink()
    info = json.loads(invoke("dataset", "info", tmp_path, "--json").stdout)
    assert info["without_train_views"] == [name] and info["views_per_instance"]["train"][0] == 0
    text = invoke("dataset", "info", tmp_path)
    assert text.exit_code == 0 and f"1 instance without train views ({name})" in text.stderr


def test_unknown_instance_suggests_the_names_it_is_part_of():
    """A name typed short (the end of a long mesh name) or in another case gets a suggestion;
    a name near nothing gets none."""
    from crfedit.names import did_you_mean

    names = ["blendswap_cc_0_armchair", "blendswap_cc_0_chair_with_cushion", "chair_000", "chair_001", "chair_010"]
    assert did_you_mean("chair_with_cushion", names) == "; did you mean 'blendswap_cc_0_chair_with_cushion'?"
    assert did_you_mean("CHAIR_000", names) == "; did you mean 'chair_000'?"
    assert did_you_mean("chair_00", names) == "; did you mean 'chair_000' or 'chair_001'?"
    assert did_you_mean("chair_01", names) == "; did you mean 'chair_010'?"
    for far in ("sofa", "chair_999", "../../etc/passwd", "ch", "chair"):  # "chair" is in five names: no guess
        assert did_you_mean(far, names) == ""


def test_exr_images_are_linear_and_premultiplied(tiny_chairs, tmp_path):
    """An EXR image holds linear light, its colour premultiplied by alpha (OpenEXR; Blender
    writes it so): read as it was, a dataset of them trained 17 dB against its PNG twin's 30 (the
    chair rendered dark).  Converted to the PNG's straight sRGB, its views load as the PNG's."""
    from crfedit.data.format import srgb_from_linear

    root = tmp_path / "exr"
    shutil.copytree(tiny_chairs / "chair_000", root)
    doc = json.loads((root / "transforms_train.json").read_text())
    frame = doc["frames"][0]
    png = root / (frame["file_path"] + ".png")
    rgba = np.asarray(Image.open(png).convert("RGBA"), dtype=np.float64) / 255.0
    srgb = rgba[..., :3]
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    assert np.allclose(srgb_from_linear(linear), srgb, atol=1e-6)  # the transfer function's inverse
    a = rgba[..., 3]
    write_exr(root / (frame["file_path"] + ".exr"), {c: (linear[..., i] * a).astype(np.float32) for i, c in enumerate("RGB")} | {"A": a.astype(np.float32)})
    frame["file_path"] += ".exr"
    (root / "transforms_train.json").write_text(json.dumps(doc))
    from_exr = load_category(root).instances[0].splits["train"][0]
    from_png = load_category(tiny_chairs / "chair_000").instances[0].splits["train"][0]
    assert np.abs(from_exr.rgb - from_png.rgb).max() < 2e-3 and np.abs(from_exr.alpha - from_png.alpha).max() < 1e-6


def test_dataset_info_says_what_train_would(tmp_path):
    """`dataset info` is what a user runs first: it says what train warns of or refuses (an
    instance with far fewer views, poses in OpenCV axes, no alpha), which it printed as a
    clean summary."""
    from crfedit.data.synth import SynthConfig, write_synth_category

    root = tmp_path / "c"
    write_synth_category(root, SynthConfig(instances=2, views=20, res=8, seed=0, twins=False))
    clean = invoke("dataset", "info", root)
    assert clean.exit_code == 0 and clean.stderr == "", clean.stderr
    doc = json.loads((root / "chair_001" / "transforms_train.json").read_text())
    doc["frames"] = doc["frames"][:2]  # 2 training views against 16
    (root / "chair_001" / "transforms_train.json").write_text(json.dumps(doc))
    few = invoke("dataset", "info", root)
    assert few.exit_code == 0 and few.stderr.startswith(f"note: chair_001 (2 views) of {root}: far fewer training views than the others"), few.stderr
    for name in ("chair_000", "chair_001"):  # every instance in OpenCV/COLMAP axes: Y down, Z forward
        doc = json.loads((root / name / "transforms_train.json").read_text())
        for f in doc["frames"]:
            f["transform_matrix"] = (np.array(f["transform_matrix"]) * [1, -1, -1, 1]).tolist()
        (root / name / "transforms_train.json").write_text(json.dumps(doc))
    flipped = invoke("dataset", "info", root)
    assert flipped.exit_code == 0 and "flip the Y and Z axes of OpenCV/COLMAP poses (train refuses the dataset)" in flipped.stderr, flipped.stderr
    assert "instance chair_000 (and 1 of the other 1 instances): its training silhouettes carve an empty visual hull" in flipped.stderr


def test_an_object_a_few_pixels_large_is_named_as_such_not_as_camera_axes():
    """A mesh whose bounding box a stray triangle far away enlarged shows 0–2 pixels a view:
    the hull it carves is empty, and the error named OpenCV camera axes (the dataset was
    crfedit's own renders)."""
    from types import SimpleNamespace as NS

    import torch

    from crfedit.train import check_hulls

    speck = np.zeros((64, 64), np.float32)
    speck[3, 3] = 1.0
    inst = NS(path="p", name="stray", splits={"train": [NS(alpha=speck) for _ in range(5)]})
    with pytest.raises(CrfError, match=r"^p: instance stray: its training views show the object on 1 pixel \(median\), too few"):
        check_hulls(NS(instances=[inst]), torch.zeros(1, 4, 4, 4, dtype=torch.bool))
    big = np.zeros((64, 64), np.float32)
    big[10:40, 10:40] = 1.0
    inst = NS(path="p", name="seen", splits={"train": [NS(alpha=big) for _ in range(5)]})
    with pytest.raises(CrfError, match="poses must use OpenGL/NeRF camera axes"):
        check_hulls(NS(instances=[inst]), torch.zeros(1, 4, 4, 4, dtype=torch.bool))

