"""Shareable models (issue 18): ``info``'s size breakdown, ``crfedit model strip`` and ``edits bake``
writing a model without the training state."""

from __future__ import annotations

import json

import numpy as np
import torch
import pytest

from crfedit.config import make_config
from crfedit.data import load_category
from crfedit.io import write_png
from crfedit.model import load_model
from crfedit.modelfile import SIZE_KINDS, size_breakdown
from crfedit.renderer import render_camera
from crfedit.safefile import read_header
from crfedit.train import train

from cli_helpers import assert_user_error, invoke


def test_size_breakdown_adds_up_and_names_the_training_state(tiny_model):
    sizes = size_breakdown(tiny_model)
    assert sum(sizes.values()) == tiny_model.stat().st_size and set(sizes) == {*SIZE_KINDS, "header"}
    header, _ = read_header(tiny_model)
    train_bytes = sum(e - s for n, i in header.items() if n.startswith("train.") for s, e in [i["data_offsets"]])
    assert sizes["training state"] == train_bytes > sizes["weights"] > 0  # Adam's two moments per weight, and more
    info = json.loads(invoke("info", tiny_model, "--json").stdout)
    assert info["sizes"] == sizes
    text = invoke("info", tiny_model).stdout
    assert "training state" in text and "crfedit model strip" in text


def test_strip_keeps_renders_and_drops_resume(tiny_model, tiny_chairs, tmp_path):
    small = tmp_path / "small.safetensors"
    r = invoke("model", "strip", tiny_model, "--out", small)
    assert r.exit_code == 0 and "training state dropped" in r.stdout, r.output
    again = invoke("model", "strip", small, "--out", tmp_path / "again.safetensors")  # nothing left to drop: said so
    (tmp_path / "again.safetensors").unlink()
    assert again.exit_code == 0 and "it held no training state (a copy)" in again.stdout, again.output
    sizes = size_breakdown(small)
    assert sizes["training state"] == 0 and small.stat().st_size < tiny_model.stat().st_size - size_breakdown(tiny_model)["training state"] + 16384
    (a, _), (b, state) = load_model(tiny_model), load_model(small)
    assert state == {} and a.fingerprint() == b.fingerprint()
    cam = a.views["test"].cameras(0)[0]
    assert torch.equal(render_camera(a.field_for(0), cam, 0).rgb, render_camera(b.field_for(0), cam, 0).rgb)
    cfg = make_config("fast", overrides=dict(steps=31, rays=256, checkpoint_every=10))
    from crfedit.errors import CrfError

    with pytest.raises(CrfError, match="holds no training state"):
        train(load_category(tiny_chairs), cfg, small, torch.device("cpu"), resume=True)
    r = invoke("train", tiny_chairs, "--out", small, "--resume", "--minutes", 1, "--device", "cpu")
    assert_user_error(r, "holds no training state")  # from the header, before the run's records are written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.safetensors"]
    r = invoke("model", "strip", small, "--out", small)
    assert r.exit_code == 2 and "is the model file" in r.stderr


def test_bake_writes_a_stripped_model_by_default(tiny_model, tmp_path):
    mask = np.zeros((16, 16), np.uint8)
    mask[6:10, 6:10] = 255
    write_png(tmp_path / "s.png", mask)
    edit = tmp_path / "e.safetensors"
    r = invoke("edit-color", tiny_model, "--instance", 0, "--view", "train:0", "--scribble", tmp_path / "s.png",
               "--color", "red", "--steps", 2, "--device", "cpu", "--out", edit)
    assert r.exit_code == 0, r.output
    r = invoke("edits", "bake", tiny_model, "--edit", edit, "--out", tmp_path / "b.safetensors")
    assert r.exit_code == 0 and "without training state" in r.stdout and "is unchanged" in r.stdout, r.output
    assert size_breakdown(tmp_path / "b.safetensors")["training state"] == 0
    r = invoke("edits", "bake", tiny_model, "--edit", edit, "--out", tmp_path / "c.safetensors", "--training-state")
    assert r.exit_code == 0 and size_breakdown(tmp_path / "c.safetensors")["training state"] == size_breakdown(tiny_model)["training state"]
    # an existing model is replaced only with --overwrite (it took training to make); an edit
    # replaces an edit, and an empty file (mktemp), but never a file that is not crfedit's
    c_bytes = (tmp_path / "c.safetensors").read_bytes()
    r = invoke("edits", "bake", tiny_model, "--edit", edit, "--out", tmp_path / "c.safetensors")
    assert r.exit_code == 2 and "is a crfedit model already" in r.stderr and (tmp_path / "c.safetensors").read_bytes() == c_bytes
    r = invoke("model", "strip", tiny_model, "--out", tmp_path / "c.safetensors")
    assert r.exit_code == 2 and "--overwrite" in r.stderr and (tmp_path / "c.safetensors").read_bytes() == c_bytes
    r = invoke("edits", "bake", tiny_model, "--edit", edit, "--out", tmp_path / "c.safetensors", "--overwrite")
    assert r.exit_code == 0 and size_breakdown(tmp_path / "c.safetensors")["training state"] == 0
    (tmp_path / "empty.safetensors").write_bytes(b"")
    notes = tmp_path / "notes.safetensors"
    notes.write_text("not a model")
    for out, code in ((edit, 0), (tmp_path / "empty.safetensors", 0), (notes, 2)):
        r = invoke("edit-color", tiny_model, "--instance", 0, "--view", "train:0", "--scribble", tmp_path / "s.png",
                   "--color", "blue", "--steps", 2, "--device", "cpu", "--out", out)
        assert r.exit_code == code, r.output
    assert "not crfedit's" in r.stderr and notes.read_text() == "not a model"


def test_loading_and_growing_leave_the_global_random_stream(tiny_model):
    """A script's ``torch.manual_seed`` stream is where it was after loading a model or adding an
    instance to it (the fields built to be loaded draw no random numbers)."""
    from crfedit.delta import grow

    torch.manual_seed(123)
    model, _ = load_model(tiny_model)
    grow(model, "new_chair")
    after = torch.rand(4)
    torch.manual_seed(123)
    assert torch.equal(after, torch.rand(4))


def test_files_are_the_same_bytes_in_every_process():
    """safetensors orders metadata keys from a hash map seeded per process; the files crfedit
    writes sort them, so the same contents give the same bytes (the pixels of an edit file, a
    re-pinned stack, a baked model), and the header stays one safetensors reads back."""
    import subprocess
    import sys

    script = (
        "import sys, torch; from crfedit.safefile import safetensors_bytes; "
        "meta = {f'key{i}': f'value {i} \\u00e9' for i in range(12)}; "
        "sys.stdout.buffer.write(safetensors_bytes({'w': torch.arange(5.0), 'g': torch.ones(3, dtype=torch.uint8)}, meta))"
    )
    runs = [subprocess.run([sys.executable, "-c", script], capture_output=True, check=True).stdout for _ in range(3)]
    assert runs[0] == runs[1] == runs[2]
    from safetensors.torch import load

    tensors = load(runs[0])
    assert torch.equal(tensors["w"], torch.arange(5.0)) and torch.equal(tensors["g"], torch.ones(3, dtype=torch.uint8))
    n = int.from_bytes(runs[0][:8], "little")
    meta = json.loads(runs[0][8 : 8 + n])["__metadata__"]
    assert list(meta) == sorted(meta) and meta["key3"] == "value 3 é" and (8 + n) % 8 == 0


def test_metadata_that_is_not_utf8_is_escaped_not_a_crash():
    """A file name that is not UTF-8 reaches the recorded command line as a surrogate escape;
    the write escapes it (it used to fail after the edit had run)."""
    from crfedit.safefile import safetensors_bytes

    data = safetensors_bytes({"w": torch.zeros(2)}, {"command": "crfedit edit-color --scribble scr\udce9.png"})
    n = int.from_bytes(data[:8], "little")
    assert json.loads(data[8 : 8 + n])["__metadata__"]["command"] == "crfedit edit-color --scribble scr\\udce9.png"
