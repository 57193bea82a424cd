"""Binary raster masks (numpy [H, W] bool): square dilation and erosion, thick polylines.

Low in the data flow so that both the synthetic generator (data/) and the scribbles of the edits
(edit/) use them.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def as_mask(mask, what: str = "scribble") -> np.ndarray:
    """A mask a caller handed the library as a bool ndarray [H, W]: a NumPy or torch array (or
    nested lists) of bools, of integers (non-zero is set) or of floats (0.5 or more is set).
    Any other shape or type is one :class:`~crfedit.errors.CrfError` line naming ``what``."""
    from .errors import CrfError

    if hasattr(mask, "detach") and hasattr(mask, "cpu"):  # a torch tensor, without importing torch here
        mask = mask.detach().cpu().numpy()
    try:
        arr = np.asarray(mask)
    except (TypeError, ValueError):
        arr = np.asarray(None)
    if arr.ndim != 2 or arr.dtype.kind not in "biuf":
        raise CrfError(f"{what} mask: expected a [H, W] array of bools (or 0/1 numbers), got {type(mask).__name__} "
                       f"of shape {list(arr.shape)} and type {arr.dtype}")
    if arr.dtype.kind == "f":
        if not np.isfinite(arr).all():
            raise CrfError(f"{what} mask: holds NaN or infinite values")
        return arr >= 0.5
    return arr.astype(bool, copy=False)


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation by a (2r+1)² square; outside the image counts as off."""
    return _square(mask, radius, np.zeros_like, np.bitwise_or)


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary erosion by a (2r+1)² square; outside the image counts as off."""
    return _square(mask, radius, np.ones_like, np.bitwise_and)


def _square(mask: np.ndarray, radius: int, start, combine) -> np.ndarray:
    """``combine`` (in place) of the mask shifted to every offset of a (2r+1)² square, from ``start``."""
    if radius <= 0:
        return mask.copy()
    h, w = mask.shape
    padded = np.pad(mask, radius)
    out = start(mask)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            combine(out, padded[dy : dy + h, dx : dx + w], out=out)
    return out


def strokes_mask(shape: tuple[int, int], strokes: Sequence[np.ndarray], radius: float) -> np.ndarray:
    """Pixels whose centers lie within ``radius`` of any of the polylines ``strokes`` (each
    [K, 2] x, y, pixel units with (0, 0) the center of the top-left pixel).  A single point
    draws a dot.

    Shared by the generator's twin scribbles and the edit commands' ``--scribble-json`` strokes.
    Each segment is measured over the pixels of its box grown by ``radius`` alone (the same
    arithmetic per pixel, so the same bits as over the whole view), and a segment drawn again
    is skipped: the page's stroke requests within their limits took seconds.
    """
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    pix = np.stack([xx, yy], -1).astype(np.float64)  # [H, W, 2] pixel index coordinates
    mask = np.zeros(shape, bool)
    seen = set()
    for points in strokes:
        points = np.asarray(points, dtype=np.float64)
        for a, b in list(zip(points[:-1], points[1:])) or [(points[0], points[0])]:
            key = (*a.tolist(), *b.tolist())
            if key in seen:  # a segment drawn again adds nothing (20 000 points of one back-and-forth line took 4 s)
                continue
            seen.add(key)
            # only the pixels within ``radius`` of the segment's box can lie within it of the segment
            lo = np.floor(np.minimum(a, b) - radius) - 1
            hi = np.ceil(np.maximum(a, b) + radius) + 1
            x0, y0 = int(max(lo[0], 0)), int(max(lo[1], 0))
            x1, y1 = int(min(hi[0] + 1, shape[1])), int(min(hi[1] + 1, shape[0]))
            if x0 >= x1 or y0 >= y1:
                continue
            win = pix[y0:y1, x0:x1]
            ab = b - a
            s = np.clip(((win - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            mask[y0:y1, x0:x1] |= np.linalg.norm(win - (a + s[..., None] * ab), axis=-1) <= radius
    return mask


def mask_digest(mask: np.ndarray | None) -> str | None:
    """16 hex digits naming a mask's pixels and size (None for no mask): what an edit file
    records of the scribble it was made from, so a re-run from other strokes shows."""
    if mask is None:
        return None
    import hashlib

    mask = np.asarray(mask, dtype=bool)
    return hashlib.sha256(f"{mask.shape}".encode() + np.packbits(mask).tobytes()).hexdigest()[:16]
