"""Shared pieces of the CLI: the Typer apps, error handling, common options."""

from __future__ import annotations

import enum
import functools
import sys
from typing import Annotated

import typer

from ..errors import EXIT_USER_ERROR, CrfError

app = typer.Typer(
    name="crfedit",
    help="Train, render and edit conditional radiance fields of object categories.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
dataset_app = typer.Typer(help="Make and inspect category datasets.", no_args_is_help=True)
edits_app = typer.Typer(help="Inspect, check and bake edit files.", no_args_is_help=True)
eval_app = typer.Typer(help="Evaluate reconstruction and edits against ground truth.", no_args_is_help=True)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        import torch

        try:
            ours = version("crfedit")
        except PackageNotFoundError:  # run from a source tree without installing
            ours = "unknown (not installed)"
        typer.echo(f"crfedit {ours} (torch {torch.__version__})")
        raise typer.Exit()


@app.callback()
def _root(
    show_version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")] = False,
) -> None:
    """Train, render and edit conditional radiance fields of object categories."""


app.add_typer(dataset_app, name="dataset")
app.add_typer(edits_app, name="edits")
app.add_typer(eval_app, name="eval")


def printable(text: object) -> str:
    """``text`` with control characters (ESC, BEL, …) escaped: strings from shared files must
    not be able to drive the user's terminal."""
    return "".join(c if c.isprintable() or c in "\n\t" else repr(c)[1:-1] for c in str(text))


def fail(message: str) -> "typer.Exit":
    """Print ``error: message`` to stderr and return the exit to raise (code 2)."""
    typer.echo(f"error: {printable(' '.join(str(message).split()))}", err=True)
    return typer.Exit(EXIT_USER_ERROR)


def user_errors(fn):
    """Decorator for commands: a CrfError (or a broken pipe / Ctrl-C) exits cleanly, no traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except CrfError as e:
            raise fail(str(e)) from None
        except KeyboardInterrupt:
            typer.echo("interrupted", err=True)
            raise typer.Exit(130) from None
        except MemoryError:
            raise fail("out of memory (try a smaller --res, --rays or --chunk)") from None

    return wrapper


class DeviceChoice(str, enum.Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


DeviceOpt = Annotated[DeviceChoice, typer.Option("--device", help="Where to compute: auto picks cuda when available.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed; the same seed gives the same result.")]
AaOpt = Annotated[
    int, typer.Option("--aa", help="Antialiasing: aa×aa rays per pixel, box-filtered (1 = one ray per pixel center, aliased).")
]


def command_line() -> str:
    """The command line as typed, for edit/model metadata."""
    return " ".join(["crfedit", *sys.argv[1:]])
