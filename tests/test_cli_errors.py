"""The CLI's error paths on the installed Typer: Ctrl-C (typer.Abort), unexpected exceptions
(one line, exit 1; the traceback with --debug or CRFEDIT_DEBUG=1), OS errors (one line, exit 2),
and an interrupted ``dataset synth`` leaving no partial folder (issue 18)."""

from __future__ import annotations

import errno
import subprocess
import sys
from pathlib import Path

import pytest
import typer

import crfedit.data.synth as synth
from crfedit.cli import main
from crfedit.data.synth import SynthConfig, write_synth_category

from cli_helpers import assert_user_error, invoke

SYNTH = ["dataset", "synth", "--instances", "1", "--views", "3", "--res", "8", "--no-twins"]


def run_main(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``crfedit ARGS`` through :func:`crfedit.cli.main`."""
    monkeypatch.setattr(sys, "argv", ["crfedit", *args])
    with pytest.raises(SystemExit) as e:
        main()
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def raiser(exc: BaseException):
    def fail(*args, **kwargs):
        raise exc

    return fail


def test_typer_abort_is_caught_on_the_installed_typer(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(synth, "write_synth_category", raiser(typer.Abort()))
    code, _, err = run_main(monkeypatch, capsys, *SYNTH[:2], str(tmp_path / "ds"), *SYNTH[2:])
    assert code == 130 and err == "error: aborted\n", err
    assert "AttributeError" not in err


def test_an_unexpected_error_is_one_line_with_the_path_and_exit_1(monkeypatch, capsys, tmp_path):
    monkeypatch.delenv("CRFEDIT_DEBUG", raising=False)
    monkeypatch.setattr(synth, "write_synth_category", raiser(RuntimeError("cannot frobnicate\nthe chair")))
    code, _, err = run_main(monkeypatch, capsys, *SYNTH[:2], str(tmp_path / "ds"), *SYNTH[2:])
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith("error: unexpected RuntimeError: cannot frobnicate the chair at ") and "--debug" in err
    assert "test_cli_errors.py" not in err and "Traceback" not in err
    monkeypatch.setattr(synth, "write_synth_category", raiser(KeyError("x")))
    _, _, err = run_main(monkeypatch, capsys, *SYNTH[:2], str(tmp_path / "ds"), *SYNTH[2:])
    assert err.startswith("error: unexpected KeyError: 'x'")


@pytest.mark.parametrize("how", ["flag", "env"])
def test_debug_shows_the_traceback(monkeypatch, capsys, tmp_path, how):
    monkeypatch.delenv("CRFEDIT_DEBUG", raising=False)
    monkeypatch.setattr(synth, "write_synth_category", raiser(RuntimeError("boom")))
    args = [*SYNTH[:2], str(tmp_path / "ds"), *SYNTH[2:]]
    if how == "env":
        monkeypatch.setenv("CRFEDIT_DEBUG", "1")
    else:
        args.insert(0, "--debug")
    monkeypatch.setattr(sys, "argv", ["crfedit", *args])
    monkeypatch.setattr("crfedit.cli.common.Session.debug", False)
    with pytest.raises(RuntimeError, match="boom"):
        main()


def test_debug_traceback_in_a_real_process():
    """End to end: an OS error is one line; with --debug, Python's traceback of it."""
    cmd = [sys.executable, "-m", "crfedit", *SYNTH[:2], "/sys/crfedit-ds", *SYNTH[2:]]
    run = dict(capture_output=True, text=True, cwd=Path(__file__).parents[1])
    quiet = subprocess.run(cmd, **run)
    assert quiet.returncode == 2 and "Traceback" not in quiet.stderr
    assert quiet.stderr.strip().splitlines()[-1].startswith("error: /sys/crfedit-ds: ")
    loud = subprocess.run(cmd[:3] + ["--debug"] + cmd[3:], **run)
    assert loud.returncode == 1 and "Traceback" in loud.stderr and "OSError" in loud.stderr, loud.stderr


@pytest.mark.parametrize(
    "code, words",
    [(errno.EACCES, "permission denied"), (errno.ENOSPC, "the disk is full"), (errno.EROFS, "read-only file system")],
)
def test_os_errors_read_as_user_errors(monkeypatch, tmp_path, code, words):
    out = tmp_path / "ds"
    monkeypatch.setattr(synth, "write_synth_category", raiser(OSError(code, "strerror", str(out))))
    result = invoke(*SYNTH[:2], out, *SYNTH[2:])
    assert result.exit_code == 2 and result.stderr == f"error: {out}: {words}\n", result.output
    assert not out.exists()


def test_synth_into_an_unwritable_place_names_the_folder(capsys, monkeypatch):
    """/sys refuses new folders even for root (a chmod'ed folder does not stop root)."""
    code, _, err = run_main(monkeypatch, capsys, *SYNTH[:2], "/sys/crfedit-ds", *SYNTH[2:])
    assert code == 2 and err.startswith("error: /sys/crfedit-ds: ") and err.count("\n") == 1, err


def test_interrupted_synth_leaves_no_partial_folder(monkeypatch, tmp_path):
    out = tmp_path / "ds"
    calls = []

    def progress(label):
        calls.append(label)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_synth_category(out, SynthConfig(instances=3, views=3, res=8, twins=False), progress)
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_interrupted_resynth_keeps_the_previous_dataset(tmp_path):
    out = tmp_path / "ds"
    write_synth_category(out, SynthConfig(instances=2, views=3, res=8, twins=False))
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    with pytest.raises(KeyboardInterrupt):
        write_synth_category(out, SynthConfig(instances=3, views=3, res=8, seed=1, twins=False), raiser(KeyboardInterrupt()))
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]
    result = write_synth_category(out, SynthConfig(instances=3, views=3, res=8, seed=1, twins=False))
    assert (out / "instances.txt").read_text().split() == result.names == ["chair_000", "chair_001", "chair_002"]
    assert [p.name for p in tmp_path.iterdir()] == ["ds"] and oct(out.stat().st_mode & 0o777) != "0o700"


def test_synth_over_an_earlier_synth_output_says_it_replaced_it(tmp_path):
    out = tmp_path / "ds"
    first = invoke(*SYNTH[:2], out, *SYNTH[2:])
    assert first.exit_code == 0 and "replaced" not in first.stdout, first.output
    again = invoke(*SYNTH[:2], out, "--instances", "2", *SYNTH[4:])
    assert again.exit_code == 0 and "(it replaced the dataset that was there)" in again.stdout, again.output
    # the user's files beside the dataset and inside its instance folders are carried over, and said
    assert invoke("dataset", "synth", out, "--instances", "2", "--views", "10", "--res", "8", "--no-twins").exit_code == 0
    frames = {p.name for p in (out / "chair_000" / "train").iterdir()}
    (out / "NOTES.md").write_text("mine")
    (out / "chair_000" / "my_scribbles").mkdir()
    (out / "chair_000" / "my_scribbles" / "seat.png").write_bytes(b"s")
    (out / "chair_000" / "train" / "my_extra.png").write_bytes(b"x")
    again = invoke(*SYNTH[:2], out, "--instances", "2", *SYNTH[4:])
    assert ("(it replaced the dataset that was there; kept what was not the dataset's: NOTES.md, chair_000/my_scribbles, "
            "chair_000/train/my_extra.png)") in again.stdout, again.output
    assert (out / "NOTES.md").read_text() == "mine" and (out / "chair_000" / "my_scribbles" / "seat.png").read_bytes() == b"s"
    assert (out / "chair_000" / "train" / "my_extra.png").read_bytes() == b"x"
    left = {p.name for p in (out / "chair_000" / "train").iterdir()}
    assert left < frames | {"my_extra.png"} and len(left) < len(frames)  # the earlier build's own frames do not stay (3 views now)
    assert (out / "instances.txt").read_text().split() == ["chair_000", "chair_001"]


def test_a_dash_for_an_output_is_refused_not_made_a_file_named_dash(tmp_path, monkeypatch):
    """`-` does not mean standard output to crfedit: every option that names a file or folder to
    write refuses it in one line (before opening anything), instead of writing `./-`; and every
    output option of every command is one the check knows."""
    import typer.main

    from cli_helpers import assert_user_error

    from crfedit.cli.common import OUTPUTS, app

    monkeypatch.chdir(tmp_path)
    for args, option in (
        (["render", "m.safetensors", "--instance", "0", "--views", "orbit:2", "--out", "-"], "--out -"),
        (["render", "m.safetensors", "--instance", "0", "--views", "orbit:2", "--out", "r", "--video", "-"], "--video -"),
        (["dataset", "synth", "-"], "OUT -"), (["export", "mesh", "m.safetensors", "--instance", "0", "--out", "-"], "--out -"),
        (["edits", "rebase", "m.safetensors", "--edit", "e", "--out-dir", "-"], "--out-dir -"),
        (["bench", "--csv", "-"], "--csv -"), (["ui", "m.safetensors", "--workdir", "-"], "--workdir -"),
    ):
        assert_user_error(invoke(*args), option, "crfedit writes files, not standard output")
    assert list(tmp_path.iterdir()) == []

    def leaves(command):
        subs = getattr(command, "commands", None)
        return [leaf for sub in subs.values() for leaf in leaves(sub)] if subs else [command]

    for command in leaves(typer.main.get_command(app)):
        for param in command.params:
            writes = any(o.startswith(("--out", "--preview", "--video", "--csv", "--md", "--work")) for o in getattr(param, "opts", []))
            assert not writes or param.name in OUTPUTS, (command.name, param.name)


def test_a_bad_choice_reads_without_the_validators_wording(monkeypatch, capsys, tmp_path):
    """`--device gpu`: one line naming the choices, without pydantic's "Value error," that
    Typer 0.29's choice check leaves in it."""
    code, _, err = run_main(monkeypatch, capsys, "render", str(tmp_path / "m.safetensors"), "--instance", "0", "--views", "test",
                            "--out", str(tmp_path / "r"), "--device", "gpu")
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("error: Invalid value for '--device': 'gpu' is not one of 'auto', 'cpu', 'cuda'. (see "), err


def test_sigterm_that_typer_takes_for_ctrl_c_exits_143(monkeypatch, capsys):
    """SIGTERM while Typer builds the command: Typer catches the KeyboardInterrupt and exits 130
    silently; the command line says it was terminated and exits 143, as for any SIGTERM."""
    import crfedit.cli as cli
    from crfedit.cli.common import Session

    def swallowed(*args, **kwargs):
        Session.terminated = True  # what the SIGTERM handler records before it raises
        return 130

    monkeypatch.setattr(cli, "app", swallowed)
    monkeypatch.setattr(Session, "terminated", False)
    code, out, err = run_main(monkeypatch, capsys, "info", "x")
    assert (code, out, err) == (143, "", "error: terminated (SIGTERM)\n")


def test_a_failed_allocation_is_out_of_memory_in_one_line(capsys):
    """torch's CPU allocator fails with a RuntimeError ("not enough memory"), which read as an
    unexpected error (export mesh --res 1024 under a memory limit); other RuntimeErrors stay."""
    import typer

    from crfedit.cli.common import user_errors

    @user_errors
    def allocating():
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:121] data. DefaultCPUAllocator: not enough memory: "
                           "you tried to allocate 12884901888 bytes.")

    with pytest.raises(typer.Exit) as e:
        allocating()
    assert e.value.exit_code == 2 and capsys.readouterr().err == "error: out of memory (try a smaller --res, --rays or --chunk)\n"

    @user_errors
    def broken():
        raise RuntimeError("a bug")

    with pytest.raises(RuntimeError, match="a bug"):
        broken()


def test_an_unknown_instance_without_a_close_name_points_to_fit_real_edits():
    """``export mesh --instance photo1`` of an instance fit-real added, without its edit: the
    line says where such an instance lives (a bare 'unknown instance' before)."""
    from types import SimpleNamespace

    from crfedit.errors import CrfError
    from crfedit.model import CategoryModel

    model = SimpleNamespace(names=["chair_000", "chair_001"])
    with pytest.raises(CrfError, match=r"^unknown instance 'photo1' \(instances: chair_000, chair_001\); an instance fit-real added "
                                       r"exists with its edit file \(--edit\) or baked in \(edits bake\)$"):
        CategoryModel.instance_index(model, "photo1")
    with pytest.raises(CrfError, match=r"did you mean 'chair_001'") as e:
        CategoryModel.instance_index(model, "chair_01")
    assert "fit-real" not in str(e.value)


def test_occluded_without_method_paper_is_refused_before_any_work(tiny_model, tmp_path):
    """``remove --occluded`` belongs to ``--method paper``: it was refused only after the
    selection had been lifted and its lines printed (a second of work, then a contradiction)."""
    from PIL import Image
    import numpy as np

    mask = np.zeros((16, 16), np.uint8)
    mask[6:10, 6:10] = 255
    Image.fromarray(mask).save(tmp_path / "s.png")
    r = invoke("remove", tiny_model, "--instance", "0", "--view", "train:0", "--scribble", tmp_path / "s.png", "--occluded",
               "--out", tmp_path / "r.safetensors", "--device", "cpu")
    assert_user_error(r, "--occluded belongs to --method paper")
    assert "selection:" not in r.stderr and not (tmp_path / "r.safetensors").exists()


def test_the_removal_line_says_the_selection_and_its_skin():
    """A --for color selection given to remove has no skin: the line said "the selection with
    the skin around it" for a skin of 0 cells."""
    from types import SimpleNamespace

    from crfedit.cli.edit import _skin_text

    assert _skin_text(9244, 8127, None) == "the selection's 8127 and a skin of 1117 around it"
    assert _skin_text(7077, 7077, SimpleNamespace(meta={"for": "color"})) == (
        "the selection's 7077, no skin (made --for color, it holds no cell of a removal's lower values)")
    assert _skin_text(50, 50, None) == "the selection's 50, no skin" and _skin_text(50, None, None) == "the selection with the skin around it"


def test_an_option_of_one_value_given_twice_is_refused(monkeypatch, capsys, tmp_path):
    """Click keeps the last of an option given twice: `remove --view A --scribble a --view B
    --scribble b` removed what B alone selects while its file recorded both views.  Refused
    before any file is read, naming the option (and `select` for a view's strokes); an option
    that repeats (`select --view`) and a flag given twice still pass the check."""
    from crfedit.cli import app
    from crfedit.cli.common import repeated_option
    import typer

    m = str(tmp_path / "m.safetensors")
    code, _, err = run_main(monkeypatch, capsys, "remove", m, "--instance", "0", "--view", "train:1", "--scribble", "a.png",
                            "--view=train:2", "--scribble", "b.png", "--out", str(tmp_path / "r.safetensors"))
    assert code == 2 and err == ("error: --view given 2 times; `crfedit remove` takes one: an edit is drawn on one view; to select "
                                 "a part from several, repeat --view/--scribble/--keep in `crfedit select` and pass its file as --selection\n"), err
    code, _, err = run_main(monkeypatch, capsys, "edit-color", m, "--instance", "0", "--view", "train:1", "--scribble", "a.png",
                            "--color", "red", "--colour", "blue", "--out", str(tmp_path / "r.safetensors"))
    assert code == 2 and err == "error: --color given 2 times; `crfedit edit-color` takes one\n", err
    code, _, err = run_main(monkeypatch, capsys, "eval", "edits", m, "d", "--steps", "5", "--steps", "6")
    assert code == 2 and err == "error: --steps given 2 times; `crfedit eval edits` takes one\n", err
    root = typer.main.get_command(app)
    assert repeated_option(root, ["select", m, "--instance", "0", "--view", "train:1", "--scribble", "a.png", "--view", "train:2",
                                  "--scribble", "b.png", "--out", "s.safetensors"]) is None
    assert repeated_option(root, ["remove", m, "--force", "--force", "--instance", "0"]) is None
    assert repeated_option(root, ["nonsense", "--view", "a", "--view", "b"]) is None  # click's own error says it
    code, _, err = run_main(monkeypatch, capsys, "render", m, "--instance", "0", "--views", "test", "--out", str(tmp_path / "r"), "--debug")
    assert code == 2 and err == "error: No such option: --debug (--debug goes before the command: crfedit --debug COMMAND …)\n", err
