"""Pose conventions: yaw sign of LiDAR Iris / Scan Context, ground truth, errors, loop export,
and the frozen evaluation settings."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.base import yaw_to_pose
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.loop_export import export_loop_file as export_loops
from lidar_iris_eval.evaluation.poses import (
    pose_errors,
    relative_ground_truth,
    summarize_pose_errors,
)
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.matching.geometry import transform_points, yaw_pose


def street_scan(seed: int = 0) -> np.ndarray:
    """Ground plus walls and poles at random bearings: enough structure for a yaw."""
    rng = np.random.default_rng(seed)
    parts = [np.c_[rng.uniform(-40, 40, (4000, 2)), np.full(4000, -1.7)]]
    for _ in range(25):
        c = rng.uniform(-35, 35, 2)
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        t = rng.uniform(0, rng.uniform(2, 12), 300)
        z = rng.uniform(-1.7, rng.uniform(0, 6), 300)
        parts.append(np.c_[c + t[:, None] * d, z])
    return np.concatenate(parts).astype(np.float32)


@pytest.mark.parametrize("name", ["lidar-iris", "scan-context"])
@pytest.mark.parametrize("angle", [30.0, 150.0, 180.0, 250.0])
def test_yaw_only_pose_of_a_rotated_scan_matches_ground_truth(name, angle):
    desc = get_descriptor(name)
    query = street_scan()
    # the candidate scan is the same place seen by a sensor turned by -angle: its points
    # are the query's turned CCW by angle
    candidate = transform_points(yaw_pose(angle), query).astype(np.float32)
    _, yaw = desc.distance(desc.compute(query), desc.compute(candidate))
    # LiDAR poses: the query at the origin, the candidate turned by -angle, so that
    # P_candidate @ candidate_points == query_points (the same world)
    poses = np.stack([yaw_pose(-angle), np.eye(4)])
    np.testing.assert_allclose(transform_points(poses[0], candidate), query, atol=1e-4)
    gt = relative_ground_truth(poses, np.array([1]), np.array([0]))
    rre, rte = pose_errors(yaw_to_pose(np.array([yaw])), gt)
    assert rre[0] < 3.5  # one Scan Context sector is 6 degrees
    assert np.isnan(rte[0])  # yaw only: no translation error
    # the opposite sign would be off by 2 * angle (mod 360): the test can fail
    wrong, _ = pose_errors(yaw_to_pose(np.array([-yaw])), gt)
    if angle != 180.0:
        assert wrong[0] > 40


def test_pose_errors_hand_computed():
    gt = np.stack([yaw_pose(10.0, (1, 0, 0)), yaw_pose(0.0, (0, 0, 0))])
    est = np.stack([yaw_pose(13.0, (1, 0.3, 0.4)), yaw_to_pose(np.array(350.0))])
    rre, rte = pose_errors(est, gt)
    np.testing.assert_allclose(rre, [3.0, 10.0])  # full pose: 3 deg; yaw-only 350 -> -10
    np.testing.assert_allclose(rte[:1], [0.5])
    assert np.isnan(rte[1])
    s = summarize_pose_errors(np.array([1.0, 2, 3, np.nan]), np.full(4, np.nan),
                              np.array([True, True, True, True]))
    assert s["rre_deg_median"] == 2.0 and s["n_rre_deg"] == 3
    assert s["rte_m_median"] is None and s["rte_m_p90"] is None


def test_relative_ground_truth_is_query_frame():
    P = np.stack([yaw_pose(90.0, (10, 0, 0)), yaw_pose(0.0, (0, 0, 0))])
    T = relative_ground_truth(P, np.array([1, 0]), np.array([0, -1]))
    # frame 0 sits at (10, 0, 0) facing +y: its origin is (10, 0, 0) in frame 1
    np.testing.assert_allclose(T[0] @ [0, 0, 0, 1], [10, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(T[0] @ [1, 0, 0, 1], [10, 1, 0, 1], atol=1e-12)
    assert np.isnan(T[1]).all()


def test_export_loops_formats(tmp_path):
    pose = np.stack([yaw_pose(90.0, (1, 2, 3)), yaw_to_pose(np.array(90.0))])
    with pytest.warns(UserWarning, match="1 accepted loop"):
        n = export_loops(tmp_path / "l.g2o", np.array([5, 6]), np.array([1, 2]), pose,
                         vertex_poses=np.tile(np.eye(4), (7, 1, 1)))
    assert n == 1
    line = (tmp_path / "l.g2o").read_text().splitlines()[-1].split()
    assert line[:3] == ["EDGE_SE3:QUAT", "5", "1"]
    h = np.sqrt(0.5)
    np.testing.assert_allclose([float(v) for v in line[3:10]], [1, 2, 3, 0, 0, h, h])
    info = [float(v) for v in line[10:]]
    assert len(info) == 21 and sum(info) == 6.0  # identity, upper triangle
    assert export_loops(tmp_path / "l.txt", np.array([5, 6]), np.array([1, 2]), pose) == 2
    rows = np.loadtxt(tmp_path / "l.txt")
    np.testing.assert_allclose(rows[1, 5:], [0, 0, -h, h], atol=1e-9)  # yaw 90 -> Rz(-90)
    assert np.isnan(rows[1, 2:5]).all()
    with pytest.raises(LirisError, match="g2o, .tum, .txt"):
        export_loops(tmp_path / "l.csv", np.array([1]), np.array([0]), pose[:1])


def test_settings_named_exclusion_windows_and_library_errors(monkeypatch):
    monkeypatch.setattr("lidar_iris_eval.errors._FLAGS", {})  # as without the CLI loaded
    assert Settings().exclude == 30 and Settings().exclude_name == "paper"
    s = Settings(exclude="reference")
    assert (s.exclude, s.exclude_name) == (300, "reference")
    assert Settings(exclude=50).exclude_name == "custom"
    with pytest.raises(AttributeError):
        s.radius = 3.0  # frozen
    with pytest.raises(LirisError) as err:
        Settings(exclude="sometimes")
    assert str(err.value).startswith("exclude='sometimes'")  # a keyword, not a CLI flag
    with pytest.raises(LirisError, match="radius"):
        Settings(radius=0)
    with pytest.raises(LirisError, match="recall_denominator"):
        Settings(recall_denominator="all")
