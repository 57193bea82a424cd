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


def _unexpected(e: BaseException) -> str:
    """One line for an error crfedit did not anticipate: its type, message, the path it names
    (if any) and the innermost crfedit line that raised it."""
    import traceback

    frames = [f for f in traceback.extract_tb(e.__traceback__) if "crfedit" in f.filename]
    where = f" at {frames[-1].filename.rsplit('crfedit', 1)[-1].lstrip('/')}:{frames[-1].lineno}" if frames else ""
    path = getattr(e, "filename", None)
    text = " ".join(str(e).split()) or "no message"
    named = f"{path}: " if path is not None and str(path) not in text else ""
    return f"unexpected {e.__class__.__name__}: {named}{text}{where} (for the traceback: crfedit --debug COMMAND …, the flag before the command, or CRFEDIT_DEBUG=1)"


def main() -> None:
    """Run the command line.  Usage errors (an unknown command or option, a value Typer cannot
    parse) are one line on stderr and exit 2, like every other bad input; an unexpected error is
    one line and exit 1, its traceback shown with ``--debug`` or ``CRFEDIT_DEBUG=1``.  A rank
    whose collective failed exits at once after its line (:func:`crfedit.distributed.broken`)."""
    try:
        _main()
    except SystemExit as e:
        _leave_a_broken_job(e.code)
        raise
    _leave_a_broken_job(0)


def _leave_a_broken_job(code) -> None:
    """``os._exit(code)`` when a collective of this process failed: no interpreter teardown, so
    no gloo connection to a dead rank is closed (which can abort with SIGABRT)."""
    import os
    import sys

    dist = sys.modules.get("crfedit.distributed")  # not imported: no job, nothing to leave
    if dist is not None and dist.broken():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code if isinstance(code, int) else 1)


def _main() -> None:
    import os
    import sys

    import typer

    try:  # Typer ≥ 0.2x vendors click; older Typer depends on it
        from typer._click import exceptions as click_errors
    except ImportError:  # pragma: no cover - depends on the installed Typer
        import click.exceptions as click_errors

    from ..errors import CrfError
    from ..threads import threads_choice
    from .common import Session, Terminated, debug_requested, terminate_as_interrupt, torchrun_ranks

    def rank_0() -> bool:
        """Whether this process says the command line's own errors: under torchrun rank 0
        alone (every rank parsed the same arguments)."""
        ranks = torchrun_ranks()
        return ranks is None or ranks.main

    def say(line: str) -> None:
        if rank_0():
            print(line, file=sys.stderr)

    # Typer 0.29 vendors click without its Abort; typer.Abort is what it raises on Ctrl-C.
    aborts = tuple({typer.Abort, getattr(click_errors, "Abort", typer.Abort)})
    if not rank_0() and {"--help", "--version"} & set(sys.argv[1:]):
        sys.stdout = open(os.devnull, "w")  # under torchrun the help (the version) is rank 0's to print, once
    try:
        terminate_as_interrupt()
        try:
            Session.threads, Session.threads_why = threads_choice()
        except CrfError as e:  # a bad CRFEDIT_THREADS / OMP_NUM_THREADS: --threads may override it, --help needs none
            Session.threads_error = e
        code = app(standalone_mode=False)
    except CrfError as e:
        say(f"error: {e}")
        raise SystemExit(2) from None
    except getattr(click_errors, "NoArgsIsHelpError", ()) as e:  # a group or command called bare: its help
        if rank_0():
            e.show()
        raise SystemExit(2) from None
    except click_errors.UsageError as e:
        hint = f" (see '{e.ctx.command_path} --help')" if e.ctx is not None else ""
        for flag in ("--debug", "--threads"):  # a root flag given after the command
            if e.format_message().startswith(f"No such option: {flag}"):
                hint = f" ({flag} goes before the command: crfedit {flag}{' N' * (flag == '--threads')} COMMAND …)"
        # Typer 0.29 checks choices with pydantic, whose line reads "Value error, 'gpu' is not one of ..."
        say(f"error: {' '.join(e.format_message().split()).replace(': Value error, ', ': ')}{hint}")
        raise SystemExit(2) from None
    except click_errors.ClickException as e:
        say(f"error: {' '.join(e.format_message().split())}")
        raise SystemExit(e.exit_code) from None
    except (*aborts, KeyboardInterrupt) as e:
        say("error: aborted")
        raise SystemExit(143 if isinstance(e, Terminated) else 130) from None
    except Exception as e:
        if debug_requested():
            raise
        print(f"error: {_unexpected(e)}", file=sys.stderr)
        raise SystemExit(1) from None
    if code == 130 and Session.terminated:  # SIGTERM while Typer built the command: it exits 130, silently
        say("error: terminated (SIGTERM)")
        raise SystemExit(143)
    if isinstance(code, int) and code != 0:
        raise SystemExit(code)
