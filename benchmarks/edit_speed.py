"""Seconds per selection-supervised edit on a dataset's twins, one torch thread.

    python benchmarks/edit_speed.py MODEL DATA [--repeat 7] [--out FILE.md]

Each twin's scribbles are lifted to the selection its edit makes (the edit kind's options,
timed as `select`); then its edit — the
recolour or the removal that `crfedit eval edits` makes, default options — is made ``--repeat``
times with that selection, after one warm-up edit.  The edit's seconds are the library's own
: ``EditResult.optimize_seconds``, the 100 optimization steps the goals count, and
``EditResult.seconds``, the whole edit after the selection (cached passes, targets, steps and
the delta).  Prints a markdown table (and writes it to --out): per twin the medians.
Run it on an otherwise idle machine: a busy second core slows these small-tensor loops.
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import time
from pathlib import Path

import numpy as np
import torch

from crfedit.edit import EditOptions
from crfedit.evaluation import apply_twin_edit, twin_appearance, twin_selection
from crfedit.report import emit_table
from crfedit.errors import CrfError, run_script

_spec = importlib.util.spec_from_file_location("bench_selection", Path(__file__).with_name("selection.py"))
bench_selection = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_selection)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--repeat", type=int, default=7, help="edits of each twin after a warm-up; their medians count (default 7)")
    ap.add_argument("--out", type=Path, help="also write the table to this markdown file")
    args = ap.parse_args()
    if args.repeat < 1:  # the medians of no edits printed a table of NaN
        raise CrfError(f"--repeat {args.repeat}: must be at least 1")
    model, category, cases = bench_selection.load_twin_benchmark(args.model, args.data)
    twin_selection(model, cases[0])  # warm-up
    options = EditOptions()
    lines = [
        f"Model `{args.model}`, data `{args.data}`; {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} thread; medians of {args.repeat} edits after a warm-up.", "",
        "| twin | edit | select s | optimization s | whole edit s | steps |", "|---|---|---:|---:|---:|---:|",
    ]
    per_kind: dict[str, list[tuple[float, float]]] = {}
    for case in cases:
        t = time.perf_counter()
        sel = twin_selection(model, case)
        select_s = time.perf_counter() - t
        appear = twin_appearance(category, case)
        edit = lambda: apply_twin_edit(model, case, options, appear=appear, selection=sel)
        edit()  # warm-up
        runs = [edit() for _ in range(args.repeat)]
        opt_s, whole_s = (float(np.median([getattr(r, a) for r in runs])) for a in ("optimize_seconds", "seconds"))
        per_kind.setdefault(case.spec.kind, []).append((opt_s, whole_s))
        line = f"| {case.spec.name} | {case.spec.kind} | {select_s:.2f} | {opt_s:.3f} | {whole_s:.3f} | {options.steps} |"
        print(line, flush=True)
        lines.append(line)
    for kind, values in per_kind.items():
        opt_s, whole_s = np.mean(values, axis=0)
        lines.append(f"| **mean** | {kind} | | **{opt_s:.3f}** | {whole_s:.3f} | |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
