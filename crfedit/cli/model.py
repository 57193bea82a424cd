"""``crfedit model strip``: a shareable copy of a model file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..names import MODEL_FORMAT
from .common import app, check_out_file, size_text, user_errors

model_app = typer.Typer(help="Shareable model files.", no_args_is_help=True)
app.add_typer(model_app, name="model")



@model_app.command("strip")
@user_errors
def strip_cmd(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="Model file (.safetensors) written by crfedit train.")],
    out: Annotated[Path, typer.Option("--out", metavar="SMALL", help="Model file to write, without the training state.")],
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --out model instead of refusing.")] = False,
) -> None:
    """Copy a model without its training state (optimizer moments, occupancy statistics).

    The copy renders, edits and bakes exactly like the original; only --resume needs the state.
    """
    from ..modelfile import strip_model

    check_out_file(out, {"MODEL": model}, "stripped model", "small.safetensors", MODEL_FORMAT, overwrite)
    before = model.stat().st_size if model.is_file() else 0
    sizes = strip_model(model, out)
    after = out.stat().st_size
    dropped = "training state dropped" if after < before else "it held no training state (a copy)"
    typer.echo(f"wrote {out} ({size_text(after)}) from {model} ({size_text(before)}): {dropped}, "
               f"weights {size_text(sizes['weights'])}, codes {size_text(sizes['codes'])}, occupancy {size_text(sizes['occupancy'])}")
