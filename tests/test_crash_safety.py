"""Crash safety (docs/robustness.md, "Hostile inputs"): what a killed or diverging run leaves.

* ``crfedit train`` killed with SIGKILL at seeded random moments (checkpoint every 5 steps):
  after every kill the model file, if there is one, loads with :func:`crfedit.model.load_model`,
  its step only moves forward, and ``--resume`` then trains to the last step.
* ``crfedit edit-color --steps 100000`` killed mid-optimization: no edit file, no temporary
  file, and an edit file that was already there stays byte-identical.
* A non-finite loss (the renderer poisoned with NaN at step k, in process) raises
  :class:`~crfedit.errors.NonFiniteError` and leaves the previous checkpoint byte-identical.

The commands run as real processes (``python -m crfedit``), one OpenMP thread each on this
shared machine.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import crfedit.train
from crfedit.config import make_config
from crfedit.data import load_category
from crfedit.errors import NonFiniteError
from crfedit.model import load_model
from crfedit.train import train

CLI = [sys.executable, "-m", "crfedit"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
STEPS = 300  # long enough (several seconds here) that every kill lands before the run ends
EVERY = 5


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def leftovers(folder: Path) -> list[Path]:
    return sorted(folder.rglob(".*.tmp"))


def launch(args: list, log: Path) -> subprocess.Popen:
    with open(log, "wb") as f:
        return subprocess.Popen([*CLI, *map(str, args)], stdout=f, stderr=subprocess.STDOUT, env=ENV)


def kill(proc: subprocess.Popen) -> bool:
    """SIGKILL ``proc`` (a process this test started) unless it already ended; True if it was killed."""
    alive = proc.poll() is None
    if alive:
        proc.kill()
    proc.wait()
    return alive


def checkpoint_id(path: Path) -> tuple[int, int] | None:
    """Changes whenever a checkpoint is renamed over ``path``."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns


def wait_for_new_checkpoint(path: Path, since: tuple[int, int] | None, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while checkpoint_id(path) in (since, None) and proc.poll() is None:
        assert time.monotonic() < deadline, "no checkpoint was written"
        time.sleep(0.005)


# ----------------------------------------------------------------------------- train


def test_sigkill_during_training_leaves_a_loadable_model_and_resume_finishes(tiny_chairs: Path, tmp_path: Path):
    out = tmp_path / "model.safetensors"
    args = ["train", tiny_chairs, "--out", out, "--steps", STEPS, "--set", f"checkpoint_every={EVERY}", "--set", "rays=256", "--device", "cpu"]
    rng = random.Random(1234)
    steps, kills = [], 0
    for attempt in range(3):
        proc = launch(args + (["--resume"] if out.exists() else []), tmp_path / f"run{attempt}.log")
        try:
            if attempt == 0:
                time.sleep(rng.uniform(1.0, 4.0))  # anywhere: start-up, hull carving or the first steps
            else:
                wait_for_new_checkpoint(out, checkpoint_id(out), proc)
                time.sleep(rng.uniform(0.0, 0.25))  # a random phase of the 5-step checkpoint cycle (writes included)
        finally:
            killed = kill(proc)
        if not killed:
            break
        kills += 1
        if out.exists():
            model, state = load_model(out)
            step = int(state["step"])
            assert model.meta["step"] == str(step) and step % EVERY == 0 and 0 < step <= STEPS
            assert not steps or step >= steps[-1], "a killed run left an older checkpoint than its predecessor"
            steps.append(step)
    assert kills == 3 and steps, "the kills came too late to interrupt training"
    stale = leftovers(tmp_path)
    assert all(p.name.startswith(".model.safetensors.") for p in stale), stale  # only the atomic writer's temp files

    final = subprocess.run([*CLI, *map(str, args), "--resume"], env=ENV, capture_output=True, text=True)
    assert final.returncode == 0, final.stdout[-2000:] + final.stderr[-2000:]
    assert f"-> {out}" in final.stdout
    model, state = load_model(out)
    assert int(state["step"]) == STEPS and model.meta["step"] == str(STEPS)


# ----------------------------------------------------------------------------- edit


def test_sigkill_during_an_edit_leaves_no_partial_file(tiny_model: Path, tmp_path: Path):
    mask = np.zeros((16, 16), np.uint8)
    mask[5:11, 5:11] = 255
    Image.fromarray(mask, "L").save(tmp_path / "scribble.png")
    out = tmp_path / "edit.safetensors"
    args = ["edit-color", tiny_model, "--instance", "0", "--view", "train:0", "--color", "red",
            "--scribble", tmp_path / "scribble.png", "--out", out, "--device", "cpu"]
    model_hash = sha(tiny_model)

    t0 = time.monotonic()
    quick = subprocess.run([*CLI, *map(str, args), "--steps", "1"], env=ENV, capture_output=True, text=True)
    start_up = time.monotonic() - t0  # start-up, loading and one step: the long run is optimizing after this
    assert quick.returncode == 0, quick.stderr
    out.rename(tmp_path / "earlier.safetensors")

    rng = random.Random(99)
    for existing in (False, True):
        if existing:
            (tmp_path / "earlier.safetensors").rename(out)
        before = sha(out) if existing else None
        proc = launch(args + ["--steps", "100000"], tmp_path / "edit.log")
        try:
            time.sleep(start_up + rng.uniform(1.0, 2.0))
        finally:
            assert kill(proc), "the 100000-step edit ended before it was killed"
        assert leftovers(tmp_path) == []
        if existing:
            assert sha(out) == before, "the edit file that was there changed"
        else:
            assert not out.exists(), "a partial edit file was left"
    assert sha(tiny_model) == model_hash


# ----------------------------------------------------------------------------- non-finite loss


def poison_renderer(monkeypatch, call: int) -> None:
    """``render_rays`` in crfedit.train returns NaN colours on its ``call``-th call (1-based)."""
    real = crfedit.train.render_rays
    calls = 0

    def poisoned(*args, **kwargs):
        nonlocal calls
        calls += 1
        out = real(*args, **kwargs)
        return dataclasses.replace(out, rgb=out.rgb * float("nan")) if calls == call else out

    monkeypatch.setattr(crfedit.train, "render_rays", poisoned)


@pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad=True")  # the bug the CLI test below marks
@pytest.mark.parametrize("nan_step", [15, 3])
def test_non_finite_loss_raises_and_keeps_the_last_checkpoint(tiny_chairs: Path, tmp_path: Path, monkeypatch, nan_step: int):
    """Checkpoints every 10 steps: NaN at step 15 leaves the step-10 file byte for byte; NaN at
    step 3, before any checkpoint, leaves no file."""
    out = tmp_path / "model.safetensors"
    poison_renderer(monkeypatch, nan_step + 1)
    seen: dict[int, str] = {}

    def on_step(step: int, *rest) -> None:
        if out.exists():
            seen[step] = sha(out)

    cfg = make_config("fast", overrides=dict(steps=30, rays=256, checkpoint_every=10))
    left = "keeps its last checkpoint" if nan_step > 10 else "no checkpoint was written yet"
    with pytest.raises(NonFiniteError, match=f"training diverged at step {nan_step} .*{left}"):
        train(load_category(tiny_chairs), cfg, out, torch.device("cpu"), seed=0, on_step=on_step)
    assert leftovers(tmp_path) == []
    if nan_step < 10:
        assert not out.exists()
        return
    assert sha(out) == seen[11] == seen[nan_step], "the last checkpoint changed"
    model, state = load_model(out)
    assert int(state["step"]) == 10 and model.meta["step"] == "10"


POISONED_CLI = """
import dataclasses, sys
import crfedit.train as t
real, calls, nan_call = t.render_rays, [0], int(sys.argv.pop(1))
def poisoned(*args, **kwargs):
    calls[0] += 1
    out = real(*args, **kwargs)
    return dataclasses.replace(out, rgb=out.rgb * float("nan")) if calls[0] == nan_call else out
t.render_rays = poisoned
from crfedit.cli import main
main()
"""


def test_non_finite_loss_through_the_cli_is_one_line(tiny_chairs: Path, tmp_path: Path):
    """The real command in its own process (so Python's warnings reach stderr), its renderer
    poisoned at step 12: exit 2, one error line, the step-10 checkpoint kept."""
    out = tmp_path / "model.safetensors"
    args = ["train", tiny_chairs, "--out", out, "--steps", 20, "--set", "checkpoint_every=10", "--set", "rays=256", "--device", "cpu"]
    result = subprocess.run([sys.executable, "-c", POISONED_CLI, "13", *map(str, args)], env=ENV, capture_output=True, text=True)
    assert int(load_model(out)[1]["step"]) == 10 and leftovers(tmp_path) == []
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.splitlines()
    assert lines[-1].startswith("error: training diverged at step 12"), result.stderr
    assert len(lines) == 1, result.stderr
