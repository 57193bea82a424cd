"""Does a second view fix a selection?  The twins' selections corrected by a simulated user, and
the edits made with them, scored like `crfedit eval edits`.

    python benchmarks/correction.py MODEL DATA [--rounds 2] [--pick worst|random|farthest] [--seed 0]
        [--errors thin|eroded] [--filler none|right] [--out FILE.md]

`crfedit select` takes one set of strokes per view, so that a user who sees a wrong selection in
the preview can correct it from another view.  Each round here plays that user, as interactive
segmentation benchmarks do with their simulated clicks: among the twin's train views not used yet,
it takes the one where the current selection errs on the most pixels (ground-truth part maps,
each error region eroded by 1 px so that the blur at part boundaries does not count;
``--errors thin`` also strokes a thin part taken or missed whole, :func:`error_regions`), draws keep
strokes on the wrongly selected pixels and scribble strokes on the missed ones (2 strokes each, the
dataset's stroke size; with nothing missed the view holds keep strokes alone, or with
``--filler right`` also a stroke on the part where it is rightly selected, as it had to before
a view could go without a scribble), adds that view to the scribbles and selects again.  The simulated
user reads the ground truth, so this measures the multi-view selection, not a method.

``--pick`` says which unused train view the user corrects from: ``worst`` (the default, above),
``random`` (any one, drawn with ``--seed``), or ``farthest`` (the one whose viewing direction
makes the largest angle with the nearest of the views already used: what a user who knows
nothing of the errors would turn to).  Only ``worst`` reads the ground truth to choose.
``same`` corrects in the scribbled view itself: the user looks at the preview of the view they
scribbled, strokes its errors there, and the new strokes join that view's (no second view).
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import numpy as np

from crfedit.data.synth import random_strokes
from crfedit.edit.selection import ScribbleView, options_for, select, surface_points
from crfedit.edit.selection.base import merge_views
from crfedit.masks import dilate, erode
from crfedit.twin_scores import part_map, part_of
from crfedit.report import emit_table
from crfedit.errors import run_script

_spec = importlib.util.spec_from_file_location("bench_selection", Path(__file__).with_name("selection.py"))
bench_selection = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_selection)


PICKS = ("worst", "random", "farthest", "same")


def looking(camera) -> np.ndarray:
    """The unit direction a camera looks along (its −Z axis)."""
    d = -np.asarray(camera.c2w, dtype=np.float64)[:3, 2]
    return d / np.linalg.norm(d)


def view_order(inst, used: dict[str, object], pick: str, rng: np.random.Generator) -> list[int]:
    """The unused train views of ``inst`` the user looks at, by ``pick`` (``used``: name →
    camera): one for ``random`` and ``farthest`` (the first of equals), all for ``worst``
    (the error count decides); for ``same`` the scribbled view (the first of ``used``)."""
    if pick == "same":
        split, index = next(iter(used)).split(":")
        if split != "train":
            raise SystemExit(f"--pick same: the scribbled view {split}:{index} is not a train view")
        return [int(index)]
    free = [i for i in range(len(inst.splits["train"])) if f"train:{i}" not in used]
    if pick == "random":
        return [free[int(rng.integers(len(free)))]] if free else []
    if pick == "farthest":
        seen = [looking(c) for c in used.values()]

        def angle(i: int) -> float:  # to the nearest view used
            return min(float(np.arccos(np.clip(looking(inst.splits["train"][i].camera) @ s, -1, 1))) for s in seen)

        return [max(free, key=angle)] if free else []
    return free


ERRORS = ("eroded", "thin")


def error_regions(pred: np.ndarray, gt: np.ndarray, parts: np.ndarray, rule: str = "eroded") -> tuple[np.ndarray, np.ndarray]:
    """(wrongly selected, missed) pixels [H, W] a simulated user would stroke, from the selection
    ``pred``, the part ``gt`` (both on the rendered object) and the view's part map ``parts``
    (0: background).  ``rule`` ``eroded`` (the default): each error region eroded by 1 px, so
    that the blur of the model's and the selection's edges does not count; a 2-px leg taken or
    missed whole is then no error.  ``thin``: that, and, so that such a leg is not eroded away,
    a wrong pixel on another part more than 1 px from the part itself, and a
    missed pixel more than 1 px from both the selection and the other parts (not the part seen
    through a 1-px gap of a grille, where a stroke lifts to the grille's depth)."""
    if rule == "eroded":
        return erode(pred & ~gt, 1), erode(gt & ~pred, 1)
    others = (parts > 0) & ~gt
    wrong = erode(pred & ~gt, 1) | (pred & ~gt & (parts > 0) & ~dilate(gt, 1))
    missed = erode(gt & ~pred, 1) | (gt & ~pred & ~dilate(pred, 1) & ~dilate(others, 1))
    return wrong, missed


FILLERS = ("none", "right")


def correction_view(model, case, inst, part_id: int, sel, used: dict[str, object], rng: np.random.Generator, pick: str = "worst",
                    errors: str = "eroded", filler: str = "none"):
    """(view name, camera, ScribbleView or None) of one simulated correction of ``sel``, or None
    when no view is left to look at.  The ScribbleView is None where the view looked at shows no
    error region (:func:`error_regions`; the user checked it and found nothing to fix);
    ``worst`` looks only where there is one."""
    field, best = model.field_for(case.instance), None
    for i in view_order(inst, used, pick, rng):
        view, name = inst.splits["train"][i], f"train:{i}"
        pts, on = surface_points(field, view.camera, case.instance)
        shape = (view.camera.height, view.camera.width)
        on = on.cpu().numpy().reshape(shape)
        pred = sel.at(field.normalize(pts)).cpu().numpy().reshape(shape) & on
        parts = part_map(inst.path, view)
        gt = (parts == part_id) & on
        wrong, missed = error_regions(pred, gt, parts, errors)
        count = int(wrong.sum() + missed.sum())
        if (count or pick != "worst") and (best is None or count > best[0]):
            best = (count, name, view, wrong, missed, pred & gt)
    if best is None:
        return None
    count, name, view, wrong, missed, right = best
    if not count:
        return name, view.camera, None
    size = view.camera.height
    step, radius = max(3.0, size / 10), max(1.0, size / 48)
    keep = random_strokes(rng, wrong, 2, step, radius)
    scribble = random_strokes(rng, missed, 2, step, radius)
    if not scribble.any() and (filler == "right" or not keep.any()):
        scribble = random_strokes(rng, erode(right, 1) if erode(right, 1).any() else right, 1, step, radius)
    if not scribble.any() and not keep.any():
        return name, view.camera, None
    return name, view.camera, ScribbleView(view.camera, scribble, keep if keep.any() else None)


merged = merge_views  # the library's: ``select`` merges one view given twice the same way


def corrected_selections(model, category, cases, rounds: int, seed: int = 0, pick: str = "worst", errors: str = "eroded",
                         filler: str = "none") -> list[dict]:
    """Per round (0: the twins' own scribbles), {id(case.scribble): Selection} for every twin."""
    out = [dict() for _ in range(rounds + 1)]
    for case in cases:
        inst = category.instance(case.spec.source)
        pid = part_of(inst.path, case.spec.part)["id"]
        options = options_for(case.spec.kind)
        views, used = [ScribbleView(case.camera, case.scribble, case.keep)], {case.spec.view: case.camera}
        rng = np.random.default_rng(seed)
        sel = select(model, case.instance, views, options)
        out[0][id(case.scribble)] = sel
        for r in range(1, rounds + 1):
            found = correction_view(model, case, inst, pid, sel, used, rng, pick, errors, filler)
            if found is not None:
                name, camera, view = found
                used[name] = camera
                if view is not None:
                    if pick == "same":
                        views[0] = merged(views[0], view)
                    else:
                        views.append(view)
                    sel = select(model, case.instance, views, options)
            out[r][id(case.scribble)] = sel
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--pick", choices=PICKS, default="worst", help="which view each correction comes from")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated strokes (and of --pick random)")
    ap.add_argument("--errors", choices=ERRORS, default="eroded", help="which errors the simulated user strokes (error_regions)")
    ap.add_argument("--filler", choices=FILLERS, default="none", help="with nothing missed in a view: keep strokes alone, or also a stroke on the rightly selected part")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    model, category, cases = bench_selection.load_twin_benchmark(args.model, args.data)
    per_round = corrected_selections(model, category, cases, args.rounds, args.seed, args.pick, args.errors, args.filler)
    where = "in the scribbled view" if args.pick == "same" else f"from the {args.pick} unused train view"
    lines = [
        f"Model `{args.model}`, data `{args.data}`, {len(cases)} twins; hybrid strategy, default options; "
        f"round r: the scribbles plus r simulated corrections, each {where} (seed {args.seed}, {args.errors} errors, filler {args.filler}).", "", *bench_selection.edit_table_header("round"),
    ]
    per_twin = []
    for r, selections in enumerate(per_round):
        row, runs = bench_selection.edits_with(model, category, cases, selections)
        lines.append(f"| {r} | {row}")
        per_twin.append({x["twin"]: (x["gap_closed"], x["selection_iou"]) for x in runs})
    lines += ["", "Per twin, gap closed (selection IoU) by round:", "", "| twin | " + " | ".join(f"round {r}" for r in range(len(per_twin))) + " |",
              "|---|" + "---:|" * len(per_twin)]
    for twin in per_twin[0]:
        lines.append(f"| {twin} | " + " | ".join(f"{t[twin][0]:.2f} ({t[twin][1]:.2f})" for t in per_twin) + " |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
