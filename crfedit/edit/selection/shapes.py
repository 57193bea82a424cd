"""The shape gate: orientation tests between the occupied cells' local frames and the scribbled
points' (lines at odds with the scribble, sheets, rims), which keep a removal's joins from
taking parts of another shape."""

from __future__ import annotations

import torch
from torch import Tensor

from .features import Frames
from .refine import components

SHAPE_CLASH = 0.25
""":func:`odd_lines`: a cell and a scribbled point agree in orientation where their clash (the
squared sine of the angle between them) is at most this: within 30°."""
SHAPE_AGREE = 0.25
""":func:`odd_lines`: a line is at odds with the scribble where it agrees with fewer than this
share of the scribbled points."""
SHAPE_LINE = 0.5
""":func:`odd_lines`: a cell is a line where its linearity is at least this and its planarity."""
JOIN_LINES = 0.5
""":attr:`SelectOptions.join_lines` and :attr:`SelectOptions.line_negatives` run when at least this
share of the scribbled points lie on lines."""
RIM_SHEETS = 0.5
""":attr:`SelectOptions.rim_fill` runs when at least this share of the scribbled points lie on sheets."""
SHAPE_GATE_POINTS = 512
""":attr:`SelectOptions.shape_gate` compares the cells with at most this many scribbled points,
evenly spaced (the comparison is cells × points)."""
BARS_RADIUS = 3
"""The block whether the scribble lies on bars (:data:`JOIN_LINES`; the share
:attr:`SelectOptions.sheet_veto` compares too) is read in: (2r + 1)³ cells, one wider than
:data:`SHAPE_GATE_RADIUS`.  A square leg 3–4 cells thick at 64³ is no
line in a 5³ block: 5 of the 9 procedural chairs' leg scribbles read at 0.14–0.39 of their
points on lines there, at 7³ at 0.80–1.0, while every seat, back and shell scribble of the
benchmark stays at 0–0.09 (`chair_009`'s back frame 0.71 → 0.92).  Measured (edit seed 0):
the 16-twin benchmark's recolours and removals and the frame recolours of
``benchmarks/frame_recolours.py`` the same to the bit on all six models; every chair's legs
(``--part legs``) gap closed 0.733 → 0.859 (`g_p0`) and 0.606 → 0.756 (`g_p1`)."""
SHAPE_GATE_RADIUS = 2
"""The block :func:`odd_lines` reads the orientation in: at 3³ cells half a chair's legs
(two cells thick) read as lines, at 5³ nine in ten do."""


def shape_agreement(cells: Frames, points: Frames, chunk: int = 8192) -> Tensor:
    """Each cell's share of ``points`` whose orientation it agrees with, their clash at most
    :data:`SHAPE_CLASH`.  Each counts as a line or a sheet, whichever of its linearity and
    planarity is larger, and the clash is the squared sine of the angle between the two lines
    or the two normals, or the squared cosine between the line and the normal: 0 where they
    agree (a line along a line, a sheet parallel to a sheet, a line lying in a sheet such as a
    panel's rim), 1 where they are square (a leg under a stretcher, under a seat).  [N]"""
    p_line = (points.linear >= points.planar)[None]
    c_line = cells.linear >= cells.planar
    out = []
    for lo in range(0, len(c_line), chunk):
        cu, cn = cells.direction[lo : lo + chunk], cells.normal[lo : lo + chunk]
        line_vs = torch.where(p_line, 1 - (cu @ points.direction.T) ** 2, (cu @ points.normal.T) ** 2)
        sheet_vs = torch.where(p_line, (cn @ points.direction.T) ** 2, 1 - (cn @ points.normal.T) ** 2)
        clash = torch.where(c_line[lo : lo + chunk, None], line_vs, sheet_vs)
        out.append((clash <= SHAPE_CLASH).float().mean(dim=1))
    return torch.cat(out) if out else cells.linear.new_zeros(0)


def lines_of(frames: Frames) -> Tensor:
    """[N] bool: the points on a line, linearity at least :data:`SHAPE_LINE` and the planarity."""
    return (frames.linear >= frames.planar) & (frames.linear >= SHAPE_LINE)


def odd_lines(cells: Frames, points: Frames) -> Tensor:
    """[N] bool: the cells that are lines (:func:`lines_of`) and agree in orientation with
    fewer than :data:`SHAPE_AGREE` of the scribbled ``points`` (:func:`shape_agreement`)."""
    line = lines_of(cells)
    odd = torch.zeros_like(line)
    odd[line] = shape_agreement(Frames(*(f[line] for f in cells)), points) < SHAPE_AGREE  # the lines' agreement only
    return odd


SHEET_PLANAR = 0.7
""":func:`sheets_of`: a cell is a sheet where its planarity is at least this and its linearity
(at 0.5 a tube running along a panel's edge read as a sheet: the real `modern_armchair`'s
frame removal 0.77 → 0.68, at 0.6 0.70)."""


def sheets_of(frames: Frames) -> Tensor:
    """[N] bool: the points on a sheet, planarity at least :data:`SHEET_PLANAR` and above the linearity."""
    return (frames.planar > frames.linear) & (frames.planar >= SHEET_PLANAR)


def rim_lines(cells: Frames, points: Frames, share: float) -> Tensor:
    """[N] bool: the cells that are lines (:func:`lines_of`) lying in the plane (within 30°,
    :data:`SHAPE_CLASH`) of at least ``share`` of the ``points`` that are sheets
    (:attr:`SelectOptions.rim_fill`); none when no point is a sheet."""
    sheets = points.planar > points.linear
    line = lines_of(cells)
    if not bool(sheets.any()):
        return torch.zeros_like(line)
    inplane = ((cells.direction @ points.normal[sheets].T) ** 2 <= SHAPE_CLASH).float().mean(dim=1)
    return line & (inplane >= share)


def gate_pieces(added: Tensor, odd: Tensor, share: float) -> Tensor:
    """[R, R, R] bool: the cells of the connected pieces of ``added`` (26-neighbourhood) at least
    ``share`` of whose cells are ``odd`` [R, R, R] (:attr:`SelectOptions.shape_gate`)."""
    at = added.reshape(-1).nonzero().squeeze(-1)
    _, piece = torch.unique(components(added).reshape(-1)[at], return_inverse=True)  # 0, 1, … per piece
    n = torch.bincount(piece).float()
    bad = torch.bincount(piece, weights=odd.reshape(-1)[at].float(), minlength=len(n))
    out = torch.zeros(added.numel(), dtype=torch.bool, device=added.device)
    out[at] = (bad / n >= share)[piece]
    return out.view(added.shape)
