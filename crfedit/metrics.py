"""Image quality metrics: PSNR, SSIM and LPIPS as small pure functions.

Images are ``[..., H, W, C]`` arrays (torch tensors or NumPy arrays, C = 3 for RGB) with values
in ``[0, max_val]``; every metric is computed per image and returns a tensor of the leading
shape ``[...]``.  PSNR and SSIM are computed in float64 whatever the input dtype; LPIPS in
float32 (as its reference implementation does).

LPIPS needs pretrained network weights that no package reachable here ships.  They are read from
a local safetensors file (``--lpips-weights PATH`` or the ``CRFEDIT_LPIPS_WEIGHTS`` environment
variable); without one, :func:`lpips` returns ``None`` and :func:`lpips_unavailable_reason` says
why, so a table prints ``LPIPS: skipped (no weights)``.  No other metric is ever reported under
the LPIPS name.
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .errors import CrfError

LPIPS_ENV = "CRFEDIT_LPIPS_WEIGHTS"

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _as_tensor(image, dtype: torch.dtype | None = None) -> Tensor:
    if isinstance(image, Tensor):
        t = image
    else:
        a = np.asarray(image)
        t = torch.as_tensor(a if a.flags.writeable else a.copy())  # an array read from PIL is read-only: torch warned
    return t.to(dtype) if dtype is not None else t


def _unit_range(images, what: str) -> None:
    """Refuse ``images`` that are not floats in [0, 1] (uint8 ones scored −36 dB)."""
    for i, image in enumerate(images):
        t = _as_tensor(image)
        if not (t.is_floating_point() or t.dtype == torch.bool):
            raise CrfError(f"{what} {i}: values are {str(t.dtype).replace('torch.', '')}; give floats in [0, 1] (8-bit images divided by 255)")
        if t.numel() and not bool(torch.isfinite(t).all()):
            raise CrfError(f"{what} {i}: holds NaN or infinite values; give floats in [0, 1]")
        if t.numel() and (float(t.min()) < -1e-3 or float(t.max()) > 1 + 1e-3):
            raise CrfError(f"{what} {i}: values span {float(t.min()):.4g}…{float(t.max()):.4g}; give floats in [0, 1]")


def _check_pair(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape:
        raise ValueError(f"image shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.ndim < 3:
        raise ValueError(f"expected images of shape [..., H, W, C], got {tuple(pred.shape)}")
    if pred.shape[-3] == 0 or pred.shape[-2] == 0 or pred.shape[-1] == 0:
        raise ValueError(f"empty image of shape {tuple(pred.shape)}")


# --------------------------------------------------------------------------------------------
# PSNR


def mse_to_psnr(mse, max_val: float = 1.0):
    """PSNR in dB from a mean squared error: ``10 · log10(max_val² / mse)``.

    ``mse = 0`` gives ``+inf``.  A tensor comes back as a tensor of its own dtype (gradients
    flow, so training logs can use it); a Python or NumPy number comes back as a ``float``.
    Example: ``mse_to_psnr(0.01) == 20.0``.
    """
    if isinstance(mse, Tensor):
        return 10.0 * torch.log10(max_val**2 / mse)
    mse = float(mse)
    return math.inf if mse == 0.0 else 10.0 * math.log10(max_val**2 / mse)


def psnr(pred, target, max_val: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio per image, in dB, float64.

    pred, target: ``[..., H, W, C]``; returns ``[...]``.  The MSE is averaged over the
    H·W·C values of each image, so ``PSNR = 10 · log10(max_val² / mse)``.  Identical images give
    ``+inf`` — it is not capped; tables print ``inf``, and a mean over images that contains one
    is ``inf`` too.  Example: ``target + 0.1`` everywhere → mse 0.01 → exactly 20 dB.
    """
    pred, target = _as_tensor(pred, torch.float64), _as_tensor(target, torch.float64)
    _check_pair(pred, target)
    mse = (pred - target).square().mean(dim=(-3, -2, -1))
    return mse_to_psnr(mse, max_val)


# --------------------------------------------------------------------------------------------
# SSIM


def gaussian_window_1d(size: int, sigma: float = SSIM_SIGMA) -> Tensor:
    """Normalized 1-D Gaussian taps ``exp(-(i - r)² / 2σ²) / Σ``, i = 0..size-1, r = size // 2.

    The 2-D SSIM window is the outer product of this with itself, which equals MATLAB's
    ``fspecial('gaussian', size, sigma)`` and SciPy's ``gaussian_filter`` kernel for
    ``size = 2·round(3.5σ) + 1`` (11 for σ = 1.5).
    """
    i = torch.arange(size, dtype=torch.float64) - (size // 2)
    g = torch.exp(-(i**2) / (2.0 * sigma**2))
    return g / g.sum()


def ssim_window_size(height: int, width: int) -> int:
    """11, or the largest odd size that fits inside a smaller image (1 for a 1- or 2-px side)."""
    side = min(height, width, SSIM_WINDOW)
    return side if side % 2 == 1 else side - 1


def ssim(pred, target, max_val: float = 1.0) -> Tensor:
    """Structural similarity (Wang, Bovik, Sheikh & Simoncelli 2004) per image, float64.

    pred, target: ``[..., H, W, C]``; returns ``[...]``, the mean of the SSIM map over the valid
    pixels and the C channels.  Per channel, with ``w`` an 11×11 Gaussian window of σ = 1.5
    (weights summing to 1) applied as a *valid* convolution (no padding: the map is
    ``(H-10) × (W-10)``)::

        μx = w∗x,   σx² = w∗x² − μx²,   σxy = w∗(x·y) − μx·μy,   (likewise μy, σy²)
        SSIM = (2μxμy + C1)(2σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2))
        C1 = (0.01·max_val)²,  C2 = (0.03·max_val)²

    The (co)variances are the window-weighted population moments (no N/(N−1) correction).  This
    is exactly ``skimage.metrics.structural_similarity(x, y, channel_axis=-1, data_range=max_val,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False)`` (whose reflect-padded
    filtering followed by a 5-pixel border crop equals the valid convolution here), and Wang's
    reference ``ssim_index.m`` per channel without its automatic downsampling.

    An image smaller than 11 px on a side uses the largest odd window that fits
    (:func:`ssim_window_size`) with the same σ = 1.5 Gaussian truncated to it and renormalized;
    for a side of 1 or 2 px that is a single pixel, where SSIM becomes the per-pixel luminance
    term ``(2xy + C1) / (x² + y² + C1)``.

    Example: two constant images a and b have zero variances, so
    ``SSIM = (2ab + C1) / (a² + b² + C1)``.
    """
    pred, target = _as_tensor(pred, torch.float64), _as_tensor(target, torch.float64)
    _check_pair(pred, target)
    *lead, height, width, channels = pred.shape
    size = ssim_window_size(height, width)
    g = gaussian_window_1d(size).to(pred.device)

    def blur(t: Tensor) -> Tensor:  # [N, 1, H, W] -> [N, 1, H-size+1, W-size+1]
        t = F.conv2d(t, g.view(1, 1, size, 1))
        return F.conv2d(t, g.view(1, 1, 1, size))

    def planes(t: Tensor) -> Tensor:  # [..., H, W, C] -> [N·C, 1, H, W]
        return t.reshape(-1, height, width, channels).permute(0, 3, 1, 2).reshape(-1, 1, height, width)

    x, y = planes(pred), planes(target)
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x * mu_x
    var_y = blur(y * y) - mu_y * mu_y
    cov_xy = blur(x * y) - mu_x * mu_y
    c1 = (SSIM_K1 * max_val) ** 2
    c2 = (SSIM_K2 * max_val) ** 2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))
    per_image = ssim_map.reshape(-1, channels, ssim_map.shape[-2] * ssim_map.shape[-1]).mean(dim=(1, 2))
    return per_image.reshape(lead)


# --------------------------------------------------------------------------------------------
# LPIPS (AlexNet, v0.1)

# The five AlexNet conv layers LPIPS reads (torchvision's ``features`` indices 0, 3, 6, 8, 10),
# each followed by a ReLU whose output is one of the five compared feature maps; a 3×3/2 max-pool
# precedes conv 2 and conv 3.  (out, in, kernel, stride, padding)
_ALEX_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1))
_ALEX_INDEX = (0, 3, 6, 8, 10)
# LPIPS's ScalingLayer: inputs in [-1, 1] are mapped with (x - shift) / scale.
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
LPIPS_MIN_SIZE = 31
"""Smallest image side AlexNet's strides and two max-pools leave non-empty (conv1 → ≥ 7 px)."""


def lpips_tensor_names() -> dict[str, tuple[int, ...]]:
    """The tensors an LPIPS weights file must hold, with their shapes (canonical names).

    These are the keys of ``lpips.LPIPS(net="alex", version="0.1").state_dict()``::

        net.slice1.0.weight  [64, 3, 11, 11]    net.slice1.0.bias  [64]
        net.slice2.3.weight  [192, 64, 5, 5]    net.slice2.3.bias  [192]
        net.slice3.6.weight  [384, 192, 3, 3]   net.slice3.6.bias  [384]
        net.slice4.8.weight  [256, 384, 3, 3]   net.slice4.8.bias  [256]
        net.slice5.10.weight [256, 256, 3, 3]   net.slice5.10.bias [256]
        lin0.model.1.weight  [1, 64, 1, 1]      lin1.model.1.weight [1, 192, 1, 1]
        lin2.model.1.weight  [1, 384, 1, 1]     lin3.model.1.weight [1, 256, 1, 1]
        lin4.model.1.weight  [1, 256, 1, 1]

    ``safetensors.torch.save_model(lpips.LPIPS(net="alex"), path)`` writes exactly these (plus
    ``scaling_layer.*``; it drops the ``lins.K.*`` duplicates that ``state_dict()`` also holds).
    Also accepted: torchvision's AlexNet names for the backbone (``features.0.weight`` …
    ``features.10.bias``) in place of ``net.sliceK.N.*``, and ``lins.K.model.1.weight`` in place
    of ``linK.model.1.weight``.  Other tensors in the file (``scaling_layer.*`` — its values are
    LPIPS's fixed constants —, ``classifier.*``) are ignored.
    """
    names: dict[str, tuple[int, ...]] = {}
    for k, ((out, inp, ks, _, _), idx) in enumerate(zip(_ALEX_CONVS, _ALEX_INDEX)):
        names[f"net.slice{k + 1}.{idx}.weight"] = (out, inp, ks, ks)
        names[f"net.slice{k + 1}.{idx}.bias"] = (out,)
    for k, (out, *_rest) in enumerate(_ALEX_CONVS):
        names[f"lin{k}.model.1.weight"] = (1, out, 1, 1)
    return names


def _aliases(name: str) -> tuple[str, ...]:
    """Other names a tensor may carry: torchvision's ``features.N.*``, LPIPS's ``lins.K.*`` list."""
    if name.startswith("net.slice"):
        return ("features." + name.split(".", 2)[2],)
    if name.startswith("lin"):
        return ("lins." + name[3:],)
    return ()


def lpips_weights_path(weights_path: str | os.PathLike | None = None) -> Path | None:
    """The configured weights file: ``weights_path`` if given, else ``$CRFEDIT_LPIPS_WEIGHTS``, else None."""
    if weights_path is not None and str(weights_path) != "":
        return Path(weights_path)
    env = os.environ.get(LPIPS_ENV, "")
    return Path(env) if env else None


def lpips_unavailable_reason(weights_path: str | os.PathLike | None = None) -> str | None:
    """Why LPIPS cannot be computed (one line), or None when a weights file is configured and exists."""
    path = lpips_weights_path(weights_path)
    if path is None:
        return f"no weights (pass --lpips-weights PATH or set {LPIPS_ENV} to an LPIPS-AlexNet .safetensors file)"
    if not path.is_file():
        origin = "--lpips-weights" if weights_path not in (None, "") else LPIPS_ENV
        return f"{origin} {path}: file not found"
    return None


def lpips_available(weights_path: str | os.PathLike | None = None) -> bool:
    """True when a weights file is configured and exists (its contents are checked on load)."""
    return lpips_unavailable_reason(weights_path) is None


def load_lpips_weights(path: str | os.PathLike) -> dict[str, Tensor]:
    """Read and validate an LPIPS-AlexNet safetensors file; return tensors by canonical name.

    A missing file, a file safetensors cannot parse, a missing tensor, a wrong shape or a
    non-finite value is a one-line :class:`CrfError` naming the file.
    """
    path = Path(path)
    stat = path.stat() if path.is_file() else None
    if stat is None:
        raise CrfError(f"{path}: LPIPS weights file not found")
    return dict(_load_lpips_cached(str(path.resolve()), stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=2)
def _load_lpips_cached(path: str, _mtime_ns: int, _size: int) -> dict[str, Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        raw = load_file(path, device="cpu")
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise CrfError(f"{path}: not a readable safetensors file ({e.__class__.__name__})") from None
    weights: dict[str, Tensor] = {}
    missing = []
    for name, shape in lpips_tensor_names().items():
        tensor = next((raw[n] for n in (name, *_aliases(name)) if n in raw), None)
        if tensor is None:
            missing.append(name)
            continue
        if tuple(tensor.shape) != shape:
            raise CrfError(f"{path}: LPIPS tensor {name} has shape {list(tensor.shape)}, expected {list(shape)}")
        if not tensor.is_floating_point() or not bool(torch.isfinite(tensor).all()):
            raise CrfError(f"{path}: LPIPS tensor {name} is not finite floating point")
        weights[name] = tensor.to(torch.float32)
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise CrfError(
            f"{path}: not an LPIPS-AlexNet weights file: missing {', '.join(missing[:3])}{more} "
            "(expected the keys of lpips.LPIPS(net='alex').state_dict())"
        )
    return weights


def _lpips_features(x: Tensor, w: dict[str, Tensor]) -> list[Tensor]:
    """AlexNet relu1..relu5 feature maps of ``x`` [N, 3, H, W] (already scaled)."""
    feats = []
    for k, ((_, _, _, stride, pad), idx) in enumerate(zip(_ALEX_CONVS, _ALEX_INDEX)):
        if k in (1, 2):
            x = F.max_pool2d(x, kernel_size=3, stride=2)
        x = F.relu(F.conv2d(x, w[f"net.slice{k + 1}.{idx}.weight"], w[f"net.slice{k + 1}.{idx}.bias"], stride=stride, padding=pad))
        feats.append(x)
    return feats


def lpips_from_weights(pred, target, weights: dict[str, Tensor], chunk: int = 8) -> Tensor:
    """LPIPS-AlexNet v0.1 distance per image with given weights (see :func:`load_lpips_weights`).

    pred, target: ``[..., H, W, 3]`` in [0, 1], H and W ≥ 31; returns float32 ``[...]``.
    Each image is mapped to [-1, 1], then ``(x − shift) / scale``; for each AlexNet ReLU output
    ``f_l`` (l = 1..5) the features are unit-normalized over channels
    (``f / (‖f‖₂ + 1e-10)``), and ``d = Σ_l mean_hw( lin_l · (f̂_l(pred) − f̂_l(target))² )``,
    ``lin_l`` a 1×1 convolution to one channel without bias.  Identical images give 0.
    """
    pred, target = _as_tensor(pred, torch.float32), _as_tensor(target, torch.float32)
    _check_pair(pred, target)
    *lead, height, width, channels = pred.shape
    if channels != 3:
        raise ValueError(f"LPIPS needs RGB images [..., H, W, 3], got {tuple(pred.shape)}")
    if min(height, width) < LPIPS_MIN_SIZE:
        raise CrfError(f"LPIPS needs images of at least {LPIPS_MIN_SIZE}×{LPIPS_MIN_SIZE} pixels, got {height}×{width}")
    w = {k: v.to(pred.device) for k, v in weights.items()}
    shift = torch.tensor(_LPIPS_SHIFT, dtype=torch.float32, device=pred.device).view(1, 3, 1, 1)
    scale = torch.tensor(_LPIPS_SCALE, dtype=torch.float32, device=pred.device).view(1, 3, 1, 1)

    def prepare(t: Tensor) -> Tensor:  # [n, H, W, 3] in [0, 1] -> [n, 3, H, W] scaled
        return ((t.permute(0, 3, 1, 2) * 2.0 - 1.0) - shift) / scale

    a_all = pred.reshape(-1, height, width, 3)
    b_all = target.reshape(-1, height, width, 3)
    out = []
    for start in range(0, a_all.shape[0], chunk):
        fa = _lpips_features(prepare(a_all[start : start + chunk]), w)
        fb = _lpips_features(prepare(b_all[start : start + chunk]), w)
        total = 0.0
        for k, (a, b) in enumerate(zip(fa, fb)):
            a = a / (a.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            b = b / (b.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            total = total + F.conv2d((a - b).square(), w[f"lin{k}.model.1.weight"]).mean(dim=(1, 2, 3))
        out.append(total)
    return torch.cat(out).reshape(lead)


def lpips(pred, target, weights_path: str | os.PathLike | None = None) -> Tensor | None:
    """LPIPS-AlexNet distance per image ``[...]``, or ``None`` when no weights file is configured.

    The weights come from ``weights_path`` (the CLI's ``--lpips-weights``), else the
    ``CRFEDIT_LPIPS_WEIGHTS`` environment variable; :func:`lpips_unavailable_reason` tells the
    caller what to print when this returns ``None``.  A configured path that does not exist or
    does not hold valid weights is a :class:`CrfError`, not a silent skip.
    """
    path = lpips_weights_path(weights_path)
    if path is None:
        return None
    reason = lpips_unavailable_reason(weights_path)
    if reason is not None:
        raise CrfError(reason)
    return lpips_from_weights(pred, target, load_lpips_weights(path))


# --------------------------------------------------------------------------------------------
# Tables


def score_images(
    preds: Sequence | Tensor | np.ndarray,
    targets: Sequence | Tensor | np.ndarray,
    lpips_weights: str | os.PathLike | None = None,
) -> dict:
    """Mean PSNR, SSIM and LPIPS over a set of image pairs, for evaluation tables.

    preds, targets: sequences of ``[H, W, 3]`` images (sizes may differ between pairs) or
    stacked ``[N, H, W, 3]`` arrays, floats in [0, 1] (others are refused: :class:`CrfError`).  Returns::

        {"n": N, "psnr": mean dB (inf if any pair is identical), "ssim": mean,
         "lpips": mean or None, "lpips_note": None or why LPIPS was skipped}

    PSNR is averaged per image in dB (the NeRF-literature convention), not computed from the
    pooled MSE.  LPIPS is skipped (``None`` with a note) when no weights are configured or an
    image is smaller than 31 px; a configured but invalid weights file raises :class:`CrfError`.
    """
    if len(preds) != len(targets):
        raise ValueError(f"{len(preds)} predictions for {len(targets)} targets")
    if len(preds) == 0:
        raise ValueError("no images to score")
    _unit_range(preds, "prediction")
    _unit_range(targets, "target")
    path = lpips_weights_path(lpips_weights)
    weights, note = None, None
    if path is None:
        note = lpips_unavailable_reason(lpips_weights)
    else:
        reason = lpips_unavailable_reason(lpips_weights)
        if reason is not None:
            raise CrfError(reason)
        weights = load_lpips_weights(path)
        if min(min(_as_tensor(p).shape[-3:-1]) for p in preds) < LPIPS_MIN_SIZE:
            weights, note = None, f"images smaller than {LPIPS_MIN_SIZE}×{LPIPS_MIN_SIZE} px"
    psnrs, ssims, lpipses = [], [], []
    for pred, target in zip(preds, targets):
        psnrs.append(float(psnr(pred, target)))
        ssims.append(float(ssim(pred, target)))
        if weights is not None:
            lpipses.append(float(lpips_from_weights(pred, target, weights)))
    return {
        "n": len(psnrs),
        "psnr": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "lpips": float(np.mean(lpipses)) if lpipses else None,
        "lpips_note": note,
    }
