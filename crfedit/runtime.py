"""Devices, seeding and threads: the only place that decides where tensors live."""

from __future__ import annotations

import random

import numpy as np
import torch

from .errors import CrfError


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` → cuda when available, else cpu; asking for cuda without one is a user error.
    A ``torch.device`` (a rank's, from :func:`crfedit.distributed.rank_device`) passes through;
    a script may also name one GPU, ``cuda:1``."""
    if isinstance(name, torch.device):
        return name
    name = getattr(name, "value", name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu:0":  # the one CPU device torch numbers
        name = "cpu"
    index = name[len("cuda:"):] if isinstance(name, str) and name.startswith("cuda:") else None
    if name not in ("cpu", "cuda") and not (index is not None and index.isascii() and index.isdigit()):
        raise CrfError(f"--device {name}: expected auto, cpu or cuda")
    if name != "cpu" and not torch.cuda.is_available():
        raise CrfError(f"--device {name}: no CUDA device is available (use --device cpu or auto)")
    if index is not None and int(index) >= torch.cuda.device_count():
        raise CrfError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA devices")
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


def full_precision(fn):
    """Run ``fn`` with ``torch.autocast`` off (CPU, and CUDA where there is one): an edit or a
    selection computes in the float32 of the model's weights, and under a caller's bf16
    autocast an edit met mixed dtypes in ``index_put`` (a raw RuntimeError).  Rendering alone
    runs under autocast (docs/robustness.md)."""
    import contextlib
    import functools

    @functools.wraps(fn)
    def run(*args, **kwargs):
        with contextlib.ExitStack() as stack:
            stack.enter_context(torch.autocast("cpu", enabled=False))
            if torch.cuda.is_available():
                stack.enter_context(torch.autocast("cuda", enabled=False))
            return fn(*args, **kwargs)

    return run
