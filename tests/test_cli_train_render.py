"""``crfedit train``, ``info``, ``render`` end to end on a tiny category (2 chairs × 6 views, 16×16)."""

from __future__ import annotations

import contextlib
import json
import re
import shutil
from pathlib import Path

import numpy as np

from crfedit.preview import depth_preview, turbo
import pytest
import torch

import crfedit.train
from crfedit.data.loading import load_category
from crfedit.delta import apply_edit_files, read_delta, save_delta
from crfedit.errors import CrfError
from crfedit.evaluation import held_out_split, render_views, score_model
from crfedit.io import read_exr, read_image
from crfedit.model import load_model
from crfedit.modelfile import model_info, stored_training
from crfedit.render_files import render_to_folder
from crfedit.video import write_video
from crfedit.views import resolve_views

from cli_helpers import assert_user_error, invoke

TINY = ["--device", "cpu", "--set", "rays=256", "--set", "occ_res=16", "--set", "grid_res=16"]


@pytest.fixture(scope="module")
def data(tiny_chairs) -> Path:
    return tiny_chairs


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory) -> tuple[Path, str]:
    """(model file, stdout) of ``crfedit train``."""
    out = tmp_path_factory.mktemp("cli") / "model.safetensors"
    result = invoke("train", data, "--out", out, "--steps", 30, *TINY)
    assert result.exit_code == 0, result.output
    assert "held-out val (2 views): PSNR" in result.stdout
    assert "trained 2 instances for 30 steps" in result.stdout
    assert f"CPU threads: {torch.get_num_threads()}\n" in result.stdout  # what it computes with
    assert json.loads(out.with_name("model.run.json").read_text())["threads"] == torch.get_num_threads()
    return out, result.stdout


@pytest.fixture(scope="module")
def model_path(trained) -> Path:
    return trained[0]


def test_training_written_to_a_file_prints_progress_lines(data, tmp_path, monkeypatch):
    """Not a terminal (CliRunner's output, like `2> train.log`): plain progress lines while it
    trains, not only the bar's last state at the end, on stderr: stdout keeps the results."""
    from crfedit.cli.train import TrainProgress

    monkeypatch.setattr(TrainProgress, "LINE_SECONDS", 0.0)
    result = invoke("train", data, "--out", tmp_path / "m.safetensors", "--steps", 6, *TINY)
    assert result.exit_code == 0, result.output
    line = re.compile(r"\s*(\d+)/6  loss (\S+)  PSNR +(\S+)  \S+ rays/s  \d+:\d\d:\d\d  ETA \d+:\d\d:\d\d")
    lines = [m for m in map(line.fullmatch, result.stderr.splitlines()) if m]
    assert [int(m[1]) for m in lines] == [1, 2, 3, 4, 5, 6], result.stderr
    assert lines[0][2] == "-" and float(lines[-1][2]) > 0 and float(lines[-1][3]) > 0, result.stderr  # loss read out by the end
    assert not any(map(line.fullmatch, result.stdout.splitlines())) and "━" not in result.stdout


def test_training_end_score_is_score_model_on_val(trained, data):
    model, _ = load_model(trained[0])
    category = load_category(data)
    assert held_out_split(category, "val") == "val"
    score = score_model(model, category, "val", max_views=model.cfg.eval_views)
    assert f"held-out val ({score['n']} views): PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.3f}\n" in trained[1]


def test_stored_training_reads_the_header(model_path):
    model, _ = load_model(model_path)
    stored = stored_training(model_path)
    cfg, step, sizes = stored.cfg, stored.step, stored.sizes
    assert cfg == model.cfg and step == 30
    assert stored.dataset == model.dataset_fingerprint and stored.elapsed > 0 and stored.minutes is None
    assert sizes == {split: [t.width, t.height] for split, t in model.views.items()} and sizes["train"] == [16, 16]


def test_train_writes_a_loadable_model(model_path, data):
    model, state = load_model(model_path)
    assert model.names == ["chair_000", "chair_001"]
    assert model.meta["step"] == "30" and model.meta["command"].startswith("crfedit")  # sys.argv: pytest here
    assert model.cfg.rays == 256 and model.cfg.occ_res == 16 and model.cfg.steps == 30
    assert set(model.views) == {"train", "val", "test"} and model.views["train"].width == 16
    assert int(state["step"]) == 30


@contextlib.contextmanager
def interrupted_at(stop: int):
    """Within the block, training raises KeyboardInterrupt (Ctrl-C) right after step ``stop``."""
    real_train = crfedit.train.train

    def interrupted(*a, on_step=None, **kw):
        def hook(step, *rest):
            on_step(step, *rest)
            if step == stop:
                raise KeyboardInterrupt

        return real_train(*a, on_step=hook, **kw)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(crfedit.train, "train", interrupted)
        yield


def test_resume_after_an_interrupt_is_bit_identical(data, tmp_path):
    """Ctrl-C at step 11 writes a step-11 checkpoint; --resume must then reach exactly the
    weights, optimizer moments and sampler state of an uninterrupted run.  Occupancy refreshes
    (every 3 steps from step 3) fall on both sides of the interruption."""
    args = ["--steps", 20, "--seed", 5, *TINY, "--set", "checkpoint_every=10", "--set", "occ_warmup=3", "--set", "occ_every=3"]
    full, part = tmp_path / "full.safetensors", tmp_path / "part.safetensors"
    assert invoke("train", data, "--out", full, *args).exit_code == 0

    with interrupted_at(11):
        result = invoke("train", data, "--out", part, *args)
    assert result.exit_code == 130 and "interrupted: checkpoint at step 11" in result.stderr
    assert load_model(part)[0].meta["step"] == "11" and load_model(part)[0].meta["seed"] == "5"
    other_seed = [*args[:2], "--seed", 6, *args[4:]]  # the run goes on with its own seed, and says so
    result = invoke("train", data, "--out", part, *other_seed, "--resume")
    assert result.exit_code == 0, result.output
    assert "ignored: seed 6 (stored 5)" in result.stderr, result.stderr

    (a, state_a), (b, state_b) = load_model(full), load_model(part)
    assert b.meta["step"] == "20"
    differ = [k for k, v in a.state().items() if not torch.equal(v, b.state()[k])]
    assert not differ, f"weights differ after resume: {differ}"
    differ = [k for k, v in state_a.items() if k != "elapsed" and not torch.equal(v, state_b[k])]
    assert not differ, f"training state differs after resume: {differ}"
    assert a.fingerprint() == b.fingerprint()


def test_resume_keeps_the_first_start_in_the_run_record(data, tmp_path):
    """After an interrupted run is resumed, run.json still names the command that began the run
    and lists the resume; resuming the finished run changes nothing."""
    out = tmp_path / "m.safetensors"
    with interrupted_at(6):
        assert invoke("train", data, "--out", out, "--steps", 12, "--log-every", 2, *TINY).exit_code == 130
    first = json.loads((tmp_path / "m.run.json").read_text())
    now = torch.get_num_threads()
    first["threads"] = now + 1  # as if the run had begun at another thread count: the resume says what that costs
    (tmp_path / "m.run.json").write_text(json.dumps(first))
    result = invoke("train", data, "--out", out, "--resume", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert (f"note: this run trained with {now + 1} CPU threads and goes on with {now}: the same seed gives the same model only "
            f"at one thread count throughout (CRFEDIT_THREADS={now + 1} keeps it)") in result.stderr, result.stderr
    record = json.loads((tmp_path / "m.run.json").read_text())
    assert record["command"] == first["command"] and record["config"] == first["config"]
    assert [r["resumed_at"] for r in record["resumes"]] == [6]  # (the command is sys.argv: pytest's here)
    # the resume keeps the run's --log-every (it fell back to 100: rows at 2, 4, 6, then 12 only)
    steps = [int(row.split(",")[0]) for row in (tmp_path / "m.log.csv").read_text().splitlines()[1:]]
    assert steps == [2, 4, 6, 8, 10, 12] and [r["log_every"] for r in record["resumes"]] == [2], steps
    before = (out.read_bytes(), (tmp_path / "m.run.json").read_bytes(), (tmp_path / "m.log.csv").read_bytes())
    again = invoke("train", data, "--out", out, "--resume", "--device", "cpu")
    assert again.exit_code == 0 and "is trained to step 12 of 12: nothing to resume" in again.stdout, again.output
    assert before == (out.read_bytes(), (tmp_path / "m.run.json").read_bytes(), (tmp_path / "m.log.csv").read_bytes())


def test_resume_keeps_the_time_budget(data, tmp_path):
    """A run that ended on its --minutes is finished for --resume without --minutes (the header
    keeps the budget, so the learning-rate schedule is not restarted by steps); a larger
    --minutes trains on."""
    out = tmp_path / "m.safetensors"
    assert invoke("train", data, "--out", out, "--steps", 100000, "--minutes", 0.01, *TINY).exit_code == 0
    stored = stored_training(out)
    elapsed, step = stored.elapsed, stored.step
    assert stored.minutes == 0.01 and elapsed >= 0.6 and 0 < step < 100000
    before = out.read_bytes()
    again = invoke("train", data, "--out", out, "--resume", "--device", "cpu")
    assert again.exit_code == 0, again.output
    assert "with its time budget, --minutes 0.01" in again.stderr
    assert f"has trained its --minutes 0.01 ({elapsed:.0f} s, step {step} of 100000): nothing to resume" in again.stdout
    assert out.read_bytes() == before
    more = invoke("train", data, "--out", out, "--resume", "--minutes", 0.03, "--device", "cpu")
    assert more.exit_code == 0, more.output
    assert stored_training(out).step > step and stored_training(out).minutes == 0.03


def test_resume_errors(data, model_path, tmp_path):
    assert_user_error(invoke("train", data, "--out", tmp_path / "none.safetensors", "--resume", *TINY), "--resume", "does not exist")
    assert_user_error(invoke("train", data, "--out", model_path, "--resume", "--res", 8, *TINY), "trained at width 16")


def test_render_files_sizes_depth_and_determinism(model_path, tmp_path):
    out = tmp_path / "deep" / "renders"  # created with its parents
    result = invoke("render", model_path, "--instance", "chair_001", "--views", "orbit:3", "--res", 12, "--out", out, "--depth", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "rendered 3 views of chair_001 at 12x12" in result.stdout and "s per view" in result.stdout
    assert "note:" not in result.stderr  # narrower than the training views: nothing to say
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"{i:04d}{tail}" for i in range(3) for tail in (".png", "_depth.exr", "_depth.png")] + ["views.json"]

    model, _ = load_model(model_path)
    cams = [cam for _, cam in resolve_views("orbit:3", model, 1, res=12)]
    refs = render_views(model, 1, cams)
    for i, ref in enumerate(refs):
        image = read_image(out / f"{i:04d}.png")
        assert image.shape == (12, 12, 3)
        # the reference quantized as write_png does (in float64: a float32 product can land on x.5)
        np.testing.assert_array_equal(np.round(image * 255), np.round(ref.rgb.clamp(0, 1).numpy().astype(np.float64) * 255))
        exr = read_exr(out / f"{i:04d}_depth.exr")
        assert set(exr) == {"Z", "A"} and exr["Z"].dtype == np.float32 and exr["Z"].shape == (12, 12)
        z, a = exr["Z"], exr["A"]
        np.testing.assert_array_equal(a, ref.opacity.clamp(0, 1).numpy())  # Σw can round past 1: A stays in [0, 1]
        assert (a > 0.5).any() and a.max() <= 1
        assert np.isfinite(z[a > 1e-3]).all() and (z[a > 1e-3] > 0).all()
        assert np.isposinf(z[a <= 1e-3]).all()
        hit = a > 1e-3
        np.testing.assert_allclose(z[hit] * a[hit], ref.depth.numpy()[hit], rtol=1e-5)
        preview = read_image(out / f"{i:04d}_depth.png")
        np.testing.assert_array_equal(np.round(preview * 255), np.round(depth_preview(z, a) * 255))
        assert (preview[a < 0.5] == 1.0).all() and (preview[a >= 0.5] < 1.0).any(axis=-1).all()
    listed = json.loads((out / "views.json").read_text())
    assert [v["view"] for v in listed["views"]] == ["orbit:3@30:0", "orbit:3@30:1", "orbit:3@30:2"] and listed["instance"] == "chair_001"
    # what the views are of: the model file, its --edit stack, swapped codes and --res (a swapped render looked plain)
    assert {k: listed[k] for k in ("model", "edits", "res", "shape_from", "color_from")} == {
        "model": str(model_path), "edits": [], "res": 12, "shape_from": None, "color_from": None}

    again = tmp_path / "again"
    # the same device as the first run: on a machine with a GPU, auto would render on it
    assert invoke("render", model_path, "--instance", "1", "--views", "orbit:3", "--res", 12, "--out", again, "--depth", "--device", "cpu").exit_code == 0
    for name in names:
        if name.endswith(".exr"):
            for channel, values in read_exr(out / name).items():
                np.testing.assert_array_equal(values, read_exr(again / name)[channel])
        else:
            assert (out / name).read_bytes() == (again / name).read_bytes(), name
    # the views.json passed back as the view spec renders the same cameras, each at its recorded size
    replay = tmp_path / "replay"
    assert invoke("render", model_path, "--instance", "1", "--views", out / "views.json", "--out", replay, "--device", "cpu").exit_code == 0
    for i in range(3):
        assert (replay / f"{i:04d}.png").read_bytes() == (out / f"{i:04d}.png").read_bytes()
    assert [v["view"] for v in json.loads((replay / "views.json").read_text())["views"]] == [f"views.json:{i}" for i in range(3)]
    # a label is a spec of its view: views.json:2 picks that one (its frame, byte for byte)
    assert invoke("render", model_path, "--instance", "1", "--views", f"{out / 'views.json'}:2", "--out", tmp_path / "one", "--device", "cpu").exit_code == 0
    assert (tmp_path / "one" / "0000.png").read_bytes() == (out / "0002.png").read_bytes()
    assert_user_error(invoke("render", model_path, "--instance", "1", "--views", f"{out / 'views.json'}:5", "--out", tmp_path / "x"), "index 5 out of range (0-2)")
    # a camera of the file too far to render: refused before the first view, naming the view (the line named none)
    far = json.loads((out / "views.json").read_text())
    far["views"][1]["transform_matrix"][0][3] = 1e7
    (tmp_path / "far.json").write_text(json.dumps(far))
    line = assert_user_error(invoke("render", model_path, "--instance", "1", "--views", tmp_path / "far.json", "--out", tmp_path / "far",
                                    "--device", "cpu"), "scene-box diagonals from the scene")
    assert line.startswith("error: view far.json:1: it lies ") and not (tmp_path / "far").exists(), line
    # a camera turned away from the chair renders blank: said, naming the view (a 3.1-radian view did it silently)
    away = json.loads((out / "views.json").read_text())
    m = np.array(away["views"][2]["transform_matrix"])
    m[:3, :3] = m[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # half a turn about its up axis: still rigid
    away["views"][2]["transform_matrix"] = m.tolist()
    (tmp_path / "away.json").write_text(json.dumps(away))
    result = invoke("render", model_path, "--instance", "1", "--views", tmp_path / "away.json", "--out", tmp_path / "away", "--device", "cpu")
    assert result.exit_code == 0 and result.stderr.splitlines() == [
        "note: 1 of the 3 views show nothing of chair_001 (away.json:2): a camera looking away from it, inside it, too far from it, "
        "or with so wide a field of view that it covers no pixel"], result.stderr
    assert "blank" not in (tmp_path / "away" / "views.json").read_text()
    # wider than the model was trained at: said, since the render holds no finer detail
    wide = model.views["train"].width + 4
    result = invoke("render", model_path, "--instance", "1", "--views", "test:0", "--res", wide, "--out", tmp_path / "wide", "--device", "cpu")
    assert result.exit_code == 0 and result.stderr.splitlines() == [
        f"note: views {wide} pixels wide are wider than the {wide - 4}-pixel views the model was trained on: "
        "the rays are denser, but the field holds no finer detail than it learned"], result.stderr


def test_render_to_folder_library(model_path, tmp_path):
    model, _ = load_model(model_path)
    out = tmp_path / "frames"
    result = render_to_folder(model, 0, "orbit:2", out, res=8, video=tmp_path / "turn.gif")
    assert (result.count, result.width, result.height, result.video) == (2, 8, 8, tmp_path / "turn.gif")
    refs = render_views(model, 0, [cam for _, cam in resolve_views("orbit:2", model, 0, res=8)])
    for i, ref in enumerate(refs):
        np.testing.assert_array_equal(np.round(read_image(out / f"{i:04d}.png") * 255), np.round(ref.rgb.clamp(0, 1).numpy() * 255))
    assert result.video.stat().st_size > 0
    with pytest.raises(CrfError, match="exists and is not a folder"):
        render_to_folder(model, 0, "orbit:2", tmp_path / "turn.gif")


def test_a_render_that_fails_part_way_leaves_none_of_its_frames(model_path, tmp_path, monkeypatch):
    """A full disk at the third frame: the two frames written are removed again, the folder's
    other files stay; a bad --fps fails before the first frame."""
    import errno

    import crfedit.render_files as render_files

    model, _ = load_model(model_path)
    out = tmp_path / "frames"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    real, calls = render_files.write_png, []

    def write_png(path, image):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, image)

    monkeypatch.setattr(render_files, "write_png", write_png)
    with pytest.raises(OSError):
        render_to_folder(model, 0, "orbit:4", out, res=8)
    assert len(calls) == 3 and sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    monkeypatch.setattr(render_files, "write_png", real)
    for fps in ("0", "nan", "300", "0.001"):  # 0.001: past a GIF's longest frame delay (an OverflowError)
        assert_user_error(invoke("render", model_path, "--instance", 0, "--views", "orbit:2", "--fps", fps,
                                 "--video", tmp_path / "t.gif", "--out", tmp_path / "r"), "--fps", "must be from 0.01 (100 s a frame) to 240")
        assert not (tmp_path / "r").exists() and not (tmp_path / "t.gif").exists()


def test_render_split_views_at_stored_size_and_gif(model_path, tmp_path):
    out = tmp_path / "r"
    result = invoke("render", model_path, "--instance", 0, "--views", "train:0-2", "--out", out, "--video", tmp_path / "t.gif")
    assert result.exit_code == 0, result.output
    assert read_image(out / "0002.png").shape == (16, 16, 3) and not (out / "0003.png").exists()
    # the default 12 fps is 8.33 hundredths of a second a frame: the GIF stores 8, and says so
    assert f"wrote GIF {tmp_path / 't.gif'} at 12.5 fps (a GIF's frame time is whole hundredths of a second; --fps 12 asked)" in result.stdout
    from PIL import Image

    with Image.open(tmp_path / "t.gif") as gif:
        assert gif.n_frames == 3 and gif.size == (16, 16) and gif.info["duration"] == 80
    result = invoke("render", model_path, "--instance", 0, "--views", "train:0-2", "--out", out, "--video", tmp_path / "t.gif", "--fps", 20)
    assert result.exit_code == 0 and f"wrote GIF {tmp_path / 't.gif'}\n" in result.stdout  # 5 hundredths: as asked
    with Image.open(tmp_path / "t.gif") as gif:
        assert gif.info["duration"] == 50


def test_video_falls_back_to_gif_without_imageio_ffmpeg(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails
    frames = [np.full((5, 7, 3), k / 4, dtype=np.float32) for k in range(4)]
    assert write_video(tmp_path / "v.mp4", frames) == tmp_path / "v.gif"
    assert (tmp_path / "v.gif").is_file() and not (tmp_path / "v.mp4").exists()


def test_render_refuses_a_gif_fallback_over_an_existing_gif(model_path, tmp_path, monkeypatch):
    """--video v.mp4 without the extra writes v.gif: a file the user did not name, so an existing
    one is refused before any rendering (naming v.gif replaces it)."""
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    (tmp_path / "v.gif").write_bytes(b"GIF89a mine")
    result = invoke("render", model_path, "--instance", 0, "--views", "test", "--out", tmp_path / "r", "--video", tmp_path / "v.mp4")
    assert_user_error(result, "v.gif, which exists already", f"--video {tmp_path / 'v.gif'}")
    assert (tmp_path / "v.gif").read_bytes() == b"GIF89a mine" and not (tmp_path / "r").exists()
    result = invoke("render", model_path, "--instance", 0, "--views", "test", "--out", tmp_path / "r", "--video", tmp_path / "v.gif")
    assert result.exit_code == 0 and (tmp_path / "v.gif").read_bytes()[:6] == b"GIF89a" and len((tmp_path / "v.gif").read_bytes()) > 11


@pytest.mark.skipif(not __import__("crfedit.video").video.mp4_available(), reason="imageio-ffmpeg is not installed")
def test_video_mp4(tmp_path):
    frames = [np.full((5, 7, 3), k / 4, dtype=np.float32) for k in range(4)]
    assert write_video(tmp_path / "v.mp4", frames) == tmp_path / "v.mp4"
    assert (tmp_path / "v.mp4").read_bytes()[4:8] == b"ftyp"


def test_render_with_swapped_codes_differs(model_path, tmp_path):
    pytest.importorskip("crfedit.edit.transfer")
    plain, swapped = tmp_path / "plain", tmp_path / "swapped"
    assert invoke("render", model_path, "--instance", 0, "--views", "test", "--out", plain).exit_code == 0
    result = invoke("render", model_path, "--instance", 0, "--views", "test", "--out", swapped, "--color-from", "chair_001")
    assert result.exit_code == 0, result.output
    assert (plain / "0000.png").read_bytes() != (swapped / "0000.png").read_bytes()
    assert_user_error(invoke("render", model_path, "--instance", 0, "--views", "test", "--out", swapped, "--shape-from", "nope"), "nope")
    own = tmp_path / "own"  # the instance's own codes: the plain render, not a transfer's error
    result = invoke("render", model_path, "--instance", 0, "--views", "test", "--out", own, "--shape-from", 0, "--color-from", "chair_000")
    assert result.exit_code == 0, result.output
    assert (own / "0000.png").read_bytes() == (plain / "0000.png").read_bytes()


def test_render_with_missing_edit_file(model_path, tmp_path):
    pytest.importorskip("crfedit.delta")
    result = invoke("render", model_path, "--instance", 0, "--views", "test", "--out", tmp_path / "r", "--edit", tmp_path / "none.safetensors")
    assert_user_error(result, "none.safetensors")


def test_info_json_and_text(model_path):
    result = invoke("info", model_path, "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info == model_info(model_path)
    model, _ = load_model(model_path)
    assert info["instances"] == 2 and info["names"] == model.names and info["preset"] == "fast" and info["arch"] == "ours"
    # the synthetic dataset has part maps and depth, so `train` also trained the part head F_part
    assert list(info["modules"]) == ["F_share", "F_inst", "F_fuse", "F_dens", "bottleneck", "F_rad", "shape_codes", "color_codes", "F_part"]
    assert info["modules"]["F_part"] == {"params": 64 * 16 + 16, "bytes": (64 * 16 + 16) * 4}
    assert info["parameters"] == sum(p.numel() for p in model.field.parameters())
    assert info["modules"]["shape_codes"] == {"params": 2 * 32, "bytes": 2 * 32 * 4}
    assert info["fingerprint"] == model.fingerprint() and info["dataset_fingerprint"] == model.dataset_fingerprint
    assert info["step"] == 30 and 0 < info["occupancy"]["mean_fill"] <= 1
    text = invoke("info", model_path)
    assert text.exit_code == 0 and "F_rad" in text.stdout and model.fingerprint() in text.stdout


def test_user_errors_exit_2(data, model_path, tmp_path):
    def render(*extra):
        return invoke("render", model_path, "--out", tmp_path / "r", *extra)

    assert_user_error(render("--instance", "chair_999", "--views", "test"), "unknown instance 'chair_999'")
    # the dataset where the model goes (arguments swapped): the line says which comes first
    assert_user_error(invoke("eval", "recon", data, model_path), "is a folder, not a file; it is a dataset: the model file (.safetensors) comes first")
    # an instance given to another option is named by it (the line named only the value)
    line = assert_user_error(render("--instance", "0", "--views", "test", "--color-from", "chair_999"), "unknown instance 'chair_999'")
    assert line.startswith("error: --color-from: "), line
    assert_user_error(render("--instance", "7", "--views", "test"), "instance 7: out of range")
    assert_user_error(render("--instance", "0", "--views", "tset:1"), "'tset:1'")
    assert_user_error(render("--instance", "0", "--views", "test:5"), "'test:5'", "out of range")
    assert_user_error(render("--instance", "0", "--views", "test", "--res", "0"), "--res 0")
    assert_user_error(render("--instance", "0", "--views", "test", "--chunk", "0"), "--chunk 0")
    assert_user_error(render("--instance", "0", "--views", "test", "--video", tmp_path / "v.avi"), ".mp4 or .gif")
    (tmp_path / "file").write_text("x")
    assert_user_error(invoke("render", model_path, "--instance", 0, "--views", "test", "--out", tmp_path / "file"), "not a folder")
    assert_user_error(invoke("render", tmp_path / "nope.safetensors", "--instance", 0, "--views", "test", "--out", tmp_path / "r"), "not found")
    assert_user_error(invoke("info", tmp_path / "file"), "not a safetensors file")

    out = tmp_path / "m.safetensors"
    assert_user_error(invoke("train", data, "--out", out, "--steps", 0, *TINY), "--steps 0")
    assert_user_error(invoke("train", data, "--out", out, "--res", -4, *TINY), "--res -4")
    assert_user_error(invoke("train", data, "--out", out, "--minutes", 0, *TINY), "--minutes 0")
    assert_user_error(invoke("train", tmp_path / "no-such-data", "--out", out, *TINY), "no-such-data", "not found")
    (tmp_path / "plain").write_text("x")
    assert_user_error(invoke("train", data, "--out", tmp_path / "plain" / "m.safetensors", *TINY), "is a file, not a folder")
    assert_user_error(invoke("train", data, "--out", tmp_path, *TINY), "is a folder")
    assert_user_error(invoke("train", data, "--out", out, "--set", "bogus=1", *TINY), "--set bogus=1")
    assert not out.exists()


def test_quickstart_end_to_end(tmp_path):
    out = tmp_path / "qs"
    result = invoke("quickstart", "--out", out, "--minutes", 0.02, "--instances", 1, "--res", 16, "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "held-out test (5 views): PSNR" in result.stdout
    assert sorted(p.name for p in (out / "turntable").glob("*.png")) == [f"{i:04d}.png" for i in range(24)]
    assert (out / "turntable.gif").is_file() and load_model(out / "model.safetensors")[0].names == ["chair_000"]
    score = json.loads((out / "score.json").read_text())
    assert score["split"] == "test" and score["n"] == 5 and set(score["instances"]) == {"chair_000"}
    # step 5: chair 0's recolour and removal from the dataset's scribbles, each a delta of the model
    model = load_model(out / "model.safetensors")[0]
    assert [(e["kind"], e["twin"]) for e in score["edits"]] == [("color", "chair_000_color"), ("remove", "chair_000_remove")]
    camera = load_category(out / "data").instance("chair_000").view("test:0").camera
    before = render_views(model, 0, [camera])[0].rgb
    for e in score["edits"]:
        assert Path(e["delta"]) == out / "edits" / f"{e['twin']}.safetensors"
        edited = apply_edit_files(model, [e["delta"]])
        assert not torch.equal(render_views(edited, 0, [camera])[0].rgb, before)
        assert e["psnr"] > 0 and e["psnr_before"] > 0 and e["psnr_ceiling"] > 0
        # a model of a few seconds' training may render the source no closer than unedited: no gap
        gap = "n/a" if e["gap_closed"] is None else f"{e['gap_closed']:.2f}"
        assert (e["gap_closed"] is None) == (e["psnr_ceiling"] - e["psnr_before"] <= 1e-9)
        assert f"chair_000's {e['part']}: closes {gap} of the PSNR gap" in result.stdout
    # an edit that ends below the unedited chair is said to be worse than none (a one-minute model's recolour closed -0.01)
    worse = sum(e["gap_closed"] is not None and e["gap_closed"] < 0 for e in score["edits"])
    assert result.stdout.count("worse than no edit: a model of ") == worse
    import importlib.util

    assert ("needs pip install -e '.[ui]'" in result.stdout) == (importlib.util.find_spec("aiohttp") is None)
    # two rows (recolour, removal) of the scribbled view + two test views × (before, after, twin), 16 px × 3
    assert read_image(out / "edits" / "edits.png").shape[:2] == (2 * (48 + 16 + 6) + 6, 6 + 6 * 54 + 2 * 18 + 48 + 6)
    # run again into the folder, without edits: the earlier run's edits (made for the model it
    # replaced) and their picture go, with a note; a file of the user's stays
    (out / "edits" / "mine.txt").write_text("notes")
    mine = out / "edits" / "my_edit.safetensors"  # the user's own edit of the earlier model: it stays
    shutil.copy(out / "edits" / "chair_000_color.safetensors", mine)
    delta = read_delta(mine)
    save_delta(mine, delta.tensors, {k: v for k, v in delta.meta.items() if k != "made_by"})
    again = invoke("quickstart", "--out", out, "--minutes", 0.01, "--instances", 1, "--res", 16, "--no-edits", "--device", "cpu")
    assert again.exit_code == 0 and "an earlier quickstart's, made for another model" in again.stderr, again.output
    assert sorted(p.name for p in (out / "edits").iterdir()) == ["mine.txt", "my_edit.safetensors"]
    plain = tmp_path / "plain"
    result = invoke("quickstart", "--out", plain, "--minutes", 0.01, "--instances", 1, "--res", 8, "--no-edits", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "4/4 scoring" in result.stdout and "edits" not in json.loads((plain / "score.json").read_text())
    assert not (plain / "edits").exists() and not (plain / "data" / "twins.json").exists()
    # at 8 px the twins' keep strokes vanish under the scribble: the edits are skipped, said why, and nothing else fails
    small = tmp_path / "small"
    result = invoke("quickstart", "--out", small, "--minutes", 0.01, "--instances", 1, "--res", 8, "--device", "cpu")
    assert result.exit_code == 0, result.output
    skipped = json.loads((small / "score.json").read_text())["edits_skipped"]
    assert "keep mask" in skipped and f"edits      skipped: {skipped}" in result.stdout and "edits" not in json.loads((small / "score.json").read_text())
    (tmp_path / "file").write_text("x")
    assert_user_error(invoke("quickstart", "--out", tmp_path / "file"), "not a folder")


def test_quickstart_keeps_the_edits_it_could_make(tmp_path, monkeypatch):
    """One twin's edit failing as a user error (here: the removal, made to fail) skips that
    twin alone: the recolour is still saved, scored and drawn, and the skip is said."""
    import crfedit.evaluation as evaluation

    apply = evaluation.apply_twin_edit

    def removal_fails(model, case, options, *args, **kwargs):
        if case.spec.kind == "remove":
            raise CrfError("the scribble lies on the background only")
        return apply(model, case, options, *args, **kwargs)

    monkeypatch.setattr(evaluation, "apply_twin_edit", removal_fails)
    out = tmp_path / "qs"
    result = invoke("quickstart", "--out", out, "--minutes", 0.01, "--instances", 1, "--res", 16, "--device", "cpu")
    assert result.exit_code == 0, result.output
    score = json.loads((out / "score.json").read_text())
    assert [e["twin"] for e in score["edits"]] == ["chair_000_color"]
    assert score["edits_skipped"] == "chair_000_remove: the scribble lies on the background only"
    assert f"edits      skipped: {score['edits_skipped']}" in result.stdout and f"recolour   chair_000's {score['edits'][0]['part']}: closes" in result.stdout
    assert (out / "edits" / "chair_000_color.safetensors").is_file() and not (out / "edits" / "chair_000_remove.safetensors").exists()
    assert read_image(out / "edits" / "edits.png").shape[:2] == (48 + 16 + 6 + 6, 6 + 6 * 54 + 2 * 18 + 48 + 6)
    assert_user_error(invoke("quickstart", "--out", out, "--minutes", -1), "--minutes -1")


def test_depth_preview_colours_near_red_far_blue():
    depth = np.array([[1.0, 2.0, 3.0, np.inf]])
    opacity = np.array([[1.0, 1.0, 0.9, 0.0]])
    rgb = depth_preview(depth, opacity)
    assert np.allclose(rgb[0, 0], turbo(1.0)) and np.allclose(rgb[0, 2], turbo(0.0)) and (rgb[0, 3] == 1).all()
    assert rgb[0, 0, 0] > 2 * rgb[0, 0, 2] and turbo(0.15)[2] > 2 * turbo(0.15)[0]  # near is red, far is blue
    assert turbo(0.5)[1] > 0.95 and turbo(0.5)[1] > turbo(0.5)[0] > turbo(0.5)[2]  # green-yellow middle


def test_a_render_refuses_to_write_over_files_no_render_listed(model_path, tmp_path):
    """A user's photo named 0000.png (or notes in a views.json of their own) in --out was
    replaced by the render without a word; with no earlier render's record listing it, the
    render refuses and the file stays."""
    for name, data in (("0000.png", b"my photo"), ("views.json", b'{"my": "notes"}'), ("0001_depth.png", b"mine")):
        out = tmp_path / name.replace(".", "_")
        out.mkdir()
        (out / name).write_bytes(data)
        done = invoke("render", model_path, "--instance", 0, "--views", "orbit:2", "--depth", "--out", out, "--device", "cpu")
        assert_user_error(done, f"holds {name}, which no earlier render listed and this one would write over")
        assert (out / name).read_bytes() == data


def test_a_render_into_a_used_folder_leaves_one_set_of_frames(model_path, tmp_path):
    """The frames an earlier render listed in views.json and this one does not write again go;
    files crfedit did not list stay.  A --video beside --out's new folder is fine."""
    out = tmp_path / "r" / "s"
    first = invoke("render", model_path, "--instance", 0, "--views", "orbit:4", "--out", out, "--depth",
                   "--video", tmp_path / "r" / "s.gif", "--device", "cpu")
    assert first.exit_code == 0 and (tmp_path / "r" / "s.gif").is_file(), first.output
    (out / "notes.txt").write_text("mine")
    (out / "0009.png").write_bytes(b"not listed")
    again = invoke("render", model_path, "--instance", 0, "--views", "orbit:2", "--out", out, "--device", "cpu")
    assert again.exit_code == 0, again.output
    assert sorted(p.name for p in out.iterdir()) == ["0000.png", "0001.png", "0009.png", "notes.txt", "views.json"]
    assert len(json.loads((out / "views.json").read_text())["views"]) == 2


def test_an_interrupted_or_overtaken_render_leaves_one_whole_set(model_path, tmp_path, monkeypatch):
    """Ctrl-C at the third frame of a render into an earlier render's folder leaves that render
    as it was; a render that another finishes into the same --out while it runs ends with its own
    set whole (the last wins), the other's files and the hidden folders gone.  A folder in --out
    (which the swap would lose) and the current folder are refused before any work."""
    import crfedit.render_files as render_files

    model, _ = load_model(model_path)
    out = tmp_path / "r"
    render_to_folder(model, 0, "orbit:4", out, res=8)
    (out / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = render_files.write_png, []

    def interrupted(path, image):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        real(path, image)

    monkeypatch.setattr(render_files, "write_png", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_to_folder(model, 1, "orbit:3", out, res=12)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before and [p.name for p in tmp_path.iterdir()] == ["r"]

    def overtaken(path, image):  # another render finishes into --out while this one writes its first frame
        if not calls:
            calls.append(path)
            monkeypatch.setattr(render_files, "write_png", real)
            render_to_folder(model, 1, "orbit:2", out, res=12)
        real(path, image)

    calls.clear()
    monkeypatch.setattr(render_files, "write_png", overtaken)
    render_to_folder(model, 0, "orbit:3", out, res=8)
    listed = json.loads((out / "views.json").read_text())
    assert (listed["instance"], len(listed["views"])) == (model.names[0], 3) and [p.name for p in tmp_path.iterdir()] == ["r"]
    assert sorted(p.name for p in out.iterdir()) == ["0000.png", "0001.png", "0002.png", "notes.txt", "views.json"]
    assert read_image(out / "0001.png").shape == (8, 8, 3) and (out / "notes.txt").read_text() == "mine"
    (out / "sub").mkdir()
    assert_user_error(invoke("render", model_path, "--instance", 0, "--views", "orbit:2", "--out", out), "holds a folder (sub)")
    monkeypatch.chdir(out / "sub")
    assert_user_error(invoke("render", model_path, "--instance", 0, "--views", "orbit:2", "--out", ".."), "is the current folder or holds it")


def test_views_of_several_sizes_keep_their_own_size(tiny_chairs, model_path, tmp_path):
    """A category whose second chair is 24×24 (the first 16×16, the same field of view): the model
    stores each view's size and focal, so `train:0` of the second chair renders at 24×24 from its
    dataset camera; a category of one size stores no size tensor (the same file as before)."""
    import shutil

    from crfedit.data.synth import SynthConfig, write_synth_category
    from crfedit.safefile import read_safetensors

    big = tmp_path / "big"
    write_synth_category(big, SynthConfig(instances=2, views=6, res=24, seed=0, twins=False))
    data = tmp_path / "mixed"
    shutil.copytree(tiny_chairs, data)
    shutil.rmtree(data / "chair_001")
    shutil.copytree(big / "chair_001", data / "chair_001")
    out = tmp_path / "model.safetensors"
    result = invoke("train", data, "--out", out, "--steps", 4, *TINY)
    assert result.exit_code == 0, result.output
    category = load_category(data)
    model, _ = load_model(out)
    for k, inst in enumerate(category.instances):
        for split, views in inst.splits.items():
            stored = model.views[split].cameras(k)
            assert [(c.width, c.height) for c in stored] == [(v.camera.width, v.camera.height) for v in views]
            assert np.allclose([c.focal for c in stored], [v.camera.focal for v in views], rtol=1e-12)
    rendered = tmp_path / "r"
    assert invoke("render", out, "--instance", 1, "--views", "train:0", "--out", rendered, "--device", "cpu").exit_code == 0
    assert read_image(rendered / "0000.png").shape[:2] == (24, 24)
    info = invoke("info", out, "--json")
    assert json.loads(info.stdout)["views"]["train"] == {"count": 8, "size": [16, 16], "sizes": [[16, 16], [24, 24]]}
    assert "train 8 at 16x16 / 24x24" in invoke("info", out).stdout
    from crfedit.render_files import RenderResult  # render's line for a spec whose views come in two sizes

    assert RenderResult(2, 16, 16, 0.1, None, ((16, 16), (24, 24))).size_text == "16x16 / 24x24"
    tensors, _ = read_safetensors(out)
    assert "views.train.size" in tensors and "views.train.size" not in read_safetensors(model_path)[0]
    # --resume loads each view at its own width again (not every view at the first's)
    assert stored_training(out).widths["train"] == [16, 24] and stored_training(model_path).widths == {}
    from crfedit.cli.train import _resumed
    from crfedit.distributed import SINGLE

    assert _resumed(out, None, None, SINGLE)[1] is None
    assert_user_error(invoke("train", data, "--out", out, "--resume", "--res", 16, *TINY), "each view at its own width (16, 24)")


def test_sigterm_stops_a_render_as_ctrl_c_does(tiny_model, tmp_path):
    """SIGTERM (timeout, kill, a scheduler's stop) runs Ctrl-C's clean-up: the render's hidden
    part-built folder goes, the earlier set stays whole, and the exit status is 143.  (Before,
    the process died where it stood and left the hidden folder behind.)"""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "views"
    first = invoke("render", tiny_model, "--instance", 0, "--views", "orbit:2", "--out", out, "--device", "cpu")
    assert first.exit_code == 0, first.output
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    env = {**os.environ, "CRFEDIT_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "crfedit", "render", str(tiny_model), "--instance", "0", "--views", "orbit:5000",
                             "--out", str(out), "--device", "cpu"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".views.") and any(p.iterdir()) for p in tmp_path.iterdir() if p.is_dir()):  # frames being written
        assert proc.poll() is None and time.monotonic() < deadline, "the render ended before it could be stopped"
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and err.splitlines()[-1] == "terminated (SIGTERM)", (proc.returncode, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["views"]  # no hidden folder left
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
