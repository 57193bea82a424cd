"""Make the README's before/after picture from a trained model and its dataset's twins.

For the first color twin and the first removal twin: run the edit from the twin's scribbles
through the CLI, render a held-out test view before and after, and put them beside the
ground-truth twin.  Usage:

    python benchmarks/figure.py MODEL DATA [--out docs/img/edit_before_after.png] [--view 0]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from crfedit.data.loading import load_twins
from crfedit.io import read_image, write_png


def crfedit(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "crfedit", *args], check=True, stdout=subprocess.DEVNULL)


def render(model: str, instance: str, view: str, out: Path, edit: Path | None = None) -> np.ndarray:
    extra = ["--edit", str(edit)] if edit else []
    crfedit("render", model, "--instance", instance, "--views", view, "--out", str(out), *extra)
    return read_image(out / "0000.png")[..., :3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", default="docs/img/edit_before_after.png")
    ap.add_argument("--view", type=int, default=0, help="test view index to show")
    ap.add_argument("--scale", type=int, default=3)
    args = ap.parse_args()
    root = Path(args.data)
    twins = load_twins(root)
    rows, labels = [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for kind in ("color", "remove"):
            spec, data = next((s, d) for s, d in twins if s.kind == kind)
            edit = tmp / f"{kind}.safetensors"
            common = [args.model, "--instance", spec.source, "--view", spec.view, "--scribble", str(root / spec.scribble),
                      "--keep", str(root / spec.keep), "--out", str(edit)]
            crfedit("edit-color", *common, "--color", spec.color) if kind == "color" else crfedit("remove", *common)
            view = f"test:{args.view}"
            before = render(args.model, spec.source, view, tmp / f"{kind}_before")
            after = render(args.model, spec.source, view, tmp / f"{kind}_after", edit)
            truth = data.splits["test"][args.view].rgb
            rows.append([before, after, truth])
            labels.append(("before", "recolored" if kind == "color" else "part removed", "ground truth"))
    h, w = rows[0][0].shape[:2]
    s, pad, text_h = args.scale, 6, 16
    canvas = Image.new("RGB", (3 * w * s + 4 * pad, len(rows) * (h * s + text_h + pad) + pad), "white")
    draw = ImageDraw.Draw(canvas)
    for r, (images, names) in enumerate(zip(rows, labels)):
        y = pad + r * (h * s + text_h + pad)
        for c, (img, name) in enumerate(zip(images, names)):
            x = pad + c * (w * s + pad)
            tile = Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).resize((w * s, h * s), Image.NEAREST)
            canvas.paste(tile, (x, y + text_h))
            draw.text((x + 2, y + 2), name, fill=(40, 40, 40))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_png(args.out, np.asarray(canvas))
    print(json.dumps({"wrote": args.out}))


if __name__ == "__main__":
    main()
