"""What a model file holds, by kind, and a copy of it without the training state.

A model file written by ``crfedit train`` carries, besides the networks, what ``--resume``
needs: Adam's two moments per parameter, the occupancy EMA and visual hulls.  That state is
most of the file; a recipient who only renders or edits needs none of it.
"""

from __future__ import annotations

import os
from pathlib import Path

from .safefile import read_header, read_safetensors, write_safetensors

CODES = ("field.shape_codes", "field.color_codes")
SIZE_KINDS = ("weights", "codes", "occupancy", "cameras", "baked edits", "training state")


def tensor_kind(name: str) -> str:
    """The size category of a tensor of a model file, from its name."""
    if name.startswith("train."):
        return "training state"
    if name.startswith("views."):
        return "cameras"
    if name.startswith("override."):
        return "baked edits"
    if name.startswith(CODES):
        return "codes"
    if name.startswith("field.") and "occupancy" in name:
        return "occupancy"
    return "weights"


def size_breakdown(path: str | os.PathLike) -> dict[str, int]:
    """Bytes of tensor data per kind (:data:`SIZE_KINDS`) plus ``header``, read from the header
    only; the values add up to the file size."""
    header, _ = read_header(path)
    sizes = dict.fromkeys(SIZE_KINDS, 0)
    for name, info in header.items():
        start, end = info["data_offsets"]
        sizes[tensor_kind(name)] += end - start
    sizes["header"] = Path(path).stat().st_size - sum(sizes.values())
    return sizes


def strip_model(path: str | os.PathLike, out: str | os.PathLike) -> dict[str, int]:
    """Write ``out``: the model at ``path`` without its training state (it renders, edits and
    bakes the same, bit for bit, but cannot be resumed).  Returns ``out``'s size breakdown."""
    from .model import load_model

    load_model(path)  # validates the file before anything is written
    tensors, meta = read_safetensors(path)
    kept = {name: t for name, t in tensors.items() if tensor_kind(name) != "training state"}
    write_safetensors(out, kept, meta)
    return size_breakdown(out)
