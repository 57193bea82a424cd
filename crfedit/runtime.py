"""Devices, seeding and threads: the only place that decides where tensors live."""

from __future__ import annotations

import random

import numpy as np
import torch

from .errors import CrfError


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` → cuda when available, else cpu; asking for cuda without one is a user error."""
    name = getattr(name, "value", name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise CrfError("--device cuda: no CUDA device is available (use --device cpu or auto)")
    if name not in ("cpu", "cuda"):
        raise CrfError(f"--device {name}: expected auto, cpu or cuda")
    return torch.device(name)


def configure_threads() -> int:
    """Set torch's CPU threads: ``CRFEDIT_THREADS`` if set, else 1.

    crfedit's networks are narrow (64 wide).  On an idle 2-core machine two threads are faster
    (training 30 against 38 ms per step, a 128² render about 1.5×), but when anything else
    runs a second OpenMP thread spin-waits and made renders 13× slower (4.9 s against 0.37 s,
    measured).  One thread is the safe default; ``CRFEDIT_THREADS=2`` (or more) on an idle
    machine.  Results depend on the thread count in the last float bits.
    """
    import os

    value = os.environ.get("CRFEDIT_THREADS", "1")
    try:
        n = int(value)
        if n < 1:
            raise ValueError
    except ValueError:
        raise CrfError(f"CRFEDIT_THREADS={value!r}: expected a positive integer") from None
    torch.set_num_threads(n)
    return n


def seed_everything(seed: int) -> torch.Generator:
    """Seed Python, NumPy and torch; return a CPU generator for explicit sampling."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)
