"""The library API under a script's inputs: masks as torch tensors or numbers, colours as
tuples, instances as NumPy integers, one edit path alone; bad ones are one CrfError line, not
a traceback from deep inside.  Loading leaves torch's global random stream alone
(tests/test_modelfile.py) and an edit's seconds count the selection it made."""

from __future__ import annotations

import time
import warnings

import numpy as np
import pytest
import torch

from crfedit.delta import apply_edit_files
from crfedit.edit import EditOptions, edit_color, remove
from crfedit.edit.scribble import as_rgb
from crfedit.edit.selection import preview, select_for
from crfedit.errors import CrfError
from crfedit.masks import as_mask
from crfedit.model import load_model
from crfedit.renderer import render_camera

FAST = EditOptions(steps=2, rays=128)


@pytest.fixture(scope="module")
def scene(tiny_model):
    model, _ = load_model(tiny_model)
    camera = model.views["train"].cameras(0)[0]
    opacity = render_camera(model.field, camera, 0).opacity.numpy()
    ys, xs = np.nonzero(opacity > 0.5)
    scribble = np.zeros_like(opacity, dtype=bool)
    scribble[ys[: max(3, len(ys) // 4)], xs[: max(3, len(xs) // 4)]] = True
    return model, camera, scribble


def test_as_mask_takes_tensors_and_numbers_and_names_bad_input():
    m = np.array([[True, False], [False, True]])
    for given in (m, torch.from_numpy(m), m.astype(np.uint8), m.astype(np.float32), m.tolist()):
        out = as_mask(given)
        assert out.dtype == bool and np.array_equal(out, m)
    assert np.array_equal(as_mask(np.array([[0.2, 0.7]])), [[False, True]])  # floats: 0.5 or more
    with pytest.raises(CrfError, match=r"keep mask: expected a \[H, W\] array .* shape \[2, 2, 3\]"):
        as_mask(np.zeros((2, 2, 3), bool), "keep")
    with pytest.raises(CrfError, match="NaN"):
        as_mask(np.array([[np.nan, 1.0]]))
    with pytest.raises(CrfError, match="expected a \\[H, W\\] array"):
        as_mask("not a mask")


def test_an_edit_reads_a_torch_mask_as_the_numpy_one(scene):
    model, camera, scribble = scene
    a = edit_color(model, 0, camera, scribble, "red", options=FAST)
    b = edit_color(model, 0, camera, torch.from_numpy(scribble), "red", options=FAST)
    c = edit_color(model, np.int64(0), camera, scribble.astype(np.uint8), (1.0, 0.0, 0.0), options=FAST)
    for other in (b, c):
        assert other.tensors.keys() == a.tensors.keys() and all(torch.equal(other.tensors[n], t) for n, t in a.tensors.items())


def test_colours_instances_renders_devices_and_paths_refuse_bad_input(scene, tiny_model, tmp_path):
    model, camera, scribble = scene
    assert as_rgb("#f00") == as_rgb((1, 0, 0)) == (1.0, 0.0, 0.0)
    for bad in ((255, 0, 0), (1.0, 0.0), (float("nan"), 0, 0), 3):
        with pytest.raises(CrfError, match="three numbers"):
            as_rgb(bad)
    with pytest.raises(CrfError, match="three numbers"):  # refused before any work, not trained toward
        edit_color(model, 0, camera, scribble, (255, 0, 0), options=FAST)
    for bad in (True, 0.0, None):
        with pytest.raises(CrfError, match="expected an instance name or an integer index"):
            model.instance_index(bad)
    for bad in (99, -1, "chair_000", True):
        with pytest.raises(CrfError, match="is not an index of the field's 2 instances"):
            render_camera(model.field, camera, bad)
    with pytest.raises(CrfError, match="chunk 0"):
        render_camera(model.field, camera, 0, chunk=0)
    assert torch.equal(render_camera(model.field, camera, np.int64(1)).rgb, render_camera(model.field, camera, 1).rgb)
    with pytest.raises(CrfError, match="expected auto, cpu or cuda"):
        load_model(tiny_model, "gpu")
    assert load_model(tiny_model, "cpu:0")[0].device == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(CrfError, match="no CUDA device"):
            load_model(tiny_model, "cuda:0")
    edit = tmp_path / "e.safetensors"
    remove(model, 0, camera, scribble, options=FAST).save(edit)
    assert 0 in apply_edit_files(model, edit).overrides  # one path alone is a stack of one


def test_preview_refuses_another_model_s_selection(scene, tiny_model):
    model, camera, scribble = scene
    sel = select_for(model, 0, camera, scribble, None, "color")
    other, _ = load_model(tiny_model)
    with torch.no_grad():
        other.field.F_dens.bias += 0.5
    assert preview(model, sel, camera).shape == (camera.height, camera.width, 3)
    with pytest.raises(CrfError, match="made for another model"):
        preview(other, sel, camera)


def test_a_selection_made_without_the_stack_s_edits_says_so(scene, tmp_path):
    """A selection of the bare model used on the model with an earlier edit applied (README's
    recolour, then a removal with --selection): the error says which edits are missing, not
    that the model is another one."""
    from crfedit.edit import transfer

    model, camera, scribble = scene
    sel = select_for(model, 0, camera, scribble, None, "color")
    transfer(model, 0, color_from=1).save(tmp_path / "t.safetensors")
    stacked = apply_edit_files(model, [tmp_path / "t.safetensors"])
    with pytest.raises(CrfError, match=r"made on the model without the 1 earlier edit\(s\) applied here; make it with the same --edit files"):
        sel.check_for(stacked, 0)
    sel.check_for(model, 0)  # the model it was made on


def test_an_edit_s_seconds_count_the_selection_it_made(scene, monkeypatch):
    import crfedit.edit.shape as shape

    model, camera, scribble = scene
    slow = shape.select_for

    def select_slowly(*args, **kwargs):
        time.sleep(0.3)
        return slow(*args, **kwargs)

    monkeypatch.setattr(shape, "select_for", select_slowly)
    result = remove(model, 0, camera, scribble, options=FAST)
    assert result.seconds >= 0.3 and result.meta["seconds"] == f"{result.seconds:.3f}"
    given = remove(model, 0, camera, scribble, options=FAST, selection=slow(model, 0, camera, scribble, None, "remove"))
    assert given.seconds < 0.3 <= result.seconds


def test_names_for_instances_and_the_library_s_own_checks(scene, tmp_path):
    """What a script author met (sixty-seventh session): ``field_for`` of a name gave the
    unedited field; ``resolve_views`` and ``score_model`` failed deep inside on a name; a view
    spec string or a focal of 0 given for a camera, a NaN background, uint8 images to score,
    reserved keys in ``save``'s provenance (a file crfedit then refused) — each one CrfError line,
    or the right answer.  ``select_for`` records the kind it selected for, as ``select --for``."""
    from dataclasses import replace

    from crfedit.cameras import Camera
    from crfedit.delta import read_delta
    from crfedit.metrics import score_images
    from crfedit.views import resolve_views

    model, camera, scribble = scene
    result = edit_color(model, 0, camera, scribble, "red", options=FAST)
    edited = result.model
    name = edited.names[0]
    field = edited.field_for(name)
    assert field is not edited.field and all(torch.equal(a, b) for a, b in zip(field.parameters(), edited.field_for(0).parameters()))
    with pytest.raises(CrfError, match="out of range"):
        edited.field_for(99)
    assert [c.c2w.tolist() for _, c in resolve_views("train:0", model, name)] == [c.c2w.tolist() for _, c in resolve_views("train:0", model, 0)]
    listed = Camera(camera.c2w.tolist(), camera.focal, camera.width, camera.height)
    assert isinstance(listed.c2w, np.ndarray) and torch.equal(render_camera(model.field, listed, 0).rgb, render_camera(model.field, camera, 0).rgb)
    with pytest.raises(CrfError, match="camera: focal 0.0 must be a positive number"):
        render_camera(model.field, replace(camera, focal=0.0), 0)
    with pytest.raises(CrfError, match="background nan must be a grey level from 0 to 1"):
        render_camera(model.field, camera, 0, background=float("nan"))
    with pytest.raises(CrfError, match="camera: expected a Camera, not str"):
        remove(model, 0, "train:0", scribble, options=FAST)
    image = np.full((8, 8, 3), 128, np.uint8)
    with pytest.raises(CrfError, match="prediction 0: values are uint8; give floats in"):
        score_images([image], [image])
    with pytest.raises(CrfError, match="target 0: holds NaN or infinite values"):
        score_images([np.full((8, 8, 3), 0.5)], [np.full((8, 8, 3), np.nan)])
    from crfedit.evaluation import score_model

    for bad in ([], "chair_000", 0, (k for k in [0])):  # a bare name iterated its letters ("unknown instance 'c'"); 0 had no len()
        with pytest.raises(CrfError, match="give a list of instance names or indices"):
            score_model(model, None, instances=bad)
    read_only = np.full((8, 8, 3), 0.5, np.float32)
    read_only.flags.writeable = False
    with warnings.catch_warnings():  # an array read from PIL is read-only: torch warned on stderr
        warnings.simplefilter("error")
        assert score_images([read_only], [read_only])["psnr"] == float("inf")
    with pytest.raises(CrfError, match="save: instance, kind are the edit's own metadata"):
        result.save(tmp_path / "e.safetensors", kind="recolour", instance="other")
    with pytest.raises(CrfError, match="save: final_loss is the edit's own metadata"):
        result.save(tmp_path / "e.safetensors", final_loss="abc")
    with pytest.raises(CrfError, match="save: a metadata key is empty"):
        result.save(tmp_path / "e.safetensors", **{"": "x"})
    result.save(tmp_path / "e.safetensors", note="kept\nby a script")
    assert read_delta(tmp_path / "e.safetensors").meta["note"] == "kept\nby a script"
    from cli_helpers import invoke

    shown = invoke("edits", "show", tmp_path / "e.safetensors").stdout  # a script's own key gets its row
    assert "\nnote          kept\\nby a script\n" in shown and "first_loss" not in result.meta  # one line, the break escaped; 2 steps: too few to judge
    ten = edit_color(model, 0, camera, scribble, "red", options=EditOptions(steps=10, rays=128))
    ten.save(tmp_path / "t.safetensors")
    shown = invoke("edits", "show", tmp_path / "t.safetensors").stdout
    assert f"\nfirst_loss    {ten.meta['first_loss']}\nfit_loss      {ten.meta['fit_loss']}\n" in shown, shown
    assert float(ten.meta["first_loss"]) > float(ten.meta["fit_loss"])
    assert select_for(model, 0, camera, scribble, None, "remove").meta["for"] == "remove"
    from crfedit.evaluation import evaluate_edits

    with pytest.raises(CrfError, match="tpu"):  # the baseline's device, checked before any work (it was ignored)
        evaluate_edits(model, None, [], device="tpu")



def test_the_commands_progress_bar_changes_nothing_the_edit_computes(scene, monkeypatch):
    """`edit-color`, `remove` and `add` draw a progress bar once an edit has run a second
    (``--rays 4194304`` ran for minutes without a word): its ``on_step`` reads each step's loss,
    and the edit is bit-identical to the one without it; a second fit (a recolour refitted)
    starts the count again."""
    import crfedit.cli.edit as cli_edit

    monkeypatch.setattr(cli_edit, "SHOW_AFTER", 0.0)
    model, camera, scribble = scene
    options = EditOptions(steps=12, rays=128)
    plain = edit_color(model, 0, camera, scribble, "red", options=options)
    with cli_edit.edit_progress(options, "colour edit") as shown:
        assert shown.on_step is not None and options.on_step is None
        barred = edit_color(model, 0, camera, scribble, "red", options=shown)
    assert barred.tensors.keys() == plain.tensors.keys() and all(torch.equal(barred.tensors[n], t) for n, t in plain.tensors.items())
    assert barred.meta["first_loss"] == plain.meta["first_loss"] and barred.meta["fit_loss"] == plain.meta["fit_loss"]
    with cli_edit.edit_progress(EditOptions(steps=3), "removal") as shown:
        for step in (1, 2, 3, 1, 2, 3):  # a refit: the bar is reset, nothing raises
            shown.on_step(step, 0.1)
