"""Fitting a new instance to one photo of a real object of the category (paper, Sec. 5).

The photo is center-cropped to the pose camera's aspect, area-resized to its size (the model's
training resolution) and composited on white with its object mask (alpha channel or a mask
file).  The new instance k is then fitted in two stages, both on the photometric MSE
``mean_r ‖C(r) − C_photo(r)‖²`` over the photo's pixels:

1. **codes**: only k's shape and colour codes, started from the mean code of the training
   instances; every weight is frozen.
2. **joint**: k's codes and a copy of the network weights under :data:`JOINT` (by default
   ``F_fuse``, ``F_dens`` and ``F_rad``; the paper fine-tunes the whole network, ``all``),
   with ``λ · Σ_tensors mean((θ − θ₀)²)`` pulling the copy towards the shared weights θ₀
   (λ = 10, as the edits do).  The copy renders k only.

Occupancy: k's grid starts as the union of every training instance's grid carved by the
photo's silhouette seen from the pose (a one-view visual hull), dilated by one cell; after
fitting it is re-thresholded from the fitted density within that hull.

The result is a ``fit-real`` delta (crfedit/delta.py) that *adds* instance k: its code rows,
its occupancy grid and the weight differences of stage 2.  The base model is untouched.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from . import occupancy
from .cameras import Camera, Rays, camera_problem, rays_from_camera
from .data.format import resize_area
from .delta import Delta, apply_deltas, grow, make_delta
from .edit.core import EditResult, camera_meta
from .edit.losses import mse, weight_penalty
from .edit.params import used_code_tables
from .edit.core import rethreshold
from .errors import CrfError
from .field import ConditionalRadianceField
from .io import read_image
from .metrics import mse_to_psnr
from .model import CategoryModel
from .optim import FusedAdam, run_adam
from .renderer import render_camera, render_rays
from .runtime import full_precision

JOINT: dict[str, tuple[str, ...]] = {
    "heads": ("F_fuse.", "F_dens.", "F_rad.", "coarse.F_fuse.", "coarse.F_dens.", "coarse.F_rad."),
    "all": ("F_share.", "F_inst.", "F_fuse.", "F_dens.", "bottleneck.", "F_rad.", "coarse."),
}
"""The weights stage 2 fine-tunes (state-dict prefixes; those the field lacks are dropped):
``heads`` — fusion, density and radiance layers (of both networks in the paper preset);
``all`` — every network weight, as the paper does."""

MASK_LEVEL = 0.1
"""A mask-file pixel is object when its brightest channel exceeds this (non-black, robust to
JPEG noise around black)."""


# ----------------------------------------------------------------------------- the photo


@dataclass(frozen=True, eq=False)
class Photo:
    """A photo ready to fit: composited on white at the camera's size."""

    rgb: np.ndarray  # [H, W, 3] float32, rgb·a + (1 − a)
    alpha: np.ndarray  # [H, W] float32 object coverage in [0, 1]
    silhouette: str = "alpha"
    """Where the object's outline came from: ``mask`` (--mask), ``alpha`` (the photo's alpha
    channel), ``white background`` (:func:`white_background`) or ``whole photo``."""

    @property
    def mask(self) -> np.ndarray:
        """[H, W] bool: pixels the object covers more than faintly (:data:`FAINT_ALPHA`; the
        silhouette that carves the hull and picks the starting chair)."""
        return self.alpha > FAINT_ALPHA


FAINT_ALPHA = 0.05
"""An alpha (or a resized mask's coverage) at most this is not the object.  A photo resized with
a Lanczos or bicubic filter keeps a halo of alpha 1–7/255 around the object: counted, it grew a
tester's chair from 736 to 1035 pixels, started the fit from another chair, doubled the grid and
fitted 8 dB worse.  A 1-px leg area-resized 8× down still covers 0.125."""


def read_object_mask(path: str | Path, photo: tuple[str, int, int] | None = None) -> np.ndarray:
    """A mask file as bool [H, W]: where the image has transparency, alpha > :data:`FAINT_ALPHA` is the object;
    otherwise non-black pixels (brightest channel > :data:`MASK_LEVEL`) are.  ``photo`` (its
    path, width, height): the size it must have, checked first (an empty mask of another size
    was called empty, the more basic mistake unsaid)."""
    image = read_image(path)
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise CrfError(f"{path}: mask is empty (0 pixels)")
    if photo is not None and image.shape[:2] != (photo[2], photo[1]):
        raise CrfError(f"{path}: mask is {image.shape[1]}x{image.shape[0]} but the photo {photo[0]} is {photo[1]}x{photo[2]}")
    if image.shape[2] == 4 and bool((image[..., 3] < 1.0).any()):
        mask = image[..., 3] > FAINT_ALPHA
    else:
        mask = image[..., :3].max(axis=-1) > MASK_LEVEL
    if not mask.any():
        raise CrfError(f"{path}: mask is empty (no non-black or non-transparent pixel marks the object)")
    return mask


def center_crop(image: np.ndarray, aspect: float) -> np.ndarray:
    """The largest centered window of ``image`` [H, W, ...] with width / height = ``aspect``.

    Example: a 40×30 (W×H) image cropped to aspect 1 keeps columns 5…34, every row.
    """
    h, w = image.shape[:2]
    if w > aspect * h:
        cw = max(1, round(aspect * h))
        x0 = (w - cw) // 2
        return image[:, x0 : x0 + cw]
    ch = max(1, round(w / aspect))
    y0 = (h - ch) // 2
    return image[y0 : y0 + ch]


WHITE_LEVEL = 0.94
"""A pixel whose every channel is at least this is white background where it connects to the
photo's border (:func:`white_background`): 15/255 of JPEG noise and paper tint below pure white."""


def white_background(rgb: np.ndarray, level: float = WHITE_LEVEL) -> np.ndarray:
    """[H, W] bool: the white pixels (every channel ≥ ``level``) connected to the image's border
    through white pixels (4-neighbours).  A chair shot on white gets its silhouette from this;
    white parts inside the chair, enclosed by darker ones, stay object."""
    white = rgb.min(axis=-1) >= level
    reached = np.zeros_like(white)
    reached[0], reached[-1], reached[:, 0], reached[:, -1] = white[0], white[-1], white[:, 0], white[:, -1]
    while True:  # grow from the border: at most one pass per pixel of the longest white path
        grown = reached.copy()
        grown[1:] |= reached[:-1]
        grown[:-1] |= reached[1:]
        grown[:, 1:] |= reached[:, :-1]
        grown[:, :-1] |= reached[:, 1:]
        grown &= white
        if np.array_equal(grown, reached):
            return reached
        reached = grown


def has_transparency(image: np.ndarray) -> bool:
    """Whether ``image`` [H, W, C] has an alpha channel that marks anything transparent: an
    editor's RGBA export with alpha 1 everywhere outlines nothing (as ``--mask`` reads it)."""
    return image.shape[2] == 4 and bool((image[..., 3] < 1.0).any())


def prepare_photo(image: np.ndarray, mask: np.ndarray | None, width: int, height: int, where: str = "photo") -> Photo:
    """Crop ``image`` [H, W, 3|4] (floats in [0, 1]) to the aspect width/height, area-resize it
    to (width, height) and composite it on white.

    The object is ``mask`` [H, W] bool when given; else the image's alpha channel where it has
    transparency (:func:`has_transparency`); else, for a photo on white, everything but the
    white background around it (:func:`white_background` at the view's size: on a tester's
    photo the same outline as its mask file's; without it a photo on white fitted a haze over
    the whole view, since the outline carves the starting grid); else the whole photo.
    Compositing happens before resizing (straight alpha), so edge pixels blend with white as
    the training images do.  A photo white all over is an error.
    """
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise CrfError(f"{where}: image is empty (0 pixels)")
    h, w = image.shape[:2]
    if mask is not None and tuple(mask.shape) != (h, w):
        raise CrfError(f"{where}: mask is {mask.shape[1]}x{mask.shape[0]} but the photo is {w}x{h}")
    silhouette = "mask" if mask is not None else "alpha" if has_transparency(image) else "whole photo"
    if silhouette == "mask":
        alpha = mask.astype(np.float32)
    elif silhouette == "alpha":
        alpha = image[..., 3].astype(np.float32)
    else:
        alpha = np.ones((h, w), np.float32)
    shown = alpha > FAINT_ALPHA
    if not shown.any():
        raise CrfError(f"{where}: the object mask is empty ({transparent_text(alpha)})")
    cut = crop_cut(shown, width, height) if silhouette != "whole photo" else 0.0
    if cut > CROP_REFUSE:
        raise CrfError(f"{where}: the centre crop to the view's {width}:{height} aspect cuts off {cut:.0%} of the object's "
                       "pixels: crop the photo around the object first")
    rgb = image[..., :3] * alpha[..., None] + (1.0 - alpha[..., None])
    stacked = center_crop(np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.float32), width / height)
    out = np.clip(resize_area(stacked, width, height), 0.0, 1.0)
    if silhouette == "whole photo":
        background = white_background(out[..., :3])
        if background.all() and bool((rgb.min(axis=-1) < WHITE_LEVEL).any()):  # the object is there, beside the crop
            raise CrfError(f"{where}: the centre crop to the view's {width}:{height} aspect leaves none of the object, which lies "
                           "beside it: crop the photo around the object first")
        if background.all():
            raise CrfError(f"{where}: the photo is white all over at the view's size: no object to fit "
                           "(an object as white as its background needs --mask or an alpha channel)")
        if background.any():
            out[..., 3] = ~background
            silhouette = "white background"
    photo = Photo(np.ascontiguousarray(out[..., :3]), np.ascontiguousarray(out[..., 3]), silhouette)
    if not photo.mask.any():
        raise CrfError(f"{where}: the object mask is empty once the photo is cropped to the view's aspect")
    return photo


WHITE_BORDER = 0.5
"""A photo without an object mask takes its outline from the white around it
(:func:`white_background`); :func:`photo_warnings` warns unless at least this share of its
border (the outermost pixels) is white at :data:`WHITE_LEVEL`, where the outline would be
missing or partial and the background fitted as part of the object."""


CROP_CUT = 0.02
""":func:`photo_warnings` warns when the centre crop to the view's aspect drops more than this
share of the object's pixels (an object off the centre of a wide photo is fitted in part)."""


def transparent_text(alpha: np.ndarray) -> str:
    """Why an alpha channel [H, W] outlines nothing: all 0, or nothing above :data:`FAINT_ALPHA`."""
    return "every pixel is transparent" if not (alpha > 0).any() else f"no pixel's alpha is above {FAINT_ALPHA}: a faint halo, not an object"


CROP_REFUSE = 0.5
""":func:`prepare_photo` refuses a photo whose centre crop drops more than this share of the
object's pixels: a tester's chair cut to its last 6 % fitted nothing, and the error blamed
``--pose`` after the warning."""


def crop_cut(target: np.ndarray, width: int, height: int) -> float:
    """The share of ``target``'s [H, W] bool pixels that the centre crop to ``width``:``height``
    drops (0 for an empty target)."""
    total = float(target.sum())
    return 1.0 - float(center_crop(target, width / height).sum()) / total if total else 0.0


def photo_warnings(image: np.ndarray, mask: np.ndarray | None, width: int, height: int) -> list[str]:
    """What makes a fit to this photo doubtful, one line each ([] when nothing does): no object
    mask and a border that is not white (the background is fitted as part of the object), or a
    photo smaller than the view it is fitted in (it is upscaled: its PSNR flatters the fit)."""
    out = []
    h, w = image.shape[:2]
    if mask is not None:
        target = mask
    elif has_transparency(image):
        target = image[..., 3] > FAINT_ALPHA
    else:
        target = image[..., :3].min(axis=-1) < WHITE_LEVEL  # the object, where the border is white
        border = np.concatenate([image[0, :, :3], image[-1, :, :3], image[:, 0, :3], image[:, -1, :3]])
        if float((border.min(axis=-1) >= WHITE_LEVEL).mean()) < WHITE_BORDER:
            target = None  # no outline to judge the crop by (warned below)
            out.append(f"the photo has no alpha channel and no --mask, and its border is not white (mean {float(border.mean()):.2f}; "
                       f"white is every channel at least {WHITE_LEVEL}): the background is fitted as part of the object; "
                       "give --mask, or a photo on white")
    if target is not None:
        cut = crop_cut(target, width, height)
        if cut > CROP_CUT:
            out.append(f"the centre crop to the view's {width}:{height} aspect cuts off {cut:.0%} of the object's pixels: "
                       "crop the photo around the object first")
    crop_w, crop_h = (min(w, round(h * width / height)), h) if w * height >= h * width else (w, min(h, round(w * height / width)))
    if crop_w < width or crop_h < height:
        out.append(f"the photo gives {crop_w}x{crop_h} pixels for the {width}x{height} view: it is upscaled, and its PSNR "
                   "measures the fit to a blurred photo")
    return out


def read_photo(path: str | Path, mask_path: str | Path | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(image [H, W, 3|4] float32, mask [H, W] bool or None) from a PNG/JPEG and an optional mask
    file, checked: readable, not empty, the mask the photo's size and not empty."""
    image = read_image(path)
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise CrfError(f"{path}: image is empty (0 pixels)")
    if mask_path is None:
        if image.shape[2] == 4 and not (image[..., 3] > FAINT_ALPHA).any():
            raise CrfError(f"{path}: the object mask is empty ({transparent_text(image[..., 3])})")
        return image, None
    return image, read_object_mask(mask_path, (str(path), image.shape[1], image.shape[0]))


# ----------------------------------------------------------------------------- options


STARTS = ("nearest", "mean", "nearest-codes")
OUTLINE_WARN = 0.5
"""``fit-real`` warns when no training instance's outline from the pose matches the photo's
this well (IoU): a pose that does not see the object as the photo does, an object off the
photo's centre (a tester's shifted chair matched at 0.25, its own pose at 0.70)."""
NEAREST_GRIDS = 1


@dataclass(frozen=True)
class FitOptions:
    """How ``fit-real`` optimizes."""

    steps_codes: int = 200
    """Stage 1: Adam steps on the new instance's codes only."""
    steps_joint: int = 200
    """Stage 2: Adam steps on codes and the :data:`JOINT` weights (0 = codes only)."""
    weights: str = "heads"
    """Which weights stage 2 opens: a key of :data:`JOINT`."""
    lr_codes: float = 1e-2
    """Adam learning rate of the codes (both stages)."""
    lr_weights: float = 1e-3
    """Adam learning rate of the weights (stage 2)."""
    rays: int = 4096
    """Rays per step, sampled from the photo's pixels (all of them when it has no more)."""
    lambda_reg: float = 10.0
    """Weight of Σ_tensors mean((θ − θ₀)²) towards the shared weights in stage 2."""
    distortion: float = 0.1
    """Weight of Mip-NeRF 360's distortion loss on the photo's rays in stage 2 (grid sampler;
    :func:`~crfedit.rendering.distortion_packed`).  One view leaves the depth along each ray
    free, and the heads stage 2 opens spread each surface over ~5 cells of depth without it: a
    recolour's selection then held 0.47 of the scribbled pixels' weight and the seat came out
    olive, not red; at 0.1 it held 0.98 and the seat turned red.  Held-out chairs' other views
    scored within 0.1 dB of the fit without it; in stage 1 too it cost the codes-only fit
    0.47 dB (docs/benchmarks.md, sixty-second session)."""
    seed: int = 0
    """Seeds the rays, the sample jitter and the occupancy probes."""
    grids: int = NEAREST_GRIDS
    """With ``start="nearest"``: how many of the best-matching instances' grids the start's grid
    unites (1: the best match's alone; 3 gave 0.3–0.4 dB less, each other grid's haze with it)."""
    start: str = "nearest"
    """Where the fit starts: ``nearest`` (the codes of the training instance whose render from
    the pose best matches the photo's outline, in its grid (:attr:`grids`) carved by that
    outline), ``mean`` (the mean code in every training grid's union, carved: the paper's
    start), or ``nearest-codes`` (those codes in the union of every grid).  The model's density
    is trained only inside each chair's own grid, so every grid's union shows the other chairs'
    haze, which the codes cannot clear: a photo of a training chair with its own codes scored
    17.2 dB there against 28.3 in its own grid.  Measured (docs/benchmarks.md, sixty-fifth
    session) on procedural chairs the model never saw, other views: 19.35 → 20.24 dB with
    their true camera, 18.67 → 19.39 dB with the nearest training camera as a user would pick;
    on the real chairs' photos see there."""

    def validated(self) -> "FitOptions":
        checks = [
            (self.steps_codes >= 0, f"--steps-codes {self.steps_codes}: must be 0 or more"),
            (self.steps_joint >= 0, f"--steps-joint {self.steps_joint}: must be 0 or more"),
            (self.weights in JOINT, f"--weights {self.weights}: expected one of {', '.join(JOINT)}"),
            (math.isfinite(self.lr_codes) and self.lr_codes > 0, f"--lr-codes {self.lr_codes}: must be a finite positive number"),
            (math.isfinite(self.lr_weights) and self.lr_weights > 0, f"--lr-weights {self.lr_weights}: must be a finite positive number"),
            (self.rays >= 2, f"--rays {self.rays}: need at least 2"),
            (math.isfinite(self.lambda_reg) and self.lambda_reg >= 0, f"lambda_reg {self.lambda_reg}: must be ≥ 0"),
            (math.isfinite(self.distortion) and self.distortion >= 0, f"--distortion {self.distortion}: must be 0 or more"),
            (self.start in STARTS, f"--start {self.start}: expected one of {', '.join(STARTS)}"),
            (self.grids >= 1, f"--grids {self.grids}: must be 1 or more"),
        ]
        for ok, message in checks:
            if not ok:
                raise CrfError(message)
        return self


@dataclass(frozen=True)
class StageReport:
    """The photometric fit at the end of a stage: a deterministic render of the pose vs the photo."""

    stage: str  # "codes" | "joint" | "final" (the stored result, occupancy refreshed)
    steps: int
    loss: float  # MSE over every pixel of the photo
    psnr: float
    seconds: float  # time spent in this stage


@dataclass
class FitResult(EditResult):
    """A fit-real edit: the model with the new instance (as the delta reproduces it), the delta
    file's contents, and one :class:`StageReport` per stage."""

    stages: list[StageReport]
    instance: int


# ----------------------------------------------------------------------------- pieces


def check_new_name(model: CategoryModel, name: str, what: str = "--name") -> str:
    """A valid name for an added instance: non-empty, not a number, not taken.  ``what`` says
    where the name came from in the error message."""
    if not name or name != name.strip() or not name.isprintable():
        raise CrfError(f"{what} {name!r}: must be non-empty, without surrounding spaces, line breaks or control characters")
    if any(c in name for c in "/\\") or name in (".", ".."):  # names become file and folder names (a render's, the page's)
        raise CrfError(f"{what} {name!r}: must not hold / or \\ (it names files)")
    if name.lstrip("-").isdigit():
        raise CrfError(f"{what} {name}: must not be a number (numbers select instances by index); pick a name with --name")
    same = [n for n in model.names if unicodedata.normalize("NFC", n) == unicodedata.normalize("NFC", name)]
    if same:  # "café" typed with é or with e and a combining accent: one name to a reader
        alike = "" if same[0] == name else f" ({same[0]!r}, spelt with other Unicode code points)"
        raise CrfError(f"{what} {name}: the model already has an instance of that name{alike} (pick another with --name)")
    return name


def joint_prefixes(field: ConditionalRadianceField, weights: str) -> tuple[str, ...]:
    """The :data:`JOINT` prefixes of ``weights`` that match parameters of ``field``."""
    names = [n for n, _ in field.named_parameters()]
    return tuple(p for p in JOINT[weights] if any(n.startswith(p) for n in names))


def mean_codes(field: ConditionalRadianceField, tables: list[str]) -> dict[str, Tensor]:
    """The mean row [D] of each code table in ``tables`` (the start of a fit)."""
    return {t: getattr(field, t).detach().mean(dim=0) for t in tables}


def outline_ranking(model: CategoryModel, camera: Camera, mask: np.ndarray) -> list[tuple[float, int]]:
    """(IoU, instance) of every instance, best first: the IoU of its opacity > 0.5 rendered from
    ``camera`` with the photo's object ``mask`` [H, W]."""
    want = torch.from_numpy(np.asarray(mask, dtype=bool))
    out = []
    for j in range(len(model.names)):
        seen = render_camera(model.field_for(j), camera, j, colour=False).opacity.cpu() > 0.5
        union = int((seen | want).sum())
        out.append((int((seen & want).sum()) / union if union else 0.0, j))
    return sorted(out, key=lambda t: -t[0])


def photo_hull(model: CategoryModel, camera: Camera, mask: np.ndarray, grids: list[int] | None = None) -> Tensor:
    """The new instance's starting grid [R, R, R]: the union of the training instances' grids
    (``grids``: of those instances alone, the nearest start's best match), carved by the photo's silhouette seen from ``camera`` (cells outside the view or off the
    object go), dilated by one cell."""
    field = model.field
    union = (field.occupancy if grids is None else field.occupancy[grids]).any(dim=0).cpu()
    carved = occupancy.carve_visual_hull([camera], [mask], field.aabb.detach().cpu(), field.cfg.occ_res, margin=0)
    hull = occupancy.dilate(union & carved, 1)
    if not hull.any():
        raise CrfError(
            "the photo's silhouette, seen from --pose, covers no occupied cell of the category: "
            "check that --pose views the object as the photo does"
        )
    return hull.to(model.device)


def photo_error(field: ConditionalRadianceField, camera: Camera, instance: int, target: Tensor) -> tuple[float, float]:
    """(MSE, PSNR) of a deterministic render of ``camera`` against ``target`` [H·W, 3]."""
    rgb = render_camera(field, camera, instance).rgb.reshape(-1, 3)
    value = float(mse(rgb, target))
    return value, mse_to_psnr(value)


class _Fitter:
    """The photometric loss of instance ``k`` of ``field`` on random photo rays."""

    distortion = 0.0
    """Weight of the distortion loss on the batch's rays (stage 2 sets it: :attr:`FitOptions.distortion`)."""

    def __init__(self, field: ConditionalRadianceField, k: int, camera: Camera, photo: Photo, rays: int, generator: torch.Generator):
        device = field.aabb.device
        self.field, self.k, self.rays, self.generator = field, k, rays, generator
        self.all_rays = rays_from_camera(camera, device)
        self.target = torch.from_numpy(photo.rgb.reshape(-1, 3)).to(device)

    def loss(self) -> tuple[Tensor, float]:
        """(loss to minimize, photometric MSE of the batch)."""
        n = self.target.shape[0]
        if self.rays >= n:
            idx = torch.arange(n, device=self.target.device)
        else:
            idx = torch.randperm(n, generator=self.generator)[: self.rays].to(self.target.device)
        rays = Rays(self.all_rays.origins[idx], self.all_rays.directions[idx])
        out = render_rays(self.field, rays, self.k, generator=self.generator, early_stop=self.field.cfg.train_early_stop,
                          distortion=self.distortion > 0)
        loss = mse(out.rgb, self.target[idx])
        photometric = float(loss.detach())  # the batch's colour error alone, what the progress reports
        if self.distortion > 0:
            loss = loss + self.distortion * out.distortion.mean()
        if out.coarse_rgb is not None:
            loss = loss + mse(out.coarse_rgb, self.target[idx])
        return loss, photometric


StepCallback = Callable[[str, int, int, float, float], None]
"""``on_step(stage, step, steps, loss, psnr)``: after every Adam step (PSNR of the batch)."""


def _run_stage(
    stage: str, fitter: _Fitter, groups: list[dict], steps: int, penalty: Callable[[], Tensor] | None, on_step: StepCallback | None
) -> None:
    """``steps`` Adam steps on the photometric loss (+ ``penalty()``); NaN/inf stops with nothing written."""
    photometric = [float("nan")]

    def loss_fn() -> Tensor:
        loss, photometric[0] = fitter.loss()
        return loss if penalty is None else loss + penalty()

    report = None if on_step is None else (lambda step, _: on_step(stage, step, steps, photometric[0], mse_to_psnr(photometric[0])))
    run_adam(FusedAdam(groups), loss_fn, steps, f"fit-real's {stage} stage", report)


# ----------------------------------------------------------------------------- fitting


@full_precision
def fit_real(
    model: CategoryModel,
    photo: Photo,
    camera: Camera,
    name: str,
    options: FitOptions = FitOptions(),
    on_step: StepCallback | None = None,
    on_stage: Callable[[StageReport], None] | None = None,
    on_note: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit a new instance ``name`` to ``photo`` seen from ``camera`` (same size as the photo).

    Returns the ``fit-real`` delta and the model it reproduces (``model`` + delta, exactly as
    :func:`~crfedit.delta.apply_edit_files` computes it).  ``model`` is not modified.
    """
    started = time.perf_counter()
    options = options.validated()
    problem = camera_problem(camera)  # before the hull, whose carving would blame --pose for a NaN pose
    if problem:
        raise CrfError(f"camera: {problem}")
    check_new_name(model, name)
    if photo.rgb.shape[:2] != (camera.height, camera.width):
        raise CrfError(
            f"the photo is {photo.rgb.shape[1]}x{photo.rgb.shape[0]} but the pose camera is {camera.width}x{camera.height}"
        )
    tables = used_code_tables(model.field)
    if not tables:
        raise CrfError(f"fit-real: a model of arch {model.field.arch!r} has no per-instance codes to fit")
    grid_sampler = model.cfg.sampler == "grid"
    ranking = outline_ranking(model, camera, photo.mask) if options.start != "mean" else None
    if ranking and ranking[0][0] < OUTLINE_WARN and on_note is not None:  # said before the fit, which it bodes ill for
        on_note(f"no training instance's outline from the pose matches the photo's well (best: {model.names[ranking[0][1]]}, "
                f"IoU {ranking[0][0]:.2f}): check that the pose sees the object as the photo does and that the object is "
                "centred in the photo")
    grids = [j for _, j in ranking[:options.grids]] if options.start == "nearest" else None
    hull = photo_hull(model, camera, photo.mask, grids) if grid_sampler else None
    grown = grow(model, name)
    k = len(model.names)
    field = grown.field
    with torch.no_grad():
        start_rows = mean_codes(model.field, tables) if ranking is None else {t: getattr(model.field, t).detach()[ranking[0][1]] for t in tables}
        for table, row in start_rows.items():
            getattr(field, table)[k] = row
        if hull is not None:
            field.occupancy[k] = hull
    for p in field.parameters():
        p.requires_grad_(False)
    generator = torch.Generator().manual_seed(options.seed)
    distortion = options.distortion if grid_sampler else 0.0  # the distortion loss reads the grid sampler's intervals
    fitter = _Fitter(field, k, camera, photo, options.rays, generator)
    codes = [getattr(field, t) for t in tables]
    reports: list[StageReport] = []

    def report(stage: str, steps: int, since: float, f: ConditionalRadianceField) -> None:
        loss, psnr = photo_error(f, camera, k, fitter.target)
        reports.append(StageReport(stage, steps, loss, psnr, time.perf_counter() - since))
        if on_stage is not None:
            on_stage(reports[-1])

    t0 = time.perf_counter()
    for p in codes:
        p.requires_grad_(True)
    _run_stage("codes", fitter, [{"params": codes, "lr": options.lr_codes}], options.steps_codes, None, on_step)
    report("codes", options.steps_codes, t0, field)
    fitter.distortion = distortion  # the codes keep the category's shapes; the heads of stage 2 can spread one in depth

    prefixes: tuple[str, ...] = ()
    if options.steps_joint > 0:
        t0 = time.perf_counter()
        prefixes = joint_prefixes(field, options.weights)
        weights = {n: p for n, p in field.named_parameters() if n.startswith(prefixes)}
        start = {n: p.detach().clone() for n, p in weights.items()}
        for p in weights.values():
            p.requires_grad_(True)
        groups = [{"params": codes, "lr": options.lr_codes}, {"params": list(weights.values()), "lr": options.lr_weights}]

        def penalty() -> Tensor:
            return options.lambda_reg * weight_penalty(weights, start, {})

        _run_stage("joint", fitter, groups, options.steps_joint, penalty, on_step)
        report("joint", options.steps_joint, t0, field)
    for p in field.parameters():
        p.requires_grad_(False)

    t0 = time.perf_counter()
    if hull is not None:
        with torch.no_grad():
            field.occupancy[k] = rethreshold(field, k, hull, generator)
    modules = (*prefixes, *tables, *(("occupancy",) if grid_sampler else ()))
    hyper = {
        "steps_codes": options.steps_codes, "steps_joint": options.steps_joint, "weights": options.weights,
        "lr_codes": options.lr_codes, "lr_weights": options.lr_weights, "rays": options.rays,
        "lambda_reg": options.lambda_reg, "distortion": distortion, "seed": options.seed,
        "init": "mean code" if ranking is None else f"{model.names[ranking[0][1]]}'s codes (outline IoU {ranking[0][0]:.3f})",
        **({"outline_iou": round(ranking[0][0], 3), "nearest": model.names[ranking[0][1]]} if ranking else {}),
        "start": options.start, **({"grids": [model.names[j] for j in grids]} if grids else {}), "camera": camera_meta(camera),
        "hull_cells": int(hull.sum()) if hull is not None else None,
    }
    after = dataclasses.replace(grown, field=field)
    tensors, meta = make_delta(model, after, k, "fit-real", modules, {"hyperparameters": json.dumps(hyper, sort_keys=True)})
    result = apply_deltas(model, [Delta("(new edit)", tensors, meta)])
    report("final", 0, t0, result.field_for(k))
    seconds = time.perf_counter() - started
    final = reports[-1]
    # Provenance only: none of these is part of the edit's fingerprint (delta.IDENTITY).
    meta.update(
        stages=json.dumps([dataclasses.asdict(r) for r in reports]),
        final_loss=repr(final.loss),
        photo_psnr=f"{final.psnr:.4f}",
        seconds=f"{seconds:.3f}",
        command="",
    )
    return FitResult(result, tensors, meta, final.loss, seconds, reports, k)
