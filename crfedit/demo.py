"""The quickstart's edit demonstration: a chair's ground-truth twins (a recolour and a removal)
edited from their scribbles with the default method, each delta saved, a before/after picture,
and each edit scored against its twin.

The scribbles are the dataset's own (``twins.json``): what a user would draw on one view. The
twins are the chair rendered with the part really recoloured or removed, so the picture and
the scores show what the edit does in views nobody scribbled on.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .data.loading import Category
from .edit import EditOptions, EditResult
from .errors import CrfError
from .evaluation import Progress, TwinCase, evaluate_edits, load_twin_cases, render_views
from .io import write_png
from .model import CategoryModel

DEMO_VIEWS = (0, 2)
"""The twins' test views the picture shows (those the twins have, of these)."""
SCRIBBLE_RGB, KEEP_RGB = (1.0, 0.15, 0.1), (0.2, 0.35, 1.0)
"""How the picture draws the strokes: red the part, blue what to keep."""
EDITED = {"color": "recoloured", "remove": "part removed"}


MADE_BY = "quickstart"
"""The ``made_by`` metadata of the edits :func:`demo_edits` writes (provenance: not in the
fingerprint), by which :func:`clear_stale_demo` knows them from a user's."""


def clear_stale_demo(out: str | Path, model: CategoryModel) -> list[str]:
    """Remove from ``out`` (a quickstart's ``edits/`` folder) the edit files an earlier
    quickstart made (their metadata's ``made_by`` is :data:`MADE_BY`) for another model
    than ``model``, and the picture of them: a quickstart run again into its folder trains a new
    model, and the earlier run's edits (and ``edits.png``, which shows them) stood beside it,
    stale, when this run made none (``--no-edits``, or a twin it could not edit).  Every other
    file stays, the user's own edits too.  Returns the names removed."""
    from .delta import read_delta
    from .names import EDIT_FORMAT
    from .safefile import file_format

    out, removed = Path(out), []
    if not out.is_dir():
        return removed
    for path in sorted(out.glob("*.safetensors")):
        try:
            meta = read_delta(path).meta if file_format(path) == EDIT_FORMAT else {}
            stale = meta.get("made_by") == MADE_BY and meta.get("base") != model.fingerprint()
        except CrfError:  # a damaged file: not one this tool can tell is its own; it stays
            continue
        if stale:
            path.unlink()
            removed.append(path.name)
    if removed and (out / "edits.png").is_file():
        (out / "edits.png").unlink()
        removed.append("edits.png")
    return removed


def demo_edits(
    model: CategoryModel, category: Category, out: str | Path, seed: int = 0, views: Sequence[int] = DEMO_VIEWS,
    command: str = "", progress: Progress | None = None,
) -> dict:
    """Edit every twin of ``category`` (:func:`~crfedit.evaluation.evaluate_edits`, hybrid
    strategy, default options), write each delta as ``out/<twin>.safetensors`` and the picture
    as ``out/edits.png``.  Returns ``{"edits": [one row per twin edited: twin, kind, source,
    part, delta, psnr, psnr_before, psnr_ceiling, gap_closed, selection_iou, seconds],
    "skipped": {twin: why}, "picture"}``; a twin whose edit is a user error (a scribble the
    model does not show) is skipped and the others go on; with none edited, that error is
    raised.  ``command`` is written into each delta as its provenance."""
    cases = load_twin_cases(model, category)
    if not cases:
        raise CrfError(f"{category.root}: the dataset has no ground-truth twins (twins.json) to demonstrate edits on")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    edited: dict[str, tuple[TwinCase, EditResult, Path]] = {}

    def keep(case: TwinCase, strategy: str, result: EditResult) -> None:
        path = out / f"{case.spec.name}.safetensors"
        result.save(path, view=case.spec.view, made_by=MADE_BY, **({"command": command} if command else {}))
        edited[case.spec.name] = (case, result, path)

    rows, skipped, error = [], {}, None
    for case in cases:  # one twin at a time, so that one that cannot be edited leaves the others
        try:
            report = evaluate_edits(model, category, [case], ("hybrid",), EditOptions(seed=seed), device=model.device, seed=seed,
                                    progress=progress, paper=False, on_edit=keep)
        except CrfError as e:
            skipped[case.spec.name], error = str(e), e
            continue
        run = next(r for r in report["runs"] if r["method"] == "hybrid")
        rows.append({
            "twin": run["twin"], "kind": run["kind"], "source": run["source"], "part": case.spec.part, "delta": str(edited[run["twin"]][2]),
            **{key: run.get(key) for key in ("psnr", "psnr_before", "psnr_ceiling", "gap_closed", "selection_iou", "seconds")},
        })
    if not rows:
        raise error
    picture = out / "edits.png"
    write_png(picture, before_after(model, [edited[r["twin"]][:2] for r in rows], views))
    return {"edits": rows, "skipped": skipped, "picture": str(picture)}


def before_after(model: CategoryModel, edits: Sequence[tuple[TwinCase, EditResult]], views: Sequence[int], scale: int = 3) -> np.ndarray:
    """One row per edit: the scribbled view with its strokes drawn on it, then for each of the
    twin's test ``views`` the render before the edit, after it, and the ground-truth twin.  [H, W, 3]"""
    rows, labels = [], []
    for case, result in edits:
        shown = [i for i in views if i < len(case.views)]
        cameras = [case.camera] + [case.views[i].camera for i in shown]
        before = [rgb_of(o) for o in render_views(model, case.instance, cameras)]
        after = [rgb_of(o) for o in render_views(result.model, case.instance, cameras[1:])]
        scribbled = before[0].copy()
        scribbled[case.keep] = KEEP_RGB
        scribbled[case.scribble] = SCRIBBLE_RGB
        row, names = [scribbled], ["scribbled view"]
        for i, b, a in zip(shown, before[1:], after):
            row += [b, a, case.views[i].rgb[..., :3]]
            names += [f"test view {i}: before", EDITED[case.spec.kind], "ground-truth twin"]
        rows.append(row)
        labels.append(names)
    return tiled(rows, labels, scale, group=3)


def rgb_of(render) -> np.ndarray:
    """A render's colour [H, W, 3] in [0, 1] on the CPU."""
    return render.rgb.clamp(0.0, 1.0).cpu().numpy()


def tiled(rows: Sequence[Sequence[np.ndarray]], labels: Sequence[Sequence[str]], scale: int = 3, group: int = 3) -> np.ndarray:
    """Images [h, w, 3] in [0, 1] laid out in rows, each scaled ``scale``× (nearest) under its
    label, with a wider gap before the first image and after every ``group`` after it (the
    before / after / twin triples).  [H, W, 3] uint8"""
    from PIL import Image, ImageDraw

    h, w = rows[0][0].shape[:2]
    pad, gap, text_h = 6, 18, 16
    columns = max(len(r) for r in rows)
    x_of = lambda c: pad + c * (w * scale + pad) + (gap * ((c - 1) // group + 1) if c > 0 else 0)
    canvas = Image.new("RGB", (x_of(columns - 1) + w * scale + pad, len(rows) * (h * scale + text_h + pad) + pad), "white")
    draw = ImageDraw.Draw(canvas)
    for r, (images, names) in enumerate(zip(rows, labels)):
        y = pad + r * (h * scale + text_h + pad)
        for c, (img, name) in enumerate(zip(images, names)):
            tile = Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).resize((w * scale, h * scale), Image.NEAREST)
            canvas.paste(tile, (x_of(c), y + text_h))
            draw.text((x_of(c) + 2, y + 2), name, fill=(40, 40, 40))
    return np.asarray(canvas)
