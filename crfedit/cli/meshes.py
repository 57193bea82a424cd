"""``crfedit dataset from-meshes``: a category rendered from real mesh files."""

from __future__ import annotations

import enum
from pathlib import Path
from typing import Annotated

import typer

from .common import AaOpt, SeedOpt, TwinSourcesOpt, dataset_app, printable, stderr_progress, user_errors


class PaletteChoice(str, enum.Enum):
    random = "random"
    mtl = "mtl"


class UpChoice(str, enum.Enum):
    z = "z"
    y = "y"


@dataset_app.command("from-meshes")
@user_errors
def from_meshes(
    out: Annotated[Path, typer.Argument(help="Folder to write the category to (new, or a previous dataset).")],
    meshes: Annotated[list[Path], typer.Argument(help="Mesh files (OBJ+MTL, PLY, GLB/glTF, OFF, STL), one instance each.")],
    views: Annotated[int, typer.Option("--views", help="Views per mesh, split 80/10/10 into train/val/test.")] = 50,
    res: Annotated[int, typer.Option("--res", help="Image width and height in pixels.")] = 64,
    seed: SeedOpt = 0,
    palette: Annotated[
        PaletteChoice, typer.Option("--palette", help="Part colors: random (synth's palette) or mtl (the material's own color).")
    ] = PaletteChoice.random,
    up: Annotated[UpChoice, typer.Option("--up", help="The files' up axis: z, or y (most OBJ files, every glTF).")] = UpChoice.z,
    twins: Annotated[bool, typer.Option("--twins/--no-twins", help="Also write ground-truth color/removal twins.")] = True,
    twin_sources: TwinSourcesOpt = 4,
    aa: AaOpt = 3,
) -> None:
    """Render mesh files as a category: parts from material groups, depth and part maps, twins.

    Each mesh is centered, scaled to unit size and turned Z-up; a sidecar <stem>.meta.json may
    give its attribution (written to ATTRIBUTION.txt) and a rotation.  Needs the [meshes] extra.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

    from ..data.meshes import MeshDatasetConfig, mesh_steps, write_mesh_category
    from .dataset import _rate_column, replaced_note

    replaced = (out / "instances.txt").is_file()  # the build's check let it through: an earlier dataset
    config = MeshDatasetConfig(views=views, res=res, seed=seed, palette=palette.value, up=up.value, twins=twins, aa=aa, twin_sources=twin_sources)
    columns = (TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(), _rate_column(), TimeRemainingColumn())
    with stderr_progress(*columns) as bar:
        task = bar.add_task("loading meshes", total=mesh_steps(len(meshes), config))
        result = write_mesh_category(out, meshes, config, lambda label: bar.update(task, advance=1, description=label))
    n, parts, t = len(result.names), sum(result.parts), len(result.twins)
    typer.echo(
        f"wrote {n} mesh{'es' * (n != 1)} ({parts} part{'s' * (parts != 1)}) x {views} view{'s' * (views != 1)} at {res}x{res}"
        f" + {t} twin{'s' * (t != 1)} to {out} in {result.seconds:.1f} s" + replaced_note(replaced, result.kept)
    )
    for note in result.notes:
        typer.echo(printable(f"note: {note}"), err=True)
