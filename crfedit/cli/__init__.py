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
    import sys

    from ..errors import CrfError
    from ..runtime import configure_threads

    try:
        configure_threads()
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    app()
