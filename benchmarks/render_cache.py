"""Seconds per rendered view: from scratch, and re-rendered from cached features after a colour edit.

    python benchmarks/render_cache.py MODEL DATA                 # 128×128, 1 and 2 threads
    python benchmarks/render_cache.py MODEL DATA --res 256 --threads 2 --md /tmp/b.md

The first colour twin of DATA is edited (hybrid strategy, default options).  For each of the
source chair's test poses, rendered at --res:

* ``scratch``: ``render_camera`` of the unedited model (the full march: occupancy grid, early
  termination, the whole field);
* ``uncached``: ``render_camera`` of the edited model, which is what ``crfedit render --edit``
  does;
* ``cache build``: :class:`crfedit.edit.cache.ViewCache` of the unedited model (once per view,
  e.g. when an editor first shows it);
* ``cached``: ``ViewCache.render`` of the edited model: F_rad alone on the cached samples.

Times are medians over --repeats renders of each view after a warm-up.  The table goes
between ``<!-- cache:begin -->`` and ``<!-- cache:end -->`` of --md, stamped with the machine.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from crfedit.data.loading import load_category
from crfedit.edit import EditOptions
from crfedit.edit.cache import ViewCache
from crfedit.errors import CrfError
from crfedit.evaluation import apply_twin_edit, load_twin_cases
from crfedit.machine import machine_info
from crfedit.model import load_model
from crfedit.renderer import render_camera
from crfedit.report import update_markdown

BEGIN, END = "<!-- cache:begin -->", "<!-- cache:end -->"


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def measure(model_path: Path, data: Path, res: int, threads: list[int], repeats: int) -> tuple[list[dict], dict]:
    model, _ = load_model(model_path)
    category = load_category(data)
    case = next((c for c in load_twin_cases(model, category) if c.spec.kind == "color"), None)
    if case is None:
        raise CrfError(f"{data} has no colour twin to edit")
    k = case.instance
    edited = apply_twin_edit(model, case, EditOptions()).model
    cameras = [v.camera.resized(res) for v in case.views]
    rows = []
    for n in threads:
        torch.set_num_threads(n)
        for i, cam in enumerate(cameras):
            with torch.no_grad():
                scratch = median_ms(lambda cam=cam: render_camera(model.field_for(k), cam, k), repeats)
                uncached_out = render_camera(edited.field_for(k), cam, k)
                uncached = median_ms(lambda cam=cam: render_camera(edited.field_for(k), cam, k), repeats)
                t0 = time.perf_counter()
                cache = ViewCache(model.field_for(k), cam, k)
                build = 1000.0 * (time.perf_counter() - t0)
                cached = median_ms(lambda cache=cache: cache.render(edited.field_for(k)), repeats)
                diff = float((cache.render(edited.field_for(k)) - uncached_out.rgb).abs().max())
            rows.append({
                "threads": n, "view": i, "scratch_ms": scratch, "uncached_ms": uncached, "build_ms": build,
                "cached_ms": cached, "max_diff": diff, "samples_per_ray": uncached_out.n_samples / (res * res),
                "cached_samples": cache.n_cached,
            })
            print(f"threads {n} view {i}: scratch {scratch:.1f} ms, uncached {uncached:.1f} ms, cached {cached:.2f} ms "
                  f"(build {build:.0f} ms), max |diff| {diff:.1e}", file=sys.stderr)
    meta = {"model": str(model_path), "data": str(data), "twin": case.spec.name, "res": res, "repeats": repeats,
            "threads": ",".join(str(n) for n in threads)}
    return rows, meta


def markdown(rows: list[dict], meta: dict, machine: dict) -> str:
    res = meta["res"]
    lines = [
        BEGIN,
        f"Measured by `python benchmarks/render_cache.py {meta['model']} {meta['data']} --res {res} --threads {meta['threads']} "
        f"--repeats {meta['repeats']}` on "
        f"{machine['cpu']} ({machine['cores']} cores), torch {machine['torch']}, {machine['date']}, revision "
        f"{machine['revision']}. Colour twin `{meta['twin']}` edited with the default options; its "
        f"{len({r['view'] for r in rows})} test poses rendered at {res}×{res}; medians of {meta['repeats']} renders.",
        "",
        "| torch threads | from scratch (unedited) | after the edit, uncached | after the edit, cached | cache build (once per view) | max abs difference | samples per ray |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for n in sorted({r["threads"] for r in rows}):
        rs = [r for r in rows if r["threads"] == n]
        med = lambda key, rs=rs: statistics.median(r[key] for r in rs)
        lines.append(
            f"| {n} | {med('scratch_ms'):.1f} ms | {med('uncached_ms'):.1f} ms | **{med('cached_ms'):.2f} ms** | "
            f"{med('build_ms'):.0f} ms | {max(r['max_diff'] for r in rs):.1e} | {med('samples_per_ray'):.2f} |"
        )
    lines.append(END)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("data", type=Path)
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--threads", default="1,2", help="torch thread counts to measure, comma-separated")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--md", type=Path, default=None, help="markdown page to update between the cache markers "
                        "(default: print the table; the repository's page only when named: --md docs/benchmarks.md)")
    args = parser.parse_args(argv)
    try:
        threads = [int(t) for t in args.threads.split(",") if t.strip()]
        if not threads or min(threads) < 1 or args.res < 8 or args.repeats < 1:
            raise CrfError("--threads needs positive counts, --res at least 8, --repeats at least 1")
        rows, meta = measure(args.model, args.data, args.res, threads, args.repeats)
        table = markdown(rows, meta, machine_info())
        if args.md is None:
            print(table)
            return 0
        update_markdown(args.md, table, BEGIN, END)
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
