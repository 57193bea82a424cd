"""The machinery every optimized edit shares: a trainable copy of the field that renders one
instance, the weight penalty against its starting point, the optimization loop, and the
delta that records the result.

Edits are instance-scoped: instance k's edit trains a *copy* of the tensors that render k
(θ₀ = the state it starts from, prior edits included) and the result replaces them for k only
(``CategoryModel.overrides[k]``).  The returned model is the one the delta reproduces
(``before`` + delta, exactly as :func:`~crfedit.delta.apply_edit_files` computes it).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import time
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .. import occupancy
from ..cameras import Camera, Rays, rays_from_camera
from ..delta import RESERVED, Delta, apply_deltas, make_delta, save_delta
from ..errors import CrfError
from ..field import ConditionalRadianceField
from ..model import CategoryModel
from ..names import CODE_TABLES, RECOLOR_RULES, real_number, whole_number
from ..optim import FusedAdam, late_loss, run_adam
from .losses import PENALTIES, add_weight_penalty_grad_, weight_penalty
from .params import STRATEGIES, trained_names, trained_prefixes


MAX_EDIT_RAYS = 1 << 22
"""An edit's ``--rays`` at most (as ``train``'s ``rays``): a billion ran a 256-pixel view out of memory."""
MAX_EDIT_STEPS = 10_000_000
"""An edit's ``--steps`` at most: 10²⁰ passed and failed inside torch (an int64 overflow, with a
page of C++ frames); ten million steps is days of optimization on any machine."""


@dataclass(frozen=True)
class EditOptions:
    """How an edit optimizes.  Defaults follow the paper's editing protocol."""

    strategy: str = "hybrid"
    """hybrid (the paper's: see params.TRAINED) | codes (the instance's code row only) | all."""
    steps: int = 100
    """Adam steps."""
    lr: float = 1e-2
    """Adam learning rate."""
    rays: int = 1024
    """Most rays the edit renders per step (scribbled rays plus rays that keep their colour)."""
    seed: int = 0
    """Seeds the choice of rays and the occupancy probes; the same seed gives the same edit."""
    lambda_reg: float = 10.0
    """Weight of the weight penalty: Σ_numbers (θ − θ₀)² / 4096, or with ``penalty="tensor"``
    Σ_tensors mean((θ − θ₀)²) (:func:`~crfedit.edit.losses.weight_penalty`)."""
    penalty: str = "element"
    """``element`` (every trained number weighed alike, so strategies that train tensors of
    different sizes are penalised alike) or ``tensor`` (per-tensor means, the rule before
    issue 14's fairness change; docs/benchmarks.md compares the two)."""
    recolor: str = RECOLOR_RULES[0]
    """Selection recolour target inside S (:class:`~crfedit.edit.supervised.RecolorTarget`):
    ``shading`` (the new colour × the sample's shading along the scribbled mean; default) or
    ``ratio`` (the sample's colour × new / old, per channel: the rule before, which also scales
    the model's colour noise)."""
    lambda_dens: float = 0.01
    """Weight of the density entropy of scribbled rays (removal)."""
    lambda_surface: float = 0.1
    """Shape edits: weight of the log-density terms that lower what scribbled rays see and hold
    what kept rays see (losses.visible_log_density / log_density_drift)."""
    lambda_match: float = 0.1
    """add --method density: weight of the cross-entropy to the donor's density distribution
    (at 1 its gradient, which never saturates, overrides the colour terms and smears the object)."""
    cache: bool = True
    """Compute what the trained parameters cannot change once (:mod:`.cache`); off, every step
    runs the whole field on the edit's samples (the same result, slower: a benchmark knob)."""
    on_step: Callable[[int, float], None] | None = None
    """Called after each optimization step with (step, loss), 1-based; an exception it raises
    ends the edit before anything is returned or written (``crfedit ui``: progress and cancel).
    A recolour fitted a second time (:data:`~crfedit.edit.supervised.BLEED_LIMIT`) counts that
    fit's steps from 1 again."""

    def validated(self) -> "EditOptions":
        def whole(v) -> bool:  # an int, not a bool or a float that happens to be whole
            return whole_number(v) is not None

        def number(v) -> bool:  # finite, not a bool
            x = real_number(v)
            return x is not None and math.isfinite(x)

        weights = {"lambda_reg": self.lambda_reg, "lambda_dens": self.lambda_dens, "lambda_surface": self.lambda_surface,
                   "lambda_match": self.lambda_match}
        bad_weight = next((k for k, v in weights.items() if not (number(v) and v >= 0)), None)  # NaN passed a min() ≥ 0
        checks = [
            (self.strategy in STRATEGIES, f"--strategy {self.strategy}: expected one of {', '.join(STRATEGIES)}"),
            (whole(self.steps) and 1 <= self.steps <= MAX_EDIT_STEPS, f"--steps {self.steps}: need a whole number from 1 to {MAX_EDIT_STEPS:,}"),
            (number(self.lr) and self.lr > 0, f"--lr {self.lr}: must be a finite positive number"),
            (whole(self.rays) and 2 <= self.rays <= MAX_EDIT_RAYS,
             f"--rays {self.rays}: need a whole number, at least 2 and at most {MAX_EDIT_RAYS} (the most rays a step can hold)"),
            (whole(self.seed) and 0 <= self.seed <= 2**63 - 1, f"--seed {self.seed}: a seed is a whole number from 0 to 2^63 - 1"),
            (bad_weight is None, f"{bad_weight} {weights.get(bad_weight)}: loss weights must be finite numbers ≥ 0"),
            (self.penalty in PENALTIES, f"--penalty {self.penalty}: expected one of {', '.join(PENALTIES)}"),
            (self.recolor in RECOLOR_RULES, f"--recolor {self.recolor}: expected one of {', '.join(RECOLOR_RULES)}"),
        ]
        for ok, message in checks:
            if not ok:
                raise CrfError(message)
        return self


@dataclass
class EditResult:
    """An edit: the edited model and the delta file's contents."""

    model: CategoryModel
    tensors: dict[str, Tensor]
    meta: dict[str, str]
    final_loss: float
    seconds: float
    """The whole edit's wall time: a selection the edit made from its scribbles included, one
    it was given excluded (:func:`since`)."""
    optimize_seconds: float = dataclasses.field(default=0.0, kw_only=True)
    """Of which the optimization steps (:func:`optimize`); 0 for edits without any."""

    def save(self, path, **extra_meta: str) -> None:
        """Write the delta atomically; ``extra_meta`` (``command``, ``view`` …) is provenance
        only and does not change the edit's fingerprint; the keys that make up the edit itself
        (``kind``, ``instance``, ``fingerprint`` …: :data:`~crfedit.delta.RESERVED`; overwritten,
        they wrote a file crfedit then refused to load) and what it measured (:data:`RECORDED`)
        are refused, and so is an empty key."""
        clash = sorted(set(extra_meta) & set(RECORDED))
        if clash:
            raise CrfError(f"save: {', '.join(clash)} {'is' if len(clash) == 1 else 'are'} the edit's own metadata, not provenance; "
                           "give other keys")
        if "" in extra_meta:
            raise CrfError("save: a metadata key is empty")
        save_delta(path, self.tensors, {**self.meta, **{k: str(v) for k, v in extra_meta.items()}})


RECORDED = (*RESERVED, "hyperparameters", "first_loss", "fit_loss", "final_loss", "seconds")
""":meth:`EditResult.save`'s refused provenance keys: the edit's identity and what it measured."""


class InstanceEdit:
    """A trainable copy of the field that renders ``instance``, with θ₀ kept for the penalty.

    Only the parameters under the strategy's prefixes require gradients.
    """

    def __init__(self, model: CategoryModel, instance: int, group: str, strategy: str, penalty: str = "element",
                 extra: tuple[str, ...] = ()):
        self.before, self.instance = model, instance
        field = model.field_for(instance)
        self.field = copy.deepcopy(field) if field is model.field else field
        self.prefixes = trained_prefixes(self.field, group, strategy)
        self.prefixes += tuple(x for x in extra if x not in self.prefixes)  # a recolour that bled (supervised.WIDENED)
        names = set(trained_names(self.field, self.prefixes))
        self.params: dict[str, Tensor] = {}
        for name, p in self.field.named_parameters():
            p.requires_grad_(name in names)
            if name in names:
                self.params[name] = p
        if not self.params:
            raise CrfError(f"--strategy {strategy}: this model has no parameters to train for a {group} edit")
        self.start = {n: p.detach().clone() for n, p in self.params.items()}
        self.rows = {n: instance for n in self.params if n in CODE_TABLES}
        self.per = penalty
        self.optimize_seconds = 0.0  # set by optimize()
        self.first_loss: float | None = None  # the first step's loss, set by optimize()
        self.fit_loss: float | None = None  # the last tenth of the steps' mean loss, without the weight penalty: set by optimize()

    def penalty(self) -> Tensor:
        return weight_penalty(self.params, self.start, self.rows, self.per)

    def add_penalty_grad(self, scale: float) -> None:
        """Add ``scale`` · ∇ :meth:`penalty` to the trained tensors' gradients (closed form)."""
        add_weight_penalty_grad_(self.params, self.start, self.rows, self.per, scale)

    def occupancy_delta(self, grid: Tensor) -> tuple[dict, tuple[str, ...]]:
        """(extra overrides, extra modules) for :func:`finish` that store ``grid`` [R, R, R] as
        the instance's occupancy (nothing without the grid sampler)."""
        if self.field.cfg.sampler != "grid":
            return {}, ()
        table = self.field.occupancy.detach().clone()
        table[self.instance] = grid
        return {"occupancy": table}, ("occupancy",)

    def after(self, extra: Mapping[str, Tensor] | None = None) -> CategoryModel:
        """``before`` with the instance's trained tensors (and ``extra`` state, e.g. a new
        occupancy table) replaced; code tables keep every other row."""
        replaced = dict(self.before.overrides.get(self.instance, {}))
        with torch.no_grad():
            for name, p in self.params.items():
                value = p.detach().clone()
                if name in self.rows:
                    row = value[self.instance].clone()
                    value = self.start[name].clone()
                    value[self.instance] = row
                replaced[name] = value
        replaced.update(extra or {})
        return dataclasses.replace(self.before, overrides={**self.before.overrides, self.instance: replaced})


OCC_PROBES = 4
"""Random density probes per candidate cell when a shape edit re-thresholds the grid."""


@torch.no_grad()
def rethreshold(field: ConditionalRadianceField, instance: int, candidates: Tensor, generator: torch.Generator) -> Tensor:
    """The instance's occupancy grid [R, R, R] after a shape edit: candidate cells whose edited
    density passes the training threshold at any of :data:`OCC_PROBES` random probes, dilated by
    one cell and kept within ``candidates``."""
    cfg = field.cfg
    res = candidates.shape[-1]
    density = functools.partial(field.density, instance=instance)
    ema = torch.zeros(res**3, device=candidates.device)
    step = occupancy.step_size(field.aabb, res, cfg.steps_per_cell)
    grid = candidates.reshape(-1)
    for _ in range(OCC_PROBES):
        grid = occupancy.update_from_density(ema, candidates.reshape(-1), density, step, cfg.occ_threshold, 1.0, generator)
    return occupancy.dilate(grid.view(res, res, res), 1) & candidates


def occupancy_after(
    edit: InstanceEdit, candidates: Tensor, generator: torch.Generator, kept: Tensor | None = None
) -> tuple[dict, tuple[str, ...]]:
    """:meth:`InstanceEdit.occupancy_delta` of the re-thresholded ``candidates`` (grid sampler
    only), plus the cells ``kept`` [R, R, R] holds whatever their probes say: an addition keeps
    every cell the instance had (a few random probes miss a thin surface inside a cell, and an
    addition re-thresholding the whole instance freed 1 364 cells, shaving its outline)."""
    if edit.field.cfg.sampler != "grid":
        return {}, ()
    grid = rethreshold(edit.field, edit.instance, candidates, generator)
    return edit.occupancy_delta(grid if kept is None else grid | kept)

def optimize(edit: InstanceEdit, loss_fn: Callable[[], Tensor], options: EditOptions, what: str) -> float:
    """``options.steps`` Adam steps on ``loss_fn() + options.lambda_reg · edit.penalty()``;
    returns the last step's ``loss_fn()`` plus the penalty at the result.

    The penalty's gradient is added in closed form after each backward pass
    (:func:`~crfedit.edit.losses.add_weight_penalty_grad_`), so ``loss_fn`` leaves it out.  A
    NaN/inf loss or parameter raises :class:`NonFiniteError` (nothing is written);
    ``options.on_step(step, loss)`` after each step sees ``loss_fn()``'s value.
    """
    started = time.perf_counter()
    opt = FusedAdam(edit.params.values(), lr=options.lr)
    losses: list[float] = []
    last = run_adam(opt, loss_fn, options.steps, what, options.on_step, before_step=lambda: edit.add_penalty_grad(options.lambda_reg),
                    refuse_rise=True, losses=losses)
    late = late_loss(losses)
    if late is not None:  # how far the edit moved (finish records it)
        edit.first_loss, edit.fit_loss = losses[0], late
    with torch.no_grad():
        last += options.lambda_reg * float(edit.penalty())
    edit.optimize_seconds = time.perf_counter() - started
    return last


def finish(
    edit: InstanceEdit,
    kind: str,
    options: EditOptions,
    hyper: Mapping[str, object],
    final_loss: float,
    started: float,
    extra: Mapping[str, Tensor] | None = None,
    extra_modules: Sequence[str] = (),
) -> EditResult:
    """Record the edit as a delta and return the model that delta reproduces; its
    hyper-parameters are ``hyper`` and the ones every edit has (strategy, steps, learning
    rate, seed, penalty and its weight)."""
    after = edit.after(extra)
    seconds = time.perf_counter() - started
    hyper = {"strategy": options.strategy, "steps": options.steps, "lr": options.lr, "seed": options.seed,
             "lambda_reg": options.lambda_reg, **hyper, "penalty": edit.per}
    meta = {
        "hyperparameters": json.dumps(hyper, sort_keys=True),
        "final_loss": repr(final_loss),
        **({"first_loss": repr(edit.first_loss), "fit_loss": repr(edit.fit_loss)} if edit.first_loss is not None else {}),
        "seconds": f"{seconds:.3f}",
        "command": "",
    }
    tensors, meta = make_delta(edit.before, after, edit.instance, kind, (*edit.prefixes, *extra_modules), meta)
    model = apply_deltas(edit.before, [Delta("(new edit)", tensors, meta)])
    return EditResult(model, tensors, meta, final_loss, seconds, optimize_seconds=edit.optimize_seconds)


def camera_meta(camera: Camera) -> dict:
    return {"c2w": np.asarray(camera.c2w).tolist(), "focal": camera.focal, "width": camera.width, "height": camera.height}


def select_rays(camera: Camera, pixels: Tensor, device: torch.device) -> Rays:
    """The rays of ``camera`` through the flat pixel indices ``pixels``."""
    rays = rays_from_camera(camera, device)
    idx = pixels.to(device)
    return Rays(rays.origins[idx], rays.directions[idx])


def since(result: EditResult, started: float) -> EditResult:
    """``result`` timed from ``started``, its ``seconds`` and the delta's ``seconds`` record
    alike: an edit that made its own selection counts it, as the whole edit's wall time."""
    seconds = time.perf_counter() - started
    return dataclasses.replace(result, meta={**result.meta, "seconds": f"{seconds:.3f}"}, seconds=seconds)
