"""The one ending mechanism shared by the CLI and the maintainer scripts (``run_guarded``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lidar_iris_eval.cli import run_guarded
from lidar_iris_eval.errors import LirisError

ROOT = Path(__file__).resolve().parents[1]


def test_returns_what_the_body_returns():
    assert run_guarded(lambda: 41 + 1) == 42


def test_liris_error_is_one_line_exit_2(capsys):
    def body():
        raise LirisError("--out x.npz", "first line\n  second part")

    with pytest.raises(SystemExit) as stop:
        run_guarded(body)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["liris: error: --out x.npz: first line second part"]


def test_os_error_names_its_path(capsys, tmp_path):
    missing = tmp_path / "nope" / "file.csv"

    def body():
        missing.read_text()

    with pytest.raises(SystemExit) as stop:
        run_guarded(body)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "no such file" in err[0], err


def test_a_programming_error_is_not_hidden():
    def body():
        raise ZeroDivisionError("a bug, not the user's input")

    with pytest.raises(ZeroDivisionError):
        run_guarded(body)


@pytest.mark.parametrize("script, args", [
    ("esm_segments.py", ["{tmp}/no-such-sequence", "--out", "{tmp}/s.npz"]),
    ("table1.py", ["--out", "{tmp}/t", "--worlds", "no-such-world"]),
])
def test_scripts_end_through_it(tmp_path, script, args):
    """A maintainer script's bad input: one ``liris: error:`` line, exit 2, no traceback."""
    argv = [a.format(tmp=tmp_path) for a in args]
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / script), *argv],
                          capture_output=True, text=True, timeout=300)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr
    assert lines and lines[-1].startswith("liris: error:"), done.stderr
    assert "Traceback" not in done.stderr
