"""Shape and colour transfer: instance k takes instance j's shape code or colour code.

No optimization: the edit is the difference of code row k (and, for shape, j's occupancy
grid, since the new shape occupies other cells).  The code rows are the ones that *render*
each instance, i.e. prior edits of either instance are taken into account; j's edited
weights are not (they belong to j).

:func:`swap_codes` (used by ``render --shape-from/--color-from``) and :func:`transfer` (the
``transfer`` command) go through the same delta arithmetic, so rendering a saved transfer and
rendering the swap give bit-identical images.
"""

from __future__ import annotations

import dataclasses
import json
import time

from ..delta import GRID, Delta, apply_one, apply_deltas, instance_state, make_delta
from ..errors import CrfError
from ..model import CategoryModel
from ..names import COLOR_CODES, SHAPE_CODES
from .core import EditResult
from .params import used_code_tables


SAME_CODE = 1e-5
"""A transfer whose code rows move no more than this (and its grid not at all) changes nothing
(codes are of order 1; applying a difference rounds by ~1e-7)."""


def _swapped(
    model: CategoryModel, instance: int | str, shape_from: int | str | None, color_from: int | str | None
) -> tuple[int, CategoryModel, tuple[str, ...], dict]:
    """(k, the model with raw swapped rows, modules, hyper-parameters)."""
    if shape_from is None and color_from is None:
        raise CrfError("transfer: give --shape-from or --color-from (or both)")
    k = model.instance_index(instance)
    field = model.field
    used = used_code_tables(field)
    current = instance_state(model, k)
    replaced = dict(model.overrides.get(k, {}))
    modules: list[str] = []
    hyper: dict = {}
    for which, source, table in (("shape", shape_from, SHAPE_CODES), ("color", color_from, COLOR_CODES)):
        if source is None:
            continue
        if table not in used:
            raise CrfError(f"--{which}-from: a model of arch {field.arch!r} has no separate {which} code")
        j = model.instance_index(source)
        if j == k:
            raise CrfError(f"--{which}-from {model.names[j]}: is the instance being edited; a transfer from itself changes nothing")
        donor = instance_state(model, j)
        value = current[table].clone()
        value[k] = donor[table][j]
        replaced[table] = value
        modules.append(table)
        hyper[f"{which}_from"] = model.names[j]
        if which == "shape" and field.cfg.sampler == "grid":
            grid = current[GRID].clone()
            grid[k] = donor[GRID][j]
            replaced[GRID] = grid
            modules.append(GRID)
    return k, dataclasses.replace(model, overrides={**model.overrides, k: replaced}), tuple(modules), hyper


def own_weights(model: CategoryModel, i: int, which: str) -> list[str]:
    """The modules instance ``i`` renders with weights of its own (fit-real's, or a prior edit's)
    that bear on its ``which`` ("shape": every module but F_rad; "color": F_rad), in model order."""
    from ..names import MODULES

    own = {name.split(".")[0] for name in model.overrides.get(i, {})}
    return [m for m in MODULES if m in own and (m == "F_rad") == (which == "color")]


def weights_not_carried(
    model: CategoryModel, instance: int | str, shape_from: int | str | None = None, color_from: int | str | None = None
) -> list[str]:
    """Notes for a transfer whose codes do not carry a look: a source whose shape or colour comes
    partly from weights of its own, which a code transfer leaves behind (a chair fitted to a
    photo: its F_fuse/F_dens/F_rad), or a target whose own weights read the code it takes."""
    k = model.instance_index(instance)
    taken: dict[int, list[str]] = {}  # source -> what it gives ("shape", "color")
    for which, source in (("shape", shape_from), ("color", color_from)):
        if source is not None and (j := model.instance_index(source)) != k:
            taken.setdefault(j, []).append(which)
    codes = lambda whiches: " and ".join(f"{'colour' if w == 'color' else w} code" for w in whiches)
    notes = []
    for j, whiches in taken.items():
        if mods := [m for w in whiches for m in own_weights(model, j, w)]:
            # a shape's grid travels with its code: cells a removal emptied stay empty (that removal carries over),
            # while matter its own weights make (an added part, a fitted shape) comes as loose specks at most
            grid = ("" if "shape" not in whiches or not [m for m in own_weights(model, j, "shape")] else
                    "; its occupancy grid goes with the shape code, so what a removal took from it stays away, but what its own "
                    "weights add (an added part, a fitted shape) shows as loose specks at most")
            notes.append(f"{model.names[j]} renders with its own {', '.join(mods)} (fitted or edited for it alone): the "
                         f"transfer carries its {codes(whiches)}, not those weights, so {model.names[k]} will not look like it{grid}")
    whiches = [w for ws in taken.values() for w in ws]
    if mods := [m for w in whiches for m in own_weights(model, k, w)]:
        notes.append(f"{model.names[k]} has its own {', '.join(mods)} (fitted or edited for it alone), which read the "
                     f"{codes(whiches)} it takes: it can change less than an instance without weights of its own")
    return notes


def swap_codes(
    model: CategoryModel, instance: int | str, shape_from: int | str | None = None, color_from: int | str | None = None
) -> CategoryModel:
    """A new model (sharing the base field) in which ``instance`` renders with ``shape_from``'s
    shape code and occupancy grid and/or ``color_from``'s colour code; other instances are
    untouched."""
    k, raw, modules, _ = _swapped(model, instance, shape_from, color_from)
    tensors, meta = make_delta(model, raw, k, "transfer", modules)
    return apply_one(model, Delta("(swap)", tensors, meta))


def transfer(
    model: CategoryModel, instance: int | str, shape_from: int | str | None = None, color_from: int | str | None = None
) -> EditResult:
    """The ``transfer`` edit: :func:`swap_codes` recorded as a delta."""
    started = time.perf_counter()
    k, raw, modules, hyper = _swapped(model, instance, shape_from, color_from)
    seconds = time.perf_counter() - started
    extra = {"hyperparameters": json.dumps(hyper, sort_keys=True), "final_loss": "0.0",
             "seconds": f"{seconds:.3f}", "command": ""}
    tensors, meta = make_delta(model, raw, k, "transfer", modules, extra)
    # a transfer given again on its own result wrote an edit that did nothing (its rows differ by
    # the float rounding of applying the first one's difference: k + (j - k) is not j bit for bit)
    if all(float(t.abs().max()) <= SAME_CODE if t.is_floating_point() else not bool(t.any()) for t in tensors.values()):
        took = " and ".join(f"{hyper[w + '_from']}'s {'colour' if w == 'color' else w} code" for w in ("shape", "color") if w + "_from" in hyper)
        raise CrfError(f"{model.names[k]} already renders with {took} (a transfer of it already applied?): this transfer changes "
                       "nothing; nothing was written")
    edited = apply_deltas(model, [Delta("(new edit)", tensors, meta)])
    return EditResult(edited, tensors, meta, 0.0, seconds)
