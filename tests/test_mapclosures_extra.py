"""Without the optional extra, -d mapclosures is one error line naming it (base install)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

from conftest import assert_one_line_error, run_cli
from test_protocols import two_pass_sequence

from lidar_iris_eval.descriptors.mapclosures import backend

ROOT = Path(__file__).resolve().parents[1]


def test_eval_without_the_extra_is_one_line_naming_it(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(backend, "available", lambda: False)  # as in a base install
    seq = two_pass_sequence(tmp_path / "seq", n_per_pass=4)
    code, _, err = run_cli(["eval", seq, "-d", "mapclosures", "--protocol", "1",
                            "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run",
                            "--quiet"], capsys)
    assert_one_line_error(code, err, "mapclosures", "'mapclosures'", ".[mapclosures]")
    assert not (tmp_path / "run").exists()


def test_importing_the_method_does_not_import_map_closures():
    code = ("import sys; import lidar_iris_eval.descriptors.mapclosures; "
            "print('map_closures' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert out.stdout.strip() == "False"


def test_base_dependencies_do_not_include_the_extra():
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    deps = text.split("dependencies = [", 1)[1].split("]", 1)[0]
    assert "map-closures" not in deps and "map_closures" not in deps
    assert 'mapclosures = ["map-closures==' in text


def test_available_agrees_with_the_import_system():
    assert backend.available() == (importlib.util.find_spec("map_closures") is not None)
