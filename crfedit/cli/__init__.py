"""The ``crfedit`` command line: thin Typer commands over the library API.

Each command group lives in its own module and registers itself on :data:`app` when imported;
:func:`main` imports them all.  Commands hold no math: they parse options, call the library and
print.  A :class:`~crfedit.errors.CrfError` becomes one line on stderr and exit code 2.
"""

from .common import app


def _register() -> None:
    import importlib
    import pkgutil

    for mod in pkgutil.iter_modules(__path__):
        if mod.name != "common":
            importlib.import_module(f"{__name__}.{mod.name}")


_register()


def main() -> None:
    """Run the command line.  Usage errors (an unknown command or option, a value Typer cannot
    parse) are one line on stderr and exit 2, like every other bad input."""
    import sys

    try:  # Typer ≥ 0.2x vendors click; older Typer depends on it
        from typer._click import exceptions as click_errors
    except ImportError:  # pragma: no cover - depends on the installed Typer
        import click.exceptions as click_errors

    from ..errors import CrfError
    from ..runtime import configure_threads

    try:
        configure_threads()
        code = app(standalone_mode=False)
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    except getattr(click_errors, "NoArgsIsHelpError", ()) as e:  # a group or command called bare: its help
        e.show()
        raise SystemExit(2) from None
    except click_errors.UsageError as e:
        hint = f" (see '{e.ctx.command_path} --help')" if e.ctx is not None else ""
        print(f"error: {' '.join(e.format_message().split())}{hint}", file=sys.stderr)
        raise SystemExit(2) from None
    except click_errors.ClickException as e:
        print(f"error: {' '.join(e.format_message().split())}", file=sys.stderr)
        raise SystemExit(e.exit_code) from None
    except click_errors.Abort:
        print("error: aborted", file=sys.stderr)
        raise SystemExit(130) from None
    if isinstance(code, int) and code != 0:
        raise SystemExit(code)
