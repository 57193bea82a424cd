"""The example scripts run as a user runs them: examples/quickstart.sh end to end at a tiny
size, in a folder whose name has a space, and again in the same folder (the README points new
users at it; a space failed after training, and a second run failed at `train`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--minutes", "0.05", "--instances", "2", "--views", "8", "--res", "32"]


def run_quickstart(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}  # crfedit, python
    return subprocess.run(["bash", str(ROOT / "examples" / "quickstart.sh"), *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)


def test_quickstart_script_runs_end_to_end_and_again(tmp_path):
    work = tmp_path / "my work"
    for attempt in ("first", "again"):
        done = run_quickstart("--work", str(work), *TINY)
        assert done.returncode == 0, (attempt, done.stderr[-2000:])
        for name in ("chairs.safetensors", "recolor.safetensors", "removed.safetensors", "colours.safetensors",
                     "chairs-edited.safetensors", "render/orbit.gif", "render/recolored.gif"):
            assert (work / name).is_file(), (attempt, name)
        assert len(list((work / "render" / "removed").glob("*.png"))) == 8, attempt
        assert done.stdout.rstrip().endswith(f"{work / 'chairs-edited.safetensors'}"), done.stdout[-500:]
    assert "replaced the dataset that was there" in done.stdout  # the second run began again


def test_quickstart_script_refuses_a_bad_option_before_any_work(tmp_path):
    for args, said in ((["--minutes"], "error: --minutes : expected a number of minutes"),
                       (["--minutes", "abc"], "error: --minutes abc: expected a number of minutes"),
                       (["--instances", "2.5"], "error: --instances 2.5: expected a whole number"),
                       (["--colour", "red"], "error: unknown argument --colour (see --help)")):
        done = run_quickstart("--work", str(tmp_path / "w"), *args)
        assert done.returncode == 2 and done.stderr.strip() == said, (args, done.stderr)
    assert not (tmp_path / "w").exists()
