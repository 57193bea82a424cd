"""What a model file holds: its recorded training, a summary (``crfedit info``), bytes by kind,
and a copy of it without the training state.

A model file written by ``crfedit train`` carries, besides the networks, what ``--resume``
needs: Adam's two moments per parameter, the occupancy EMA and visual hulls.  That state is
most of the file; a recipient who only renders or edits needs none of it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import NamedTuple

from .config import Config
from .names import CODE_TABLES, MODULES, is_digits
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


def _view_summary(table) -> dict:
    """``info``'s record of a split's cameras: their count, the first view's size and, for
    views of several sizes, every size (width, height) they come in."""
    out = {"count": int(table.focal.numel()), "size": [table.width, table.height]}
    if table.sizes is not None:
        out["sizes"] = [list(size) for size in sorted({tuple(row) for row in table.sizes.tolist()})]
    return out


def strip_model(path: str | os.PathLike, out: str | os.PathLike) -> dict[str, int]:
    """Write ``out``: the model at ``path`` without its training state (it renders, edits and
    bakes the same, bit for bit, but cannot be resumed).  Returns ``out``'s size breakdown."""
    from .model import load_model

    load_model(path)  # validates the file before anything is written
    tensors, meta = read_safetensors(path)
    kept = {name: t for name, t in tensors.items() if tensor_kind(name) != "training state"}
    write_safetensors(out, kept, meta)
    return size_breakdown(out)


# ----------------------------------------------------------------------------- summaries


class StoredRun(NamedTuple):
    """What a model file's header says of its training run: what ``train --resume`` checks
    before loading anything."""

    cfg: Config
    step: int
    sizes: dict  # split -> [width, height] of the stored views
    elapsed: float | None  # seconds trained; None: written before the key
    minutes: float | None  # the run's --minutes budget; None: none, or written before the key
    dataset: str  # fingerprint of the dataset it was trained on
    resumable: bool  # it holds training state (not baked or stripped)
    seed: int | None = None  # the run's --seed; None: written before the key
    widths: dict | None = None  # split -> the widths of its views, where they come in several


def stored_training(path: str | os.PathLike) -> StoredRun:
    """The run recorded in a model file, read from its header only."""
    header, meta = read_header(path)
    cfg = Config.from_json(meta.get("config", ""))
    step = int(meta["step"]) if is_digits(meta.get("step", "")) else 0
    try:
        sizes = json.loads(meta.get("view_sizes", "{}"))
        widths = json.loads(meta.get("view_widths", "{}"))
    except json.JSONDecodeError:
        sizes, widths = {}, {}

    def number(key: str) -> float | None:
        try:
            value = float(meta[key])
        except (KeyError, ValueError):
            return None
        return value if math.isfinite(value) and value >= 0 else None

    return StoredRun(cfg, step, sizes if isinstance(sizes, dict) else {}, number("elapsed"), number("minutes"),
                     meta.get("dataset_fingerprint", ""), any(tensor_kind(n) == "training state" for n in header),
                     int(meta["seed"]) if is_digits(meta.get("seed", "")) else None,
                     widths if isinstance(widths, dict) else None)


MODULE_ORDER = (*MODULES, *CODE_TABLES)


def _number(text) -> float | None:
    """A metadata value as a finite number (None when it is missing or not one)."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _baked_edits(meta: dict[str, str]) -> list[str] | None:
    """The fingerprints of the edits ``crfedit edits bake`` folded in, in order (None: not a
    baked model, or a record that does not read as a list of them)."""
    try:
        stack = json.loads(meta.get("baked_edits", ""))
    except json.JSONDecodeError:
        return None
    return stack if isinstance(stack, list) and all(isinstance(s, str) for s in stack) else None


def model_info(path: str | os.PathLike) -> dict:
    """What ``crfedit info`` prints, as plain JSON types."""
    from .model import load_model
    from .parts import labelled_names

    path = Path(path)
    model, state = load_model(path)
    field = model.field
    modules: dict[str, dict[str, int]] = {}
    for name, p in field.named_parameters():
        parts = name.split(".")
        key = ".".join(parts[:2]) if parts[0] == "coarse" else parts[0]
        entry = modules.setdefault(key, {"params": 0, "bytes": 0})
        entry["params"] += p.numel()
        entry["bytes"] += p.numel() * p.element_size()
    order = {name: i for i, name in enumerate(MODULE_ORDER)}
    modules = dict(sorted(modules.items(), key=lambda kv: (kv[0].startswith("coarse."), order.get(kv[0].removeprefix("coarse."), len(order)))))
    buffers = {name: b.numel() * b.element_size() for name, b in field.named_buffers()}
    fill = field.occupancy.flatten(1).float().mean(dim=1).tolist()
    for k, params in model.overrides.items():  # a baked edit's grid is the one that instance renders with
        if "occupancy" in params:
            fill[k] = float(params["occupancy"][k].float().mean())
    cfg = model.cfg
    meta = model.meta
    return {
        "path": str(path),
        "file_bytes": path.stat().st_size,
        "sizes": size_breakdown(path),
        "preset": cfg.preset,
        "arch": cfg.arch,
        "sampler": cfg.sampler,
        "instances": len(model.names),
        "names": model.names,
        "parameters": sum(m["params"] for m in modules.values()),
        "modules": modules,
        "buffer_bytes": buffers,
        "occupancy": {
            "used": cfg.sampler == "grid",
            "res": cfg.occ_res,
            "mean_fill": sum(fill) / len(fill),
            "fill": dict(zip(model.names, fill)),
        },
        "scene_box": {"min": field.aabb[:3].tolist(), "max": field.aabb[3:].tolist()},
        "views": {split: _view_summary(t) for split, t in model.views.items()},
        "baked_instances": [model.names[k] for k in sorted(model.overrides)],
        "baked_edits": _baked_edits(meta),
        "baked_from": meta.get("baked_from"),
        "dataset_fingerprint": model.dataset_fingerprint,
        "part_labelled": labelled_names(meta) if field.F_part is not None else None,
        "fingerprint": model.fingerprint(),
        "step": int(meta["step"]) if is_digits(meta.get("step", "")) else None,
        "steps": cfg.steps,
        "train_seconds": float(state["elapsed"]) if "elapsed" in state else _number(meta.get("elapsed")),  # a stripped model keeps it in its metadata
        "resumable": bool(state),
        "command": meta.get("command"),
        "config": json.loads(cfg.to_json()),
    }
