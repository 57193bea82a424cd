"""Adding a part: how well each `add --method` puts a donor's part into another chair, in views
it was not edited from.

    python benchmarks/add.py MODEL DATA [--pairs 2:6,3:5,9:7,11:21] [--part arms] [--grow N] [--shift DX,DY] [--snap] [--whole-strokes] [--out FILE.md]

For each pair TARGET:DONOR[:PART] (instance indices or names) the donor's part (default
``--part``, the arms; the real chairs' parts carry their meshes' own names, so give each pair
its own, e.g. ``13:0:armrest``) is copied from the donor's train
view where it shows most, at offset 0,0, into the target seen from the same camera (so it lands
where the donor has it); ``--grow N`` draws the copy strokes N px wider than the part, as a
user's brush does; ``--shift DX,DY`` moves them, as an unsteady hand does (the part and its
placement stay where they were); ``--snap`` lets additions snap a stroke lying mostly off the
object onto it, as recolours and removals do (``STROKE_SNAP``); and ``--whole-strokes`` lifts every copied pixel rather than the strokes'
centres (the default before 2026-11-26, selection method only).  Scored on the donor's test views, whose part maps say where the part
is: the expected silhouette is the target's own (before the edit) united with the donor part's
pixels.

- **added**: the share of the part's pixels, not already covered by the target, that the edit
  made opaque (opacity > 0.5);
- **spill**: pixels made opaque outside the expected silhouette, as a share of the part's;
- **IoU**: of the edited silhouette with the expected one;
- **outside**: PSNR of the edited render against the unedited one away from the part (two
  pixels of margin): the damage to the rest of the target;
- **seconds** of the edit, one torch thread.

There is no ground-truth image of a chair with another chair's arms, so colour is not scored:
the pasted part takes the target's colour code, as in the paper.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from sloppy_scribbles import moved

from crfedit.data.loading import load_category
from crfedit.edit import EditOptions, add
from crfedit.edit.selection import ScribbleView, options_for, select
from crfedit.edit.selection.options import STROKE_SNAP
from crfedit.evaluation import model_width
from crfedit.masks import dilate
from crfedit.model import load_model
from crfedit.names import ADD_METHODS
from crfedit.renderer import render_camera
from crfedit.report import emit_table
from crfedit.errors import CrfError, run_script


def part_id(instance, name: str) -> int:
    return next(p["id"] for p in json.loads((instance.path / "parts.json").read_text()) if p["name"] == name)


@torch.no_grad()
def render(model, k, camera):
    out = render_camera(model.field_for(k), camera, k)
    return out.rgb.numpy(), out.opacity.numpy()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2)) if a.size else 0.0
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def score_pair(model, category, k: int, j: int, part: str, method: str, options: EditOptions, grow: int = 0,
               whole_strokes: bool = False, shift: tuple[int, int] = (0, 0), snap: bool = False) -> dict:
    donor = category.instances[j]
    pid = part_id(donor, part)
    view = max(donor.splits["train"], key=lambda v: int((v.parts == pid).sum()))
    mask = moved(dilate(view.parts == pid, grow) if grow else view.parts == pid, *shift)
    t0 = time.perf_counter()
    selection = None
    if (whole_strokes or snap) and method == "selection":
        select_options = dataclasses.replace(options_for("add"), stroke_centres=options_for("add").stroke_centres and not whole_strokes,
                                             stroke_snap=STROKE_SNAP if snap else options_for("add").stroke_snap)
        selection = select(model, j, [ScribbleView(view.camera, mask)], select_options)
    result = add(model, k, view.camera, j, mask, (0, 0), view.camera, method, options=options, selection=selection)
    seconds = time.perf_counter() - t0
    added = spill = part_px = 0
    inter = union = 0
    outside_before, outside_after = [], []
    for v in donor.splits["test"]:
        p = v.parts == pid
        rgb0, a0 = render(model, k, v.camera)
        rgb1, a1 = render(result.model, k, v.camera)
        own, now = a0 > 0.5, a1 > 0.5
        expected = own | p
        new_part = p & ~own
        part_px += int(new_part.sum())
        added += int((now & new_part).sum())
        spill += int((now & ~expected).sum())
        inter += int((now & expected).sum())
        union += int((now | expected).sum())
        away = ~dilate(p, 2)
        outside_before.append(rgb0[away])
        outside_after.append(rgb1[away])
    return {
        "added": added / max(part_px, 1), "spill": spill / max(part_px, 1), "iou": inter / max(union, 1),
        "outside": psnr(np.concatenate(outside_after), np.concatenate(outside_before)), "seconds": seconds,
    }


def parse_pair(model, spec: str, part: str) -> tuple[int, int, str]:
    """``TARGET:DONOR[:PART]`` (indices or names) -> (target, donor, part)."""
    fields = spec.split(":")
    if len(fields) not in (2, 3):
        raise CrfError(f"--pairs {spec!r}: expected TARGET:DONOR[:PART]")
    try:
        k, j = (model.instance_index(int(x) if x.isdigit() else x) for x in fields[:2])
    except CrfError as e:  # the default pairs are the 24-chair benchmark category's
        raise CrfError(f"--pairs {spec}: {e} (the default pairs are runs/bench/chairs' 24 chairs: give --pairs for another model)") from None
    return k, j, fields[2] if len(fields) == 3 else part


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--pairs", default="2:6,3:5,9:7,11:21", help="TARGET:DONOR[:PART], instance indices or names, comma-separated (the default: pairs of the 24-chair benchmark category, runs/bench/chairs)")
    ap.add_argument("--part", default="arms")
    ap.add_argument("--methods", default=",".join(ADD_METHODS))
    ap.add_argument("--grow", type=int, default=0, help="copy strokes this many pixels wider than the part (a square brush)")
    ap.add_argument("--shift", default="0,0", help="DX,DY: move the copy strokes this many px right and down")
    ap.add_argument("--snap", action="store_true", help="snap a copy stroke lying mostly off the donor onto it (STROKE_SNAP)")
    ap.add_argument("--whole-strokes", action="store_true", help="lift every copied pixel, not the strokes' centres")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model, _ = load_model(args.model)
    category = load_category(Path(args.data), res=model_width(model, "test"), with_parts=True)
    pairs = [parse_pair(model, p, args.part) for p in args.pairs.split(",")]
    shift = tuple(int(x) for x in args.shift.split(","))
    rows = []
    for method in args.methods.split(","):
        scores = [score_pair(model, category, k, j, part, method, EditOptions(), args.grow, args.whole_strokes, shift, args.snap)
                  for k, j, part in pairs]
        for (k, j, part), s in zip(pairs, scores):
            print(f"{method:10s} {model.names[k]} <- {model.names[j]} {part}: added {s['added']:.2f} spill {s['spill']:.2f} "
                  f"IoU {s['iou']:.3f} outside {s['outside']:.2f} dB  {s['seconds']:.2f} s", flush=True)
        mean = {key: float(np.mean([s[key] for s in scores])) for key in scores[0]}
        rows.append((method, mean))
    names = ", ".join(f"{model.names[k]} ← {model.names[j]}'s {part}" for k, j, part in pairs)
    lines = [
        f"Model `{args.model}`, data `{args.data}`; {names}, offset 0,0"
        f"{f', copy strokes {args.grow} px wider than the part' if args.grow else ''}"
        f"{f', copy strokes moved {shift[0]},{shift[1]} px' if any(shift) else ''}"
        f"{'; copy strokes snapped (--snap)' if args.snap else ''}"
        f"{'; every copied pixel lifted (--whole-strokes)' if args.whole_strokes else ''}; "
        f"scored on the donors' test views. Means over the {len(pairs)} pairs.", "",
        "| add --method | added | spill | silhouette IoU | outside | seconds |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method, m in rows:
        lines.append(f"| {method} | {m['added']:.2f} | {m['spill']:.2f} | {m['iou']:.3f} | {m['outside']:.2f} dB | {m['seconds']:.2f} |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    run_script(main)
