"""Issue 23: loop export a back end loads (g2o vertices + edges with information, TUM text)."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.loop_export import (
    export_loop_file,
    information_from_fitness,
    read_g2o,
    upper_triangle,
)
from lidar_iris_eval.matching.geometry import invert_pose, yaw_pose


def _trajectory(n: int = 8) -> np.ndarray:
    """A quarter circle of poses, turning 10 deg a frame, 1 m apart, climbing 0.1 m."""
    P = np.stack([yaw_pose(10.0 * k, (np.cos(k / 5), np.sin(k / 5), 0.1 * k)) for k in range(n)])
    return P


def test_information_from_fitness_hand_computed():
    # rmse 0.2 m, inlier ratio 0.25: sigma_t = 0.2 / 0.5 = 0.4 m, sigma_r = 0.04 rad
    info = information_from_fitness(0.25, 0.2)
    assert np.allclose(np.diag(info), [6.25] * 3 + [4 / 0.04**2] * 3)
    assert np.count_nonzero(info - np.diag(np.diag(info))) == 0
    # the 1 cm floor: a perfect fit does not give an infinite weight
    assert np.allclose(np.diag(information_from_fitness(1.0, 0.0))[:3], 1e4)
    # no fitness (not refined): the identity placeholder
    assert np.array_equal(information_from_fitness(np.nan, np.nan), np.eye(6))
    assert len(upper_triangle(info)) == 21


def test_g2o_round_trip_counts_and_poses(tmp_path):
    P = _trajectory()
    q, m = np.array([5, 6, 7]), np.array([0, 1, 2])
    T = invert_pose(P[q]) @ P[m]  # consistent loops: P_j = P_i @ T
    T[1, :3, 3] = np.nan  # a yaw-only loop: not an SE(3) edge
    ids = np.arange(100, 108)
    with pytest.warns(UserWarning, match="1 accepted loop"):
        n = export_loop_file(tmp_path / "l.g2o", q, m, T, vertex_poses=P, frame_ids=ids,
                             inlier_ratio=np.array([0.5, 0.6, np.nan]),
                             rmse_m=np.array([0.1, 0.1, np.nan]))
    assert n == 2
    g = read_g2o(tmp_path / "l.g2o")
    assert sorted(g.vertices) == list(ids) and g.fixed == [100]
    assert [(a, b) for a, b, _, _ in g.edges] == [(105, 100), (107, 102)]
    for k, (_vid, pose) in enumerate(sorted(g.vertices.items())):
        assert np.allclose(pose, P[k], atol=1e-7)
    for a, b, meas, _ in g.edges:  # each edge agrees with its vertices
        assert np.allclose(invert_pose(g.vertices[a]) @ g.vertices[b], meas, atol=1e-6)
    assert np.allclose(np.diag(g.edges[0][3]), [50] * 3 + [2e4] * 3)  # sigma_t 0.1/sqrt(.5)
    assert np.array_equal(g.edges[1][3], np.eye(6))


def test_g2o_loads_in_gtsam_with_zero_error(tmp_path):
    gtsam = pytest.importorskip("gtsam")
    P = _trajectory()
    q, m = np.array([5, 6, 7]), np.array([0, 1, 2])
    T = invert_pose(P[q]) @ P[m]
    path = tmp_path / "l.g2o"
    export_loop_file(path, q, m, T, vertex_poses=P, inlier_ratio=np.full(3, 0.7),
                     rmse_m=np.full(3, 0.2))
    graph, initial = gtsam.readG2o(str(path), True)
    assert initial.size() == len(P) and graph.size() == 3
    # loops consistent with the vertices: the graph's error at the initial values is zero
    assert graph.error(initial) == pytest.approx(0.0, abs=1e-9)
    # a wrong loop (1 m off) is not: the convention of the edge direction is checked
    T[0, 0, 3] += 1.0
    export_loop_file(path, q, m, T, vertex_poses=P, inlier_ratio=np.full(3, 0.7),
                     rmse_m=np.full(3, 0.2))
    graph, initial = gtsam.readG2o(str(path), True)
    assert graph.error(initial) > 1.0


def test_tum_and_txt_formats(tmp_path):
    P = _trajectory()
    q, m = np.array([5, 6]), np.array([0, 1])
    T = invert_pose(P[q]) @ P[m]
    T[1, :3, 3] = np.nan
    times = np.arange(8) * 0.1 + 1000.0
    assert export_loop_file(tmp_path / "l.tum", q, m, T, times=times) == 2
    lines = (tmp_path / "l.tum").read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 3
    first = lines[1].split()
    assert len(first) == 9 and float(first[0]) == pytest.approx(1000.5)
    assert float(first[1]) == pytest.approx(1000.0)
    assert lines[2].split()[2] == "nan"  # yaw-only: translation unknown
    assert export_loop_file(tmp_path / "l.txt", q, m, T) == 2
    assert (tmp_path / "l.txt").read_text().split()[:2] == ["5", "0"]


def test_bad_export_and_bad_g2o(tmp_path):
    with pytest.raises(LirisError, match="needs a"):
        export_loop_file(tmp_path / "l.csv", np.array([1]), np.array([0]), np.eye(4)[None])
    with pytest.raises(LirisError, match="one pose per frame"):
        export_loop_file(tmp_path / "l.g2o", np.array([1]), np.array([0]), np.eye(4)[None])
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1"
                   + " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n")
    with pytest.raises(LirisError, match="missing vertex"):
        read_g2o(bad)
    bad.write_text("VERTEX_SE2 0 0 0 0\n")
    with pytest.raises(LirisError, match="unknown record"):
        read_g2o(bad)
