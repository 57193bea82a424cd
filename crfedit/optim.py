"""The Adam step that training, the edits and fit-real share, and the non-finite guard: a run
that produced a NaN/inf loss or non-finite weights is refused, so a diverged run never
overwrites a good model file or writes an edit.

The guard costs no host read per step: each step's loss goes into a buffer on the device
(:class:`StepLog`), read in one transfer every few steps; the first non-finite loss in it
raises :class:`NonFiniteError` naming its step.  Callers read it before anything is written.
"""

from __future__ import annotations

import math
from typing import Callable, Iterable

import torch
from torch import Tensor

from .errors import NonFiniteError


class StepLog:
    """Per-step scalars (``columns`` of them, the loss first) kept on the device and read back
    in one transfer (:meth:`read`): a GPU step then never waits for the host."""

    def __init__(self, columns: int, device: torch.device | str, size: int = 16):
        self.rows = torch.zeros(max(1, size), columns, device=device)
        self.steps: list[int] = []

    def record(self, step: int, values: Tensor) -> None:
        """Store step ``step``'s ``values`` [columns] (a device-to-device copy)."""
        if len(self.steps) == self.rows.shape[0]:
            self.rows = torch.cat([self.rows, torch.zeros_like(self.rows)])
        self.rows[len(self.steps)] = values.detach()
        self.steps.append(step)

    def read(self) -> list[tuple[int, list[float]]]:
        """The (step, values) recorded since the last read; one host read (none when empty)."""
        if not self.steps:
            return []
        rows = self.rows[: len(self.steps)].tolist()
        out, self.steps = list(zip(self.steps, rows)), []
        return out


def check_losses(rows: list[tuple[int, list[float]]], what: str, consequence: str) -> None:
    """Raise :class:`NonFiniteError` at the first row of :meth:`StepLog.read` whose loss (the
    first value) is NaN or inf: ``"{what} diverged at step {step} (loss is …); {consequence}"``."""
    for step, values in rows:
        if not math.isfinite(values[0]):
            raise NonFiniteError(f"{what} diverged at step {step} (loss is {values[0]}); {consequence}")


class FusedAdam:
    """Adam (β = 0.9, 0.999; no weight decay) over a list of tensors, or of parameter groups
    (``{"params": [...], "lr": ...}``, each its own learning rate), one fused kernel per step and
    group: the arithmetic of ``torch.optim.Adam(params, lr, eps=eps, fused=True)``, to the bit
    (tested).

    Why not torch.optim: its first use in a process imports ``torch._dynamo`` (its methods are
    wrapped to keep the compiler out), 0.75–0.9 s on this project's CPU, which every
    ``crfedit edit-color`` / ``remove`` / ``add`` / ``fit-real`` process paid inside an edit of
    0.15–0.5 s (a fit of 15–30 s).  Training keeps torch.optim (one import per run of minutes,
    and its state dict for ``--resume``).  Parameters without a gradient after a backward pass
    are skipped, as torch.optim does."""

    def __init__(self, params: Iterable[Tensor] | Iterable[dict], lr: float | None = None, eps: float = 1e-8,
                 betas: tuple[float, float] = (0.9, 0.999)):
        given = list(params)
        if given and isinstance(given[0], dict):
            self.param_groups = [{"params": list(g["params"]), "lr": float(g.get("lr", lr))} for g in given]
        else:
            self.param_groups = [{"params": given, "lr": float(lr)}]
        self.eps, self.betas = float(eps), betas
        self.state: dict[Tensor, tuple[Tensor, Tensor, Tensor]] = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in [q for g in self.param_groups for q in g["params"]]:  # the groups' params, as torch.optim keeps them
            if set_to_none:
                p.grad = None
            elif p.grad is not None:
                p.grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            lists: dict[tuple, list[list[Tensor]]] = {}
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p not in self.state:  # fused Adam keeps its step count as a float32 tensor
                    self.state[p] = (torch.zeros_like(p), torch.zeros_like(p), torch.zeros((), dtype=torch.float32, device=p.device))
                m, v, t = self.state[p]
                for out, x in zip(lists.setdefault((p.device, p.dtype), [[], [], [], [], []]), (p, p.grad, m, v, t)):
                    out.append(x)
            for ps, grads, ms, vs, ts in lists.values():
                torch._foreach_add_(ts, 1)
                torch._fused_adam_(
                    ps, grads, ms, vs, [], ts, amsgrad=False, lr=group["lr"], beta1=self.betas[0], beta2=self.betas[1],
                    weight_decay=0.0, eps=self.eps, maximize=False, grad_scale=None, found_inf=None,
                )


def adam_step(opt: torch.optim.Optimizer | FusedAdam, loss: Tensor, before_step: Callable[[], None] | None = None) -> None:
    """One optimizer step on ``loss``, reading nothing back.  ``before_step`` runs between the
    backward pass and the step (training averages the gradients over ranks there).  A loss that
    no parameter reaches (a batch whose few rays all missed the object) is no step at all; under
    ``before_step`` every rank must step, so there it is an error as before."""
    opt.zero_grad(set_to_none=True)
    if not loss.requires_grad and before_step is None:
        return
    loss.backward()
    if before_step is not None:
        before_step()
    opt.step()


def check_finite(params: Iterable[Tensor], what: str, consequence: str) -> None:
    """Raise :class:`NonFiniteError` if any of ``params`` holds NaN or inf (one host read)."""
    flags = [torch.isfinite(p).all() for p in params]
    if flags and not bool(torch.stack(flags).all()):
        raise NonFiniteError(f"{what} produced NaN or inf weights; {consequence}")


RISE_LIMIT = 1.5
""":func:`run_adam` with ``refuse_rise`` refuses a run whose last tenth of losses average more
than this × its first loss (at least 10 steps).  A fit starts from the weights it changes, so
its first loss is the unedited model's; ending well above it is divergence that stayed finite:
``--lr 1`` (100× the edits' default) took a removal of one leg pixel from 2.59 to 63 and emptied
the chair, a recolour from 0.47 to 1.15 and blackened it, both written without a word.  At the
default the last tenth sits at 0.48 and 0.04 of the first loss (quickstart model)."""


def late_loss(values: list[float]) -> float | None:
    """The mean of the last tenth of ``values`` (one loss per step), where a run ends; None for
    fewer than 10 steps, which are not judged (one step's random rays can cost more than the
    first's).  :func:`check_descent` and an edit's record of how far it moved read it."""
    if len(values) < 10:
        return None
    tail = values[-max(1, len(values) // 10):]
    return sum(tail) / len(tail)


def check_descent(values: list[float], what: str, consequence: str) -> None:
    """Raise :class:`NonFiniteError` when the last tenth of ``values`` (one loss per step)
    averages more than :data:`RISE_LIMIT` × the first (:func:`late_loss`)."""
    late = late_loss(values)
    if late is not None and late > RISE_LIMIT * values[0]:
        raise NonFiniteError(f"{what} diverged: its loss rose from {values[0]:.4g} to {late:.4g} over {len(values)} steps "
                             f"(a learning rate too large, or too few steps for a rise to settle: a lower --lr or more --steps); {consequence}")


def run_adam(
    opt: torch.optim.Optimizer | FusedAdam, loss_fn: Callable[[], Tensor], steps: int, what: str,
    on_step: Callable[[int, float], None] | None = None, consequence: str = "nothing was written",
    before_step: Callable[[], None] | None = None, refuse_rise: bool = False, losses: list[float] | None = None,
) -> float:
    """``steps`` steps of ``opt`` on ``loss_fn()``, then a check that every loss and every
    parameter it trains is finite (and with ``refuse_rise`` that the loss did not end far above
    where it began: :func:`check_descent`); returns the last loss.  ``on_step(step, loss)`` after
    each step (1-based) reads each loss as it comes, and a NaN/inf one stops before its gradient;
    without it the losses are read once, at the end.  ``before_step`` as in :func:`adam_step`;
    ``losses``, when given, is extended with every step's loss (read with the others)."""
    params = [p for g in opt.param_groups for p in g["params"]]
    log = StepLog(1, params[0].device if params else "cpu", size=steps)
    value, seen = float("nan"), []
    for step in range(steps):
        loss = loss_fn()
        if on_step is not None:
            value = float(loss.detach())
            check_losses([(step, [value])], what, consequence)
            seen.append(value)
        else:
            log.record(step, loss.detach().reshape(1))
        adam_step(opt, loss, before_step)
        if on_step is not None:
            on_step(step + 1, value)
    rows = log.read()
    check_losses(rows, what, consequence)
    check_finite(params, what, consequence)
    values = seen or [r[1][0] for r in rows]
    if refuse_rise:
        check_descent(values, what, consequence)
    if losses is not None:
        losses.extend(values)
    return rows[-1][1][0] if rows else value
