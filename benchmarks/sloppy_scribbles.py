"""Selections from sloppy scribbles: the twins' scribbles drawn with a wider brush, or aimed
a pixel off.

    python benchmarks/sloppy_scribbles.py MODEL DATA [--brush grow1,grow2,shift1,shift1grow1,keep5,nokeep] [--whole-strokes] [--no-snap] [--out FILE.md]

The benchmark's scribbles lie inside each part, eroded by up to 2 px; a user's brush does not
stay inside a 1–2 px tube at 64². Each twin's scribble is changed as ``--brush`` says: ``growN``
dilates it by N px (a square brush N px wider on every side), ``shiftN`` moves it N px to the
right, ``shiftNgrowM`` does both; ``keepN`` dilates the keep strokes instead (they lie at least 4 px
off the part, so ``keep5`` strays a pixel onto it), and ``nokeep`` drops them (a user who draws
only the scribble). The keep strokes lose what the changed
scribble covers, and the selection is made again with the edit kind's default options. Printed per change: mean
selection IoU on the source's test views, per kind, and where the scribbled pixels land in the
scribbled view's ground truth (on the part, on another part, on the background: a background
pixel is lifted only where the model draws some opacity), and how many keep pixels land on the
part.  A scribble the tool refuses (all on the background, say) counts as IoU 0 and is named.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time
from pathlib import Path

import numpy as np

from selection import load_twin_benchmark

from crfedit.edit.selection import ScribbleView, options_for, select
from crfedit.errors import CrfError
from crfedit.masks import dilate
from crfedit.report import emit_table
from crfedit.twin_scores import part_map, part_of, selection_iou
from crfedit.errors import run_script


def landing(category, case, scribble: np.ndarray) -> tuple[int, int, int] | None:
    """(on the part, on another part, on the background) pixels of ``scribble`` in the
    scribbled view's part map; None without part maps."""
    inst = category.instance(case.spec.source)
    parts, record = part_map(inst.path, inst.view(case.spec.view)), part_of(inst.path, case.spec.part)
    if parts is None or record is None:
        return None
    on = parts[scribble]
    return int((on == record["id"]).sum()), int(((on != record["id"]) & (on > 0)).sum()), int((on == 0).sum())


def sloppy(scribble: np.ndarray, change: str) -> np.ndarray:
    """``scribble`` [H, W] changed as ``change`` says (``""``: as it is; ``growN``, ``shiftN``,
    ``shiftNgrowM``; a shift moves it right, what leaves the image is lost)."""
    m = re.fullmatch(r"(?:shift(\d+))?(?:grow(\d+))?", change)
    if m is None:
        raise SystemExit(f"--brush {change!r}: expected growN, shiftN, shiftNgrowM, keepN or nokeep")
    out = moved(scribble, int(m.group(1)), 0) if m.group(1) else scribble
    return dilate(out, int(m.group(2))) if m.group(2) else out


def moved(mask: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``mask`` moved ``dx`` px right and ``dy`` px down; what leaves the image is lost."""
    out = np.zeros_like(mask)
    h, w = mask.shape
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = mask[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    return out


def sloppy_strokes(scribble: np.ndarray, keep: np.ndarray | None, change: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(scribble, keep strokes) changed as ``change`` says: ``keepN`` dilates the keep strokes
    by N px, ``nokeep`` drops them, anything else changes the scribble (:func:`sloppy`); the
    keep strokes lose what the scribble covers."""
    if change == "nokeep":
        return scribble, None
    m = re.fullmatch(r"keep(\d+)", change)
    if m is not None:
        fg = scribble
        keep = None if keep is None else dilate(keep, int(m.group(1)))
    else:
        fg = sloppy(scribble, change)
    return fg, None if keep is None else keep & ~fg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--brush", default="grow1,grow2,shift1,shift1grow1",
                    help="changes to measure, comma-separated (the benchmark's own scribbles always run first)")
    ap.add_argument("--whole-strokes", action="store_true", help="lift every scribbled pixel, not the strokes' centres (the default before 2026-11-26)")
    ap.add_argument("--no-snap", action="store_true", help="do not snap a scribble lying mostly off the object onto it (the default before 2026-11-26)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    model, category, cases = load_twin_benchmark(args.model, args.data)
    changes = [""] + [c for c in args.brush.split(",") if c]
    for c in changes:
        sloppy_strokes(np.zeros((2, 2), bool), np.zeros((2, 2), bool), c)  # a bad --brush fails before any selection
    lines = [
        f"Model `{args.model}`, data `{args.data}`, {len(cases)} twins; IoU on each source's test views"
        f"{'; every scribbled pixel lifted (--whole-strokes)' if args.whole_strokes else ''}"
        f"{'; no snap (--no-snap)' if args.no_snap else ''}.", "",
        "| scribble | colour IoU | removal IoU | min IoU | scribbled pixels: on the part / other parts / background | keep pixels on the part | seconds |",
        "|---|---:|---:|---:|---|---:|---:|",
    ]
    per_twin = {}
    for change in changes:
        ious, land, kept_on, secs = {"color": [], "remove": []}, np.zeros(3, int), 0, []
        for case in cases:
            fg, keep = sloppy_strokes(case.scribble, case.keep, change)
            t = time.perf_counter()
            options = options_for(case.spec.kind)
            if args.whole_strokes:
                options = dataclasses.replace(options, stroke_centres=False)
            if args.no_snap:
                options = dataclasses.replace(options, stroke_snap=0.0)
            inst = category.instance(case.spec.source)
            try:
                sel = select(model, case.instance, [ScribbleView(case.camera, fg, keep)], options)
            except CrfError as e:  # the tool refuses the scribble (e.g. all on the background): a lost twin
                print(f"{change or 'as drawn'}: {case.spec.name} refused: {e}", flush=True)
                iou = 0.0 if part_of(inst.path, case.spec.part) is not None else None
            else:
                secs.append(time.perf_counter() - t)
                iou = selection_iou(model, sel, inst.path, inst.splits["test"], case.spec.part)
            if iou is not None:
                ious[case.spec.kind].append(iou)
                per_twin.setdefault(case.spec.name, []).append(iou)
            spots = landing(category, case, fg)
            if spots is not None:
                land += spots
            spots = None if keep is None else landing(category, case, keep)
            if spots is not None:
                kept_on += spots[0]
        every = ious["color"] + ious["remove"]
        mean = lambda xs: f"{np.mean(xs):.3f}" if xs else "–"
        line = (f"| {change or 'as drawn'} | {mean(ious['color'])} | {mean(ious['remove'])} | {np.min(every) if every else float('nan'):.3f} "
                f"| {land[0]} / {land[1]} / {land[2]} | {kept_on} | {np.mean(secs):.2f} |")
        print(line, flush=True)
        lines.append(line)
    lines += ["", "| twin | " + " | ".join(c or "as drawn" for c in changes) + " |", "|---|" + "---:|" * len(changes)]
    lines += [f"| `{name}` | " + " | ".join(f"{x:.3f}" for x in xs) + " |" for name, xs in per_twin.items()]
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
