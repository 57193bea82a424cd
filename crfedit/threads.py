"""How many CPU threads torch should use, decided without importing torch.

The default follows the machine: the cores this process may run on (``os.sched_getaffinity``,
capped by a cgroup CPU quota when one is set) minus the cores other processes keep busy (the
1-minute load average), at least one.  On a shared, busy machine that is one thread (a
second OpenMP thread spin-waits there: a render ran 13× slower), on an idle machine every
usable core (on 16 cores training ran at 30.9k rays/s against 14.9k with one thread, issue 18).
``CRFEDIT_THREADS=N`` overrides it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from .errors import CrfError


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity, capped by a cgroup v2 quota (cpu.max)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cores = os.cpu_count() or 1
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            cores = min(cores, max(1, math.floor(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(1, cores)


def busy_cores() -> float:
    """Runnable processes over the last minute (the load average); 0 where it is unknown."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return 0.0


def default_threads(cores: int | None = None, load: float | None = None) -> int:
    """``cores − round(load)``, between 1 and ``cores``: the cores that nothing else is using.

    ``default_threads(2, 0.1) == 2`` (idle 2-core box), ``default_threads(2, 1.4) == 1``,
    ``default_threads(16, 3.2) == 13``.
    """
    cores = usable_cores() if cores is None else cores
    load = busy_cores() if load is None else load
    return max(1, min(cores, cores - int(math.floor(load + 0.5))))


def requested_threads() -> int:
    """``CRFEDIT_THREADS`` when set, else ``OMP_NUM_THREADS`` when set, else :func:`default_threads`.

    Either must be a positive integer, else a :class:`CrfError`; of ``OMP_NUM_THREADS``'s
    per-level list (``"4,2"``) the first entry counts, the threads torch's pool gets.
    """
    for name in ("CRFEDIT_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(name)
        if value is None or not value.strip():
            continue
        try:
            n = int(value.split(",")[0] if name == "OMP_NUM_THREADS" else value)
            if n < 1:
                raise ValueError
        except ValueError:
            raise CrfError(f"{name}={value!r}: expected a positive integer") from None
        return n
    return default_threads()
