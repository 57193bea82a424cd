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

import crfedit.evaluation as evaluation
from crfedit.evaluation import evaluate_edits
from crfedit.twin_scores import part_of

_spec = importlib.util.spec_from_file_location("bench_selection", Path(__file__).with_name("selection.py"))
bench_selection = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_selection)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    model, category, cases = bench_selection.load_twin_benchmark(args.model, args.data)
    rows = {}
    for label, oracle in (("selection from the scribbles (default)", False), ("oracle selection", True)):
        if oracle:
            by_scribble = {}
            for case in cases:
                inst = category.instance(case.spec.source)
                pid = part_of(inst.path, case.spec.part)["id"]
                by_scribble[id(case.scribble)] = bench_selection.oracle_selection(model, case, inst, pid)
            # evaluate_edits calls select(model, k, [ScribbleView(camera, scribble, keep)]) once per twin
            evaluation.select = lambda m, k, views, *a, **kw: by_scribble[id(views[0].scribble)]
        result = evaluate_edits(model, category, cases, strategies=("hybrid",), paper=False)
        rows[label] = result["tables"]
    lines = [
        f"Model `{args.model}`, data `{args.data}`, {len(cases)} twins; hybrid strategy, default options.", "",
        "| selection | colour gap closed | colour outside | colour sel. IoU | removal gap closed | removal outside | removal sel. IoU |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, tables in rows.items():
        c = next(r for r in tables["color"] if r["method"] == "hybrid")
        r = next(r for r in tables["remove"] if r["method"] == "hybrid")
        lines.append(
            f"| {label} | {c['gap_closed']:.3f} | {c['psnr_outside']:.2f} dB | {c['selection_iou']:.3f} "
            f"| {r['gap_closed']:.3f} | {r['psnr_outside']:.2f} dB | {r['selection_iou']:.3f} |"
        )
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
