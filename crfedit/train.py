"""Training a category model: codes and weights jointly, occupancy grids alongside.

1. The scene box and each instance's starting occupancy grid come from its training
   silhouettes (visual hull), so no sample is ever spent outside the object's hull.
2. Each step renders a batch of random rays (3/4 from object pixels, 1/4 from background
   pixels, which carve the hull's margin), each over a random background colour in the fast
   preset (:func:`over_background`), takes the MSE to the pixels (plus, where the dataset has
   part maps, the part loss of :mod:`crfedit.parts` on 1 024 labelled surface points) and one
   Adam step on weights and codes.
3. Every ``occ_every`` steps a few instances' grids are refreshed from the density.
4. Checkpoints hold the optimizer, RNG, grid and buffer-size state, so ``--resume`` continues
   bit for bit.

A step of the fast preset is device-resident: rays, sample offsets and grid probes are drawn on
the device from a device generator, the optimizer is fused Adam, and on a GPU the march packs
its samples into fixed-capacity buffers (:class:`~crfedit.renderer.FixedMarch`), so nothing is
read back to the host.  The loss, the non-finite guard and the buffer sizes are read every
``read_every`` steps and before every checkpoint (:class:`~crfedit.optim.StepLog`), so a GPU runs
ahead of the host between reads, and a diverged run still never overwrites its last good
checkpoint.  On a CPU the march sizes its samples exactly (``nonzero``): a host read costs a CPU
nothing, while a fixed buffer's padding costs compute (docs/gpu.md has the measurements).

Under ``torchrun`` (``ranks``, see :mod:`crfedit.distributed`) each rank samples its share of
the step's rays from its own instances with its own generator, the gradients are averaged in
one all-reduce, grid refreshes run identically on every rank from a shared generator (and are
checked), and rank 0 alone writes the checkpoint, in the single-process format.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch

from . import occupancy
from .cameras import Rays, off_centre_target, rays_from_camera
from .config import Config
from .data.format import SMALL_COVER, median_cover
from .data.loading import Category, TrainingRays, pixels_digest, training_rays
from .distributed import SINGLE, Ranks, rank_seed
from .errors import CrfError, Terminated
from .field import ConditionalRadianceField
from .optim import StepLog, adam_step, check_finite, check_losses
from .parts import labelled_instances, labelled_points, part_config, part_contrastive_loss, sample_parts
from .model import CategoryModel, ViewTable, load_model, save_model
from .names import is_digits
from .renderer import FixedMarch, render_rays
from .sampling import ray_aabb_intersect

FG_FRACTION = 0.75
READ_EVERY = 16
"""Steps between reads of the loss, the non-finite guard and the march's buffer sizes."""


@dataclass
class TrainResult:
    steps: int
    seconds: float
    final_loss: float
    train_psnr: float
    dropped_rays: int = 0
    """Rays left out of a step's loss because their samples overflowed a march buffer."""


def check_trainable(category: Category, world: int, rays: int) -> None:
    """A one-line error unless ``world`` ranks can train ``category`` with ``rays`` a step:
    every instance it lists has train views (each gets codes, and codes learn only from train
    views), and at most one rank per instance and per ray (each rank samples its own instances
    and draws its share of a step's rays)."""
    bare = [inst.name for inst in category.instances if not inst.splits.get("train")]
    if bare:
        raise CrfError(f"{category.root}: instance {bare[0]} has no train views (transforms_train.json missing)"
                       + (f", nor do {len(bare) - 1} more" if len(bare) > 1 else "") + "; a category model trains every instance it lists")
    instances = len(category.instances)
    if world > min(rays, instances):
        raise CrfError(f"{world} ranks: at most one rank per instance and per ray ({instances} instance{'s' * (instances != 1)}, "
                       f"rays={rays}); launch at most {min(rays, instances)}")


LEAVE_SHARE = 1e-3
""":func:`scene_box`: the silhouettes show the object beyond a box when more than this share of
their pixels look along rays that miss it."""


def scene_box(category: Category, res: int = 48, views_per_instance: int = 40,
              on_note: Callable[[str], None] | None = None) -> torch.Tensor:
    """The world box [6] around every instance's visual hull, carved inside a cube of half the
    nearest camera distance (which contains the object in object-centric captures).  When the
    silhouettes show the object beyond that cube (:func:`silhouettes_leave`), the cube is
    carved again around the point the cameras look at (their axes' least-squares meeting point)
    if that lies off the origin, and kept if the silhouettes stay inside it; otherwise
    ``on_note`` gets a warning.  (A hull that merely reaches the cube's faces is not cut off:
    views all from above leave the cone under a seat uncarved down to the floor.)"""
    views = [v for inst in category.instances for v in inst.splits["train"][:views_per_instance]]
    centers = np.stack([v.camera.center for v in views]).astype(np.float64)
    radius = min(float((v.camera.center**2).sum() ** 0.5) for v in views)
    cube = torch.tensor([-0.5, -0.5, -0.5, 0.5, 0.5, 0.5]) * radius
    union = _hull_union(category, cube, res, views_per_instance)
    leaving = silhouettes_leave(category, cube, views_per_instance)
    if union.any() and not leaving:
        return occupancy.occupied_box(union, cube, margin_cells=2)
    target = off_centre_target([v.camera for v in views])
    if target is not None:
        half = 0.5 * float(np.linalg.norm(centers - target, axis=1).min())
        moved = torch.tensor(np.concatenate([target - half, target + half]), dtype=torch.float32)
        moved_union = _hull_union(category, moved, res, views_per_instance)
        if moved_union.any() and not silhouettes_leave(category, moved, views_per_instance):
            return occupancy.occupied_box(moved_union, moved, margin_cells=2)
    if on_note is not None and union.any():  # an empty one is check_hulls' error
        on_note(f"{category.root}: the silhouettes show the object beyond the scene box (a cube around the origin, "
                f"half the nearest camera's distance across; {100 * leaving:.1f} % of their pixels look past it): "
                "it will be cut off; centre the poses on the object")
    return occupancy.occupied_box(union, cube, margin_cells=2)


def silhouettes_leave(category: Category, box: torch.Tensor, views_per_instance: int = 40) -> float:
    """The share of the training silhouettes' pixels (of the views the hull is carved from)
    whose rays miss ``box`` [6], if above :data:`LEAVE_SHARE`, else 0: matter the box cannot hold."""
    missed = total = 0
    for inst in category.instances:
        for v in inst.splits["train"][:views_per_instance]:
            on = torch.from_numpy(np.ascontiguousarray(v.alpha > 0).reshape(-1))
            rays = rays_from_camera(v.camera)
            _, _, hit = ray_aabb_intersect(rays.origins[on], rays.directions[on], box)
            missed, total = missed + int((~hit).sum()), total + int(on.sum())
    share = missed / max(total, 1)
    return share if share > LEAVE_SHARE else 0.0


def _hull_union(category: Category, cube: torch.Tensor, res: int, views_per_instance: int) -> torch.Tensor:
    union = torch.zeros((res,) * 3, dtype=torch.bool)
    for inst in category.instances:
        vs = inst.splits["train"][:views_per_instance]
        union |= occupancy.carve_visual_hull([v.camera for v in vs], [v.alpha > 0 for v in vs], cube, res, margin=0)
    return union


def silhouette(alpha: np.ndarray, grow: int = 1) -> np.ndarray:
    """Object mask grown by ``grow`` pixels, so a cell whose center projects just outside the
    silhouette but whose footprint overlaps it is not carved away (thin legs survive)."""
    mask = alpha > 0
    for _ in range(grow):
        padded = np.pad(mask, 1)
        mask = padded[1:-1, 1:-1] | padded[:-2, 1:-1] | padded[2:, 1:-1] | padded[1:-1, :-2] | padded[1:-1, 2:]
    return mask


def visual_hulls(category: Category, aabb: torch.Tensor, res: int, margin: int = 0) -> torch.Tensor:
    """Each instance's visual hull from all its training silhouettes.  [K, R, R, R] bool

    ``margin`` cells of 3-D dilation on top; ``margin`` < 0 skips carving (all cells occupied).
    """
    if margin < 0:
        return torch.ones(len(category.instances), res, res, res, dtype=torch.bool)
    return torch.stack([
        occupancy.carve_visual_hull(
            [v.camera for v in inst.splits["train"]], [silhouette(v.alpha) for v in inst.splits["train"]], aabb, res, margin=margin
        )
        for inst in category.instances
    ])


def dataset_notes(category: Category) -> list[str]:
    """What training a model of ``category`` warns of (and ``dataset info`` says first):
    instances without alpha or masks, and instances with far fewer training rays than the
    others (:data:`BALANCE_RATIO`)."""
    notes = []
    opaque = [inst.name for inst in category.instances if inst.splits.get("train") and all(float(v.alpha.min()) >= 1.0 for v in inst.splits["train"])]
    if opaque:
        shown = ", ".join(opaque[:3]) + (", …" if len(opaque) > 3 else "")
        notes.append(f"{len(opaque)} instance{'s' * (len(opaque) != 1)} ({shown}) of {category.root} {'have' if len(opaque) != 1 else 'has'} no alpha or mask in any "
                     "training view: the whole frame counts as the object, so the background is fitted as matter (a cloud "
                     "around it, and a worse model for the rest); give RGBA images, or masks (nerfstudio mask_path)")
    rays = {inst.name: sum(v.camera.width * v.camera.height for v in inst.splits.get("train", [])) for inst in category.instances}
    rays = {name: n for name, n in rays.items() if n}
    if rays and max(rays.values()) > BALANCE_RATIO * min(rays.values()):
        median = sorted(rays.values())[len(rays) // 2]
        few = [name for name, n in rays.items() if n * BALANCE_RATIO < median] or [min(rays, key=rays.get)]
        views = {inst.name: len(inst.splits.get("train", [])) for inst in category.instances}
        shown = ", ".join(f"{name} ({views[name]} view{'s' * (views[name] != 1)})" for name in few[:3]) + (", …" if len(few) > 3 else "")
        notes.append(f"{shown} of {category.root}: far fewer training views than the others (median "
                     f"{sorted(views[n] for n in rays)[len(rays) // 2]}): each batch draws every instance's rays equally, so "
                     "they get their share, but so few views may not fit them as well")
    return notes


def check_camera_reach(category: Category, aabb: torch.Tensor) -> None:
    """A one-line :class:`CrfError` naming the first view (file, split and index) whose camera
    lies too far from the scene box for float32 rays (:func:`~crfedit.renderer.camera_far_problem`):
    a frame 10³⁰ away trained, and then every render and eval of the model failed naming no view."""
    from .renderer import camera_far_problem

    for inst in category.instances:
        for split, views in inst.splits.items():
            for i, view in enumerate(views):
                problem = camera_far_problem(view.camera, aabb)
                if problem is not None:
                    raise CrfError(f"{inst.path}: {split}:{i} ({view.file_path}): camera: {problem}")


def check_hulls(category: Category, hulls: torch.Tensor) -> None:
    """A one-line error naming the first instance whose training silhouettes carve nothing
    (``hulls`` [K, R, R, R]): a model of it would train blank."""
    empty = [inst for inst, hull in zip(category.instances, hulls) if not hull.any()]
    others = f" (and {len(empty) - 1} of the other {len(category.instances) - 1} instances)" if len(empty) > 1 else ""
    for inst in empty[:1]:  # the first, and how many more: all of them says the dataset's axes are OpenCV's
        if not any(v.alpha.any() for v in inst.splits["train"]):
            raise CrfError(f"{inst.path}: instance {inst.name}{others}: every training view's alpha (or mask) is 0, so there is no object to train")
        cover = median_cover([v.alpha for v in inst.splits["train"]])
        if cover < SMALL_COVER:  # a speck, not a pose problem
            n = round(cover * inst.splits["train"][0].alpha.size)
            raise CrfError(f"{inst.path}: instance {inst.name}{others}: its training views show the object on {n} pixel{'s' * (n != 1)} "
                           "(median), too few for the grid to carve it; render it larger in its views (a mesh whose "
                           "bounding box a stray piece far away enlarged?)")
        raise CrfError(f"{inst.path}: instance {inst.name}{others}: its training silhouettes carve an empty visual hull (no point projects onto the "
                       "object in every view); poses must use OpenGL/NeRF camera axes (the camera looks down -Z, +Y up): "
                       "flip the Y and Z axes of OpenCV/COLMAP poses")


def learning_rate(cfg: Config, base: float, step: int, progress: float | None = None) -> float:
    """Cosine decay from ``base`` to ``base·lr_final``; ``progress`` in [0, 1] overrides step/steps."""
    p = min(1.0, step / cfg.steps) if progress is None else min(1.0, progress)
    return base * (cfg.lr_final + (1.0 - cfg.lr_final) * 0.5 * (1.0 + math.cos(math.pi * p)))


def make_optimizer(field: ConditionalRadianceField, cfg: Config) -> torch.optim.Adam:
    codes = [field.shape_codes, field.color_codes]
    grid = [p for n, p in field.named_parameters() if n.endswith(".grid")]
    ids = {id(p) for p in codes + grid}
    rest = [p for p in field.parameters() if id(p) not in ids]
    groups = [
        {"params": rest, "lr": cfg.lr, "base_lr": cfg.lr},
        {"params": codes, "lr": cfg.lr_codes, "base_lr": cfg.lr_codes},
    ]
    if grid:
        groups.append({"params": grid, "lr": 2 * cfg.lr, "base_lr": 2 * cfg.lr})
    return torch.optim.Adam(groups, eps=1e-15, fused=True)  # one kernel per step, and no .item() per parameter


def optimizer_tensors(opt: torch.optim.Adam) -> dict[str, torch.Tensor]:
    """Adam's moments and step counts as flat named tensors (for the checkpoint)."""
    out = {}
    for i, p in enumerate(q for g in opt.param_groups for q in g["params"]):
        for key, value in opt.state.get(p, {}).items():
            out[f"opt.{i}.{key}"] = value if isinstance(value, torch.Tensor) else torch.tensor(value)
    return out


def restore_optimizer(opt: torch.optim.Adam, tensors: dict[str, torch.Tensor]) -> None:
    params = [q for g in opt.param_groups for q in g["params"]]
    for name, value in tensors.items():
        if not name.startswith("opt."):
            continue
        _, i, key = name.split(".", 2)
        if not i.isdigit() or int(i) >= len(params):
            raise CrfError(f"checkpoint optimizer state does not match the model ({name})")
        p = params[int(i)]
        if key != "step" and value.shape != p.shape:
            raise CrfError(f"checkpoint optimizer state does not match the model ({name})")
        # fused Adam keeps its step count as a float32 tensor beside the parameter
        opt.state.setdefault(p, {})[key] = value.to(p.device) if key != "step" else value.to(p.device, torch.float32).clone()


class TrainBatch(NamedTuple):
    """One step's rays with their pixels, and where each marching step's sample sits."""

    rays: Rays
    rgb: torch.Tensor  # [N, 3] target colour
    instance: torch.Tensor  # [N] long
    jitter: torch.Tensor | None  # [N] in [0, 1) (grid sampler); None: the renderer draws its own
    background: torch.Tensor | None = None  # [N, 3] colour behind each ray; None: white


BatchSource = Callable[[int, torch.Generator], TrainBatch]
"""``(rays, generator) → batch``: where :func:`train` takes its rays from (:class:`BatchSampler`)."""


BALANCE_RATIO = 4.0
"""When one instance's training rays outnumber another's by more than this, each batch draws
every instance's rays equally (instance first, then a ray of it) instead of every ray equally:
a chair with 3 training views among chairs with 40 got 2.4 % of the rays and fitted its own
training views at 19.8 dB (the others 31–32).  Within the ratio (every dataset crfedit writes)
the draw is the plain one, bit for bit."""


class BatchSampler:
    """Random training rays: ``FG_FRACTION`` of each batch from object pixels, the rest from
    background; with ``jitter`` the sample offsets too, and with ``random_background`` a
    uniformly random colour behind each ray (:func:`over_background`), both drawn after the rays
    from the same generator.  Draws happen on the generator's device: a GPU generator samples
    without a copy.  Instances far apart in ray count are drawn equally (:data:`BALANCE_RATIO`)."""

    def __init__(self, data: TrainingRays, device: torch.device, jitter: bool = True, random_background: bool = False):
        self.data = TrainingRays(*(t.to(device) for t in (data.origins, data.directions, data.rgb, data.alpha, data.instance)))
        self.fg = (data.alpha > 0).nonzero().squeeze(-1).to(device)
        self.bg = (data.alpha <= 0).nonzero().squeeze(-1).to(device)
        self.jitter = jitter
        self.random_background = random_background
        counts = torch.bincount(data.instance)
        counts = counts[counts > 0]
        self.balanced = bool(len(counts)) and float(counts.max()) > BALANCE_RATIO * float(counts.min())
        if self.balanced:  # each pool ordered by instance, with each instance's start and count in it
            self.spans = [self._spans(pool) for pool in (self.fg, self.bg)]

    def _spans(self, pool: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(pool sorted by instance, each present instance's start in it, its count)."""
        inst = self.data.instance[pool]
        order = torch.argsort(inst, stable=True)
        _, counts = torch.unique_consecutive(inst[order], return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        return pool[order], starts, counts

    def _draw(self, which: int, pool: torch.Tensor, m: int, generator: torch.Generator) -> torch.Tensor:
        if not self.balanced:
            return pool[torch.randint(len(pool), (m,), generator=generator, device=generator.device).to(pool.device)]
        ordered, starts, counts = self.spans[which]
        k = torch.randint(len(counts), (m,), generator=generator, device=generator.device).to(pool.device)
        u = torch.rand(m, generator=generator, device=generator.device).to(pool.device)
        offset = (u * counts[k]).long().clamp(max=counts[k] - 1)
        return ordered[starts[k] + offset]

    def __call__(self, n: int, generator: torch.Generator) -> TrainBatch:
        n_fg = n if len(self.bg) == 0 else (0 if len(self.fg) == 0 else round(n * FG_FRACTION))
        pick = []
        for which, (pool, m) in enumerate(((self.fg, n_fg), (self.bg, n - n_fg))):
            if m:
                pick.append(self._draw(which, pool, m, generator))
        idx = torch.cat(pick)
        d = self.data
        jitter = torch.rand(n, generator=generator, device=generator.device).to(idx.device) if self.jitter else None
        rgb, background = d.rgb[idx], None
        if self.random_background:
            background = torch.rand(n, 3, generator=generator, device=generator.device).to(idx.device)
            rgb = over_background(rgb, d.alpha[idx], background)
        return TrainBatch(Rays(d.origins[idx], d.directions[idx]), rgb, d.instance[idx], jitter, background)


def over_background(rgb_white: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Pixels composited over white (``rgb_white`` [N, 3], straight ``alpha`` [N]) recomposited
    over ``background`` [N, 3]: c·α + b·(1 − α) = rgb_white + (b − 1)(1 − α).

    Over white alone, a white part rendered half transparent, or a white floater in front of
    the background, costs nothing, and the model learns both; a recolour then shows the
    background through the part, a removal leaves the floaters.  Over a random colour each
    step, only the true coverage fits (the trick of instant-ngp's and nerfstudio's synthetic
    scenes)."""
    return rgb_white + (background - 1.0) * (1.0 - alpha)[:, None]


def view_dependence_penalty(field, rays: Rays, inst: torch.Tensor, depth: torch.Tensor, opacity: torch.Tensor,
                            generator: torch.Generator, n_points: int = 128, n_dirs: int = 64) -> torch.Tensor:
    """The paper's regularizer for one-view-per-instance data: the variance of radiance at a
    surface point over ``n_dirs`` random view directions, for the first ``n_points`` rays that
    are at least half opaque (fixed shapes: the rows past them are masked, not cut)."""
    hit = opacity > 0.5
    rows = torch.argsort((~hit).to(torch.int8), stable=True)[:n_points]  # the hit rays first, in order
    used = hit[rows].to(depth.dtype)
    x = rays.origins[rows] + rays.directions[rows] * (depth[rows] / opacity[rows].clamp_min(1e-6)).detach()[:, None]
    feat = field.features(field.normalize(x), inst[rows])
    draw = torch.randn(len(rows), n_dirs, 3, generator=generator, device=generator.device).to(x.device)
    dirs = torch.nn.functional.normalize(draw, dim=-1)
    rgb = field.radiance(feat.repeat_interleave(n_dirs, 0), dirs.reshape(-1, 3), inst[rows].repeat_interleave(n_dirs, 0))
    per_point = rgb.view(len(rows), n_dirs, 3).var(dim=1).mean(dim=-1)
    return (per_point * used).sum() / used.sum().clamp_min(1.0)


def batch_mse(rgb: torch.Tensor, target: torch.Tensor, complete: torch.Tensor | None) -> torch.Tensor:
    """Mean squared error of a ray batch; with ``complete`` [N] bool, over the complete rays only
    (a ray whose samples overflowed a march buffer was rendered without some of them)."""
    if complete is None:
        return torch.mean((rgb - target) ** 2)
    return batch_mean(((rgb - target) ** 2).mean(dim=-1), complete)


def batch_mean(per_ray: torch.Tensor, complete: torch.Tensor | None) -> torch.Tensor:
    """The mean of a per-ray loss [N]; with ``complete`` [N] bool, over the complete rays only
    (:func:`batch_mse`, the distortion loss)."""
    if complete is None:
        return per_ray.mean()
    used = complete.to(per_ray.dtype)
    return (per_ray * used).sum() / used.sum().clamp_min(1.0)


def refresh_occupancy(field, hulls, ema, instances, generator, ranks: Ranks = SINGLE, cells=None, step=None) -> None:
    """Refresh the grids of ``instances`` from the density (candidates = visual hull).

    Every rank runs it with the same weights and an identical ``generator``, so the grids agree;
    a checksum all-reduce proves it (rank 0's grids would overwrite any that differ).  ``cells``
    (each hull's cell indices) and ``step`` (the marching step), computed once by a caller that
    refreshes often, spare the host reads of finding them."""
    s = occupancy.step_size(field.aabb, field.cfg.occ_res, field.cfg.steps_per_cell) if step is None else step
    with torch.no_grad():
        for k in instances:
            density = functools.partial(field.density, instance=k)
            grid = occupancy.update_from_density(
                ema[k], hulls[k].reshape(-1), density, s, field.cfg.occ_threshold, generator=generator,
                cells=None if cells is None else cells[k],
            )
            field.occupancy[k] = grid.view_as(field.occupancy[k])
        if ranks.world > 1:
            rows = [field.occupancy[instances], ema[instances]]
            if not ranks.same_on_all(rows, "occupancy grids"):
                field.occupancy[instances], ema[instances] = rows


@contextlib.contextmanager
def interrupt_between_steps(enabled: bool = True):
    """Yield an event that the first Ctrl-C (SIGINT) or SIGTERM sets instead of raising, for the
    training loop to read between steps (``event.signal`` says which came): the checkpoint an
    interrupted run writes is then a step boundary (weights, optimizer moments and generator
    state of the same step), and ``--resume`` goes on as if never stopped.  A second signal
    interrupts at once.  Only in the main thread, and for SIGINT only where Python's own handler
    is installed (a background job starts with SIGINT ignored, and is stopped by SIGTERM, which
    is handled unless ignored), and not under torchrun, whose ranks could stop at different
    steps: elsewhere the event is never set and the signal acts as it would."""
    event = threading.Event()
    event.signal = None
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield event
        return

    def on_signal(signum, frame) -> None:
        if event.is_set():
            raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt
        event.signal = signum
        event.set()

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    taken = [sig for sig, h in previous.items() if (h is signal.default_int_handler if sig == signal.SIGINT else h is not signal.SIG_IGN)]
    for sig in taken:
        signal.signal(sig, on_signal)
    try:
        yield event
    finally:
        for sig in taken:
            signal.signal(sig, previous[sig])


def train(
    category: Category,
    cfg: Config,
    out: str | Path,
    device: torch.device | str,
    seed: int = 0,
    minutes: float | None = None,
    resume: bool = False,
    on_step: Callable[[int, float, float, float], None] | None = None,
    extra_meta: dict[str, str] | None = None,
    ranks: Ranks = SINGLE,
    batches: BatchSource | None = None,
    read_every: int = READ_EVERY,
    compile: bool = False,
    fixed_shapes: bool | None = None,
    on_note: Callable[[str], None] | None = None,
) -> tuple[CategoryModel, TrainResult]:
    """Train (or, with ``resume``, continue training) a model of ``category`` and write it to ``out``.

    ``on_step(step, loss, psnr, rays_per_s)`` reports progress after every step; loss and PSNR
    are those of the last read-out, every ``read_every`` steps (and at checkpoints), so that the
    steps between read nothing back from the device.  The model file is rewritten atomically
    every ``checkpoint_every`` steps, at the end and on Ctrl-C, each time after a read-out: a
    non-finite loss (or weight) stops training with :class:`NonFiniteError` naming the step of
    the first non-finite loss, leaving the last checkpoint as it was.

    ``fixed_shapes`` marches with fixed-capacity buffers (:class:`~crfedit.renderer.FixedMarch`:
    no host read inside a step); None chooses them everywhere but on a CPU.  ``compile`` runs
    the fixed-shape march's networks through ``torch.compile``.  ``on_note`` gets the scene box's
    warning (:func:`scene_box`), if any.

    ``ranks`` places this process in a torchrun job: ``cfg.rays`` is then the rays of a step over
    all ranks, each rank drawing its share from the instances :meth:`Ranks.shard` gives it.
    ``batches`` replaces that random sampler (e.g. to feed every world size the same rays).
    """
    out, device = Path(out), torch.device(device)
    check_trainable(category, ranks.world, cfg.rays)
    if read_every < 1:
        raise CrfError(f"read_every {read_every}: must be at least 1")
    fixed_shapes = (device.type != "cpu" or compile) if fixed_shapes is None else fixed_shapes
    if compile and not fixed_shapes:
        raise CrfError("--compile compiles the fixed-shape march: it cannot be combined with --march exact")
    generator = torch.Generator(device=device).manual_seed(seed)
    if resume:
        if not out.is_file():
            raise CrfError(f"--resume: {out} does not exist (start without --resume)")
        model, state = load_model(out, device)
        if not state:
            raise CrfError(f"--resume: {out} holds no training state (it was baked or stripped)")
        if model.dataset_fingerprint != category.fingerprint:
            raise CrfError(f"--resume: {out} was trained on another dataset (fingerprint {model.dataset_fingerprint})")
        if model.cfg.to_json() != cfg.to_json():
            cfg = model.cfg  # resuming keeps the stored config, whatever the preset flags say
        stored_seed = model.meta.get("seed", "")
        if is_digits(stored_seed):  # ... and its seed, which the part points and a fresh stream read
            seed = int(stored_seed)
            generator.manual_seed(seed)
        field = model.field
        hulls, ema = state["hull"].to(device), state["occ_ema"].to(device).clone()
        step, elapsed = int(state["step"]), float(state["elapsed"])
        next_instance = int(state.get("next_instance", torch.tensor(0)))
        restore_generator(generator, state["rng"], seed, 0, step)
    else:
        cfg = part_config(category, cfg)
        for note in dataset_notes(category) if on_note is not None else ():
            on_note(note)
        aabb = scene_box(category, on_note=on_note)
        check_camera_reach(category, aabb)
        carved = visual_hulls(category, aabb, cfg.occ_res, max(cfg.hull_margin, 0))  # whatever the sampler: an empty hull stops here
        check_hulls(category, carved)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)  # the initial weights depend on the seed alone
            field = ConditionalRadianceField(cfg, len(category.instances), aabb).to(device)
        hulls = (carved if cfg.hull_margin >= 0 else visual_hulls(category, aabb, cfg.occ_res, -1)).to(device) if cfg.sampler == "grid" else None
        if hulls is not None:
            field.occupancy.copy_(hulls)
        ema = torch.zeros(len(category.instances), cfg.occ_res**3, device=device)
        model = CategoryModel(field, category.names, category.fingerprint)
        for split in ("train", "val", "test"):
            table = ViewTable.from_category(category, split)
            if table is not None:
                model.views[split] = table
        step, elapsed, next_instance = 0, 0.0, 0
        state = {}
    rank_generator = rank_generator_for(state, seed, ranks, step, device) or generator
    if ranks.world > 1:  # the pixels' digest costs a pass over the images: for ranks only
        ranks.agree({"dataset": category.fingerprint, "images": pixels_digest(category), "seed": seed, "step": step, "minutes": minutes,
                     **json.loads(cfg.to_json())}, "comparing the ranks' settings")
    ranks.broadcast_(list(field.parameters()), "sharing the initial weights")
    opt = make_optimizer(field, cfg)
    restore_optimizer(opt, state)
    params = [p for g in opt.param_groups for p in g["params"]]
    if batches is None:
        own = training_rays(category, "train", ranks.shard(range(len(category.instances))))
        batches = BatchSampler(own, device, jitter=cfg.sampler == "grid", random_background=cfg.random_background)
    n_rays = ranks.share(cfg.rays)
    parts, learned = None, []  # every rank draws part points of every labelled instance (crfedit.parts)
    if field.F_part is not None and cfg.part_weight > 0:
        parts = labelled_points(category, labelled_instances(category, cfg.part_labels), seed=seed)
        learned = [] if parts is None else [category.names[k] for k in parts.instance.tolist()]
        parts = None if parts is None else parts.to(device)
        n_labels = 0 if parts is None else int(parts.labels.max()) + 1
    weight = n_rays * ranks.world / cfg.rays  # this rank's part of the step's mean loss, times world
    meta = {**(extra_meta or {}), "seed": str(seed)}  # the run's seed: --resume goes on with it
    if field.F_part is not None:  # whose part maps the head learned: `eval edits` warns when a twin's source is among them
        meta["part_labelled"] = json.dumps(learned)
    march = FixedMarch(field, compile) if cfg.sampler == "grid" and fixed_shapes else None
    if march is not None:
        march.load_state(state, device)
    cells = None if hulls is None else [h.reshape(-1).nonzero().squeeze(-1) for h in hulls]  # once: hulls are fixed
    # what a failed run leaves, said in its error: this run's last checkpoint once it wrote one
    consequence = (f"{out} keeps its last checkpoint" if resume else
                   f"{out} is left as it was (this run wrote no checkpoint yet)" if out.exists() else "no checkpoint was written yet")
    log = StepLog(2, device, size=read_every)  # per step: loss, MSE
    loss_value, mse_value, dropped = float("nan"), float("nan"), 0

    def read_out(resize: bool) -> None:
        """The steps' losses since the last read (raising on a non-finite one) and, at a
        ``read_every`` boundary, the march's buffer sizes: one host read each."""
        nonlocal loss_value, mse_value, dropped
        rows = log.read()
        check_losses(rows, "training", consequence)
        if rows and ranks.world == 1:
            loss_value, mse_value = rows[-1][1]
        if resize and march is not None:
            dropped += march.resize()

    saved = None  # the step of the last checkpoint this run wrote

    def checkpoint() -> None:
        nonlocal consequence, saved
        read_out(False)
        check_finite(params, "training", consequence)
        rank_states = ranks.gather(rank_generator.get_state().tolist(), "gathering generator states") if ranks.world > 1 else []
        if ranks.main:
            train_state = {
                "step": torch.tensor(step),
                "elapsed": torch.tensor(elapsed, dtype=torch.float64),
                "rng": generator.get_state(),
                "occ_ema": ema,
                "next_instance": torch.tensor(next_instance),
                **optimizer_tensors(opt),
                **{f"rng_rank.{r}": torch.tensor(s, dtype=torch.uint8) for r, s in enumerate(rank_states)},
                **(march.state() if march is not None else {}),
            }
            if rank_states:
                train_state["world"] = torch.tensor(ranks.world)
            if hulls is not None:
                train_state["hull"] = hulls
            # the header also says how far the run's clock and time budget are, for --resume
            timing = {"elapsed": f"{elapsed:.3f}", **({"minutes": repr(float(minutes))} if minutes is not None else {})}
            save_model(out, model, train_state, {**meta, "step": str(step), **timing})
        consequence = f"{out} keeps its last checkpoint"
        saved = step
        ranks.barrier("waiting for rank 0 to write the checkpoint")

    budget = None if minutes is None else 60.0 * minutes
    t_start = time.perf_counter() - elapsed
    try:  # Ctrl-C writes a checkpoint first, so an interrupted run can be resumed
        with interrupt_between_steps(ranks.world == 1) as interrupted:
            while step < cfg.steps and (budget is None or elapsed < budget):
                if interrupted.is_set():
                    raise Terminated() if interrupted.signal == signal.SIGTERM else KeyboardInterrupt
                progress = None if budget is None else max(step / cfg.steps, elapsed / budget)
                for g in opt.param_groups:
                    g["lr"] = learning_rate(cfg, g["base_lr"], step, progress)
                batch = batches(n_rays, rank_generator)
                noise = cfg.density_noise * max(0.0, 1.0 - step / max(1, cfg.occ_warmup))
                out_r = render_rays(
                    field, batch.rays, batch.instance, generator=rank_generator, density_noise=noise,
                    early_stop=cfg.train_early_stop, jitter=batch.jitter, march=march,
                    background=1.0 if batch.background is None else batch.background, distortion=cfg.distortion > 0,
                )
                loss = batch_mse(out_r.rgb, batch.rgb, out_r.complete)
                mse = loss.detach()
                if out_r.coarse_rgb is not None:
                    loss = loss + batch_mse(out_r.coarse_rgb, batch.rgb, None)
                if cfg.distortion > 0:
                    loss = loss + cfg.distortion * batch_mean(out_r.distortion, out_r.complete)
                if cfg.view_reg > 0:
                    loss = loss + cfg.view_reg * view_dependence_penalty(field, batch.rays, batch.instance, out_r.depth, out_r.opacity, rank_generator)
                if parts is not None:
                    x, inst, labels = sample_parts(parts, rank_generator)
                    embedding = field.part_embedding(field.fuse_features(field.normalize(x), inst))
                    loss = loss + cfg.part_weight * part_contrastive_loss(embedding.view(*labels.shape, -1), labels, n_labels)
                loss = loss if weight == 1.0 else loss * weight
                log.record(step, torch.stack([loss.detach(), mse]))
                shared = []  # under torchrun: the step's mean loss, MSE and clock over ranks, from the gradient all-reduce

                def average_gradients() -> None:  # one host read per step: every rank must agree on when to stop
                    shared[:] = ranks.average(params, [float(loss.detach()), float(mse) * weight, time.perf_counter() - t_start])
                    check_losses([(step, shared)], "training", consequence)

                adam_step(opt, loss, average_gradients if ranks.world > 1 else None)
                step += 1
                if hulls is not None and step >= cfg.occ_warmup and step % cfg.occ_every == 0:
                    per_update = max(1, math.ceil(len(category.instances) / 4))
                    ks = [(next_instance + i) % len(category.instances) for i in range(per_update)]
                    next_instance = (next_instance + per_update) % len(category.instances)
                    refresh_occupancy(field, hulls, ema, ks, generator, ranks, cells, march.step if march else None)
                if ranks.world > 1:
                    loss_value, mse_value, elapsed = shared  # every rank stops at the same step
                else:
                    elapsed = time.perf_counter() - t_start
                if step % read_every == 0 or step % cfg.checkpoint_every == 0:
                    read_out(step % read_every == 0)
                if on_step is not None:
                    on_step(step, loss_value, mse_to_psnr(mse_value), cfg.rays * step / max(elapsed, 1e-9))
                if step % cfg.checkpoint_every == 0:
                    checkpoint()
    except KeyboardInterrupt as e:
        stop = type(e) if isinstance(e, Terminated) else KeyboardInterrupt  # SIGTERM stays itself (the CLI's exit 143)
        if ranks.world > 1:  # the ranks may be interrupted inside different collectives: no joint write
            if saved is None and not resume:
                raise stop(f"at step {step}, before this run's first checkpoint: nothing to resume") from None
            kept = f"its checkpoint at step {saved}" if saved is not None else "the checkpoint it was resumed from"
            raise stop(f"{out} keeps {kept} (interrupted at step {step}); continue with --resume") from None
        checkpoint()
        raise stop(f"checkpoint at step {step} written to {out}; continue with --resume") from None
    checkpoint()
    dropped += march.pending_drops() if march is not None else 0
    return model, TrainResult(step, elapsed, loss_value, mse_to_psnr(mse_value), dropped)


def mse_to_psnr(mse: float) -> float:
    """PSNR of images in [0, 1] from their MSE (NaN before the first read-out)."""
    return -10.0 * math.log10(max(mse, 1e-10)) if math.isfinite(mse) else float("nan")


def restore_generator(gen: torch.Generator, saved: torch.Tensor, seed: int, rank: int, step: int) -> torch.Generator:
    """``gen`` at a checkpoint's state.  A state saved on another kind of device (a CUDA
    generator's is 16 bytes, a CPU one's 5056) cannot be continued, so such a run resumes with a
    fresh stream seeded by ``(seed, rank, step)``."""
    try:
        return gen.set_state(saved.to(torch.uint8))
    except RuntimeError:
        return gen.manual_seed(rank_seed(seed, rank, step))


def rank_generator_for(state: dict[str, torch.Tensor], seed: int, ranks: Ranks, step: int,
                       device: torch.device | str = "cpu") -> torch.Generator | None:
    """This rank's own sampling generator on ``device`` (None for a single process, which uses
    the shared one): its checkpointed state when the run resumes at the same world size, else
    seeded by ``(seed, rank, step)``."""
    if ranks.world == 1:
        return None
    gen = torch.Generator(device=device)
    key = f"rng_rank.{ranks.rank}"
    if key in state and int(state.get("world", torch.tensor(0))) == ranks.world:
        return restore_generator(gen, state[key], seed, ranks.rank, step)
    return gen.manual_seed(rank_seed(seed, ranks.rank, step))
