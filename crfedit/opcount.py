"""What a training step costs the host, counted by ``torch.profiler`` (issue 15).

Per step: the aten ops the host dispatches (all events, and the top-level ones that Python
called), host reads of a tensor value (``aten::item`` / ``aten::_local_scalar_dense``: a
synchronization on a GPU), ``aten::nonzero`` (a read of its output size), and on CUDA the kernel
launches and stream/device synchronizations of the CUDA runtime.  The steps are real
:func:`crfedit.train.train` steps: the profiler starts in ``on_step`` after step ``first`` and
stops after step ``first + count``, so a window can be placed between read-outs.
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import torch

from .config import Config
from .data.loading import Category

HOST_READS = ("aten::_local_scalar_dense",)
"""Every ``.item()``, ``float(t)``, ``bool(t)`` reads through this op (``aten::item`` wraps it)."""
KERNEL_READS = ("aten::_fused_adam_",)
"""Ops whose CPU kernel reads its own CPU tensors (fused Adam its step counts): the same op on a
GPU reads nothing back, so these reads are counted apart (``kernel_reads``), not as host reads."""
LAUNCHES = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")
SYNCS = ("cudaStreamSynchronize", "cudaDeviceSynchronize")


@dataclass(frozen=True)
class StepCounts:
    """Events per training step (means over ``steps`` steps); the CUDA counts are None on a CPU."""

    steps: int
    aten_ops: float  # every aten:: event, nested ones included
    top_level_ops: float  # aten:: events with no aten:: event above them: what Python dispatched
    host_reads: float  # aten::_local_scalar_dense, outside KERNEL_READS
    item: float  # aten::item (the .item() calls among the host reads)
    kernel_reads: float  # aten::_local_scalar_dense inside a KERNEL_READS op (a CPU kernel's own)
    nonzero: float  # aten::nonzero
    kernel_launches: float | None = None
    synchronizations: float | None = None

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def count_events(events: Iterable, steps: int, cuda: bool = False) -> StepCounts:
    """Per-step :class:`StepCounts` of profiler ``events`` (``prof.events()``) recorded over ``steps`` steps."""
    events = list(events)
    aten = [e for e in events if e.name.startswith("aten::")]

    def under(e, names: tuple[str, ...] | None) -> bool:
        """``e`` is called from an aten op (``names`` None) or from one of ``names``."""
        parent = e.cpu_parent
        while parent is not None:
            if parent.name in names if names else parent.name.startswith("aten::"):
                return True
            parent = parent.cpu_parent
        return False

    def per_step(names: tuple[str, ...], inside: bool | None = None) -> float:
        hits = [e for e in events if e.name in names and (inside is None or under(e, KERNEL_READS) == inside)]
        return len(hits) / steps

    # The profiler flushes the device when it stops: a synchronization issued by no op, after
    # the window's last aten op, is its own and not the steps' (a step's reads sync inside ops).
    last_op = max((e.time_range.end for e in aten), default=float("-inf"))
    own = lambda e: e.cpu_parent is None and e.time_range.start >= last_op
    syncs = sum(1 for e in events if e.name in SYNCS and not own(e)) / steps

    return StepCounts(
        steps=steps,
        aten_ops=len(aten) / steps,
        top_level_ops=sum(1 for e in aten if not under(e, None)) / steps,
        host_reads=per_step(HOST_READS, inside=False),
        item=per_step(("aten::item",), inside=False),
        kernel_reads=per_step(HOST_READS, inside=True),
        nonzero=per_step(("aten::nonzero",)),
        kernel_launches=per_step(LAUNCHES) if cuda else None,
        synchronizations=syncs if cuda else None,
    )


def profile_training(
    category: Category, cfg: Config, device: torch.device, first: int, count: int, seed: int = 0, **train_options
) -> StepCounts:
    """Train ``first + count`` steps of ``cfg`` from scratch and count steps ``first+1 …
    first+count`` (``train_options`` go to :func:`crfedit.train.train`, e.g. ``read_every``).

    With ``read_every`` = R and ``first`` a multiple of R, ``count`` = R − 1 covers only steps
    that read nothing back; ``count`` = R adds the one read-out step of the cycle.
    """
    from .train import train

    device = torch.device(device)
    cuda = device.type == "cuda"
    activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
    prof = torch.profiler.profile(activities=activities)
    cfg = dataclasses.replace(cfg, steps=first + count, checkpoint_every=10**9)

    def on_step(step: int, *_):
        # no torch.cuda.synchronize() before stopping: it would be counted as the steps' own
        # (the counts are host events; the profiler waits for the device's records itself)
        if step == first:
            prof.start()
        elif step == first + count:
            prof.stop()

    with tempfile.TemporaryDirectory(prefix="crfedit-opcount-") as tmp:
        if first == 0:
            prof.start()
        train(category, cfg, Path(tmp) / "m.safetensors", device, seed=seed, on_step=on_step, **train_options)
    return count_events(prof.events(), count, cuda)
