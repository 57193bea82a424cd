"""Run crfedit's speed-against-error benchmark and update the docs.

    python benchmarks/run.py                  # the full sweep: about 25 minutes on 2 CPU cores
    python benchmarks/run.py --minutes 2      # shorter training curves
    python benchmarks/run.py --tiny           # seconds: a smoke test of the pipeline (writes runs/bench/tiny/)

Measures with :func:`crfedit.bench.run_bench` (the library behind ``crfedit bench``) and writes
``docs/benchmarks/bench.csv``, ``docs/benchmarks/bench_{train,render,edit}.png`` and the bench
section of ``docs/benchmarks.md``.  Without ``--data`` it runs on the procedural chair category
(24 chairs × 50 views at 64×64 with ground-truth twins), generated once into
``runs/bench/chairs``.  See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import torch

from crfedit.bench import TINY_LABEL, BenchSettings, benchmark_category, run_bench
from crfedit.report import write_outputs
from crfedit.errors import CrfError
from crfedit.io import check_folder_target, probe_folder
from crfedit.runtime import resolve_device

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="category dataset with twins (default: runs/bench/chairs, generated if missing)")
    parser.add_argument("--minutes", type=float, help="training time per curve (default 5)")
    parser.add_argument("--presets", help="training curves, comma-separated (default fast,paper)")
    parser.add_argument("--csv", type=Path, help="CSV to write, plots beside it (default docs/benchmarks/bench.csv; "
                        "with --tiny runs/bench/tiny/bench.csv: a smoke test does not replace the published tables)")
    parser.add_argument("--md", type=Path, help="markdown page with the bench section (default docs/benchmarks.md; "
                        "with --tiny runs/bench/tiny/bench.md)")
    parser.add_argument("--work", type=Path, help="keep the trained models here")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tiny", action="store_true", help="a seconds-long sweep on a generated 2-chair category")
    args = parser.parse_args(argv)
    out = ROOT / "runs" / "bench" / "tiny" if args.tiny else ROOT / "docs"
    args.csv = args.csv or out / ("bench.csv" if args.tiny else "benchmarks/bench.csv")
    args.md = args.md or out / ("bench.md" if args.tiny else "benchmarks.md")
    if args.tiny:
        args.csv.parent.mkdir(parents=True, exist_ok=True)

    if args.threads is not None and args.threads < 1:
        print(f"error: --threads {args.threads}: must be at least 1", file=sys.stderr)
        return 2
    if not 0 <= args.seed <= 2**63 - 1:  # as crfedit bench's --seed
        print(f"error: --seed {args.seed}: a seed from 0 to 2^63 - 1", file=sys.stderr)
        return 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    settings = BenchSettings.tiny() if args.tiny else BenchSettings()
    changes = {"minutes": args.minutes, "seed": args.seed}
    if args.presets:
        changes["presets"] = tuple(p.strip() for p in args.presets.split(",") if p.strip())
    settings = dataclasses.replace(settings, **{k: v for k, v in changes.items() if v is not None})
    try:
        settings = settings.validated()
        for option, path in (("--csv", args.csv), ("--md", args.md)):  # before the sweep, not after its minutes
            check_folder_target(path.parent, option)
            existing = next(p for p in (path.parent, *path.parents) if p.exists())
            probe_folder(existing, f"{option} {path}")
        device = resolve_device(args.device)
        with tempfile.TemporaryDirectory(prefix="crfedit-bench-data-") as tmp:
            category = benchmark_category(args.data, args.tiny, tmp, ROOT / "runs" / "bench" / "chairs",
                                          lambda m: print(m, file=sys.stderr))
            report = run_bench(category, settings, device, workdir=args.work, progress=lambda m: print(m, file=sys.stderr),
                               data_label=TINY_LABEL if args.tiny and args.data is None else None)
            written = write_outputs(report, args.csv, args.md)
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
