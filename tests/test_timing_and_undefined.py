"""Numbers that must not be silently wrong: timings, undefined metrics, degenerate input.

* Extraction time is the thread's CPU time in ``compute`` after an untimed
  first call (compilation), so waiting for a core is not descriptor cost.
* Matching loops run their kernels once untimed before starting the clock.
* An undefined metric is NaN in the library, ``null`` in JSON, an empty CSV
  cell and ``n/a`` in tables, with one warning saying why.
* Mostly empty descriptors (a sequence in millimetres) are warned about.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest
from conftest import run_cli, write_kitti_sequence
from test_protocols import ToyHist, ToyParams, line_poses, random_scan, two_pass_sequence

from lidar_iris_eval.descriptors import _REGISTRY
from lidar_iris_eval.errors import LirisWarning
from lidar_iris_eval.evaluation.metrics import pr_curve, summarize
from lidar_iris_eval.extract import extract
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.matching.blocks import affinity_matrix

COMPILE_S = 0.3  # CPU seconds the first call burns, like a numba compilation


def burn(seconds: float) -> None:
    """Spend ``seconds`` of this thread's CPU time."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


@dataclass(frozen=True)
class FirstCallParams(ToyParams):
    sleep: float = 0.0  # wall seconds per compute spent off the CPU (a busy machine)


class CompilesOnFirstCall(ToyHist):
    """ToyHist whose first compute and first pairwise call burn CPU (as numba compiles)."""

    name = "toy-compiles"
    params_type = FirstCallParams
    warm_up = True  # compiles: extraction must run it once untimed
    compiled: set = set()

    def compute(self, points):
        if "compute" not in self.compiled:
            self.compiled.add("compute")
            burn(COMPILE_S)
        if self.params.sleep:
            time.sleep(self.params.sleep)
        return super().compute(points)

    def pairwise(self, queries, database):
        if "pairwise" not in self.compiled:
            self.compiled.add("pairwise")
            burn(COMPILE_S)
        return super().pairwise(queries, database)


@pytest.fixture(autouse=True)
def toys(monkeypatch):
    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")
    CompilesOnFirstCall.compiled = set()


def test_extraction_time_excludes_the_first_call(tmp_path):
    seq = open_sequence(two_pass_sequence(tmp_path / "seq", n_per_pass=6))
    db = extract(seq, CompilesOnFirstCall())
    assert db.extract_s.max() < COMPILE_S / 3, db.extract_s


def test_extraction_time_is_cpu_not_waiting(tmp_path):
    """Time off the CPU (sleep here; a contended core on a busy machine) is not cost."""
    seq = open_sequence(two_pass_sequence(tmp_path / "seq", n_per_pass=4))
    db = extract(seq, CompilesOnFirstCall(FirstCallParams(sleep=0.05)))
    assert db.extract_s.max() < 0.02, db.extract_s  # wall time would be >= 0.05 each


def test_matching_time_excludes_compilation():
    rng = np.random.default_rng(0)
    descriptor = CompilesOnFirstCall()
    descs = np.stack([ToyHist().compute(random_scan(rng)) for _ in range(30)])
    affinity, _ = affinity_matrix(descriptor, descs, exclude=5)
    assert affinity.seconds < COMPILE_S / 3, affinity.seconds


# --------------------------------------------------------------------------- undefined metrics
def test_zero_positives_leave_r100p_and_ep_undefined():
    curve = pr_curve(np.array([0.1, 0.2, 0.3]), np.zeros(3, bool), denominator=0)
    with pytest.warns(LirisWarning, match="no positives"):
        values = summarize(curve, 0, 3, "protocol X")
    assert all(np.isnan(v) for v in values.values()), values


def test_positives_but_nothing_accepted_is_zero_recall():
    curve = pr_curve(np.array([np.nan, np.inf]), np.array([True, False]), denominator=1)
    values = summarize(curve, 1, 2)
    assert values["ap"] == 0.0 and values["r100p"] == 0.0 and values["f1_max"] == 0.0
    assert np.isnan(values["ep"])  # no precision at the lowest recall


def _eval(tmp_path, seq, capsys, *extra):
    out = tmp_path / "run"
    code, stdout, err = run_cli(["eval", seq, "--protocol", "1", "--protocol", "2", "-d", "toy",
                                 "--cache-dir", tmp_path / "cache", "--out", out, *extra],
                                capsys)
    assert code == 0, err
    return out, stdout, err


def _assert_undefined(out, stdout, err, protocols, keys=("ap", "f1_max", "r100p", "ep")):
    metrics = json.loads((out / "metrics.json").read_text())["results"]
    table = pd.read_csv(out / "metrics.csv")
    for row, csv_row in zip(metrics, table.to_dict("records"), strict=True):
        if row["protocol"] in protocols:
            assert all(row[k] is None for k in keys), row
            assert all(pd.isna(csv_row[k]) for k in keys), csv_row
    assert "n/a" in stdout and "0.0000" not in stdout.split("\n")[2]
    warned = [line for line in err.splitlines() if "undefined" in line]
    assert len(warned) == len(protocols), err  # once per protocol, not per descriptor


def test_exclusion_window_longer_than_sequence(tmp_path, capsys):
    seq = two_pass_sequence(tmp_path / "seq", n_per_pass=6)
    out, stdout, err = _eval(tmp_path, seq, capsys, "--exclude", "300", "-q")
    _assert_undefined(out, stdout, err, protocols={1})
    assert "the exclusion window is at least the sequence length" in err


def test_one_frame_sequence(tmp_path, capsys):
    rng = np.random.default_rng(0)
    seq = write_kitti_sequence(tmp_path / "one", [random_scan(rng)], line_poses(np.zeros(1)))
    out, stdout, err = _eval(tmp_path, seq, capsys, "--exclude", "1", "-q")
    _assert_undefined(out, stdout, err, protocols={1, 2})
    assert "fewer than 2 frames" in err


def test_zero_positives_in_the_cli(tmp_path, capsys):
    rng = np.random.default_rng(0)
    scans = [random_scan(rng) for _ in range(8)]
    seq = write_kitti_sequence(tmp_path / "far", scans, line_poses(np.arange(8) * 50.0))
    out, stdout, err = _eval(tmp_path, seq, capsys, "--exclude", "2", "-q")
    _assert_undefined(out, stdout, err, protocols={1, 2})
    assert "no positives" in err


# --------------------------------------------------------------------------- degenerate input
def test_millimetre_scans_are_warned_about(tmp_path):
    rng = np.random.default_rng(0)
    scans = []
    for _ in range(6):
        r, a = rng.uniform(3, 19, 300), rng.uniform(0, 2 * np.pi, 300)
        metres = np.stack([r * np.cos(a), r * np.sin(a), rng.normal(0, 1, 300), np.ones(300)], 1)
        metres[:, :3] *= 1000  # millimetres: every point beyond the toy's 20 m range
        scans.append(metres)
    seq = open_sequence(write_kitti_sequence(tmp_path / "mm", scans,
                                             line_poses(np.arange(6) * 10.0)))
    with pytest.warns(LirisWarning, match="6 of 6 scans .* millimetres"):
        extract(seq, ToyHist())


def test_metric_scans_are_not_warned_about(tmp_path):
    seq = open_sequence(two_pass_sequence(tmp_path / "seq", n_per_pass=4))
    with warnings.catch_warnings():
        warnings.simplefilter("error", LirisWarning)
        extract(seq, ToyHist())


def test_simulate_names_the_pose_frame_of_each_count():
    from lidar_iris_eval.simulate.pipeline import SimConfig, SimReport

    report = SimReport("out", SimConfig(), 400, 4000, 202, 1.0, revisit_queries_camera=203)
    text = report.summary()
    assert "202 revisit queries at E=30, 4 m with LiDAR-frame poses" in text
    assert "203 with camera-frame poses" in text
