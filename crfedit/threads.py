"""How many CPU threads torch should use, decided without importing torch.

The default follows the machine: the cores this process may run on (``os.sched_getaffinity``,
capped by a cgroup CPU quota when one is set) minus the cores other processes keep busy (the
1-minute load average), at least one, shared with the other crfedit processes started in the
last minute, which the load average does not show yet.  On a shared, busy machine that is one
thread (a second OpenMP thread spin-waits there: a render ran 13× slower), on an idle machine
every usable core (on 16 cores training ran at 30.9k rays/s against 14.9k with one thread,
issue 18).  Two trainings started together each took every core before the share: on an idle
16-core GPU host their start-up took 220 s against 15 s alone, on 2 cores the pair took 125–141 s
against 29 s with one thread each (``docs/benchmarks.md``, forty-seventh session).

``CRFEDIT_THREADS=N`` overrides the default, and so does ``OMP_NUM_THREADS`` (torch's own
setting, which ``torchrun`` sets to 1 a rank) when ``CRFEDIT_THREADS`` is not set.
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


RECENT = 60.0
"""Seconds since a crfedit process started during which the load average does not yet show it
(it is the 1-minute average), so :func:`default_threads` counts it as a sibling instead."""


def default_threads(cores: int | None = None, load: float | None = None, siblings: int | None = None) -> int:
    """``(cores − round(load)) // (1 + siblings)``, between 1 and ``cores``: the cores that
    nothing else is using, shared with the ``siblings`` (:func:`recent_siblings`).

    ``default_threads(2, 0.1) == 2`` (idle 2-core box), ``default_threads(2, 1.4) == 1``,
    ``default_threads(16, 3.2) == 13``, ``default_threads(16, 0.0, 1) == 8`` (two started together).
    """
    cores = usable_cores() if cores is None else cores
    load = busy_cores() if load is None else load
    siblings = recent_siblings() if siblings is None else siblings
    free = max(1, min(cores, cores - int(math.floor(load + 0.5))))
    return max(1, free // (1 + max(0, siblings)))


def is_crfedit(argv: list[str]) -> bool:
    """Whether a command line runs crfedit in Python: ``python -m crfedit ...`` or the
    ``crfedit`` console script (``python /path/bin/crfedit ...``); not a wrapper such as
    ``timeout 60 python -m crfedit``, which computes nothing itself."""
    if not argv or not Path(argv[0]).name.startswith("python"):
        return False
    rest = argv[1:]
    while rest and rest[0].startswith("-") and rest[0] not in ("-m", "-c"):
        rest = rest[2:] if rest[0] in ("-X", "-W") else rest[1:]  # interpreter options (-X and -W take a value)
    if len(rest) >= 2 and rest[0] == "-m":
        return rest[1] == "crfedit" or rest[1].startswith("crfedit.")
    return bool(rest) and Path(rest[0]).name == "crfedit"


def recent_siblings(window: float = RECENT, proc: Path = Path("/proc")) -> int:
    """Other crfedit processes (:func:`is_crfedit`) started less than ``window`` seconds ago,
    from Linux's ``/proc`` (0 where it cannot be read); this process and its parent excluded."""
    try:
        uptime = float((proc / "uptime").read_text().split()[0])
        tick = os.sysconf("SC_CLK_TCK")
        entries = [e for e in proc.iterdir() if e.name.isdigit()]
    except (OSError, ValueError, AttributeError, IndexError):
        return 0
    mine = {os.getpid(), os.getppid()}
    count = 0
    for entry in entries:
        if int(entry.name) in mine:
            continue
        try:
            argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
            if not is_crfedit([a for a in argv if a]):
                continue
            stat = (entry / "stat").read_text()
            started = int(stat[stat.rindex(")") + 2 :].split()[19]) / tick  # field 22: start time, in ticks since boot
        except (OSError, ValueError, IndexError):
            continue  # it ended, or is not ours to read
        count += uptime - started < window
    return count


MAX_THREADS = 1024
"""The most CPU threads ``CRFEDIT_THREADS`` / ``OMP_NUM_THREADS`` may ask for: 100 000 made the
OpenMP runtime fail to create them (a segmentation fault, or libgomp's own two lines)."""


def threads_choice() -> tuple[int, str]:
    """(threads, why): ``CRFEDIT_THREADS`` when set, else ``OMP_NUM_THREADS`` when set, else
    :func:`default_threads`, with what decided it in words (``train`` prints it).

    Either variable must be a positive integer, else a :class:`CrfError`; of ``OMP_NUM_THREADS``'s
    per-level list (``"4,2"``) the first entry counts, the threads torch's pool gets.
    """
    for name in ("CRFEDIT_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(name)
        if value is None or not value.strip():
            continue
        try:
            n = int(value.split(",")[0] if name == "OMP_NUM_THREADS" else value)
            if not 1 <= n <= MAX_THREADS:
                raise ValueError
        except ValueError:
            raise CrfError(f"{name}={value!r}: expected a positive integer, at most {MAX_THREADS}") from None
        return n, f"{name}={value.strip()}"
    cores, load, siblings = usable_cores(), busy_cores(), recent_siblings()
    why = f"{cores} usable cores, load average {load:.1f}"
    if siblings:
        why += f", shared with {siblings} other crfedit process{'es' * (siblings > 1)} started in the last minute"
    return default_threads(cores, load, siblings), why + "; crfedit --threads N (or CRFEDIT_THREADS=N) sets it"


def requested_threads() -> int:
    """The threads of :func:`threads_choice`."""
    return threads_choice()[0]
