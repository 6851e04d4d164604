"""scripts/bench_e2e.py on a tiny world: the JSON it records and the metric check.

No timing is asserted: only that every figure is present and follows from the
world (scan counts, results per descriptor and protocol), that the world is
simulated once and then reused, and that the metrics digest detects a change.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_e2e.py"
FRAMES = 40


@pytest.fixture(scope="module")
def e2e():
    spec = importlib.util.spec_from_file_location("bench_e2e", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def trajectory(tmp_path_factory) -> Path:
    """Two laps of a 30 m circle (KITTI camera-frame poses): the second lap revisits."""
    path = tmp_path_factory.mktemp("traj") / "poses.txt"
    rows = []
    for a in np.linspace(0, 4 * np.pi, FRAMES):
        rows.append(" ".join(f"{v:.6e}" for v in
                             [1, 0, 0, 30 * np.cos(a), 0, 1, 0, 0, 0, 0, 1, 30 * np.sin(a)]))
    path.write_text("\n".join(rows) + "\n")
    return path


def test_tiny_world_report_and_metric_check(e2e, trajectory, tmp_path, capsys):
    world, out = tmp_path / "world", tmp_path / "e2e.json"
    args = ["--world", str(world), "--trajectory", str(trajectory), "--azimuth-steps", "96",
            "-d", "scan-context,m2dp", "--workers", "1"]
    assert e2e.main([*args, "--json-out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["simulation"]["reused"] is False and report["simulation"]["frames"] == FRAMES
    assert report["wall_s"] > 0 and report["cpu_s"] > 0
    assert report["peak_rss_bytes"]["max_single_process"] > 0
    assert report["peak_rss_bytes"]["process_tree_sampled"] >= 0
    assert "--cache-dir" in report["command"]  # a fresh cache, not the user's
    for name in ("scan-context", "m2dp"):
        stage = report["stages"][name]
        assert stage["scans"] == FRAMES
        assert stage["read_s_sum"] > 0 and stage["extract_cpu_s_sum"] > 0
        assert {"protocol1", "protocol2"} <= set(stage)
    got = {(r["descriptor"], r["protocol"]) for r in report["metrics"]}
    assert got == {(d, p) for d in ("scan-context", "m2dp") for p in (1, 2)}
    assert not any("ms_per" in k or "us_per" in k for r in report["metrics"] for k in r)
    # a second run reuses the world and reproduces the metrics exactly
    again = tmp_path / "again.json"
    assert e2e.main([*args, "--json-out", str(again), "--expect", str(out)]) == 0
    second = json.loads(again.read_text())
    assert second["simulation"]["reused"] is True
    assert second["metrics_sha256"] == report["metrics_sha256"]
    assert "identical" in capsys.readouterr().err
    # a changed metric is caught
    report["metrics_sha256"] = "0" * 64
    out.write_text(json.dumps(report))
    assert e2e.main([*args, "--json-out", str(again), "--expect", str(out)]) == 1
    # another simulation in the same folder is refused, not silently reused
    with pytest.raises(SystemExit, match="holds another simulation"):
        e2e.main(["--world", str(world), "--azimuth-steps", "128"])
