"""Issue 12's pose bar on the simulated ``tiny-mixed`` sequence: LiDAR Iris and Scan Context
report a rotation error, Iris's is below 2 degrees, and reverse revisits are not off by 180."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from lidar_iris_eval.cli import main
from lidar_iris_eval.simulate import simulate_sequence

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny-mixed")
    seq = simulate_sequence(root / "seq", preset="tiny-mixed")
    run = root / "run"
    try:
        main(["eval", str(seq), "--protocol", "1", "--descriptor", "lidar-iris,scan-context",
              "--cache-dir", str(root / "cache"), "--out", str(run), "--quiet", "--json"])
    except SystemExit as exit_:
        assert exit_.code in (0, None)
    metrics = json.loads((run / "metrics.json").read_text())
    return run, {r["descriptor"]: r for r in metrics["results"]}


@pytest.mark.parametrize("name", ["lidar-iris", "scan-context"])
def test_rotation_error_is_reported(tiny_run, name):
    _, rows = tiny_run
    row = rows[name]
    assert row["pose_estimate"] == "yaw"
    assert row["rre_deg_median"] is not None and row["n_rre_deg"] == row["n_true_top1"] > 50
    assert row["rte_m_median"] is None  # yaw only: no translation
    assert row["rre_deg_median"] < 6.0  # within one Scan Context sector


def test_lidar_iris_yaw_is_within_2_degrees_also_on_reverse_revisits(tiny_run):
    run, rows = tiny_run
    iris = rows["lidar-iris"]
    assert iris["rre_deg_median"] < 2.0
    assert iris["n_revisits_reverse"] > 20
    assert iris["rre_deg_median_reverse"] < 2.0 and iris["rre_deg_p90_reverse"] < 5.0
    table = pd.read_csv(run / "protocol1" / "lidar-iris" / "matches.csv")
    reverse = table[(table.is_true == 1) & (table.is_reverse == 1)]
    assert len(reverse) > 20 and (reverse.rre_deg < 90).all()  # none flipped by 180
