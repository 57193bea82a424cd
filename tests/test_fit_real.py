"""``fit-real``: a new instance fitted to one photo of a chair the model never saw.

Fixture: 4 procedural chairs × 8 views at 24×24; the model trains on the first 3 for 150 steps
and chair_003 is held out.  Its train:0 image plays the photo.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from crfedit import occupancy
from crfedit.cameras import Camera, look_at, spherical_eye
from crfedit.config import make_config
from crfedit.data.synth import SynthConfig
from crfedit.delta import apply_edit_files, read_delta
from crfedit.fit_real import (
    JOINT,
    FitOptions,
    center_crop,
    check_new_name,
    fit_real,
    joint_prefixes,
    photo_hull,
    prepare_photo,
    read_photo,
)
from crfedit.errors import CrfError
from crfedit.field import ConditionalRadianceField
from crfedit.metrics import psnr
from crfedit.model import CategoryModel, load_model
from crfedit.renderer import render_camera

from cli_helpers import assert_user_error, invoke

RES = 24
HELD_OUT = 3


@pytest.fixture(scope="module")
def setup(trained_category):
    """(model file, model, held-out chair's data): 3 of 4 chairs trained for 300 steps, a few seconds."""
    path, model, category, _ = trained_category(
        "fit_real", SynthConfig(instances=4, views=8, res=RES, seed=0, twins=False), dict(
            steps=300, rays=256, lr=2e-2, lr_codes=2e-2, grid_res=16, occ_res=16, occ_warmup=50, checkpoint_every=10**9,
        ), n_train=HELD_OUT)
    return path, model, category.instances[HELD_OUT]


def photo_of(view):
    """The dataset view as a photo (RGBA: its alpha marks the object)."""
    return prepare_photo(np.concatenate([view.rgb, view.alpha[..., None]], axis=-1), None, view.camera.width, view.camera.height)


def mean_psnr(model, k: int, views) -> float:
    field = model.field_for(k)
    return float(np.mean([float(psnr(render_camera(field, v.camera, k).rgb, torch.from_numpy(v.rgb))) for v in views]))


FAST = FitOptions(steps_codes=150, steps_joint=30)


@pytest.fixture(scope="module")
def fitted(setup):
    _, model, held = setup
    view = held.splits["train"][0]
    return fit_real(model, photo_of(view), view.camera, "real", FAST)


# ----------------------------------------------------------------------------- fitting


def test_fit_beats_the_mean_code_at_other_views(setup, fitted):
    _, model, held = setup
    view = held.splits["train"][0]
    others = held.splits["val"] + held.splits["test"]  # views the fit never saw
    start = fit_real(model, photo_of(view), view.camera, "mean", FitOptions(steps_codes=0, steps_joint=0, start="mean"))
    k = fitted.instance
    assert k == len(model.names) and fitted.model.names[k] == "real"
    mean_score, fit_score = mean_psnr(start.model, k, others), mean_psnr(fitted.model, k, others)
    assert fit_score > mean_score + 1.0, (mean_score, fit_score)
    stages = {s.stage: s for s in fitted.stages}
    assert list(stages) == ["codes", "joint", "final"]
    # the codes alone fit the photo better (the tiny 24×24 fixture gains about 1 dB; the bar leaves margin)
    assert stages["codes"].psnr > start.stages[0].psnr + 0.5
    assert stages["joint"].psnr > stages["codes"].psnr  # opening the weights fits it better still
    assert abs(stages["final"].psnr - stages["joint"].psnr) < 0.5  # the refreshed grid keeps the look


def depth_spread(model, k: int, camera: Camera) -> float:
    """The photo's rays' mean compositing-weighted standard deviation of depth, in world units:
    how far along each ray the fitted surface is spread."""
    from crfedit.cameras import rays_from_camera
    from crfedit.renderer import render_rays

    out = render_rays(model.field_for(k), rays_from_camera(camera), k, distortion=True)
    return float(out.distortion[out.opacity > 0.5].mean().detach())  # the renderer's own measure of spread


def test_the_distortion_loss_gathers_the_fit_into_a_surface(setup, fitted):
    """One photo leaves depth free: without the distortion term the density spreads along the
    photo's rays (a recolour's selection then misses much of what the scribble shows)."""
    _, model, held = setup
    view = held.splits["train"][0]
    assert FAST.distortion > 0 and json.loads(fitted.meta["hyperparameters"])["distortion"] == FAST.distortion
    fits = {lam: fit_real(model, photo_of(view), view.camera, "real", dataclasses.replace(FAST, distortion=lam)) for lam in (0.0, 1.0)}
    spread = {lam: depth_spread(f.model, f.instance, view.camera) for lam, f in fits.items()}
    assert spread[1.0] < 0.8 * spread[0.0], spread  # the tiny fixture's 16³ cells already bound the spread at 0.1
    assert fits[1.0].stages[-1].psnr > fits[0.0].stages[-1].psnr - 1.0  # at little cost to the photo
    with pytest.raises(CrfError, match="--distortion"):
        FitOptions(distortion=float("nan")).validated()


def test_base_model_untouched_and_other_instances_identical(setup, fitted):
    path, model, _ = setup
    fresh, _ = load_model(path)
    assert model.fingerprint() == fresh.fingerprint() and model.names == fresh.names and not model.overrides
    view = fresh.views["test"].cameras(0)[0]
    for k in range(len(model.names)):
        # equal up to float rounding: the code tables gained a row, so their matmuls run one row longer
        torch.testing.assert_close(render_camera(fitted.model.field_for(k), view, k).rgb, render_camera(model.field, view, k).rgb, rtol=0, atol=1e-5)


def test_delta_adds_the_instance_and_reapplies_bit_identically(setup, fitted, tmp_path):
    path, _, held = setup
    out = tmp_path / "real.safetensors"
    fitted.save(out, command="test")
    delta = read_delta(out)
    assert delta.kind == "fit-real" and delta.meta["adds_instance"] == "real" == delta.instance
    heads = {n for n, _ in ConditionalRadianceField(fitted.model.cfg, 1).named_parameters() if n.startswith(JOINT["heads"])}
    assert set(delta.tensors) == heads | {"shape_code", "color_code", "occupancy"}
    assert [s["stage"] for s in json.loads(delta.meta["stages"])] == ["codes", "joint", "final"]
    model, _ = load_model(path)
    camera = held.splits["test"][0].camera
    a, b = apply_edit_files(model, [out]), apply_edit_files(model, [out])
    k = a.instance_index("real")
    ra, rb = render_camera(a.field_for(k), camera, k).rgb, render_camera(b.field_for(k), camera, k).rgb
    assert torch.equal(ra, rb)
    assert torch.equal(ra, render_camera(fitted.model.field_for(k), camera, k).rgb)  # what fit_real returned
    assert torch.equal(a.field_for(k).occupancy[k], fitted.model.field_for(k).occupancy[k])
    assert torch.equal(delta.tensors["occupancy"], a.field_for(k).occupancy[k].to(torch.int8) - 1)  # from the all-occupied row


def test_codes_only_stores_no_weights(setup):
    _, model, held = setup
    view = held.splits["train"][0]
    result = fit_real(model, photo_of(view), view.camera, "codes_only", FitOptions(steps_codes=5, steps_joint=0))
    assert set(result.tensors) == {"shape_code", "color_code", "occupancy"}
    assert [s.stage for s in result.stages] == ["codes", "final"]
    # --start mean: from the mean code of the training instances
    start = fit_real(model, photo_of(view), view.camera, "mean", FitOptions(steps_codes=0, steps_joint=0, start="mean"))
    torch.testing.assert_close(start.tensors["shape_code"], model.field.shape_codes.detach().mean(0), rtol=0, atol=1e-6)


def test_hull_is_the_carved_union_dilated(setup):
    _, model, held = setup
    view = held.splits["train"][0]
    photo = photo_of(view)
    hull = photo_hull(model, view.camera, photo.mask)
    union = model.field.occupancy.any(0)
    carved = occupancy.carve_visual_hull([view.camera], [photo.mask], model.field.aabb, model.cfg.occ_res, margin=0)
    assert torch.equal(hull, occupancy.dilate(union & carved, 1))
    assert 0 < int(hull.sum()) < int(occupancy.dilate(union, 1).sum())  # the silhouette carved something
    empty = np.zeros_like(photo.mask)
    empty[0, 0] = True  # a silhouette of one corner pixel sees no chair
    with pytest.raises(CrfError, match="covers no occupied cell"):
        photo_hull(model, view.camera, empty)


def test_joint_prefixes_match_parameters():
    fast = ConditionalRadianceField(make_config("fast", overrides=dict(grid_res=4, occ_res=8)), 2)
    assert joint_prefixes(fast, "heads") == ("F_fuse.", "F_dens.", "F_rad.")
    assert joint_prefixes(fast, "all") == tuple(p for p in JOINT["all"] if p != "coarse.")
    paper = ConditionalRadianceField(make_config("paper", overrides=dict(width=8, rad_width=8, share_layers=1, inst_layers=1, fuse_layers=1)), 2)
    for weights, prefixes in JOINT.items():
        assert joint_prefixes(paper, weights) == prefixes  # every prefix names parameters
    names = [n for n, _ in paper.named_parameters()]
    covered = {n for n in names if n.startswith(JOINT["all"])}
    assert covered == set(names) - {"shape_codes", "color_codes"}


def test_paper_preset_fits_both_networks_without_a_grid():
    cfg = make_config("paper", overrides=dict(
        width=8, rad_width=8, share_layers=1, inst_layers=1, fuse_layers=1, n_coarse=8, n_fine=8, pe_x=2, pe_d=1,
    ))
    torch.manual_seed(0)
    model = CategoryModel(ConditionalRadianceField(cfg, 2), ["a", "b"])
    camera = Camera(look_at(spherical_eye(30.0, 20.0, 2.0)), 10.0, 8, 8)
    photo = prepare_photo(np.full((8, 8, 3), 0.5, np.float32), None, 8, 8)
    result = fit_real(model, photo, camera, "c", FitOptions(steps_codes=2, steps_joint=2, rays=16))
    names = {n for n, _ in model.field.named_parameters() if n.startswith(JOINT["heads"])}
    assert any(n.startswith("coarse.F_rad.") for n in names)
    assert set(result.tensors) == names | {"shape_code", "color_code"}  # no occupancy: the sampler ignores it
    assert result.model.names == ["a", "b", "c"]


# ----------------------------------------------------------------------------- the photo


def test_center_crop_and_area_resize():
    image = np.zeros((30, 40, 3), np.float32)
    image[:, :5] = 0.25
    cropped = center_crop(image, 1.0)
    assert cropped.shape == (30, 30, 3) and not (cropped == 0.25).any()
    assert center_crop(np.zeros((40, 30, 3)), 1.0).shape == (30, 30, 3)
    # a 4x4 photo, left half object (red), right half transparent -> 2x2: red | white
    rgba = np.zeros((4, 4, 4), np.float32)
    rgba[:, :2] = (1.0, 0.0, 0.0, 1.0)
    rgba[:, 2:] = (0.0, 0.0, 0.0, 0.0)
    photo = prepare_photo(rgba, None, 2, 2)
    np.testing.assert_allclose(photo.rgb[:, 0], [[1, 0, 0]] * 2)
    np.testing.assert_allclose(photo.rgb[:, 1], [[1, 1, 1]] * 2)
    np.testing.assert_allclose(photo.alpha, [[1, 0], [1, 0]])
    # area filter: a pixel half covered blends with white, and still counts for the silhouette
    half = prepare_photo(rgba[:, 1:3], None, 1, 1)
    np.testing.assert_allclose(half.rgb[0, 0], [1.0, 0.5, 0.5], atol=1e-6)
    assert half.mask.all()
    # a mask replaces the alpha channel
    masked = prepare_photo(rgba, np.ones((4, 4), bool), 2, 2)
    np.testing.assert_allclose(masked.rgb[:, 1], [[0, 0, 0]] * 2)


def test_a_faint_alpha_halo_is_not_the_object_and_a_crop_that_cuts_most_of_it_is_refused():
    """A resampled photo's halo of alpha 1–7/255 around the object is not the object (counted,
    it started a tester's fit from another chair); an alpha of 0.1 still is (a thin leg area-
    resized).  A centre crop that drops over half of the object is refused, naming the crop."""
    rgba = np.zeros((8, 8, 4), np.float32)
    rgba[2:6, 2:6] = (0.2, 0.3, 0.4, 1.0)
    rgba[1, 1:7, 3] = rgba[6, 1:7, 3] = 3 / 255  # the halo
    rgba[2:6, 6, 3] = 0.1  # a faint but real edge
    photo = prepare_photo(rgba, None, 8, 8)
    expected = np.zeros((8, 8), bool)
    expected[2:6, 2:7] = True
    assert (photo.mask == expected).all()
    halo = rgba.copy()
    halo[..., 3] = np.minimum(halo[..., 3], 4 / 255)
    with pytest.raises(CrfError, match="no pixel's alpha is above 0.05: a faint halo"):
        prepare_photo(halo, None, 8, 8)
    wide = np.zeros((8, 32, 4), np.float32)
    wide[2:6, 1:11] = (0.2, 0.3, 0.4, 1.0)  # columns 1..10; the crop keeps 12..19: all of it goes
    with pytest.raises(CrfError, match="cuts off 100% of the object's pixels: crop the photo around the object first"):
        prepare_photo(wide, None, 8, 8, "p.png")
    wide[2:6, 10:16] = 1.0  # now 4 of 15 columns in the crop: 73% goes, still refused
    with pytest.raises(CrfError, match="cuts off 73%"):
        prepare_photo(wide, None, 8, 8)
    wide[2:6, 1:8, 3] = 0.0  # columns 8..15: half in the crop, the warning's case (photo_warnings), not refused
    assert prepare_photo(wide, None, 8, 8).mask.sum() == 16


def test_photo_warnings_name_a_background_fitted_as_the_object_and_an_upscaled_photo():
    from crfedit.fit_real import photo_warnings

    on_white = np.ones((64, 64, 3), np.float32)
    on_white[20:40, 20:40] = 0.3
    assert photo_warnings(on_white, None, 64, 64) == []
    on_black = np.where(on_white > 0.5, 0.0, on_white).astype(np.float32)
    [line] = photo_warnings(on_black, None, 64, 64)
    assert "no alpha channel and no --mask" in line and "border is not white (mean 0.00;" in line
    assert photo_warnings(on_black, on_black[..., 0] > 0.1, 64, 64) == []  # a mask says what the object is
    with_alpha = np.concatenate([on_black, (on_white[..., :1] < 0.5).astype(np.float32)], axis=-1)
    assert photo_warnings(with_alpha, None, 64, 64) == []
    opaque = np.concatenate([on_black, np.ones((64, 64, 1), np.float32)], axis=-1)  # an editor's RGBA: outlines nothing
    assert len(photo_warnings(opaque, None, 64, 64)) == 1
    grey = np.where(on_white > 0.5, 0.92, on_white).astype(np.float32)  # light grey, but no white: no outline, so a warning
    assert len(photo_warnings(grey, None, 64, 64)) == 1
    [line] = photo_warnings(on_white[:8, :8], None, 64, 64)
    assert "gives 8x8 pixels for the 64x64 view: it is upscaled" in line
    assert photo_warnings(np.ones((48, 200, 3), np.float32), None, 32, 32) == []  # a wide photo crops to 48x48
    # an object off the centre of a wide photo: the centre crop cuts it, and says by how much
    wide = np.ones((64, 128, 3), np.float32)
    wide[20:40, 20:52] = 0.3  # columns 20..51; the crop keeps 32..95, so 12 of 32 columns go
    [line] = photo_warnings(wide, None, 64, 64)
    assert line == ("the centre crop to the view's 64:64 aspect cuts off 38% of the object's pixels: "
                    "crop the photo around the object first"), line
    assert photo_warnings(np.roll(wide, 30, axis=1), None, 64, 64) == []  # centred: all of it stays
    assert len(photo_warnings(np.ones_like(wide), wide[..., 0] < 0.5, 64, 64)) == 1  # the mask's outline is judged alike


def test_a_photo_on_white_takes_its_outline_from_the_white_around_it(setup):
    """No alpha, no mask: the white background connected to the border is not the object, a
    white part the object encloses is; a photo with no white border stays whole."""
    _, _, held = setup
    view = held.splits["train"][0]
    on_white = view.rgb * view.alpha[..., None] + (1.0 - view.alpha[..., None])  # RGB, no alpha
    photo = prepare_photo(on_white.astype(np.float32), None, RES, RES)
    assert photo.silhouette == "white background"
    assert photo.mask[view.alpha >= 0.5].all() and not photo.mask[view.alpha == 0].any()  # faint edges may go either way
    ring = np.ones((9, 9, 3), np.float32)
    ring[2:7, 2:7] = 0.2
    ring[4, 4] = 1.0  # white, but enclosed by the dark square
    outline = prepare_photo(ring, None, 9, 9)
    assert outline.silhouette == "white background" and outline.mask.sum() == 25 and outline.mask[4, 4]
    grey = prepare_photo(np.full((6, 6, 3), 0.5, np.float32), None, 6, 6)
    assert grey.silhouette == "whole photo" and grey.mask.all()
    rgba = np.concatenate([on_white, view.alpha[..., None]], axis=-1).astype(np.float32)
    assert prepare_photo(rgba, None, RES, RES).silhouette == "alpha"
    opaque = np.concatenate([on_white, np.ones_like(view.alpha[..., None])], axis=-1).astype(np.float32)
    assert prepare_photo(opaque, None, RES, RES).silhouette == "white background"  # alpha 1 everywhere outlines nothing
    with pytest.raises(CrfError, match="white all over at the view's size: no object to fit"):
        prepare_photo(np.full((8, 8, 3), 0.97, np.float32), None, 8, 8)
    beside = np.ones((8, 24, 3), np.float32)
    beside[2:6, 1:5] = 0.2  # a dark object at the left of a wide white photo: the centre crop (columns 8..15) misses it
    with pytest.raises(CrfError, match=r"the centre crop to the view's 8:8 aspect leaves none of the object, which lies beside it"):
        prepare_photo(beside, None, 8, 8)


def test_a_nan_pose_is_named_as_the_camera_not_as_a_silhouette_off_the_object(setup):
    _, model, held = setup
    view = held.splits["train"][0]
    c2w = view.camera.c2w.copy()
    c2w[0, 0] = np.nan
    with pytest.raises(CrfError, match="^camera: c2w has non-finite values$"):
        fit_real(model, photo_of(view), Camera(c2w, view.camera.focal, view.camera.width, view.camera.height), "x", FitOptions(steps_codes=1, steps_joint=0))


def test_read_photo_with_mask_file(tmp_path):
    rgb = np.full((6, 8, 3), 80, np.uint8)
    Image.fromarray(rgb).save(tmp_path / "p.jpg")
    mask = np.zeros((6, 8), np.uint8)
    mask[2:4, 3:5] = 255
    Image.fromarray(mask).save(tmp_path / "m.png")
    image, m = read_photo(tmp_path / "p.jpg", tmp_path / "m.png")
    assert image.shape == (6, 8, 3) and m.sum() == 4 and m[2:4, 3:5].all()
    transparent = np.zeros((6, 8, 4), np.uint8)
    transparent[1, 1] = (0, 0, 0, 255)  # a black stroke on a transparent layer: alpha decides
    Image.fromarray(transparent).save(tmp_path / "t.png")
    assert read_photo(tmp_path / "p.jpg", tmp_path / "t.png")[1].sum() == 1


def test_check_new_name(setup):
    _, model, _ = setup
    assert check_new_name(model, "my_chair") == "my_chair"
    for bad, fragment in (("chair_000", "already has"), ("7", "not be a number"), ("", "non-empty"), (" x", "non-empty")):
        with pytest.raises(CrfError, match=fragment):
            check_new_name(model, bad)
    import dataclasses

    with_cafe = dataclasses.replace(model, names=[*model.names, "caf\u00e9"])  # é as one code point
    with pytest.raises(CrfError, match="already has an instance of that name .*other Unicode code points"):
        check_new_name(with_cafe, "cafe\u0301")  # e and a combining accent: the same name to a reader


# ----------------------------------------------------------------------------- the command


def test_a_camera_file_of_another_size_is_fitted_at_the_model_s_size_and_says_so(setup, tmp_path):
    """A --pose camera JSON that declares 2× the model's size: the fit runs at the model's
    training size (the photo area-resized to it, the focal scaled), as before, and a note says
    so (the declared size was dropped without a word)."""
    path, _, held = setup
    model, _ = load_model(path)
    cam = model.views["train"].cameras(0)[0]
    (tmp_path / "cam.json").write_text(json.dumps({"transform_matrix": cam.c2w.tolist(), "camera_angle_x": cam.camera_angle_x,
                                                   "width": 2 * cam.width, "height": 2 * cam.height}))
    photo = tmp_path / "p.png"
    shutil.copy(held.path / "train" / "r_000.png", photo)
    result = invoke("fit-real", path, photo, "--pose", tmp_path / "cam.json", "--out", tmp_path / "f.safetensors",
                    "--steps-codes", 1, "--steps-joint", 1, "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert (f"note: --pose {tmp_path / 'cam.json'}: a {2 * cam.width}x{2 * cam.height} camera; fit-real fits at the model's "
            f"training size, {cam.width}x{cam.height} (focal scaled with it)") in result.stderr, result.stderr
    recorded = json.loads(read_delta(tmp_path / "f.safetensors").meta["hyperparameters"])["camera"]
    assert (recorded["width"], recorded["height"]) == (cam.width, cam.height) and recorded["focal"] == pytest.approx(cam.focal)


def test_fit_real_command_then_render_and_edit(setup, tmp_path):
    path, _, held = setup
    photo = tmp_path / "my_chair.png"
    shutil.copy(held.path / "train" / "r_000.png", photo)
    out = tmp_path / "real.safetensors"
    result = invoke("fit-real", path, photo, "--pose", "train:0", "--out", out, "--steps-codes", 4, "--steps-joint", 2, "--device", "cpu")
    assert result.exit_code == 0, result.output
    for stage in ("codes", "joint", "final"):
        assert any(line.startswith(stage) and "PSNR" in line for line in result.stdout.splitlines()), result.stdout
    assert "adding instance my_chair" in result.stdout
    delta = read_delta(out)
    assert delta.meta["pose"] == "train:0 of chair_000" and delta.meta["photo"] == str(photo)  # --pose-instance's default, 0
    shown = invoke("edits", "show", out).stdout.splitlines()  # the record fit-real.md points to, in the text view too
    assert f"photo         {photo}" in shown and "pose          train:0 of chair_000" in shown
    assert [ln.split(",")[0] for ln in shown if ln.startswith("stage ")] == [f"stage         stage={s}" for s in ("codes", "joint", "final")]
    as_json = json.loads(invoke("edits", "show", out, "--json").stdout)["metadata"]
    assert isinstance(as_json["stages"], list) and as_json["photo_psnr"] == float(delta.meta["photo_psnr"])
    # --json: stdout is the written file's record, as every edit command's (the stage lines go to stderr)
    again = invoke("fit-real", path, photo, "--pose", "train:0", "--out", tmp_path / "j.safetensors", "--steps-codes", 4,
                   "--steps-joint", 2, "--device", "cpu", "--json")
    assert again.exit_code == 0 and "adding instance my_chair" in again.stderr, again.output
    assert json.loads(again.stdout) == json.loads(invoke("edits", "show", tmp_path / "j.safetensors", "--json").stdout)
    rendered = invoke("render", path, "--instance", "my_chair", "--edit", out, "--views", "orbit:2", "--out", tmp_path / "r", "--device", "cpu")
    assert rendered.exit_code == 0, rendered.output
    assert (tmp_path / "r" / "0001.png").is_file()
    # from the photo's own camera: --views photo reads it from the fit-real edit
    assert_user_error(invoke("render", path, "--instance", "my_chair", "--edit", out, "--views", "test", "--out", tmp_path / "t"), "with --views photo")
    shown = invoke("render", path, "--instance", "my_chair", "--edit", out, "--views", "photo", "--out", tmp_path / "p", "--device", "cpu")
    assert shown.exit_code == 0, shown.output
    fitted, _ = load_model(path)
    fitted = apply_edit_files(fitted, [out])
    k = fitted.instance_index("my_chair")
    expected = render_camera(fitted.field_for(k), fitted.views["train"].cameras(0)[0], k).rgb.clamp(0, 1).numpy()
    got = np.asarray(Image.open(tmp_path / "p" / "0000.png"), dtype=np.float64) / 255.0
    assert got.shape == expected.shape and np.abs(got - expected).max() <= 1.0 / 255 + 1e-6
    assert json.loads((tmp_path / "p" / "views.json").read_text())["views"][0]["view"] == "photo"
    assert_user_error(invoke("render", path, "--instance", 0, "--edit", out, "--views", "photo", "--out", tmp_path / "q"),
                      "was not added by a fit-real edit")
    # its record without a camera (a version-3 file edited by hand): said to be unreadable, not "not added by a fit-real"
    import crfedit.delta as delta_file

    d = delta_file.read_delta(out)
    hyper = {k: v for k, v in json.loads(d.meta["hyperparameters"]).items() if k != "camera"}
    meta = {**d.meta, "version": "3", "hyperparameters": json.dumps(hyper)}
    meta["fingerprint"] = delta_file.delta_fingerprint(d.tensors, meta)
    (tmp_path / "nocam.safetensors").write_bytes(delta_file.delta_bytes(d.tensors, meta))
    assert_user_error(invoke("render", path, "--instance", "my_chair", "--edit", tmp_path / "nocam.safetensors", "--views", "photo",
                             "--out", tmp_path / "nc"), "the record of my_chair's photo camera cannot be read")
    # a model that baked the fit keeps the photo's camera: the same render without the edit
    assert invoke("edits", "bake", path, "--edit", out, "--out", tmp_path / "baked.safetensors").exit_code == 0
    again = invoke("render", tmp_path / "baked.safetensors", "--instance", "my_chair", "--views", "photo", "--out", tmp_path / "pb", "--device", "cpu")
    assert again.exit_code == 0 and (tmp_path / "pb" / "0000.png").read_bytes() == (tmp_path / "p" / "0000.png").read_bytes(), again.output
    # the photo's view is a view spec of every command: scribble on it, preview from it
    opacity = render_camera(fitted.field_for(k), fitted.views["train"].cameras(0)[0], k).opacity.numpy()
    scribble = tmp_path / "scribble.png"
    Image.fromarray(((opacity > 0.5) * 255).astype(np.uint8)).save(scribble)
    recoloured = invoke("edit-color", path, "--instance", "my_chair", "--edit", out, "--view", "photo", "--scribble", scribble,
                        "--color", "red", "--out", tmp_path / "red.safetensors", "--steps", 2, "--preview", tmp_path / "rp",
                        "--views", "photo", "--device", "cpu")
    assert recoloured.exit_code == 0 and (tmp_path / "rp" / "0000.png").is_file(), recoloured.output
    moved = tmp_path / "t.safetensors"
    transferred = invoke("transfer", path, "--instance", "my_chair", "--color-from", "chair_001", "--edit", out, "--out", moved, "--device", "cpu")
    assert transferred.exit_code == 0, transferred.output
    assert invoke("edits", "check", path, "--edit", out, "--edit", moved).exit_code == 0


def test_fit_real_does_not_import_the_compiler(setup, tmp_path):
    """`crfedit fit-real` in a fresh interpreter leaves torch._dynamo unimported (torch.optim's
    first use imports it: 0.75–0.9 s of a 15–30 s fit)."""
    import subprocess
    import sys

    path, _, held = setup
    probe = "import sys, torch; print('torch._dynamo' in sys.modules)"
    if subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True).stdout.strip() != "False":
        pytest.skip("this torch imports torch._dynamo with torch itself")
    args = [str(path), str(held.path / "train" / "r_000.png"), "--pose", "train:0", "--out", str(tmp_path / "f.safetensors"),
            "--steps-codes", "3", "--steps-joint", "2", "--device", "cpu"]
    script = f"""
import sys
from typer.testing import CliRunner
from crfedit.cli import app
result = CliRunner().invoke(app, ["fit-real", *{args!r}])
assert result.exit_code == 0, result.output
print('torch._dynamo' in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "False" and (tmp_path / "f.safetensors").is_file()


def test_fit_real_command_errors_write_nothing(setup, tmp_path):
    path, _, held = setup
    photo = tmp_path / "p.png"
    shutil.copy(held.path / "train" / "r_000.png", photo)
    clash = tmp_path / "chair_002.png"
    shutil.copy(photo, clash)
    out = tmp_path / "e.safetensors"
    (tmp_path / "junk.png").write_bytes(b"not an image")
    Image.fromarray(np.zeros((RES, RES), np.uint8)).save(tmp_path / "black.png")
    Image.fromarray(np.full((RES + 1, RES), 255, np.uint8)).save(tmp_path / "big.png")
    Image.fromarray(np.zeros((RES, RES, 4), np.uint8)).save(tmp_path / "clear.png")
    (tmp_path / "cam.json").write_text('{"transform_matrix": [[1, 0], [0, 1]], "camera_angle_x": 0.7}')
    (tmp_path / "broken.json").write_text('{"transform_matrix": ')
    base = ("fit-real", path)
    cases = [
        ((tmp_path / "junk.png", "--pose", "train:0"), ("junk.png", "not a readable image")),
        ((tmp_path / "missing.png", "--pose", "train:0"), ("missing.png", "not found")),
        ((tmp_path / "clear.png", "--pose", "train:0"), ("clear.png", "mask is empty")),
        ((photo, "--pose", "train:0", "--mask", tmp_path / "black.png"), ("black.png", "mask is empty")),
        ((photo, "--pose", "train:0", "--mask", tmp_path / "big.png"), ("big.png", f"{RES}x{RES + 1}", f"{RES}x{RES}")),
        ((photo, "--pose", tmp_path / "cam.json"), ("cam.json", "transform_matrix")),
        ((photo, "--pose", tmp_path / "broken.json"), ("broken.json", "malformed JSON")),
        ((photo, "--pose", "train:0-1"), ("--pose", "2 views")),
        ((photo, "--pose", "train:0", "--name", "chair_001"), ("chair_001", "already has")),
        ((clash, "--pose", "train:0"), ("chair_002", "photo's file name", "--name")),
        ((photo, "--pose", "train:0", "--steps-codes", -1), ("--steps-codes",)),
        ((photo, "--pose", "train:0", "--pose-instance", "nope"), ("nope",)),
    ]
    for args, fragments in cases:
        assert_user_error(invoke(*base, *args, "--out", out, "--device", "cpu"), *fragments)
        assert not out.exists() and not list(tmp_path.glob(".e.safetensors*"))


def test_a_nearest_start_takes_the_best_matching_instance(setup):
    """``start="nearest"``: a photo of a training chair (its own view) ranks that chair first by
    outline IoU, and the fit starts from its codes inside the grids of the best matches (not
    every training grid); a start it does not know is one line."""
    from crfedit.fit_real import NEAREST_GRIDS, outline_ranking

    _, model, _ = setup
    k = 1
    view = model.views["train"].cameras(k)[0]
    photo_mask = render_camera(model.field_for(k), view, k).opacity.numpy() > 0.5
    ranking = outline_ranking(model, view, photo_mask)
    assert ranking[0] == (1.0, k) and len(ranking) == len(model.names)
    rgb = render_camera(model.field_for(k), view, k).rgb.numpy()
    photo = prepare_photo(np.concatenate([rgb, photo_mask[..., None].astype(np.float32)], axis=-1), None, view.width, view.height)
    start = fit_real(model, photo, view, "again", FitOptions(steps_codes=0, steps_joint=0, start="nearest"))
    j = start.instance
    hyper = json.loads(start.meta["hyperparameters"])
    assert hyper["start"] == "nearest" and hyper["init"] == f"{model.names[k]}'s codes (outline IoU 1.000)"
    assert hyper["grids"] == [model.names[i] for _, i in ranking[:NEAREST_GRIDS]]
    assert torch.equal(start.model.field_for(j).shape_codes[j], model.field.shape_codes[k])  # no steps: the chair's own code
    mean = fit_real(model, photo, view, "again", FitOptions(steps_codes=0, steps_joint=0, start="mean"))
    assert start.stages[-1].psnr > mean.stages[-1].psnr + 1.0, (start.stages[-1].psnr, mean.stages[-1].psnr)
    with pytest.raises(CrfError, match="--start middle: expected one of nearest, mean, nearest-codes"):
        FitOptions(start="middle").validated()


def test_an_outline_no_training_chair_matches_is_warned_of(setup, tmp_path):
    """The nearest start ranks the training chairs by how well their outline from --pose matches
    the photo's; a best IoU under OUTLINE_WARN (a chair off the photo's centre, a wrong pose) is
    said, since the fit then starts from a poor match."""
    from crfedit.fit_real import OUTLINE_WARN

    path, _, held = setup
    rgba = np.asarray(Image.open(held.path / "train" / "r_000.png").convert("RGBA"))
    base = ("fit-real", path)
    for name, image in (("centred", rgba), ("shifted", np.roll(rgba, (RES // 4, RES // 4), axis=(0, 1)))):
        Image.fromarray(image).save(tmp_path / f"{name}.png")
        r = invoke(*base, tmp_path / f"{name}.png", "--pose", "train:0", "--pose-instance", "0", "--steps-codes", 1, "--steps-joint", 0,
                   "--out", tmp_path / f"{name}.safetensors", "--device", "cpu")
        assert r.exit_code == 0, r.output
        iou = json.loads(read_delta(tmp_path / f"{name}.safetensors").meta["hyperparameters"])["outline_iou"]
        assert ("no training instance's outline from the pose matches the photo's well" in r.stderr) == (iou < OUTLINE_WARN), (name, iou, r.stderr)
        if name == "shifted":
            assert iou < OUTLINE_WARN, iou
