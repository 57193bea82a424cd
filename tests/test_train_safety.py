"""Training's output file (issue 18): Ctrl-C writes a checkpoint, an existing model is not
replaced without --resume or --overwrite, and --out's folder is created like render's."""

from __future__ import annotations

import csv

import pytest
import torch

from crfedit.config import make_config
from crfedit.data import load_category
from crfedit.model import load_model
from crfedit.train import train

from cli_helpers import assert_user_error, invoke

TINY = ["--steps", "3", "--set", "rays=64", "--device", "cpu"]


def test_ctrl_c_before_the_first_checkpoint_writes_one(tiny_chairs, tmp_path):
    cfg = make_config("fast", overrides=dict(steps=50, rays=64, checkpoint_every=10**9))
    out = tmp_path / "m.safetensors"

    def on_step(step, *_):
        if step == 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt, match="checkpoint at step 4"):
        train(load_category(tiny_chairs), cfg, out, torch.device("cpu"), on_step=on_step)
    model, state = load_model(out)
    assert int(state["step"]) == 4 and model.meta["step"] == "4"
    model, result = train(load_category(tiny_chairs), cfg, out, torch.device("cpu"), resume=True,
                          on_step=lambda step, *_: None)
    assert result.steps == 50 and int(load_model(out)[1]["step"]) == 50


@pytest.mark.parametrize("sent", ["SIGINT", "SIGTERM"])
def test_a_ctrl_c_mid_step_stops_at_the_step_boundary_and_resume_is_bit_identical(tiny_chairs, tmp_path, sent):
    """SIGINT (or SIGTERM, in a background job whose SIGINT is ignored: a `kill` stopped such a
    run mid-step and the resumed model differed) arrives inside step 3's forward pass: the step
    finishes, the checkpoint is of step 3 (weights, Adam moments, generator), and --resume ends
    bit-identical to a run never stopped."""
    import os
    import signal

    import crfedit.train as train_module
    from crfedit.errors import Terminated

    cfg = make_config("fast", overrides=dict(steps=8, rays=64, checkpoint_every=10**9))
    category = load_category(tiny_chairs)
    whole, stopped = tmp_path / "whole.safetensors", tmp_path / "stopped.safetensors"
    train(category, cfg, whole, torch.device("cpu"), seed=0)
    real, calls = train_module.render_rays, []

    def render_rays(*args, **kwargs):  # Ctrl-C in the middle of the third step's forward pass
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), getattr(signal, sent))
        return real(*args, **kwargs)

    train_module.render_rays = render_rays
    # pytest's background runs may start with SIGINT ignored; a background job's SIGTERM case ignores it on purpose
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler if sent == "SIGINT" else signal.SIG_IGN)
    term = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        with pytest.raises(Terminated if sent == "SIGTERM" else KeyboardInterrupt, match="checkpoint at step 3"):
            train(category, cfg, stopped, torch.device("cpu"), seed=0)
        assert signal.getsignal(signal.SIGINT) in (signal.default_int_handler, signal.SIG_IGN)  # the loop's handlers are gone again
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    finally:
        train_module.render_rays = real
        signal.signal(signal.SIGINT, inherited)
        signal.signal(signal.SIGTERM, term)
    train(category, cfg, stopped, torch.device("cpu"), seed=0, resume=True)
    (a, sa), (b, sb) = load_model(whole), load_model(stopped)
    sa.pop("elapsed"), sb.pop("elapsed")
    assert a.state().keys() == b.state().keys() and sa.keys() == sb.keys()
    assert all(torch.equal(a.state()[k], b.state()[k]) for k in a.state())
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


def interrupt_training_at(monkeypatch, at: int):
    """``crfedit train`` as Ctrl-C after step ``at`` leaves it (the step's progress and log seen);
    returns the real ``train`` to put back."""
    import crfedit.train as train_module

    original = train_module.train

    def interrupted(*args, on_step=None, **kwargs):
        def stop(step, *rest):
            on_step(step, *rest)
            if step == at:
                raise KeyboardInterrupt
        return original(*args, on_step=stop, **kwargs)

    monkeypatch.setattr(train_module, "train", interrupted)
    return original


def test_cli_interrupt_message_and_resume(tiny_chairs, tmp_path, monkeypatch):
    import crfedit.train as train_module

    out = tmp_path / "m.safetensors"
    original = interrupt_training_at(monkeypatch, 2)
    r = invoke("train", tiny_chairs, "--out", out, *TINY)
    assert r.exit_code == 130 and "checkpoint at step 2" in r.stderr and "--resume" in r.stderr, r.output
    monkeypatch.setattr(train_module, "train", original)
    r = invoke("train", tiny_chairs, "--out", out, "--resume", *TINY)
    assert r.exit_code == 0, r.output
    assert int(load_model(out)[1]["step"]) == 3
    r = invoke("train", tiny_chairs, "--out", out, "--resume", "--steps", 5, "--set", "rays=32", "--device", "cpu")
    assert r.exit_code == 0 and "nothing to resume" in r.stdout and "ignored: rays 32 (stored 64), steps 5 (stored 3)" in r.stdout, r.output
    r = invoke("train", tiny_chairs, "--out", out, "--resume", "--seed", 9, "--device", "cpu")  # the finished run's seed too
    assert r.exit_code == 0 and "nothing to resume" in r.stdout and "seed 9 (stored" in r.stdout, r.output


def test_a_stopped_run_logs_its_last_read_out(tiny_chairs, tmp_path, monkeypatch):
    """A run stopped (Ctrl-C, SIGTERM) before step --log-every left its log with the header
    alone, though a checkpoint was written: the last step whose loss was read is a row."""
    interrupt_training_at(monkeypatch, 7)
    r = invoke("train", tiny_chairs, "--out", tmp_path / "m.safetensors", "--steps", 10, "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 130 and "checkpoint at step 7" in r.stderr, r.output
    rows = list(csv.DictReader((tmp_path / "m.log.csv").open()))
    assert len(rows) == 1 and 1 <= int(rows[0]["step"]) <= 7 and float(rows[0]["loss"]) > 0, rows


def test_existing_model_is_not_replaced_silently(tiny_chairs, tmp_path):
    out = tmp_path / "m.safetensors"
    out.write_bytes(b"precious")
    r = invoke("train", tiny_chairs, "--out", out, *TINY)  # not a model: neither flag would help, so neither is offered
    assert r.exit_code == 2 and "exists and is not a crfedit model" in r.stderr and "pick another name" in r.stderr, r.output
    assert out.read_bytes() == b"precious"
    r = invoke("train", tiny_chairs, "--out", out, "--overwrite", *TINY)  # --overwrite replaces models only
    assert r.exit_code == 2 and "is not a crfedit model" in r.stderr and out.read_bytes() == b"precious", r.output
    out.unlink()
    assert invoke("train", tiny_chairs, "--out", out, *TINY).exit_code == 0
    first = out.read_bytes()
    r = invoke("train", tiny_chairs, "--out", out, *TINY)  # a model: continued or replaced only when asked
    assert r.exit_code == 2 and "exists; continue its training with --resume, or replace it with --overwrite" in r.stderr, r.output
    r = invoke("train", tiny_chairs, "--out", out, "--overwrite", "--seed", 1, *TINY)
    assert r.exit_code == 0 and load_model(out)[1]["step"] == 3 and out.read_bytes() != first, r.output


def test_a_run_that_fails_before_its_first_checkpoint_leaves_the_records_as_they_were(tiny_chairs, tmp_path):
    """Diverged at once (lr 1e30): a fresh run leaves no record files, and --overwrite of a model
    leaves the model and its records byte for byte (they would describe a run the model does
    not hold); the error says what was left."""
    out = tmp_path / "m.safetensors"
    r = invoke("train", tiny_chairs, "--out", out, "--set", "lr=1e30", *TINY)
    assert r.exit_code == 2 and "no checkpoint was written yet" in r.stderr, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    assert invoke("train", tiny_chairs, "--out", out, *TINY).exit_code == 0
    files = lambda: {str(p.relative_to(tmp_path)): p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file()}
    kept = files()  # the model, its records, and TensorBoard's events where it is installed
    r = invoke("train", tiny_chairs, "--out", out, "--overwrite", "--set", "lr=1e30", *TINY)
    assert r.exit_code == 2 and "is left as it was" in r.stderr, r.output
    assert files() == kept


def test_train_out_creates_its_folder(tiny_chairs, tmp_path):
    out = tmp_path / "new" / "deeper" / "m.safetensors"
    r = invoke("train", tiny_chairs, "--out", out, *TINY)
    assert r.exit_code == 0 and out.is_file(), r.output
    (tmp_path / "file").write_text("x")
    r = invoke("train", tiny_chairs, "--out", tmp_path / "file" / "m.safetensors", *TINY)
    assert r.exit_code == 2 and "is a file, not a folder" in r.stderr
    # a run that fails before writing anything leaves no empty folder behind
    r = invoke("train", tmp_path / "no-such-data", "--out", tmp_path / "other" / "deep" / "m.safetensors", *TINY)
    assert r.exit_code == 2 and not (tmp_path / "other").exists(), r.output


def test_run_records_beside_the_model(tiny_chairs, tmp_path):
    import json

    out = tmp_path / "m.safetensors"
    r = invoke("train", tiny_chairs, "--out", out, "--log-every", 2, "--steps", 5, "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "config (also in" in r.stdout and "rays=64" in r.stdout and "steps=5" in r.stdout
    run = json.loads((tmp_path / "m.run.json").read_text())
    assert run["config"] == json.loads(load_model(out)[0].cfg.to_json()) and run["seed"] == 0 and run["world_size"] == 1
    rows = list(csv.DictReader((tmp_path / "m.log.csv").open()))
    assert [int(row["step"]) for row in rows] == [2, 4, 5]  # the last step too, off the --log-every grid
    assert all(float(row["lr"]) > 0 and float(row["rays_per_s"]) > 0 and float(row["loss"]) > 0 for row in rows)
    assert float(rows[0]["lr"]) > float(rows[1]["lr"])  # the cosine schedule decays
    r = invoke("train", tiny_chairs, "--out", out, "--resume", "--steps", 8, "--log-every", 2, "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert [int(row["step"]) for row in csv.DictReader((tmp_path / "m.log.csv").open())] == [2, 4, 5]  # stored steps=5: done
    assert "ignored: steps 8 (stored 5)" in r.stdout and "rays" not in r.stdout.split("ignored:")[1]  # only what was typed
    r = invoke("train", tiny_chairs, "--out", out, "--resume", "--device", "cpu")
    assert r.exit_code == 0 and "nothing to resume" in r.stdout and "ignored" not in r.stdout, r.stdout


def test_tensorboard_events_when_installed(tiny_chairs, tmp_path):
    pytest.importorskip("tensorboard", reason="TensorBoard events need the [tensorboard] extra")
    out = tmp_path / "m.safetensors"
    r = invoke("train", tiny_chairs, "--out", out, "--log-every", 1, *TINY)
    assert r.exit_code == 0 and list((tmp_path / "m.tb").glob("events.out.tfevents.*")), r.output
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "m.tb"))
    events.Reload()
    assert [e.step for e in events.Scalars("train/loss")] == [1, 2, 3]
    assert {"train/psnr", "train/rays_per_s", "train/lr", "train/seconds"} <= set(events.Tags()["scalars"])


def test_resume_on_another_dataset_is_refused_before_any_set_up(tiny_chairs, tmp_path):
    from crfedit.data.synth import SynthConfig, write_synth_category

    out = tmp_path / "m.safetensors"
    assert invoke("train", tiny_chairs, "--out", out, "--steps", 8, "--set", "rays=64", "--device", "cpu").exit_code == 0
    other = tmp_path / "other"
    write_synth_category(other, SynthConfig(instances=2, views=6, res=16, seed=7, twins=False))
    before = out.read_bytes(), (tmp_path / "m.run.json").read_bytes()
    r = invoke("train", other, "--out", out, "--resume", "--steps", 16, "--device", "cpu")
    assert_user_error(r, "was trained on another dataset")
    assert "config (also in" not in r.stdout and (out.read_bytes(), (tmp_path / "m.run.json").read_bytes()) == before


def test_a_second_training_of_the_same_out_is_refused_while_one_runs(tiny_chairs, tmp_path):
    """Two trainings on one --out: the second is refused at once (one line), the first's model
    is kept; the lock goes with the run that held it."""
    from crfedit.io import writer_lock

    out = tmp_path / "m.safetensors"
    with writer_lock(out):  # as a running `crfedit train --out m.safetensors` holds it
        r = invoke("train", tiny_chairs, "--out", out, *TINY)
        assert_user_error(r, "m.safetensors", "another crfedit process is writing it", f"pid {__import__('os').getpid()}")
        assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # the lock file went with the lock
    assert invoke("train", tiny_chairs, "--out", out, *TINY).exit_code == 0 and not (tmp_path / ".m.safetensors.lock").exists()


def test_a_training_removes_the_half_written_copies_a_killed_run_left(tiny_chairs, tmp_path):
    """A torchrun rank 0 killed with SIGKILL while writing a checkpoint left its temporary
    (17 MB, hidden) beside the model for good; the next training of that --out removes it (and
    a run record's), saying so, and leaves another file's temporaries alone."""
    out = tmp_path / "m.safetensors"
    stale = [tmp_path / ".m.safetensors.ab3_d2uv.safetensors.tmp", tmp_path / ".m.run.json.x9y8z7w6.json.tmp"]
    other = tmp_path / ".n.safetensors.ab3_d2uv.safetensors.tmp"
    for p in (*stale, other):
        p.write_bytes(b"\0" * 1500)
    r = invoke("train", tiny_chairs, "--out", out, *TINY)
    assert r.exit_code == 0, r.output
    assert not any(p.exists() for p in stale) and other.exists()
    assert "note: removed .m.safetensors.ab3_d2uv.safetensors.tmp (1.5 KB), a copy of m.safetensors a killed run left half-written" in r.stderr


def test_views_of_several_sizes_train_at_their_sizes(tiny_chairs, tmp_path):
    """One chair's images at 1.5x the size: training reads each view at its own size and the
    model keeps each view's (tests/test_cli_train_render.py renders them); --res R gives every
    view width R, so the table holds one size."""
    import shutil

    from PIL import Image

    data = tmp_path / "mixed"
    shutil.copytree(tiny_chairs, data)
    for png in (data / "chair_001").rglob("r_*.png"):
        if png.stem.endswith("_parts"):
            png.unlink()
            continue
        with Image.open(png) as im:
            im.resize((im.width * 3 // 2, im.height * 3 // 2), Image.BILINEAR).save(png)
    for exr in (data / "chair_001").rglob("*_depth.exr"):
        exr.unlink()
    r = invoke("train", data, "--out", tmp_path / "m.safetensors", "--steps", 1, "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 0, r.output
    from crfedit.model import load_model

    assert "sizes" not in r.stderr, r.stderr
    assert load_model(tmp_path / "m.safetensors")[0].views["train"].sizes is not None
    r = invoke("train", data, "--out", tmp_path / "r.safetensors", "--steps", 1, "--res", 16, "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 0 and "sizes" not in r.stderr, r.output
    assert load_model(tmp_path / "r.safetensors")[0].views["train"].sizes is None


def test_a_resume_drops_the_log_rows_past_its_checkpoint(tmp_path):
    """Killed at step 44 with its checkpoint at 40: --resume trains 41-44 again, so their rows
    leave the log first (they appeared twice, a zig-zag in every loss plot)."""
    from crfedit.config import make_config
    from crfedit.runlog import COLUMNS, RunLog, record_paths

    model = tmp_path / "m.safetensors"
    log = record_paths(model)["log"]
    rows = [",".join(COLUMNS)] + [f"{s},0.1,20.0,1000.0,0.01,{s / 10:.2f}" for s in range(10, 50, 10)]
    log.write_text("\n".join(rows) + "\n")
    run = RunLog(model, make_config("fast"), 10, None, True, {"resumed_at": 20, "command": "crfedit train"})
    run.on_step(30, 0.05, 22.0, 1000.0)
    run.file.close()
    steps = [line.split(",")[0] for line in log.read_text().splitlines()[1:]]
    assert steps == ["10", "20", "30"]


def test_the_last_log_row_holds_its_own_step_s_read_out(tiny_chairs, tmp_path):
    """The loss is read every few steps, and the final row was stamped with the last step but
    held a read-out steps older (step 150's row had step 148's loss); a run of 3 steps wrote no
    row.  The last row now holds the final checkpoint's own read-out: the values a run logging
    every step has at that step."""
    import csv

    def rows(out, *extra):
        r = invoke("train", tiny_chairs, "--out", out, "--steps", "6", "--set", "rays=64", "--device", "cpu", "--seed", "3", *extra)
        assert r.exit_code == 0, r.output
        return {row["step"]: (row["loss"], row["psnr"]) for row in csv.DictReader(out.with_name(out.stem + ".log.csv").open())}

    every = rows(tmp_path / "a.safetensors", "--log-every", "1")
    sparse = rows(tmp_path / "b.safetensors", "--log-every", "4")
    assert list(sparse) == ["4", "6"] and sparse["6"] == every["6"] and sparse["4"] == every["4"]
    short = rows(tmp_path / "c.safetensors")  # log every 100: the one row is the last step's
    assert list(short) == ["6"] and short["6"] == every["6"]


def test_a_log_left_empty_gets_its_header_on_resume(tmp_path):
    """A torchrun job killed before its first row left an empty log (the header still in the
    writer's buffer); the resume appended rows under no header, so a CSV reader took the first
    row for the column names.  The header is on disk as soon as the log is made, and an empty
    log is begun again."""
    import csv

    from crfedit.config import make_config
    from crfedit.runlog import COLUMNS, RunLog, record_paths

    model = tmp_path / "m.safetensors"
    log = record_paths(model)["log"]
    first = RunLog(model, make_config("fast"), 10, None, False, {"command": "crfedit train"})
    assert log.read_text().splitlines() == [",".join(COLUMNS)]  # before any row, and before the file is closed
    first.file.close()
    log.write_text("")
    run = RunLog(model, make_config("fast"), 10, None, True, {"resumed_at": 20, "command": "crfedit train"})
    run.on_step(30, 0.05, 22.0, 1000.0)
    run.file.close()
    assert [row["step"] for row in csv.DictReader(log.open())] == ["30"]


def test_a_camera_too_far_for_float32_is_named_before_training(tiny_chairs, tmp_path):
    """One training frame 10³⁰ away trained before, and then every render and eval of the model
    failed with a line naming no view; now training refuses it, naming the file and the frame."""
    import json
    import re
    import shutil

    from crfedit.errors import CrfError

    data = tmp_path / "far"
    shutil.copytree(tiny_chairs, data)
    inst = (data / "instances.txt").read_text().split()[0]
    path = data / inst / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][0]["transform_matrix"][0][3] = 1e30
    path.write_text(json.dumps(meta))
    cfg = make_config("fast", overrides=dict(steps=2, rays=64))
    with pytest.raises(CrfError, match=rf"^{re.escape(str(data / inst))}: train:0 \(.*\): camera: it lies [0-9.e+]+ scene-box diagonals"):
        train(load_category(data), cfg, tmp_path / "m.safetensors", torch.device("cpu"))
    assert not (tmp_path / "m.safetensors").exists()


def test_training_views_without_alpha_are_named_before_training(tiny_chairs, tmp_path):
    """An instance whose training images carry no alpha (JPEGs, RGB PNGs) and no masks trained
    silently into a cloud of background matter, and pulled the other chairs down; training now
    says which instances those are."""
    import shutil

    from PIL import Image

    data = tmp_path / "rgb"
    shutil.copytree(tiny_chairs, data)
    inst = (data / "instances.txt").read_text().split()[0]
    for png in (data / inst / "train").glob("r_*.png"):
        if "_" in png.stem[2:]:  # depth previews, part maps: left as they are
            continue
        rgba = Image.open(png).convert("RGBA")
        white = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
        Image.alpha_composite(white, rgba).convert("RGB").save(png)
    notes = []
    train(load_category(data), make_config("fast", overrides=dict(steps=1, rays=64)), tmp_path / "m.safetensors",
          torch.device("cpu"), on_note=notes.append)
    said = [n for n in notes if "no alpha or mask" in n]
    assert len(said) == 1 and said[0].startswith(f"1 instance ({inst}) of {data} has no alpha or mask in any training view"), notes
    notes.clear()
    train(load_category(tiny_chairs), make_config("fast", overrides=dict(steps=1, rays=64)), tmp_path / "n.safetensors",
          torch.device("cpu"), on_note=notes.append)
    assert not [n for n in notes if "no alpha" in n]
