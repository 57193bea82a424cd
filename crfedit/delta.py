"""Edit files ("deltas"): what one edit changed, relative to the state it was made on.

An edit of instance k replaces some of the tensors that render k (see
:attr:`~crfedit.model.CategoryModel.overrides`); its file stores only those tensors, as
differences from the state the edit started from (docs/edit-format.md):

=========================  =====================================================================
``F_rad.mlp.0.weight`` …   weight differences θ_after − θ_before, under their state-dict names
``shape_code``             [D] difference of row k of ``shape_codes``
``color_code``             [D] difference of row k of ``color_codes``
``occupancy``              [R, R, R] int8: the grid's change, after − before: +1 a cell the edit
                           occupied, −1 one it emptied, 0 the rest
=========================  =====================================================================

On disk (format version 3) the grid's change is bit-packed (:func:`pack_grid_change`): one bit a
cell for "changed" and one bit a changed cell for "occupied", 1/8 of the bytes of an int8 grid;
:func:`read_delta` unpacks it, so a :class:`Delta` always holds the int8 change.

Every tensor is a change, so an edit left out of a stack takes all of its change with it: drop
the first of two removals of one instance and the second's file empties only its own cells.
(Format version 1 stored the new grid itself, which kept the dropped removal's cells empty; its
files still read, and their grid still replaces the instance's.)

String metadata names the edit (``kind``, ``instance``, ``modules``) and pins it to its place:
``base`` is the fingerprint of the model file it was made for, ``parent`` a hash of ``base`` and
the fingerprints of the edits applied before it (``""`` for the first), ``fingerprint`` a hash of
this file's tensors and identity.  :func:`apply_edit_files` checks all of it, for every file,
before it computes anything, so a stack applies completely or not at all.

Applying is functional: a new :class:`CategoryModel` sharing the (untouched) base field, whose
``overrides[k]`` carries k's replaced tensors — other instances render bit-identically by
construction.  The stack applied so far is recorded in the returned model's ``meta``
(``edit_base``, ``edit_stack``, ``edit_state``), so an edit made on it knows its parent.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .errors import CrfError, ModelFileError, NonFiniteError
from .field import ConditionalRadianceField
from .io import atomic_write_bytes
from .model import CategoryModel
from .names import COLOR_CODES, SHAPE_CODES
from .safefile import (
    EDIT_FORMAT, fingerprint, grid_shape, other_kind, pack_bits, read_header, read_safetensors, safetensors_bytes,
    unpack_bits,
)

FORMAT = EDIT_FORMAT
VERSION = "4"
"""The version :func:`make_delta` writes.  Version 1 stored ``occupancy`` as the new grid itself
(bool); 2 stores its change (int8); 3 stores that change bit-packed; 4 also counts its
``hyperparameters`` into the fingerprint (:func:`identity_keys`).  All read
(:data:`READ_VERSIONS`), and :func:`save_delta` writes a file in its metadata's version."""
READ_VERSIONS = ("1", "2", "3", "4")
KINDS = ("color", "remove", "add", "transfer", "fit-real")
CODE_ROWS = {"shape_code": SHAPE_CODES, "color_code": COLOR_CODES}
"""Delta tensor name → the code table (state-dict name) whose row k it changes."""
GRID = "occupancy"
GRID_KINDS = ("remove", "add", "transfer", "fit-real")
"""Kinds that may carry a new occupancy grid (a color edit leaves density alone)."""
IDENTITY = ("format", "version", "kind", "instance", "modules", "base", "parent", "adds_instance")
"""Metadata that, with the tensors, makes up an edit's fingerprint (timings and the command do
not); from version 4 also ``hyperparameters`` (:func:`identity_keys`)."""
NUMBERS = ("first_loss", "fit_loss", "final_loss", "seconds", "photo_psnr")
"""Recorded metadata that must read as a number where present (:func:`read_delta`)."""
JSON_RECORDS = {"hyperparameters": dict, "inputs": dict, "stages": list}
"""Recorded metadata that must be JSON of this type where present (:func:`read_delta`)."""
PACKED = ("occupancy.changed", "occupancy.gained")
"""Version 3's on-disk tensors for the grid's change (:func:`pack_grid_change`)."""
PACKED_SHAPE = "occupancy_shape"
"""Version 3's metadata key for the packed grid's shape (JSON list), read back into the tensor."""
RESERVED = (*IDENTITY, "fingerprint", PACKED_SHAPE)
STACK_KEYS = ("edit_base", "edit_stack", "edit_state")
"""``CategoryModel.meta`` keys through which an applied model remembers its stack."""


def grid_packed(version: str) -> bool:
    """Whether a file of format ``version`` stores its grid change bit-packed (3 on; 1 and 2 did not)."""
    return version not in ("1", "2")


@dataclass(frozen=True)
class Delta:
    """One edit file, read and checked on its own (model-independent checks only)."""

    path: str
    tensors: dict[str, Tensor]
    meta: dict[str, str]

    @property
    def kind(self) -> str:
        return self.meta["kind"]

    @property
    def instance(self) -> str:
        return self.meta["instance"]

    @property
    def modules(self) -> list[str]:
        return json.loads(self.meta["modules"])

    @property
    def fingerprint(self) -> str:
        return self.meta["fingerprint"]


# ----------------------------------------------------------------------------- fingerprints


def identity_keys(version: str) -> tuple[str, ...]:
    """The metadata keys a file of format ``version`` counts into its fingerprint: :data:`IDENTITY`,
    and from version 4 ``hyperparameters`` too, which a transfer's re-pinning reads (whose code it
    takes) and a fit-real's ``--views photo`` (its camera): edited, they change what the file does."""
    return IDENTITY if version in ("1", "2", "3") else (*IDENTITY, "hyperparameters")


def delta_fingerprint(tensors: Mapping[str, Tensor], meta: Mapping[str, str]) -> str:
    """16 hex digits over the tensors and the identity metadata (:func:`identity_keys` of its version)."""
    identity = json.dumps({k: meta.get(k, "") for k in identity_keys(meta.get("version", VERSION))}, sort_keys=True)
    return hashlib.sha256(f"{fingerprint(dict(tensors))}|{identity}".encode()).hexdigest()[:16]


def chain_fingerprint(base: str, deltas: Sequence[str]) -> str:
    """The ``parent`` of an edit made after ``deltas`` (their fingerprints, in order) on ``base``.

    ``""`` when no edit precedes it; else 16 hex digits of sha256("base|d1|d2…").
    """
    if not deltas:
        return ""
    return hashlib.sha256("|".join([base, *deltas]).encode()).hexdigest()[:16]


def stack_of(model: CategoryModel) -> tuple[str, list[str]]:
    """(base fingerprint, fingerprints of the edits applied) of ``model``.

    A model returned by :func:`apply_edit_files` records its stack in ``meta``; that record is
    trusted only while the model still has the state it was recorded for (``edit_state``), so a
    model changed since (or any other model) counts as a base of its own with no edits.
    """
    meta = model.meta
    if all(k in meta for k in STACK_KEYS):
        try:
            stack = json.loads(meta["edit_stack"])
        except json.JSONDecodeError:
            stack = None
        if isinstance(stack, list) and all(isinstance(s, str) for s in stack) and meta["edit_state"] == model.fingerprint():
            return meta["edit_base"], stack
    return model.fingerprint(), []


# ----------------------------------------------------------------------------- per-instance state


def instance_state(model: CategoryModel, instance: int) -> dict[str, Tensor]:
    """Every state-dict tensor that renders ``instance``: the shared field's, with the
    instance's overrides on top (no copies)."""
    state = model.field.state_dict()
    state.update(model.overrides.get(instance, {}))
    return state


def _parameter_names(field: ConditionalRadianceField) -> dict[str, Tensor]:
    return dict(field.named_parameters())


def selected_names(field: ConditionalRadianceField, modules: Sequence[str]) -> list[str]:
    """Delta tensor names an edit that trains ``modules`` (state-dict prefixes) stores."""
    out = []
    for name in _parameter_names(field):
        if not name.startswith(tuple(modules)):
            continue
        row = next((r for r, table in CODE_ROWS.items() if table == name), None)
        out.append(row or name)
    if GRID in modules:
        out.append(GRID)
    return out


def make_delta(
    before: CategoryModel,
    after: CategoryModel,
    instance: int | str,
    kind: str,
    modules: Sequence[str],
    meta: Mapping[str, object] | None = None,
) -> tuple[dict[str, Tensor], dict[str, str]]:
    """(tensors, metadata) of the edit that turned ``before`` into ``after`` for one instance.

    ``modules`` are the state-dict prefixes the edit trained (``("F_rad.", "color_codes")``);
    every tensor under them is stored (weights as differences, code tables as the difference
    of row k, ``occupancy`` as the change of k's grid, int8 after − before).  ``meta`` adds string metadata (hyper-parameters,
    ``final_loss``, ``seconds``, ``command``); ``base``, ``parent`` and ``fingerprint`` come from
    ``before``'s stack.  For ``kind="fit-real"`` the instance is new in ``after`` (see :func:`grow`)
    and its code rows are stored as differences from zero.
    """
    if kind not in KINDS:
        raise ValueError(f"kind {kind!r}: expected one of {', '.join(KINDS)}")
    extra = {k: str(v) for k, v in (meta or {}).items()}
    clash = sorted(set(extra) & set(RESERVED))
    if clash:
        raise ValueError(f"make_delta: metadata keys {clash} are set by make_delta itself")
    k = after.instance_index(instance)
    name = after.names[k]
    adding = kind == "fit-real"
    if adding and name in before.names:
        raise ValueError(f"fit-real delta: instance {name!r} already exists in the model it was made on")
    if not adding and before.names[k] != name:
        raise ValueError("make_delta: before and after list different instances")
    old = instance_state(before, k) if not adding else None
    new = instance_state(after, k)
    tensors: dict[str, Tensor] = {}
    for dname in selected_names(after.field, modules):
        with torch.no_grad():
            if dname in CODE_ROWS:
                table = CODE_ROWS[dname]
                start = old[table][k] if old is not None else torch.zeros_like(new[table][k])
                tensors[dname] = (new[table][k] - start).detach().cpu().clone()
            elif dname == GRID:
                start = old[GRID][k] if old is not None else torch.ones_like(new[GRID][k])  # grow()'s row
                tensors[dname] = (new[GRID][k].to(torch.int8) - start.to(torch.int8)).cpu()
            else:
                start = old[dname] if old is not None else before.field.state_dict()[dname]
                tensors[dname] = (new[dname] - start).detach().cpu().clone()
    for dname, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise NonFiniteError(f"the edit's {dname} contains NaN or inf; nothing was written")
    base, stack = stack_of(before)
    metadata = {
        **extra,
        "format": FORMAT,
        "version": VERSION,
        "kind": kind,
        "instance": name,
        "modules": json.dumps(list(modules)),
        "base": base,
        "parent": chain_fingerprint(base, stack),
        "adds_instance": name if adding else "",
    }
    metadata["fingerprint"] = delta_fingerprint(tensors, metadata)
    return tensors, metadata


def delta_bytes(tensors: Mapping[str, Tensor], metadata: Mapping[str, str]) -> bytes:
    """The bytes of an edit file, in the version its metadata names: a version-3 file's grid
    change is bit-packed, an older one (a re-pinned file keeps its version) stores it as it is.
    What :func:`save_delta` writes, and what the page's Download gives.  A tensor with NaN or
    inf is refused here, as :func:`read_delta` would refuse the file."""
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CrfError(f"edit tensor {name} contains NaN or inf: not written (no edit file could be read back with it)")
    out, meta = dict(tensors), {k: str(v) for k, v in metadata.items() if k != PACKED_SHAPE}
    if grid_packed(meta.get("version", VERSION)) and GRID in out:
        packed, shape = pack_grid_change(out.pop(GRID))
        out.update(packed)
        meta[PACKED_SHAPE] = shape
    return safetensors_bytes(out, meta)


def save_delta(path: str | os.PathLike, tensors: Mapping[str, Tensor], metadata: Mapping[str, str]) -> None:
    """Write :func:`delta_bytes` atomically (temp file, fsync, rename): never a partial file."""
    atomic_write_bytes(path, delta_bytes(tensors, metadata))


def pack_grid_change(change: Tensor) -> tuple[dict[str, Tensor], str]:
    """(tensors, shape) of version 3's on-disk form of an int8 grid change (values −1, 0, 1).

    ``occupancy.changed``: uint8, one bit per cell in C order, set where the change is not 0;
    ``occupancy.gained``: uint8, one bit per *changed* cell in the same order, set where it is +1
    (a cell occupied) and clear where it is −1 (emptied).  Bits are packed most significant first,
    as ``numpy.packbits`` packs them, the last byte padded with zeros.  A 64³ removal is 32 KiB
    plus a byte per 8 cells it emptied, against 256 KiB as int8.  ``shape`` is the JSON list of
    the grid's shape, which the bits alone do not tell.
    """
    flat = change.detach().to("cpu", torch.int8).reshape(-1).numpy()
    changed = flat != 0
    return {PACKED[0]: pack_bits(changed), PACKED[1]: pack_bits(flat[changed] > 0)}, json.dumps(list(change.shape))


def unpack_grid_change(changed: Tensor, gained: Tensor, shape: str, path: str = "edit file") -> Tensor:
    """The int8 grid change :func:`pack_grid_change` packed; every length, the shape and the
    padding bits are checked first (a hostile shape allocates nothing), errors one line."""
    def bad(why: str) -> ModelFileError:
        return ModelFileError(f"{path}: bad packed {GRID} ({why})")

    dims = grid_shape(shape, bad)
    n = dims[0] * dims[1] * dims[2]
    where = unpack_bits(changed, n, PACKED[0], bad, "cells")
    up = unpack_bits(gained, int(where.sum()), PACKED[1], bad, "changed cells")
    out = np.zeros(n, dtype=np.int8)
    out[where] = np.where(up, 1, -1)
    return torch.from_numpy(out.reshape(dims))


# ----------------------------------------------------------------------------- reading


def read_delta(path: str | os.PathLike) -> Delta:
    """Read an edit file and check what can be checked without the model: format, version,
    kind, metadata, dtypes, finite values and the recorded fingerprint."""
    path = str(path)
    header, meta = read_header(path)
    if meta.get("format") != FORMAT:
        raise ModelFileError(f"{path}: not a crfedit edit file (format {meta.get('format', 'unknown')!r}){other_kind(meta.get('format'))}")
    if meta.get("version") not in READ_VERSIONS:
        raise ModelFileError(f"{path}: edit format version {meta.get('version')!r} is not supported (expected {', '.join(READ_VERSIONS[:-1])} or {READ_VERSIONS[-1]})")
    missing = [k for k in RESERVED if k not in meta and k not in ("adds_instance", PACKED_SHAPE)]
    if missing:
        raise ModelFileError(f"{path}: bad edit metadata (missing {', '.join(missing)})")
    if meta["kind"] not in KINDS:
        raise ModelFileError(f"{path}: unknown edit kind {meta['kind']!r} (expected one of {', '.join(KINDS)})")
    try:
        modules = json.loads(meta["modules"])
    except json.JSONDecodeError:
        modules = None
    if not isinstance(modules, list) or not modules or not all(isinstance(m, str) and m for m in modules):
        raise ModelFileError(f"{path}: bad edit metadata (modules must be a non-empty JSON list of names)")
    if not meta["instance"]:
        raise ModelFileError(f"{path}: bad edit metadata (no instance)")
    for key in NUMBERS:
        if key in meta and not _is_number(meta[key], infinite=key == "photo_psnr"):
            raise ModelFileError(f"{path}: bad edit metadata ({key} {meta[key][:40]!r} is not a number)")
    for key, kind in JSON_RECORDS.items():
        if meta.get(key) and not isinstance(_json_or_none(meta[key]), kind):
            raise ModelFileError(f"{path}: bad edit metadata ({key} is not a JSON {'object' if kind is dict else 'list'})")
    if (meta["kind"] == "fit-real") != bool(meta.get("adds_instance")) or (
        meta.get("adds_instance") and meta["adds_instance"] != meta["instance"]
    ):
        raise ModelFileError(f"{path}: bad edit metadata (adds_instance must name the instance of a fit-real edit, only)")
    if not header:
        raise ModelFileError(f"{path}: edit file holds no tensors")
    packed = grid_packed(meta["version"])
    grid_dtype = {"1": "BOOL", "2": "I8"}.get(meta["version"], "U8")
    grid_names = PACKED if packed else (GRID,)
    for name, info in header.items():
        if info["dtype"] not in ("F32", "F64", "F16", "BF16") and not (name in grid_names and info["dtype"] == grid_dtype):
            what = f"a bit-packed {GRID} change ({', '.join(PACKED)}) of U8" if packed else f"an {GRID} grid of {grid_dtype}"
            raise ModelFileError(f"{path}: tensor {name[:80]} has dtype {info['dtype']} (edits of format version {meta['version']} hold floats and {what})")
    if packed:
        present = [n for n in PACKED if n in header]
        if GRID in header or len(present) == 1 or (present and PACKED_SHAPE not in meta):
            raise ModelFileError(f"{path}: a version-{meta['version']} file stores its {GRID} change as {' and '.join(PACKED)} with {PACKED_SHAPE} metadata")
    tensors, meta = read_safetensors(path)
    if packed and PACKED[0] in tensors:
        tensors[GRID] = unpack_grid_change(tensors.pop(PACKED[0]), tensors.pop(PACKED[1]), meta[PACKED_SHAPE], path)
    meta.pop(PACKED_SHAPE, None)
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise ModelFileError(f"{path}: tensor {name[:80]} contains NaN or inf")
    if GRID in tensors and tensors[GRID].dtype == torch.int8 and not bool(((tensors[GRID] >= -1) & (tensors[GRID] <= 1)).all()):
        raise ModelFileError(f"{path}: tensor {GRID} holds values other than -1, 0 and 1 (a grid's change)")
    if delta_fingerprint(tensors, meta) != meta["fingerprint"]:
        raise ModelFileError(f"{path}: contents do not match the recorded fingerprint (file damaged?)")
    return Delta(path, tensors, meta)


NUMBER = re.compile(r"[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?")
"""A number as crfedit writes one (``repr`` of a float, ``f"{x:.3f}"``): no ``1_0``, no NaN."""


def _is_number(text: str, infinite: bool = False) -> bool:
    """Whether ``text`` is a finite number as :data:`NUMBER` spells it, or with ``infinite``
    also ``inf`` (a PSNR of a perfect fit)."""
    return bool(NUMBER.fullmatch(text)) or (infinite and text == "inf")


def _json_or_none(text: str):
    """``text`` parsed as JSON; None if it is not."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return None


# ----------------------------------------------------------------------------- validating a stack


def _allowed(field: ConditionalRadianceField, kind: str, version: str) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """Delta tensor name → (shape, dtype) a ``kind`` edit of ``field`` in format ``version`` may store."""
    out: dict[str, tuple[tuple[int, ...], torch.dtype]] = {}
    params = _parameter_names(field)
    if kind != "transfer":
        out.update({n: (tuple(p.shape), p.dtype) for n, p in params.items() if n not in CODE_ROWS.values()})
    for row, table in CODE_ROWS.items():
        out[row] = (tuple(params[table].shape[1:]), params[table].dtype)
    if kind in GRID_KINDS:
        out[GRID] = (tuple(field.occupancy.shape[1:]), field.occupancy.dtype if version == "1" else torch.int8)  # 3: unpacked
    return out


def _base_error(delta: Delta, model: CategoryModel, base: str) -> ModelFileError:
    """Why ``delta`` does not apply to ``model`` (of base ``base``): made for another model, or
    already baked into this one (its ``baked_edits`` list it)."""
    try:
        baked = json.loads(model.meta.get("baked_edits", "[]"))
    except json.JSONDecodeError:
        baked = []
    if isinstance(baked, list) and delta.fingerprint in baked:
        return ModelFileError(f"{delta.path}: is already baked into this model; leave it out (crfedit info lists the baked edits)")
    return ModelFileError(f"{delta.path}: made for model {delta.meta['base']}, not this model ({base}); edits apply only to the model they were made on")


def _order_error(delta: Delta, position: int, deltas: Sequence[Delta], base: str, applied: Sequence[str], baked: bool = False) -> ModelFileError:
    """Why ``delta``'s parent does not match its place in the stack, in one line."""
    where = f"{delta.path}: "
    parent = delta.meta["parent"]
    if delta.fingerprint in applied:  # in the stack the model stands on (a baked model's, or one applied before)
        return ModelFileError(f"{where}is already baked into this model; leave it out (crfedit info lists the baked edits)" if baked
                              else f"{where}is already applied to this model; leave it out")
    if delta.fingerprint in [d.fingerprint for d in deltas[:position]]:
        return ModelFileError(f"{where}is given twice (edit {position + 1} of the stack is an earlier one again); give each edit once")
    if parent == "":
        other = next((d.path for d in deltas[:position] if d.meta["parent"] == ""), None)
        if other is not None:  # two edits of the bare model: alternatives, not a stack
            return ModelFileError(f"{where}made on the bare model, as {other} was: they are two edits of one model, not a stack; "
                                  "to apply both, re-pin them as one with `crfedit edits rebase MODEL --edit … --out-dir DIR`")
        # no other bare edit before it, so the model it meets stands on edits (baked in, or applied before)
        n = len(applied)
        has = f"{n} edit{'s' * (n != 1)} " + ("baked in (crfedit info lists them)" if baked else "applied already")
        return ModelFileError(f"{where}made on the bare model, but this model has {has}; apply it to the model it was made "
                              "on, or re-pin it onto this one with `crfedit edits rebase MODEL --edit … --out-dir DIR`")
    names = [d.path for d in deltas]
    fps = [d.fingerprint for d in deltas]
    # Which earlier prefix (in some order of the other given files) was it made after?
    prefix = list(applied)
    for i, fp in enumerate(fps):
        if i == position:
            continue
        prefix.append(fp)
        if chain_fingerprint(base, prefix) == parent:
            after = ", ".join(n for j, n in enumerate(names) if j != position and j <= i)
            if i < position:  # its stack is a shorter run of the files before it: the rest do not belong there
                extra = [str(n) for n in names[i + 1 : position]]
                return ModelFileError(f"{where}was made after {after} alone, not after {', '.join(extra)}: leave "
                                      f"{'it' if len(extra) == 1 else 'them'} out before it, or re-pin with `crfedit edits rebase`")
            return ModelFileError(f"{where}was made after {after}; pass the --edit files in the order they were made")
    made_on = made_on_files(delta)
    made = "re-pinned onto" if delta.meta.get("rebased") else "made on"
    named = "" if made_on_stack(delta) is not None else ", as recorded"  # those paths may since hold other files
    here = f"{len(applied)} {'baked into' if baked else 'applied to'} the model and {position}" if applied else f"{position}"
    told = (f"; it was {made} {len(made_on)} edit{'s' * (len(made_on) != 1)} ({', '.join(made_on)}{named}), "
            f"here {here} come{'s' * (position == 1 and not applied)} before it"
            if made_on else "; or it was re-pinned onto a model with edits baked in: apply it to that one" if position == 0 and not applied
            else "")
    return ModelFileError(
        f"{where}was made after other edits than the ones before it here (parent {parent}, "
        f"expected {chain_fingerprint(base, list(applied) + fps[:position]) or 'none'}{told}); "
        "pass the --edit files in the order they were made, or re-pin them with `crfedit edits rebase`"
    )


def made_on_files(delta: Delta) -> list[str]:
    """The ``--edit`` files ``delta`` was made on as its command line named them, or, for a file
    re-pinned by ``crfedit edits rebase``, the files given before it in the last rebase (its
    ``command`` still names the stack it was first made on)."""
    rebased = delta.meta.get("rebased")
    if not rebased:
        return _command_edits(delta.meta.get("command", ""))
    last = rebased.split("; then ")[-1]
    given, out_dir = _command_edits(last), _command_option(last, "--out-dir")
    own = os.path.basename(str(delta.path))
    at = next((i for i, e in enumerate(given) if os.path.basename(e) == own), None)
    before = given[:at] if at is not None else []
    # the re-pinned files it sits on are the ones written beside it, not the inputs of the same names
    return [os.path.join(out_dir, os.path.basename(e)) if out_dir else e for e in before]


def made_on_stack(delta: Delta) -> list[Delta] | None:
    """The files :func:`made_on_files` names, read, when they are the very edits ``delta`` was
    made on (their fingerprints chain from its ``base`` to its ``parent``); else None: a recorded
    path may since name another file (moved, renamed, replaced: a shared stack's recipient has
    other files of those names), or the stack stood on a model with edits baked in."""
    paths = made_on_files(delta)
    if not paths:
        return None
    try:
        read = [read_delta(p) for p in paths]
    except (CrfError, OSError, ValueError):
        return None
    return read if chain_fingerprint(delta.meta["base"], [d.fingerprint for d in read]) == delta.meta["parent"] else None


def _command_edits(command: str) -> list[str]:
    """The ``--edit`` files a recorded command line gave (an edit made on a stack names it there);
    [] when it names none or cannot be split."""
    return _command_values(command, "--edit")


def _command_option(command: str, option: str) -> str | None:
    """The last value of ``option`` in a recorded command line, or None."""
    values = _command_values(command, option)
    return values[-1] if values else None


def _command_values(command: str, option: str) -> list[str]:
    """Every value of ``option`` (``--opt V`` or ``--opt=V``) in a recorded command line; [] when
    it has none or cannot be split."""
    import shlex

    try:
        words = shlex.split(command)
    except ValueError:
        return []
    return [w.split("=", 1)[1] if w.startswith(f"{option}=") else words[i + 1] for i, w in enumerate(words)
            if (w == option and i + 1 < len(words)) or w.startswith(f"{option}=")]


def check_stack(model: CategoryModel, deltas: Sequence[Delta], stack: tuple[str, list[str]] | None = None) -> None:
    """Raise a one-line :class:`ModelFileError` naming the first file that does not fit, before
    anything is applied: base model, parent chain (order), instance, tensor names for the kind,
    shapes and dtypes.  ``stack`` is :func:`stack_of` ``(model)`` when the caller has it."""
    base, applied = stack if stack is not None else stack_of(model)
    fps = list(applied)
    names = list(model.names)
    for i, d in enumerate(deltas):
        if d.meta["base"] != base:
            raise _base_error(d, model, base)
        if d.meta["parent"] != chain_fingerprint(base, fps):
            raise _order_error(d, i, deltas, base, applied, "baked_edits" in model.meta)
        if d.kind == "fit-real":
            if d.instance in names:
                raise ModelFileError(f"{d.path}: adds instance {d.instance!r}, which the model already has")
            names.append(d.instance)
        elif d.instance not in names:
            raise ModelFileError(f"{d.path}: edits instance {d.instance!r}, which the model does not have")
        allowed = _allowed(model.field, d.kind, d.meta["version"])
        modules = tuple(d.modules)
        for name, t in d.tensors.items():
            if name not in allowed:
                raise ModelFileError(f"{d.path}: a {d.kind} edit may not hold tensor {name[:80]!r}")
            state = CODE_ROWS.get(name, name)
            if not state.startswith(modules):
                raise ModelFileError(f"{d.path}: tensor {name} lies outside the edit's modules {list(modules)}")
            shape, dtype = allowed[name]
            if tuple(t.shape) != shape or t.dtype != dtype:
                raise ModelFileError(f"{d.path}: tensor {name} has shape {tuple(t.shape)} {t.dtype}, expected {shape} {dtype}")
        fps.append(d.fingerprint)


def rebase(delta: Delta, model: CategoryModel) -> Delta:
    """``delta`` pinned to ``model``'s place instead of its own: the same change, with
    ``base``, ``parent`` and ``fingerprint`` recomputed from :func:`stack_of` ``(model)``.
    Unchanged (the very same object) when it already fits there (:func:`restack` re-pins a
    whole stack); the result passes :func:`check_stack` wherever its instance and tensors fit
    the model.  An optimized edit keeps its tensors; a transfer's change is "take J's code"
    (:func:`retaken`), so its tensors are derived again at the new place."""
    base, stack = stack_of(model)
    parent = chain_fingerprint(base, stack)
    if delta.meta["base"] == base and delta.meta["parent"] == parent:
        return delta
    tensors = retaken(delta, model) if delta.kind == "transfer" else delta.tensors
    meta = {**delta.meta, "base": base, "parent": parent}
    meta["fingerprint"] = delta_fingerprint(tensors, meta)
    return Delta(delta.path, tensors, meta)


def retaken(delta: Delta, model: CategoryModel) -> dict[str, Tensor]:
    """A transfer's tensors as it would make them on ``model``: each code row it took becomes
    the source's row minus the instance's there (and a shape transfer's grid the source's grid
    minus the instance's).  Stored as differences, a transfer rebased as-is took the source's
    code only where the instance's code was what it was when made: left out of a stack's middle,
    a colour transfer gave a code no chair has (1.46 from its source's, chairs lie ~1.15 apart).
    Each code row it stores must name its source in ``hyperparameters`` (``shape_from``,
    ``color_from``: another instance), else a one-line error (``read_delta`` checked it is a JSON
    object; from version 4 the fingerprint covers it)."""
    hyper = _json_or_none(delta.meta.get("hyperparameters") or "{}")
    k = model.instance_index(delta.instance)
    here = instance_state(model, k)
    out = dict(delta.tensors)
    for row, table in CODE_ROWS.items():
        key = f"{'shape' if table == SHAPE_CODES else 'color'}_from"
        source = hyper.get(key) if isinstance(hyper, dict) else None
        if row not in out:
            continue
        if not isinstance(source, str) or not source or source == delta.instance:
            took = "does not name" if source in (None, "") else f"names {str(source)[:40]!r} as"
            raise ModelFileError(f"{delta.path}: a transfer's hyperparameters {took} the instance whose {key[:-5]} code it took ({key}), "
                                 "so it cannot be re-pinned")
        if source not in model.names:
            raise ModelFileError(f"{delta.path}: a transfer takes {source}'s code, and {source} is not in the model at this place "
                                 "(an instance fit-real added: give the edit that adds it before this one)")
        j = model.instance_index(source)
        there = instance_state(model, j)
        out[row] = (there[table][j] - here[table][k]).detach().cpu().to(out[row].dtype).clone()
        if table == SHAPE_CODES and GRID in out:
            out[GRID] = (there[GRID][j].to(torch.int8) - here[GRID][k].to(torch.int8)).cpu()
    return out


def made_where_it_stands(delta: Delta, model: CategoryModel) -> bool:
    """Whether ``delta`` was made on ``model`` as it stands: its parent is the chain of the edits
    ``model`` stands on (so what it recorded can be checked against ``model``)."""
    base, applied = stack_of(model)
    return delta.meta["base"] == base and delta.meta["parent"] == chain_fingerprint(base, applied)


def _check_transfer_record(delta: Delta, model: CategoryModel) -> None:
    """A one-line error unless ``delta`` (a transfer made on ``model`` as it stands) stores the
    change its ``hyperparameters`` name: each code row the named source's minus the instance's.
    A version-3 file's hyperparameters lie outside its fingerprint: one edited to name another
    source passed every check, and re-pinned it took that source's code."""
    stored = dict(delta.tensors)
    expected = retaken(delta, model)
    for row in CODE_ROWS:
        if row in stored and not torch.allclose(stored[row].float(), expected[row].float(), rtol=0, atol=1e-5):
            which = "shape" if row == "shape_code" else "color"
            source = json.loads(delta.meta["hyperparameters"]).get(f"{which}_from")
            raise ModelFileError(f"{delta.path}: its hyperparameters say it took {source}'s {which} code, but the change it "
                                 f"stores is not that ({which}_from edited by hand?); it cannot be re-pinned")


def restack(model: CategoryModel, deltas: Sequence[Delta]) -> tuple[CategoryModel, list[Delta]]:
    """(``model`` with ``deltas`` applied, the deltas re-pinned): each :func:`rebase`-d, in the
    order given, onto the ones before it, to leave an edit out of the middle of a stack, reorder
    it, or share one edit on its own (``crfedit edits rebase``, and ``crfedit ui``'s stack).
    Each keeps its change; an edit made after one that is now left out was optimized on top of
    it, and applies without it.  Every file must be made for ``model`` (its ``base``); instances
    and tensors are checked as :func:`apply_deltas` checks them."""
    base, applied = stack_of(model)
    current, out = model, []
    for i, d in enumerate(deltas):
        if d.meta["base"] != base:
            raise _base_error(d, model, base)
        if d.fingerprint in applied or d.fingerprint in [e.fingerprint for e in deltas[:i]]:  # re-pinned, it applied twice
            raise _order_error(d, i, deltas, base, applied, "baked_edits" in model.meta)
        if d.kind == "transfer" and made_where_it_stands(d, model):  # its record can be checked there
            _check_transfer_record(d, model)
        pinned = rebase(d, current)
        current = apply_deltas(current, [pinned])
        out.append(pinned)
    return current, out


# ----------------------------------------------------------------------------- applying


def grow(model: CategoryModel, name: str) -> CategoryModel:
    """``model`` with one more instance ``name``: zero code rows, an all-occupied grid (safe: it
    renders correctly, only slower).  Overrides of other instances are padded with the same rows."""
    if name in model.names:
        raise ValueError(f"grow: instance {name!r} exists")
    old = model.field
    k = old.n_instances
    field = ConditionalRadianceField.to_load(old.cfg, k + 1, old.aabb.detach().clone()).to(model.device)
    state = {n: t.clone() for n, t in old.state_dict().items()}
    state = _pad(state, k)
    field.load_state_dict(state)
    overrides = {i: _pad(dict(p), k) for i, p in model.overrides.items()}
    return dataclasses.replace(model, field=field, names=[*model.names, name], overrides=overrides, meta=dict(model.meta))


def _pad(state: dict[str, Tensor], k: int) -> dict[str, Tensor]:
    """Append instance row ``k`` (zeros for codes, all-occupied for the grid) to per-instance tables."""
    out = dict(state)
    for table in CODE_ROWS.values():
        if table in out and out[table].shape[0] == k:
            out[table] = torch.cat([out[table], torch.zeros_like(out[table][:1])])
    if GRID in out and out[GRID].shape[0] == k:
        out[GRID] = torch.cat([out[GRID], torch.ones_like(out[GRID][:1])])
    return out


def apply_one(model: CategoryModel, delta: Delta) -> CategoryModel:
    """``model`` with one delta applied, without any check (see :func:`apply_deltas`)."""
    if delta.kind == "fit-real":
        model = grow(model, delta.instance)
    k = model.names.index(delta.instance)
    current = instance_state(model, k)
    replaced = dict(model.overrides.get(k, {}))
    with torch.no_grad():
        for name, t in delta.tensors.items():
            t = t.to(model.device)
            if name in CODE_ROWS:
                table = current[CODE_ROWS[name]].clone()
                table[k] = table[k] + t
                replaced[CODE_ROWS[name]] = current[CODE_ROWS[name]] = table
            elif name == GRID:
                grid = current[GRID].clone()
                grid[k] = t if t.dtype == torch.bool else (grid[k] | (t > 0)) & ~(t < 0)  # version 1: the grid itself
                replaced[GRID] = current[GRID] = grid
            else:
                replaced[name] = current[name] = current[name] + t
    return dataclasses.replace(model, overrides={**model.overrides, k: replaced})


def apply_deltas(model: CategoryModel, deltas: Sequence[Delta]) -> CategoryModel:
    """Check the whole stack (:func:`check_stack`), then apply it; ``model`` is not modified."""
    base, applied = stack_of(model)
    check_stack(model, deltas, (base, applied))
    out = dataclasses.replace(model, meta=dict(model.meta))
    for d in deltas:
        out = apply_one(out, d)
    stack = [*applied, *(d.fingerprint for d in deltas)]
    out.meta.update(edit_base=base, edit_stack=json.dumps(stack))
    cameras = photo_cameras(model, deltas)  # so that the view spec `photo` finds them (views.resolve_views), and bake keeps them
    if cameras:
        out.meta[PHOTO_CAMERAS] = json.dumps(cameras, sort_keys=True)
    out.meta["edit_state"] = out.fingerprint()
    return out


def apply_edit_files(model: CategoryModel, paths: Sequence[str | os.PathLike]) -> CategoryModel:
    """The model with the edit files applied in order.  Every file is read and checked (format,
    version, fingerprint, base model, parent chain, instance, tensor names, shapes, dtypes,
    finite values) before anything is applied; a problem is one :class:`ModelFileError` line
    naming the file and what was expected.  One path alone is a stack of one."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    return apply_deltas(model, [read_delta(p) for p in paths])


def bake(model: CategoryModel, edits: Sequence[str | os.PathLike | Delta]) -> CategoryModel:
    """The stack folded into a model of its own: the edited tensors become ``overrides`` (which
    :func:`~crfedit.model.save_model` writes as ``override.<k>.<name>``).  The baked model keeps
    the stack's record (:func:`stack_of`), so it stands where the stack does: an edit made on the
    unbaked stack continues it, an edit made on the baked model applies to the unbaked stack,
    and a bake of a bake lists every edit since the first base.  ``edits``: edit files, or edits
    already read (the page bakes before it writes anything).  The cameras of the photos that
    fit-real edits fitted their instances to go with them (:func:`photo_cameras`, which
    :func:`apply_deltas` records in the model's metadata)."""
    deltas = [e if isinstance(e, Delta) else read_delta(e) for e in edits]
    applied = apply_deltas(model, deltas)
    base, stack = stack_of(applied)
    meta = dict(applied.meta)  # its stack record too: trusted while the state is the stack's (stack_of)
    meta.update(baked_from=base, baked_edits=json.dumps(stack))
    return dataclasses.replace(applied, names=list(applied.names), meta=meta)


PHOTO_CAMERAS = "photo_cameras"
"""A model's metadata key: {instance name: camera} of the instances fit-real added (a baked
model's, and one :func:`apply_deltas` returns)."""


def photo_cameras(model: CategoryModel, deltas: Sequence[Delta] = ()) -> dict:
    """{instance name: camera record (``c2w``, ``focal``, ``width``, ``height``)} of the instances
    that fit-real edits added: the camera each was fitted from, as ``render --views photo``
    renders it; from ``model``'s metadata (a baked model's) and then ``deltas`` (the later
    wins).  A fit-real edit whose record cannot be read gives an empty record, which
    ``--views photo`` names as unreadable (left out, it was said not to be a fit-real's)."""
    out = {}
    try:
        stored = json.loads(model.meta.get(PHOTO_CAMERAS, "{}"))
        out.update({k: v for k, v in stored.items() if isinstance(k, str) and isinstance(v, dict)} if isinstance(stored, dict) else {})
    except ValueError:
        pass
    for d in deltas:
        if d.kind == "fit-real":
            try:
                camera = json.loads(d.meta["hyperparameters"])["camera"]
            except (KeyError, TypeError, ValueError):
                camera = None
            out[d.instance] = camera if isinstance(camera, dict) else {}
    return out

