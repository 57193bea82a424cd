"""Scale-out on ``torch.distributed``: one process per rank, launched by ``torchrun``.

``torchrun`` sets ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK``; :func:`ranks_from_env` reads them
and :func:`process_group` joins the group (gloo on CPU, nccl on CUDA, device ``cuda:LOCAL_RANK``
for ``--device auto``).  Everything else here is the few collectives crfedit needs, each of
which turns a lost peer (a rank that died, a collective past ``CRFEDIT_DIST_TIMEOUT`` seconds)
into one :class:`DistributedError` line instead of a traceback:

- :meth:`Ranks.average` — one all-reduce of a flat buffer holding every gradient (the code
  tables' too) plus a few scalars, so all ranks step with the same averaged gradient and agree on
  the loss and the clock;
- :meth:`Ranks.same_on_all` — a checksum all-reduce that proves (or, from rank 0, restores)
  that a tensor is identical on every rank;
- :meth:`Ranks.gather` / :meth:`Ranks.barrier` — summaries to rank 0, and the wait while rank 0
  writes a file.

A single process is ``Ranks(0, 1, 0)`` (:data:`SINGLE`): every method is then a no-op, so
library code calls them unconditionally.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from typing import Iterator, Sequence

import numpy as np
import torch
from torch import Tensor

from .errors import CrfError

DEFAULT_TIMEOUT_S = 300.0
MAX_TIMEOUT_S = 7 * 24 * 3600.0


class DistributedError(CrfError):
    """Another rank died or a collective timed out; the job stops, the last checkpoint stays.
    ``echoed``: rank 0 prints the same line, so the other ranks keep quiet (one line, not one
    per rank)."""

    def __init__(self, message: str, echoed: bool = False):
        super().__init__(message)
        self.echoed = echoed


@dataclass(frozen=True)
class Ranks:
    """This process's place in the job: global ``rank`` of ``world``, ``local_rank`` on its node."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the one that prints and writes the shared files."""
        return self.rank == 0

    def share(self, total: int) -> int:
        """This rank's part of ``total`` items split as evenly as possible (the first
        ``total % world`` ranks take one more)."""
        return total // self.world + (1 if self.rank < total % self.world else 0)

    def shard(self, items: Sequence) -> list:
        """Every ``world``-th item starting at ``rank`` (round robin, so long and short items mix)."""
        return list(items[self.rank :: self.world])

    # ------------------------------------------------------------------------- collectives

    def average(self, params: Sequence[torch.nn.Parameter], scalars: Sequence[float] = ()) -> list[float]:
        """Replace each parameter's gradient by its mean over ranks, in one all-reduce; return the
        means of ``scalars``.

        A parameter no rank computed a gradient for keeps ``grad = None`` (Adam skips it, as in a
        single process); one that only some ranks touched counts zeros for the others.
        """
        if self.world == 1:
            return list(scalars)
        device = params[0].device
        has = [p.grad is not None for p in params]
        parts = [p.grad.reshape(-1) if p.grad is not None else torch.zeros(p.numel(), device=device) for p in params]
        extra = torch.tensor([float(h) for h in has] + [float(s) for s in scalars], device=device, dtype=torch.float32)
        flat = torch.cat(parts + [extra])
        with _collective(self, "averaging gradients"):
            torch.distributed.all_reduce(flat)
        flat /= self.world
        flags = flat[flat.numel() - extra.numel() :].tolist()
        offset = 0
        for i, p in enumerate(params):
            p.grad = flat[offset : offset + p.numel()].view_as(p) if flags[i] > 0 else None
            offset += p.numel()
        return flags[len(params) :]

    def same_on_all(self, tensors: Sequence[Tensor], what: str) -> bool:
        """True when every tensor is identical on all ranks (checksums compared by a MIN and a MAX
        all-reduce); otherwise rank 0's tensors are broadcast into the others' and False is
        returned.  Every rank gets the same answer."""
        if self.world == 1:
            return True
        sums = torch.stack([_checksum(t) for t in tensors])
        lo, hi = sums.clone(), sums.clone()
        with _collective(self, f"checking {what}"):
            torch.distributed.all_reduce(lo, op=torch.distributed.ReduceOp.MIN)
            torch.distributed.all_reduce(hi, op=torch.distributed.ReduceOp.MAX)
            if bool((lo == hi).all()):
                return True
            for t in tensors:
                buf = t.to(torch.uint8) if t.dtype == torch.bool else t.contiguous()
                torch.distributed.broadcast(buf, src=0)
                t.copy_(buf)
        return False

    def broadcast_(self, tensors: Sequence[Tensor], what: str) -> None:
        """Overwrite ``tensors`` with rank 0's, in place."""
        if self.world == 1:
            return
        with _collective(self, what), torch.no_grad():
            for t in tensors:
                buf = t.to(torch.uint8) if t.dtype == torch.bool else t.detach().contiguous()
                torch.distributed.broadcast(buf, src=0)
                t.copy_(buf)

    def gather(self, obj, what: str) -> list:
        """Every rank's ``obj`` (JSON-like), in rank order, on every rank."""
        if self.world == 1:
            return [obj]
        out: list = [None] * self.world
        with _collective(self, what):
            torch.distributed.all_gather_object(out, obj)
        return out

    def agree(self, settings: dict, what: str) -> None:
        """Refuse, on every rank, to go on when this rank's ``settings`` (JSON-like values by
        name) differ from rank 0's: ranks started with other arguments (a learning rate, a
        seed, a width, a step count, another dataset) trained silently to a worse model, or
        stalled in a collective until the timeout and blamed a lost rank."""
        if self.world == 1:
            return
        every = self.gather(settings, what)
        for rank, theirs in enumerate(every[1:], start=1):
            differ = [name for name in every[0] if theirs.get(name) != every[0][name]]
            if differ:
                said = "; ".join(f"{name} {_clipped(str(theirs.get(name)), 60)} (rank 0: {_clipped(str(every[0][name]), 60)})" for name in differ[:3])
                raise DistributedError(f"rank {rank} of {self.world} was started with other settings than rank 0: {said}; "
                                       "start every rank with the same arguments and data", echoed=not self.main)

    def barrier(self, what: str) -> None:
        if self.world == 1:
            return
        with _collective(self, what):
            torch.distributed.barrier()


SINGLE = Ranks()


def _checksum(t: Tensor) -> Tensor:
    """Two float64 numbers that differ between two tensors in all but contrived cases: the sum,
    and a sum weighted by position."""
    flat = t.detach().reshape(-1).double()
    weights = torch.arange(1, flat.numel() + 1, device=flat.device, dtype=torch.float64).remainder_(1009.0)
    return torch.stack([flat.sum(), (flat * weights).sum()])


_BROKEN = False
_JOINED = False


def joined() -> bool:
    """Whether this process has joined a process group (:func:`process_group`), even one torn
    down since: an error raised inside the group reaches the command line after the group's
    clean-up, and is this rank's own (its share of the work), not every rank's."""
    return _JOINED


def broken() -> bool:
    """Whether a collective of this process has failed (another rank died or timed out).

    The process group is then left as it is: gloo reports a dead peer from its own threads, and
    tearing down its connections afterwards can abort the process (``terminate called after
    throwing gloo::IoException``, SIGABRT) before the one-line error reaches the user.  The
    command line exits with ``os._exit`` after printing it (:func:`crfedit.cli.main`)."""
    return _BROKEN


@contextmanager
def _collective(ranks: Ranks, what: str) -> Iterator[None]:
    global _BROKEN
    try:
        yield
    except RuntimeError as e:  # torch's DistBackendError and gloo/nccl errors are RuntimeErrors
        _BROKEN = True
        first = _clipped(str(e).strip().splitlines()[0]) if str(e).strip() else e.__class__.__name__
        raise DistributedError(
            f"rank {ranks.rank} of {ranks.world}: {what} failed, another rank stopped or the collective "
            f"timed out ({first}); the job stops"
        ) from None


def _clipped(text: str, limit: int = 160) -> str:
    """``text`` cut to about ``limit`` characters at a word boundary, "…" marking the cut."""
    if len(text) <= limit:
        return text
    cut = text[:limit].rsplit(" ", 1)[0].rstrip(" ,;:")
    return f"{cut}…"


# ----------------------------------------------------------------------------- launching


def ranks_from_env(environ: dict[str, str] | None = None) -> Ranks | None:
    """The :class:`Ranks` torchrun describes in ``RANK``/``WORLD_SIZE``/``LOCAL_RANK``; None
    when they are not set (a plain single-process run)."""
    env = os.environ if environ is None else environ
    if "WORLD_SIZE" not in env and "RANK" not in env:
        return None
    try:
        world, rank = int(env.get("WORLD_SIZE", "")), int(env.get("RANK", ""))
        local = int(env.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise CrfError("RANK, WORLD_SIZE and LOCAL_RANK must be integers (set by torchrun)") from None
    if not (world >= 1 and 0 <= rank < world and local >= 0):
        raise CrfError(f"RANK={rank} WORLD_SIZE={world}: expected 0 <= RANK < WORLD_SIZE")
    return Ranks(rank, world, local)


def rank_device(choice: str, ranks: Ranks) -> torch.device:
    """``auto`` → ``cuda:LOCAL_RANK`` when CUDA is available, else cpu; ``cuda`` → ``cuda:LOCAL_RANK``."""
    choice = getattr(choice, "value", choice)
    if choice == "cpu" or (choice == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if choice not in ("auto", "cuda"):
        raise CrfError(f"--device {choice}: expected auto, cpu or cuda")
    if not torch.cuda.is_available():
        raise CrfError("--device cuda: no CUDA device is available (use --device cpu or auto)")
    if ranks.local_rank >= torch.cuda.device_count():
        raise DistributedError(f"rank {ranks.rank} of {ranks.world}: LOCAL_RANK {ranks.local_rank}, but this node has only {torch.cuda.device_count()} CUDA devices")
    return torch.device("cuda", ranks.local_rank)


def collective_timeout() -> float:
    """Seconds a collective may wait for the other ranks: ``CRFEDIT_DIST_TIMEOUT``, default 300."""
    value = os.environ.get("CRFEDIT_DIST_TIMEOUT", str(DEFAULT_TIMEOUT_S))
    try:
        seconds = float(value)
        if not 0 < seconds <= MAX_TIMEOUT_S:  # False for NaN; inf and years overflow the backends' clocks
            raise ValueError
    except ValueError:
        raise CrfError(f"CRFEDIT_DIST_TIMEOUT={value!r}: expected a number of seconds above 0 and at most "
                       f"{MAX_TIMEOUT_S:.0f} (a week)") from None
    return seconds


@contextmanager
def process_group(ranks: Ranks, device: torch.device, timeout_s: float | None = None) -> Iterator[Ranks]:
    """Join the job's process group for the duration (gloo on CPU, nccl on CUDA); a world of
    one joins nothing."""
    import torch.distributed as dist

    if ranks.world == 1:
        yield ranks
        return
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    timeout = timedelta(seconds=collective_timeout() if timeout_s is None else timeout_s)
    global _JOINED
    try:
        dist.init_process_group(backend, rank=ranks.rank, world_size=ranks.world, timeout=timeout)
    except (RuntimeError, ValueError) as e:
        raise DistributedError(f"rank {ranks.rank}: cannot join the process group ({_clipped(str(e).strip())})") from None
    _JOINED = True
    try:
        yield ranks
    finally:
        if not _BROKEN:  # see broken(): a group with a dead peer is not torn down
            dist.destroy_process_group()


def rank_seed(seed: int, rank: int, step: int = 0) -> int:
    """A 63-bit seed for ``(seed, rank, step)``: independent streams per rank (NumPy SeedSequence)."""
    return int(np.random.SeedSequence([seed, rank, step]).generate_state(1, np.uint64)[0]) >> 1
