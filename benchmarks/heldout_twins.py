"""The edits on twins the selection's rules were never tuned on: the benchmark's category again,
with a ground-truth twin for every chair that has a part for one (``--twin-sources 24``), scored
by ``crfedit eval edits`` and summarized here in two groups, the benchmark's own twins and the
others (held out).

    crfedit dataset synth runs/heldout/proc --twin-sources 24       # runs/chairs8's chairs, 40 twins
    crfedit dataset from-meshes runs/heldout/real64 runs/real-chairs/meshes/*/*.obj --up y \\
        --views 50 --res 64 --twin-sources 24                       # runs/real-chairs/chairs64's, 33 twins
    crfedit eval edits MODEL runs/heldout/proc --strategies hybrid --no-nerf-baseline --json > scores.json
    python benchmarks/heldout_twins.py --bench runs/chairs8 scores.json [scores.json ...] [--pool] [--out FILE.md]
    python benchmarks/heldout_twins.py --bench runs/chairs8 --folds 2 runs/heldout/proc   # part_labels per fold

The generators draw the same chairs, views and scribbles whatever the count (a twin's scribble is
seeded by its chair), and the default count's twin sources are always among a larger count's,
so the benchmark's twins come out to the byte and the models trained on the benchmark's
dataset evaluate on the larger one.  ``--bench`` names the benchmark's dataset: its twins are
the first group, every other twin of a scores file is held out.

What held out means here: the rules (`crfedit.edit.selection.options`) were chosen on the
benchmark's twins alone.  The part head is another matter: a model trained with the default
``part_labels=not-twins`` learned the part maps of every chair but the benchmark's twin
sources, so on a held-out twin's chair it has seen the part's labels.  That is a user's own
labelled category, not the benchmark's unlabelled case; the first group stays the measure of
the latter.  A model trained with ``--set part_labels=not:twins,NAME,…`` hides the named
chairs' maps too.  Its file records whose maps the head learned, and ``eval edits`` reports
them (``part_labels_seen``); the table then splits the held-out twins by it (the six
benchmark models predate the record).  ``--folds K HELDOUT`` prints, for K models, the
``part_labels`` that hide the benchmark's sources and every K-th of the held-out dataset's
other sources (sorted), so that each held-out twin is edited by a model whose head never saw
its chair's maps and by K − 1 that did; ``--pool`` adds the groups' means over all the files.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from crfedit.data.loading import read_twin_specs
from crfedit.evaluation import below_unedited
from crfedit.report import emit_table
from crfedit.errors import CrfError, run_script
from edit_models import hybrid_rows


def summarize(runs: list[dict], names: set[str], kind: str) -> dict | None:
    """The hybrid edits of ``kind`` among the twins ``names``: their count, mean gap closed,
    mean PSNR outside the part against unedited, mean selection IoU and how many end below
    their unedited PSNR (None: no such twin)."""
    before = {r["twin"]: r for r in runs if r["method"] == "unedited"}
    rows = [r for r in hybrid_rows(runs, kind) if r["twin"] in names]
    if not rows:
        return None
    ious = [r["selection_iou"] for r in rows if r.get("selection_iou") is not None]
    return {
        "n": len(rows),
        "gap": sum(r["gap_closed"] for r in rows) / len(rows),
        "outside": sum(r["psnr_outside"] - before[r["twin"]]["psnr_outside"] for r in rows) / len(rows),
        "iou": sum(ious) / len(ious) if ious else math.nan,
        "below": below_unedited(rows),
    }


def fold_labels(bench: Path, heldout: Path, folds: int) -> list[str]:
    """``part_labels`` for each of ``folds`` models: the benchmark's twin sources and every
    ``folds``-th other twin source of ``heldout`` (sorted names) hidden from the part head."""
    own = {spec.source for spec in read_twin_specs(bench)}
    others = sorted({spec.source for spec in read_twin_specs(heldout)} - own)
    return ["not:" + ",".join(["twins", *others[i::folds]]) for i in range(folds)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scores", nargs="+", type=Path, help="`crfedit eval edits --json` outputs on the larger dataset "
                    "(with --folds: that dataset)")
    ap.add_argument("--bench", type=Path, required=True, help="the benchmark's dataset (its twins are the first group)")
    ap.add_argument("--folds", type=int, help="print the part_labels of this many fold models and stop")
    ap.add_argument("--pool", action="store_true", help="also each group's mean over all the scores files")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if args.folds:
        for i, labels in enumerate(fold_labels(args.bench, args.scores[0], args.folds)):
            print(f"fold {i}: --set part_labels={labels}")
        return
    bench = {spec.name for spec in read_twin_specs(args.bench)}
    lines = [
        f"Twins of `{args.bench}` (the benchmark) and the others (held out); hybrid edits, mean over the twins;",
        "outside: PSNR on the pixels the twin leaves unchanged, against unedited.", "",
        "| scores | twins | kind | n | gap closed | outside (dB) | selection IoU | below unedited |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    pooled: dict[tuple[str, str], list[dict | None]] = {}  # (group, kind): each file's summary
    for path in args.scores:
        try:
            report = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise CrfError(f"{path}: not JSON ({e.msg}); give `crfedit eval edits --json` outputs") from None
        if not isinstance(report, dict) or not isinstance(report.get("runs"), list):  # a KeyError traceback named nothing
            raise CrfError(f"{path}: not a `crfedit eval edits --json` output (it has no runs list)")
        runs = report["runs"]
        names = {r["twin"] for r in runs}
        groups = [("benchmark", names & bench), ("held out", names - bench)]
        seen = report.get("part_labels_seen")  # the sources whose part maps the head learned, where the model file says
        if seen is not None:
            of_seen = {r["twin"] for r in runs if r["source"] in seen}
            groups += [("held out, head saw the labels", (names - bench) & of_seen), ("held out, labels hidden", names - bench - of_seen)]
        for group, members in groups:
            for kind in ("color", "remove"):
                s = summarize(runs, members, kind)
                pooled.setdefault((group, kind), []).append(s)
                if s is not None:
                    lines.append(row(f"`{path.name}`", group, kind, s))
    if args.pool:
        for (group, kind), summaries in pooled.items():
            s = pool(summaries)
            if s is not None:
                lines.append(row(f"all {len(args.scores)}", group, kind, s))
    emit_table(lines, args.out)


def row(name: str, group: str, kind: str, s: dict) -> str:
    return f"| {name} | {group} | {kind} | {s['n']} | {s['gap']:.3f} | {s['outside']:+.2f} | {s['iou']:.3f} | {s['below']} |"


def pool(summaries: list[dict | None]) -> dict | None:
    """The twins' means over several :func:`summarize` results (each weighted by its count)."""
    got = [s for s in summaries if s is not None]
    if not got:
        return None
    n = sum(s["n"] for s in got)
    mean = lambda key: sum(s[key] * s["n"] for s in got) / n
    return {"n": n, "gap": mean("gap"), "outside": mean("outside"), "iou": mean("iou"), "below": sum(s["below"] for s in got)}


if __name__ == "__main__":
    run_script(main)
