"""How far the selection limits the edits: the twins' edits made with the oracle selection
(cells labelled by the train views' ground-truth part maps, see benchmarks/selection.py) in place
of the selection computed from the scribbles, scored like `crfedit eval edits`.

    python benchmarks/edit_ceiling.py MODEL DATA [--out FILE.md]

The oracle reads the answer, so this is a diagnostic, not a method: with it, what is left of
the gap to the twin is the edit's own (the losses, the modules it trains, the model), not the
selection's.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from crfedit.twin_scores import part_of
from crfedit.report import emit_table
from crfedit.errors import run_script

_spec = importlib.util.spec_from_file_location("bench_selection", Path(__file__).with_name("selection.py"))
bench_selection = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_selection)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    model, category, cases = bench_selection.load_twin_benchmark(args.model, args.data)
    oracle = {}
    for case in cases:
        inst = category.instance(case.spec.source)
        oracle[id(case.scribble)] = bench_selection.oracle_selection(model, case, inst, part_of(inst.path, case.spec.part)["id"])
    lines = [f"Model `{args.model}`, data `{args.data}`, {len(cases)} twins; hybrid strategy, default options.", "",
             *bench_selection.edit_table_header("selection")]
    for label, by_scribble in (("selection from the scribbles (default)", None), ("oracle selection", oracle)):
        lines.append(f"| {label} | " + bench_selection.edits_with(model, category, cases, by_scribble)[0])
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
