"""Selection quality and speed on a dataset's twins: IoU of the 3-D selection of each twin's
scribbles with the part's pixels on the source's test views, per selection variant.

    python benchmarks/selection.py MODEL DATA [--sources NAME,...] [--out FILE.md]

Prints a markdown table (and writes it to --out): mean IoU over twins per variant, and the
mean seconds of `select` (one torch thread).  Two last rows read the answer: an oracle
selection built from the ground-truth part maps of the train views (per cell), and an oracle
that labels each test surface point by its nearest labelled train surface point (per point):
what any labelling of this model's surface can reach under this IoU.  ``--default-only`` skips
the variants.  ``--sources`` keeps only the twins of the named chairs: e.g. the held-out chairs
whose part maps a fold model's head never learned (``benchmarks/heldout_twins.py --folds``
prints them), to measure the variants on chairs the rules were not tuned on.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from crfedit.data.loading import load_category
from crfedit import occupancy
from crfedit.edit.selection import ScribbleView, Selection, options_for, select, select_for, surface_points
import crfedit.evaluation as evaluation
from crfedit.evaluation import evaluate_edits, load_twin_cases, model_width
from crfedit.model import load_model
from crfedit.twin_scores import part_map, part_of, selection_iou, surface_iou
from crfedit.report import emit_table
from crfedit.errors import run_script

VARIANTS = {  # name: (overrides of the edit kind's SelectOptions (options_for), keep strokes given, recolour grows the selection)
    "default (bottleneck + colour + chromaticity + position at each cell's centre moved a half cell up the density gradient; logistic, 3 self-training rounds with the appearance fit, appearance gate, smoothing (bilateral for removals), connectivity; recolours and removals join the chromaticity-only selection; recolours fill the rims; both veto other colours)": ({}, True, False),
    "removals: the shape read from the occupancy grid, weighted 0.25, no gate, no rims (before 2026-11-26)": ({"shape_from": "occupancy", "geometry_weight": 0.25, "shape_gate": 0.0, "rim_fill": 0.0}, True, False),
    "removals: no shape gate": ({"shape_gate": 0.0}, True, False),
    "removals: no rims": ({"rim_fill": 0.0}, True, False),
    "the join refused above 2.5× the full features' cells (the previous default)": ({"chroma_union": 2.5}, True, False),
    "removals do not veto other colours (the revision before)": ({"veto_chroma": 0.0}, True, False),
    "recolours do not fill the rims (an earlier default)": ({"fill_share": 0.0}, True, False),
    "rims filled at a share of 0.3, removals too": ({"fill_share": 0.3}, True, False),
    "rims filled at a share of 0.5, removals too": ({"fill_share": 0.5}, True, False),
    "cells described at their centres (an earlier default)": ({"cell_ascent": 0.0}, True, False),
    "cells moved a quarter cell up the density gradient": ({"cell_ascent": 0.5}, True, False),
    "cells moved a whole cell up the density gradient": ({"cell_ascent": 2.0}, True, False),
    "removals smooth with the plain mean (an earlier default)": ({"smooth_bandwidth": 0.0}, True, False),
    "recolours smooth bilaterally too": ({"smooth_bandwidth": 0.7}, True, False),
    "without the chromaticity-only join": ({"chroma_union": 0.0}, True, False),
    "the join without the saturation test (recolours' default since 2026-11-26)": ({"chroma_saturation": 0.0}, True, False),
    "no pale veto (removals and recolours)": ({"pale_veto": 0.0}, True, False),
    "colour twins scored on the selection grown by hysteresis (Selection.grown; not what the edits use)": ({}, True, True),
    "no appearance gate": ({"appearance_gate": 0.0}, True, False),
    "no appearance fit in self-training": ({"appearance_self_training": False}, True, False),
    "previous default (no appearance fit, no gate, no growth)": ({"appearance_gate": 0.0, "appearance_self_training": False}, True, False),
    "no keep strokes": ({}, False, False),
    "no self-training": ({"self_training": 0}, True, False),
    "no smoothing, no connectivity": ({"smooth": False, "connected": False}, True, False),
    "features: colour + position": ({"features": ("color", "position")}, True, False),
    "features: bottleneck + position": ({"features": ("bottleneck", "position")}, True, False),
    "features: bottleneck + colour": ({"features": ("bottleneck", "color")}, True, False),
    "features: bottleneck + chromaticity + position": ({"features": ("bottleneck", "chroma", "position")}, True, False),
    "features: F_fuse activations in place of the bottleneck": ({"features": ("fuse", "color", "chroma", "position")}, True, False),
    "features: F_fuse activations added": ({"features": ("bottleneck", "fuse", "color", "chroma", "position")}, True, False),
}


@torch.no_grad()
def train_surfaces(model, case, inst) -> list[tuple[torch.Tensor, torch.Tensor, np.ndarray]]:
    """Each train view's rendered surface points [H·W, 3], on-object mask [H·W] and
    ground-truth part ids [H·W]: what both oracles read, rendered once."""
    field = model.field_for(case.instance)
    return [(*surface_points(field, v.camera, case.instance), part_map(inst.path, v).reshape(-1)) for v in inst.splits["train"]]


@torch.no_grad()
def oracle_selection(model, case, inst, part_id: int, surfaces=None) -> Selection:
    """The best a per-cell selection can do on this model: each cell takes the majority label
    of the ground-truth part maps of the train views at the surface points the model renders
    in it (``surfaces``: :func:`train_surfaces`, rendered here when None).  Its IoU on the test views is the ceiling of
    the cell representation (cell size, rendered depth and blur), not a method: it reads the
    ground truth."""
    field, res = model.field_for(case.instance), model.cfg.occ_res
    hit, total = torch.zeros(res**3), torch.zeros(res**3)
    for pts, on, ids in train_surfaces(model, case, inst) if surfaces is None else surfaces:
        ijk, inside = occupancy.cell_index(field.normalize(pts), res)
        m = on & inside
        cell = (ijk[:, 0] * res + ijk[:, 1]) * res + ijk[:, 2]
        gt = torch.from_numpy(ids == part_id).float()
        hit.index_add_(0, cell[m], gt[m])
        total.index_add_(0, cell[m], torch.ones(int(m.sum())))
    values = (hit / total.clamp_min(1)).view(res, res, res)
    return Selection(values, case.instance, model.names[case.instance], model.fingerprint(), {})


@torch.no_grad()
def point_oracle_iou(model, case, inst, part_id: int, surfaces=None) -> float | None:
    """IoU on the test views of labelling each rendered surface point with the ground-truth part
    of the nearest labelled surface point of the train views (``surfaces``:
    :func:`train_surfaces`, rendered here when None; reads the answer, not a method).  No cell size limits it: what is
    left is the model's rendered surface itself, whose depth blurs across part boundaries and
    whose silhouettes differ from the part maps' at 64²."""
    points, labels = [], []
    for pts, on, ids in train_surfaces(model, case, inst) if surfaces is None else surfaces:
        m = on.cpu().numpy() & (ids > 0)
        points.append(pts[torch.from_numpy(m)])
        labels.append(torch.from_numpy(ids[m] == part_id))
    points, labels = torch.cat(points), torch.cat(labels)

    def nearest_label(pts, _camera):
        best = torch.cat([torch.cdist(chunk, points).argmin(1) for chunk in pts.split(4096)])
        return labels[best]

    return surface_iou(model.field_for(case.instance), case.instance, inst.path, inst.splits["test"], part_id, nearest_label)


def edit_table_header(first: str) -> list[str]:
    """Header of the hybrid edits' table that edit_ceiling.py and correction.py print, rows
    from :func:`edits_with`."""
    return [
        f"| {first} | colour gap closed | colour outside | colour sel. IoU | removal gap closed | removal outside | removal sel. IoU |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]


def edits_with(model, category, cases, by_scribble: dict | None = None) -> tuple[str, list[dict]]:
    """The twins' edits (hybrid, default options), made with the given selections
    (``by_scribble``: ``id(case.scribble)`` → Selection) in place of those of their scribbles
    when given: (the table row after its first cell, the hybrid runs per twin)."""
    if by_scribble is not None:  # evaluate_edits calls select_for(model, k, camera, scribble, keep, kind) once per twin
        evaluation.select_for = lambda m, k, camera, scribble, *a, **kw: by_scribble[id(scribble)]
    try:
        result = evaluate_edits(model, category, cases, strategies=("hybrid",), paper=False)
    finally:
        evaluation.select_for = select_for
    c = next(r for r in result["tables"]["color"] if r["method"] == "hybrid")
    r = next(r for r in result["tables"]["remove"] if r["method"] == "hybrid")
    row = (f"{c['gap_closed']:.3f} | {c['psnr_outside']:.2f} dB | {c['selection_iou']:.3f} "
           f"| {r['gap_closed']:.3f} | {r['psnr_outside']:.2f} dB | {r['selection_iou']:.3f} |")
    return row, [x for x in result["runs"] if x["method"] == "hybrid"]


def twins_of(cases: list, sources: list[str]) -> list:
    """The ``cases`` whose source is one of ``sources``; a name that is no twin's source is an error."""
    known, wanted = {case.spec.source for case in cases}, set(sources)
    unknown = [name for name in sources if name not in known]
    if unknown:
        raise SystemExit(f"--sources: no twin has the source {', '.join(unknown)}")
    return [case for case in cases if case.spec.source in wanted]


def load_twin_benchmark(model_path: str, data: str):
    """(model, category at the model's test width, twin cases), one torch thread: what the twin
    benchmarks (this one and edit_ceiling.py) run on."""
    torch.set_num_threads(1)
    model, _ = load_model(model_path)
    category = load_category(Path(data), res=model_width(model, "test"))
    return model, category, load_twin_cases(model, category)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--default-only", action="store_true", help="the default and the oracles, no variants")
    ap.add_argument("--sources", help="only the twins of these chairs (comma-separated names)")
    args = ap.parse_args()
    model, category, cases = load_twin_benchmark(args.model, args.data)
    if args.sources:
        cases = twins_of(cases, args.sources.split(","))
    select(model, cases[0].instance, [ScribbleView(cases[0].camera, cases[0].scribble, cases[0].keep)])  # warm-up
    lines = [
        f"Model `{args.model}`, data `{args.data}`, {len(cases)} twins; IoU on each source's test views.", "",
        "Colour twins are scored on the selection as the recolour uses it, except in the row that says it grows it by hysteresis.", "",
        "| variant | mean IoU | colour twins | removal twins | min IoU | seconds |", "|---|---:|---:|---:|---:|---:|",
    ]

    def iou_line(name, ious, secs):
        """A table row from the twins' IoUs per kind (None: no part maps to score)."""
        ious = {k: [x for x in v if x is not None] for k, v in ious.items()}
        every = ious["color"] + ious["remove"]
        if not every:
            return
        kind = lambda k: f"{np.mean(ious[k]):.3f}" if ious[k] else "–"
        line = f"| {name} | {np.mean(every):.3f} | {kind('color')} | {kind('remove')} | {np.min(every):.3f} | {secs} |"
        print(line, flush=True)
        lines.append(line)

    def row(name, sels, secs, grow):
        ious = {"color": [], "remove": []}
        for case, sel in zip(cases, sels):
            inst = category.instance(case.spec.source)
            changed = sel.grown() if grow and case.spec.kind == "color" else sel
            ious[case.spec.kind].append(selection_iou(model, changed, inst.path, inst.splits["test"], case.spec.part))
        iou_line(name, ious, secs)

    for name, (overrides, with_keep, grow) in list(VARIANTS.items())[: 1 if args.default_only else None]:
        sels, secs = [], []
        for case in cases:
            options = dataclasses.replace(options_for(case.spec.kind), **overrides)
            t = time.perf_counter()
            sels.append(select(model, case.instance, [ScribbleView(case.camera, case.scribble, case.keep if with_keep else None)], options))
            secs.append(time.perf_counter() - t)
        row(name, sels, f"{np.mean(secs):.2f}", grow)
    oracles, points = [], {"color": [], "remove": []}
    for case in cases:
        inst = category.instance(case.spec.source)
        record = part_of(inst.path, case.spec.part)
        if record is None or part_map(inst.path, inst.splits["train"][0]) is None:
            break  # no part maps: no oracle
        surfaces = train_surfaces(model, case, inst)
        oracles.append(oracle_selection(model, case, inst, record["id"], surfaces))
        points[case.spec.kind].append(point_oracle_iou(model, case, inst, record["id"], surfaces))
    else:
        row("oracle: cells labelled by the train views' ground-truth part maps (reads the answer; not a method)", oracles, "–", False)
        iou_line("oracle: each test surface point labelled as its nearest labelled train surface point (reads the answer; no cells)", points, "–")
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
