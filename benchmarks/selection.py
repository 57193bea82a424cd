"""Selection quality and speed on a dataset's twins: IoU of the 3-D selection of each twin's
scribbles with the part's pixels on the source's test views, per selection variant.

    python benchmarks/selection.py MODEL DATA [--out FILE.md]

Prints a markdown table (and writes it to --out): mean IoU over twins per variant, and the
mean seconds of `select` (one torch thread).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from crfedit.data.loading import load_category
from crfedit.edit.selection import ScribbleView, SelectOptions, select
from crfedit.evaluation import load_twin_cases, model_width
from crfedit.model import load_model
from crfedit.twin_scores import selection_iou

VARIANTS = {
    "default (logistic, 3 self-training rounds, smoothing, connectivity)": ({}, True),
    "no keep strokes": ({}, False),
    "no self-training": ({"self_training": 0}, True),
    "no smoothing, no connectivity": ({"smooth": False, "connected": False}, True),
    "features: colour + position": ({"features": ("color", "position")}, True),
    "features: bottleneck + position": ({"features": ("bottleneck", "position")}, True),
    "features: bottleneck + colour": ({"features": ("bottleneck", "color")}, True),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model, _ = load_model(args.model)
    category = load_category(Path(args.data), res=model_width(model, "test"))
    cases = load_twin_cases(model, category)
    select(model, cases[0].instance, [ScribbleView(cases[0].camera, cases[0].scribble, cases[0].keep)])  # warm-up
    lines = [
        f"Model `{args.model}`, data `{args.data}`, {len(cases)} twins; IoU on each source's test views.", "",
        "| variant | mean IoU | min IoU | seconds |", "|---|---:|---:|---:|",
    ]
    for name, (overrides, with_keep) in VARIANTS.items():
        options = dataclasses.replace(SelectOptions(), **overrides)
        ious, secs = [], []
        for case in cases:
            inst = category.instance(case.spec.source)
            t = time.perf_counter()
            sel = select(model, case.instance, [ScribbleView(case.camera, case.scribble, case.keep if with_keep else None)], options)
            secs.append(time.perf_counter() - t)
            ious.append(selection_iou(model, sel, inst.path, inst.splits["test"], case.spec.part))
        ious = [v for v in ious if v is not None]
        row = f"| {name} | {np.mean(ious):.3f} | {np.min(ious):.3f} | {np.mean(secs):.2f} |"
        print(row, flush=True)
        lines.append(row)
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
