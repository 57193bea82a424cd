"""Shared pieces of the CLI: the Typer apps, error handling, common options."""

from __future__ import annotations

import contextlib
import enum
import errno
import functools
import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import EXIT_USER_ERROR, CrfError, Terminated
from ..names import EDIT_FORMAT, MODEL_FORMAT, SELECTION_FORMAT
from ..threads import MAX_THREADS

def _readable(param) -> None:
    """Give a click parameter a readable metavar: its name in capitals (MODEL, EDIT), N for an
    integer, X for a number; choices stay as they are."""
    desc = getattr(param, "type_descriptor", None)  # Typer ≥ 0.2x; older Typer: click's param.type
    annotation = getattr(desc, "annotation", None)
    kind = "choice" if getattr(desc, "is_choice", False) else getattr(annotation, "__name__", getattr(getattr(param, "type", None), "name", ""))
    if param.param_type_name == "argument":
        label = param.metavar or param.name.upper()
        param.metavar = label
        display = (label if param.required else f"[{label}]") + ("..." if param.nargs != 1 else "")
        param._usage_display_name = lambda: display  # Typer 0.29 writes {model}
        # Typer 0.27 asks make_metavar(ctx, usage=True) for the usage line instead, and writes {MODEL}
        param.make_metavar = lambda *args, usage=False, **kwargs: display if usage else label
    elif not (getattr(param, "is_flag", False) or getattr(param, "count", False) or kind == "choice"):
        param.metavar = {"int": "N", "integer": "N", "float": "X"}.get(kind, param.name.upper().replace("_", "-"))


def _readable_tree(command) -> None:
    for param in command.params:
        if param.metavar is None or param.param_type_name == "argument":  # a named argument too: Typer writes {MODEL}
            _readable(param)
    for sub in getattr(command, "commands", {}).values():
        _readable_tree(sub)


class ReadableGroup(typer.core.TyperGroup):
    """The root command group: on construction, every parameter of every (sub)command without a
    metavar gets a readable one (Typer 0.29 prints ``{model}`` and ``<list[Path]>``)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        _readable_tree(self)

    def parse_args(self, ctx, args):
        problem = repeated_option(self, args)
        if problem is not None:
            raise _one_line_usage_error(problem)
        return super().parse_args(ctx, args)


def _one_line_usage_error(message: str) -> Exception:
    """A click exception that says ``error: message`` in one line and exits 2, from
    :func:`crfedit.cli.main` and from Typer's own runner (a CliRunner) alike."""
    try:  # Typer ≥ 0.2x vendors click; older Typer depends on it
        from typer._click.exceptions import ClickException
    except ImportError:  # pragma: no cover - depends on the installed Typer
        from click.exceptions import ClickException

    class OneLine(ClickException):
        exit_code = EXIT_USER_ERROR

        def show(self, file=None) -> None:
            print(f"error: {self.format_message()}", file=sys.stderr)

    return OneLine(message)


SCRIBBLE_OPTIONS = ("view", "scribble", "scribble_json", "keep", "keep_json")
"""The options of one scribbled view: ``select`` repeats them, the edits take one set."""


def repeated_option(group, args: list[str]) -> str | None:
    """Why ``args`` (the command line after ``crfedit``) is refused, or None: an option that takes
    one value given more than once.  Click keeps the last silently, so ``remove --view train:23
    --scribble a.png --view train:22 --scribble b.png`` removed what the second view alone
    selects while its file recorded both views."""
    command, rest, path = group, list(args), []
    while hasattr(command, "commands"):  # down to the command the words name
        words = [i for i, a in enumerate(rest) if not a.startswith("-")]
        if not words or rest[: words[0]].count("--") or rest[words[0]] not in command.commands:
            return None  # click says what is wrong with it
        command, path, rest = command.commands[rest[words[0]]], path + [rest[words[0]]], rest[words[0] + 1 :]
    single = {o: p for p in command.params if p.param_type_name == "option" and not (p.multiple or p.count or p.is_flag) for o in p.opts}
    seen: dict[str, list[str]] = {}
    for a in rest[: rest.index("--")] if "--" in rest else rest:
        p = single.get(a.split("=", 1)[0])
        if p is not None:
            seen.setdefault(p.name, []).append(a.split("=", 1)[0])
    for name, given in seen.items():
        if len(given) > 1:
            hint = ""
            if name in SCRIBBLE_OPTIONS and "select" in group.commands:
                hint = (": an edit is drawn on one view; to select a part from several, repeat --view/--scribble/--keep in "
                        "`crfedit select` and pass its file as --selection")
            return f"{given[0]} given {len(given)} times; `crfedit {' '.join(path)}` takes one{hint}"
    return None


app = typer.Typer(
    name="crfedit",
    cls=ReadableGroup,
    help="Train, render and edit conditional radiance fields of object categories.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
dataset_app = typer.Typer(help="Make and inspect category datasets.", no_args_is_help=True)
edits_app = typer.Typer(help="Inspect, check, re-pin (rebase) and bake edit files.", no_args_is_help=True)
eval_app = typer.Typer(help="Evaluate reconstruction and edits against ground truth.", no_args_is_help=True)


class Session:
    """Process-wide CLI settings that :func:`crfedit.cli.main` decides before a command runs."""

    debug = False
    """Show the traceback of an unexpected error (``--debug`` or ``CRFEDIT_DEBUG=1``)."""
    threads: int | None = None
    """torch CPU threads to set when a command starts (None: leave torch as it is)."""
    threads_why: str = ""
    """What decided :attr:`threads` (:func:`crfedit.threads.threads_choice`), for ``train`` to say."""
    threads_error: CrfError | None = None
    """Why the environment's thread count could not be read; raised when a command runs without
    ``--threads`` (``--help`` and ``--version`` need none)."""
    terminated: bool = False
    """SIGTERM arrived (:func:`terminate_as_interrupt`): what the command line reads when Typer
    took the exception for Ctrl-C and exited 130."""


def debug_requested() -> bool:
    return Session.debug or os.environ.get("CRFEDIT_DEBUG", "").strip() not in ("", "0")


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
    debug: Annotated[bool, typer.Option("--debug", help="Show the full traceback of an unexpected error (also CRFEDIT_DEBUG=1).")] = False,
    threads: Annotated[Optional[int], typer.Option("--threads", min=1, max=MAX_THREADS, help="torch CPU threads for the command (also CRFEDIT_THREADS=N; default: the cores the machine's load leaves free).")] = None,
) -> None:
    """Train, render and edit conditional radiance fields of object categories."""
    Session.debug = Session.debug or debug
    if threads is not None:  # before the command runs: user_errors sets torch's threads from Session
        Session.threads, Session.threads_why, Session.threads_error = threads, f"--threads {threads}", None


app.add_typer(dataset_app, name="dataset")
app.add_typer(edits_app, name="edits")
app.add_typer(eval_app, name="eval")


def printable(text: object) -> str:
    """``text`` with control characters (ESC, BEL, …) escaped: strings from shared files must
    not be able to drive the user's terminal."""
    return "".join(c if c.isprintable() or c in "\n\t" else repr(c)[1:-1] for c in str(text))


def table_row(key: str, value: object, width: int = 13) -> str:
    """One row of a file's table (``edits show``, ``info``): the key padded to ``width``
    columns, key and value :func:`printable` with their line breaks escaped too, so a key or
    value read from a shared file cannot print a row of its own (a forged ``fingerprint`` line)."""
    def one_line(text: object) -> str:  # escaped before padding, so a row's columns line up
        return printable(text).replace("\t", "\\t").replace("\r", "\\r").replace("\n", "\\n")

    return f"{one_line(key):<{width}} " + one_line(value)  # a key read from a file too


def instance_option(model, value, option: str) -> int:
    """``model.instance_index(value)`` for an option other than ``--instance``: its error line
    names the option (``--color-from: unknown instance …``), not just the value."""
    try:
        return model.instance_index(value)
    except CrfError as e:
        raise CrfError(f"{option}: {e}") from None


def size_text(n: float) -> str:
    """A byte count as every command prints it, in decimal units (B, KB, MB, GB) as the docs give
    sizes: ``66 200`` → ``66.2 KB``."""
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return ""


def fail(message: str) -> "typer.Exit":
    """Print ``error: message`` to stderr and return the exit to raise (code 2)."""
    typer.echo(f"error: {printable(' '.join(str(message).split()))}", err=True)
    return typer.Exit(EXIT_USER_ERROR)


OS_ERROR_HINTS = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
}


def os_error_message(e: OSError) -> str:
    """One line for an operating-system error: the path(s) and what went wrong."""
    what = OS_ERROR_HINTS.get(e.errno) or (e.strerror or e.__class__.__name__).lower()
    paths = [str(p) for p in (e.filename, e.filename2) if p is not None]
    return f"{' -> '.join(paths)}: {what}" if paths else what


OTHER_KINDS = frozenset((".ply", ".obj", ".glb", ".gltf", ".off", ".stl", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".bmp",
                         ".exr", ".hdr", ".gif", ".mp4", ".webm", ".json", ".csv", ".md", ".txt", ".npy", ".npz", ".pt", ".pth", ".ckpt"))
"""Suffixes of the other kinds of files (meshes, images, videos, tables, arrays, pickles): a
model, edit or selection written under one (``model strip --out s.ply``) was refused later as
"not a PLY file"."""


def check_kind_suffix(out: Path, what: str, example: str, label: str) -> None:
    """Refuse an output ``out`` named as another kind of file (:data:`OTHER_KINDS`) for a
    ``what`` (model, edit, selection), which crfedit writes as safetensors."""
    if out.suffix.lower() in OTHER_KINDS:
        article = "an" if what[:1] in "aeiou" else "a"
        raise CrfError(f"{label}: {article} {what} is written as .safetensors, not {out.suffix} (that names another kind of file); "
                       f"give a name such as {example}")


def check_out_file(out: Path, inputs: dict[str, object], what: str = "edit", example: str = "edit.safetensors",
                   writes: str = EDIT_FORMAT, overwrite: bool = False, label: str | None = None,
                   instead: str = "pick another name") -> None:
    """A command's one ``--out`` file, checked before any work: not one of the files the command
    reads (``inputs``: the option's name → a path, a list of paths or None; ``MODEL`` for the
    model argument), since the finished write would replace it; not a folder, device or pipe;
    not a non-empty file that is not crfedit's (a photo or notes, lost to a typo); not a crfedit
    file of another kind than the one it ``writes`` (an edit written over a copy of a model); not
    a model when it writes one, unless ``overwrite`` (a model took training to make, as
    ``train --overwrite``); not named as another kind of file (:data:`OTHER_KINDS`); in a
    folder that exists and can be written.  An edit or selection
    replaces one of its own kind, or an empty file (``mktemp``): both are seconds to remake.
    ``label`` starts the error lines (default ``--out OUT``); ``instead`` ends them (a folder
    option's outputs are named after its inputs: "pick another folder")."""
    label = label or f"--out {out}"
    if out.exists():
        for option, given in inputs.items():
            for path in [given] if isinstance(given, (str, Path)) else list(given or []):
                if Path(path).exists() and os.path.samefile(out, path):
                    name = "the model file" if option == "MODEL" else f"the {option} file"
                    raise CrfError(f"{label}: is {name}; pick another name for the {what}")
    check_kind_suffix(out, what, example, label)
    if out.exists():
        if out.is_dir():
            raise CrfError(f"{label}: is a folder; give a file name such as {example}")
        if not out.is_file():
            raise CrfError(f"{label}: is not a regular file (a device or pipe); give a file name such as {example}")
        from ..safefile import file_format

        held = file_format(out)  # None: not a crfedit file
        kinds = {MODEL_FORMAT: "model", EDIT_FORMAT: "edit", SELECTION_FORMAT: "selection"}
        if held not in kinds and out.stat().st_size > 0:
            raise CrfError(f"{label}: holds a file that is not crfedit's, which the {what} would replace; {instead}")
        if held != writes:
            if held in kinds:
                raise CrfError(f"{label}: is a crfedit {kinds[held]} file, which the {what} would replace; {instead}")
        elif held == MODEL_FORMAT and not overwrite:
            raise CrfError(f"{label}: is a crfedit model already; replace it with --overwrite, or {instead}")
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        under = next((p for p in (folder, *folder.parents) if p.exists()), None)
        if under is not None and not under.is_dir():  # a file where a folder should be
            raise CrfError(f"{label}: {under} is a file, not a folder")
        # refused, not made: a typo's folder would hold the one file nobody looks for
        raise CrfError(f"{label}: folder {folder} does not exist (make it first: mkdir -p {folder})")
    if not os.access(folder, os.W_OK):
        raise CrfError(f"{label}: folder {folder} is not writable")


def stderr_progress(*columns):
    """A rich progress bar of ``columns`` on stderr, drawn only on a terminal and gone when it
    ends: stdout keeps the command's results, and a log or an error line stays clean."""
    from rich.console import Console
    from rich.progress import Progress

    console = Console(stderr=True)
    return Progress(*columns, console=console, transient=True, disable=not console.is_terminal)


def torchrun_ranks():
    """This process's :class:`~crfedit.distributed.Ranks` under torchrun, None for a plain run
    (torch is imported only then).  Values torchrun would not set count as a plain run here: the
    command's own :func:`~crfedit.distributed.ranks_from_env` names them."""
    if "WORLD_SIZE" not in os.environ and "RANK" not in os.environ:
        return None
    from ..distributed import ranks_from_env

    try:
        return ranks_from_env()
    except CrfError:
        return None


def terminate_as_interrupt() -> None:
    """Make SIGTERM raise :class:`Terminated` in the main thread, unless something else
    already handles it.  Without this a killed render left its hidden part-built folder and a
    killed training run records that described no model."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return

    def handler(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM during the clean-up ends it at once
        Session.terminated = True  # what main reads when Typer took the exception as Ctrl-C (its exit 130)
        raise Terminated()

    signal.signal(signal.SIGTERM, handler)


def out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is an allocation that failed: Python's MemoryError, torch's on a CPU (a
    RuntimeError, "DefaultCPUAllocator: not enough memory: you tried to allocate …", which read
    as an unexpected error) or on a GPU (``torch.OutOfMemoryError``)."""
    return (isinstance(error, MemoryError) or type(error).__name__ == "OutOfMemoryError"
            or (isinstance(error, RuntimeError) and "not enough memory" in str(error)))


def _says_it(error: BaseException) -> bool:
    """Whether this process prints ``error``.  Under torchrun a rank other than 0 keeps quiet
    about Ctrl-C, and so does one other than its node's first (``LOCAL_RANK`` 0) about a user
    error met before its process group formed: it read the same arguments and files as that
    one, whose line says it (one line per node, not one per rank).  Each node's first process
    says it: another node's files may differ (a dataset missing there printed nothing, and rank
    0 waited out the join's timeout).  Errors of its own (a collective, its device, its disk)
    every rank prints, its rank named, and so any error met once the group formed (each rank's
    work is its own share: rank 1's twin whose edit diverged printed nothing, rank 0 was
    stopped by torchrun)."""
    ranks = torchrun_ranks()
    if ranks is None or ranks.main:
        return True
    if isinstance(error, KeyboardInterrupt) or getattr(error, "echoed", False):  # rank 0 says the same line
        return False
    if ranks.local_rank == 0:
        return True
    from ..distributed import DistributedError, joined

    # joined: the error met this rank's own share of the work (an edit of its twin diverged), and
    # the group is torn down by the time it gets here (so is_initialized() no longer says so)
    return not isinstance(error, CrfError) or isinstance(error, DistributedError) or joined()


OUTPUTS = ("out", "out_dir", "preview", "video", "csv_path", "md_path", "models", "work", "workdir")
"""The parameters (by name) through which commands take a file or folder to write."""


def check_not_stdout(fn, kwargs: dict) -> None:
    """``-`` given to command ``fn`` for an output (:data:`OUTPUTS`) is a user error: crfedit
    writes files, and a ``-`` taken as a name makes a file or folder called ``-``."""
    for name in OUTPUTS:
        if str(kwargs.get(name)) == "-":
            import typing

            hint = typing.get_type_hints(fn, include_extras=True).get(name)
            decls = [d for m in getattr(hint, "__metadata__", ()) for d in (getattr(m, "default", None), *(getattr(m, "param_decls", None) or ()))
                     if isinstance(d, str) and d.startswith("--")]  # typer.Option("--out") keeps the name as its default
            raise CrfError(f"{decls[0] if decls else name.upper()} -: crfedit writes files, not standard output; "
                           "give a file or folder name (./- for one named -)")


JsonOpt = Annotated[bool, typer.Option("--json", help="Print the written file's record as JSON on stdout (what `crfedit info FILE --json` prints); the other lines go to stderr.")]


def json_record(fn):
    """For a command that writes one crfedit file (``out``) and takes ``--json``: its lines go to
    stderr and stdout gets one JSON object, the written file's ``info --json`` record (an edit's
    :func:`~.edit.print_edit`, a selection's :func:`~.select.print_selection`), so a script
    reads one place."""

    @functools.wraps(fn)
    def run(*args, **kwargs):
        if not kwargs.get("as_json"):
            return fn(*args, **kwargs)
        with contextlib.redirect_stdout(sys.stderr):
            fn(*args, **kwargs)
        from ..safefile import read_header

        out = kwargs["out"]
        _, meta = read_header(out)
        if meta.get("format") == SELECTION_FORMAT:
            from .select import print_selection

            print_selection(out, True, meta.get("version"))
        else:
            from .edit import print_edit

            print_edit(out, True)

    return run


def user_errors(fn=None, *, ranked: bool = False):
    """Decorator for commands: a CrfError, an OS error (permission, disk full, read-only file
    system), a broken pipe or Ctrl-C exits cleanly with one line, no traceback.  Sets torch's
    threads first when :class:`Session` says so (torch is imported only here, when a command runs).
    Under torchrun a command that does not share its work over the ranks (``ranked=False``:
    every one but train, render and eval recon/edits) is refused rather than run once per rank,
    and a rank other than 0 prints only errors of its own (:func:`_says_it`)."""
    if fn is None:
        return functools.partial(user_errors, ranked=ranked)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        def stop(message: str, error: BaseException) -> "typer.Exit":
            if not _says_it(error):
                return typer.Exit(EXIT_USER_ERROR)
            ranks = torchrun_ranks()
            named = ranks is None or ranks.main or message.startswith("rank ")
            return fail(message if named else f"rank {ranks.rank} of {ranks.world}: {message}")

        try:
            ranks = torchrun_ranks()
            if ranks is not None and ranks.world > 1 and not ranked:
                raise CrfError("this command does not share its work over torchrun's ranks (train, render, eval recon "
                               "and eval edits do); run it once, without torchrun")
            if Session.threads_error is not None:
                raise Session.threads_error
            if Session.threads is not None:
                from ..runtime import configure_threads

                configure_threads(Session.threads)
            check_not_stdout(fn, kwargs)
            return fn(*args, **kwargs)
        except CrfError as e:
            raise stop(str(e), e) from None
        except KeyboardInterrupt as e:
            if _says_it(e):
                word = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
                ranks = torchrun_ranks()
                if isinstance(e, Terminated) and ranks is not None and ranks.world > 1:  # torchrun's SIGTERM: its summary says why
                    word = "terminated (SIGTERM from torchrun: Ctrl-C, or another rank stopped; torchrun's summary names it)"
                typer.echo(f"{word}{': ' + str(e) if str(e) else ''}", err=True)
            raise typer.Exit(143 if isinstance(e, Terminated) else 130) from None
        except (MemoryError, RuntimeError) as e:
            if not out_of_memory(e):
                raise
            raise stop("out of memory (try a smaller --res, --rays or --chunk)", e) from None
        except BrokenPipeError:
            raise typer.Exit(1) from None
        except OSError as e:
            if debug_requested():
                raise
            raise stop(os_error_message(e), e) from None

    return wrapper


class DeviceChoice(str, enum.Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


DeviceOpt = Annotated[DeviceChoice, typer.Option("--device", help="Where to compute: auto picks cuda when available.")]
def seed_in_range(value: int | None) -> int | None:
    """A ``--seed`` torch's generators take: 0 to 2⁶³ − 1 (checked here, not by a Click range,
    whose help printed ``0<=x<=9223372036854775807`` under every command)."""
    if value is not None and not 0 <= value <= 2**63 - 1:
        raise typer.BadParameter(f"{value} is not a seed from 0 to 2^63 - 1")
    return value


SeedOpt = Annotated[int, typer.Option("--seed", callback=seed_in_range, help="Random seed from 0; the same seed gives the same result.")]
"""Seeds torch's generators take: 0 to 2⁶³ − 1."""
AaOpt = Annotated[
    int, typer.Option("--aa", help="Antialiasing: aa×aa rays per pixel, box-filtered (1 = one ray per pixel center, aliased).")
]
TwinSourcesOpt = Annotated[
    int,
    typer.Option("--twin-sources", help="Instances per twin kind that get a twin; more than 4 only adds twins (the default 4 stay).", min=1),
]


def command_line() -> str:
    """The command line as typed, for edit/model metadata, quoted for a POSIX shell
    (``shlex.join``): a path with a space or a ``#rrggbb`` colour pastes back as one argument."""
    import shlex

    return shlex.join(["crfedit", *sys.argv[1:]])


def echo_notes(category) -> None:
    """What loading ``category`` left out (:attr:`~crfedit.data.loading.Category.notes`), a note line each on stderr."""
    for note in category.notes:
        typer.echo(printable(f"note: {note}"), err=True)
