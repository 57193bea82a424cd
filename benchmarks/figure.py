"""Make the README's before/after picture from a trained model and its dataset's twins.

For one colour twin and one removal twin (the dataset's first of each, or ``--color-twin`` /
``--remove-twin``): run the edit from the twin's scribbles through the CLI with its default
method, then show the scribbled view with the strokes drawn on it (red: the part, blue: keep),
and, for each of ``--views`` held-out test views, the render before, after, and the
ground-truth twin.  A recolour is given the colour the part should *appear* under the scribble
(what `crfedit eval edits` gives it: the twin's new albedo times the mean shading there), or the
twin's albedo when the dataset has no part maps.  Usage:

    python benchmarks/figure.py MODEL DATA --out PNG [--views 0,3]   (the README's: --out docs/img/edit_before_after.png)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import crfedit.evaluation as evaluation
from crfedit.data.synth import rgb_to_hex
from crfedit.demo import tiled
from crfedit.io import read_image, write_png
from crfedit.model import load_model
from crfedit.errors import CrfError, run_script


def crfedit(*args: str) -> None:
    """Run a crfedit command; its own one-line error (on stderr) ends the script with its status."""
    done = subprocess.run([sys.executable, "-m", "crfedit", *args], stdout=subprocess.DEVNULL)
    if done.returncode:
        sys.exit(done.returncode)


def render(model: str, instance: str, view: str, out: Path, edit: Path | None = None) -> np.ndarray:
    extra = ["--edit", str(edit)] if edit else []
    crfedit("render", model, "--instance", instance, "--views", view, "--out", str(out), *extra)
    return read_image(out / "0000.png")[..., :3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", required=True, help="PNG to write (the README's is docs/img/edit_before_after.png: named, never by default)")
    ap.add_argument("--views", default="0,3", help="held-out test view indices to show, comma-separated")
    ap.add_argument("--color-twin", help="the colour twin to show (default: the dataset's first)")
    ap.add_argument("--remove-twin", help="the removal twin to show (default: the dataset's first)")
    ap.add_argument("--scale", type=int, default=3, help="pixels per rendered pixel in the figure (default 3)")
    args = ap.parse_args()
    if args.scale < 1:
        raise CrfError(f"--scale {args.scale}: must be at least 1")
    try:
        views = [int(v) for v in args.views.split(",")]
    except ValueError:
        raise CrfError(f"--views {args.views}: expected test view indices, comma-separated (0,3)") from None
    model, _ = load_model(args.model)
    category = evaluation.load_category_for(model, args.data)
    cases = evaluation.load_twin_cases(model, category)
    chosen = {"color": args.color_twin, "remove": args.remove_twin}
    rows, labels, said, before = [], [], {}, {}  # before: (instance, test view) → its unedited render
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for kind in ("color", "remove"):
            case = next((c for c in cases if c.spec.kind == kind and chosen[kind] in (None, c.spec.name)), None)
            if case is None:  # a bare StopIteration named nothing
                names = ", ".join(c.spec.name for c in cases if c.spec.kind == kind) or "none"
                raise CrfError(f"--{'color' if kind == 'color' else 'remove'}-twin {chosen[kind]}: not a {kind} twin of {args.data} ({names})")
            spec = case.spec
            edit = tmp / f"{kind}.safetensors"
            common = [args.model, "--instance", spec.source, "--view", spec.view, "--scribble", str(category.root / spec.scribble),
                      "--keep", str(category.root / spec.keep), "--out", str(edit)]
            if kind == "color":
                appear = evaluation.twin_appearance(category, case)
                color = rgb_to_hex(appear) if appear is not None else spec.color
                crfedit("edit-color", *common, "--color", color)
                said[spec.name] = {"color": color, "albedo": spec.color}
            else:
                crfedit("remove", *common)
                said[spec.name] = {}
            scribbled = render(args.model, spec.source, spec.view, tmp / f"{kind}_scribbled").copy()
            scribbled[case.keep] = (0.2, 0.35, 1.0)
            scribbled[case.scribble] = (1.0, 0.15, 0.1)
            row, names = [scribbled], ["scribbled view"]
            for i in views:
                if (spec.source, i) not in before:  # the two twins often share their source
                    before[spec.source, i] = render(args.model, spec.source, f"test:{i}", tmp / f"{kind}_before{i}")
                row += [before[spec.source, i],
                        render(args.model, spec.source, f"test:{i}", tmp / f"{kind}_after{i}", edit),
                        case.views[i].rgb[..., :3]]
                names += [f"test view {i}: before", "recoloured" if kind == "color" else "part removed", "ground-truth twin"]
            rows.append(row)
            labels.append(names)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_png(args.out, tiled(rows, labels, args.scale, group=3))
    print(json.dumps({"wrote": args.out, "twins": said}))


if __name__ == "__main__":
    run_script(main)
