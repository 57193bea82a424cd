"""Measure crfedit on whatever device there is (CUDA if available, else the CPU) and write the
"GPU" section of docs/benchmarks.md (issue 15).

    python benchmarks/gpu.py --data runs/chairs                      # 1-minute curves at 1024 and 8192 rays
    python benchmarks/gpu.py --data runs/chairs --rays 1024,8192,65536 --minutes 0.5 --compile
    python benchmarks/gpu.py --tiny --md /tmp/g.md --json /tmp/g.json  # seconds: a smoke test

What it measures, on one device, stamped with its name, torch and CUDA versions, date and the
command:

* **host cost of a training step** (:mod:`crfedit.opcount`): aten ops, host reads, ``nonzero``,
  and on CUDA kernel launches and synchronizations, per step between read-outs and per
  read-out cycle (``--compile`` adds the compiled step);
* **speed against error**: held-out PSNR against training seconds of the fast preset, one curve
  per ``--rays`` setting (checkpoints of one run each, as :func:`crfedit.bench.train_curve`);
* with the first curve's model: a ``--res``² view rendered from scratch, re-rendered from cached
  features after a colour edit, and the times of a colour edit and a removal (the dataset's
  first twins, default edit options); medians of ``--repeats``, the device synchronized.

Without ``--data`` it generates the benchmark category (24 procedural chairs at 64², with
twins) into runs/bench/chairs, as benchmarks/run.py does.  On a CPU the section says plainly
that no GPU was measured.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from crfedit.bench import BenchSettings, benchmark_category, train_curve
from crfedit.config import make_config
from crfedit.data.loading import Category
from crfedit.edit import EditOptions
from crfedit.edit.cache import ViewCache
from crfedit.errors import CrfError
from crfedit.evaluation import apply_twin_edit, load_twin_cases
from crfedit.io import atomic_write_text
from crfedit.machine import machine_info
from crfedit.opcount import profile_training
from crfedit.renderer import render_camera
from crfedit.report import update_markdown
from crfedit.runtime import configure_threads, resolve_device
from crfedit.train import READ_EVERY

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- gpu:begin -->", "<!-- gpu:end -->"


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_seconds(fn, device: torch.device, repeats: int) -> float:
    """Median wall time of ``fn()`` after one warm-up call, the device synchronized around each."""
    fn()
    times = []
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def host_costs(category: Category, cfg, device: torch.device, compile_too: bool) -> list[dict]:
    """Profiler counts of training steps, both marches (and the compiled one): between
    read-outs, and over a read-out cycle."""
    variants = [("exact", dict(fixed_shapes=False)), ("fixed", dict(fixed_shapes=True))]
    variants += [("fixed, compiled", dict(fixed_shapes=True, compile=True))] if compile_too else []
    rows = []
    for name, options in variants:
        first = 2 * READ_EVERY  # past the first steps (buffer sizing, compilation)
        for window, count in (("between read-outs", READ_EVERY - 1), ("read-out cycle", READ_EVERY)):
            counts = profile_training(category, cfg, device, first, count, **options)
            rows.append({"march": name, "window": window, **counts.as_dict()})
            print(f"host cost ({name}, {window}): {counts}", file=sys.stderr)
    return rows


def view_and_edit_times(model, category: Category, device: torch.device, res: int, repeats: int) -> dict:
    """Render, cached re-render, colour-edit and removal times (seconds) with ``model``."""
    cases = load_twin_cases(model, category)
    color = next((c for c in cases if c.spec.kind == "color"), None)
    removal = next((c for c in cases if c.spec.kind == "remove"), None)
    out: dict = {}
    k = color.instance if color is not None else 0
    camera = (color.views[0].camera if color is not None else category.instances[0].splits["test"][0].camera).resized(res)
    with torch.no_grad():
        out["render_s"] = median_seconds(lambda: render_camera(model.field_for(k), camera, k), device, repeats)
    if color is not None:
        out["color_edit_s"] = median_seconds(lambda: apply_twin_edit(model, color, EditOptions()), device, repeats)
        edited = apply_twin_edit(model, color, EditOptions()).model
        with torch.no_grad():
            cache = ViewCache(model.field_for(k), camera, k)
            out["cached_rerender_s"] = median_seconds(lambda: cache.render(edited.field_for(k)), device, repeats)
    if removal is not None:
        out["removal_s"] = median_seconds(lambda: apply_twin_edit(model, removal, EditOptions()), device, repeats)
    return out


def measure(category: Category, device: torch.device, args) -> dict:
    load_before = os.getloadavg()[0]
    base = make_config("fast", sets=list(args.set), device_type=device.type)
    costs = host_costs(category, dataclasses.replace(base, rays=args.profile_rays), device, args.compile)
    settings = BenchSettings(minutes=args.minutes, steps=args.steps, checkpoints=args.checkpoints, seed=args.seed)
    curves, first_model = [], None
    with tempfile.TemporaryDirectory(prefix="crfedit-gpu-") as tmp:
        for rays in args.rays:
            label = f"{rays} rays"
            rows, model = train_curve(category, dataclasses.replace(base, rays=rays), label, settings, device, Path(tmp),
                                      lambda m: print(m, file=sys.stderr))
            curves += [dataclasses.asdict(r) for r in rows]
            first_model = first_model or model
    times = view_and_edit_times(first_model, category, device, args.res, args.repeats)
    info = machine_info(device)
    info["cuda"] = torch.version.cuda or "none"
    info["command"] = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    info["load"] = f"{load_before:.2f} at the start, {os.getloadavg()[0]:.2f} at the end (1-minute load average)"
    resolution = category.instances[0].splits["train"][0].camera.width
    data = f"{category.root} ({len(category.instances)} instances, {resolution} px)"
    return {"machine": info, "data": data, "settings": vars(args) | {"md": str(args.md), "json": str(args.json)},
            "host_costs": costs, "curves": curves, "times": times}


def fmt(x) -> str:
    return "–" if x is None else f"{x:.1f}" if isinstance(x, float) else str(x)


def section(result: dict) -> str:
    """The markdown section (markers included) for ``result`` of :func:`measure`."""
    m, t = result["machine"], result["times"]
    gpu = m["device"].startswith("cuda")
    lines = [BEGIN, "## GPU", ""]
    if not gpu:
        lines += ["**No GPU was measured.** This run found no CUDA device, so everything below was measured on the "
                  "CPU: the host-overhead counts of a training step, and the CPU's own curve and times. (A CPU's "
                  "host reads cost nothing; `.tolist()` read-outs are no aten op there, so they do not show.)", ""]
    lines += [
        f"Measured {m['date']} on {m['device']} (CPU {m['cpu']}, {m['cores']} cores, torch threads: {m['threads']}), "
        f"torch {m['torch']}, CUDA {m['cuda']}, crfedit revision `{m['revision']}`. Data: `{result['data']}`."
        + (f" Load: {m['load']}." if "load" in m else ""),
        "", f"Command: `{m['command']}`", "",
        f"### Host cost of a training step ({result['settings']['profile_rays']} rays, torch.profiler)", "",
        "| march | window | aten ops | top-level ops | host reads | `item` | `nonzero` | kernel launches | synchronizations |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["host_costs"]:
        lines.append(f"| {r['march']} | {r['window']} ({r['steps']} steps) | {fmt(r['aten_ops'])} | "
                     f"{fmt(r['top_level_ops'])} | {fmt(r['host_reads'])} | {fmt(r['item'])} | {fmt(r['nonzero'])} | "
                     f"{fmt(r['kernel_launches'])} | {fmt(r['synchronizations'])} |")
    lines += ["", "### Held-out PSNR against training time (fast preset)", "",
              "| curve | step | seconds | PSNR (dB) | SSIM |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {r['curve']} | {r['value']} | {r['seconds']:.3g} | {r['psnr']:.2f} | {r['ssim']:.3f} |" for r in result["curves"]]
    res = result["settings"]["res"]
    ms = lambda key: f"{1000 * t[key]:.2f} ms" if key in t else "not measured (no twin)"
    lines += ["", f"### Views and edits (the first curve's model; medians of {result['settings']['repeats']})", "",
              "| measurement | time |", "|---|---:|",
              f"| {res}×{res} view from scratch | {ms('render_s')} |",
              f"| the same view re-rendered from cached features after a colour edit | {ms('cached_rerender_s')} |",
              f"| colour edit (default options) | {ms('color_edit_s')} |",
              f"| removal (default options) | {ms('removal_s')} |", END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="category with twins (default: runs/bench/chairs, generated if missing)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--rays", default="1024,8192", help="rays per step of each training curve, comma-separated")
    parser.add_argument("--minutes", type=float, default=1.0, help="training time per curve")
    parser.add_argument("--steps", type=int, help="step cap per curve (default: the time alone)")
    parser.add_argument("--checkpoints", type=int, default=4, help="points scored along each curve, the last at its end")
    parser.add_argument("--profile-rays", type=int, default=1024, help="rays per step of the profiled steps")
    parser.add_argument("--compile", action="store_true", help="also count the compiled step")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every run")
    parser.add_argument("--res", type=int, default=128, help="rendered view size")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: crfedit's, as the CLI picks them)")
    parser.add_argument("--md", type=Path, default=ROOT / "docs" / "benchmarks.md")
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "benchmarks" / "gpu.json")
    parser.add_argument("--tiny", action="store_true", help="seconds: the 2-chair 16-pixel category, 24-step curves")
    args = parser.parse_args(argv)
    try:
        args.rays = [int(r) for r in args.rays.split(",") if r.strip()]
        if not args.rays or min(args.rays) < 1 or args.res < 8 or args.repeats < 1 or args.minutes <= 0:
            raise CrfError("--rays needs positive counts, --res at least 8, --repeats at least 1, --minutes > 0")
        if args.tiny:
            args.steps, args.checkpoints, args.repeats = args.steps or 24, 2, min(args.repeats, 2)
            args.set += ["occ_res=16", "grid_res=16"]
        configure_threads(args.threads)
        device = resolve_device(args.device)
        with tempfile.TemporaryDirectory(prefix="crfedit-gpu-data-") as tmp:
            category = benchmark_category(args.data, args.tiny, tmp, ROOT / "runs" / "bench" / "chairs")
            result = measure(category, device, args)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.json, json.dumps(result, indent=1, default=str) + "\n")
        update_markdown(args.md, section(result), BEGIN, END)
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.md} and {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
