"""Images for looking at, not measuring: a colour-mapped depth preview."""

from __future__ import annotations

import numpy as np

# Turbo colour map as degree-5 polynomials per channel (Google's fit, max error below 1/255·3)
_TURBO = np.array([
    [0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
    [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
    [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973],
])


def turbo(t: np.ndarray) -> np.ndarray:
    """Turbo colour of ``t`` in [0, 1] → RGB [..., 3] in [0, 1] (0 dark blue, 0.5 green, 1 dark red)."""
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    powers = np.stack([t**k for k in range(6)], axis=-1)
    return np.clip(powers @ _TURBO.T, 0.0, 1.0)


def depth_preview(depth: np.ndarray, opacity: np.ndarray, min_opacity: float = 0.5) -> np.ndarray:
    """RGB [H, W, 3]: near surfaces red, far ones blue (turbo over the view's own depth range),
    white where ``opacity`` < ``min_opacity`` or the depth is not finite."""
    depth = np.asarray(depth, np.float64)
    hit = (np.asarray(opacity) >= min_opacity) & np.isfinite(depth)
    out = np.ones(depth.shape + (3,))
    if hit.any():
        lo, hi = depth[hit].min(), depth[hit].max()
        t = (hi - depth[hit]) / max(hi - lo, 1e-12)
        out[hit] = turbo(t)
    return out
