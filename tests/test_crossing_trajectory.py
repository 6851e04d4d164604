"""scripts/crossing_trajectory.py: the drive re-crosses its start at the angle asked for."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.simulate.trajectories import trajectory_from_file
from lidar_iris_eval.simulate.writer import default_tr

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "crossing_trajectory.py"
spec = importlib.util.spec_from_file_location("crossing_trajectory", SCRIPT)
crossing = importlib.util.module_from_spec(spec)
spec.loader.exec_module(crossing)


@pytest.mark.parametrize("angle", [90.0, 70.0, 120.0])
def test_the_return_crosses_the_start_at_the_angle(tmp_path, angle):
    out = tmp_path / "x.txt"
    crossing.main([str(out), "--angle", str(angle), "--step", "1.0"])
    cam = np.loadtxt(out).reshape(-1, 3, 4)
    full = np.tile(np.eye(4), (len(cam), 1, 1))
    full[:, :3] = cam
    lidar = trajectory_from_file(full, default_tr(), None)  # what liris simulate drives
    xy = lidar[:, :2, 3]
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    # poses every step along the rounded path: a chord is never longer than its arc
    assert np.all(steps <= 1.0 + 1e-6) and np.median(steps) > 0.999
    assert np.allclose(lidar[:, 2, 3], 0) and np.allclose(lidar[:, 2, 2], 1)  # planar, z up
    yaw = np.degrees(np.arctan2(lidar[:, 1, 0], lidar[:, 0, 0]))
    assert abs(yaw[0]) < 1.0  # leaves along +x
    late = np.arange(len(xy)) > len(xy) // 2
    near = np.flatnonzero(late & (np.linalg.norm(xy, axis=1) < 1.0))
    assert len(near) >= 1  # comes back through the origin
    turn = (yaw[near] - yaw[0] + 180) % 360 - 180
    assert np.allclose(turn, angle, atol=2.0)
