"""``crfedit export mesh``: an instance's surface as a vertex-coloured mesh."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import CrfError
from ..io import check_replaceable
from ..names import MIN_PIECE
from .common import DeviceChoice, DeviceOpt, app, stderr_progress, user_errors

export_app = typer.Typer(help="Export an instance as a mesh.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@export_app.command("mesh")
@user_errors
def mesh_cmd(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="Model file (.safetensors).")],
    instance: Annotated[str, typer.Option("--instance", help="Instance to export: a name or an index.")],
    out: Annotated[Path, typer.Option("--out", metavar="MESH", help="Mesh file: .ply, .obj or .glb (with vertex colours; .glb turned Y-up, as glTF is), .off or .stl.")],
    edit: Annotated[Optional[list[Path]], typer.Option("--edit", metavar="EDIT", help="Apply this edit file first (repeatable, in order).")] = None,
    res: Annotated[int, typer.Option("--res", help="Marching-cubes lattice points per side of the scene box, 8–1024 (the density volume is 4·N³ bytes: 67 MB at 256, 4.3 GB at 1024; time grows as N³ too).")] = 256,
    level: Annotated[Optional[float], typer.Option("--level", help="Density σ of the surface (default: ln 2 / render step, where one step is half opaque).")] = None,
    min_piece: Annotated[float, typer.Option("--min-piece", metavar="SHARE", help="Drop pieces (connected components) with fewer faces than this share of the largest piece's: floaters (0 keeps every piece).")] = MIN_PIECE,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Extract the density level set by marching cubes over the occupied cells, with vertex
    colours from the radiance seen along each vertex normal (like nerfstudio's ns-export)."""
    from ..export import MESH_SUFFIXES, drop_small_pieces, extract_mesh, write_mesh
    from ..model import load_model
    from ..runtime import resolve_device

    check_replaceable(out, "--out", MESH_SUFFIXES)
    if not 0 <= min_piece < 1:
        raise CrfError(f"--min-piece {min_piece:g}: expected a share of the largest piece's faces from 0 (keep every piece) to below 1")
    m, _ = load_model(model, resolve_device(device))
    if edit:
        from ..delta import apply_edit_files

        m = apply_edit_files(m, list(edit))
    k = m.instance_index(instance)
    if edit and k not in m.overrides:  # as render says it: likely a slip
        typer.echo(f"note: the --edit files edit other instances than {m.names[k]}: they leave this mesh unchanged", err=True)
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

    from .dataset import _rate_column

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), _rate_column(), TimeRemainingColumn())
    with stderr_progress(*columns) as bar:  # the density lattice is most of the time: minutes at --res 512 on a CPU
        task = bar.add_task(f"σ on the {res}³ lattice (planes)", total=res)
        mesh = extract_mesh(m, k, res, level, on_planes=lambda n: bar.update(task, advance=n))
    mesh, dropped = drop_small_pieces(mesh, min_piece)
    write_mesh(mesh, out)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    typer.echo(
        f"wrote {out}: {m.names[k]}, {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces at σ = {mesh.level:.4g}, "
        f"extent [{', '.join(f'{x:.3f}' for x in lo)}] .. [{', '.join(f'{x:.3f}' for x in hi)}]"
        + (" in crfedit's Z-up world (the .glb holds it turned Y-up)" if out.suffix.lower() == ".glb" else "")
        + (f"; dropped {dropped} floater{'s' if dropped != 1 else ''} (pieces under {min_piece:g} of the largest's faces; --min-piece 0 keeps them)"
           if dropped else "")
    )
