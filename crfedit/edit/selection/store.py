"""The selection file (``crfedit select --out``): safetensors, version 2 stores only the cells
with a value; version 1 still reads."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from ...config import MAX_GRID_SIDE
from ...errors import CrfError
from ...safefile import SELECTION_FORMAT, grid_shape, other_kind, pack_bits, read_safetensors, unpack_bits, write_safetensors
from .base import Selection

FORMAT = SELECTION_FORMAT
VERSION = "2"
READ_VERSIONS = ("1", "2")
"""Version 1 stored ``values`` as uint8 [R, R, R]; version 2 stores only the cells with a value
(``nonzero`` bit-packed, ``levels`` uint8): 39–50 KB against 263 KB for the benchmark twins'
64³ selections.  Both read."""
SPARSE = ("nonzero", "levels")


def quantized(values: Tensor, cuts: Sequence[float]) -> Tensor:
    """``values`` [R, R, R] clamped to [0, 1] and rounded to the 256 levels k/255 a selection
    file stores, each cell kept on its side of every cut in ``cuts``.

    A selection is used as computed (the page, one-step edits) and as read back from its file
    (``--selection``): the two must be the same tensor.  Plain rounding is not enough at a cut:
    filling the rims sets cells to exactly the recolour's cut 0.3, which rounds to 76/255 =
    0.298, below it, so a file dropped every filled cell.

    Each cell's level depends on its own value alone, and with every cut above 0 a cell at or
    below 0 is level 0: only the cells above 0 (the occupied ones, a seventh of a 64³ grid) are
    rounded, to the same bits."""
    if all(cut > 0 for cut in cuts):
        above = values > 0
        out = torch.zeros_like(values)
        out[above] = _levels(values[above], cuts)
        return out
    return _levels(values, cuts)


def _levels(values: Tensor, cuts: Sequence[float]) -> Tensor:
    """:func:`quantized` of every value."""
    v = values.clamp(0, 1)
    q = (v * 255).round()
    levels = torch.arange(256, dtype=q.dtype, device=q.device)
    for cut in cuts:
        up = float(levels[levels / 255.0 >= cut][0]) if cut <= 1 else 256.0  # the lowest level on or above the cut, read
        down = up - 1  # back as the file's reader does (float32), and the one below it
        q = torch.where((v >= cut) & (q / 255.0 < cut), torch.full_like(q, up), q)
        q = torch.where((v < cut) & (q / 255.0 >= cut), torch.full_like(q, down), q)
    return q / 255.0


def save_selection(path: str | Path, sel: Selection) -> None:
    """Write ``sel`` atomically as safetensors (version 2), sparse: ``nonzero`` uint8, one bit per
    cell of the [R, R, R] grid in C order (most significant first, as ``numpy.packbits``), set
    where the value is above 0; ``levels`` uint8, value·255 of each such cell in the same order;
    and string metadata, ``shape`` the grid's JSON shape.  A 64³ grid's mask is 32 KiB plus a
    byte per cell with a value, against 256 KiB for the whole grid as uint8 (version 1).
    Values outside [0, 1], NaN or a threshold outside (0, 1] are refused (:meth:`Selection.check_values`):
    the file would read back otherwise, or not at all."""
    sel.check_values()
    q = (sel.values * 255).round().to(torch.uint8).cpu().contiguous().numpy()
    nonzero = q.reshape(-1) != 0
    meta = {
        "format": FORMAT, "version": VERSION, "model_fingerprint": sel.model_fingerprint,
        "instance": sel.instance_name, "instance_index": str(sel.instance), "threshold": repr(float(sel.threshold)),  # a numpy float's repr is np.float64(0.5)
        "shape": json.dumps(list(q.shape)), "info": json.dumps(sel.meta, sort_keys=True),
    }
    tensors = {SPARSE[0]: pack_bits(nonzero), SPARSE[1]: torch.from_numpy(q.reshape(-1)[nonzero])}
    write_safetensors(Path(path), tensors, meta)


def grid_values(path: str | Path, tensors: dict[str, Tensor], meta: dict[str, str]) -> Tensor:
    """The uint8 [R, R, R] grid a selection file holds, in either version; every shape, length
    and padding bit is checked (a declared shape the file does not fill allocates nothing)."""
    def bad(why: str) -> CrfError:
        return CrfError(f"{path}: bad selection grid ({why})")

    if meta.get("version") == "1":
        values = tensors.get("values")
        if values is None or values.dtype != torch.uint8 or values.dim() != 3 or len(set(values.shape)) != 1:
            raise CrfError(f"{path}: 'values' must be a uint8 [R, R, R] grid")
        if values.shape[0] > MAX_GRID_SIDE:
            raise bad(f"its side is {values.shape[0]}, at most {MAX_GRID_SIDE}")
        return values
    if set(tensors) != set(SPARSE) or "shape" not in meta:
        raise bad(f"a version-2 file holds the tensors {' and '.join(SPARSE)} and the metadata key shape")
    dims = grid_shape(meta["shape"], bad)
    if len(set(dims)) != 1:
        raise bad(f"the grid must be a cube, not {dims}")
    nonzero = unpack_bits(tensors[SPARSE[0]], dims[0] ** 3, SPARSE[0], bad, "cells")
    levels = tensors[SPARSE[1]]
    if levels.dtype != torch.uint8 or levels.dim() != 1 or levels.numel() != int(nonzero.sum()):
        raise bad(f"{SPARSE[1]} must be {int(nonzero.sum())} uint8 values, one per set bit of {SPARSE[0]}, not {list(levels.shape)} {str(levels.dtype).replace('torch.', '')}")
    if levels.numel() and int(levels.min()) == 0:
        raise bad(f"{SPARSE[1]} holds a 0 where {SPARSE[0]} says the cell has a value")
    out = np.zeros(dims[0] ** 3, dtype=np.uint8)
    out[nonzero] = levels.numpy()
    return torch.from_numpy(out.reshape(dims))


def load_selection(path: str | Path) -> Selection:
    """Read a selection file, version 1 or 2 (safetensors only; nothing in it is executed)."""
    tensors, meta = read_safetensors(Path(path))
    if meta.get("format") != FORMAT:
        raise CrfError(f"{path}: not a crfedit selection file (format {meta.get('format')!r}){other_kind(meta.get('format'))}")
    if meta.get("version") not in READ_VERSIONS:
        raise CrfError(f"{path}: selection format version {meta.get('version')!r} is not supported (expected {' or '.join(READ_VERSIONS)})")
    values = grid_values(path, tensors, meta)
    try:
        info = json.loads(meta.get("info", "{}"))
        threshold = float(meta.get("threshold", "0.5"))
        index = int(meta.get("instance_index", "-1"))
    except ValueError as e:
        raise CrfError(f"{path}: corrupt selection metadata ({e})") from None
    if not 0.0 < threshold <= 1.0:  # False for NaN: every cell would count as unselected
        raise CrfError(f"{path}: corrupt selection metadata (threshold {meta.get('threshold')!r}: expected a number in (0, 1])")
    return Selection(values.float() / 255.0, index, meta.get("instance", ""), meta.get("model_fingerprint", ""), info, threshold)
