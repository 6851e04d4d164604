"""ESM through liris eval: both protocols via the two-stage interface, full 6-DoF poses."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import run_cli

from lidar_iris_eval.descriptors.esm import network
from lidar_iris_eval.simulate.pipeline import simulate_sequence


@pytest.mark.skipif(not network.WEIGHTS_FILE.is_file(), reason="no ESM weights shipped")
def test_esm_runs_both_protocols(tmp_path, capsys):
    seq = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=60, azimuth_steps=1024)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "-d", "esm:single-scan", "--protocol", "1",
                            "--protocol", "2",
                            "--cache-dir", tmp_path / "cache", "--out", out, "-q"], capsys)
    assert code == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    rows = {r["protocol"]: r for r in metrics["results"] if r["descriptor"] == "esm"}
    assert set(rows) == {1, 2}
    assert rows[1]["pose_estimate"] == "full"
    m = pd.read_csv(out / "protocol1" / "esm" / "matches.csv")
    accepted = m[np.isfinite(m["distance"])]
    assert len(accepted) > 0
    # every accepted match has a pose with a proper rotation and >= 3 inliers
    assert (accepted["inliers"] >= 3).all()
    for _, r in accepted.iterrows():
        R = np.array([[r[f"T{i}{j}"] for j in range(3)] for i in range(3)])
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.isclose(np.linalg.det(R), 1)
    rejected = m[~np.isfinite(m["distance"])]
    assert (rejected["match"] == -1).all() or len(rejected) == 0
