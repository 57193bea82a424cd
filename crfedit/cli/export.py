"""``crfedit export mesh``: an instance's surface as a vertex-coloured mesh."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..io import check_replaceable
from .common import DeviceChoice, DeviceOpt, app, user_errors

export_app = typer.Typer(help="Export an instance as a mesh.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@export_app.command("mesh")
@user_errors
def mesh_cmd(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="Model file (.safetensors).")],
    instance: Annotated[str, typer.Option("--instance", help="Instance to export: a name or an index.")],
    out: Annotated[Path, typer.Option("--out", metavar="MESH", help="Mesh file: .ply or .obj (vertex colours), .glb, .off, .stl.")],
    edit: Annotated[Optional[list[Path]], typer.Option("--edit", metavar="EDIT", help="Apply this edit file first (repeatable, in order).")] = None,
    res: Annotated[int, typer.Option("--res", help="Marching-cubes lattice points per side of the scene box.")] = 256,
    level: Annotated[Optional[float], typer.Option("--level", help="Density σ of the surface (default: ln 2 / render step, where one step is half opaque).")] = None,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Extract the density level set by marching cubes over the occupied cells, with vertex
    colours from the radiance seen along each vertex normal (like nerfstudio's ns-export)."""
    from ..export import MESH_SUFFIXES, extract_mesh, write_mesh
    from ..model import load_model
    from ..runtime import resolve_device

    check_replaceable(out, "--out", MESH_SUFFIXES)
    m, _ = load_model(model, resolve_device(device))
    if edit:
        from ..delta import apply_edit_files

        m = apply_edit_files(m, list(edit))
    k = m.instance_index(instance)
    if edit and k not in m.overrides:  # as render says it: likely a slip
        typer.echo(f"note: the --edit files edit other instances than {m.names[k]}: they leave this mesh unchanged", err=True)
    mesh = extract_mesh(m, k, res, level)
    write_mesh(mesh, out)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    typer.echo(
        f"wrote {out}: {m.names[k]}, {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces at σ = {mesh.level:.4g}, "
        f"extent [{', '.join(f'{x:.3f}' for x in lo)}] .. [{', '.join(f'{x:.3f}' for x in hi)}]"
    )
