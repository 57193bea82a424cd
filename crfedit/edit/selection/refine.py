"""Refining a selection over the occupancy grid: smoothing over occupied neighbours (plain or
bilateral), rim filling, hysteresis and connected components."""

from __future__ import annotations

import itertools
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from ... import occupancy


def smooth_over_occupied(values: Tensor, occupied: Tensor) -> Tensor:
    """Mean of ``values`` [R, R, R] over each occupied cell's occupied 3×3×3 neighbourhood.

    Pooled over the occupied cells' bounding box one cell wider (:func:`occupied_slices`), not
    the whole grid: every occupied cell's window lies in it, or ends at the grid's edge as it
    would, so the result is the same bits (a test) in a third of the time on a chair."""
    out = torch.zeros_like(values)
    box = occupied_slices(occupied)
    if box is None:
        return out
    occupied, values = occupied[box], values[box]
    num = F.avg_pool3d((values * occupied)[None, None], 3, stride=1, padding=1, count_include_pad=False)
    den = F.avg_pool3d(occupied.float()[None, None], 3, stride=1, padding=1, count_include_pad=False)
    out[box] = torch.where(occupied, (num / den.clamp_min(1e-12))[0, 0], torch.zeros_like(values))
    return out


def occupied_slices(occupied: Tensor, margin: int = 1) -> tuple[slice, slice, slice] | None:
    """The slices of the occupied cells' bounding box in ``occupied`` [D, H, W], ``margin``
    cells wider on each side within the grid; None when no cell is occupied."""
    box = []
    for axis in range(3):
        hit = occupied.any(dim=tuple(a for a in range(3) if a != axis)).nonzero().squeeze(-1)
        if hit.numel() == 0:
            return None
        box.append(slice(max(int(hit[0]) - margin, 0), int(hit[-1]) + 1 + margin))
    return tuple(box)


def neighbour_table(cells: Tensor, res: int | Sequence[int], half: bool = False) -> Tensor:
    """For each of the flat cell indices ``cells`` [N] (ascending) of an [R, R, R] grid (or a
    grid of shape ``res``), the positions in ``cells`` of its 26 neighbours, −1 where a
    neighbour is not among them.  [N, 26]; with ``half`` the first 13 columns only, whose
    opposites are the other 13 (each pair of neighbours once).  [N, 13]

    The cells' positions written into a grid padded by one empty cell on each side, and read
    back at each cell's flat index plus the 26 offsets' flat steps: no neighbour falls off the
    grid, so none needs a bounds test."""
    shape = (res,) * 3 if isinstance(res, int) else tuple(res)
    d, h, w = (n + 2 for n in shape)
    index = torch.full((d * h * w,), -1, dtype=torch.long, device=cells.device)
    padded = ((cells // (shape[1] * shape[2]) + 1) * h + cells // shape[2] % shape[1] + 1) * w + cells % shape[2] + 1
    index[padded] = torch.arange(cells.numel(), device=cells.device)
    steps = torch.tensor([(a * h + b) * w + c for a, b, c in NEIGHBOUR_OFFSETS[: 13 if half else 26]], device=cells.device)
    at = steps[:, None] + padded[None]  # [26, N]: laid out offset by offset, as bilateral_smooth reads it
    return occupancy.gather_flat(index, at).T


NEIGHBOUR_OFFSETS = [o for o in itertools.product((-1, 0, 1), repeat=3) if any(o)]
"""The 26 neighbour offsets in :func:`neighbour_table`'s column order; column j's opposite is
column 25 − j."""


def bilateral_smooth(values: Tensor, features: Tensor, neighbours: Tensor, bandwidth: float, rounds: int) -> Tensor:
    """``rounds`` times, each cell's value [N] blended half-and-half with the mean over itself and
    its occupied neighbours (``neighbours`` from :func:`neighbour_table`), a neighbour weighing
    exp(−d²/2h²) for d the distance between the two cells' ``features`` [N, F] and h
    ``bandwidth`` (the cell itself weighs 1).  With h → ∞ one round is
    :func:`smooth_over_occupied`'s blend."""
    columns = neighbours.T  # [26, N]: contiguous as neighbour_table makes it, one row per offset
    valid = columns >= 0
    columns = columns.clamp_min(0)
    # d² is symmetric: the distance to the neighbour in row 25 − j is that neighbour's distance
    # in row j, so half the rows are computed and the others gathered
    w = features.new_empty(columns.shape)
    for j in range(13):
        torch.sum(features.index_select(0, columns[j]).sub_(features).square_(), dim=-1, out=w[j])
    w[13:] = w[:13].flip(0).gather(1, columns[13:])
    # exp(−60) ≈ 10⁻²⁶ weighs nothing beside the cell's own 1, and the clamp keeps exp off
    # float32's subnormal range, where it is ten times slower
    w.div_(-2.0 * bandwidth**2).clamp_min_(-60.0).exp_().mul_(valid)
    total = 1.0 + w.sum(dim=0)
    flat = columns.reshape(-1)
    for _ in range(rounds):
        values = 0.5 * (values + (values + (w * values.index_select(0, flat).view_as(w)).sum(dim=0)) / total)
    return values


def fill_rims(values: Tensor, at: float, occupied: Tensor, kept: Tensor, share: float) -> Tensor:
    """``values`` [R, R, R] with every occupied cell outside ``kept`` raised to ``at`` where at
    least ``share`` of its occupied 3×3×3 neighbourhood (itself included) has value ≥ ``at``.

    One pass, so the selection grows by at most one cell, and only where it surrounds a cell:
    the rim of a selected slab (a cell whose occupied neighbours are the slab) joins it, a cell
    of a bulky part that the slab merely touches (most of its occupied neighbours its own
    part's) does not."""
    sel = (values >= at) & occupied
    fill = surrounded_by(sel, occupied, share) & ~sel & ~kept
    return torch.where(fill, values.clamp_min(at), values)


def surrounded_by(selected: Tensor, occupied: Tensor, share: float) -> Tensor:
    """[R, R, R] bool: the occupied cells at least ``share`` of whose occupied 3×3×3
    neighbourhood (itself included) is ``selected`` (a cell's share among the cells around it:
    :func:`fill_rims` and a removal's skin, ``supervised.removal_cells``)."""
    return occupied & (smooth_over_occupied(selected.float(), occupied) >= share - 1e-6)


def hysteresis(values: Tensor, seeds: Tensor, high: float, low: float) -> Tensor:
    """``values`` [R, R, R] with the cells reached from ``seeds`` through cells of value ≥
    ``low`` raised to at least ``high`` and every other cell capped just below ``high``."""
    return raised(values, connected_to(values >= low, seeds), high)


def raised(values: Tensor, reached: Tensor, high: float) -> Tensor:
    """``values`` [R, R, R] raised to at least ``high`` in the cells of ``reached`` and capped
    just below ``high`` everywhere else (:func:`hysteresis`' last step)."""
    return torch.where(reached, values.clamp_min(high), values.clamp(max=high * 0.999))


def components(selected: Tensor) -> Tensor:
    """The connected pieces (26-neighbourhood) of ``selected`` [D, H, W]: each selected cell
    labelled with 1 + the largest flat index in its piece, every other cell with 0.  [D, H, W]
    long

    Over the selected cells only (their :func:`neighbour_table`), each cell pointing at a cell
    of its piece (a larger one, or itself: a root).  Each round hooks every root onto the
    largest root beside any cell pointing at it, then follows the pointers to their roots
    (pointer jumping), so a piece of n cells settles in about log₂ n rounds, not its diameter."""
    out = torch.zeros(selected.shape, dtype=torch.long, device=selected.device)
    cells = selected.reshape(-1).nonzero().squeeze(-1)
    if cells.numel() == 0:
        return out
    nb = neighbour_table(cells, selected.shape, half=True)
    one, column = (nb >= 0).nonzero(as_tuple=True)  # each pair of neighbouring selected cells once
    other = nb[one, column]
    src, dst = torch.cat([one, other]), torch.cat([other, one])
    label = torch.arange(cells.numel(), device=cells.device)  # positions in cells, ascending as the flat indices
    while True:
        beside = label.scatter_reduce(0, src, label[dst], "amax")  # the largest label beside a cell, or its own
        grown = label.scatter_reduce(0, label, beside, "amax")  # hook: a root takes the largest root beside its cells
        while True:
            jumped = grown[grown]
            if torch.equal(jumped, grown):
                break
            grown = jumped
        if torch.equal(grown, label):
            break
        label = grown
    out.view(-1)[cells] = cells[label] + 1
    return out


def large_pieces(selected: Tensor, least: float) -> tuple[Tensor, int]:
    """(the cells [D, H, W] bool of the connected pieces of ``selected`` (26-neighbourhood,
    :func:`components`) that hold at least ``least`` cells, how many pieces those are).  No
    piece is sought when ``selected`` holds fewer cells than that in all (most selections:
    a few specks)."""
    if int(selected.sum()) < max(least, 1):
        return torch.zeros_like(selected), 0
    label = components(selected).reshape(-1)
    ids, piece, count = torch.unique(label, return_inverse=True, return_counts=True)
    large = (count >= least) & (ids > 0)
    return large[piece].view(selected.shape), int(large.sum())


def connected_to(selected: Tensor, seeds: Tensor) -> Tensor:
    """Cells of ``selected`` [R, R, R] reachable from ``seeds`` through selected cells
    (26-neighbourhood), grown within the selected cells' bounding box."""
    out = torch.zeros_like(selected, dtype=torch.bool)
    box = occupied_slices(selected, margin=0)
    if box is None:
        return out
    inside = selected[box]
    reached = seeds[box] & inside
    while True:
        grown = occupancy.dilate(reached, 1) & inside
        if torch.equal(grown, reached):
            break
        reached = grown
    out[box] = reached
    return out
