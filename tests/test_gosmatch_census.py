"""``scripts/bench_gosmatch.py census``: the object counts docs/esm.md uses to explain park's 0.

A two-scan KITTI-layout sequence built by hand, so every count is known:
scan 0 holds two compact trunks (12 points each), one car (15 points) and five
lone trunk points 5 m apart (clusters of one, dropped); scan 1 holds four
compact trunks. Objects per scan are then 3 and 4, one scan reaches the four
objects verification needs, and 72 of the 77 trunk points lie in kept clusters.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_gosmatch.py"
TRUNK, CAR = 71, 10


def blob(centre, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points within 0.1 m of ``centre`` (one cluster at 0.5 m linkage)."""
    return np.asarray(centre, dtype=np.float64) + rng.uniform(-0.1, 0.1, size=(n, 3))


def write_scan(seq: Path, i: int, parts: list[tuple[np.ndarray, int]]) -> None:
    points = np.concatenate([p for p, _ in parts])
    labels = np.concatenate([np.full(len(p), c, dtype=np.uint32) for p, c in parts])
    cloud = np.zeros((len(points), 4), dtype=np.float32)
    cloud[:, :3] = points
    cloud.tofile(seq / "velodyne" / f"{i:06d}.bin")
    labels.tofile(seq / "labels" / f"{i:06d}.label")


@pytest.fixture
def sequence(tmp_path):
    rng = np.random.default_rng(0)
    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    (seq / "labels").mkdir()
    lone = np.array([[20.0 + 5 * k, -10.0, 0.0] for k in range(5)])
    write_scan(seq, 0, [(blob([5, 0, 0], 12, rng), TRUNK), (blob([0, 8, 0], 12, rng), TRUNK),
                        (blob([-6, -3, 0], 15, rng), CAR), (lone, TRUNK)])
    write_scan(seq, 1, [(blob([5 * k - 8, 4, 0], 12, rng), TRUNK) for k in range(4)])
    np.savetxt(seq / "poses.txt", np.tile(np.eye(4)[:3].reshape(1, 12), (2, 1)))
    np.savetxt(seq / "times.txt", [0.0, 0.1])
    (seq / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return seq


def test_census_counts_objects_and_what_verification_needs(sequence):
    done = subprocess.run([sys.executable, str(SCRIPT), "census", str(sequence)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["scans"] == 2
    assert report["labelled_points_per_scan_mean"] == {"vehicle": 7.5, "trunk": 38.5,
                                                       "pole": 0.0}
    assert report["objects_per_scan_mean"] == {"vehicle": 0.5, "trunk": 3.0, "pole": 0.0}
    assert report["objects_per_scan_max"] == 4 and report["objects_per_scan_median"] == 3.5
    assert report["min_inliers"] == 4 and report["scans_with_at_least_4_objects"] == 1
    assert report["trunk_points_in_kept_clusters"] == pytest.approx(72 / 77, abs=1e-3)
