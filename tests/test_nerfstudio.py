"""nerfstudio ``transforms.json`` scenes load as categories (issue 18): a fixture converted from
the tiny synthetic category loads with the same cameras and pixels."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from PIL import Image

from crfedit.data import load_category
from crfedit.errors import DataError

from cli_helpers import assert_user_error, invoke


def to_nerfstudio(instance_dir, out, with_mask: bool = False, listed: bool = False):
    """Write ``out/transforms.json`` + images from a NeRF-synthetic instance (train then test frames)."""
    out.mkdir(parents=True)
    frames, splits = [], {"train": [], "test": []}
    for split in ("train", "test"):
        meta = json.loads((instance_dir / f"transforms_{split}.json").read_text())
        for f in meta["frames"]:
            src = instance_dir / (f["file_path"] + ".png")
            name = f"images/{split}_{src.stem}.png"
            (out / "images").mkdir(exist_ok=True)
            frame = {"file_path": name, "transform_matrix": f["transform_matrix"]}
            if with_mask:
                rgba = np.asarray(Image.open(src).convert("RGBA"))
                Image.fromarray(rgba[..., :3]).save(out / name)
                (out / "masks").mkdir(exist_ok=True)
                Image.fromarray(((rgba[..., 3] > 0) * 255).astype(np.uint8)).save(out / f"masks/{split}_{src.stem}.png")
                frame["mask_path"] = f"masks/{split}_{src.stem}.png"
            else:
                shutil.copy(src, out / name)
            frames.append(frame)
            splits[split].append(name)
    w = Image.open(out / frames[0]["file_path"]).width
    fl = 0.5 * w / math.tan(0.5 * meta["camera_angle_x"])
    doc = {"camera_model": "OPENCV", "fl_x": fl, "fl_y": fl, "cx": w / 2, "cy": w / 2, "w": w, "h": w,
           "k1": 0, "k2": 0, "p1": 0, "p2": 0, "frames": frames}
    if listed:
        doc.update(train_filenames=splits["train"], test_filenames=splits["test"])
    (out / "transforms.json").write_text(json.dumps(doc))


def test_a_scene_loads_as_a_one_instance_category(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "scene", listed=True)
    cat = load_category(tmp_path / "scene")
    ref = load_category(tiny_chairs).instances[0]
    assert cat.names == ["scene"] and set(cat.instances[0].splits) == {"train", "test"}
    for split in ("train", "test"):
        ours, theirs = cat.instances[0].splits[split], ref.splits[split]
        assert len(ours) == len(theirs)
        for a, b in zip(ours, theirs):
            assert np.array_equal(a.camera.c2w, b.camera.c2w) and a.camera.focal == pytest.approx(b.camera.focal, rel=1e-9)
            assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.alpha, b.alpha)


def test_a_folder_of_scenes_is_a_category_with_masks_and_default_split(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "cat" / "a", with_mask=True)
    to_nerfstudio(tiny_chairs / "chair_001", tmp_path / "cat" / "b")
    cat = load_category(tmp_path / "cat", res=8)
    assert cat.names == ["a", "b"] and len(cat.fingerprint) == 16
    views = cat.instances[0].splits
    n = sum(len(v) for v in views.values())
    assert n < 10 and [len(views["train"]), len(views["test"])] == [n - 1, 1]  # every 10th frame, at least one
    assert views["train"][0].rgb.shape == (8, 8, 3)
    full = load_category(tmp_path / "cat").instances[0].splits["train"][0]
    assert set(np.unique(full.alpha)) <= {0.0, 1.0} and full.alpha.any() and not full.alpha.all()
    r = invoke("train", tmp_path / "cat", "--out", tmp_path / "m.safetensors", "--steps", "2", "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 0 and "trained 2 instances" in r.stdout, r.output


def test_unsupported_cameras_are_refused(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "s")
    doc = json.loads((tmp_path / "s" / "transforms.json").read_text())
    for change, fragment in (({"k1": 0.1}, "distortion"), ({"cx": 2.0}, "principal point"), ({"fl_y": 99.0}, "fl_x"),
                             ({"fl_x": 1e12, "fl_y": 1e12}, r"fl_x 1e\+12 for an image 16 pixels wide gives a 9\.17e-10° field of view, too narrow")):
        (tmp_path / "s" / "transforms.json").write_text(json.dumps({**doc, **change}))
        with pytest.raises(DataError, match=fragment):
            load_category(tmp_path / "s")


def test_an_empty_visual_hull_is_refused_before_training(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "opencv")
    doc = json.loads((tmp_path / "opencv" / "transforms.json").read_text())
    for f in doc["frames"]:  # OpenCV/COLMAP axes: Y down, Z forward
        f["transform_matrix"] = (np.array(f["transform_matrix"]) * [1, -1, -1, 1]).tolist()
    (tmp_path / "opencv" / "transforms.json").write_text(json.dumps(doc))
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "clear")
    for png in (tmp_path / "clear" / "images").iterdir():
        rgba = np.asarray(Image.open(png)).copy()
        rgba[..., 3] = 0
        Image.fromarray(rgba).save(png)
    for scene, fragment in (("opencv", "flip the Y and Z axes"), ("clear", "alpha (or mask) is 0")):
        out = tmp_path / f"{scene}.safetensors"
        r = invoke("train", tmp_path / scene, "--out", out, "--steps", 2, "--set", "rays=64", "--device", "cpu")
        assert_user_error(r, f"instance {scene}:", fragment)
        assert not out.exists()


def test_split_lists_match_as_nerfstudio_does(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "s", listed=True)
    path = tmp_path / "s" / "transforms.json"
    doc = json.loads(path.read_text())
    n_train, n_test = len(doc["train_filenames"]), len(doc["test_filenames"])
    path.write_text(json.dumps({**doc, "test_filenames": ["./" + f for f in doc["test_filenames"]]}))
    cat = load_category(tmp_path / "s")
    assert [len(cat.instances[0].splits[s]) for s in ("train", "test")] == [n_train, n_test] and cat.notes == ()
    path.write_text(json.dumps({**doc, "test_filenames": ["images/nope.png"]}))
    with pytest.raises(DataError, match="test_filenames lists 'images/nope.png', which is no frame's file_path"):
        load_category(tmp_path / "s")
    path.write_text(json.dumps({**doc, "train_filenames": doc["train_filenames"][:2], "test_filenames": []}))
    cat = load_category(tmp_path / "s")  # frames in no list are left out, not trained on
    assert set(cat.instances[0].splits) == {"train"} and len(cat.instances[0].splits["train"]) == 2
    assert len(cat.notes) == 1 and f"{n_train + n_test - 2} frames in none of train_filenames, test_filenames left out" in cat.notes[0]
    r = invoke("dataset", "info", tmp_path / "s")
    assert r.exit_code == 0 and r.stderr.startswith("note: ") and "left out" in r.stderr, r.output


def test_camera_angle_x_stands_for_the_intrinsics_and_strings_are_refused(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "s")
    path = tmp_path / "s" / "transforms.json"
    doc = json.loads(path.read_text())
    ref = load_category(tmp_path / "s").instances[0].splits["train"][0].camera
    angle = 2 * math.atan(0.5 * doc["w"] / doc["fl_x"])
    path.write_text(json.dumps({**{k: v for k, v in doc.items() if k not in ("fl_x", "fl_y", "cx", "cy", "w", "h")}, "camera_angle_x": angle}))
    assert load_category(tmp_path / "s").instances[0].splits["train"][0].camera.focal == pytest.approx(ref.focal, rel=1e-9)
    path.write_text(json.dumps({**doc, "fl_x": str(doc["fl_x"])}))
    with pytest.raises(DataError, match="fl_x '.*' must be a number"):
        load_category(tmp_path / "s")


def test_sub_folders_that_are_no_scenes_are_named_in_a_note(tiny_chairs, tmp_path):
    to_nerfstudio(tiny_chairs / "chair_000", tmp_path / "cat" / "a")
    shutil.copytree(tiny_chairs / "chair_001", tmp_path / "cat" / "b_blender")
    (tmp_path / "cat" / ".cache").mkdir()
    cat = load_category(tmp_path / "cat")
    assert cat.names == ["a"] and cat.notes == (f"{tmp_path / 'cat'}: sub-folder without transforms.json skipped: b_blender",)
