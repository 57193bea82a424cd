"""Devices, seeding and threads: the only place that decides where tensors live."""

from __future__ import annotations

import random

import numpy as np
import torch

from .errors import CrfError


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` → cuda when available, else cpu; asking for cuda without one is a user error.
    A ``torch.device`` (a rank's, from :func:`crfedit.distributed.rank_device`) passes through."""
    if isinstance(name, torch.device):
        return name
    name = getattr(name, "value", name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise CrfError("--device cuda: no CUDA device is available (use --device cpu or auto)")
    if name not in ("cpu", "cuda"):
        raise CrfError(f"--device {name}: expected auto, cpu or cuda")
    return torch.device(name)


def configure_threads(n: int | None = None) -> int:
    """Set torch's CPU threads to ``n``, by default :func:`crfedit.threads.requested_threads`
    (``CRFEDIT_THREADS``, else the cores nothing else is using).  Results depend on the thread
    count in the last float bits."""
    from .threads import requested_threads

    n = requested_threads() if n is None else n
    torch.set_num_threads(n)
    return n


def seed_everything(seed: int) -> torch.Generator:
    """Seed Python, NumPy and torch; return a CPU generator for explicit sampling."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)
