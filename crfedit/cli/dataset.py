"""``crfedit dataset synth`` and ``crfedit dataset info``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ..errors import CrfError
from .common import AaOpt, SeedOpt, TwinSourcesOpt, dataset_app, echo_notes, printable, stderr_progress, user_errors


def _rate_column():
    from rich.progress import ProgressColumn
    from rich.text import Text

    class RateColumn(ProgressColumn):
        """Steps per second."""

        def render(self, task) -> Text:
            return Text("?/s" if not task.speed else f"{task.speed:.2f}/s", style="progress.data.speed")

    return RateColumn()


@dataset_app.command("synth")
@user_errors
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the category to (new, or a previous synth output).")],
    instances: Annotated[int, typer.Option("--instances", help="Number of chairs.")] = 24,
    views: Annotated[int, typer.Option("--views", help="Views per chair, split 80/10/10 into train/val/test.")] = 50,
    res: Annotated[int, typer.Option("--res", help="Image width and height in pixels.")] = 64,
    seed: SeedOpt = 0,
    twins: Annotated[bool, typer.Option("--twins/--no-twins", help="Also write ground-truth color/removal twins.")] = True,
    twin_sources: TwinSourcesOpt = 4,
    aa: AaOpt = 3,
) -> None:
    """Render procedural chairs with depth, part maps and edit twins."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

    from ..data.synth import SynthConfig, check_synth_args, synth_steps, write_synth_category

    config = SynthConfig(instances=instances, views=views, res=res, seed=seed, twins=twins, aa=aa, twin_sources=twin_sources)
    check_synth_args(out, config)
    replaced = (out / "instances.txt").is_file()  # check_synth_args let it through: an earlier synth output
    columns = (TextColumn("{task.description:<18}"), BarColumn(), MofNCompleteColumn(), _rate_column(), TimeRemainingColumn())
    with stderr_progress(*columns) as bar:
        task = bar.add_task("chairs", total=synth_steps(config))
        result = write_synth_category(out, config, lambda label: bar.update(task, advance=1, description=label))
    typer.echo(
        f"wrote {len(result.names)} chairs x {views} views at {res}x{res}"
        f" + {len(result.twins)} twins to {out} in {result.seconds:.1f} s" + replaced_note(replaced, result.kept)
    )


def replaced_note(replaced: bool, kept: list[str]) -> str:
    """What a dataset build says of the folder it replaced: that it did, and the user's entries
    it carried over (notes, scribbles: everything that was not the dataset's)."""
    if not replaced:
        return ""
    return " (it replaced the dataset that was there" + (f"; kept what was not the dataset's: {', '.join(kept)})" if kept else ")")


def _vec(values: list[float]) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in values) + "]"


@dataset_app.command("info")
@user_errors
def info(
    data: Annotated[Path, typer.Argument(help="Category folder (instances.txt) or a NeRF-synthetic scene folder.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Summarize a dataset: instances, views, size, bbox, fingerprint."""
    from ..data.loading import dataset_info, load_category
    from ..train import check_hulls, dataset_notes, scene_box, visual_hulls

    category = load_category(data, with_depth=True)
    echo_notes(category)
    meta = dataset_info(category)
    if as_json:
        typer.echo(json.dumps(meta, indent=2))
        return
    names = meta["names"]
    shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
    views = ", ".join(
        f"{split} {total} ({lo if lo == hi else f'{lo}-{hi}'} per instance)"
        for (split, total), (lo, hi) in zip(meta["views"].items(), meta["views_per_instance"].values())
    )
    box = meta["bbox"]
    rows = [
        ("root", meta["root"]),
        ("instances", f"{meta['instances']}: {shown}"),
        ("views", views),
        ("resolution", ", ".join(meta["resolutions"])),
        ("bbox", f"{_vec(box['min'])} .. {_vec(box['max'])} "
                 + ("(from depth)" if box["source"] == "depth" else "(of the camera positions: no depth maps place the object)")),
        ("twins", str(meta["twins"])),
        ("fingerprint", meta["fingerprint"]),
    ]
    for key, value in rows:
        typer.echo(f"{key:<12} {value}")
    for note in dataset_notes(category):  # what train would say, said first
        typer.echo(printable(f"note: {note}"), err=True)
    bare = meta["without_train_views"]
    if not bare:  # (an instance without train views is said below: train refuses that first)
        try:
            check_hulls(category, visual_hulls(category, scene_box(category), 32, 0))  # an empty hull: OpenCV poses
        except CrfError as e:
            typer.echo(printable(f"warning: {e} (train refuses the dataset)"), err=True)
    if bare:
        typer.echo(f"warning: {len(bare)} instance{'s' * (len(bare) != 1)} without train views ({', '.join(bare[:4])}"
                   f"{', ...' if len(bare) > 4 else ''}): train refuses the dataset until each has some", err=True)
