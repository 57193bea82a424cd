"""The CLI tests' two helpers: run a command in-process, and check it failed as a user error."""

from __future__ import annotations

from typer.testing import CliRunner

from crfedit.cli import app


def invoke(*args):
    """``crfedit ARGS`` in this process (paths and numbers as strings), with stdout and stderr apart."""
    return CliRunner().invoke(app, [str(a) for a in args])


def assert_user_error(result, *fragments: str) -> str:
    """Exit 2 with one line ``error: ...`` on stderr that contains every fragment, and no
    traceback anywhere; the line."""
    assert result.exit_code == 2, (result.exit_code, result.output, repr(result.exception))
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.output and "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]
