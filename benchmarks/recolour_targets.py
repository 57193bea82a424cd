"""How much of each colour twin's gap the recolour's *targets* close, before any network fit:
every twin's test views rendered with each sample's colour set to the target the recolour's loss
gives it (the starting model's density, so each pixel is its samples' weighted sum).

    python benchmarks/recolour_targets.py MODEL DATA [--out FILE.md]

Rows vary where the targets say the part is:
* **cell test**: a sample takes the new colour in S's cells and when its ray's surface lies in S
  (`supervised.in_selection`; the rule before `sample_share`);
* **share** (what the edits use): and elsewhere in proportion to S's share interpolated over the
  occupied cells (`supervised.sample_share`);
* each with S from the scribbles (`evaluation.twin_selection`) or the oracle selection of
  benchmarks/selection.py (ground-truth part maps of the train views);
* **share per point**: the share alone, without the ray-surface test: a function of the 3-D point,
  which is all a network fit can reproduce (F_rad never sees the ray);
* **pixel-perfect**: every sample of a ray whose test-view pixel shows the part (read from the
  ground truth): what the target rule itself leaves.

Every row but the pixel-perfect one holds, outside S's interior, the samples whose colour is
unlike the scribbled pixels' (`supervised.mixed_at`, `RecolorTarget.likeness`), as the edits do.

Two more rows are the edits themselves (selection from the scribbles, default options), the
``hybrid`` strategy (F_rad + colour code, the paper's) and ``all`` (every weight): a fit row below
its target row is what the network could not reproduce.

Scored like `crfedit eval edits` (mean PSNR over the views, gap closed to the source's own
reconstruction), and outside the part: the PSNR of the pixels where the twin equals the source
(`psnr_outside`), and how much of the squared error there that the row adds to the unedited
render's lies on pixels the ground truth shows as background (a silhouette the model draws
wider than the mesh, invisible in the old colour).  Like edit_ceiling.py it reads answers, so it is a diagnostic, not a method:
the distance from a row to the edit's own gap closed is the network fit's.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import numpy as np
import torch

import crfedit.evaluation as evaluation
from crfedit.cameras import rays_from_camera
from crfedit.edit import EditOptions
from crfedit.edit.cache import edit_passes
from crfedit.edit.selection import MIN_OPACITY
from crfedit.edit.supervised import RecolorTarget, in_selection, mixed_at, selection_share
from crfedit.metrics import score_images
from crfedit.renderer import render_camera
from crfedit.twin_scores import changed_regions, gap_closed, masked_psnr, part_map, part_of
from crfedit.report import emit_table
from crfedit.errors import run_script

_spec = importlib.util.spec_from_file_location("bench_selection", Path(__file__).with_name("selection.py"))
bench_selection = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_selection)

ROWS = (  # (label, selection, rule)
    ("cell test, selection from the scribbles", "scribbles", "cells"),
    ("share, selection from the scribbles (the edits' targets)", "scribbles", "share"),
    ("cell test, oracle selection", "oracle", "cells"),
    ("share, oracle selection", "oracle", "share"),
    ("share per point, selection from the scribbles (no ray-surface test)", "scribbles", "point"),
    ("pixel-perfect (ground-truth part pixels)", None, "pixels"),
)


@torch.no_grad()
def target_render(model, case, category, sel, rule: str) -> list[np.ndarray]:
    """The twin's test views with every kept sample at its recolour target."""
    k, field = case.instance, model.field_for(case.instance)
    view = render_camera(field, case.camera, k)
    on = torch.from_numpy(case.scribble) & (view.opacity.cpu() >= MIN_OPACITY)
    recolor = RecolorTarget(evaluation.twin_appearance(category, case), view.rgb.cpu()[on])
    grid = field.occupancy[k]
    inst = category.instance(case.spec.source)
    part_id = part_of(inst.path, case.spec.part)["id"]
    images = []
    for source_view, twin_view in zip(inst.splits["test"], case.views):
        rays = rays_from_camera(twin_view.camera, model.device)
        (p,) = edit_passes(field, rays, k, ["F_rad.", "color_codes"], density_changes=False)
        _, code = field.codes(k)
        rgb0 = p.sample_rgb(p.net, code)
        n = p.constant.shape[0]
        if rule == "pixels":
            on_part = torch.from_numpy(part_map(inst.path, source_view).reshape(-1) == part_id).to(p.ray.device)
            share = on_part[p.ray].to(rgb0.dtype)
        else:
            m = sel.mask.to(grid.device) & grid
            full = in_selection(m, p.ray, p.xn_kept, p.w, n) if rule != "point" else torch.zeros_like(p.ray, dtype=torch.bool)
            share = full.to(rgb0.dtype) if rule == "cells" else selection_share(m, grid, p.xn_kept, full)
        target = recolor.toward(rgb0, share, None if rule == "pixels" else mixed_at(m, grid, p.xn_kept))
        pixels = p.constant.index_add(0, p.ray, p.w[:, None] * target)
        h, w = twin_view.rgb.shape[:2]
        images.append(pixels.clamp(0, 1).view(h, w, 3).cpu().numpy())
    return images


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    model, category, cases = bench_selection.load_twin_benchmark(args.model, args.data)
    cases = [c for c in cases if c.spec.kind == "color" and evaluation.twin_appearance(category, c) is not None]
    if not cases:
        raise SystemExit("no colour twin with part maps in this dataset")
    def views_of(m, case) -> list[np.ndarray]:
        return [o.rgb.clamp(0, 1).cpu().numpy() for o in evaluation.render_views(m, case.instance, [v.camera for v in case.views])]

    selections, before, ceiling, outside, background, unedited_err, unedited_out = {}, [], [], [], [], [], []
    for case in cases:
        inst = category.instance(case.spec.source)
        selections[case.spec.name] = {
            "scribbles": evaluation.twin_selection(model, case),
            "oracle": bench_selection.oracle_selection(model, case, inst, part_of(inst.path, case.spec.part)["id"]),
        }
        unedited = views_of(model, case)
        before.append(score_images(unedited, [v.rgb for v in case.views])["psnr"])
        source_views = inst.splits["test"][: len(case.views)]
        ceiling.append(score_images(unedited, [v.rgb for v in source_views])["psnr"])
        outside.append([~r for r in changed_regions(source_views, case.views)])
        background.append([part_map(inst.path, v) == 0 for v in source_views])
        unedited_err.append(outside_errors(unedited, case.views, outside[-1], background[-1]))
        unedited_out.append(masked_psnr(unedited, [v.rgb for v in case.views], outside[-1]))
    names = [c.spec.name for c in cases]
    lines = [
        f"Model `{args.model}`, data `{args.data}`, {len(cases)} colour twins; gap closed by the target render (no fit), then by the edits;",
        "outside the part: mean `psnr_outside` (unedited: "
        f"{np.mean(unedited_out):.2f} dB), "
        "and the share of the squared error added there on ground-truth background pixels.", "",
        "| targets | mean gap closed | outside (dB) | added outside error on background | " + " | ".join(names) + " |",
        "|---|---:|---:|---:|" + "---:|" * len(names),
    ]

    def row(label: str, images_of) -> None:
        """One table row: each case's gap closed by ``images_of(case)``, their mean, the mean
        PSNR outside the part and the background's share of the error added there."""
        gaps, outs, added, added_bg = [], [], 0.0, 0.0
        for i, case in enumerate(cases):
            images = images_of(case)
            gaps.append(gap_closed(score_images(images, [v.rgb for v in case.views])["psnr"], before[i], ceiling[i]))
            outs.append(masked_psnr(images, [v.rgb for v in case.views], outside[i]))
            err, err_bg = outside_errors(images, case.views, outside[i], background[i])
            added, added_bg = added + err - unedited_err[i][0], added_bg + err_bg - unedited_err[i][1]
        share = f"{added_bg / added:.2f}" if added > 0 else "–"
        lines.append(f"| {label} | {np.mean(gaps):.3f} | {np.mean(outs):.2f} | {share} | " + " | ".join(f"{g:.3f}" for g in gaps) + " |")
        print(lines[-1], flush=True)

    for label, which, rule in ROWS:
        row(label, lambda case: target_render(model, case, category, selections[case.spec.name][which] if which else None, rule))
    for strategy, which in (("hybrid", "scribbles"), ("all", "scribbles"), ("hybrid", "oracle")):
        edit = lambda case: evaluation.apply_twin_edit(model, case, EditOptions(strategy=strategy), appear=evaluation.twin_appearance(category, case),
                                                       selection=selections[case.spec.name][which]).model
        source = "selection from the scribbles" if which == "scribbles" else "oracle selection"
        row(f"the edit, `{strategy}` (fit, {source})", lambda case: views_of(edit(case), case))
    emit_table(lines, args.out)


def outside_errors(images, twin_views, outside, background) -> tuple[float, float]:
    """(squared error summed over the ``outside`` pixels of all views, and over those of them
    that are ``background``)."""
    err = [((im - v.rgb) ** 2).sum(axis=-1) for im, v in zip(images, twin_views)]
    return (float(sum(e[o].sum() for e, o in zip(err, outside))),
            float(sum(e[o & b].sum() for e, o, b in zip(err, outside, background))))


if __name__ == "__main__":
    run_script(main)
