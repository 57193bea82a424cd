"""Benchmark ``fit-real``: fit chairs the model never saw from one view, score the other views.

For every held-out instance of a dataset (instances the model was not trained on), one view is
the "photo" (its RGBA image, the alpha marking the object) and the new instance is fitted from
it three ways:

* ``mean code`` — no optimization: the training instances' mean codes (the starting point);
* ``codes only`` — stage 1 alone (``--steps-codes`` steps, weights frozen);
* ``codes + weights`` — stage 1, then stage 2 (``--steps-joint`` steps on codes and the
  ``--weights`` copy of the network).

Each fit is scored by PSNR and SSIM against the ground truth at every *other* view of that
instance (all splits, at most ``--max-views``), and timed (after a 1+1-step warm-up fit).  The
pose of the photo is its true camera (``--pose exact``) or, as a user would pick it, the
training view whose camera direction is closest (``--pose nearest``).  Prints a markdown table
and writes the numbers as JSON.

    python benchmarks/fit_real.py --model runs/chairs.safetensors --data runs/chairs --holdout chair_020,chair_021
    python benchmarks/fit_real.py          # no --model/--data: a tiny synthetic set-up, a smoke run

The model file must come from a dataset whose held-out instances are in ``--data`` but not in
the model (e.g. ``crfedit dataset synth`` with N chairs, then training on a subset).
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from crfedit.cameras import Camera
from crfedit.data.loading import Category, InstanceData, instance_names, load_category, load_instance_dir
from crfedit.fit_real import JOINT, STARTS, FitOptions, fit_real, prepare_photo
from crfedit.errors import CrfError
from crfedit.io import write_json
from crfedit.metrics import score_images
from crfedit.model import CategoryModel, load_model
from crfedit.renderer import render_camera
from crfedit.runtime import resolve_device

DEFAULT_JSON = Path(__file__).resolve().parent.parent / "runs" / "bench" / "fit_real.json"
"""Under the repository's git-ignored runs/ (it wrote benchmarks/results/, which git showed as new)."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", type=Path, help="Trained model file (.safetensors). Without --model/--data: a tiny synthetic set-up.")
    p.add_argument("--data", type=Path, help="Dataset folder that holds the held-out instances.")
    p.add_argument("--holdout", default="all", help="Comma-separated instance names, or 'all': every instance of --data not in the model.")
    p.add_argument("--max-instances", type=int, default=None, help="Fit at most this many held-out instances.")
    p.add_argument("--view", default="train:0", help="Which view of each held-out instance is the photo (SPLIT:INDEX).")
    p.add_argument("--pose", choices=("exact", "nearest"), default="exact", help="The photo's true camera, or the nearest training view's.")
    p.add_argument("--max-views", type=int, default=None, help="Score at most this many other views per instance.")
    p.add_argument("--steps-codes", type=int, default=FitOptions.steps_codes)
    p.add_argument("--steps-joint", type=int, default=FitOptions.steps_joint)
    p.add_argument("--weights", choices=tuple(JOINT), default=FitOptions.weights)
    p.add_argument("--distortion", type=float, default=FitOptions.distortion, help="Weight of fit-real's distortion loss (0: off).")
    p.add_argument("--start", default=FitOptions.start, choices=STARTS, help="Where the fits start (fit-real --start).")
    p.add_argument("--grids", type=int, default=FitOptions.grids, help="With --start nearest: the best-matching grids united.")
    p.add_argument("--rays", type=int, default=FitOptions.rays)
    p.add_argument("--lr-codes", type=float, default=FitOptions.lr_codes)
    p.add_argument("--lr-weights", type=float, default=FitOptions.lr_weights)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice).")
    p.add_argument("--json", type=Path, default=DEFAULT_JSON, help=f"Where to write the numbers (default {DEFAULT_JSON}).")
    return p.parse_args(argv)


def tiny_setup(folder: Path) -> tuple[Path, Path, list[str]]:
    """4 procedural chairs × 8 views at 24×24; a model trained on the first 3 for 300 steps."""
    from crfedit.config import make_config
    from crfedit.data.synth import SynthConfig, write_synth_category
    from crfedit.train import train

    write_synth_category(folder / "chairs", SynthConfig(instances=4, views=8, res=24, seed=0, twins=False))
    category = load_category(folder / "chairs")
    cfg = make_config("fast", overrides=dict(
        steps=300, rays=256, lr=2e-2, lr_codes=2e-2, grid_res=16, occ_res=16, occ_warmup=50, checkpoint_every=10**9,
    ))
    train(Category(category.root, category.instances[:3], category.fingerprint), cfg, folder / "model.safetensors", torch.device("cpu"))
    return folder / "model.safetensors", folder / "chairs", [category.names[3]]


def held_out_names(model: CategoryModel, data: Path, holdout: str) -> list[str]:
    names = instance_names(data)
    if holdout == "all":
        chosen = [n for n in names if n not in model.names]
        if not chosen:
            raise CrfError(f"{data}: every instance is in the model; train on a subset to hold some out")
        return chosen
    chosen = [n.strip() for n in holdout.split(",") if n.strip()]
    for n in chosen:
        if n not in names:
            raise CrfError(f"--holdout {n}: not an instance of {data}")
        if n in model.names:
            raise CrfError(f"--holdout {n}: the model was trained on it, so it is not held out")
    return chosen


def nearest_training_camera(model: CategoryModel, camera: Camera) -> Camera:
    """The stored training view whose camera direction (from the origin) is closest to ``camera``'s."""
    table = model.views.get("train")
    if table is None:
        raise CrfError("--pose nearest: the model stores no training cameras")
    centers = table.c2w[:, :3, 3]
    target = torch.as_tensor(camera.center, dtype=torch.float64)
    cos = (centers @ target) / (centers.norm(dim=-1) * target.norm())
    i = int(cos.argmax())
    return Camera(table.c2w[i].numpy().copy(), float(table.focal[i]), table.width, table.height).resized(camera.width, camera.height)


def split_view(instance: InstanceData, spec: str):
    split, _, index = spec.partition(":")
    views = instance.splits.get(split, [])
    if not index.isdigit() or int(index) >= len(views):
        raise CrfError(f"--view {spec}: {instance.name} has {len(views)} {split} views")
    return views[int(index)]


def score(model: CategoryModel, k: int, views) -> dict:
    field = model.field_for(k)
    preds = [render_camera(field, v.camera, k).rgb.clamp(0, 1).cpu().numpy() for v in views]
    s = score_images(preds, [v.rgb for v in views])
    return {"psnr": s["psnr"], "ssim": s["ssim"], "views": s["n"]}


def fit_configs(args: argparse.Namespace) -> dict[str, FitOptions]:
    """The three fits the table compares, each :meth:`FitOptions.validated`."""
    configs = {
        "start": FitOptions(steps_codes=0, steps_joint=0, start=args.start, grids=args.grids),
        "codes only": FitOptions(steps_codes=args.steps_codes, steps_joint=0, rays=args.rays, distortion=args.distortion, seed=args.seed,
                                 start=args.start, grids=args.grids, lr_codes=args.lr_codes),
        "codes + weights": FitOptions(
            steps_codes=args.steps_codes, steps_joint=args.steps_joint, weights=args.weights, rays=args.rays,
            distortion=args.distortion, seed=args.seed, start=args.start, grids=args.grids,
            lr_codes=args.lr_codes, lr_weights=args.lr_weights,
        ),
    }
    return {label: options.validated() for label, options in configs.items()}


def run(args: argparse.Namespace) -> dict:
    if (args.model is None) != (args.data is None):
        raise CrfError("give both --model and --data, or neither (a tiny synthetic smoke run)")
    device = resolve_device(args.device)
    configs = fit_configs(args)  # checked before any set-up or loading: a bad option is a second's error
    scratch = None
    if args.model is None:
        scratch = tempfile.TemporaryDirectory(prefix="fit_real_bench_")
        print("no --model/--data: building a tiny synthetic set-up (4 chairs at 24x24, 3 trained, 1 held out)", file=sys.stderr)
        args.model, args.data, names = tiny_setup(Path(scratch.name))
        args.holdout = ",".join(names)
    model, _ = load_model(args.model, device)
    names = held_out_names(model, args.data, args.holdout)[: args.max_instances]
    train = model.views.get("train")
    res = train.width if train is not None else None
    per_instance: dict[str, dict] = {}
    for n, name in enumerate(names):
        instance = load_instance_dir(Path(args.data) / name, name, res)
        view = split_view(instance, args.view)
        others = [v for vs in instance.splits.values() for v in vs if v is not view][: args.max_views]
        if not others:
            raise CrfError(f"{name}: no other view to score")
        camera = view.camera if args.pose == "exact" else nearest_training_camera(model, view.camera)
        rgba = np.concatenate([view.rgb, view.alpha[..., None]], axis=-1)
        photo = prepare_photo(rgba, None, camera.width, camera.height, f"{name} {args.view}")
        if n == 0:  # one-off costs (allocator, kernels) stay out of the timings
            fit_real(model, photo, camera, "warm_up", FitOptions(steps_codes=1, steps_joint=1, rays=args.rays))
        rows = {}
        for label, options in configs.items():
            t0 = time.perf_counter()
            result = fit_real(model, photo, camera, f"fit_{name}", options)
            seconds = time.perf_counter() - t0
            rows[label] = {**score(result.model, result.instance, others), "photo_psnr": result.stages[-1].psnr, "seconds": seconds}
            print(f"[{n + 1}/{len(names)}] {name} {label}: PSNR {rows[label]['psnr']:.2f} dB, {seconds:.1f} s", file=sys.stderr)
        per_instance[name] = rows
    summary = {}
    for label in configs:
        rows = [per_instance[n][label] for n in names]
        summary[label] = {key: float(np.mean([r[key] for r in rows])) for key in ("psnr", "ssim", "photo_psnr", "seconds")}
        summary[label]["views"] = int(sum(r["views"] for r in rows))
    report = {
        "model": str(args.model) if scratch is None else "(tiny synthetic set-up)",
        "data": str(args.data) if scratch is None else "(tiny synthetic set-up)",
        "holdout": names,
        "photo_view": args.view,
        "pose": args.pose,
        "options": {
            "steps_codes": args.steps_codes, "steps_joint": args.steps_joint, "weights": args.weights, "distortion": args.distortion,
            "rays": args.rays, "seed": args.seed, "start": args.start, "grids": args.grids, "lr_codes": args.lr_codes, "lr_weights": args.lr_weights,
        },
        "device": str(device),
        "machine": {
            "python": platform.python_version(), "torch": torch.__version__,
            "cpu": platform.processor() or platform.machine(), "threads": torch.get_num_threads(),
        },
        "summary": summary,
        "instances": per_instance,
    }
    if scratch is not None:
        scratch.cleanup()
    return report


def markdown(report: dict) -> str:
    o = report["options"]
    lines = [
        f"fit-real on {len(report['holdout'])} held-out instance(s), photo = {report['photo_view']}, pose = {report['pose']}, "
        f"{o['steps_codes']} code steps + {o['steps_joint']} joint steps ({o['weights']}), distortion {o['distortion']:g}, {report['device']}",
        "",
        "| fit | PSNR other views (dB) | SSIM other views | PSNR photo (dB) | seconds |",
        "|---|---:|---:|---:|---:|",
    ]
    for label, s in report["summary"].items():
        lines.append(f"| {label} | {s['psnr']:.2f} | {s['ssim']:.3f} | {s['photo_psnr']:.2f} | {s['seconds']:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.threads is not None and args.threads < 1:  # it ran with one thread, saying nothing
        print(f"error: --threads {args.threads}: must be at least 1", file=sys.stderr)
        return 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    try:
        report = run(args)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, report)
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(markdown(report))
    print(f"\nwrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
