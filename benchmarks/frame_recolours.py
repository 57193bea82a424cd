"""Recolours of bars and frames, with ground truth: a companion dataset whose colour twins
recolour the parts that a dataset's removal twins remove (arms, slats, stretchers; the real
chairs' metal frames), from the removal twins' own scribbles and keep strokes.

    python benchmarks/frame_recolours.py DATA OUT [--meshes DIR]
    python benchmarks/frame_recolours.py DATA OUT --part legs      # procedural: every chair's legs
    crfedit eval edits MODEL OUT --strategies hybrid --no-nerf-baseline --json > scores.json
    python benchmarks/frame_recolours.py --summary scores.json [scores.json ...]

The benchmark's own colour twins recolour seats, backs and shells: parts that lie on sheets.
A user who paints a chair's legs or frame scribbles on bars, and the selection has rules for
that case (``SelectOptions.join_lines``, ``line_negatives``) that those twins barely test.
Here each removal twin's part gets a colour twin: the source rendered again, exactly as the
dataset generator rendered it, with that part in :func:`~crfedit.data.synth.contrasting_color`
of the source's colours, at the source's test poses.

``OUT`` holds links to ``DATA``'s instances, so models trained on ``DATA`` evaluate on it; only
``twins/`` and ``twins.json`` are new.  The geometry is rebuilt: procedural chairs from the
generator's seeds (``crfedit dataset synth`` with its defaults: seed 0, 50 views at 64², 3×3
supersamples), real chairs from the meshes ``--meshes`` names (``examples/real-chairs.sh``'s
``meshes/`` folder, read as ``crfedit dataset from-meshes --up y`` read them).  Before a twin is
written, the source's first test view is rendered again and must equal the stored one to the
byte, so a rebuild that differs from the dataset stops with an error rather than score edits
against the wrong chair.

``--part NAME`` (procedural chairs only) recolours that part of every chair that has one
instead, scribbled as the generator scribbles a twin (:func:`~crfedit.data.synth.scribbles`,
in the train view that shows the part most): 24 twins of the legs, say.  Only the twin
sources' part maps are left out of a part head's training (``--set part_labels=not-twins``),
so on the other chairs a model's part head has seen the part's labels: compare options on
them, do not read their IoU as held out.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from crfedit.data.format import TwinSpec, write_twins_json
from crfedit.data.synth import SynthConfig, contrasting_color, sample_cameras, twin_sources
from crfedit.errors import run_script
from edit_models import hybrid_rows

SUFFIX = "_frame_color"
"""The new twins' names: the source's name and this."""


def _same_test_view(rendered: Path, stored: Path) -> bool:
    """Whether the first test view's colour image written under ``rendered`` equals ``stored``'s."""
    name = sorted(p.name for p in (stored / "test").glob("r_*.png") if not p.name.endswith("_parts.png"))[0]
    return (rendered / "test" / name).read_bytes() == (stored / "test" / name).read_bytes()


def _chair(names: list[str], source: str):
    """(the procedural chair ``source`` as :func:`~crfedit.data.synth.write_synth_category`
    made it, its cameras per split, the generator's config)."""
    from crfedit.data.synth import make_chair

    config = SynthConfig(instances=len(names))
    armed = set(twin_sources(config.instances))  # the default sources get arms (write_synth_category)
    index = names.index(source)
    chair = make_chair(np.random.default_rng([config.seed, index, 0]), arms=True if index in armed else None)
    return chair, sample_cameras(np.random.default_rng([config.seed, index, 1]), config.views, config.res), config


def _procedural(names: list[str]):
    """A function (source name, part name) → (writer of the source's test views into a folder,
    writer of the twin's, the twin's colour), for :func:`crfedit.data.synth.write_synth_category`'s chairs."""
    from crfedit.data.synth import _write_instance

    def twin(source: str, part: str):
        chair, cams, config = _chair(names, source)
        color = contrasting_color([p.color for p in chair.parts])
        return (lambda folder: _write_instance(folder, chair, {"test": cams["test"]}, config.aa),
                lambda folder: _write_instance(folder, chair.recolored(part, color), {"test": cams["test"]}, config.aa), color)

    return twin


def _part_twins(names: list[str], part: str, tmp: Path) -> list[dict]:
    """Twin records (as ``twins.json``'s, kind aside) of ``part`` of every procedural chair that
    has it, their scribbles drawn into ``tmp`` as the generator draws a twin's."""
    from crfedit.data.synth import best_view, render_chair, scribbles
    from crfedit.io import write_png

    out = []
    for index, source in enumerate(names):
        chair, cams, config = _chair(names, source)
        if chair.part(part) is None:
            continue
        pid = chair.part(part).id
        frames = [render_chair(chair, cam, config.aa) for cam in cams["train"]]
        view, _ = best_view(frames, pid)
        fg, keep = scribbles(np.random.default_rng([config.seed, index, 4]), frames[view].parts, pid)
        if not fg.any():
            continue
        folder = tmp / "strokes" / source
        folder.mkdir(parents=True)
        write_png(folder / "scribble.png", fg.astype(np.uint8) * 255)
        write_png(folder / "keep.png", keep.astype(np.uint8) * 255)
        out.append({"source": source, "part": part, "view": f"train:{view}", "scribble": str(folder / "scribble.png"),
                    "keep": str(folder / "keep.png")})
    return out


def _meshes(data: Path, names: list[str], meshes: Path):
    """As :func:`_procedural`, for ``crfedit dataset from-meshes DATA MESHES/*/*.obj --up y``."""
    from crfedit.data.mesh_io import load_normalized
    from crfedit.data.meshes import _write_instance, instance_names_from

    paths = sorted(meshes.glob("*/*.obj"))
    by_name = dict(zip(instance_names_from(paths), paths))
    config = SynthConfig(instances=len(names))

    def twin(source: str, part: str):
        if source not in by_name:
            raise SystemExit(f"{meshes}: no mesh for instance {source}")
        index = names.index(source)
        mesh, _ = load_normalized(by_name[source], "y")
        cams = sample_cameras(np.random.default_rng([config.seed, index, 1]), config.views, config.res)
        listed = json.loads((data / source / "parts.json").read_text())
        colors = {p["id"]: p["color"] for p in listed}
        part_id = next(p["id"] for p in listed if p["name"] == part)
        # parts the mesh lists but no face uses are left out of parts.json; any colour does for them
        source_colors = [colors.get(p.id, "#808080") for p in mesh.parts]
        color = contrasting_color([p["color"] for p in listed])
        twin_colors = [color if p.id == part_id else c for p, c in zip(mesh.parts, source_colors)]
        return (lambda folder: _write_instance(folder, mesh, source_colors, {"test": cams["test"]}, config.aa),
                lambda folder: _write_instance(folder, mesh, twin_colors, {"test": cams["test"]}, config.aa), color)

    return twin


def build(data: Path, out: Path, meshes: Path | None, part: str | None = None) -> list[TwinSpec]:
    """Write the companion dataset (see the module docstring); returns its twins."""
    names = (data / "instances.txt").read_text().split()
    if part is not None and meshes is not None:
        raise SystemExit("--part is for procedural chairs only")
    make = _meshes(data, names, meshes) if meshes is not None else _procedural(names)
    if out.exists():
        raise SystemExit(f"{out}: exists; pick a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=out.name + ".", dir=out.parent))  # renamed onto OUT once whole
    try:
        if part is None:
            removals = [t for t in json.loads((data / "twins.json").read_text())["twins"] if t["kind"] == "remove"]
            removals = [{**t, "scribble": data / t["scribble"], "keep": data / t["keep"]} for t in removals]
        else:
            removals = _part_twins(names, part, tmp)
        if not removals:
            raise SystemExit(f"{data}: no removal twins" if part is None else f"{data}: no chair has a part named {part}")
        specs = []
        for t in removals:
            source, edited = t["source"], t["part"]
            write_source, write_twin, color = make(source, edited)
            with tempfile.TemporaryDirectory() as check:
                write_source(Path(check))
                if not _same_test_view(Path(check), data / source):
                    raise SystemExit(f"{source}: the rebuilt chair's first test view differs from {data / source}; not the generator's chair")
            name = source + (SUFFIX if part is None else f"_{part}_color")
            folder = Path("twins") / name
            write_twin(tmp / folder)
            for stroke in ("scribble", "keep"):
                shutil.copyfile(t[stroke], tmp / folder / f"{stroke}.png")
            specs.append(TwinSpec(name, "color", source, t["view"], edited, color, str(folder / "scribble.png"), str(folder / "keep.png"),
                                  str(folder)))
            print(f"{name}: {edited} → {color}", file=sys.stderr)
        for name in names:
            (tmp / name).symlink_to((data / name).resolve(), target_is_directory=True)
        shutil.copyfile(data / "instances.txt", tmp / "instances.txt")
        write_twins_json(tmp, specs)
        shutil.rmtree(tmp / "strokes", ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    tmp.rename(out)
    return specs


def summary(paths: list[str]) -> str:
    """A markdown table of ``crfedit eval edits --json`` reports on a companion dataset: per
    report, the hybrid recolours' mean gap closed, outside change and selection IoU, and the
    worst twin."""
    rows = ["| report | twins | gap closed | outside vs unedited | selection IoU | worst twin (gap closed) |", "|---|---:|---:|---:|---:|---|"]
    for path in paths:
        runs = json.loads(Path(path).read_text())["runs"]
        base = {r["twin"]: r for r in runs if r["method"] == "unedited"}
        edits = hybrid_rows(runs, "color")
        if not edits:
            continue
        gap = np.mean([r["gap_closed"] for r in edits])
        outside = np.mean([r["psnr_outside"] - base[r["twin"]]["psnr_outside"] for r in edits])
        ious = [r["selection_iou"] for r in edits if r.get("selection_iou") is not None]
        worst = min(edits, key=lambda r: r["gap_closed"])
        rows.append(f"| {Path(path).stem} | {len(edits)} | {gap:.3f} | {outside:+.2f} dB | {np.mean(ious):.3f} | "
                    f"`{worst['source']}` ({worst['gap_closed']:.2f}) |")
    return "\n".join(rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", nargs="?", type=Path)
    p.add_argument("out", nargs="?", type=Path)
    p.add_argument("--meshes", type=Path, help="the real chairs' meshes/ folder (examples/real-chairs.sh)")
    p.add_argument("--part", help="procedural chairs: recolour this part of every chair that has it (e.g. legs)")
    p.add_argument("--summary", nargs="+", metavar="JSON", help="summarize `crfedit eval edits --json` reports instead")
    a = p.parse_args()
    if a.summary:
        print(summary(a.summary))
        return
    if a.data is None or a.out is None:
        p.error("give DATA and OUT (or --summary)")
    build(a.data, a.out, a.meshes, a.part)


if __name__ == "__main__":
    run_script(main)
