"""The state behind one ``crfedit ui`` page: the model, the edit stack, the selection shown and
caches of rendered views, over the library API (no math here).

The stack is a list of deltas, each on or off.  The model shown is the base model with the
enabled deltas applied in order, re-pinned onto the ones before them (:func:`~crfedit.delta.restack`):
the same tensors (the same change), pinned to its new place, so a saved file of the stack
passes ``crfedit edits check``.  Turning edits off and on again gives back the very same state.

Thread-safe: the server calls it from worker threads; state changes happen under one lock,
renders and edits run outside it on a snapshot.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import io
import itertools
import json
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ..cameras import eye_angles
from ..data.loading import Category
from ..delta import Delta, apply_deltas, bake, delta_bytes, read_delta, restack, save_delta
from ..edit import add, edit_color, remove, transfer
from ..edit.cache import ViewCache
from ..edit.params import TRAINED
from ..edit.selection import SUMMARIES, CellPoints, ScribbleView, Selection, cell_points, options_for, preview, select
from ..edit.supervised import outside_box_note
from ..errors import CrfError
from ..safefile import read_header
from ..model import CategoryModel, save_model
from ..renderer import render_camera
from .recipe import EditRequest, Replay, ScribbleSet, instance_of, parse_scribbles, parse_view

FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,120}\.safetensors")
THUMB_VIEW = {"azimuth": 45.0, "elevation": 30.0}
RENDER_CACHE = 512
"""Rendered views kept (PNG bytes; a 64² view is ~8 KB)."""
VIEW_CACHES = 4
"""Views whose features are kept for instant re-rendering after a colour edit."""
VIEW_RENDERS = 24
"""Views whose renders are kept (their colour, depth and opacity, ~0.1 MB at 64²): a view is
rendered once per instance and stack state, and shown plain, tinted by any selection (the
turntable's eight views at every Select) and lifted by select from it."""


def png_bytes(rgb) -> bytes:
    """A float [H, W, 3] image in [0, 1] (tensor or array) as 8-bit PNG bytes."""
    from PIL import Image

    arr = rgb.detach().cpu().numpy() if isinstance(rgb, torch.Tensor) else np.asarray(rgb)
    arr = np.clip(np.round(np.nan_to_num(arr.astype(np.float64)) * 255.0), 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(arr)).save(buf, format="PNG")
    return buf.getvalue()


def data_url(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode()


@dataclass
class Entry:
    """One edit of the stack: its delta as made (or loaded), how it was made, and whether it is on."""

    id: int
    delta: Delta
    recipe: EditRequest | None  # None: loaded from a file with --edit
    seconds: float
    enabled: bool = True
    source: str = ""  # the file it was loaded from
    made_on: tuple[int, ...] = ()  # the ids of the edits on when it was made, in their order then


class _Lru(OrderedDict):
    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def put(self, key, value):
        self[key] = value
        self.move_to_end(key)
        while len(self) > self.size:
            self.popitem(last=False)
        return value


def _header_says(path: Path, fingerprint: str) -> bool:
    """Whether the safetensors header of ``path`` records ``fingerprint`` (a cheap test before
    :func:`_holds` reads the file)."""
    try:
        return read_header(path)[1].get("fingerprint") == fingerprint
    except (CrfError, OSError, ValueError):
        return False


def _holds(path: Path, edit: Delta | None = None, model: str | None = None) -> bool:
    """Whether the file at ``path`` already holds ``edit`` (its fingerprint) or the model of
    fingerprint ``model`` (read from its header): Save and Bake then leave it as it is."""
    try:
        if edit is not None:
            return read_delta(path).fingerprint == edit.fingerprint
        if model is not None:
            return read_header(path)[1].get("fingerprint") == model
    except (CrfError, OSError):
        return False
    return False


class UiSession:
    """A model, its edit stack and the page's caches (see the module docstring)."""

    def __init__(self, model_path: Path, base: CategoryModel, workdir: Path, device_flag: str | None = None,
                 category: Category | None = None, loaded: list[Delta] = ()):
        self.model_path, self.base, self.workdir = Path(model_path), base, Path(workdir)
        self.device_flag, self.category = device_flag, category
        self._lock = threading.RLock()
        self.entries = [Entry(i + 1, d, None, float(d.meta.get("seconds", "0") or 0), source=d.path) for i, d in enumerate(loaded)]
        self._next_id = len(self.entries) + 1
        self.model, self.pinned = self._rebuild(self.entries)
        self._renders = _Lru(RENDER_CACHE)
        self._fields = _Lru(4)
        self._view_caches = _Lru(VIEW_CACHES)
        self._selections = _Lru(16)
        self._cell_points = _Lru(4)  # (state, instance, ascent) → CellPoints: a stroke re-selects without the density ascent
        self._views = _Lru(VIEW_RENDERS)  # (state, instance, view) → the view's RenderOutput
        self._shown: dict[int, tuple[tuple[ScribbleSet, ...], str]] = {}  # instance → (scribbles, edit kind)
        self._sizes: dict[str, int] = {}

    # ------------------------------------------------------------------------- state

    @property
    def state_key(self) -> tuple[str, ...]:
        return tuple(d.fingerprint for d in self.pinned.values())

    def _rebuild(self, entries: list[Entry]) -> tuple[CategoryModel, dict[int, Delta]]:
        """(model, pinned deltas by entry id) of the enabled entries applied in order."""
        enabled = [e for e in entries if e.enabled]
        model, pinned = restack(self.base, [e.delta for e in enabled])
        return model, {e.id: d for e, d in zip(enabled, pinned)}

    def _snapshot(self, which: str = "current") -> tuple[CategoryModel, tuple[str, ...]]:
        with self._lock:
            return (self.base, ()) if which == "base" else (self.model, self.state_key)

    def state_name(self) -> str:
        key = self.state_key
        return "base" if not key else hashlib.sha256("|".join(key).encode()).hexdigest()[:12]

    def _cached(self, lru: _Lru, key, make: Callable[[], object]):
        """``lru``'s value for ``key``; made by ``make()`` outside the lock and kept when missing."""
        with self._lock:
            hit = lru.get(key)
        if hit is None:
            hit = make()
            with self._lock:
                lru.put(key, hit)
        return hit

    def _field(self, model: CategoryModel, key, k: int):
        return self._cached(self._fields, (key, k), lambda: model.field_for(k))

    def _entry(self, entry_id) -> Entry:
        if isinstance(entry_id, bool) or not isinstance(entry_id, int):
            raise CrfError("id: expected an edit number")
        e = next((e for e in self.entries if e.id == entry_id), None)
        if e is None:
            raise CrfError(f"edit {entry_id!r}: no such edit in the stack")
        return e

    # ------------------------------------------------------------------------- what the page shows

    def info(self) -> dict:
        """Instances, view counts per split, image size, the stack and the state's name."""
        m = self.base
        splits = {s: [len(t.cameras(k)) for k in range(len(m.names))] for s, t in m.views.items()}
        photos = sorted({s for inst in self.category.instances for s in inst.splits}) if self.category else []
        first = next(iter(m.views.values()), None)
        return {
            "model": self.model_path.name, "instances": list(m.names), "splits": splits, "photos": photos,
            "width": first.width if first else None, "height": first.height if first else None,
            "workdir": str(self.workdir), "stack": self.stack_info(), "state": self.state_name(),
        }

    def render(self, instance, view, which: str = "current", tint: bool = False) -> bytes:
        """PNG of ``view`` of ``instance`` in the current (or base) state, the shown selection
        tinted over it when ``tint``."""
        if which not in ("current", "base"):
            raise CrfError("state: expected current or base")
        model, key = self._snapshot(which)
        k = instance_of(model, instance)
        ref = parse_view(view, model, k)
        shown = self._shown_scribbles(k) if tint else None
        cache_key = (key, k, ref.key, None if shown is None else (_canon(shown[0]), shown[1]))

        def make() -> bytes:
            out = self._view(model, key, k, ref)
            if shown is not None:
                return png_bytes(preview(model, self._selection(model, key, k, *shown), ref.camera, out=out, field=self._field(model, key, k)))
            return png_bytes(out.rgb)

        return self._cached(self._renders, cache_key, make)

    def view_angles(self, instance) -> dict:
        """``{split: [[azimuth, elevation], ...]}``: where each stored view of ``instance`` looks
        from, in whole degrees (:func:`~crfedit.cameras.eye_angles`), so the page's orbit sliders
        and orbit tool go on from a stored view instead of from where they were."""
        k = instance_of(self.base, instance)
        return {split: [[round(a) % 360, round(e)] for a, e in (eye_angles(c.c2w[:3, 3]) for c in table.cameras(k))]
                for split, table in self.base.views.items()}

    def thumbnail(self, instance) -> bytes:
        return self.render(instance, THUMB_VIEW)

    def photo(self, instance, split: str, index: int) -> bytes:
        """PNG of a view of ``--data`` (the dataset's own image)."""
        if self.category is None:
            raise CrfError("no dataset: start crfedit ui with --data DATA to see its views")
        k = instance_of(self.base, instance)
        name = self.base.names[k]
        if name not in self.category.names:
            raise CrfError(f"the dataset has no instance {name!r}")
        views = self.category.instance(name).splits.get(split)
        if views is None or not isinstance(index, int) or not 0 <= index < len(views):
            raise CrfError(f"the dataset has no view {split}:{index} of {name}")
        return png_bytes(views[index].rgb)

    # ------------------------------------------------------------------------- selection

    def _selection(self, model: CategoryModel, key, k: int, scribbles: tuple[ScribbleSet, ...], kind: str) -> Selection:
        """The selection ``scribbles`` mean for an edit of ``kind`` (:func:`options_for`), cached."""
        options = options_for(kind)

        def make() -> Selection:
            views = [ScribbleView(s.view.camera, s.fg.mask, None if s.bg is None else s.bg.mask) for s in scribbles]
            renders = [self._view(model, key, k, s.view) for s in scribbles]
            return select(model, k, views, options, renders=renders, points=self._points(model, key, k, options.cell_ascent))

        return self._cached(self._selections, (key, k, _canon(scribbles), kind), make)

    def _points(self, model: CategoryModel, key, k: int, ascent: float) -> CellPoints:
        """Instance ``k``'s :func:`cell_points` in state ``key``, cached: the same for every
        scribble, and the costliest step of a selection (a density ascent over every cell)."""
        return self._cached(self._cell_points, (key, k, ascent), lambda: cell_points(self._field(model, key, k), k, ascent))

    def _view(self, model: CategoryModel, key, k: int, view):
        """Instance ``k``'s render of ``view`` (a parsed view: ``.key``, ``.camera``) in state
        ``key``, cached (:data:`VIEW_RENDERS`): what the page shows, tints a selection over and
        lifts the strokes with (its depth and opacity are a colourless render's bits)."""
        def make():
            with torch.no_grad():
                return render_camera(self._field(model, key, k), view.camera, k)

        return self._cached(self._views, (key, k, view.key), make)

    def _shown_scribbles(self, k: int) -> tuple[tuple[ScribbleSet, ...], str]:
        """(scribbles, edit kind) of the selection shown on instance ``k``."""
        with self._lock:
            shown = self._shown.get(k)
        if shown is None:
            raise CrfError("nothing is selected: scribble 'edit here' on the part and press Select")
        return shown

    def select(self, body) -> dict:
        """Lift the page's scribbles (``{"instance", "views": [{"view", "fg", "bg"}, …], "kind"}``)
        to a 3-D selection for an edit of ``kind`` (color, the default, remove or add), show it
        from now on, and keep the scribbled views' features for a colour edit."""
        if not isinstance(body, dict):
            raise CrfError("expected a JSON object")
        model, key = self._snapshot()
        k = instance_of(model, body.get("instance"))
        scribbles = parse_scribbles(body.get("views"), model, k)
        kind = body.get("kind", "color")
        sel = self._selection(model, key, k, scribbles, kind)
        with self._lock:
            self._shown[k] = (scribbles, kind)
        for s in scribbles:
            self._view_cache(model, key, k, s.view)
        info = sel.meta
        said = [(label, summary(info)) for label, summary in SUMMARIES]
        return {"instance": k, "selected_cells": info["selected_cells"], "occupied_cells": info["occupied_cells"],
                "views": len(scribbles), "seconds": info["seconds"],
                **{label.replace(" ", "_"): line for label, line in said},
                "summaries": [[label, line] for label, line in said if line is not None]}  # the page's line, in order

    def clear_selection(self, instance) -> None:
        k = instance_of(self.base, instance)
        with self._lock:
            self._shown.pop(k, None)

    def _view_cache(self, model, key, k: int, view) -> ViewCache:
        return self._cached(self._view_caches, (key, k, view.key), lambda: ViewCache(self._field(model, key, k), view.camera, k))

    # ------------------------------------------------------------------------- edits

    def run_edit(self, req: EditRequest, on_step: Callable[[int, float], None] | None = None) -> dict:
        """Make the edit ``req`` on the current state and push it onto the stack; returns the new
        entry and the edited view (a colour edit's re-rendered from cached features).  On any
        error the stack is as it was and nothing is written."""
        model, key = self._snapshot()
        k = req.instance
        options = dataclasses.replace(req.options, on_step=on_step)
        if req.kind == "transfer":
            result = transfer(model, k, shape_from=req.shape_from, color_from=req.color_from)
        elif req.kind == "add":
            result = add(model, k, req.view.camera, req.donor, req.copy.mask, req.offset, req.donor_view.camera,
                         req.method, None if req.keep is None else req.keep.mask, options)
        else:
            drawn = req.drawn
            fg, bg = drawn.fg.mask, None if drawn.bg is None else drawn.bg.mask
            sel = self._selection(model, key, k, req.scribbles, req.kind) if req.method == "selection" else None
            if req.kind == "color":
                cache = self._view_cache(model, key, k, req.view)
                result = edit_color(model, k, req.view.camera, fg, req.color, bg, options, req.method, sel)
            else:
                result = remove(model, k, req.view.camera, fg, bg, False, options, req.method, sel)
        png = None
        if req.kind == "color":  # F_rad alone on the view's cached samples (within 1.6e-3 of a full render)
            png = png_bytes(cache.render(result.model.field_for(k)))
        elif req.view is not None:
            shown = render_camera(result.model.field_for(k), req.view.camera, k)
            png = png_bytes(shown.rgb)
        label = "" if req.view is None else req.view.label
        delta = Delta("(page)", result.tensors, {**result.meta, "command": "crfedit ui", "view": label})
        with self._lock:
            if self.state_key != key:
                raise CrfError("the stack changed while the edit ran; apply it again")
            entry = Entry(self._next_id, delta, req, result.seconds, made_on=tuple(e.id for e in self.entries if e.enabled))
            self._next_id += 1
            self.entries.append(entry)
            self.model, self.pinned = result.model, {**self.pinned, entry.id: delta}
            if png is not None and req.kind != "color":
                self._renders.put((self.state_key, k, req.view.key, None), png)  # render()'s key for the untinted view
                self._views.put((self.state_key, k, req.view.key), shown)  # and the render, for a tint or a Select on it
        out = {"entry": entry.id, "stack": self.stack_info(), "state": self.state_name()}
        note = outside_box_note(result.meta, "the paste") if req.kind == "add" else None
        if note:  # as `crfedit add` warns
            out["warning"] = note
        if png is not None and req.on_screen:  # else the page renders the view it shows (a keep-only view's)
            out["image"] = data_url(png)
        return out

    # ------------------------------------------------------------------------- the stack

    def stack_info(self) -> list[dict]:
        with self._lock:
            rows = []
            for i, e in enumerate(self.entries):
                d = self.pinned.get(e.id, e.delta)
                if d.fingerprint not in self._sizes:
                    self._sizes[d.fingerprint] = len(delta_bytes(d.tensors, d.meta))
                rows.append({
                    "id": e.id, "position": i + 1, "kind": d.kind, "instance": d.instance, "bytes": self._sizes[d.fingerprint],
                    "seconds": round(e.seconds, 3), "enabled": e.enabled, "source": Path(e.source).name if e.source else "page",
                    "label": describe(e, self.base.names), "fingerprint": d.fingerprint, "name": self._default_name(i, d), "modules": d.modules,
                    "up": i > 0 and self._commute(self.entries[i - 1], e) is None,
                    "down": i + 1 < len(self.entries) and self._commute(e, self.entries[i + 1]) is None,
                })
            return rows

    def _set(self, entries: list[Entry]) -> dict:
        """Make ``entries`` the stack (a one-line error, and no change, when it does not apply)."""
        model, pinned = self._rebuild(entries)
        self.entries, self.model, self.pinned = entries, model, pinned
        return {"stack": self.stack_info(), "state": self.state_name()}

    def toggle(self, entry_id, enabled: bool) -> dict:
        """Turn an edit on or off (off: the model as if it had not been made)."""
        if not isinstance(enabled, bool):
            raise CrfError("enabled: expected true or false")
        with self._lock:
            entries = [dataclasses.replace(e, enabled=enabled) if e.id == entry_id else e for e in self.entries]
            self._entry(entry_id)
            return self._set(entries)

    @staticmethod
    def _commute(a: Entry, b: Entry) -> str | None:
        """None when edits ``a`` and ``b`` change disjoint tensors (their order cannot change what
        renders), else why they must stay in order."""
        def touched(d: Delta) -> set:
            return {(d.instance, "*")} if d.kind == "fit-real" else {(d.instance, n) for n in d.tensors}

        ta, tb = touched(a.delta), touched(b.delta)
        clash = ta & tb or {x for x in ta if x[1] == "*" and x[0] in {y[0] for y in tb}}
        clash |= {y for y in tb if y[1] == "*" and y[0] in {x[0] for x in ta}}
        if not clash:
            return None
        names = sorted({n for _, n in clash})
        return (f"edits {a.id} and {b.id} both change {', '.join(names[:3])}{', …' if len(names) > 3 else ''} "
                f"of {a.delta.instance}, so their order matters and they stay as made")

    def move(self, entry_id, to) -> dict:
        """Move an edit to position ``to`` (1-based), past edits that change other tensors only."""
        with self._lock:
            e = self._entry(entry_id)
            if isinstance(to, bool) or not isinstance(to, int) or not 1 <= to <= len(self.entries):
                raise CrfError(f"to: expected a position between 1 and {len(self.entries)}")
            entries = list(self.entries)
            i = entries.index(e)
            while i != to - 1:
                j = i + (1 if to - 1 > i else -1)
                a, b = (entries[i], entries[j]) if j > i else (entries[j], entries[i])
                why = self._commute(a, b)
                if why is not None:
                    raise CrfError(why)
                entries[i], entries[j] = entries[j], entries[i]
                i = j
            return self._set(entries)

    def _default_name(self, i: int, d: Delta) -> str:
        safe = re.sub(r"[^A-Za-z0-9._-]", "_", d.instance)[:60]
        return f"{i + 1:02d}-{d.kind}-{safe}.safetensors"

    def target(self, name) -> Path:
        """``workdir/name`` for a plain file name ending in .safetensors; anything else (a path,
        ``..``, the model file itself) is refused."""
        if not isinstance(name, str) or not FILE_NAME.fullmatch(name) or ".." in name:
            raise CrfError("name: expected a plain file name ending in .safetensors (letters, digits, . _ -), written in the work dir")
        path = self.workdir / name
        if path.resolve().parent != self.workdir.resolve() or path.resolve() == self.model_path.resolve():
            raise CrfError(f"name {name}: must name a new file inside the work dir")
        return path

    def free_target(self, name, default: str, edit: Delta | None = None, taken: Sequence[Path] = (), model: str | None = None) -> Path:
        """Where a Save or Bake writes: :meth:`target` of ``name``, which must not exist yet, or
        with no name the first free one of ``default``, ``default-2``, … (none in ``taken``
        either).  A file of the work dir that already holds ``edit`` (the same fingerprint), or
        the model of fingerprint ``model``, whatever its name, is its place: saving an edit or baking a stack twice gives one
        file (an existing path returned holds it already: the caller does not write it again).
        Nothing in the work dir is ever overwritten."""
        holds_edit = lambda path: _holds(path, edit, model)

        if name is not None:
            path = self.target(name)
            if path.exists() and not holds_edit(path):
                raise CrfError(f"name {name}: a file of that name is already in the work dir; pick another name")
            return path
        if edit is not None or model is not None:  # under any name: a Save after the edit moved in the stack found no file of its new default name
            for path in sorted(self.workdir.glob("*.safetensors")) if self.workdir.is_dir() else ():
                if path not in taken and _header_says(path, (edit.fingerprint if edit is not None else model)) and holds_edit(path):
                    return path
        stem = default.removesuffix(".safetensors")
        for i in itertools.count(1):
            path = self.target(default if i == 1 else f"{stem}-{i}.safetensors")
            if path not in taken and (not path.exists() or holds_edit(path)):
                return path

    def delta_file(self, entry_id) -> tuple[str, bytes]:
        """(default file name, bytes) of an edit as it applies in the stack now."""
        with self._lock:
            e = self._entry(entry_id)
            d = self.pinned.get(e.id, e.delta)
            return self._default_name(self.entries.index(e), d), delta_bytes(d.tensors, d.meta)

    def save(self, entry_id, name=None) -> tuple[Path, bool]:
        """Write an edit into the work dir (atomically) as it applies in the stack now, under a
        name no other file there has (:meth:`free_target`); a file that holds it already is
        left as it is.  (The path, whether it was written now.)"""
        with self._lock:
            e = self._entry(entry_id)
            d = self.pinned.get(e.id, e.delta)
            path = self.free_target(name, self._default_name(self.entries.index(e), d), d)
        self.workdir.mkdir(parents=True, exist_ok=True)
        if path.exists():  # free_target gives an existing file only when it holds the edit already
            return path, False
        save_delta(path, d.tensors, d.meta)
        return path, True

    def bake(self, name=None) -> dict:
        """Save every enabled edit into the work dir and fold them into a new model file there."""
        with self._lock:
            enabled = [e for e in self.entries if e.enabled]
            if not enabled:
                raise CrfError("bake: no edit is on; there is nothing to fold into a model")
            targets: list[Path] = []
            for e in enabled:
                d = self.pinned[e.id]
                targets.append(self.free_target(None, self._default_name(self.entries.index(e), d), d, targets))
            files = [(t, self.pinned[e.id]) for t, e in zip(targets, enabled)]
            if name is not None:
                self.target(name)  # a bad name is refused before the stack is baked
        baked = bake(self.base, [d for _, d in files])  # in memory: nothing is written before every check passed
        fingerprint = baked.fingerprint()
        with self._lock:
            out = self.free_target(name, f"{self.model_path.stem}-baked.safetensors", taken=targets, model=fingerprint)
        if out in targets:
            raise CrfError(f"name {out.name}: is the file of an edit; pick another name for the model")
        self.workdir.mkdir(parents=True, exist_ok=True)
        for path, d in files:
            if not path.exists():  # free_target gives an existing file only when it holds the edit already
                save_delta(path, d.tensors, d.meta)
        again = out.exists()  # likewise: the same stack's baked model
        if not again:
            save_model(out, baked, None, extra_meta={"command": "crfedit ui (bake)"})
        return {"model": str(out), "edits": [str(p) for p, _ in files], "again": again}

    def _made_elsewhere(self, e: Entry, i: int) -> bool:
        """Whether edit ``e`` (at ``i`` in the stack) was made with other edits of the instances it
        reads before it (its own; an addition's donor too) than those on before it now: then the
        replay optimizes it again on another state.  A transfer takes its code again, exactly."""
        req = e.recipe
        if req is None or req.kind == "transfer":
            return False
        target, donor = self.base.names[req.instance], self.base.names[req.donor] if req.kind == "add" else None
        by_id = {x.id: x for x in self.entries}

        def read(x: Entry) -> bool:
            """Whether edit ``x`` changes what ``e`` reads: any edit of its instance (a selection reads
            colour too), but an addition reads the target's density and features only, not its colour."""
            if x.delta.instance == donor:
                return True
            colour_only = all(m.startswith(TRAINED["color"]) for m in x.delta.modules)
            return x.delta.instance == target and not (req.kind == "add" and colour_only)

        touches = lambda ids: [j for j in ids if j in by_id and read(by_id[j])]
        return touches(e.made_on) != touches(x.id for x in self.entries[:i] if x.enabled)

    def shell(self) -> str:
        """The ``crfedit`` command lines that replay the enabled edits in order."""
        with self._lock:
            replay = Replay(str(self.model_path.resolve()), list(self.base.names), self.device_flag)
            for i, e in enumerate(self.entries):
                if not e.enabled:
                    continue
                if e.recipe is not None:
                    replay.add_recipe(i + 1, e.recipe, "made on the page with other edits of the chairs it reads before it (one turned "
                                      "off or moved since): here it is optimized again on the edits above, so its file and result differ "
                                      "from the page's" if self._made_elsewhere(e, i) else "")
                elif self.pinned[e.id].fingerprint == e.delta.fingerprint:
                    replay.add_file(str(Path(e.source).resolve()))
                else:
                    path = self.workdir.resolve() / self._default_name(i, self.pinned[e.id])
                    replay.add_file(str(path), f"{e.source} sits elsewhere in the stack now: press Save on it in the page to write {path}")
            return replay.script()


def _canon(scribbles: tuple[ScribbleSet, ...]) -> str:
    """The scribbles as one string: the key of the selection they make."""
    return json.dumps([[s.view.key, s.fg.data, None if s.bg is None else s.bg.data] for s in scribbles], sort_keys=True)


def describe(e: Entry, names: list[str]) -> str:
    """One line about how an edit was made, for the stack panel."""
    r = e.recipe
    if r is None:
        return f"loaded from {Path(e.source).name}"
    if r.kind == "color":
        return f"recolour to {r.color} from {r.view.label}" + (f" (+{len(r.scribbles) - 1} views)" if len(r.scribbles) > 1 else "")
    if r.kind == "remove":
        return f"remove, drawn on {r.view.label}" + (f" (+{len(r.scribbles) - 1} views)" if len(r.scribbles) > 1 else "")
    if r.kind == "add":
        return f"add from {names[r.donor]}, pasted {r.offset[0]},{r.offset[1]} px away on {r.view.label}"
    parts = [f"shape of {names[r.shape_from]}" if r.shape_from is not None else "",
             f"colour of {names[r.color_from]}" if r.color_from is not None else ""]
    return "transfer: " + " and ".join(p for p in parts if p)


def open_session(model_path: Path, data: Path | None, edits: list[Path], workdir: Path, device: str) -> tuple[UiSession, list[str]]:
    """A session on ``model_path`` with the ``--edit`` files on its stack; (session, warnings)."""
    from ..data import load_category
    from ..model import load_model
    from ..runtime import resolve_device

    base, _ = load_model(model_path, resolve_device(device))
    loaded = [read_delta(p) for p in edits]
    apply_deltas(base, loaded)  # every file checked before the page opens
    warnings, category = [], None
    if data is not None:
        category = load_category(Path(data))
        if not set(category.names) & set(base.names):
            raise CrfError(f"--data {data}: none of its instances is in the model")
        if base.dataset_fingerprint and category.fingerprint != base.dataset_fingerprint:
            warnings.append(f"--data {data}: not the dataset the model was trained on (fingerprint differs); its photos may not match the views")
    flag = None if device == "auto" else device
    return UiSession(model_path, base, workdir, flag, category, loaded), warnings
