"""Reading and writing safetensors files defensively.

Files that users share (models, edits) are parsed without executing anything: the 8-byte
header length and the JSON header are checked by hand (size limits, dtypes, shapes, offsets)
before safetensors touches the data, and metadata is only ever treated as strings.
"""

from __future__ import annotations

import json
import os
import re
import struct
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from .config import MAX_GRID_SIDE
from .errors import ModelFileError
from .io import atomic_write_bytes
from .names import EDIT_FORMAT, MODEL_FORMAT, SELECTION_FORMAT

MAX_HEADER_BYTES = 16 * 1024 * 1024
MAX_FILE_BYTES = 4 * 1024**3
DTYPES = {"F64": 8, "F32": 4, "F16": 2, "BF16": 2, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1, "BOOL": 1}


MAX_META_DEPTH = 64
"""How deep the JSON in a metadata value may nest (crfedit's own nest 4 deep)."""
MAX_META_DIGITS = 1000
"""A run of this many digits in a metadata value is refused (Python reads at most 4300)."""


def _unreadable_json(text: str) -> bool:
    """Whether JSON ``text`` nests past :data:`MAX_META_DEPTH` or holds a number of
    :data:`MAX_META_DIGITS` digits: a shared file's metadata that would make ``json.loads``
    raise RecursionError or ValueError, not a one-line error.  Brackets inside strings count
    too, which only makes it stricter."""
    if re.search(rf"\d{{{MAX_META_DIGITS}}}", text):
        return True
    if text.count("[") + text.count("{") <= MAX_META_DEPTH:
        return False
    depth = 0
    for ch in text:
        if ch in "[{":
            depth += 1
            if depth > MAX_META_DEPTH:
                return True
        elif ch in "]}":
            depth -= 1
    return False


def read_header(path: str | os.PathLike) -> tuple[dict, dict[str, str]]:
    """Validated (tensor table, metadata) of a safetensors file, reading only its header."""
    path = Path(path)
    if not path.is_file():
        from .io import not_a_file

        dataset = path.is_dir() and any((path / n).is_file() for n in ("instances.txt", "transforms_train.json", "transforms.json"))
        hint = "; it is a dataset: the model file (.safetensors) comes first (crfedit COMMAND MODEL DATA)" if dataset else ""
        raise ModelFileError(f"{path}: {not_a_file(path)}{hint}")
    size = path.stat().st_size
    if size < 8:
        raise ModelFileError(f"{path}: not a safetensors file (only {size} bytes)")
    if size > MAX_FILE_BYTES:
        raise ModelFileError(f"{path}: file is larger than {MAX_FILE_BYTES >> 30} GiB")
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        if n > MAX_HEADER_BYTES or n > size - 8:
            if f.read(1) != b"{":  # no header length, and no JSON object after it: a mesh, an image, a text file
                raise ModelFileError(f"{path}: not a safetensors file (crfedit reads models, edits and selections "
                                     "in safetensors; this file's bytes are of another kind)")
            raise ModelFileError(f"{path}: corrupt safetensors header (length {n})")
        raw = f.read(n)
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ModelFileError(f"{path}: corrupt safetensors header (not JSON)") from None
    if not isinstance(header, dict):
        raise ModelFileError(f"{path}: corrupt safetensors header")
    meta = header.pop("__metadata__", {}) or {}
    if not isinstance(meta, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items()):
        raise ModelFileError(f"{path}: metadata must be a table of strings")
    for key, value in meta.items():  # what the loaders' json.loads could not read back (RecursionError, ValueError)
        if _unreadable_json(value):
            raise ModelFileError(f"{path}: bad metadata ({key[:40]!r} nests more than {MAX_META_DEPTH} deep or holds a number "
                                 f"of {MAX_META_DIGITS} digits or more)")
    data_len = size - 8 - n
    for name, info in header.items():
        ok = isinstance(info, dict) and info.get("dtype") in DTYPES and isinstance(info.get("shape"), list)
        ok = ok and all(isinstance(d, int) and d >= 0 for d in info["shape"])
        offs = info.get("data_offsets") if ok else None
        ok = ok and isinstance(offs, list) and len(offs) == 2 and all(isinstance(o, int) for o in offs)
        if ok:
            numel = 1
            for d in info["shape"]:
                numel *= d
            ok = 0 <= offs[0] <= offs[1] <= data_len and offs[1] - offs[0] == numel * DTYPES[info["dtype"]]
        if not ok:
            raise ModelFileError(f"{path}: corrupt entry for tensor {name[:80]!r}")
    return header, meta


def read_safetensors(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """(tensors on CPU, string metadata) after :func:`read_header` validated the file."""
    _, meta = read_header(path)
    try:
        tensors = st_load(Path(path).read_bytes())
    except Exception as e:  # safetensors raises its own error types for corrupt data
        raise ModelFileError(f"{path}: corrupt safetensors data ({e.__class__.__name__})") from None
    return tensors, meta


def safetensors_bytes(tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> bytes:
    """The bytes of a safetensors file of ``tensors`` (moved to CPU, made contiguous) with string
    metadata, the same bytes for the same contents in every process (:func:`canonical_header`)."""
    cpu = {k: v.detach().to("cpu").contiguous() for k, v in tensors.items()}
    return canonical_header(st_save(cpu, metadata={k: utf8(str(v)) for k, v in metadata.items()}))


def utf8(text: str) -> str:
    """``text`` with anything UTF-8 cannot hold written as a backslash escape: a file name that
    is not UTF-8 (in the recorded command line, Python's surrogate escapes) would otherwise fail
    the write after all the work is done."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def canonical_header(raw: bytes) -> bytes:
    """``raw`` (a safetensors file) with its metadata keys in sorted order.  safetensors writes
    them from a hash map in an order that changes from process to process, so two runs of the
    same edit would differ in bytes, not just in their timings; the tensor entries and the data
    are kept as they are (their offsets count from the end of the header, which is padded with
    spaces to 8 bytes, as safetensors pads it)."""
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + n])
    meta = header.pop("__metadata__", None)
    ordered = ({"__metadata__": dict(sorted(meta.items()))} if meta is not None else {}) | header
    text = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + raw[8 + n :]


def write_safetensors(path: str | os.PathLike, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    """Atomically write :func:`safetensors_bytes` ``(tensors, metadata)`` to ``path``."""
    atomic_write_bytes(path, safetensors_bytes(tensors, metadata))


def check_tensors(path, tensors: dict[str, torch.Tensor], expected: dict[str, tuple[tuple[int, ...], torch.dtype]]) -> None:
    """Every tensor must be expected, with the expected shape and dtype."""
    for name, t in tensors.items():
        if name not in expected:
            raise ModelFileError(f"{path}: unexpected tensor {name[:80]!r}")
        shape, dtype = expected[name]
        if tuple(t.shape) != tuple(shape) or t.dtype != dtype:
            raise ModelFileError(
                f"{path}: tensor {name} has shape {tuple(t.shape)} {t.dtype}, expected {tuple(shape)} {dtype}"
            )
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise ModelFileError(f"{path}: tensor {name} contains NaN or inf")


def fingerprint(tensors: dict[str, torch.Tensor]) -> str:
    """A stable 16-hex-digit hash of named tensors (names, dtypes, shapes and bytes)."""
    import hashlib

    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().to("cpu").contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        if t.numel():  # the array's own buffer: no copy of the bytes (10 MB on a 24-chair model)
            h.update(t.reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()[:16]


"""The ``format`` metadata of crfedit's three kinds of file, here so that each kind's module
(:mod:`.model`, :mod:`.delta`, :mod:`.edit.selection.store`) and :func:`other_kind` name them
from one place."""


def other_kind(fmt: object) -> str:
    """What a crfedit file of format ``fmt`` is and where it goes, for an error that found it in
    the wrong place ("" for a format that is not crfedit's)."""
    return {
        MODEL_FORMAT: "; it is a model, which commands take as their MODEL argument",
        EDIT_FORMAT: "; it is an edit file, which commands take as --edit",
        SELECTION_FORMAT: "; it is a selection (crfedit select --out), which edit-color, remove and add take as --selection",
    }.get(fmt if isinstance(fmt, str) else "", "")


def file_format(path: str | os.PathLike) -> str | None:
    """The ``format`` its metadata names of a safetensors file at ``path`` (a crfedit model, edit
    or selection), None for a file that is not safetensors or cannot be read."""
    try:
        return read_header(path)[1].get("format")
    except (ModelFileError, OSError):
        return None


# ----------------------------------------------------------------------------- bit-packed grids


def grid_shape(text: str, bad) -> list[int]:
    """The JSON shape of a packed grid, 3 sizes in [1, MAX_GRID_SIDE]; ``bad(why)`` makes the error."""
    try:
        dims = json.loads(text)
    except (json.JSONDecodeError, TypeError):
        dims = None
    if not isinstance(dims, list) or len(dims) != 3 or not all(type(d) is int and 0 < d <= MAX_GRID_SIDE for d in dims):
        raise bad(f"its shape must be a JSON list of 3 sizes from 1 to {MAX_GRID_SIDE}, not {str(text)[:40]!r}")
    return dims


def pack_bits(mask: np.ndarray) -> torch.Tensor:
    """A bool vector as uint8, one bit per entry, most significant first (``numpy.packbits``),
    the last byte padded with zero bits."""
    return torch.from_numpy(np.packbits(mask.astype(bool, copy=False)))


def unpack_bits(packed: torch.Tensor, n: int, name: str, bad, unit: str = "entries") -> np.ndarray:
    """The ``n`` bools :func:`pack_bits` packed into ``packed``; its dtype, length and zero
    padding are checked first (nothing is unpacked from a tensor of the wrong length)."""
    if packed.dtype != torch.uint8 or packed.dim() != 1:
        raise bad(f"{name} must be a 1-d uint8 tensor, not {list(packed.shape)} {str(packed.dtype).replace('torch.', '')}")
    if packed.numel() != (n + 7) // 8:
        raise bad(f"{name} has {packed.numel()} bytes, {n} {unit} need {(n + 7) // 8}")
    bits = np.unpackbits(packed.numpy())
    if bits[n:].any():
        raise bad(f"{name}'s padding bits are not zero")
    return bits[:n].astype(bool)
