"""Edit files: exactly the touched tensors, instance scoping, stacks (order, base, parent), revert,
bake, and clear one-line errors for files that are damaged or belong elsewhere.

Uses a tiny untrained field with hand-set occupancy: every property here is bitwise, not about
what an edit looks like (tests/test_edits.py covers that on a trained model).
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from typer.testing import CliRunner

from crfedit.cameras import Camera, look_at
from crfedit.cli import app
from crfedit.config import make_config
from crfedit.delta import (
    Delta,
    apply_deltas,
    apply_edit_files,
    bake,
    chain_fingerprint,
    grow,
    instance_state,
    make_delta,
    read_delta,
    save_delta,
    stack_of,
)
from crfedit.edit import EditOptions, edit_color, swap_codes, transfer
from crfedit.errors import CrfError, ModelFileError
from crfedit.field import ConditionalRadianceField
from crfedit.model import CategoryModel, ViewTable, load_model, save_model
from crfedit.renderer import render_camera

from cli_helpers import assert_user_error

RES = 12


def camera(azimuth: float = 0.3) -> Camera:
    eye = np.array([2.0 * np.cos(azimuth), 2.0 * np.sin(azimuth), 0.6])
    return Camera(look_at(eye), 14.0, RES, RES)


def make_model(n: int = 3, seed: int = 0) -> CategoryModel:
    cfg = make_config("fast", overrides=dict(code_dim=4, code_embed=5, width=16, rad_width=12, grid_res=4, grid_features=2, occ_res=8))
    torch.manual_seed(seed)
    field = ConditionalRadianceField(cfg, n)
    with torch.no_grad():
        field.shape_codes.normal_()
        field.color_codes.normal_()
        field.F_share.grid.normal_()
        field.F_dens.bias.fill_(2.0)
        c = (torch.arange(8) + 0.5) / 4 - 1
        r = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).norm(dim=-1)
        for k in range(n):
            field.occupancy[k] = r < 0.5 + 0.2 * k
    cams = [camera(a) for a in (0.3, 1.5, 2.7)]
    table = ViewTable(
        torch.tensor(np.stack([c.c2w for c in cams * n])), torch.full((3 * n,), 14.0, dtype=torch.float64),
        torch.arange(n).repeat_interleave(3), RES, RES,
    )
    return CategoryModel(field, [f"chair_{i}" for i in range(n)], "dataset0", views={"train": table})


def render(model: CategoryModel, k: int, cam: Camera | None = None) -> torch.Tensor:
    return render_camera(model.field_for(k), cam or camera(), k).rgb


def perturbed(model: CategoryModel, k: int, names: dict[str, float]) -> CategoryModel:
    """``model`` with instance k's tensors ``names`` shifted by the given amounts (code tables: row k)."""
    state = dict(model.field.state_dict())
    state.update(model.overrides.get(k, {}))
    replaced = dict(model.overrides.get(k, {}))
    for name, shift in names.items():
        t = state[name].clone()
        if name in ("shape_codes", "color_codes"):
            t[k] += shift
        elif name == "occupancy":
            t[k] = ~t[k]
        else:
            t += shift
        replaced[name] = t
    return dataclasses.replace(model, overrides={**model.overrides, k: replaced})


def delta_file(tmp_path: Path, name: str, before: CategoryModel, k: int, kind: str, shifts: dict[str, float], modules) -> Path:
    tensors, meta = make_delta(before, perturbed(before, k, shifts), k, kind, modules, {"command": "test"})
    path = tmp_path / name
    save_delta(path, tensors, meta)
    return path


@pytest.fixture()
def model() -> CategoryModel:
    return make_model()


def test_delta_holds_exactly_the_touched_tensors(tmp_path, model):
    path = delta_file(tmp_path, "a.safetensors", model, 1, "color", {"F_rad.out.bias": 0.1, "color_codes": 0.5}, ("F_rad.", "color_codes"))
    d = read_delta(path)
    f_rad = {n for n, _ in model.field.named_parameters() if n.startswith("F_rad.")}
    assert set(d.tensors) == f_rad | {"color_code"}
    assert d.tensors["color_code"].shape == (4,)
    torch.testing.assert_close(d.tensors["color_code"], torch.full((4,), 0.5), rtol=0, atol=1e-6)
    torch.testing.assert_close(d.tensors["F_rad.out.bias"], torch.full((3,), 0.1), rtol=0, atol=1e-6)
    assert float(d.tensors["F_rad.out.weight"].abs().max()) == 0.0
    meta = d.meta
    assert (meta["format"], meta["kind"], meta["instance"], meta["parent"]) == ("crfedit-edit", "color", "chair_1", "")
    assert json.loads(meta["modules"]) == ["F_rad.", "color_codes"] and meta["base"] == model.fingerprint()
    grid = delta_file(tmp_path, "g.safetensors", model, 0, "remove", {"F_dens.bias": -0.5, "occupancy": 0}, ("F_dens.", "occupancy"))
    g = read_delta(grid)
    assert set(g.tensors) == {"F_dens.weight", "F_dens.bias", "occupancy"}
    assert g.tensors["occupancy"].dtype == torch.int8 and g.tensors["occupancy"].shape == (8, 8, 8)
    old = model.field.occupancy[0]  # the grid's change, after − before: the edit inverted the grid
    assert torch.equal(g.tensors["occupancy"], torch.where(old, -1, 1).to(torch.int8))
    assert g.meta["version"] == "4" and "occupancy_shape" not in g.meta
    with safe_open(str(grid), "pt") as f:  # on disk: bit-packed, 1 bit a cell + 1 bit a changed cell
        assert sorted(f.keys()) == ["F_dens.bias", "F_dens.weight", "occupancy.changed", "occupancy.gained"]
        assert f.get_tensor("occupancy.changed").tolist() == [255] * 64 and f.get_tensor("occupancy.gained").numel() == 64
        assert json.loads(f.metadata()["occupancy_shape"]) == [8, 8, 8]


def test_other_instances_bit_identical_and_input_untouched(tmp_path, model):
    fp = model.fingerprint()
    renders = [render(model, k) for k in range(3)]
    path = delta_file(tmp_path, "a.safetensors", model, 1, "color", {"F_rad.out.bias": 0.3, "color_codes": 1.0}, ("F_rad.", "color_codes"))
    edited = apply_edit_files(model, [path])
    assert model.fingerprint() == fp and not model.overrides
    assert edited.field is model.field and set(edited.overrides) == {1}
    for k in (0, 2):
        assert edited.field_for(k) is model.field
        assert torch.equal(render(edited, k), renders[k])
    assert not torch.allclose(render(edited, 1), renders[1])


def test_real_edit_roundtrips_through_its_file(tmp_path, model):
    cam = camera()
    scribble = np.zeros((RES, RES), bool)
    scribble[4:8, 4:8] = True
    result = edit_color(model, 0, cam, scribble, "red", options=EditOptions(steps=3, rays=64), method="paper")
    result.save(tmp_path / "e.safetensors", command="crfedit edit-color …")
    loaded = apply_edit_files(model, [tmp_path / "e.safetensors"])
    assert torch.equal(render(loaded, 0), render(result.model, 0))
    assert not torch.equal(render(loaded, 0), render(model, 0))
    assert read_delta(tmp_path / "e.safetensors").meta["command"] == "crfedit edit-color …"


def test_stack_then_revert_is_bit_identical(tmp_path, model):
    original = [render(model, k) for k in range(3)]
    a = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    after_a = apply_edit_files(model, [a])
    b = delta_file(tmp_path, "b.safetensors", after_a, 0, "remove", {"F_dens.bias": -1.0}, ("F_dens.",))
    after_ab = apply_edit_files(model, [a, b])
    assert read_delta(b).meta["parent"] == chain_fingerprint(model.fingerprint(), [read_delta(a).fingerprint])
    assert not torch.equal(render(after_ab, 0), render(after_a, 0))
    assert torch.equal(render(apply_edit_files(model, [a]), 0), render(after_a, 0))  # b left out
    reverted = apply_edit_files(model, [])
    for k in range(3):
        assert torch.equal(render(reverted, k), original[k])
    # applying in two goes continues the same stack
    assert apply_edit_files(after_a, [b]).fingerprint() == after_ab.fingerprint()


def grid_edit(before: CategoryModel, k: int, cells: torch.Tensor, occupied: bool, name: str, tmp_path: Path) -> Path:
    """A removal (``occupied=False``) or addition file that only sets instance k's ``cells`` [R, R, R]."""
    grid = dict(before.field.state_dict(), **before.overrides.get(k, {}))["occupancy"].clone()
    grid[k] = grid[k] | cells if occupied else grid[k] & ~cells
    after = dataclasses.replace(before, overrides={**before.overrides, k: {**before.overrides.get(k, {}), "occupancy": grid}})
    tensors, meta = make_delta(before, after, k, "remove" if not occupied else "add", ("occupancy",))
    save_delta(tmp_path / name, tensors, meta)
    return tmp_path / name


def test_dropping_an_earlier_grid_edit_gives_its_cells_back(tmp_path, model):
    """Two removals of one instance; the first left out and the second re-pinned (as ``crfedit
    edits rebase`` and the page's off switch do): the first removal's cells are occupied again,
    the second's stay empty.  (Format version 1 stored the second's grid itself, which kept the
    first's cells empty: a revert that did not revert.)"""
    from crfedit.delta import rebase

    grid0 = model.field.occupancy[0].clone()
    low, high = torch.zeros_like(grid0), torch.zeros_like(grid0)
    low[:, :, :4], high[:, :, 4:] = True, True
    a = grid_edit(model, 0, low, False, "a.safetensors", tmp_path)
    after_a = apply_edit_files(model, [a])
    b = grid_edit(after_a, 0, high, False, "b.safetensors", tmp_path)
    both = apply_edit_files(model, [a, b])
    assert not bool(both.field_for(0).occupancy[0].any())  # both halves emptied
    only_b = apply_deltas(model, [rebase(read_delta(b), model)])
    assert torch.equal(only_b.field_for(0).occupancy[0], grid0 & ~high)
    # an addition's cells come back empty when it is left out, the same way
    c = grid_edit(both, 0, high & grid0, True, "c.safetensors", tmp_path)
    assert torch.equal(apply_edit_files(model, [a, b, c]).field_for(0).occupancy[0], grid0 & high)


def test_version_1_and_2_files_still_apply(tmp_path, model):
    """A version-1 file stores the new grid itself (bool) and still replaces the instance's grid;
    a version-2 file stores the change unpacked (int8) and applies as version 3's packed one."""
    v3 = grid_edit(model, 1, torch.ones_like(model.field.occupancy[1]), False, "v3.safetensors", tmp_path)
    d = read_delta(v3)
    new_grid = model.field.occupancy[1] & (d.tensors["occupancy"] >= 0)
    v1 = rewrite(v3, tmp_path / "v1.safetensors", {"occupancy": new_grid}, {"version": "1"})
    v2 = rewrite(v3, tmp_path / "v2.safetensors", dict(d.tensors), {"version": "2"})
    assert torch.equal(read_delta(v2).tensors["occupancy"], d.tensors["occupancy"])
    for path in (v1, v2, v3):
        assert torch.equal(apply_edit_files(model, [path]).field_for(1).occupancy[1], new_grid)
    # re-pinned (`edits rebase`, the page's stack), a file keeps its version and its encoding
    for path, version in ((v1, "1"), (v2, "2")):
        other = save_delta_back(read_delta(path), tmp_path / f"again{version}.safetensors")
        assert read_delta(other).meta["version"] == version and other.stat().st_size == path.stat().st_size
    with pytest.raises(ModelFileError, match="has dtype I8"):  # a version-1 file with a change
        read_delta(rewrite(v2, tmp_path / "mixed.safetensors", dict(d.tensors), {"version": "1"}))
    with pytest.raises(ModelFileError, match="has dtype BOOL"):  # a version-2 file with a grid
        read_delta(rewrite(v3, tmp_path / "mixed2.safetensors", {"occupancy": new_grid}, {"version": "2"}))
    with pytest.raises(ModelFileError, match="values other than -1, 0 and 1"):
        read_delta(rewrite(v3, tmp_path / "two.safetensors", {"occupancy": d.tensors["occupancy"] * 2}, {"version": "2"}))
    with pytest.raises(ModelFileError, match="has dtype I8 .*bit-packed"):  # a version-3 file with an int8 change
        read_delta(rewrite(v3, tmp_path / "mixed3.safetensors", dict(d.tensors)))
    from crfedit.delta import pack_grid_change

    packed, dims = pack_grid_change(d.tensors["occupancy"])
    rest = {k: v for k, v in d.tensors.items() if k != "occupancy"}
    for i, (t, meta) in enumerate((({**rest, "occupancy.changed": packed["occupancy.changed"]}, {"occupancy_shape": dims}), ({**rest, **packed}, {}))):
        with pytest.raises(ModelFileError, match="stores its occupancy change as occupancy.changed and occupancy.gained with occupancy_shape"):
            read_delta(rewrite(v3, tmp_path / f"half{i}.safetensors", t, meta))
    whole = rewrite(v3, tmp_path / "whole.safetensors", {**rest, **packed}, {"occupancy_shape": dims}, refingerprint=False)
    assert torch.equal(read_delta(whole).tensors["occupancy"], d.tensors["occupancy"])  # written by hand, read the same


def save_delta_back(d, path: Path) -> Path:
    save_delta(path, d.tensors, d.meta)
    return path


def test_grid_change_packs_and_unpacks_exactly(tmp_path):
    """Version 3's bit-packing round-trips every change (gains, losses, none, a size that is not a
    multiple of 8) to the bit, at 1/8 of a byte a cell plus a bit a changed cell."""
    from crfedit.delta import pack_grid_change, unpack_grid_change

    g = torch.Generator().manual_seed(0)
    for shape in ((8, 8, 8), (5, 3, 7), (64, 64, 64)):
        for p in (0.0, 0.03, 0.5, 1.0):
            change = torch.randint(0, 2, shape, generator=g).to(torch.int8) * 2 - 1
            change[torch.rand(shape, generator=g) >= p] = 0
            packed, dims = pack_grid_change(change)
            n, c = change.numel(), int((change != 0).sum())
            assert packed["occupancy.changed"].numel() == (n + 7) // 8 and packed["occupancy.gained"].numel() == (c + 7) // 8
            back = unpack_grid_change(packed["occupancy.changed"], packed["occupancy.gained"], dims)
            assert back.dtype == torch.int8 and torch.equal(back, change)
    changed, gained = packed["occupancy.changed"], packed["occupancy.gained"]
    cases = [
        (changed[:-1], gained, "[64, 64, 64]", "has 32767 bytes, 262144 cells need 32768"),
        (changed, gained[:-1], "[64, 64, 64]", "262144 changed cells need 32768"),
        (changed, gained, "[64, 64]", "must be a JSON list of 3 sizes from 1 to 512"),
        (changed, gained, "[100000, 100000, 100000]", "3 sizes from 1 to 512, not '[100000"),  # allocates nothing
        (changed, gained, "[512, 512, 512]", "134217728 cells need 16777216"),  # nor does a shape the bits do not fill
        (changed.to(torch.int8), gained, "[64, 64, 64]", "must be a 1-d uint8 tensor"),
        (torch.tensor([255, 1], dtype=torch.uint8), torch.zeros(2, dtype=torch.uint8), "[3, 3, 1]", "padding bits are not zero"),
        (torch.tensor([255, 128], dtype=torch.uint8), torch.tensor([0, 1], dtype=torch.uint8), "[3, 3, 1]", "gained's padding bits are not zero"),
    ]
    for ch, ga, dims, message in cases:
        with pytest.raises(ModelFileError, match=message.replace("[", r"\[").replace("]", r"\]")) as e:
            unpack_grid_change(ch, ga, dims)
        assert "\n" not in str(e.value)


def test_wrong_order_parent_and_base_are_rejected(tmp_path, model):
    a = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    b = delta_file(tmp_path, "b.safetensors", apply_edit_files(model, [a]), 1, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    c = delta_file(tmp_path, "c.safetensors", model, 2, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    with pytest.raises(ModelFileError, match=r"b\.safetensors: was made after .*a\.safetensors; pass the --edit files in the order"):
        apply_edit_files(model, [b, a])
    with pytest.raises(ModelFileError, match=r"b\.safetensors: was made after other edits .*; or it was re-pinned onto a model "
                                             r"with edits baked in: apply it to that one\); pass the --edit files"):
        apply_edit_files(model, [b])  # first, on the bare model: re-pinned onto a baked model is the other way it comes
    # an edit missing from the stack: the line names the stack its command was given
    from crfedit.delta import check_stack, read_delta

    missing = read_delta(b)
    missing.meta["command"] = "crfedit edit-color m.safetensors --edit 'x/a 1.safetensors' --edit=x/z.safetensors --out b.safetensors"
    with pytest.raises(ModelFileError, match=r"was made after other edits .*; it was made on 2 edits \(x/a 1\.safetensors, "
                                             r"x/z\.safetensors, as recorded\), here 0 come before it\); pass"):
        check_stack(model, [missing])
    with pytest.raises(ModelFileError, match=r"c\.safetensors: made on the bare model, as .*a\.safetensors was: they are two edits of one "
                                             r"model, not a stack; to apply both, re-pin them as one with `crfedit edits rebase"):
        apply_edit_files(model, [a, c])
    with pytest.raises(ModelFileError, match=r"c\.safetensors: made on the bare model, but this model has 1 edit applied already; "
                                             r"apply it to the model it was made on, or re-pin it onto this one with `crfedit edits rebase"):
        apply_edit_files(apply_edit_files(model, [a]), [c])  # first of the stack, but the model stands on an edit
    with pytest.raises(ModelFileError, match=r"a\.safetensors: is given twice \(edit 2 of the stack"):
        apply_edit_files(model, [a, a])
    other = make_model(seed=1)
    with pytest.raises(ModelFileError, match=rf"a\.safetensors: made for model {model.fingerprint()}, not this model \({other.fingerprint()}\)"):
        apply_edit_files(other, [a])
    for bad in ([b, a], [a, c]):
        with pytest.raises(ModelFileError) as e:
            apply_edit_files(model, bad)
        assert "\n" not in str(e.value)


def test_instance_and_names_checked_against_the_model(tmp_path, model):
    a = delta_file(tmp_path, "a.safetensors", model, 2, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    two = dataclasses.replace(model, names=["chair_0", "chair_1", "other"])
    with pytest.raises(ModelFileError, match="instance 'chair_2', which the model does not have"):
        apply_edit_files(two, [a])
    # any parameter may be stored by a weight-training edit (strategy all), none by a transfer
    tensors, meta = make_delta(model, perturbed(model, 0, {"F_dens.bias": 0.1}), 0, "color", ("F_dens.",))
    save_delta(tmp_path / "bad.safetensors", tensors, meta)
    apply_edit_files(model, [tmp_path / "bad.safetensors"])
    tensors, meta = make_delta(model, perturbed(model, 0, {"F_dens.bias": 0.1}), 0, "transfer", ("F_dens.",))
    save_delta(tmp_path / "t.safetensors", tensors, meta)
    with pytest.raises(ModelFileError, match="a transfer edit may not hold tensor 'F_dens\\.(weight|bias)'"):
        apply_edit_files(model, [tmp_path / "t.safetensors"])


def test_bake_renders_bit_identical_to_the_stack(tmp_path, model):
    a = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2, "color_codes": 0.7}, ("F_rad.", "color_codes"))
    b = delta_file(tmp_path, "b.safetensors", apply_edit_files(model, [a]), 0, "remove",
                   {"F_dens.bias": -0.5, "occupancy": 0}, ("F_fuse.", "F_dens.", "occupancy"))
    stacked = apply_edit_files(model, [a, b])
    baked = bake(model, [a, b])
    save_model(tmp_path / "baked.safetensors", baked)
    loaded, state = load_model(tmp_path / "baked.safetensors")
    assert not state and set(loaded.overrides) == {0}
    # the baked grid and code tables are stored as chair 0's own rows (the rest is the field's), read back whole
    from safetensors import safe_open

    with safe_open(str(tmp_path / "baked.safetensors"), "pt") as f:
        stored = {n: tuple(f.get_slice(n).get_shape()) for n in f.keys() if n.startswith("override.0.")}
    assert stored["override.0.occupancy"] == tuple(model.field.occupancy.shape[1:]) and stored["override.0.color_codes"] == (model.field.color_codes.shape[1],)
    assert loaded.fingerprint() == baked.fingerprint() and torch.equal(loaded.overrides[0]["occupancy"], baked.overrides[0]["occupancy"])
    from crfedit.modelfile import model_info  # `info` reports the grid chair 0 renders with, the baked one

    fill = model_info(tmp_path / "baked.safetensors")["occupancy"]["fill"]
    assert fill[model.names[0]] == pytest.approx(float(loaded.overrides[0]["occupancy"][0].float().mean()))
    assert fill[model.names[0]] != pytest.approx(float(model.field.occupancy[0].float().mean()))
    for k in range(3):
        assert torch.equal(render(loaded, k), render(stacked, k))
    assert json.loads(loaded.meta["baked_edits"]) == [read_delta(a).fingerprint, read_delta(b).fingerprint]
    c = delta_file(tmp_path, "c.safetensors", model, 2, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    with pytest.raises(ModelFileError, match=r"c\.safetensors: made on the bare model, but this model has 2 edits baked in \(crfedit info"):
        apply_edit_files(loaded, [c])  # said it must come first, and it was first
    with pytest.raises(ModelFileError, match="a.safetensors: is already baked into this model"):
        apply_edit_files(loaded, [a])
    # the baked model stands where the stack does: an edit made on it continues the unbaked stack
    # (and the other way round), and a bake of a bake lists every edit since the first base
    c = delta_file(tmp_path, "c.safetensors", loaded, 1, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    assert read_delta(c).meta["base"] == model.fingerprint()
    assert read_delta(c).meta["parent"] == chain_fingerprint(model.fingerprint(), [read_delta(p).fingerprint for p in (a, b)])
    on_baked, on_stack = apply_edit_files(loaded, [c]), apply_edit_files(model, [a, b, c])
    for k in range(3):
        assert torch.equal(render(on_baked, k), render(on_stack, k))
    half = bake(model, [a])  # a stack baked part way goes on with the rest
    assert all(torch.equal(render(apply_edit_files(half, [b, c]), k), render(on_stack, k)) for k in range(3))
    twice = bake(half, [b, c])
    assert json.loads(twice.meta["baked_edits"]) == [read_delta(p).fingerprint for p in (a, b, c)]
    assert twice.meta["baked_from"] == model.fingerprint()
    with pytest.raises(ModelFileError, match="b.safetensors: is already baked into this model"):
        apply_edit_files(twice, [b])
    with pytest.raises(ModelFileError, match="b.safetensors: is already applied to this model"):
        apply_edit_files(apply_edit_files(model, [a, b]), [b])
    # a bake whose weights changed since (trained on) is a base of its own, as before this record
    changed = dataclasses.replace(loaded, meta={**loaded.meta, "edit_state": "0" * 16})
    assert stack_of(changed) == (changed.fingerprint(), [])


def test_transfer_delta_equals_swap_codes(tmp_path, model):
    result = transfer(model, 0, shape_from=2, color_from=1)
    assert set(result.tensors) == {"shape_code", "color_code", "occupancy"}
    result.save(tmp_path / "t.safetensors")
    via_file = apply_edit_files(model, [tmp_path / "t.safetensors"])
    swapped = swap_codes(model, 0, shape_from=2, color_from=1)
    assert swapped.field is model.field
    assert torch.equal(render(via_file, 0), render(swapped, 0))
    assert torch.equal(swapped.overrides[0]["occupancy"][0], model.field.occupancy[2])
    torch.testing.assert_close(swapped.overrides[0]["color_codes"][0], model.field.color_codes[1].detach(), rtol=1e-6, atol=1e-6)
    with pytest.raises(CrfError, match="give --shape-from or --color-from"):
        swap_codes(model, 0)


def test_a_transfer_that_changes_nothing_is_refused(model):
    """The same colour transfer given again on its own result wrote an edit of zeros in
    silence, while a transfer from the instance itself is refused: both are refused now."""
    first = transfer(model, 0, color_from=1)
    with pytest.raises(CrfError, match=r"^chair_0 already renders with chair_1's colour code \(a transfer of it already applied\?\): "
                                       r"this transfer changes nothing; nothing was written$"):
        transfer(first.model, 0, color_from=1)
    assert transfer(first.model, 0, color_from=2).tensors["color_code"].abs().sum() > 0  # another source still moves it


def test_a_transfer_rebased_still_takes_its_source_s_code(tmp_path, model):
    """Three colour transfers onto chair 0 (from 1, then 2, then 1 again, each on the one before);
    the middle one left out, the last still gives chair 0 exactly chair 1's colour code and the
    grid a shape transfer took, where its stored difference would give a code no chair has."""
    from crfedit.delta import restack

    files, current = [], model
    for i, source in enumerate((1, 2, 1)):
        result = transfer(current, 0, color_from=source, shape_from=2 if i == 1 else None)
        result.save(tmp_path / f"t{i}.safetensors")
        files.append(read_delta(tmp_path / f"t{i}.safetensors"))
        current = result.model
    kept, pinned = restack(model, [files[0], files[2]])
    torch.testing.assert_close(instance_state(kept, 0)["color_codes"][0], model.field.color_codes[1].detach(), rtol=0, atol=1e-6)
    assert torch.equal(kept.field_for(0).occupancy[0], model.field.occupancy[0])  # the shape transfer left out: chair 0's grid
    stale = files[2].tensors["color_code"]  # as stored: chair 1 minus chair 2, from the place it was made
    assert not torch.allclose(pinned[1].tensors["color_code"], stale)
    # the shape transfer alone, moved to the front: it takes chair 2's grid and shape code where it now stands
    kept, _ = restack(model, [files[1]])
    assert torch.equal(kept.field_for(0).occupancy[0], model.field.occupancy[2])
    torch.testing.assert_close(instance_state(kept, 0)["color_codes"][0], model.field.color_codes[2].detach(), rtol=0, atol=1e-6)
    # in place, each transfer is the very same file
    assert all(a is b for a, b in zip(restack(model, files)[1], files))
    # a transfer from an instance a fit-real edit added, rebased without that edit: named, with the fix
    after = grow(model, "real_0")
    after.overrides[3] = {"color_codes": after.field.color_codes.detach().clone(), "occupancy": after.field.occupancy.clone()}
    tensors, meta = make_delta(model, after, "real_0", "fit-real", ("color_codes", "occupancy"))
    save_delta(tmp_path / "fit.safetensors", tensors, meta)
    grown = apply_edit_files(model, [tmp_path / "fit.safetensors"])
    transfer(grown, 0, color_from=3).save(tmp_path / "from_real.safetensors")
    with pytest.raises(ModelFileError, match=r"from_real\.safetensors: a transfer takes real_0's code, and real_0 is not in the model at this place"):
        restack(model, [read_delta(tmp_path / "from_real.safetensors")])


def test_a_transfer_s_source_is_part_of_its_fingerprint_and_must_be_named(tmp_path, model):
    """From version 4 a transfer's ``hyperparameters`` (whose code it took, which re-pinning
    reads) count into its fingerprint: renamed to another source, the file reads as damaged.
    A version-3 file (fingerprinted without them) whose hyperparameters name no source, or the
    instance itself, is refused by a rebase in one line instead of keeping its stale difference;
    hyperparameters that are not JSON are refused on reading."""
    from crfedit.delta import delta_fingerprint, restack

    first = transfer(model, 0, color_from=1)
    first.save(tmp_path / "a.safetensors")
    transfer(first.model, 0, color_from=2).save(tmp_path / "b.safetensors")
    b = read_delta(tmp_path / "b.safetensors")
    assert b.meta["version"] == "4" and json.loads(b.meta["hyperparameters"])["color_from"] == "chair_2"
    tampered = {**b.meta, "hyperparameters": json.dumps({"color_from": "chair_1"})}
    save_file(b.tensors, str(tmp_path / "t.safetensors"), metadata=tampered)
    with pytest.raises(ModelFileError, match=r"t\.safetensors: contents do not match the recorded fingerprint"):
        read_delta(tmp_path / "t.safetensors")
    for name, hyper, said in (("none", "{}", "does not name the instance whose color code it took"),
                              ("self", json.dumps({"color_from": "chair_0"}), "names 'chair_0' as the instance whose color code it took")):
        meta = {**b.meta, "version": "3", "hyperparameters": hyper}
        meta["fingerprint"] = delta_fingerprint(b.tensors, meta)
        save_file(b.tensors, str(tmp_path / f"{name}.safetensors"), metadata=meta)
        old = read_delta(tmp_path / f"{name}.safetensors")  # a version-3 file: reads, its hyperparameters outside the fingerprint
        with pytest.raises(ModelFileError, match=rf"{name}\.safetensors: a transfer's hyperparameters {said} \(color_from\), so it cannot be re-pinned"):
            restack(model, [old])  # b left without a: re-pinned, it must take its source's code again
    # a version-3 transfer made on the bare model whose source was edited to another: its stored
    # change is checked against the named source where it was made, and refused
    a = read_delta(tmp_path / "a.safetensors")
    meta = {**a.meta, "version": "3", "hyperparameters": json.dumps({"color_from": "chair_2"})}
    meta["fingerprint"] = delta_fingerprint(a.tensors, meta)
    save_file(a.tensors, str(tmp_path / "forged.safetensors"), metadata=meta)
    with pytest.raises(ModelFileError, match=r"forged\.safetensors: its hyperparameters say it took chair_2's color code, but the change it stores is not that"):
        restack(model, [read_delta(tmp_path / "forged.safetensors")])
    meta = {**a.meta, "version": "3"}  # the same file, its record true: re-pins (in place: the very file)
    meta["fingerprint"] = delta_fingerprint(a.tensors, meta)
    save_file(a.tensors, str(tmp_path / "true3.safetensors"), metadata=meta)
    assert restack(model, [read_delta(tmp_path / "true3.safetensors")])[1][0].tensors["color_code"].equal(a.tensors["color_code"])
    meta = {**b.meta, "hyperparameters": "not json"}
    meta["fingerprint"] = delta_fingerprint(b.tensors, meta)
    save_file(b.tensors, str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(ModelFileError, match=r"bad\.safetensors: bad edit metadata \(hyperparameters is not a JSON object\)"):
        read_delta(tmp_path / "bad.safetensors")


def test_rebase_notes_an_old_transfer_it_cannot_check(tmp_path, model):
    """A version-3 transfer made after another edit cannot be checked against its stored change
    on the bare model: re-pinned there, the rebase says so on stderr."""
    from crfedit.delta import delta_fingerprint

    save_model(tmp_path / "m.safetensors", model)
    m, _ = load_model(tmp_path / "m.safetensors")
    a = delta_file(tmp_path, "a.safetensors", m, 0, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    t = transfer(apply_edit_files(m, [a]), 1, color_from=2)
    meta = {**t.meta, "version": "3"}
    meta["fingerprint"] = delta_fingerprint(t.tensors, meta)
    save_delta(tmp_path / "t.safetensors", t.tensors, meta)
    done = CliRunner().invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(tmp_path / "t.safetensors"),
                                    "--out-dir", str(tmp_path / "out")])
    assert done.exit_code == 0, done.output
    assert ("note: t.safetensors is a format-version-3 transfer: the source it names (chair_2) lies outside its fingerprint "
            "and could not be checked") in done.stderr, done.stderr


@pytest.mark.parametrize("key,value", [("seconds", "abc"), ("final_loss", "nan"), ("first_loss", ""), ("inputs", "{bad"), ("stages", "{}"),
                                       ("final_loss", "1_0"), ("final_loss", "inf"), ("photo_psnr", "nan")])
def test_recorded_numbers_and_records_must_be_well_formed(tmp_path, model, key, value):
    """What an edit measured reads as a number, its JSON records as JSON of their type: a file
    whose ``seconds`` is ``abc`` (provenance, outside the fingerprint) is refused in one line,
    not shown as a string where ``--json`` promises a number."""
    good = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    d = read_delta(good)
    save_file(d.tensors, str(tmp_path / "x.safetensors"), metadata={**d.meta, key: value})
    what = "is not a number" if key in ("seconds", "final_loss", "first_loss", "photo_psnr") else "is not a JSON"
    with pytest.raises(ModelFileError, match=rf"x\.safetensors: bad edit metadata \({key}.*{what}"):
        read_delta(tmp_path / "x.safetensors")


def test_fit_real_delta_adds_an_instance(tmp_path, model):
    after = grow(model, "real_0")
    with torch.no_grad():
        table = after.field.shape_codes.detach().clone()
        table[3] = model.field.shape_codes[1]
        grid = after.field.occupancy.clone()
        grid[3] = model.field.occupancy[1]
    after.overrides[3] = {"shape_codes": table, "color_codes": after.field.color_codes.detach().clone(), "occupancy": grid}
    tensors, meta = make_delta(model, after, "real_0", "fit-real", ("shape_codes", "color_codes", "occupancy"))
    assert meta["adds_instance"] == "real_0"
    save_delta(tmp_path / "fit.safetensors", tensors, meta)
    grown = apply_edit_files(model, [tmp_path / "fit.safetensors"])
    assert grown.names == ["chair_0", "chair_1", "chair_2", "real_0"] and model.names == ["chair_0", "chair_1", "chair_2"]
    assert grown.field.n_instances == 4
    torch.testing.assert_close(grown.field_for(3).shape_codes[3], model.field.shape_codes[1].detach())
    base, stack = stack_of(grown)
    again = Delta("again.safetensors", tensors, {**meta, "parent": chain_fingerprint(base, stack)})
    with pytest.raises(ModelFileError, match="again.safetensors: adds instance 'real_0', which the model already has"):
        apply_deltas(grown, [again])

# ----------------------------------------------------------------------------- damaged files


def assert_one_line(error: pytest.ExceptionInfo, path: Path) -> str:
    msg = str(error.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_zero_byte_truncated_and_corrupt_files(tmp_path, model):
    good = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    data = good.read_bytes()
    cases = {
        "zero.safetensors": b"",
        "truncated.safetensors": data[: len(data) // 2],
        "header.safetensors": struct.pack("<Q", 40) + b"{not json" + b" " * 31,
        "flipped.safetensors": data[:-4] + bytes([data[-4] ^ 1]) + data[-3:],  # a last-bit change of one float
    }
    expected = {
        "zero.safetensors": "only 0 bytes",
        "truncated.safetensors": "corrupt",
        "header.safetensors": "corrupt safetensors header",
        "flipped.safetensors": "do not match the recorded fingerprint",
    }
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(ModelFileError) as e:
            apply_edit_files(model, [good, tmp_path / name])
        assert expected[name] in assert_one_line(e, tmp_path / name)
    with pytest.raises(ModelFileError, match="file not found"):
        apply_edit_files(model, [tmp_path / "missing.safetensors"])
    save_model(tmp_path / "model.safetensors", model)
    with pytest.raises(ModelFileError, match="not a crfedit edit file \\(format 'crfedit-model'\\)"):
        read_delta(tmp_path / "model.safetensors")


def rewrite(path: Path, out: Path, tensors: dict, meta_changes: dict | None = None, refingerprint: bool = True) -> Path:
    """Write ``tensors`` with ``path``'s metadata (changed), fingerprint recomputed so only the
    model-dependent checks can catch the problem."""
    from crfedit.delta import delta_fingerprint

    meta = {**read_delta(path).meta, **(meta_changes or {})}
    if refingerprint:
        meta["fingerprint"] = delta_fingerprint(tensors, meta)
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(out), metadata=meta)
    return out


def test_wrong_shapes_dtypes_and_names(tmp_path, model):
    good = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2, "color_codes": 0.1}, ("F_rad.", "color_codes"))
    tensors = dict(read_delta(good).tensors)
    cases = [
        ({**tensors, "F_rad.out.bias": torch.zeros(4)}, {}, "tensor F_rad.out.bias has shape (4,) torch.float32, expected (3,) torch.float32"),
        ({**tensors, "F_rad.out.bias": torch.zeros(3, dtype=torch.float64)}, {}, "expected (3,) torch.float32"),
        ({**tensors, "color_code": torch.zeros(5)}, {}, "tensor color_code has shape (5,)"),
        ({**tensors, "F_share.mlp.0.bias": torch.zeros(16)}, {}, "outside the edit's modules"),
        ({**tensors, "aabb": torch.zeros(6)}, {}, "may not hold tensor 'aabb'"),
        ({**tensors, "occupancy": torch.zeros(8, 8, 8, dtype=torch.int8)}, {"modules": '["F_rad.", "color_codes", "occupancy"]', "version": "2"}, "a color edit may not hold tensor 'occupancy'"),
        ({**tensors, "F_rad.out.bias": torch.tensor([0.0, float("nan"), 0.0])}, {}, "contains NaN or inf"),
        (tensors, {"kind": "sculpt"}, "unknown edit kind 'sculpt'"),
        (tensors, {"version": "9"}, "edit format version '9' is not supported"),
        (tensors, {"modules": "F_rad."}, "modules must be a non-empty JSON list"),
    ]
    for i, (t, meta, message) in enumerate(cases):
        path = rewrite(good, tmp_path / f"bad{i}.safetensors", t, meta)
        with pytest.raises(ModelFileError) as e:
            apply_edit_files(model, [path])
        assert message in assert_one_line(e, path), (i, str(e.value))
    with pytest.raises(ModelFileError, match="has dtype I64"):
        apply_edit_files(model, [rewrite(good, tmp_path / "int.safetensors", {**tensors, "color_code": torch.zeros(4, dtype=torch.int64)})])


# ----------------------------------------------------------------------------- CLI


def test_edits_show_check_bake_cli(tmp_path, model):
    save_model(tmp_path / "m.safetensors", model)
    loaded, _ = load_model(tmp_path / "m.safetensors")
    a = delta_file(tmp_path, "a.safetensors", loaded, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    b = delta_file(tmp_path, "b.safetensors", apply_edit_files(loaded, [a]), 1, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    runner = CliRunner()
    shown = runner.invoke(app, ["edits", "show", str(a), "--json"])
    assert shown.exit_code == 0, shown.output
    info = json.loads(shown.output)
    assert info["metadata"]["kind"] == "color" and info["tensors"]["F_rad.out.bias"] == {"shape": [3], "dtype": "float32"}
    from crfedit.cli.edit import _parsed

    assert (_parsed("final_loss", "0.5"), _parsed("final_loss", "nan"), _parsed("hyperparameters", '{"lr": 0.01}')) == (0.5, "nan", {"lr": 0.01})
    assert _parsed("instance", "123") == "123" and _parsed("modules", "not json") == "not json"
    assert info["metadata"]["modules"] == ["F_rad."] and json.loads(runner.invoke(app, ["info", str(a), "--json"]).output) == info
    table = runner.invoke(app, ["edits", "show", str(a)])
    assert table.exit_code == 0 and "parent        (none)" in table.output and 'modules       ["F_rad."]' in table.output and "tensor        F_rad.out.bias [3] float32" in table.output
    ok = runner.invoke(app, ["edits", "check", str(tmp_path / "m.safetensors"), "--edit", str(a), "--edit", str(b)])
    assert ok.exit_code == 0 and "ok: 2 edit(s)" in ok.output
    bad = runner.invoke(app, ["edits", "check", str(tmp_path / "m.safetensors"), "--edit", str(b), "--edit", str(a)])
    assert_user_error(bad, "in the order they were made")
    baked = runner.invoke(app, ["edits", "bake", str(tmp_path / "m.safetensors"), "--edit", str(a), "--edit", str(b), "--out", str(tmp_path / "baked.safetensors")])
    assert baked.exit_code == 0, baked.output
    m2, _ = load_model(tmp_path / "baked.safetensors")
    info = runner.invoke(app, ["info", str(tmp_path / "baked.safetensors")])
    names = ", ".join(m2.names[k] for k in (0, 1))
    assert f"baked edits    {names} (2 edits onto {loaded.fingerprint()})" in info.output, info.output
    plain = runner.invoke(app, ["info", str(tmp_path / "m.safetensors")])
    assert "baked edits    none" in plain.output
    again = runner.invoke(app, ["edits", "check", str(tmp_path / "baked.safetensors"), "--edit", str(b)])
    assert_user_error(again, f"{b}: is already baked into this model")
    stacked = apply_edit_files(loaded, [a, b])
    for k in range(3):
        assert torch.equal(render(m2, k), render(stacked, k))
    other = make_model(seed=3)
    save_model(tmp_path / "other.safetensors", other)
    wrong = runner.invoke(app, ["edits", "check", str(tmp_path / "other.safetensors"), "--edit", str(a)])
    assert_user_error(wrong, "made for model")
    same = runner.invoke(app, ["edits", "bake", str(tmp_path / "m.safetensors"), "--edit", str(a), "--out", str(tmp_path / "m.safetensors")])
    assert_user_error(same, "is the model file", "pick another name for the baked model")


def test_edits_rebase_cli_drops_an_edit_from_the_middle(tmp_path, model):
    """A removal, a recolour, a second removal of one instance; `edits rebase` without the first
    writes files that check and render as the two kept changes alone, the input files untouched."""
    save_model(tmp_path / "m.safetensors", model)
    m, _ = load_model(tmp_path / "m.safetensors")
    grid0 = m.field.occupancy[0].clone()
    low, high = torch.zeros_like(grid0), torch.zeros_like(grid0)
    low[:, :, :3], high[:, :, 5:] = True, True
    a = grid_edit(m, 0, low, False, "a.safetensors", tmp_path)
    b = delta_file(tmp_path, "b.safetensors", apply_edit_files(m, [a]), 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    c = grid_edit(apply_edit_files(m, [a, b]), 0, high, False, "c.safetensors", tmp_path)
    inputs = {p: p.read_bytes() for p in (a, b, c)}
    runner, out = CliRunner(), tmp_path / "rebased"
    shown = runner.invoke(app, ["edits", "show", str(a)])
    emptied = int((grid0 & low).sum())
    assert f"occupancy     {emptied} cells emptied, 0 occupied" in shown.output, shown.output
    assert f"tensor        occupancy [8, 8, 8] int8, stored bit-packed in {64 + (emptied + 7) // 8} bytes" in shown.output
    assert f"size          {a.stat().st_size} bytes, 1 tensor, edit format version 4" in shown.output
    refused = runner.invoke(app, ["edits", "check", str(tmp_path / "m.safetensors"), "--edit", str(b), "--edit", str(c)])
    assert_user_error(refused, "crfedit edits rebase")
    done = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(b), "--edit", str(c), "--out-dir", str(out)])
    assert done.exit_code == 0, done.output
    assert "b.safetensors: color edit of chair_0, re-pinned" in done.output and "ok: 2 edit(s)" in done.output
    assert "note: a re-pinned edit keeps the change it was optimized for" in done.output
    kept = apply_edit_files(m, [out / "b.safetensors", out / "c.safetensors"])
    assert torch.equal(kept.field_for(0).occupancy[0], grid0 & ~high)  # the first removal's cells are back
    for name in ("b.safetensors", "c.safetensors"):  # the same change, a new place, and the command that put it there
        old, new = read_delta(tmp_path / name), read_delta(out / name)
        assert new.fingerprint != old.fingerprint and all(torch.equal(new.tensors[n], t) for n, t in old.tensors.items())
        assert new.meta["rebased"] == shlex.join(["crfedit", *sys.argv[1:]]) and "rebased" not in old.meta  # CliRunner keeps pytest's argv
    assert "rebased       crfedit " in runner.invoke(app, ["edits", "show", str(out / "c.safetensors")]).output
    first = (out / "c.safetensors").read_bytes()  # the same command again: the same bytes
    assert runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(b), "--edit", str(c), "--out-dir", str(out)]).exit_code == 0
    assert (out / "c.safetensors").read_bytes() == first
    # re-pinned again (c alone): the earlier rebase's record stays, the new one after it
    assert runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(out / "c.safetensors"),
                               "--out-dir", str(tmp_path / "alone")]).exit_code == 0
    argv = shlex.join(["crfedit", *sys.argv[1:]])
    assert read_delta(tmp_path / "alone" / "c.safetensors").meta["rebased"] == f"{argv}; then {argv}"
    typo = tmp_path / "no-such-folder" / "rebased"  # the folder is made, a missing one above it is a typo
    assert_user_error(runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(b), "--out-dir", str(typo)]),
                      "no-such-folder does not exist")
    assert not typo.parent.exists()
    assert all(p.read_bytes() == data for p, data in inputs.items())
    again = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(a), "--out-dir", str(out)])
    assert again.exit_code == 0 and "unchanged (already in this place)" in again.output and "re-pinned" not in again.output
    # the folder still holds the earlier rebase's files, which this stack leaves out: said, as edits check with them fails
    assert [ln for ln in again.output.splitlines() if ln.startswith("note:")] == [
        f"note: {out} also holds b.safetensors, c.safetensors from before, which this stack does not include"], again.output
    again = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(a), "--out-dir", str(out)])
    assert again.exit_code == 0 and "a.safetensors: remove edit of chair_0, unchanged (already in this place), replacing the edit file there" in again.output
    (out / "c.safetensors").write_text("notes, not an edit")  # a file of the same name that is not an edit: refused, kept
    assert_user_error(runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(b), "--edit", str(c), "--out-dir", str(out)]),
                      "c.safetensors", "not crfedit's", "pick another folder")
    assert (out / "c.safetensors").read_text() == "notes, not an edit"
    into_inputs = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(b), "--out-dir", str(tmp_path)])
    assert_user_error(into_inputs, "holds the input")
    assert b.read_bytes() == inputs[b]
    other = make_model(seed=3)
    save_model(tmp_path / "other.safetensors", other)
    wrong = runner.invoke(app, ["edits", "rebase", str(tmp_path / "other.safetensors"), "--edit", str(b), "--out-dir", str(tmp_path / "o")])
    assert_user_error(wrong, "made for model")
    assert not (tmp_path / "o").exists()


def test_rebase_refuses_an_edit_baked_in_or_given_twice_and_check_names_the_rebased_stack(tmp_path, model, monkeypatch):
    """`edits rebase` re-pinned an edit already baked into the model, or one given twice, and
    the stack then applied it twice (a recolour's red 182 → 231); it refuses both as `check`
    does.  `check` of a re-pinned file names the stack it was re-pinned onto (it named the one
    it was first made on), and a file made after fewer of the files before it says which do not
    belong (it said to pass them in the order they were made, which they were)."""
    save_model(tmp_path / "m.safetensors", model)
    m, _ = load_model(tmp_path / "m.safetensors")
    a = delta_file(tmp_path, "a.safetensors", m, 0, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    b = delta_file(tmp_path, "b.safetensors", apply_edit_files(m, [a]), 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    c = delta_file(tmp_path, "c.safetensors", apply_edit_files(m, [a, b]), 0, "color", {"F_rad.out.bias": 0.3}, ("F_rad.",))
    runner, bare = CliRunner(), str(tmp_path / "m.safetensors")
    assert runner.invoke(app, ["edits", "bake", bare, "--edit", str(a), "--out", str(tmp_path / "baked.safetensors")]).exit_code == 0
    baked = runner.invoke(app, ["edits", "rebase", str(tmp_path / "baked.safetensors"), "--edit", str(a), "--out-dir", str(tmp_path / "x")])
    assert_user_error(baked, "a.safetensors: is already baked into this model; leave it out")
    (tmp_path / "cpy").mkdir()
    again = tmp_path / "cpy" / "a.safetensors"
    again.write_bytes(a.read_bytes())
    twice = runner.invoke(app, ["edits", "rebase", bare, "--edit", str(a), "--edit", str(again), "--out-dir", str(tmp_path / "y")])
    assert_user_error(twice, "is given twice")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    out = tmp_path / "no_b"
    args = ["edits", "rebase", bare, "--edit", str(a), "--edit", str(c), "--out-dir", str(out)]
    monkeypatch.setattr(sys, "argv", ["crfedit", *args])  # the file's record of the rebase (CliRunner leaves pytest's argv)
    assert runner.invoke(app, args).exit_code == 0
    alone = runner.invoke(app, ["edits", "check", bare, "--edit", str(out / "c.safetensors")])
    assert_user_error(alone, f"it was re-pinned onto 1 edit ({out / 'a.safetensors'}), here 0 come before it")
    # on a model with both baked in, the line counts them (it said 0 came before it)
    assert runner.invoke(app, ["edits", "bake", bare, "--edit", str(a), "--edit", str(b), "--out", str(tmp_path / "ab.safetensors")]).exit_code == 0
    on_baked = runner.invoke(app, ["edits", "check", str(tmp_path / "ab.safetensors"), "--edit", str(out / "c.safetensors")])
    assert_user_error(on_baked, f"it was re-pinned onto 1 edit ({out / 'a.safetensors'}), here 2 baked into the model and 0 come before it")
    extra = runner.invoke(app, ["edits", "check", bare, "--edit", str(a), "--edit", str(b), "--edit", str(out / "c.safetensors")])
    assert_user_error(extra, f"was made after {a} alone, not after {b}: leave it out before it")


def test_rebase_names_the_left_out_removal_a_recolour_was_optimized_on(tmp_path, model):
    """A recolour made on a removal, re-pinned without it: the note names the removal it was
    optimized on (read from the recolour's recorded command) and what may show (the removed
    part back, in the colour the recolour spread onto it); a stack that leaves nothing out that
    an edit was made on keeps the general note."""
    save_model(tmp_path / "m.safetensors", model)
    m, _ = load_model(tmp_path / "m.safetensors")
    low = torch.zeros_like(m.field.occupancy[0])
    low[:, :, :3] = True
    a = grid_edit(m, 0, low, False, "a.safetensors", tmp_path)
    tensors, meta = make_delta(apply_edit_files(m, [a]), perturbed(apply_edit_files(m, [a]), 0, {"F_rad.out.bias": 0.2}), 0, "color",
                               ("F_rad.",), {"command": f"crfedit edit-color m.safetensors --edit {a} --out b.safetensors"})
    save_delta(tmp_path / "b.safetensors", tensors, meta)
    runner = CliRunner()
    done = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(tmp_path / "b.safetensors"),
                               "--out-dir", str(tmp_path / "out")])
    assert done.exit_code == 0, done.output
    assert ("note: b.safetensors was optimized on top of a.safetensors (a remove edit of chair_0), which this stack leaves out; it "
            "keeps the change it learnt there (a part the left-out removal took comes back") in done.stderr, done.stderr
    assert "note: a re-pinned edit keeps" not in done.output
    kept = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(a), "--edit", str(tmp_path / "b.safetensors"),
                               "--out-dir", str(tmp_path / "same")])
    assert kept.exit_code == 0 and "optimized on top of" not in kept.output
    # the recorded a.safetensors replaced by another edit (a shared stack's recipient has their own): named as recorded, no kind
    other = delta_file(tmp_path, "o.safetensors", m, 1, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    a.write_bytes(other.read_bytes())
    swapped = runner.invoke(app, ["edits", "rebase", str(tmp_path / "m.safetensors"), "--edit", str(tmp_path / "b.safetensors"),
                                  "--out-dir", str(tmp_path / "out2")])
    assert swapped.exit_code == 0, swapped.output
    assert "note: b.safetensors was optimized on top of a.safetensors (as recorded), which this stack leaves out" in swapped.stderr, swapped.stderr


def test_edits_check_json(tmp_path, model):
    """A script reads `edits check --json`: the stack's files, kinds and fingerprints on stdout;
    a stack that does not apply prints nothing there (its line on stderr, exit 2)."""
    save_model(tmp_path / "m.safetensors", model)
    m, _ = load_model(tmp_path / "m.safetensors")
    a = delta_file(tmp_path, "a.safetensors", m, 0, "color", {"F_rad.out.bias": 0.1}, ("F_rad.",))
    b = delta_file(tmp_path, "b.safetensors", apply_edit_files(m, [a]), 1, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    runner = CliRunner()
    ok = runner.invoke(app, ["edits", "check", str(tmp_path / "m.safetensors"), "--edit", str(a), "--edit", str(b), "--json"])
    assert ok.exit_code == 0, ok.output
    record = json.loads(ok.stdout)
    assert record["ok"] is True and record["base"] == m.fingerprint()
    assert [(e["file"], e["kind"], e["instance"], e["fingerprint"]) for e in record["edits"]] == [
        (str(p), "color", name, read_delta(p).fingerprint) for p, name in ((a, "chair_0"), (b, "chair_1"))]
    wrong = runner.invoke(app, ["edits", "check", str(tmp_path / "m.safetensors"), "--edit", str(b), "--json"])
    assert wrong.exit_code == 2 and wrong.stdout == "" and wrong.stderr.startswith("error: ")


def test_edits_show_escapes_line_breaks_in_recorded_values(tmp_path, model):
    """A shared file's provenance (outside the fingerprint) holding a line break printed a row
    of its own, a forged ``fingerprint`` line among them; the value is shown on its one row."""
    good = delta_file(tmp_path, "a.safetensors", model, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    d = read_delta(good)
    save_file(d.tensors, str(tmp_path / "x.safetensors"), metadata={**d.meta, "command": "crfedit ok\nfingerprint   deadbeefdeadbeef",
                                                                     "note\nfingerprint  ": "0123456789abcdef"})
    shown = CliRunner().invoke(app, ["edits", "show", str(tmp_path / "x.safetensors")])
    assert shown.exit_code == 0, shown.output
    rows = shown.output.splitlines()
    assert [r for r in rows if r.startswith("fingerprint")] == [f"fingerprint   {d.fingerprint}"]
    assert "command       crfedit ok\\nfingerprint   deadbeefdeadbeef" in rows
    assert "note\\nfingerprint   0123456789abcdef" in rows  # a key's line break too, escaped before the padding


def test_edits_show_table_shortens_hyperparameters():
    """The table rounds floats and counts camera records (``--json`` keeps them whole)."""
    from crfedit.cli.edit import _short

    assert _short(0.12549019607843137) == "0.1255" and _short(10.0) == "10"
    assert _short([0.5, 1 / 3, 7]) == "[0.5, 0.3333, 7]"
    assert _short([{"c2w": [[1.0]]}]) == "[1 record]" and _short([{}, {}]) == "[2 records]"
    assert _short("selection") == "selection" and _short(True) == "True" and _short([]) == "[]"
    # a recolour's widened refit: shown, with the fit it kept (the table left it out and showed the discarded fit's bleed alone)
    assert _short({"modules": ["F_fuse.bottleneck"], "bleed": 0.01612, "kept": True}) == "{modules=[F_fuse.bottleneck], bleed=0.01612, kept=True}"


def test_an_edit_with_nan_is_refused_when_written_not_when_read(tmp_path, model):
    """save_delta checks what read_delta would refuse, so no unreadable edit file is made."""
    from crfedit.errors import CrfError

    save_model(tmp_path / "m.safetensors", model)
    m, _ = load_model(tmp_path / "m.safetensors")
    good = delta_file(tmp_path, "good.safetensors", m, 0, "color", {"F_rad.out.bias": 0.2}, ("F_rad.",))
    d = read_delta(good)
    bad = {**d.tensors, "F_rad.out.bias": torch.full_like(d.tensors["F_rad.out.bias"], float("nan"))}
    with pytest.raises(CrfError, match="F_rad.out.bias contains NaN or inf: not written"):
        save_delta(tmp_path / "bad.safetensors", bad, d.meta)
    assert not (tmp_path / "bad.safetensors").exists()
