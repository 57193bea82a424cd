"""`select` from scratch on every twin of a model: one thread, best of 5, the largest grids first.

    python benchmarks/select_speed.py MODEL DATA

The issue's goal is ≤ 0.5 s for a 64³ grid on one core (docs/benchmarks.md says which machine
gave which times: a second job on a 2-core machine changes them a lot).
"""

from __future__ import annotations

import argparse
import time

import torch

from crfedit.edit.selection import select_for
from crfedit.evaluation import load_category_for, load_twin_cases
from crfedit.model import load_model
from crfedit.errors import CrfError, run_script


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--repeats", type=int, default=5, help="selections of each twin; the best time counts (default 5)")
    args = ap.parse_args()
    if args.repeats < 1:  # min() of no times was a traceback
        raise CrfError(f"--repeats {args.repeats}: must be at least 1")
    torch.set_num_threads(1)
    model, _ = load_model(args.model)
    rows = []
    for case in load_twin_cases(model, load_category_for(model, args.data)):
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            select_for(model, case.instance, case.camera, case.scribble, case.keep, case.spec.kind)
            times.append(time.perf_counter() - t0)
        rows.append((int(model.field_for(case.instance).occupancy[case.instance].sum()), case.spec.name, min(times)))
    rows.sort(reverse=True)
    print("| twin | occupied cells | best of %d |\n|---|---:|---:|" % args.repeats)
    for cells, name, best in rows:
        print(f"| {name} | {cells} | {best:.3f} s |")
    print(f"\nmean {sum(r[2] for r in rows) / len(rows):.3f} s, longest {max(r[2] for r in rows):.3f} s")


if __name__ == "__main__":
    run_script(main)
