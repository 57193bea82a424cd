"""What one view can give: the twins' edits made from their scribbles, and from the scribbled
view's whole ground-truth part map, scored like `crfedit eval edits`.

    python benchmarks/full_scribble.py DATA MODEL [MODEL ...] [--out FILE.md]

The dataset's scribbles are a few strokes.  Here the simulated user paints the whole part in the
scribbled view (the part's pixels eroded by 1 px, or all of them where fewer than 8 survive) and
every other part as keep (the other parts' pixels 1 px away from it): the most a user can say
from that view.  It reads the ground truth, so it measures how far one view can take the
selection and the edits, not a method.

A third column isolates the features from the rest of the selection: a logistic regression
(:func:`~crfedit.edit.selection.classify.fit_logistic`, default feature groups: bottleneck, colour,
chromaticity, position) fitted on the fully labelled view's rendered surface points and
evaluated at the test views' rendered surface points, over the pixels the part map and the
render both show as object (:func:`~crfedit.twin_scores.surface_iou`, as ``selection_iou``),
with no cells and no refinement.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import platform
from pathlib import Path

import numpy as np
import torch

from crfedit.edit import EditOptions
from crfedit.edit.selection import FEATURES, point_features, surface_points
from crfedit.edit.selection.classify import fit_logistic
from crfedit.evaluation import evaluate_edits, load_category_for, load_twin_cases
from crfedit.masks import dilate, erode
from crfedit.model import load_model
from crfedit.twin_scores import part_map, part_of, surface_iou
from crfedit.report import emit_table
from crfedit.errors import run_script

_spec = importlib.util.spec_from_file_location("bench_edit_models", Path(__file__).with_name("edit_models.py"))
edit_models = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(edit_models)

MIN_FG = 8


def full_labels(parts: np.ndarray, part_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(scribble, keep) painting the whole part and every other part of a part map [H, W]."""
    part = parts == part_id
    fg = erode(part, 1)
    fg = fg if fg.sum() >= MIN_FG else part
    return fg, (parts > 0) & ~dilate(part, 1)


def fully_scribbled(category, case):
    """The twin ``case`` with its scribbles replaced by :func:`full_labels` of its view."""
    inst = category.instance(case.spec.source)
    view = inst.view(case.spec.view)
    ids = part_map(inst.path, view)
    fg, keep = full_labels(ids, part_of(inst.path, case.spec.part)["id"])
    return dataclasses.replace(case, scribble=fg, keep=keep)


@torch.no_grad()
def point_classifier_iou(model, category, case) -> float:
    """The features' own reach: see the module docstring."""
    field, k = model.field_for(case.instance), case.instance
    inst = category.instance(case.spec.source)
    eye = lambda cam: torch.as_tensor(cam.c2w[:3, 3], dtype=torch.float32)
    pts, on = surface_points(field, case.camera, k)
    fg, keep = (torch.from_numpy(m.reshape(-1)) & on for m in (case.scribble, case.keep))
    f_pos, f_neg = (point_features(field, k, pts[m], eye(case.camera), FEATURES) for m in (fg, keep))
    both = torch.cat([f_pos, f_neg])
    mean, std = both.mean(dim=0), both.std(dim=0).clamp_min(1e-6)
    z = lambda f: ((f - mean) / std).double()
    clf = fit_logistic(z(f_pos), z(f_neg), torch.ones(len(f_neg), dtype=torch.float64))
    predict = lambda pts, camera: clf(z(point_features(field, k, pts, eye(camera), FEATURES))) >= 0.5
    views = inst.splits["test"][: len(case.views)]
    return surface_iou(field, k, inst.path, views, part_of(inst.path, case.spec.part)["id"], predict) or 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data")
    ap.add_argument("models", nargs="+")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    lines = [
        f"Data `{args.data}`; {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} thread; hybrid edits, default options.", "",
        "| model | kind | scribbles: gap closed | outside | sel. IoU | whole view: gap closed | outside | sel. IoU "
        "| point classifier IoU, whole view |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for path in args.models:
        model, _ = load_model(path)
        category = load_category_for(model, args.data)
        cases = load_twin_cases(model, category)
        full = [fully_scribbled(category, c) for c in cases]
        strokes = evaluate_edits(model, category, cases, strategies=("hybrid",), options=EditOptions(), paper=False)["runs"]
        whole = evaluate_edits(model, category, full, strategies=("hybrid",), options=EditOptions(), paper=False)["runs"]
        for kind in sorted({c.spec.kind for c in cases}):
            ious = [point_classifier_iou(model, category, c) for c in full if c.spec.kind == kind]
            a, b = edit_models.kind_means(strokes, kind), edit_models.kind_means(whole, kind)
            line = (f"| `{Path(path).name}` | {kind} | {a[0]:.3f} | {a[1]:.2f} | {a[2]:.3f} | {b[0]:.3f} | {b[1]:.2f} "
                    f"| {b[2]:.3f} | {np.mean(ious):.3f} |")
            print(line, flush=True)
            lines.append(line)
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
