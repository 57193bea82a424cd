"""User-facing errors: one line, exit code 2, no traceback.

Library code raises :class:`CrfError` (or a subclass) for anything a user can cause — a
missing file, a malformed JSON, an unknown instance, an empty scribble.  The CLI catches it,
prints ``error: <message>`` to stderr and exits with :data:`EXIT_USER_ERROR`.  Programming
errors stay ordinary exceptions so they keep their traceback.
"""

from __future__ import annotations

EXIT_USER_ERROR = 2


class CrfError(Exception):
    """An error caused by user input; its message is a single line that names the problem."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


class DataError(CrfError):
    """A dataset on disk is missing, malformed or inconsistent."""


class ModelFileError(CrfError):
    """A model or edit file is missing, corrupt, or does not belong to this model."""


class NonFiniteError(CrfError):
    """Optimization produced a NaN/inf; nothing was written."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, ``kill``, a scheduler's stop) taken as Ctrl-C, so that the same
    clean-up runs (no half-written output, run records as they were); the CLI exits 143."""


def run_script(main) -> None:
    """Run a script's ``main()`` (benchmarks/) as the CLI runs a command: a :class:`CrfError`
    (or a missing file it reads itself) is one line, ``error: <message>``, on stderr and exit
    :data:`EXIT_USER_ERROR`, not a traceback (a missing model file printed 15 lines); otherwise
    exit with what it returns."""
    import sys

    try:
        code = main()
    except CrfError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    except FileNotFoundError as e:  # a path given on its command line, read by a script directly
        print(f"error: {e.filename or e}: not found", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    sys.exit(code or 0)
