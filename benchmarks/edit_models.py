"""Selection-supervised edits (hybrid) over several models of one category: per model and kind
the mean gap closed, outside PSNR and selection IoU, and the twins left below unedited; the
means' mean and spread over the models.

    python benchmarks/edit_models.py DATA MODEL [MODEL ...] [--seed 0] [--out FILE.md]

One model pair moved the category means by up to 0.2 against another trained with another
seed (docs/benchmarks.md, "The 16-twin benchmark and retrained models"): a change to the
selection or the edits is worth adopting when it holds over several models, which this
measures.  The rows are ``crfedit eval edits``' hybrid rows (`evaluation.evaluate_edits`).
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path

import numpy as np
import torch

from crfedit.edit import EditOptions
from crfedit.evaluation import below_unedited, evaluate_edits, load_category_for, load_twin_cases
from crfedit.model import load_model
from crfedit.report import emit_table
from crfedit.errors import run_script

COLUMNS = ("gap_closed", "psnr_outside", "selection_iou")


def hybrid_rows(runs: list[dict], kind: str) -> list[dict]:
    """The per-twin hybrid runs of ``kind``."""
    return [r for r in runs if r["method"] == "hybrid" and r["kind"] == kind]


def kind_means(runs: list[dict], kind: str) -> tuple[float, ...]:
    """Mean of :data:`COLUMNS` over the hybrid rows of ``kind`` (NaN where a twin has none)."""
    rows = hybrid_rows(runs, kind)
    return tuple(float(np.mean([np.nan if r.get(c) is None else r[c] for r in rows])) for c in COLUMNS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data")
    ap.add_argument("models", nargs="+")
    ap.add_argument("--seed", type=int, default=0, help="the edits' seed")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    lines = [
        f"Data `{args.data}`; {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} thread; hybrid rows, edit seed {args.seed}.", "",
        "| model | kind | twins | gap closed | outside dB | sel. IoU | below unedited |", "|---|---|---:|---:|---:|---:|---:|",
    ]
    per_kind: dict[str, list[tuple[float, ...]]] = {}
    for path in args.models:
        model, _ = load_model(path)
        category = load_category_for(model, args.data)
        cases = load_twin_cases(model, category)
        out = evaluate_edits(model, category, cases, strategies=("hybrid",), options=EditOptions(seed=args.seed), paper=False)
        for kind in sorted({c.spec.kind for c in cases}):
            means = kind_means(out["runs"], kind)
            per_kind.setdefault(kind, []).append(means)
            n = sum(c.spec.kind == kind for c in cases)
            below = below_unedited(hybrid_rows(out["runs"], kind))
            line = f"| `{Path(path).name}` | {kind} | {n} | {means[0]:.3f} | {means[1]:.2f} | {means[2]:.3f} | {below} |"
            print(line, flush=True)
            lines.append(line)
    for kind, values in per_kind.items():
        v = np.array(values)
        mean, spread = v.mean(axis=0), v.std(axis=0)
        lines.append(f"| **mean ± sd over {len(values)}** | {kind} | | **{mean[0]:.3f}** ± {spread[0]:.3f} | "
                     f"{mean[1]:.2f} ± {spread[1]:.2f} | {mean[2]:.3f} ± {spread[2]:.3f} | |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
