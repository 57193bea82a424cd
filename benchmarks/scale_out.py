"""Scale-out on one box: threads against processes, DDP against one flat all-reduce, and what
eight gloo ranks spend communicating.

    python benchmarks/scale_out.py                   # every measurement, about 6 minutes
    python benchmarks/scale_out.py --only threads,procs --seconds 30   # re-measure two runs

Runs on the procedural chair category ``runs/scale/chairs`` (8 chairs × 20 views at 64×64,
generated once), fast preset, rays = 1024 per step in total.  Each measurement is one short
training run (``--seconds``) or a fixed number of steps, in fresh processes joined by gloo on
127.0.0.1; results go to ``docs/benchmarks/scale_out.json`` and a markdown table to stdout.

- ``one``, ``threads``: 1 process × 1 and × 2 torch threads — rays/s;
- ``procs``: 2 processes × 1 thread (``train(ranks=...)``) — rays/s summed over ranks, and the
  time per step spent in the gradient all-reduce (waiting for the slower rank included);
- ``sync``: 2 processes, the same training step with the gradients averaged by
  ``DistributedDataParallel`` and by :meth:`crfedit.distributed.Ranks.average` — ms per step;
- ``eight``: 8 processes × 1 thread — step time against all-reduce time per step, and the bare
  all-reduce of the gradient buffer after a barrier;
- ``memory1``, ``memory2``: peak resident memory of each rank (1 and 2 ranks) over a 3-step
  training run; meant for a large category (``--data``), not part of the default set.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import socket
import sys
import tempfile
import time
from pathlib import Path

import torch

from crfedit.config import make_config
from crfedit.data.loading import load_category, training_rays
from crfedit.data.synth import SynthConfig, write_synth_category
from crfedit.evaluation import held_out_split, score_model
from crfedit.distributed import Ranks, process_group
from crfedit.field import ConditionalRadianceField
from crfedit.renderer import render_rays
from crfedit.train import BatchSampler, make_optimizer, scene_box, train, visual_hulls

ROOT = Path(__file__).resolve().parent.parent
CPU = torch.device("cpu")


@dataclasses.dataclass(frozen=True)
class TimedRanks(Ranks):
    """:class:`Ranks` that records the seconds each gradient all-reduce takes."""

    sync_seconds: list = dataclasses.field(default_factory=list, compare=False, hash=False)

    def average(self, params, scalars=()):
        t0 = time.perf_counter()
        out = super().average(params, scalars)
        self.sync_seconds.append(time.perf_counter() - t0)
        return out


def _train_run(category, ranks: TimedRanks, seconds: float, work: Path) -> dict:
    cfg = make_config("fast", overrides=dict(steps=100000, checkpoint_every=100000))
    model, result = train(category, cfg, work / "model.safetensors", CPU, seed=0, minutes=seconds / 60, ranks=ranks)
    sync = ranks.sync_seconds[5:]
    heldout = score_model(model, category, held_out_split(category), ranks=ranks)["psnr"]
    return {
        "heldout_psnr": heldout,
        "steps": result.steps, "seconds": result.seconds, "rays_per_s": cfg.rays * result.steps / result.seconds,
        "ms_per_step": 1e3 * result.seconds / result.steps,
        "sync_ms_per_step": 1e3 * sum(sync) / len(sync) if sync else 0.0,
    }


def _bare_all_reduce(n_floats: int, repeats: int = 20) -> float:
    """ms per all-reduce of ``n_floats`` float32, every rank starting together (after a barrier)."""
    buf = torch.zeros(n_floats)
    total = 0.0
    for _ in range(repeats):
        torch.distributed.barrier()
        t0 = time.perf_counter()
        torch.distributed.all_reduce(buf)
        total += time.perf_counter() - t0
    return 1e3 * total / repeats


def _step_loop(category, ranks: Ranks, mode: str, steps: int, warmup: int = 5) -> float:
    """ms per training step (fast preset, visual-hull grids) with gradients averaged by ``mode``:
    ``ddp`` (DistributedDataParallel) or ``flat`` (Ranks.average)."""
    cfg = make_config("fast")
    aabb = scene_box(category)
    torch.manual_seed(0)
    field = ConditionalRadianceField(cfg, len(category.instances), aabb)
    field.occupancy.copy_(visual_hulls(category, aabb, cfg.occ_res))
    sampler = BatchSampler(training_rays(category, "train", ranks.shard(range(len(category.instances)))), CPU)
    opt = make_optimizer(field, cfg)
    params = [p for g in opt.param_groups for p in g["params"]]
    gen = torch.Generator().manual_seed(ranks.rank)

    class StepLoss(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.field = field

        def forward(self, batch):
            out = render_rays(self.field, batch.rays, batch.instance, generator=gen, early_stop=cfg.train_early_stop, jitter=batch.jitter)
            return torch.mean((out.rgb - batch.rgb) ** 2)

    step_loss = StepLoss()
    if mode == "ddp":
        step_loss = torch.nn.parallel.DistributedDataParallel(step_loss, broadcast_buffers=False)
    t0 = 0.0
    for i in range(warmup + steps):
        if i == warmup:
            torch.distributed.barrier()
            t0 = time.perf_counter()
        loss = step_loss(sampler(ranks.share(cfg.rays), gen))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if mode == "flat":
            ranks.average(params)
        opt.step()
    return 1e3 * (time.perf_counter() - t0) / steps


def _worker(rank: int, world: int, port: int, task: str, data: str, seconds: float, steps: int, threads: int, out: str) -> None:
    torch.set_num_threads(threads)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    category = load_category(Path(data))
    ranks = TimedRanks(rank, world, rank)
    with process_group(ranks, CPU, timeout_s=600), tempfile.TemporaryDirectory() as tmp:
        if task.startswith("memory"):
            import resource

            cfg = make_config("fast", overrides=dict(steps=3, checkpoint_every=100000))
            t0 = time.perf_counter()
            train(category, cfg, Path(tmp) / "model.safetensors", CPU, seed=0, ranks=ranks)
            result = {"seconds": time.perf_counter() - t0, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "instances": len(category.instances), "own_train_rays": len(training_rays(category, "train", ranks.shard(range(len(category.instances)))).rgb)}
        elif task == "sync":
            order = ("flat", "ddp", "flat", "ddp")  # alternated, so a change of machine load shows
            result = {"order": order, "ms_per_step": [_step_loop(category, ranks, mode, steps) for mode in order]}
        else:
            result = _train_run(category, ranks, seconds, Path(tmp))
            if world > 1:
                n = sum(p.numel() for p in ConditionalRadianceField(make_config("fast"), len(category.instances)).parameters())
                result.update(bare_all_reduce_ms=_bare_all_reduce(n), gradient_floats=n)
    Path(out, f"{task}.rank{rank}.json").write_text(json.dumps(result))


def _launch(task: str, world: int, threads: int, args, out: Path) -> list[dict]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ctx = multiprocessing.get_context("spawn")
    load = os.getloadavg()[0]
    procs = [ctx.Process(target=_worker, args=(r, world, port, task, str(args.data), args.seconds, args.steps, threads, str(out)))
             for r in range(world)]
    for p in procs:
        p.start()
    for p in procs:
        p.join()
    if any(p.exitcode != 0 for p in procs):
        raise SystemExit(f"{task}: a rank failed (exit codes {[p.exitcode for p in procs]})")
    results = [json.loads((out / f"{task}.rank{r}.json").read_text()) for r in range(world)]
    results[0]["load_before"] = load
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    default_data = ROOT / "runs" / "scale" / "chairs"
    parser.add_argument("--data", type=Path, default=default_data, help="category to train on (default: 8 procedural chairs, made once into runs/scale/chairs)")
    parser.add_argument("--seconds", type=float, default=60.0, help="training time of each run")
    parser.add_argument("--steps", type=int, default=40, help="timed steps per mode of the sync comparison")
    parser.add_argument("--only", default="one,threads,procs,sync,eight", help="runs to make, comma-separated (of one, threads, "
                        "procs, sync, eight, memory1, memory2)")
    parser.add_argument("--json", type=Path, default=ROOT / "docs" / "benchmarks" / "scale_out.json", help="results file (runs not made keep theirs)")
    args = parser.parse_args(argv)
    plan = {"one": (1, 1), "threads": (1, 2), "procs": (2, 1), "sync": (2, 1), "eight": (8, 1), "memory1": (1, 1), "memory2": (2, 1)}
    unknown = [t for t in args.only.split(",") if t not in plan]
    if unknown:
        print(f"error: --only {args.only}: {unknown[0]!r} is not a run (one of {', '.join(plan)})", file=sys.stderr)
        return 2
    if not (args.data / "instances.txt").is_file():
        if args.data != default_data:  # a typo'd --data made a dataset where it pointed, then trained on it
            print(f"error: --data {args.data}: no category there (instances.txt); leave --data out for the default one", file=sys.stderr)
            return 2
        write_synth_category(args.data, SynthConfig(instances=8, views=20, res=64, seed=0, twins=False))
    report = json.loads(args.json.read_text()) if args.json.is_file() else {}  # --only updates its runs
    with tempfile.TemporaryDirectory() as tmp:
        for task in args.only.split(","):
            world, threads = plan[task]
            report[task] = {"world": world, "threads": threads, "ranks": _launch(task, world, threads, args, Path(tmp))}
            print(task, json.dumps(report[task]), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2))
    print(markdown(report))
    return 0


def markdown(report: dict) -> str:
    rows = ["| run | ranks × threads | load before | seconds | steps | rays/s (all ranks) | ms/step | all-reduce ms/step | bare all-reduce ms | held-out PSNR |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for task in ("one", "threads", "procs", "eight"):
        if task in report:
            r = report[task]["ranks"][0]
            psnr = f"{r['heldout_psnr']:.2f} dB" if "heldout_psnr" in r else "–"
            rows.append(
                f"| {task} | {report[task]['world']} × {report[task]['threads']} | {r['load_before']:.1f} | {r['seconds']:.0f} | {r['steps']} | "
                f"{r['rays_per_s']:.0f} | {r['ms_per_step']:.1f} | {r['sync_ms_per_step']:.1f} | "
                f"{r.get('bare_all_reduce_ms', 0.0):.1f} | {psnr} |"
            )
    if "sync" in report:
        s = report["sync"]["ranks"][0]
        runs = ", ".join(f"{mode} {ms:.1f}" for mode, ms in zip(s["order"], s["ms_per_step"]))
        rows.append(f"\nsync (2 × 1, ms per training step on rank 0, in run order): {runs}")
    return "\n".join(rows)


if __name__ == "__main__":
    sys.exit(main())
