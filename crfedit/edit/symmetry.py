"""An instance's mirror plane, and the mirror images of points, cells and cameras.

Most objects of a category are mirror-symmetric (a chair about its left–right plane), and a
part scribbled on one side usually has a twin on the other that one view hides or shows
edge-on: the far arm, the far legs.  The occupancy grid tells whether the instance is
symmetric and about which plane; a selection can then take the scribbles' mirror image as a
second, virtual view (:func:`mirror_camera`: the camera reflected, its image flipped
left–right) or take its own mirror image (:meth:`Mirror.grid`).  Measured in
docs/selection.md (*Mirror symmetry*).

The plane is searched among the grid's axis planes: for each axis, the grid flipped along it
and shifted by whole cells, the shift that makes the flipped grid cover most of the occupied
cells.  The overlaps of every shift along an axis are the diagonals of one slice-by-slice
product (:func:`mirror_overlaps`), so the search costs three small matrix products.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import occupancy
from ..cameras import Camera

MIN_OVERLAP = 0.85
"""A grid is mirror-symmetric when its mirror image covers at least this share of its occupied
cells.  The benchmark twin sources' best planes cover 0.77–0.96 (64³ grids of 10-minute
models: the grid's own noise keeps a symmetric chair below 1), their second-best axes
0.41–0.82; a five-legged swivel base, which has no mirror plane, 0.77–0.79."""
MAX_SHIFT = 8
"""The plane may lie up to this many cells (of a 64³ grid; scaled with the resolution) off the
grid's centre."""
TOLERANCE = 1.5
"""A mirrored surface point agrees with the original's mirror image when they lie within this
many cells of each other (:func:`agreeing`)."""
CONFLICT = 0.2
"""Scribbles whose mirror image lands on their keep strokes mean one side only: when more
than this share of the mirrored positives (or keep points) lies within :data:`TOLERANCE` of
a keep point (a positive), nothing is mirrored (:func:`conflict`)."""


@dataclass(frozen=True)
class Mirror:
    """The plane normalized coordinate ``axis`` = ``shift`` / ``res`` of a grid of ``res``³
    cells: cell i along ``axis`` mirrors to ``res`` − 1 − i + ``shift``."""

    axis: int
    shift: int
    res: int
    overlap: float
    """Share of the occupied cells the mirror image covers."""

    def grid(self, values: Tensor) -> Tensor:
        """``values`` [R, R, R] mirrored; cells mirrored from outside the grid are 0."""
        out = torch.roll(values.flip(self.axis), self.shift, self.axis)
        if self.shift > 0:
            out.narrow(self.axis, 0, self.shift).zero_()
        elif self.shift < 0:
            out.narrow(self.axis, self.res + self.shift, -self.shift).zero_()
        return out

    def normalized(self, xn: Tensor) -> Tensor:
        """Normalized points [..., 3] mirrored."""
        out = xn.clone()
        out[..., self.axis] = 2.0 * self.shift / self.res - xn[..., self.axis]
        return out

    def matrix(self, aabb: Tensor) -> np.ndarray:
        """The reflection in world coordinates of the scene box ``aabb`` [6], 4×4 float64."""
        lo, hi = (float(v) for v in aabb[[self.axis, self.axis + 3]].tolist())
        plane = lo + (self.shift / self.res + 1.0) * 0.5 * (hi - lo)
        m = np.eye(4)
        m[self.axis, self.axis], m[self.axis, 3] = -1.0, 2.0 * plane
        return m

    def points(self, aabb: Tensor, points: Tensor) -> Tensor:
        """World points [..., 3] mirrored."""
        m = torch.as_tensor(self.matrix(aabb), dtype=points.dtype, device=points.device)
        return points @ m[:3, :3].T + m[:3, 3]

    def cell(self, aabb: Tensor) -> float:
        """The world side of one of the grid's cells in box ``aabb`` (its largest side / ``res``):
        the tolerance within which a mirrored point meets its counterpart."""
        return occupancy.step_size(aabb, self.res, 1.0)


def mirror_overlaps(occupied: Tensor, axis: int, max_shift: int) -> Tensor:
    """[2·max_shift + 1]: for shifts −max_shift … max_shift, how many occupied cells of grid
    ``occupied`` [R, R, R] the grid flipped along ``axis`` and shifted by that many cells also
    occupies.  Slice i of the flipped, shifted grid is slice i − s of the flipped grid, so the
    count for shift s is the sum of diagonal −s of the slices' overlap matrix
    C[i, j] = |slice i of the grid ∩ slice j of the flipped grid|."""
    a = occupied.movedim(axis, 0).reshape(occupied.shape[axis], -1).float()
    c = a @ a.flip(0).T
    return torch.stack([torch.diagonal(c, offset=-s).sum() for s in range(-max_shift, max_shift + 1)])


def find_mirror(occupied: Tensor, min_overlap: float = MIN_OVERLAP) -> Mirror | None:
    """The axis plane about which grid ``occupied`` [R, R, R] is most nearly mirror-symmetric,
    when its mirror image covers at least ``min_overlap`` of the occupied cells; else None."""
    res, total = occupied.shape[-1], float(occupied.sum())
    if total == 0:
        return None
    max_shift = max(1, round(MAX_SHIFT * res / 64))
    best = None
    for axis in range(3):
        counts = mirror_overlaps(occupied, axis, max_shift)
        i = int(counts.argmax())
        share = float(counts[i]) / total
        if best is None or share > best.overlap:
            best = Mirror(axis, i - max_shift, res, share)
    return best if best.overlap >= min_overlap else None


def mirror_camera(camera: Camera, mirror: Mirror, aabb: Tensor) -> Camera:
    """The camera reflected about the plane, its x axis negated to stay right-handed: its pixel
    (i, j) looks along the mirror image of the original's ray through pixel (W − 1 − i, j), so
    it sees the mirror image of what the original sees, flipped left–right
    (:func:`mirror_image`).  Exact for the centred principal point of :mod:`..cameras`."""
    c2w = mirror.matrix(aabb) @ np.asarray(camera.c2w, dtype=np.float64)
    c2w[:3, 0] *= -1.0
    return dataclasses.replace(camera, c2w=c2w)


def mirror_image(image: np.ndarray | None) -> np.ndarray | None:
    """An image [H, W, ...] flipped left–right (None stays None)."""
    return None if image is None else np.ascontiguousarray(image[:, ::-1])


def agreeing(mirrored: Tensor, original: Tensor, cell: float) -> Tensor:
    """[H·W] bool: where the mirrored view's surface points ``mirrored`` [H·W, 3] lie within
    :data:`TOLERANCE` cells (of world size ``cell``) of ``original`` [H·W, 3], the original
    view's points mirrored and flipped to the mirrored view's pixels.  Elsewhere the instance is
    not symmetric there, or the mirrored view sees past what the original's surface hides."""
    return (mirrored - original).norm(dim=-1) <= TOLERANCE * cell


def conflict(mirrored: Tensor, others: Tensor, cell: float) -> float:
    """Share of the points ``mirrored`` [M, 3] within :data:`TOLERANCE` cells of any of
    ``others`` [N, 3] (0 when either is empty)."""
    if len(mirrored) == 0 or len(others) == 0:
        return 0.0
    near = torch.cat([torch.cdist(chunk, others).amin(dim=1) for chunk in mirrored.split(4096)])
    return float((near <= TOLERANCE * cell).float().mean())
