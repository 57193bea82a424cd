"""Hostile inputs, command by command (docs/robustness.md, "Hostile inputs").

Every case of the catalogue runs one ``crfedit`` command on a damaged, foreign or malicious
input and must end the same way: exit code 2, exactly one line on stderr that starts with
``error:`` and names the problem, no traceback, no partial or temporary file left behind, and
every input file byte-identical afterwards.  The security tests then check that no module under
crfedit/ can execute code while loading (no pickle, ``torch.load``, ``eval``, ``exec``) and that
a path or code written into a model's or an edit's metadata is data: never opened, never run.

The model is the session's ``tiny_model`` (tests/conftest.py: 2 chairs × 6 views at 16×16, 30
steps); a second model trained with another seed supplies foreign edits.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import re
import shutil
import struct
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import save_file

from crfedit.config import make_config
from crfedit.data import load_category
from crfedit.delta import apply_edit_files, delta_fingerprint, pack_grid_change, read_delta
from crfedit.edit import transfer
from crfedit.errors import CrfError, ModelFileError
from crfedit.io import write_exr
from crfedit.model import load_model
from crfedit.safefile import MAX_HEADER_BYTES, read_header, read_safetensors
from crfedit.train import train

from cli_helpers import assert_user_error, invoke

CPU = ["--device", "cpu"]
FAST_EDIT = ["--steps", "1", "--rays", "64", *CPU]
TINY_TRAIN = ["--steps", "2", "--set", "rays=64", "--set", "occ_res=8", "--set", "grid_res=8", *CPU]
REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- fixtures


@dataclass(frozen=True)
class Env:
    """Shared, read-only inputs (every case hashes the ones it names before and after)."""

    root: Path
    data: Path  # the category the models were trained on
    model: Path  # seed 0
    other: Path  # seed 1: another model of the same data
    delta: Path  # transfer edit of chair_000 (colour from chair_001), made on ``model``
    second: Path  # transfer edit of chair_001 (shape from chair_000), made after ``delta``
    foreign: Path  # the same edit as ``delta``, made on ``other``
    scribble: Path  # a valid scribble of train:0 (16×16, white square on black)
    photo: Path  # a valid photo (16×16 RGBA, opaque square on transparent)


@pytest.fixture(scope="module")
def env(tmp_path_factory, tiny_chairs, tiny_model) -> Env:
    root = tmp_path_factory.mktemp("hostile")
    other = root / "other.safetensors"
    cfg = make_config("fast", overrides=dict(steps=30, rays=256, checkpoint_every=10))
    train(load_category(tiny_chairs), cfg, other, torch.device("cpu"), seed=1)
    model, _ = load_model(tiny_model)
    transfer(model, 0, color_from=1).save(root / "delta.safetensors")
    applied = apply_edit_files(model, [root / "delta.safetensors"])
    transfer(applied, 1, shape_from=0).save(root / "second.safetensors")
    transfer(load_model(other)[0], 0, color_from=1).save(root / "foreign.safetensors")
    mask = np.zeros((16, 16), np.uint8)
    mask[5:11, 5:11] = 255
    Image.fromarray(mask, "L").save(root / "scribble.png")
    rgba = np.zeros((16, 16, 4), np.uint8)
    rgba[4:12, 4:12] = (200, 40, 40, 255)
    Image.fromarray(rgba, "RGBA").save(root / "photo.png")
    return Env(
        root, tiny_chairs, tiny_model, other, root / "delta.safetensors", root / "second.safetensors",
        root / "foreign.safetensors", root / "scribble.png", root / "photo.png",
    )


# ----------------------------------------------------------------------------- hostile files


def zero_byte(tmp: Path, name: str = "zero.safetensors") -> Path:
    (tmp / name).write_bytes(b"")
    return tmp / name


def truncated(src: Path, tmp: Path) -> Path:
    data = src.read_bytes()
    (tmp / "truncated.safetensors").write_bytes(data[: len(data) // 2])
    return tmp / "truncated.safetensors"


def header_past_end(tmp: Path) -> Path:
    """A header length field of 1000 in a 31-byte file."""
    (tmp / "long.safetensors").write_bytes(struct.pack("<Q", 1000) + b'{"__metadata__": {}}   ')
    return tmp / "long.safetensors"


def header_over_limit(tmp: Path) -> Path:
    """A 17 MiB file (sparse) whose header length field is 16 MiB + 1: over the limit, inside the file."""
    path = tmp / "huge_header.safetensors"
    path.write_bytes(struct.pack("<Q", MAX_HEADER_BYTES + 1) + b"{")
    os.truncate(path, MAX_HEADER_BYTES + (1 << 20))
    return path


def header_not_json(tmp: Path) -> Path:
    blob = b"\xff\xfe{not json at all}".ljust(24, b"\x00")
    (tmp / "notjson.safetensors").write_bytes(struct.pack("<Q", len(blob)) + blob)
    return tmp / "notjson.safetensors"


def text_file(tmp: Path) -> Path:
    (tmp / "readme.safetensors").write_text("This is a plain text file, not a model.\n" * 4)
    return tmp / "readme.safetensors"


def raw_safetensors(tmp: Path, name: str, header: dict, data: bytes) -> Path:
    blob = json.dumps(header).encode()
    (tmp / name).write_bytes(struct.pack("<Q", len(blob)) + blob + data)
    return tmp / name


def flipped(src: Path, tmp: Path, prefix: str) -> Path:
    """``src`` with the lowest mantissa bit of the first float of the first tensor under ``prefix``
    flipped: still finite, still well-formed, only the fingerprint can tell."""
    header, _ = read_header(src)
    name = min(n for n in header if n.startswith(prefix) and header[n]["dtype"] == "F32" and header[n]["shape"])
    data = bytearray(src.read_bytes())
    (n,) = struct.unpack("<Q", data[:8])
    data[8 + n + header[name]["data_offsets"][0]] ^= 1
    (tmp / "flipped.safetensors").write_bytes(bytes(data))
    return tmp / "flipped.safetensors"


def model_variant(env: Env, tmp: Path, change: Callable[[dict, dict], None]) -> Path:
    """The model rewritten with ``change(tensors, meta)`` applied (fingerprint not recomputed)."""
    tensors, meta = read_safetensors(env.model)
    tensors, meta = dict(tensors), dict(meta)
    change(tensors, meta)
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp / "variant.safetensors"), metadata=meta)
    return tmp / "variant.safetensors"


def delta_variant(src: Path, tmp: Path, change: Callable[[dict, dict], None], name: str = "evil.safetensors") -> Path:
    """An edit file rewritten with ``change(tensors, meta)``, its fingerprint recomputed, so only
    the checks against the model (or of the metadata's meaning) can catch it."""
    delta = read_delta(src)
    tensors, meta = dict(delta.tensors), dict(delta.meta)
    change(tensors, meta)
    meta["fingerprint"] = delta_fingerprint(tensors, meta)
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp / name), metadata=meta)
    return tmp / name


def packed_variant(src: Path, tmp: Path, change: Callable[[dict, dict], None], name: str = "evil.safetensors") -> Path:
    """A grid edit's file rewritten with ``change`` applied to its bit-packed grid change (format
    version 3's ``occupancy.changed`` / ``occupancy.gained`` and ``occupancy_shape``)."""
    delta = read_delta(src)
    tensors, meta = dict(delta.tensors), dict(delta.meta)
    packed, meta["occupancy_shape"] = pack_grid_change(tensors.pop("occupancy"))
    tensors.update(packed)
    change(tensors, meta)
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp / name), metadata=meta)
    return tmp / name


def selection_file(tmp: Path, tensors: dict, version: str = "1", **extra: str) -> Path:
    """A hand-written selection file (``crfedit select``'s format) holding ``tensors``."""
    meta = {"format": "crfedit-selection", "version": version, "model_fingerprint": "0" * 16, "instance": "chair_000",
            "instance_index": "0", "threshold": "0.5", "info": "{}", **extra}
    save_file(tensors, str(tmp / "sel.safetensors"), metadata=meta)
    return tmp / "sel.safetensors"


def mask_png(tmp: Path, name: str, array: np.ndarray, mode: str | None = None) -> Path:
    """``array`` as a PNG (uint8 → 8-bit grey, uint16 → 16-bit grey, or ``mode``)."""
    (Image.fromarray(array, mode) if mode else Image.fromarray(array)).save(tmp / name)
    return tmp / name


def palette_png(tmp: Path, index: int) -> Path:
    """A palette-mode PNG (black, white) filled with palette entry ``index``."""
    im = Image.new("P", (16, 16), index)
    im.putpalette([0, 0, 0, 255, 255, 255])
    im.save(tmp / "palette.png")
    return tmp / "palette.png"


def copy_data(env: Env, tmp: Path) -> Path:
    shutil.copytree(env.data, tmp / "chairs")
    return tmp / "chairs"


def bomb_png(tmp: Path) -> Path:
    """A 20 000 × 20 000 PNG of 390 KB: past Pillow's decompression-bomb limit."""
    from PIL import Image

    Image.new("L", (20000, 20000), 0).save(tmp / "huge.png")
    return tmp / "huge.png"


def without(path: Path) -> Path:
    """Delete ``path``; returns the dataset folder it was in (its grandparent)."""
    path.unlink()
    return path.parent.parent


def edit_transforms(data: Path, change: Callable[[dict], None], instance: str = "chair_000", split: str = "train") -> Path:
    path = data / instance / f"transforms_{split}.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))
    return data


def nan_depth(env: Env, tmp: Path) -> Path:
    data = copy_data(env, tmp)
    depth = np.full((16, 16), np.inf, np.float32)
    depth[3, 4] = np.nan
    write_exr(data / "chair_000" / "train" / "r_000_depth.exr", {"Z": depth})
    return data


def nan_exr_image(env: Env, tmp: Path) -> Path:
    data = copy_data(env, tmp)
    rgb = np.full((16, 16), 0.5, np.float32)
    rgb_nan = rgb.copy()
    rgb_nan[7, 7] = np.nan
    write_exr(data / "chair_000" / "train" / "r_000.exr", {"R": rgb_nan, "G": rgb, "B": rgb, "A": np.ones_like(rgb)})
    return edit_transforms(data, lambda m: m["frames"][0].update(file_path="./train/r_000.exr"))


def pose(matrix: list) -> Callable[[Env, Path], Path]:
    def build(env: Env, tmp: Path) -> Path:
        return edit_transforms(copy_data(env, tmp), lambda m: m["frames"][1].update(transform_matrix=matrix))

    return build


def missing_image(env: Env, tmp: Path) -> Path:
    data = copy_data(env, tmp)
    (data / "chair_001" / "train" / "r_002.png").unlink()
    return data


def cmyk_image(env: Env, tmp: Path) -> Path:
    data = copy_data(env, tmp)
    Image.new("CMYK", (16, 16), (0, 128, 255, 0)).save(data / "chair_000" / "train" / "r_000.jpg")
    return edit_transforms(data, lambda m: m["frames"][0].update(file_path="./train/r_000.jpg"))


def other_data(env: Env, tmp: Path) -> Path:
    """The same images with one camera angle changed: another dataset fingerprint."""
    return edit_transforms(copy_data(env, tmp), lambda m: m.update(camera_angle_x=m["camera_angle_x"] * 1.01), split="test")


# ----------------------------------------------------------------------------- commands


Built = tuple[list, list[Path]]
"""(command line, paths that must not exist afterwards)."""


REPEATABLE = ("--edit", "--set")
"""Options a command takes more than once; any other given again is refused (cli.common.repeated_option)."""


def merged(args: list, extra) -> list:
    """``args`` with ``extra`` after them, an option ``extra`` gives again replacing its value in
    ``args`` (a case's ``--steps 0`` over the base's ``--steps 1``: given twice, it is refused)."""
    args, extra = list(args), list(extra)
    rest, i = [], 0
    while i < len(extra):
        word = extra[i]
        if isinstance(word, str) and word.startswith("--") and word not in REPEATABLE and word in args and i + 1 < len(extra):
            at = args.index(word)
            if at + 1 < len(args) and not str(args[at + 1]).startswith("--"):
                args[at + 1] = extra[i + 1]
                i += 2
                continue
        rest.append(word)
        i += 1
    return [*args, *rest]


def render(env: Env, tmp: Path, *extra, model: Path | None = None, instance: str = "0", views: str = "test:0",
           out: Path | None = None) -> Built:
    out = out or tmp / "frames"
    return merged(["render", model or env.model, "--instance", instance, "--views", views, "--out", out, *CPU], extra), [out]


def edit_color(env: Env, tmp: Path, *extra, model: Path | None = None, scribble: Path | None = None, with_scribble: bool = True,
               view: str = "train:0", color: str = "red", out: Path | None = None) -> Built:
    out = out or tmp / "edit.safetensors"
    args = ["edit-color", model or env.model, "--instance", "0", "--view", view, "--color", color, "--out", out]
    if with_scribble:
        args += ["--scribble", scribble or env.scribble]
    return merged([*args, *FAST_EDIT], extra), [out]


def remove(env: Env, tmp: Path, *extra, model: Path | None = None, scribble: Path | None = None) -> Built:
    out = tmp / "remove.safetensors"
    return merged(["remove", model or env.model, "--instance", "0", "--view", "train:0", "--scribble", scribble or env.scribble,
                   "--out", out, *FAST_EDIT], extra), [out]


def add(env: Env, tmp: Path, *extra, model: Path | None = None, copy: Path | None = None, offset: str = "2,0") -> Built:
    out = tmp / "add.safetensors"
    return merged(["add", model or env.model, "--instance", "0", "--view", "train:0", "--donor", "1", "--copy", copy or env.scribble,
                   "--offset", offset, "--out", out, *FAST_EDIT], extra), [out]


def transfer_cmd(env: Env, tmp: Path, *extra, model: Path | None = None, out: Path | None = None) -> Built:
    out = out or tmp / "transfer.safetensors"
    return merged(["transfer", model or env.model, "--instance", "0", "--color-from", "1", "--out", out, *CPU], extra), [out]


def fit_real(env: Env, tmp: Path, *extra, model: Path | None = None, photo: Path | None = None,
             pose_spec: str = "train:0", out: Path | None = None) -> Built:
    out = out or tmp / "real.safetensors"
    return merged(["fit-real", model or env.model, photo or env.photo, "--pose", pose_spec, "--out", out,
                   "--steps-codes", "1", "--steps-joint", "0", "--rays", "64", *CPU], extra), [out]


def train_cmd(env: Env, tmp: Path, *extra, data: Path | None = None, out: Path | None = None) -> Built:
    out = out or tmp / "model.safetensors"
    return merged(["train", data or env.data, "--out", out, *TINY_TRAIN], extra), [out]


def check(model: Path, *edits: Path) -> Built:
    return ["edits", "check", model, *[a for e in edits for a in ("--edit", e)]], []


def bake(tmp: Path, model: Path, *edits: Path, out: Path | None = None) -> Built:
    out = out or tmp / "baked.safetensors"
    return ["edits", "bake", model, *[a for e in edits for a in ("--edit", e)], "--out", out], [out]


# ----------------------------------------------------------------------------- the catalogue


@dataclass(frozen=True)
class Case:
    id: str
    build: Callable[[Env, Path], Built]
    expect: tuple[str, ...]
    """Fragments the one error line must contain (what the problem is, and where)."""
    bug: str = ""
    """A library bug this case exposes (the case is a strict xfail until it is fixed)."""

    def param(self):
        marks = [pytest.mark.xfail(strict=True, reason=self.bug)] if self.bug else []
        return pytest.param(self, marks=marks, id=self.id)


def under_a_file(tmp: Path, name: str) -> Path:
    """``tmp/plain.txt/<name>``: a path whose parent is a regular file (no chmod trick needed, root or not)."""
    (tmp / "plain.txt").write_text("a regular file\n")
    return tmp / "plain.txt" / name


def with_dir(tmp: Path, name: str) -> Path:
    (tmp / name).mkdir()
    return tmp / name


def with_fifo(tmp: Path, name: str) -> Path:
    """``tmp/name``, a named pipe: a path that exists and is no regular file (as /dev/full is)."""
    os.mkfifo(tmp / name)
    return tmp / name


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def write_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def exr(root: Path, rel: str, channels: dict) -> Path:
    """Write an EXR at ``root/rel``; returns ``root``."""
    write_exr(root / rel, channels)
    return root


def copy_file(src: Path, dst: Path) -> Path:
    shutil.copyfile(src, dst)
    return dst


def set_nan_first(tensors: dict, name: str) -> None:
    t = tensors[name].clone()
    t.view(-1)[0] = float("nan")
    tensors[name] = t


UNDER_A_FILE_BUG = (
    "an output folder under a regular file passes {} (Path.exists() is False there), then mkdir raises "
    "NotADirectoryError: exit 1 with a traceback"
)

CATALOGUE: list[Case] = [
    # --- the MODEL argument: damaged, foreign or malformed files ------------------------------
    Case("model/zero-byte/info", lambda e, t: (["info", zero_byte(t)], []), ("zero.safetensors", "only 0 bytes")),
    Case("model/truncated/render", lambda e, t: render(e, t, model=truncated(e.model, t)), ("truncated.safetensors", "corrupt")),
    Case("model/one-bit-flipped/transfer", lambda e, t: transfer_cmd(e, t, model=flipped(e.model, t, "field.F_rad")),
         ("flipped.safetensors", "do not match the recorded fingerprint")),
    Case("model/header-length-past-end/edit-color", lambda e, t: edit_color(e, t, model=header_past_end(t)),
         ("long.safetensors", "corrupt safetensors header (length 1000)")),
    Case("model/header-over-16MiB/fit-real", lambda e, t: fit_real(e, t, model=header_over_limit(t)),
         ("huge_header.safetensors", f"corrupt safetensors header (length {MAX_HEADER_BYTES + 1})")),
    Case("model/header-not-json/eval-recon", lambda e, t: (["eval", "recon", header_not_json(t), e.data, *CPU], []),
         ("notjson.safetensors", "not JSON")),
    Case("model/plain-text/edits-check", lambda e, t: check(text_file(t), e.delta), ("readme.safetensors", "not a safetensors file", "of another kind")),
    Case("model/metadata-not-strings/edits-bake",
         lambda e, t: bake(t, raw_safetensors(t, "meta.safetensors", {"__metadata__": {"format": {"x": 1}}}, b""), e.delta),
         ("meta.safetensors", "metadata must be a table of strings")),
    Case("model/unknown-dtype/info",
         lambda e, t: (["info", raw_safetensors(t, "dtype.safetensors", {"w": {"dtype": "F128", "shape": [1], "data_offsets": [0, 16]}}, bytes(16))], []),
         ("dtype.safetensors", "corrupt entry for tensor 'w'")),
    Case("model/overlapping-offsets/info",
         lambda e, t: (["info", raw_safetensors(t, "offs.safetensors", {"w": {"dtype": "F32", "shape": [4], "data_offsets": [0, 64]}}, bytes(16))], []),
         ("offs.safetensors", "corrupt entry for tensor 'w'")),
    Case("model/an-edit-file/render", lambda e, t: render(e, t, model=e.delta), ("delta.safetensors", "not a crfedit model", "crfedit-edit", "it is an edit file, which commands take as --edit")),
    Case("edit/a-selection-file/render",
         lambda e, t: render(e, t, "--edit", selection_file(t, {"values": torch.zeros(4, 4, 4, dtype=torch.uint8)})),
         ("sel.safetensors", "not a crfedit edit file", "it is a selection (crfedit select --out), which edit-color, remove and add take as --selection")),
    Case("selection/values-not-a-grid/info",
         lambda e, t: (["info", selection_file(t, {"values": torch.zeros(4, 4, dtype=torch.uint8)})], []),
         ("sel.safetensors", "'values' must be a uint8 [R, R, R] grid")),
    Case("selection/unknown-version/info",
         lambda e, t: (["info", selection_file(t, {"values": torch.zeros(4, 4, 4, dtype=torch.uint8)}, version="9")], []),
         ("sel.safetensors", "selection format version '9' is not supported")),
    Case("selection/sparse-huge-shape/info",
         lambda e, t: (["info", selection_file(t, {"nonzero": torch.zeros(8, dtype=torch.uint8), "levels": torch.zeros(0, dtype=torch.uint8)},
                                               version="2", shape="[100000, 100000, 100000]")], []),
         ("sel.safetensors", "bad selection grid", "3 sizes from 1 to 512")),
    Case("selection/sparse-mask-cut-short/info",
         lambda e, t: (["info", selection_file(t, {"nonzero": torch.zeros(7, dtype=torch.uint8), "levels": torch.zeros(0, dtype=torch.uint8)},
                                               version="2", shape="[4, 4, 4]")], []),
         ("sel.safetensors", "bad selection grid", "nonzero has 7 bytes, 64 cells need 8")),
    Case("model/nan-weight/render", lambda e, t: render(e, t, model=model_variant(e, t, lambda ts, m: set_nan_first(ts, "field.F_rad.mlp.0.weight"))),
         ("variant.safetensors", "contains NaN or inf")),
    Case("model/wrong-shape/remove",
         lambda e, t: remove(e, t, model=model_variant(e, t, lambda ts, m: ts.update({"field.color_codes": torch.zeros(2, 31)}))),
         ("variant.safetensors", "field.color_codes has shape (2, 31)")),
    Case("model/missing-tensor/info", lambda e, t: (["info", model_variant(e, t, lambda ts, m: ts.pop("field.F_rad.mlp.0.bias"))], []),
         ("variant.safetensors", "missing tensor field.F_rad.mlp.0.bias")),
    Case("model/unknown-version/add", lambda e, t: add(e, t, model=model_variant(e, t, lambda ts, m: m.update(version="99"))),
         ("variant.safetensors", "version '99' is not supported")),
    Case("model/config-unknown-key/info",
         lambda e, t: (["info", model_variant(e, t, lambda ts, m: m.update(config=json.dumps({**json.loads(m["config"]), "exec": "rm -rf /"})))], []),
         ("variant.safetensors", "bad metadata", "unknown keys: exec")),
    Case("model/duplicate-path-like-names/info",
         lambda e, t: (["info", model_variant(e, t, lambda ts, m: m.update(instances=json.dumps(["../../etc/passwd"] * 2)))], []),
         ("variant.safetensors", "duplicate instance names")),
    Case("model/bad-camera-table/render",
         lambda e, t: render(e, t, model=model_variant(e, t, lambda ts, m: ts.update({"views.test.focal": -ts["views.test.focal"]}))),
         ("variant.safetensors", "bad camera table for split 'test'")),
    Case("model/bad-view-sizes/render",
         lambda e, t: render(e, t, model=model_variant(e, t, lambda ts, m: ts.update(
             {"views.test.size": torch.zeros(len(ts["views.test.focal"]), 2, dtype=torch.int64)}))),
         ("variant.safetensors", "bad camera table for split 'test'")),
    Case("model/foreign-tensor/info",
         lambda e, t: (["info", model_variant(e, t, lambda ts, m: ts.update({"payload.exec": torch.zeros(3)}))], []),
         ("variant.safetensors", "unexpected tensor 'payload.exec'")),
    Case("model/missing/render", lambda e, t: render(e, t, model=t / "nope.safetensors"), ("nope.safetensors", "file not found")),
    # --- --edit files: damaged, foreign, malformed ----------------------------------------------
    Case("edit/zero-byte/render", lambda e, t: render(e, t, "--edit", zero_byte(t)), ("zero.safetensors", "only 0 bytes")),
    Case("edit/truncated/edit-color", lambda e, t: edit_color(e, t, "--edit", truncated(e.delta, t)), ("truncated.safetensors", "corrupt")),
    Case("edit/one-bit-flipped/edits-check", lambda e, t: check(e.model, flipped(e.delta, t, "")),
         ("flipped.safetensors", "do not match the recorded fingerprint")),
    Case("edit/header-length-past-end/add", lambda e, t: add(e, t, "--edit", header_past_end(t)),
         ("long.safetensors", "corrupt safetensors header (length 1000)")),
    Case("edit/header-over-16MiB/edits-check", lambda e, t: check(e.model, header_over_limit(t)),
         ("huge_header.safetensors", f"length {MAX_HEADER_BYTES + 1}")),
    Case("edit/made-for-another-model/render", lambda e, t: render(e, t, "--edit", e.foreign),
         ("foreign.safetensors", "made for model", "edits apply only to the model they were made on")),
    Case("edit/made-for-another-model/fit-real", lambda e, t: fit_real(e, t, "--edit", e.foreign), ("foreign.safetensors", "made for model")),
    Case("edit/another-instance/edits-check",
         lambda e, t: check(e.model, delta_variant(e.delta, t, lambda ts, m: m.update(instance="chair_999"))),
         ("evil.safetensors", "edits instance 'chair_999', which the model does not have")),
    Case("edit/path-like-instance/render",
         lambda e, t: render(e, t, "--edit", delta_variant(e.delta, t, lambda ts, m: m.update(instance="../../etc/passwd"))),
         ("evil.safetensors", "'../../etc/passwd', which the model does not have")),
    Case("edit/wrong-order/edits-check", lambda e, t: check(e.model, e.second, e.delta),
         ("second.safetensors", "was made after", "delta.safetensors")),
    Case("edit/second-without-first/render", lambda e, t: render(e, t, "--edit", e.second), ("second.safetensors", "order they were made")),
    Case("edit/wrong-shape/edits-bake",
         lambda e, t: bake(t, e.model, delta_variant(e.delta, t, lambda ts, m: ts.update(color_code=torch.zeros(31)))),
         ("evil.safetensors", "tensor color_code has shape (31,)")),
    Case("edit/wrong-dtype-f64/render",
         lambda e, t: render(e, t, "--edit", delta_variant(e.delta, t, lambda ts, m: ts.update(color_code=ts["color_code"].double()))),
         ("evil.safetensors", "torch.float64, expected (32,) torch.float32")),
    Case("edit/integer-dtype/edits-show",
         lambda e, t: (["edits", "show", delta_variant(e.delta, t, lambda ts, m: ts.update(color_code=torch.zeros(32, dtype=torch.int64)))], []),
         ("evil.safetensors", "has dtype I64")),
    Case("edit/packed-grid-cut-short/render",
         lambda e, t: render(e, t, "--edit", e.delta, "--edit", packed_variant(e.second, t, lambda ts, m: ts.update({"occupancy.changed": ts["occupancy.changed"][:-1]}))),
         ("evil.safetensors", "bad packed occupancy", "occupancy.changed has")),
    Case("edit/packed-grid-huge-shape/edits-show",
         lambda e, t: (["edits", "show", packed_variant(e.second, t, lambda ts, m: m.update(occupancy_shape="[4096, 4096, 4096]"))], []),
         ("evil.safetensors", "bad packed occupancy", "sizes from 1 to 512")),
    Case("edit/nan/transfer",
         lambda e, t: transfer_cmd(e, t, "--edit", delta_variant(e.delta, t, lambda ts, m: set_nan_first(ts, "color_code"))),
         ("evil.safetensors", "contains NaN or inf")),
    Case("edit/foreign-tensor/remove",
         lambda e, t: remove(e, t, "--edit", delta_variant(e.delta, t, lambda ts, m: ts.update({"F_share.evil": torch.zeros(2)}))),
         ("evil.safetensors", "may not hold tensor 'F_share.evil'")),
    Case("edit/unknown-kind/edits-show",
         lambda e, t: (["edits", "show", delta_variant(e.delta, t, lambda ts, m: m.update(kind="exec"))], []),
         ("evil.safetensors", "unknown edit kind 'exec'")),
    Case("edit/modules-hold-code/edits-show",
         lambda e, t: (["edits", "show", delta_variant(e.delta, t, lambda ts, m: m.update(modules="__import__('os').system('touch PWNED')"))], []),
         ("evil.safetensors", "modules must be a non-empty JSON list")),
    Case("edit/a-model-file/transfer", lambda e, t: transfer_cmd(e, t, "--edit", e.model), ("model.safetensors", "not a crfedit edit file", "it is a model, which commands take as their MODEL argument")),
    Case("edit/missing/render", lambda e, t: render(e, t, "--edit", t / "nope.safetensors"), ("nope.safetensors", "file not found")),
    # --- scribbles, keep and copy masks ------------------------------------------------------------
    Case("scribble/wrong-size/edit-color", lambda e, t: edit_color(e, t, scribble=mask_png(t, "s.png", np.full((8, 8), 255, np.uint8))),
         ("s.png", "scribble mask is 8x8 but the view is 16x16")),
    Case("scribble/empty/edit-color", lambda e, t: edit_color(e, t, scribble=mask_png(t, "s.png", np.zeros((16, 16), np.uint8))),
         ("scribble is empty",)),
    Case("scribble/all-white/edit-color", lambda e, t: edit_color(e, t, scribble=mask_png(t, "s.png", np.full((16, 16), 255, np.uint8))),
         ("covers the whole view",)),
    Case("scribble/16-bit/edit-color", lambda e, t: edit_color(e, t, scribble=mask_png(t, "s.png", np.full((16, 16), 65535, np.uint16))),
         ("covers the whole view",)),  # 16-bit masks are read (as white on black) since issue 18
    Case("scribble/palette-all-white/remove", lambda e, t: remove(e, t, scribble=palette_png(t, 1)), ("covers the whole view",)),
    Case("scribble/palette-all-black/edit-color", lambda e, t: edit_color(e, t, scribble=palette_png(t, 0)), ("scribble is empty",)),
    Case("scribble/not-an-image/edit-color", lambda e, t: edit_color(e, t, scribble=text_file(t).rename(t / "s.png")),
         ("s.png", "not a readable image")),
    Case("scribble/zero-byte/remove", lambda e, t: remove(e, t, scribble=zero_byte(t, "s.png")), ("s.png", "not a readable image")),
    Case("scribble/missing/edit-color", lambda e, t: edit_color(e, t, scribble=t / "nope.png"), ("nope.png", "not found")),
    Case("scribble/none-given/edit-color", lambda e, t: edit_color(e, t, with_scribble=False), ("--scribble",)),
    Case("keep/all-white/edit-color",
         lambda e, t: edit_color(e, t, "--keep", mask_png(t, "k.png", np.full((16, 16), 255, np.uint8))), ("keep mask covers the whole view",)),
    Case("keep/only-under-the-scribble/edit-color", lambda e, t: edit_color(e, t, "--keep", e.scribble), ("keep mask has no pixel outside",)),
    Case("strokes/not-strokes/edit-color",
         lambda e, t: edit_color(e, t, "--scribble-json", write(t / "s.json", '{"strokes": "rm -rf /"}'), with_scribble=False),
         ("s.json", "expected")),
    Case("strokes/nan-point/edit-color",
         lambda e, t: edit_color(e, t, "--scribble-json", write(t / "s.json", '[[[1, 2], [NaN, 3]]]'), with_scribble=False),
         ("s.json", "stroke 0 is not a list of [x, y] pixel positions")),
    Case("strokes/malformed-json/edit-color",
         lambda e, t: edit_color(e, t, "--scribble-json", write(t / "s.json", "[[[1, 2]"), with_scribble=False), ("s.json", "malformed JSON")),
    Case("copy/wrong-size/add", lambda e, t: add(e, t, copy=mask_png(t, "c.png", np.full((8, 8), 255, np.uint8))),
         ("c.png", "copy mask is 8x8 but the view is 16x16")),
    Case("copy/bad-offset/add", lambda e, t: add(e, t, offset="2;rm"), ("--offset 2;rm", "DX,DY")),
    # --- photos for fit-real ------------------------------------------------------------------------
    Case("photo/garbage/fit-real", lambda e, t: fit_real(e, t, photo=write_bytes(t / "p.png", bytes(range(256)) * 2)), ("p.png", "not a readable image")),
    Case("photo/zero-byte/fit-real", lambda e, t: fit_real(e, t, photo=zero_byte(t, "p.png")), ("p.png", "not a readable image")),
    Case("photo/transparent/fit-real", lambda e, t: fit_real(e, t, photo=mask_png(t, "p.png", np.zeros((16, 16, 4), np.uint8), "RGBA")),
         ("p.png", "every pixel is transparent")),
    Case("photo/missing/fit-real", lambda e, t: fit_real(e, t, photo=t / "nope.png"), ("nope.png", "not found")),
    Case("photo/mask-wrong-size/fit-real",
         lambda e, t: fit_real(e, t, "--mask", mask_png(t, "m.png", np.full((8, 8), 255, np.uint8))), ("m.png", "mask is 8x8 but the photo")),
    Case("photo/mask-wrong-size-and-empty/fit-real",  # the size is the more basic mistake: it was called empty
         lambda e, t: fit_real(e, t, "--mask", mask_png(t, "m.png", np.zeros((8, 8), np.uint8))), ("m.png", "mask is 8x8 but the photo")),
    Case("photo/name-taken/fit-real", lambda e, t: fit_real(e, t, "--name", "chair_000"), ("--name chair_000", "already has an instance")),
    Case("photo/file-name-taken/fit-real", lambda e, t: fit_real(e, t, photo=copy_file(e.photo, t / "chair_000.png")),
         ("chair_000", "--name")),
    Case("photo/name-with-line-break/fit-real", lambda e, t: fit_real(e, t, "--name", "a\nerror: fake"), ("--name", "line breaks")),
    Case("photo/name-with-a-slash/fit-real", lambda e, t: fit_real(e, t, "--name", "a/b"), ("--name 'a/b'", "must not hold /")),
    Case("photo/pose-several-views/fit-real", lambda e, t: fit_real(e, t, pose_spec="train"), ("--pose train", "names 4 views", "e.g. train:0 for its first view")),
    # --- instance and view SPECs ---------------------------------------------------------------------
    Case("spec/unknown-instance/render", lambda e, t: render(e, t, instance="chair_999"), ("unknown instance 'chair_999'",)),
    Case("spec/path-like-instance/render", lambda e, t: render(e, t, instance="../../etc/passwd"), ("unknown instance '../../etc/passwd'",)),
    Case("spec/instance-out-of-range/edit-color", lambda e, t: edit_color(e, t, "--instance", "7"), ("instance 7", "out of range")),
    Case("spec/negative-instance/render", lambda e, t: render(e, t, instance="-1"), ("instance -1", "out of range")),
    Case("spec/unknown-donor/transfer", lambda e, t: transfer_cmd(e, t, "--shape-from", "chair_999"), ("unknown instance 'chair_999'",)),
    Case("spec/view-out-of-range/edit-color", lambda e, t: edit_color(e, t, view="train:99"), ("train:99", "index 99 out of range")),
    Case("spec/view-gibberish/render", lambda e, t: render(e, t, views="bogus"), ("view spec 'bogus'",)),
    Case("spec/view-range-backwards/render", lambda e, t: render(e, t, views="train:3-1"), ("range 3-1 runs backwards",)),
    Case("spec/option-given-twice/edit-color", lambda e, t: (lambda a: ([*a[0], "--color", "blue"], a[1]))(edit_color(e, t)),
         ("--color given 2 times", "`crfedit edit-color` takes one")),
    Case("spec/view-given-twice/remove", lambda e, t: (lambda a: ([*a[0], "--view", "train:1"], a[1]))(remove(e, t)),
         ("--view given 2 times", "`crfedit select`", "--selection")),
    Case("spec/several-views-for-an-edit/remove", lambda e, t: remove(e, t, "--view", "train"), ("--view train", "names 4 views", "e.g. train:0 for its first view")),
    Case("spec/orbit-zero/render", lambda e, t: render(e, t, views="orbit:0"), ("orbit:0", "between 1 and")),
    Case("spec/orbit-pole/render", lambda e, t: render(e, t, views="orbit:3@90"), ("orbit:3@90", "elevation 90")),
    Case("spec/camera-json-malformed/render", lambda e, t: render(e, t, views=str(write(t / "cam.json", "{"))), ("cam.json", "malformed JSON")),
    Case("spec/camera-json-singular/edit-color",
         lambda e, t: edit_color(e, t, view=str(write(t / "cam.json", json.dumps({"transform_matrix": [[0] * 4] * 4, "camera_angle_x": 0.7})))),
         ("cam.json", "transform_matrix is not invertible")),
    Case("spec/pose-instance-out-of-range/fit-real", lambda e, t: fit_real(e, t, "--pose-instance", "9"), ("instance 9", "out of range")),
    # --- colours -------------------------------------------------------------------------------------
    Case("color/unknown-name/edit-color", lambda e, t: edit_color(e, t, color="notacolor"), ("--color 'notacolor'",)),
    Case("color/five-hex-digits/edit-color", lambda e, t: edit_color(e, t, color="#12345"), ("--color '#12345'",)),
    Case("color/empty/edit-color", lambda e, t: edit_color(e, t, color=""), ("--color ''",)),
    Case("color/css-function-out-of-range/edit-color", lambda e, t: edit_color(e, t, color="rgb(1,2,300)"), ("--color 'rgb(1,2,300)'", "0 to 255")),
    Case("color/with-alpha/edit-color", lambda e, t: edit_color(e, t, color="#ff000080"), ("--color '#ff000080'",)),
    # --- numbers -------------------------------------------------------------------------------------
    Case("number/steps-0/edit-color", lambda e, t: edit_color(e, t, "--steps", "0"), ("--steps 0", "from 1 to 10,000,000")),
    Case("number/steps-negative/remove", lambda e, t: remove(e, t, "--steps", "-5"), ("--steps -5",)),
    Case("number/steps-huge/edit-color", lambda e, t: edit_color(e, t, "--steps", "100000000000000000000"), ("--steps 100000000000000000000", "from 1 to 10,000,000")),
    Case("number/steps-0/train", lambda e, t: train_cmd(e, t, "--steps", "0"), ("--steps 0", "at least 1")),
    Case("number/steps-codes-negative/fit-real", lambda e, t: fit_real(e, t, "--steps-codes", "-1"), ("--steps-codes -1",)),
    Case("number/res-negative/render", lambda e, t: render(e, t, "--res", "-4"), ("--res -4",)),
    Case("number/res-0/render", lambda e, t: render(e, t, "--res", "0"), ("--res 0",)),
    Case("number/res-huge/render", lambda e, t: render(e, t, "--res", "100000"), ("--res 100000", "16384")),
    Case("number/res-negative/train", lambda e, t: train_cmd(e, t, "--res", "-1"), ("--res -1",)),
    Case("number/res-negative/dataset-synth", lambda e, t: (["dataset", "synth", t / "synth", "--res", "-1"], [t / "synth"]), ("--res -1",)),
    Case("number/lr-nan/edit-color", lambda e, t: edit_color(e, t, "--lr", "nan"), ("--lr nan",)),
    Case("number/lr-inf/fit-real", lambda e, t: fit_real(e, t, "--lr-codes", "inf"), ("--lr-codes inf",)),
    Case("number/rays-1/edit-color", lambda e, t: edit_color(e, t, "--rays", "1"), ("--rays 1",)),
    Case("number/chunk-0/render", lambda e, t: render(e, t, "--chunk", "0"), ("--chunk 0",)),
    Case("number/minutes-0/train", lambda e, t: train_cmd(e, t, "--minutes", "0"), ("--minutes 0",)),
    Case("number/minutes-nan/quickstart", lambda e, t: (["quickstart", "--out", t / "q", "--minutes", "nan", *CPU], [t / "q"]), ("--minutes nan",)),
    Case("number/set-steps-negative/train", lambda e, t: train_cmd(e, t, "--set", "steps=-3"), ("steps must be ≥ 1",)),
    Case("number/set-occ-res-too-large/train", lambda e, t: train_cmd(e, t, "--set", "occ_res=4096"), ("occ_res must be from 2 to 512",)),
    Case("number/set-distortion-nan/train", lambda e, t: train_cmd(e, t, "--set", "distortion=nan"), ("distortion nan", "finite number")),
    Case("number/set-distortion-hierarchical/train", lambda e, t: train_cmd(e, t, "--set", "distortion=0.01", "--set", "sampler=hierarchical"),
         ("distortion needs sampler grid",)),
    Case("number/set-steps-per-cell-inf/train", lambda e, t: train_cmd(e, t, "--set", "steps_per_cell=inf"), ("steps_per_cell inf", "finite")),
    Case("number/set-occ-threshold-2/train", lambda e, t: train_cmd(e, t, "--set", "occ_threshold=2"), ("occ_threshold 2", "between 0 and 1")),
    Case("number/set-grid-features-0/train", lambda e, t: train_cmd(e, t, "--set", "grid_features=0"), ("grid_features",)),
    Case("number/set-eval-views-0/train", lambda e, t: train_cmd(e, t, "--set", "eval_views=0"), ("eval_views 0",)),
    Case("number/set-width-huge/train", lambda e, t: train_cmd(e, t, "--set", "width=1000000"), ("width 1000000", "at most")),
    Case("number/set-preset/train", lambda e, t: train_cmd(e, t, "--set", "preset=paper"), ("--set preset=paper", "--preset")),
    Case("number/strategies-twice/eval-edits",
         lambda e, t: (["eval", "edits", e.model, e.data, "--strategies", "hybrid,hybrid", "--steps", "1", *CPU], []), ("named twice",)),
    Case("number/set-not-a-number/train", lambda e, t: train_cmd(e, t, "--set", "rays=abc"), ("--set rays=abc", "expected an integer")),
    Case("number/set-unknown-key/train", lambda e, t: train_cmd(e, t, "--set", "__class__=x"), ("--set __class__=x", "KEY=VALUE")),
    Case("number/max-views-0/eval-recon", lambda e, t: (["eval", "recon", e.model, e.data, "--max-views", "0", *CPU], []), ("--max-views 0",)),
    # --- output paths --------------------------------------------------------------------------------
    Case("out/missing-folder/edit-color", lambda e, t: edit_color(e, t, out=t / "missing" / "e.safetensors"), ("missing", "does not exist")),
    Case("out/under-a-file/train", lambda e, t: train_cmd(e, t, out=under_a_file(t, "m.safetensors")), ("plain.txt", "is a file, not a folder")),
    Case("out/under-a-file/render", lambda e, t: render(e, t, out=under_a_file(t, "frames")),
         ("plain.txt", "is a file, not a folder")),
    Case("out/under-a-file/transfer", lambda e, t: transfer_cmd(e, t, out=under_a_file(t, "d.safetensors")), ("plain.txt", "is a file, not a folder")),
    Case("out/missing-folder/fit-real", lambda e, t: fit_real(e, t, out=t / "missing" / "r.safetensors"), ("missing", "does not exist")),
    Case("out/missing-folder/edits-bake", lambda e, t: bake(t, e.model, e.delta, out=t / "missing" / "b.safetensors"), ("missing", "does not exist")),
    Case("out/the-model-itself/transfer", lambda e, t: (transfer_cmd(e, t, out=e.model)[0], []), ("is the model file",)),
    Case("out/the-model-itself/edits-bake", lambda e, t: (bake(t, e.model, e.delta, out=e.model)[0], []), ("is the model file",)),
    Case("out/a-folder/edit-color", lambda e, t: (edit_color(e, t, out=with_dir(t, "dir"))[0], []), ("is a folder",)),
    Case("out/a-folder/train", lambda e, t: (train_cmd(e, t, out=with_dir(t, "dir"))[0], []), ("is a folder",)),
    Case("out/its-own-scribble/edit-color", lambda e, t: (edit_color(e, t, out=e.scribble)[0], []), ("is the --scribble file",)),
    Case("out/not-crfedit/edit-color", lambda e, t: (edit_color(e, t, out=write(t / "notes", "keep me"))[0], []), ("notes", "not crfedit's")),
    Case("out/another-kind/edit-color", lambda e, t: (edit_color(e, t, out=write(t / "notes.txt", "keep me"))[0], []),
         ("notes.txt", "an edit is written as .safetensors, not .txt")),
    Case("out/another-kind/train", lambda e, t: (train_cmd(e, t, out=t / "m.tif")[0], [t / "m.tif"]),
         ("m.tif", "a model is written as .safetensors, not .tif")),
    Case("out/another-kind/model-strip", lambda e, t: (["model", "strip", e.model, "--out", t / "s.ply"], [t / "s.ply"]),
         ("s.ply", "a stripped model is written as .safetensors, not .ply", "small.safetensors")),
    Case("out/a-model/edits-bake", lambda e, t: (bake(t, e.model, e.delta, out=write_bytes(t / "m2.safetensors", e.model.read_bytes()))[0], []),
         ("m2.safetensors", "is a crfedit model already", "--overwrite")),
    Case("out/a-pipe/transfer", lambda e, t: (transfer_cmd(e, t, out=with_fifo(t, "pipe"))[0], []), ("pipe", "not a regular file")),
    Case("out/video-in-missing-folder/render", lambda e, t: (render(e, t, "--video", t / "missing" / "v.gif")[0], [t / "frames", t / "missing"]),
         ("--video", "existing folder")),
    Case("out/under-a-file/dataset-synth",
         lambda e, t: (["dataset", "synth", under_a_file(t, "chairs"), "--res", "8", "--instances", "1", "--views", "1", "--no-twins"], []),
         ("plain.txt",)),
    Case("out/under-a-file/quickstart",
         lambda e, t: (["quickstart", "--out", under_a_file(t, "q"), "--minutes", "0.01", "--instances", "1", "--res", "8", *CPU], []),
         ("plain.txt",)),
    Case("out/under-a-file/eval-ablation",
         lambda e, t: (["eval", "ablation", e.data, "--steps", "1", "--models", under_a_file(t, "models"), *CPU], []),
         ("plain.txt",)),
    Case("out/preview-a-file/remove", lambda e, t: remove(e, t, "--preview", write(t / "p.png", "x")), ("--preview", "p.png: is a file")),
    Case("spec/preview-views-gibberish/edit-color",
         lambda e, t: (lambda built: (built[0], [*built[1], t / "prev"]))(edit_color(e, t, "--preview", t / "prev", "--views", "bogus")),
         ("view spec 'bogus'",)),
    Case("out/video-bad-suffix/render", lambda e, t: render(e, t, "--video", t / "v.mp5"), ("--video", "must end in .mp4 or .gif")),
    # --- datasets --------------------------------------------------------------------------------------
    Case("data/camera-angle-0/dataset-info",
         lambda e, t: (["dataset", "info", edit_transforms(copy_data(e, t), lambda m: m.update(camera_angle_x=0))], []),
         ("transforms_train.json", "camera_angle_x 0")),
    Case("data/nan-depth/dataset-info", lambda e, t: (["dataset", "info", nan_depth(e, t)], []), ("r_000_depth.exr", "depth has NaN pixels")),
    Case("data/instance-without-train-views/train",
         lambda e, t: train_cmd(e, t, data=without(copy_data(e, t) / "chair_001" / "transforms_train.json")),
         ("instance chair_001 has no train views", "transforms_train.json missing")),
    Case("data/decompression-bomb/edit-color", lambda e, t: edit_color(e, t, scribble=bomb_png(t)), ("huge.png", "image too large to read")),
    Case("data/json-nested-too-deep/render", lambda e, t: render(e, t, "--views", write(t / "deep.json", "[" * 100000 + "]" * 100000)),
         ("deep.json", "malformed JSON (nested too deeply)")),
    Case("number/edit-rays-huge/edit-color", lambda e, t: edit_color(e, t, "--rays", "1000000000"), ("--rays 1000000000", "at most 4194304")),
    Case("model/metadata-nested-too-deep/info",
         lambda e, t: (["info", raw_safetensors(t, "deep.safetensors", {"__metadata__": {"format": "crfedit-model", "instances": "[" * 5000 + "]" * 5000}}, b"")], []),
         ("deep.safetensors", "bad metadata", "nests more than 64 deep")),
    Case("data/nan-exr-image/train", lambda e, t: train_cmd(e, t, data=nan_exr_image(e, t)), ("r_000.exr", "NaN or infinite pixels")),
    Case("data/no-twins/eval-edits", lambda e, t: (["eval", "edits", e.model, e.data, "--steps", "1", *CPU], []), ("no ground-truth twins",)),
    Case("data/singular-pose/train", lambda e, t: train_cmd(e, t, data=pose([[1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])(e, t)),
         ("transforms_train.json", "frames[1].transform_matrix is not invertible")),
    Case("data/sheared-pose/dataset-info", lambda e, t: (["dataset", "info", pose([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]])(e, t)], []),
         ("transforms_train.json", "frames[1].transform_matrix is not a rigid camera-to-world matrix")),
    Case("data/nan-pose/dataset-info", lambda e, t: (["dataset", "info", pose([[float("nan")] * 4] * 4)(e, t)], []),
         ("transforms_train.json", "non-finite")),
    Case("data/pose-not-4x4/eval-recon", lambda e, t: (["eval", "recon", e.model, pose([[1, 0, 0], [0, 1, 0]])(e, t), *CPU], []),
         ("transforms_train.json", "not a 4x4 matrix")),
    Case("data/malformed-transforms/train",
         lambda e, t: train_cmd(e, t, data=write(copy_data(e, t) / "chair_001" / "transforms_val.json", "{\"frames\": [").parents[1]),
         ("transforms_val.json", "malformed JSON")),
    Case("data/no-instances/dataset-info", lambda e, t: (["dataset", "info", write(copy_data(e, t) / "instances.txt", "# none\n").parent], []),
         ("instances.txt", "lists no instances")),
    Case("data/instance-escapes-root/train",
         lambda e, t: train_cmd(e, t, data=write(copy_data(e, t) / "instances.txt", "chair_000\n../../../../../../nonexistent_dir\n").parent),
         ("instance folder ../../../../../../nonexistent_dir not found",)),
    Case("data/missing-image/train", lambda e, t: train_cmd(e, t, data=missing_image(e, t)),
         ("r_002.png", "image not found")),
    Case("data/cmyk-image/train", lambda e, t: train_cmd(e, t, data=cmyk_image(e, t)), ("r_000.jpg", "image mode CMYK is not supported")),
    Case("data/depth-wrong-size/dataset-info",
         lambda e, t: (["dataset", "info", exr(copy_data(e, t), "chair_000/train/r_001_depth.exr", {"Z": np.ones((8, 8), np.float32)})], []),
         ("r_001_depth.exr", "depth size 8x8 != image 16x16")),
    Case("data/not-a-folder/dataset-info", lambda e, t: (["dataset", "info", text_file(t)], []), ("readme.safetensors", "is a file, not a dataset folder")),
    Case("data/resume-on-other-data/train",
         lambda e, t: (train_cmd(e, t, "--resume", data=other_data(e, t), out=copy_file(e.model, t / "m.safetensors"))[0], []),
         ("--resume", "trained on another dataset")),
]


# ----------------------------------------------------------------------------- checks


def digest(paths) -> dict[str, str]:
    """sha256 of every file at or under ``paths`` (missing paths contribute nothing)."""
    out = {}
    for p in map(Path, paths):
        files = sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p] if p.is_file() else []
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def leftovers(*folders: Path) -> list[Path]:
    """Temporary files an atomic write would leave (``.<name>.<random><suffix>.tmp``)."""
    return sorted(p for folder in folders for p in folder.rglob(".*.tmp"))


@pytest.mark.parametrize("case", [c.param() for c in CATALOGUE])
def test_hostile_input(case: Case, env: Env, tmp_path: Path):
    argv, targets = case.build(env, tmp_path)
    inputs = [a for a in argv if isinstance(a, Path) and a.exists()] + [env.root, env.data, env.model]
    before = digest(inputs)
    result = invoke(*argv)
    line = assert_user_error(result, *case.expect)
    if os.environ.get("CRFEDIT_CATALOGUE"):  # docs/robustness.md's table: CRFEDIT_CATALOGUE=rows.md pytest this file
        shown = re.sub(r"(?<![^\s'\"(=])(?:/[^\s/'\"]+)+/(?=[^\s/'\"]+)", "", line)  # absolute paths as their file names (not --a/--b)
        with open(os.environ["CRFEDIT_CATALOGUE"], "a", encoding="utf-8") as rows:
            rows.write(f"| `{case.id}` | {shown.replace('|', chr(92) + '|')} |\n")
    assert digest(inputs) == before, "an input changed"
    assert leftovers(tmp_path, env.root, env.data.parent) == []
    for target in targets:
        assert not target.exists(), f"{target} was written"
    assert not (REPO / "PWNED").exists()


def test_catalogue_is_broad():
    ids = [c.id for c in CATALOGUE]
    assert len(ids) == len(set(ids)) and len(ids) >= 30
    commands = {i.rsplit("/", 1)[1] for i in ids}
    assert {"info", "render", "edit-color", "remove", "add", "transfer", "fit-real", "train", "edits-check", "edits-bake",
            "edits-show", "eval-recon", "dataset-info", "dataset-synth", "quickstart"} <= commands


def test_bench_output_under_a_file(env: Env, tmp_path: Path, monkeypatch):
    """The sweep itself is stubbed out (it takes minutes); what matters is how the output path fails."""
    import crfedit.bench

    monkeypatch.setattr(crfedit.bench, "run_bench", lambda category, settings, *a, **k: crfedit.bench.BenchReport([], {}, settings, "data"))
    csv_path = under_a_file(tmp_path, "bench.csv")
    result = invoke("bench", env.data, "--csv", csv_path, "--md", tmp_path / "bench.md", *CPU)
    assert_user_error(result, "plain.txt")
    assert leftovers(tmp_path) == [] and not (tmp_path / "bench.md").exists()


@pytest.mark.parametrize("build, option", [
    pytest.param(lambda e, t: render(e, t, "--res", "abc"), "--res", id="render --res abc"),
    pytest.param(lambda e, t: train_cmd(e, t, "--arch", "bogus"), "--arch", id="train --arch bogus"),
    pytest.param(lambda e, t: edit_color(e, t, "--steps", "1e9"), "--steps", id="edit-color --steps 1e9"),
    pytest.param(lambda e, t: render(e, t, "--device", "tpu"), "--device", id="render --device tpu"),
])
def test_unparseable_option_values_are_typer_usage_errors(env: Env, tmp_path: Path, build, option):
    """Values Typer cannot parse never reach crfedit: exit 2 and Typer's own usage message
    naming the option (usage, a hint, ``Error: Invalid value for ...``), no traceback."""
    argv, _ = build(env, tmp_path)
    result = invoke(*argv)
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert f"Invalid value for '{option}'" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_read_only_output_folder(env: Env, tmp_path: Path):
    """An edit into a folder the user may not write to: the edit runs, the write is refused
    cleanly (root ignores permissions, so this runs only as a regular user)."""
    if os.geteuid() == 0:
        pytest.skip("root ignores folder permissions (the under-a-file cases cover unwritable paths)")
    folder = with_dir(tmp_path, "ro")
    folder.chmod(0o555)
    try:
        argv, targets = edit_color(env, tmp_path, out=folder / "e.safetensors")
        before = digest([env.model, env.scribble])
        assert_user_error(invoke(*argv), "not writable")
        assert digest([env.model, env.scribble]) == before
        assert list(folder.iterdir()) == [] and not targets[0].exists()
    finally:
        folder.chmod(0o755)


def test_palette_and_grayscale_scribbles_are_the_same_mask(env: Env, tmp_path: Path):
    """Palette PNGs are read through their palette, not as raw indices."""
    from crfedit.data.format import read_mask

    im = Image.new("P", (16, 16), 0)
    im.putpalette([0, 0, 0, 255, 255, 255])
    im.paste(1, (5, 5, 11, 11))
    im.save(tmp_path / "p.png")
    assert np.array_equal(read_mask(tmp_path / "p.png"), read_mask(env.scribble))


# ----------------------------------------------------------------------------- security: no code-executing loaders


FORBIDDEN_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "joblib", "marshal", "shelve"}
FORBIDDEN_CALLS = {"eval", "exec", "compile", "__import__"}


def unsafe_constructs(source: str, filename: str = "<string>") -> list[str]:
    """Code (not comments, not docstrings) that can execute what a file contains: pickle-family
    imports, ``torch.load`` (and ``torch.jit.load``, ``torch.serialization``), bare ``eval``,
    ``exec``, ``compile`` and ``__import__`` calls, ``numpy.load(allow_pickle=True)``."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        where = f"{filename}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, ast.Import):
            found += [f"{where} import {a.name}" for a in node.names if a.name.split(".")[0] in FORBIDDEN_MODULES]
        elif isinstance(node, ast.ImportFrom):
            root = (node.module or "").split(".")[0]
            if root in FORBIDDEN_MODULES:
                found.append(f"{where} from {node.module} import")
            if node.module in ("torch", "torch.serialization") and any(a.name in ("load", "serialization") for a in node.names):
                found.append(f"{where} from {node.module} import load")
        elif isinstance(node, ast.Attribute):
            dotted = ast.unparse(node)
            if dotted in ("torch.load", "torch.jit.load", "torch.serialization") or dotted.startswith("torch.serialization."):
                found.append(f"{where} {dotted}")
            if node.attr in ("eval", "exec") and isinstance(node.value, ast.Name) and node.value.id == "builtins":
                found.append(f"{where} {dotted}")
        elif isinstance(node, ast.Call):
            if isinstance(node.func, ast.Name) and node.func.id in FORBIDDEN_CALLS:
                found.append(f"{where} {node.func.id}(")
            if ast.unparse(node.func) in ("np.load", "numpy.load") and any(
                k.arg == "allow_pickle" and not (isinstance(k.value, ast.Constant) and k.value.value is False) for k in node.keywords
            ):
                found.append(f"{where} np.load(allow_pickle=...)")
    return found


def test_the_unsafe_construct_finder_sees_code_and_ignores_comments_and_docstrings():
    snippet = '''
"""Module docstring: torch.load(x), pickle.loads(y), eval("1"), exec("2")."""
import pickle
from torch import load
import numpy as np
def f(model, path):
    """Docstring: eval(path)."""
    # a comment: torch.load(path), exec(path)
    model.eval()
    np.load(path)
    np.load(path, allow_pickle=True)
    return torch.load(path), eval("1"), exec("2"), __import__("os")
'''
    found = [f.split(" ", 1)[1] for f in unsafe_constructs(snippet)]
    assert sorted(found) == sorted(
        ["import pickle", "from torch import load", "np.load(allow_pickle=...)", "torch.load", "eval(", "exec(", "__import__("]
    )


def test_no_module_can_execute_a_file_it_loads():
    files = sorted((REPO / "crfedit").rglob("*.py"))
    assert len(files) > 20
    found = [hit for f in files for hit in unsafe_constructs(f.read_text(encoding="utf-8"), str(f.relative_to(REPO)))]
    assert found == []


# ----------------------------------------------------------------------------- security: metadata is data


_events: list[tuple[str, tuple]] | None = None
RUN_EVENTS = {"os.system", "os.exec", "os.posix_spawn", "os.spawn", "os.fork", "subprocess.Popen", "pickle.find_class",
              "marshal.loads", "ctypes.dlopen", "os.remove", "os.rename", "os.rmdir", "shutil.rmtree"}
WATCHED = {"open", "compile", *RUN_EVENTS}
MARKERS = ("passwd", "shadow", "id_rsa", "PWNED")
"""Strings only the hostile metadata holds: no opened path and no compiled source may contain them."""


def _audit(event: str, args: tuple) -> None:
    if _events is not None and event in WATCHED:
        _events.append((event, args))


class Recorder:
    """What the process opened, ran or compiled while recording (CPython audit events).

    The audit hook cannot be removed once added, so it is added on first use and does nothing
    outside a ``with Recorder()`` block."""

    hooked = False

    def __enter__(self) -> "Recorder":
        global _events
        if not Recorder.hooked:
            sys.addaudithook(_audit)
            Recorder.hooked = True
        _events = self.events = []
        return self

    def __exit__(self, *exc) -> None:
        global _events
        _events = None

    def opened(self) -> set[str]:
        return {
            os.path.abspath(os.fsdecode(args[0]))
            for event, args in self.events
            if event == "open" and isinstance(args[0], (str, bytes, os.PathLike))
        }

    def ran(self) -> list[tuple[str, tuple]]:
        return [(e, a) for e, a in self.events if e in RUN_EVENTS]

    def compiled(self) -> list[str]:
        """Sources passed to compile() (Typer evaluates the commands' string annotations this way)."""
        out = []
        for event, args in self.events:
            if event == "compile":
                src = args[0]
                out.append(src.decode(errors="replace") if isinstance(src, bytes) else ast.unparse(src) if isinstance(src, ast.AST) else str(src))
        return out

    def assert_metadata_stayed_data(self) -> None:
        assert [p for p in self.opened() if any(m in p for m in MARKERS)] == []
        assert self.ran() == []
        assert [s for s in self.compiled() if any(m in s for m in (*MARKERS, "__import__", "system("))] == []


def python_own(path: str) -> bool:
    """Files Python opens for its own lazy imports (sources, bytecode, extension modules)."""
    prefixes = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix)} | {str(REPO / "crfedit")}
    return path.endswith((".py", ".pyc", ".so")) or any(os.path.realpath(path).startswith(p + os.sep) for p in prefixes)


HOSTILE_META = {
    "view": "../../../../etc/passwd",
    "photo": "/etc/shadow",
    "mask": "~/.ssh/id_rsa",
    "command": "$(touch PWNED); __import__('os').system('touch PWNED')",
    "hyperparameters": json.dumps({"__class__": "os.system", "path": "/etc/passwd", "lr": "__import__('os')"}),
}


def test_edit_metadata_paths_and_code_are_never_opened_or_run(env: Env, tmp_path: Path):
    """A valid edit whose provenance metadata holds paths and code, and an invalid one whose
    instance is a path: reading, checking, showing and applying them opens only the edit file
    (and the model), and runs nothing."""
    valid = delta_variant(env.delta, tmp_path, lambda ts, m: m.update(HOSTILE_META), "provenance.safetensors")
    pathlike = delta_variant(env.delta, tmp_path, lambda ts, m: m.update(instance="../../etc/passwd", **HOSTILE_META), "pathlike.safetensors")
    model, _ = load_model(env.model)
    read_delta(env.delta)  # warm up lazy imports
    apply_edit_files(model, [env.delta])

    with Recorder() as rec:
        delta = read_delta(pathlike)
        assert delta.instance == "../../etc/passwd" and delta.meta["photo"] == "/etc/shadow"
        with pytest.raises(ModelFileError, match=r"'\.\./\.\./etc/passwd', which the model does not have"):
            apply_edit_files(model, [pathlike])
        applied = apply_edit_files(model, [valid])
    assert {p for p in rec.opened() if not python_own(p)} == {str(pathlike), str(valid)}
    assert rec.ran() == [] and rec.compiled() == []
    rec.assert_metadata_stayed_data()
    assert applied.names == model.names

    invoke("edits", "show", env.delta)  # warm up the command's lazy imports
    for argv, code in [
        (["edits", "show", valid], 0),
        (["edits", "show", "--json", pathlike], 0),
        (["edits", "check", env.model, "--edit", valid], 0),
        (["edits", "check", env.model, "--edit", pathlike], 2),
    ]:
        with Recorder() as rec:
            result = invoke(*argv)
        assert result.exit_code == code, result.output
        assert {p for p in rec.opened() if not python_own(p)} <= {str(env.model), str(valid), str(pathlike)}, argv
        rec.assert_metadata_stayed_data()
    shown = invoke("edits", "show", "--json", pathlike)
    assert json.loads(shown.stdout)["metadata"]["instance"] == "../../etc/passwd"
    assert not (REPO / "PWNED").exists() and not (tmp_path / "PWNED").exists()


def test_model_metadata_paths_are_names_not_files(env: Env, tmp_path: Path):
    """A model whose instance names are paths renders under those names; the only files it
    opens are the model and what it writes into --out."""
    model = model_variant(env, tmp_path, lambda ts, m: m.update(instances=json.dumps(["../../etc/passwd", "/etc/shadow"]), **HOSTILE_META))
    invoke("render", env.model, "--instance", "0", "--views", "test:0", "--out", tmp_path / "warm", *CPU)
    out = tmp_path / "frames"
    with Recorder() as rec:
        result = invoke("render", model, "--instance", "../../etc/passwd", "--views", "test:0", "--out", out, *CPU)
    assert result.exit_code == 0, result.output
    opened = {p for p in rec.opened() if not python_own(p)}
    beside = str(out.parent / f".{out.name}.")  # the hidden folder the set is built in, then swapped in
    assert str(model) in opened and all(p == str(model) or p == str(out) or p.startswith((str(out) + os.sep, beside)) for p in opened), opened
    # atomic writes rename their temp files; the swapped-in set's old folder is removed beside --out
    assert [e for e, a in rec.ran() if e != "os.rename" and not (e in ("shutil.rmtree", "os.rmdir") and str(a[0]).startswith(beside))] == []
    assert [p for p in rec.opened() if any(m in p for m in MARKERS)] == []
    assert [c for c in rec.compiled() if any(m in c for m in (*MARKERS, "__import__", "system("))] == []
    assert json.loads((out / "views.json").read_text())["instance"] == "../../etc/passwd"
    info = invoke("info", "--json", model)
    assert info.exit_code == 0 and json.loads(info.stdout)["names"] == ["../../etc/passwd", "/etc/shadow"]


ESC = "\x1b]0;owned\x07\x1b[2J"
"""A terminal title change and a screen clear: what a shared file could make a terminal do."""


def test_edits_show_does_not_print_terminal_control_characters(env: Env, tmp_path: Path):
    hostile = delta_variant(env.delta, tmp_path, lambda ts, m: m.update(command=f"crfedit {ESC}", view=ESC))
    result = invoke("edits", "show", hostile)
    assert result.exit_code == 0
    assert "\x1b" not in result.stdout and "\x07" not in result.stdout


def test_info_does_not_print_terminal_control_characters(env: Env, tmp_path: Path):
    model = model_variant(env, tmp_path, lambda ts, m: m.update(instances=json.dumps([f"chair{ESC}", "chair_001"])))
    result = invoke("info", model)
    assert result.exit_code == 0
    assert "\x1b" not in result.stdout and "\x07" not in result.stdout


def test_error_lines_do_not_carry_terminal_control_characters(env: Env, tmp_path: Path):
    hostile = delta_variant(env.delta, tmp_path, lambda ts, m: m.update(base=f"0123{ESC}"))
    result = invoke(*render(env, tmp_path, "--edit", hostile)[0])
    assert_user_error(result, "made for model")
    assert "\x1b" not in result.stderr and "\x07" not in result.stderr


@pytest.mark.parametrize(
    "args, says",
    [
        (["train", "x", "--out", "m.safetensors", "--steps", "abc"], "Invalid value for '--steps'"),
        (["tran"], "No such command 'tran'"),
        (["dataset", "info", ".", "--bogus"], "No such option: --bogus"),
        (["render"], "Missing argument"),
    ],
)
def test_usage_errors_from_the_real_entry_point_are_one_line(args, says, tmp_path):
    """What Typer cannot parse is one line on stderr and exit 2, like every other bad input."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "crfedit", *args], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and says in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""


def test_version_prints_and_exits_zero():
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "crfedit", "--version"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.startswith("crfedit ") and "torch" in proc.stdout


def test_info_on_a_selection_with_a_hand_edited_record(tmp_path: Path):
    """`crfedit info` on a selection whose ``info`` record is not what `select` writes: the cells
    are still counted, and the lines read from the record are left out rather than guessed."""
    path = selection_file(tmp_path, {"values": torch.full((4, 4, 4), 200, dtype=torch.uint8)})
    meta = {"format": "crfedit-selection", "version": "1", "model_fingerprint": "0" * 16, "instance": "chair_\x1b[31m",
            "instance_index": "0", "threshold": "0.5", "info": json.dumps({"mirror": {"used": True}, "views": "two", "features": [1]})}
    save_file({"values": torch.full((4, 4, 4), 200, dtype=torch.uint8)}, str(path), metadata=meta)
    result = invoke("info", path)
    assert result.exit_code == 0, result.output
    assert "cells         64 of 4^3 cells selected (value >= 0.5; a 4^3 grid), 64 with a value above 0" in result.output
    assert "made from     unknown" in result.output and "mirror" not in result.output and "\x1b" not in result.output


def test_special_paths_and_a_nan_threshold_are_named(env: Env, tmp_path: Path):
    """A device, a symlink loop and a selection whose threshold is NaN: each gets the line that
    says what it is, not "not found" or "empty"."""
    from crfedit.edit.selection import load_selection
    from crfedit.safefile import read_safetensors, safetensors_bytes

    assert_user_error(invoke("info", "/dev/zero"), "/dev/zero", "not a regular file")
    (tmp_path / "loop.safetensors").symlink_to(tmp_path / "loop.safetensors")
    assert_user_error(invoke("info", tmp_path / "loop.safetensors"), "symbolic link that leads nowhere")
    data = copy_data(env, tmp_path)  # a dataset image that is a symlink loop, or a folder
    image = data / "chair_000" / "train" / "r_000.png"
    image.unlink()
    image.symlink_to(image)
    assert_user_error(invoke("dataset", "info", data), "r_000.png", "symbolic link that leads nowhere")
    image.unlink()
    image.mkdir()
    assert_user_error(invoke("dataset", "info", data), "r_000.png", "is a folder, not a file")
    sel = tmp_path / "sel.safetensors"
    r = invoke("select", env.model, "--instance", "0", "--view", "train:0", "--scribble", env.scribble, "--out", sel, *CPU)
    assert r.exit_code == 0, r.output
    tensors, meta = read_safetensors(sel)
    (tmp_path / "nan.safetensors").write_bytes(safetensors_bytes(tensors, {**meta, "threshold": "nan"}))
    with pytest.raises(CrfError, match="corrupt selection metadata \\(threshold 'nan'"):
        load_selection(tmp_path / "nan.safetensors")
