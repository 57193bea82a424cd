"""The Adam step that training, the edits and fit-real share: a NaN/inf loss stops before it
can reach any parameter, and a run that produced non-finite weights is refused, so a diverged
run never overwrites a good model file or writes an edit."""

from __future__ import annotations

import math
from typing import Callable, Iterable

import torch
from torch import Tensor

from .errors import NonFiniteError


def adam_step(
    opt: torch.optim.Optimizer, loss: Tensor, what: str, step: int, consequence: str,
    before_step: Callable[[], None] | None = None,
) -> float:
    """One optimizer step on ``loss``; returns its value.  A non-finite loss raises
    :class:`NonFiniteError` (``"{what} diverged at step {step} …; {consequence}"``) before the
    gradients are computed, so the parameters stay as they were.  ``before_step`` runs between
    the backward pass and the step (training averages the gradients over ranks there)."""
    value = float(loss.detach())
    if not math.isfinite(value):
        raise NonFiniteError(f"{what} diverged at step {step} (loss is {value}); {consequence}")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if before_step is not None:
        before_step()
    opt.step()
    return value


def check_finite(params: Iterable[Tensor], what: str, consequence: str) -> None:
    """Raise :class:`NonFiniteError` if any of ``params`` holds NaN or inf."""
    for p in params:
        if not bool(torch.isfinite(p).all()):
            raise NonFiniteError(f"{what} produced NaN or inf weights; {consequence}")


def run_adam(
    opt: torch.optim.Optimizer, loss_fn: Callable[[], Tensor], steps: int, what: str,
    on_step: Callable[[int, float], None] | None = None, consequence: str = "nothing was written",
) -> float:
    """``steps`` steps of ``opt`` on ``loss_fn()``, then a check that every parameter it
    trains is finite; returns the last loss.  ``on_step(step, loss)`` after each step (1-based)."""
    value = float("nan")
    for step in range(steps):
        value = adam_step(opt, loss_fn(), what, step, consequence)
        if on_step is not None:
            on_step(step + 1, value)
    check_finite((p for g in opt.param_groups for p in g["params"]), what, consequence)
    return value
