"""Issue 39 item 5: a method and a dataset reader from outside the repository.

A tiny external package (``liris_toyplugin``: a ring-histogram method with its own
``presets.yaml`` and a reader for a ``clouds/`` + ``trajectory.txt`` layout) is
"installed" by putting its folder and a ``.dist-info`` with ``entry_points.txt`` on
``sys.path`` (what ``pip install`` leaves in site-packages; no network). It then runs
through ``liris eval``, ``show`` and ``plot`` like a built-in.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

PACKAGE = '''
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.io.datasets import DatasetSpec
from lidar_iris_eval.io.sequence import Sequence


@dataclass(frozen=True)
class RingParams:
    rings: int = 20
    max_range: float = 40.0


class RingHistogram(Descriptor):
    name, params_type = "ring-histogram", RingParams

    def compute(self, points):
        r = np.linalg.norm(np.asarray(points, np.float64)[:, :2], axis=1)
        h = np.histogram(r, self.params.rings, (0.0, self.params.max_range))[0]
        return (h / max(1, h.sum())).astype(np.float64)

    def distance(self, query, candidate):
        return float(np.abs(query - candidate).sum()), float("nan")


def open_toy(path, poses=None, calib=None, **options):
    path = Path(path)
    rows = np.loadtxt(path / "trajectory.txt", ndmin=2)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows.reshape(-1, 3, 4)
    return Sequence(name=path.name, path=path, scan_paths=sorted((path / "clouds").glob("*.bin")),
                    poses=T)


SPEC = DatasetSpec(
    "toy-data", "Toy layout", "<seq>/clouds/NNNNNN.bin + <seq>/trajectory.txt",
    "LiDAR frame, 12 numbers a line", "none", None, "trajectory.txt beside clouds/",
    lambda p: (Path(p) / "trajectory.txt").is_file() and (Path(p) / "clouds").is_dir(),
    "liris_toyplugin:open_toy", frame="kept", intensity="as stored")
'''

PRESETS = "presets:\n  coarse: {rings: 12}\n  fine: {rings: 48}\n"

ENTRY_POINTS = """[liris.methods]
ring-histogram = liris_toyplugin:RingHistogram

[liris.datasets]
toy-data = liris_toyplugin:SPEC
"""


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(site folder, toy sequence folder): the package on a path, a sequence in its layout."""
    from lidar_iris_eval.cli import cli
    from lidar_iris_eval.io import open_sequence

    root = tmp_path_factory.mktemp("plugin")
    site = root / "site"
    (site / "liris_toyplugin").mkdir(parents=True)
    (site / "liris_toyplugin" / "__init__.py").write_text(PACKAGE)
    (site / "liris_toyplugin" / "presets.yaml").write_text(PRESETS)
    info = site / "liris_toyplugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: liris-toyplugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    sim = root / "tiny-mixed"
    result = CliRunner().invoke(cli, ["simulate", str(sim), "--world", "tiny-mixed"])
    assert result.exit_code == 0, result.output
    seq = open_sequence(sim)
    toy = root / "toy-seq"
    (toy / "clouds").mkdir(parents=True)
    for i, path in enumerate(seq.scan_paths):
        (toy / "clouds" / f"{i:06d}.bin").symlink_to(path)
    np.savetxt(toy / "trajectory.txt", seq.poses[:, :3, :].reshape(len(seq), 12))
    return site, toy


@pytest.fixture
def on_path(installed, monkeypatch):
    site, toy = installed
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.delenv("LIRIS_METHODS", raising=False)
    monkeypatch.delenv("LIRIS_DATASETS", raising=False)
    yield site, toy
    for name in [m for m in sys.modules if m.startswith("liris_toyplugin")]:
        del sys.modules[name]


def _ring_l1_matches(toy: Path, rings: int, exclude: int) -> np.ndarray:
    """Protocol 1's best match per query, computed here from the scan files."""
    hists = []
    for path in sorted((toy / "clouds").glob("*.bin")):
        pts = np.fromfile(path, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
        h = np.histogram(np.linalg.norm(pts[:, :2], axis=1), rings, (0.0, 40.0))[0]
        hists.append(h / max(1, h.sum()))
    hists = np.array(hists)
    best = np.full(len(hists), -1)
    for i in range(exclude, len(hists)):
        d = np.abs(hists[: i - exclude + 1] - hists[i]).sum(1)
        best[i] = int(np.argmin(d))
    return best


def test_external_method_and_reader_run_through_eval_show_and_plot(on_path, tmp_path):
    import pandas as pd

    from lidar_iris_eval.cli import cli
    from lidar_iris_eval.runs.reader import load_run

    site, toy = on_path
    run_dir = tmp_path / "run"
    runner = CliRunner()
    result = runner.invoke(cli, ["eval", str(toy), "-d", "ring-histogram:coarse", "--protocol",
                                 "1", "--protocol", "2", "--out", str(run_dir), "--cache-dir",
                                 str(tmp_path / "cache"), "--quiet"])
    assert result.exit_code == 0, result.output
    run = load_run(run_dir)
    assert {(r["protocol"], r["descriptor"], r["preset"]) for r in run.rows} == \
        {(1, "ring-histogram", "coarse"), (2, "ring-histogram", "coarse")}
    assert run.config["descriptors"][0]["params"] == {"rings": 12, "max_range": 40.0}
    matches = pd.read_csv(run_dir / "protocol1" / "ring-histogram" / "matches.csv")
    expected = _ring_l1_matches(toy, rings=12, exclude=30)
    got = dict(zip(matches["query"], matches["match"], strict=True))
    queries = [i for i in range(len(expected)) if expected[i] >= 0]
    assert len(got) == len(queries) > 0
    assert [got[i] for i in queries] == [expected[i] for i in queries]

    shown = runner.invoke(cli, ["show", str(run_dir)])
    assert shown.exit_code == 0, shown.output
    assert "ring-histogram" in shown.output

    plotted = runner.invoke(cli, ["plot", str(run_dir), "--out", str(tmp_path / "figs")])
    assert plotted.exit_code == 0, plotted.output
    assert (tmp_path / "figs" / "pr_protocol1.png").is_file()
    assert (tmp_path / "figs" / "trajectory.png").is_file()  # the reader reopened the poses

    listed = runner.invoke(cli, ["datasets"])
    assert listed.exit_code == 0 and "toy-data" in listed.output


def test_quick_trial_environment_variables(on_path, tmp_path, monkeypatch):
    """LIRIS_METHODS / LIRIS_DATASETS name a module in the working directory."""
    from lidar_iris_eval.cli import cli

    site, toy = on_path
    monkeypatch.syspath_prepend(str(tmp_path))  # (the CLI adds the working directory itself)
    (tmp_path / "my_trial.py").write_text(textwrap.dedent('''
        from liris_toyplugin import RingHistogram, SPEC

        class Trial(RingHistogram):
            name = "trial"
    '''))
    monkeypatch.setenv("LIRIS_METHODS", "trial=my_trial:Trial")
    monkeypatch.setenv("LIRIS_DATASETS", "toy-env=my_trial:SPEC")
    result = CliRunner().invoke(cli, ["eval", str(toy), "-d", "trial", "--protocol", "1",
                                      "--dataset", "toy-env", "--out", str(tmp_path / "run"),
                                      "--cache-dir", str(tmp_path / "cache"), "--quiet"])
    assert result.exit_code == 0, result.output
    from lidar_iris_eval.runs.reader import load_run

    run = load_run(tmp_path / "run")
    assert [r["descriptor"] for r in run.rows] == ["trial"]
    assert run.config["sequence"]["reader_options"]["dataset"] == "toy-env"
    sys.modules.pop("my_trial", None)


def _liris(args, env_extra, cwd):
    env = {k: v for k, v in os.environ.items() if k not in ("LIRIS_METHODS", "LIRIS_DATASETS")}
    env.update(env_extra)
    return subprocess.run([sys.executable, "-m", "lidar_iris_eval", *args], env=env,
                          cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("variable, value, args, named", [
    ("LIRIS_METHODS", "broken=liris_nosuch_module:Thing", ["-d", "broken"],
     "method plugin broken (liris_nosuch_module:Thing, LIRIS_METHODS)"),
    ("LIRIS_METHODS", "notaclass=liris_toyplugin:open_toy", ["-d", "notaclass"],
     "method plugin notaclass"),
    ("LIRIS_METHODS", "garbage-without-target", ["-d", "lidar-iris"], "LIRIS_METHODS="),
    ("LIRIS_DATASETS", "gone=liris_toyplugin:NOPE", ["-d", "lidar-iris"],
     "dataset plugin gone (liris_toyplugin:NOPE, LIRIS_DATASETS)"),
])
def test_broken_plugin_is_one_error_line(installed, tmp_path, variable, value, args, named):
    site, toy = installed
    proc = _liris(["eval", str(toy), *args, "--protocol", "1", "--out", str(tmp_path / "run"),
                   "--cache-dir", str(tmp_path / "cache"), "--quiet"],
                  {"PYTHONPATH": str(site), variable: value}, tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("liris: error: ") and named in lines[0], lines[0]
    assert not (tmp_path / "run").exists()


def test_broken_entry_point_names_its_distribution(installed, tmp_path):
    site, toy = installed
    other = tmp_path / "site2"
    info = other / "liris_bad-2.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: liris-bad\nVersion: 2.0\n")
    (info / "entry_points.txt").write_text("[liris.methods]\nbad = liris_bad_missing:Bad\n")
    proc = _liris(["eval", str(toy), "-d", "bad", "--protocol", "1", "--out",
                   str(tmp_path / "run"), "--quiet"],
                  {"PYTHONPATH": os.pathsep.join([str(site), str(other)])}, tmp_path)
    assert proc.returncode == 2, proc.stderr
    (line,) = [x for x in proc.stderr.splitlines() if x.strip()]
    assert line.startswith("liris: error: method plugin bad (liris_bad_missing:Bad, "
                           "entry point liris.methods of liris-bad 2.0): cannot be loaded: "
                           "ModuleNotFoundError"), line


def test_a_plugin_cannot_take_a_builtin_name(on_path, tmp_path, monkeypatch):
    from lidar_iris_eval.descriptors import descriptor_class
    from lidar_iris_eval.errors import LirisError

    monkeypatch.setenv("LIRIS_METHODS", "scan-context=liris_toyplugin:RingHistogram")
    with pytest.raises(LirisError, match="name of a built-in"):
        descriptor_class("scan-context")
