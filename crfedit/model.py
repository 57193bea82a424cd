"""The model file: one ``.safetensors`` holding a trained category.

Tensors: ``field.*`` (weights, per-instance codes, occupancy grids, scene box), optionally
``override.<k>.<param>`` (instance-scoped weights folded in by ``edits bake``) and ``train.*``
(optimizer and sampler state so ``train --resume`` continues bit for bit).  Metadata (strings):
``format``, ``version``, ``config`` (JSON), ``instances`` (JSON list of names),
``dataset_fingerprint``, ``fingerprint`` (hash of the field and overrides, which edits record
as their base), ``step``, ``elapsed`` (seconds trained) and ``minutes`` (the run's time budget,
when it has one), which ``train --resume`` reads from the header alone, and the command line.
"""

from __future__ import annotations

import copy
import json
import os
from dataclasses import dataclass, field as dc_field

import numpy as np
import torch
from torch import Tensor

from .cameras import Camera
from .config import Config
from .errors import CrfError, ModelFileError
from .field import ConditionalRadianceField
from .names import INSTANCE_TABLES, did_you_mean, is_digits, whole_number
from .safefile import MODEL_FORMAT, check_tensors, fingerprint, other_kind, read_header, read_safetensors, write_safetensors

FORMAT = MODEL_FORMAT
VERSION = "1"


@dataclass
class CategoryModel:
    """A trained category: the field, its instance names, and any baked per-instance weights."""

    field: ConditionalRadianceField
    names: list[str]
    dataset_fingerprint: str = ""
    overrides: dict[int, dict[str, Tensor]] = dc_field(default_factory=dict)
    meta: dict[str, str] = dc_field(default_factory=dict)
    views: dict[str, "ViewTable"] = dc_field(default_factory=dict)
    """The dataset's cameras per split, so ``train:7`` resolves without the dataset."""

    @property
    def cfg(self) -> Config:
        return self.field.cfg

    @property
    def device(self) -> torch.device:
        return self.field.aabb.device

    def instance_index(self, key: str | int) -> int:
        """An instance by name or index (a NumPy or torch integer too); unknown → one-line error
        naming a few valid ones."""
        if not isinstance(key, str):
            index = whole_number(key)  # np.int64 from np.argmax and 0-d integer tensors pass; bools do not
            if index is None:
                raise CrfError(f"instance {key!r}: expected an instance name or an integer index")
            key = index
        if isinstance(key, int) or (isinstance(key, str) and is_digits(key.lstrip("-")) and key not in self.names):
            k = int(key)
            if 0 <= k < len(self.names):
                return k
            raise CrfError(f"instance {k}: out of range (the model has {len(self.names)} instances, 0–{len(self.names) - 1})")
        if key in self.names:
            return self.names.index(key)
        shown = ", ".join(self.names[:5]) + (", …" if len(self.names) > 5 else "")
        hint = did_you_mean(key, self.names) or "; an instance fit-real added exists with its edit file (--edit) or baked in (edits bake)"
        raise CrfError(f"unknown instance {key!r} (instances: {shown}){hint}")

    def state(self) -> dict[str, Tensor]:
        """Every tensor that defines what the model renders (no training state)."""
        out = {f"field.{k}": v for k, v in self.field.state_dict().items()}
        for k, params in self.overrides.items():
            out.update({f"override.{k}.{name}": v for name, v in params.items()})
        return out

    def fingerprint(self) -> str:
        return fingerprint(self.state())

    def field_for(self, instance: int | str) -> ConditionalRadianceField:
        """The field that renders ``instance`` (a name or an index, :meth:`instance_index`): the
        shared one, or a copy carrying the tensors (weights, code tables, occupancy) that edits
        of this instance replaced.  (A name, looked up by index alone, gave the unedited field.)"""
        params = self.overrides.get(self.instance_index(instance))
        if not params:
            return self.field
        f = copy.deepcopy(self.field)
        with torch.no_grad():
            sd = f.state_dict(keep_vars=True)
            for name, value in params.items():
                sd[name].copy_(value)
        return f

    def to(self, device: torch.device | str) -> "CategoryModel":
        self.field.to(device)
        self.overrides = {k: {n: v.to(device) for n, v in p.items()} for k, p in self.overrides.items()}
        return self


@dataclass
class ViewTable:
    """The cameras of one split of every instance, flattened in instance then view order.

    ``width``/``height`` are the first view's size; ``sizes`` ([V, 2] int64 width, height) is
    set only when the views come in several sizes, each focal then at its own view's size (a
    table of one size is stored as before, the same bytes)."""

    c2w: Tensor  # [V, 4, 4] float64
    focal: Tensor  # [V] float64, pixels at the view's size
    instance: Tensor  # [V] int64
    width: int
    height: int
    sizes: Tensor | None = None  # [V, 2] int64 (width, height), None: every view width × height

    def size(self, row: int) -> tuple[int, int]:
        return (self.width, self.height) if self.sizes is None else tuple(int(x) for x in self.sizes[row])

    @property
    def widths(self) -> list[int]:
        """The views' distinct widths, ascending."""
        return [self.width] if self.sizes is None else sorted(set(self.sizes[:, 0].tolist()))

    def cameras(self, instance: int) -> list[Camera]:
        rows = (self.instance == instance).nonzero().squeeze(-1).tolist()
        return [Camera(self.c2w[i].numpy().copy(), float(self.focal[i]), *self.size(i)) for i in rows]

    @classmethod
    def from_category(cls, category, split: str) -> "ViewTable | None":
        views = [(k, v.camera) for k, inst in enumerate(category.instances) for v in inst.splits.get(split, [])]
        if not views:
            return None
        w, h = views[0][1].width, views[0][1].height
        sizes = [(c.width, c.height) for _, c in views]
        return cls(
            torch.tensor(np.stack([c.c2w for _, c in views]), dtype=torch.float64),
            torch.tensor([c.focal for _, c in views], dtype=torch.float64),
            torch.tensor([k for k, _ in views], dtype=torch.int64),
            w,
            h,
            None if len(set(sizes)) == 1 else torch.tensor(sizes, dtype=torch.int64),
        )

    def tensors(self, split: str) -> dict[str, Tensor]:
        out = {f"views.{split}.c2w": self.c2w, f"views.{split}.focal": self.focal, f"views.{split}.instance": self.instance}
        return out if self.sizes is None else {**out, f"views.{split}.size": self.sizes}


def save_model(
    path: str | os.PathLike,
    model: CategoryModel,
    train_state: dict[str, Tensor] | None = None,
    extra_meta: dict[str, str] | None = None,
) -> None:
    """Write the model atomically (temp file, fsync, rename).  An instance's override of a
    per-instance table (codes, occupancy grid) that differs from the field's in its own row alone
    is stored as that row: a baked removal stored the whole [K, 64³] grid table again (2.1 MB
    for 8 chairs, 6.3 MB for 24); :func:`load_model` puts the row back into the field's table."""
    tensors = model.state()
    shared = model.field.state_dict()
    for k, params in model.overrides.items():
        for name in INSTANCE_TABLES:
            t = params.get(name)
            if t is None or t.shape != shared[name].shape:
                continue
            others = torch.ones(t.shape[0], dtype=torch.bool, device=t.device)
            others[k] = False
            if torch.equal(t[others], shared[name][others]):
                tensors[f"override.{k}.{name}"] = t[k].clone()
    for split, table in model.views.items():
        tensors.update(table.tensors(split))
    tensors.update({f"train.{k}": v for k, v in (train_state or {}).items()})
    meta = dict(model.meta)
    meta.update(extra_meta or {})
    meta.update(
        format=FORMAT,
        version=VERSION,
        config=model.cfg.to_json(),
        instances=json.dumps(model.names),
        dataset_fingerprint=model.dataset_fingerprint,
        fingerprint=model.fingerprint(),
        view_sizes=json.dumps({split: [t.width, t.height] for split, t in model.views.items()}),
    )
    widths = {split: t.widths for split, t in model.views.items() if t.sizes is not None}
    if any(len(w) > 1 for w in widths.values()):  # views of several widths: --resume loads each at its own
        meta["view_widths"] = json.dumps(widths)
    write_safetensors(path, tensors, meta)


def load_model(path: str | os.PathLike, device: torch.device | str = "cpu") -> tuple[CategoryModel, dict[str, Tensor]]:
    """(model, training state) from a model file, validated before anything is used, on
    ``device`` (a ``torch.device``, or auto, cpu or cuda as ``--device`` takes)."""
    from .runtime import resolve_device

    device = resolve_device(device)
    header, meta = read_header(path)
    if meta.get("format") != FORMAT:
        kind = meta.get("format", "unknown")
        raise ModelFileError(f"{path}: not a crfedit model (format {kind!r}){other_kind(kind)}")
    if meta.get("version") != VERSION:
        raise ModelFileError(f"{path}: model format version {meta.get('version')!r} is not supported (expected {VERSION})")
    try:
        cfg = Config.from_json(meta.get("config", ""))
        names = json.loads(meta.get("instances", ""))
    except (CrfError, json.JSONDecodeError) as e:
        raise ModelFileError(f"{path}: bad metadata ({e})") from None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names) or not names:
        raise ModelFileError(f"{path}: bad metadata (instances must be a non-empty list of names)")
    if len(set(names)) != len(names):
        raise ModelFileError(f"{path}: bad metadata (duplicate instance names)")
    k = len(names)
    if header.get("field.shape_codes", {}).get("shape", [None])[0] != k:
        raise ModelFileError(f"{path}: instance list does not match the stored codes")
    tensors, meta = read_safetensors(path)
    field = ConditionalRadianceField.to_load(cfg, k)
    expected = {f"field.{n}": (tuple(v.shape), v.dtype) for n, v in field.state_dict().items()}
    params = {n: (tuple(p.shape), p.dtype) for n, p in field.state_dict().items()}
    core = {n: t for n, t in tensors.items() if n.startswith("field.")}
    missing = sorted(set(expected) - set(core))
    if missing:
        raise ModelFileError(f"{path}: missing tensor {missing[0]}")
    check_tensors(path, core, expected)
    overrides: dict[int, dict[str, Tensor]] = {}
    for name, t in tensors.items():
        if name.startswith("override."):
            _, idx, pname = name.split(".", 2)
            if not is_digits(idx) or int(idx) >= k or pname not in params:
                raise ModelFileError(f"{path}: unexpected tensor {name[:80]!r}")
            if pname in INSTANCE_TABLES and tuple(t.shape) == params[pname][0][1:] and t.dtype == params[pname][1]:
                row, t = t, core[f"field.{pname}"].clone()  # the instance's own row (save_model): into the field's table
                t[int(idx)] = row
            check_tensors(path, {pname: t}, params)
            overrides.setdefault(int(idx), {})[pname] = t.to(device)
        elif not name.startswith(("field.", "train.", "views.")):
            raise ModelFileError(f"{path}: unexpected tensor {name[:80]!r}")
    views = _read_views(path, tensors, meta, k)
    field.load_state_dict({n[len("field.") :]: t for n, t in core.items()})
    model = CategoryModel(field.to(device), names, meta.get("dataset_fingerprint", ""), overrides, meta, views)
    if meta.get("fingerprint") and meta["fingerprint"] != model.fingerprint():
        raise ModelFileError(f"{path}: contents do not match the recorded fingerprint (file damaged?)")
    train_state = {n[len("train.") :]: t for n, t in tensors.items() if n.startswith("train.")}
    return model, train_state


def _read_views(path, tensors: dict[str, Tensor], meta: dict[str, str], n_instances: int) -> dict[str, ViewTable]:
    try:
        sizes = json.loads(meta.get("view_sizes", "{}"))
    except json.JSONDecodeError:
        raise ModelFileError(f"{path}: bad metadata (view_sizes)") from None
    out = {}
    for split, size in sizes.items() if isinstance(sizes, dict) else []:
        c2w, focal, inst = (tensors.get(f"views.{split}.{n}") for n in ("c2w", "focal", "instance"))
        ok = isinstance(size, list) and len(size) == 2 and all(isinstance(x, int) and 0 < x <= 16384 for x in size)
        ok = ok and c2w is not None and focal is not None and inst is not None
        ok = ok and c2w.dtype == torch.float64 and c2w.ndim == 3 and tuple(c2w.shape[1:]) == (4, 4)
        ok = ok and focal.shape == (c2w.shape[0],) and inst.shape == (c2w.shape[0],) and inst.dtype == torch.int64
        ok = ok and bool(torch.isfinite(c2w).all()) and bool((focal > 0).all())
        ok = ok and bool(((inst >= 0) & (inst < n_instances)).all())
        each = tensors.get(f"views.{split}.size")  # views of several sizes
        ok = ok and (each is None or (each.dtype == torch.int64 and tuple(each.shape) == (c2w.shape[0], 2)
                                      and bool(((each > 0) & (each <= 16384)).all())))
        if not ok:
            raise ModelFileError(f"{path}: bad camera table for split {split!r}")
        out[split] = ViewTable(c2w, focal, inst, size[0], size[1], each)
    return out
