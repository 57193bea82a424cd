"""The thread default follows the machine, CRFEDIT_THREADS overrides it, and help text has
readable metavars and answers without importing torch (issue 18)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from crfedit.cli import app
from crfedit.errors import CrfError
from crfedit.threads import (
    default_threads,
    is_crfedit,
    recent_siblings,
    requested_threads,
    threads_choice,
    usable_cores,
)


@pytest.mark.parametrize("cores, load, expected", [(2, 0.1, 2), (2, 0.6, 1), (2, 1.4, 1), (2, 7.5, 1), (16, 3.2, 13), (16, 0.0, 16), (1, 0.0, 1)])
def test_default_threads_are_the_cores_nothing_else_uses(cores, load, expected):
    assert default_threads(cores, load, 0) == expected


@pytest.mark.parametrize("cores, load, siblings, expected", [(16, 0.0, 1, 8), (16, 0.0, 3, 4), (2, 0.1, 1, 1), (16, 3.2, 1, 6), (2, 1.4, 5, 1), (16, 0.0, 40, 1)])
def test_default_threads_are_shared_with_crfedit_processes_started_in_the_last_minute(cores, load, siblings, expected):
    """The load average cannot see a process started seconds ago: two trainings started
    together each took every core, and their start-up ran 14x slower on 16 cores."""
    assert default_threads(cores, load, siblings) == expected


def test_threads_choice_says_what_decided_it(monkeypatch):
    monkeypatch.setenv("CRFEDIT_THREADS", "3")
    monkeypatch.setenv("OMP_NUM_THREADS", "5")
    assert threads_choice() == (3, "CRFEDIT_THREADS=3")
    for many in ("100000", "99999999999"):  # the OpenMP runtime could not create them: a segfault, not a line
        monkeypatch.setenv("CRFEDIT_THREADS", many)
        with pytest.raises(CrfError, match="expected a positive integer, at most 1024"):
            threads_choice()
    monkeypatch.delenv("CRFEDIT_THREADS")
    assert threads_choice() == (5, "OMP_NUM_THREADS=5")
    monkeypatch.delenv("OMP_NUM_THREADS")
    monkeypatch.setattr("crfedit.threads.usable_cores", lambda: 16)
    monkeypatch.setattr("crfedit.threads.busy_cores", lambda: 0.2)
    monkeypatch.setattr("crfedit.threads.recent_siblings", lambda: 0)
    assert threads_choice() == (16, "16 usable cores, load average 0.2; crfedit --threads N (or CRFEDIT_THREADS=N) sets it")
    monkeypatch.setattr("crfedit.threads.recent_siblings", lambda: 3)
    assert threads_choice() == (4, "16 usable cores, load average 0.2, shared with 3 other crfedit processes started in the last minute; crfedit --threads N (or CRFEDIT_THREADS=N) sets it")


@pytest.mark.parametrize("argv, expected", [
    (["python3", "-m", "crfedit", "train", "d"], True),
    (["/x/.venv/bin/python", "/x/.venv/bin/crfedit", "ui", "m"], True),  # the console script
    (["python3.12", "-u", "-X", "importtime", "-m", "crfedit.cli"], True),
    (["timeout", "60", "python3", "-m", "crfedit", "train"], False),  # a wrapper computes nothing
    (["python3", "-m", "pytest", "crfedit"], False),
    (["python3", "-c", "import crfedit"], False),
    (["crfedit"], False),
    ([], False),
])
def test_which_command_lines_are_crfedit(argv, expected):
    assert is_crfedit(argv) is expected


def test_recent_siblings_reads_proc(tmp_path):
    """A /proc made here: crfedit processes started 10 s and 500 s ago, a wrapper, another
    program, this process; only the first counts."""
    tick = os.sysconf("SC_CLK_TCK")
    (tmp_path / "uptime").write_text("1000.00 1500.00\n")
    def proc(pid, argv, age):
        d = tmp_path / str(pid)
        d.mkdir()
        (d / "cmdline").write_bytes(b"\0".join(a.encode() for a in argv) + b"\0")
        rest = ["S"] + ["0"] * 18 + [str(int((1000.0 - age) * tick))] + ["0"] * 10  # field 22: start time
        (d / "stat").write_text(f"{pid} (py (thon)) " + " ".join(rest) + "\n")
    proc(101, ["python3", "-m", "crfedit", "train", "d"], 10)
    proc(102, ["python3", "-m", "crfedit", "render", "m"], 500)
    proc(103, ["timeout", "9", "python3", "-m", "crfedit", "train"], 10)
    proc(104, ["python3", "-m", "http.server"], 10)
    proc(os.getpid(), ["python3", "-m", "crfedit", "train"], 1)
    (tmp_path / "105").mkdir()  # a process that ended while being read
    assert recent_siblings(proc=tmp_path) == 1
    assert recent_siblings(window=600, proc=tmp_path) == 2
    assert recent_siblings(proc=tmp_path / "missing") == 0


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux's /proc")
def test_a_crfedit_process_started_now_is_a_sibling(tmp_path):
    script = tmp_path / "crfedit"
    script.write_text("import time\ntime.sleep(30)\n")
    child = subprocess.Popen([sys.executable, str(script)])
    try:
        deadline = time.monotonic() + 10
        while recent_siblings() < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert recent_siblings() >= 1
        assert default_threads(16, 0.0) <= 8
    finally:
        child.kill()
        child.wait()


def test_crfedit_threads_overrides_and_is_checked(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("CRFEDIT_THREADS", "3")
    assert requested_threads() == 3
    for bad in ("0", "-1", "two"):
        monkeypatch.setenv("CRFEDIT_THREADS", bad)
        with pytest.raises(CrfError, match="CRFEDIT_THREADS"):
            requested_threads()
    monkeypatch.delenv("CRFEDIT_THREADS")
    assert 1 <= requested_threads() <= usable_cores()


def test_omp_num_threads_is_honoured_after_crfedit_threads(monkeypatch):
    """torch's own setting (torchrun sets 1 a rank) counts: the load average cannot see a
    process started in the same second, so two runs launched together each took every core."""
    monkeypatch.delenv("CRFEDIT_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "5")
    assert requested_threads() == 5
    monkeypatch.setenv("OMP_NUM_THREADS", "4,2")  # OpenMP's per-level list: torch's pool is the first
    assert requested_threads() == 4
    monkeypatch.setenv("CRFEDIT_THREADS", "3")  # crfedit's own setting wins
    assert requested_threads() == 3
    monkeypatch.delenv("CRFEDIT_THREADS")
    for bad in ("0", "x", ",2"):
        monkeypatch.setenv("OMP_NUM_THREADS", bad)
        with pytest.raises(CrfError, match="OMP_NUM_THREADS"):
            requested_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", " ")
    assert 1 <= requested_threads() <= usable_cores()


def test_a_command_computes_with_omp_num_threads(tmp_path):
    """A command started with OMP_NUM_THREADS=N (N above this machine's cores, which the
    default never picks) leaves torch with N threads."""
    code = ("import sys, torch; sys.argv = ['crfedit', 'info', sys.argv[1]]\nfrom crfedit.cli import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\nprint(torch.get_num_threads())")
    n = usable_cores() + 1
    env = {k: v for k, v in os.environ.items() if k != "CRFEDIT_THREADS"}
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "missing.safetensors")], capture_output=True, check=False,
                         text=True, cwd=Path(__file__).parents[1], env={**env, "OMP_NUM_THREADS": str(n)})
    assert "missing.safetensors" in run.stderr and run.stdout.strip().splitlines()[-1] == str(n), run.stdout + run.stderr


def test_the_threads_flag_sets_torch_s_threads_over_the_environment(tmp_path):
    """`crfedit --threads N COMMAND` computes with N threads, over CRFEDIT_THREADS; after the
    command it is a one-line usage error saying where the flag goes."""
    code = ("import sys, torch; sys.argv = ['crfedit', *sys.argv[1:]]\nfrom crfedit.cli import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\nprint(torch.get_num_threads())")
    n = usable_cores() + 2
    env = {**os.environ, "CRFEDIT_THREADS": "1"}
    missing = str(tmp_path / "missing.safetensors")
    run = subprocess.run([sys.executable, "-c", code, "--threads", str(n), "info", missing], capture_output=True, text=True,
                         cwd=Path(__file__).parents[1], env=env)
    assert "missing.safetensors" in run.stderr and run.stdout.strip().splitlines()[-1] == str(n), run.stdout + run.stderr
    after = subprocess.run([sys.executable, "-c", code, "info", missing, "--threads", "1"], capture_output=True, text=True,
                           cwd=Path(__file__).parents[1], env=env)
    assert after.stderr.strip() == ("error: No such option: --threads (--threads goes before the command: "
                                    "crfedit --threads N COMMAND …)"), after.stderr
    # a bad CRFEDIT_THREADS is the command's error, which --threads overrides; --help needs none
    bad = {**os.environ, "CRFEDIT_THREADS": "abc"}
    over = subprocess.run([sys.executable, "-c", code, "--threads", "2", "info", missing], capture_output=True, text=True,
                          cwd=Path(__file__).parents[1], env=bad)
    assert "missing.safetensors" in over.stderr and over.stdout.strip().splitlines()[-1] == "2", over.stdout + over.stderr
    plain = subprocess.run([sys.executable, "-c", code, "info", missing], capture_output=True, text=True, cwd=Path(__file__).parents[1], env=bad)
    assert plain.stderr.strip() == "error: CRFEDIT_THREADS='abc': expected a positive integer, at most 1024", plain.stderr
    helped = subprocess.run([sys.executable, "-c", code, "--help"], capture_output=True, text=True, cwd=Path(__file__).parents[1], env=bad)
    assert "Usage:" in helped.stdout and "error" not in helped.stderr, helped.stderr


def test_help_has_readable_metavars():
    text = CliRunner().invoke(app, ["edits", "bake", "--help"], env={"COLUMNS": "200"}).stdout
    assert "edits bake [OPTIONS] MODEL" in text and "--edit EDIT" in text and "--out OUT" in text
    assert "{model}" not in text and "<list[Path]>" not in text and "<path>" not in text.split("Options:")[1]
    text = CliRunner().invoke(app, ["train", "--help"], env={"COLUMNS": "200"}).stdout
    assert "--steps N" in text and "--set KEY=VALUE" in text
    assert "--preset <fast|paper>" in text or "--preset [fast|paper]" in text  # Typer ≥ 0.2x, or click's own format
    # every command's usage line names its arguments plainly: Typer 0.27 and 0.29 write {MODEL}
    # or {model} for a required argument, with or without a metavar of ours
    usages = {}
    def walk(command, path):
        for name, sub in getattr(command, "commands", {}).items():
            walk(sub, [*path, name])
        if not hasattr(command, "commands"):
            usages[" ".join(path)] = next(ln for ln in CliRunner().invoke(app, [*path, "--help"], env={"COLUMNS": "200"}).stdout.splitlines() if ln.startswith("Usage:"))
    walk(typer.main.get_command(app), [])
    assert len(usages) > 20 and usages["render"] == "Usage: crfedit render [OPTIONS] MODEL", usages.get("render")
    assert not [u for u in usages.values() if "{" in u or "<" in u], usages


def test_help_does_not_import_torch():
    code = "import sys; sys.argv = ['crfedit', '--help']\nfrom crfedit.cli import main\ntry:\n    main()\nexcept SystemExit:\n    pass\nprint('torch' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=Path(__file__).parents[1])
    assert run.stdout.strip().splitlines()[-1] == "False", run.stdout + run.stderr


def test_ci_runs_readme_test_command_and_torch_is_uncapped():
    root = Path(__file__).parents[1]
    readme = (root / "README.md").read_text()
    command = next(ln for ln in readme.splitlines() if ln.startswith("python3 -m venv") and "pytest" in ln)
    assert f'readme_test_command="{command}"' in (root / ".ci" / "run").read_text()
    assert "-c constraints-cpu.txt" in command and "torch==2.13.0" in (root / "constraints-cpu.txt").read_text()
    assert '"torch>=2.4",' in (root / "pyproject.toml").read_text()
