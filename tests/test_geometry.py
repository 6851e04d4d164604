"""Shared geometric tools: Kabsch, RANSAC/PROSAC, nearest neighbours, pose errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_iris_eval.matching import geometry as g


def random_pose(rng: np.random.Generator, max_t: float = 20.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-max_t, max_t, 3)
    return T


# ----------------------------------------------------------------- hand-computed


def test_yaw_pose_hand_computed():
    T = g.yaw_pose(90.0)
    # x axis -> y axis for a CCW quarter turn
    np.testing.assert_allclose(T @ [1, 0, 0, 1], [0, 1, 0, 1], atol=1e-15)
    np.testing.assert_allclose(g.yaw_deg_of(g.yaw_pose(-30.0)), -30.0)
    assert np.isnan(g.yaw_pose(10, translation=(np.nan,) * 3)[:3, 3]).all()


def test_kabsch_hand_computed_quarter_turn_and_shift():
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    # rotate 90 deg about z: (x, y, z) -> (-y, x, z), then shift by (2, 3, 4)
    dst = np.array([[2, 3, 4], [2, 4, 4], [1, 3, 4], [2, 3, 5]], float)
    T = g.kabsch(src, dst)
    expected = np.array([[0, -1, 0, 2], [1, 0, 0, 3], [0, 0, 1, 4], [0, 0, 0, 1]], float)
    np.testing.assert_allclose(T, expected, atol=1e-12)


def test_kabsch_never_returns_a_reflection():
    src = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    dst = src * [1, 1, -1]  # a mirror image: best proper rotation, not the mirror
    T = g.kabsch(src, dst)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_kabsch_weights_ignore_zero_weight_outlier():
    rng = np.random.default_rng(0)
    T = random_pose(rng)
    src = rng.normal(size=(6, 3))
    dst = g.transform_points(T, src)
    dst[5] += 100.0
    w = np.array([1, 1, 1, 1, 1, 0.0])
    np.testing.assert_allclose(g.kabsch(src, dst, w), T, atol=1e-9)


def test_kabsch_rejects_too_few_points():
    with pytest.raises(ValueError, match="at least 3"):
        g.kabsch(np.zeros((2, 3)), np.zeros((2, 3)))


def test_pose_errors_hand_computed():
    a = g.yaw_pose(10.0, translation=(1, 2, 3))
    b = g.yaw_pose(-20.0, translation=(4, 6, 3))
    assert g.rotation_error_deg(a, b) == pytest.approx(30.0)
    assert g.translation_error_m(a, b) == pytest.approx(5.0)
    assert g.yaw_error_deg(g.yaw_pose(179.0), g.yaw_pose(-179.0)) == pytest.approx(2.0)
    assert g.rotation_error_deg(g.yaw_pose(0), g.yaw_pose(180)) == pytest.approx(180.0)
    # yaw error ignores roll: a 5 deg roll on the ground truth is not counted
    roll = np.eye(4)
    roll[:3, :3] = Rotation.from_euler("x", 5, degrees=True).as_matrix()
    gt = g.yaw_pose(40.0) @ roll
    assert g.yaw_error_deg(g.yaw_pose(40.0), gt) == pytest.approx(0.0, abs=1e-9)
    assert g.rotation_error_deg(g.yaw_pose(40.0), gt) == pytest.approx(5.0)


def printed(T: np.ndarray) -> np.ndarray:
    """``T`` as KITTI prints it: every entry to 7 significant digits (``%e``)."""
    return np.vectorize(lambda v: float(f"{v:.6e}"))(T)


@pytest.mark.parametrize("seed", range(6))
def test_rotation_error_of_printed_rotations_keeps_small_angles(seed):
    # Issue 40: the trace of two rotations printed to 7 digits can exceed 3 and
    # was clipped, so a pose 0.022 deg off read 0.0. The expected angle comes
    # from scipy's rotation vector of the exact relative rotation.
    rng = np.random.default_rng(seed)
    gt = random_pose(rng)
    axis = rng.normal(size=3)
    delta = Rotation.from_rotvec(np.deg2rad(0.022) * axis / np.linalg.norm(axis))
    est = gt.copy()
    est[:3, :3] = gt[:3, :3] @ delta.as_matrix()
    exact = np.rad2deg(np.linalg.norm(delta.as_rotvec()))
    got = g.rotation_error_deg(printed(est), printed(gt))
    assert got == pytest.approx(exact, abs=1e-3)


def test_rotation_error_of_stacks_with_nan_and_near_half_turns():
    near = g.yaw_pose(179.99)
    est = np.stack([g.yaw_pose(10.0), np.full((4, 4), np.nan), near])
    gt = np.stack([g.yaw_pose(10.0005), g.yaw_pose(0.0), g.yaw_pose(0.0)])
    got = g.rotation_error_deg(est, gt)
    assert got[0] == pytest.approx(0.0005, abs=1e-6)
    assert np.isnan(got[1])
    assert got[2] == pytest.approx(179.99, abs=1e-6)


def test_invert_pose_and_quaternion():
    rng = np.random.default_rng(1)
    for _ in range(20):
        T = random_pose(rng)
        np.testing.assert_allclose(g.invert_pose(T) @ T, np.eye(4), atol=1e-12)
        q = g.quaternion_xyzw(T)
        R = Rotation.from_quat(q).as_matrix()
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
        assert q[3] >= 0
    # hand-computed: 180 deg about x -> (1, 0, 0, 0)
    np.testing.assert_allclose(g.quaternion_xyzw(np.diag([1.0, -1, -1])), [1, 0, 0, 0])


# ----------------------------------------------------------------- properties


@pytest.mark.parametrize("seed", range(10))
def test_kabsch_recovers_random_rigid_transform(seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    src = rng.normal(scale=10, size=(50, 3))
    dst = g.transform_points(T, src)
    np.testing.assert_allclose(g.kabsch(src, dst), T, atol=1e-9)


@pytest.mark.parametrize("fit", ["ransac", "prosac"])
@pytest.mark.parametrize("seed", range(5))
def test_robust_fit_recovers_pose_with_60_percent_outliers(fit, seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    n, n_in = 100, 40
    src = rng.uniform(-30, 30, size=(n, 3))
    dst = g.transform_points(T, src) + rng.normal(scale=0.02, size=(n, 3))
    outliers = rng.permutation(n)[: n - n_in]
    dst[outliers] = rng.uniform(-30, 30, size=(len(outliers), 3))
    kw = dict(threshold=0.2, iterations=500, min_inliers=10, rng=np.random.default_rng(seed))
    if fit == "ransac":
        res = g.ransac_rigid(src, dst, **kw)
    else:
        # quality order: true inliers first, the way good descriptor distances rank them
        truth = np.ones(n, bool)
        truth[outliers] = False
        order = np.concatenate([np.flatnonzero(truth), outliers])
        res = g.prosac_rigid(src, dst, order, **kw)
    assert res.success
    expect = np.ones(n, bool)
    expect[outliers] = False
    assert np.array_equal(res.inliers, expect)
    assert g.rotation_error_deg(res.pose, T) < 0.1
    assert g.translation_error_m(res.pose, T) < 0.05
    assert res.residuals.shape == (n,)


def test_ransac_is_deterministic_given_rng_state():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(60, 3)) * 10
    dst = rng.normal(size=(60, 3)) * 10  # pure noise: the answer depends on the samples
    kw = dict(threshold=1.0, iterations=200, min_inliers=3)
    a = g.ransac_rigid(src, dst, rng=np.random.default_rng(7), **kw)
    b = g.ransac_rigid(src, dst, rng=np.random.default_rng(7), **kw)
    np.testing.assert_array_equal(a.pose, b.pose)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    order = np.arange(60)
    c = g.prosac_rigid(src, dst, order, rng=np.random.default_rng(7), **kw)
    d = g.prosac_rigid(src, dst, order, rng=np.random.default_rng(7), **kw)
    np.testing.assert_array_equal(c.pose, d.pose)


def test_prosac_with_confidence_stops_early_on_good_ranking():
    rng = np.random.default_rng(5)
    T = random_pose(rng)
    n = 200
    src = rng.uniform(-30, 30, size=(n, 3))
    dst = g.transform_points(T, src)
    dst[100:] = rng.uniform(-30, 30, size=(100, 3))
    res = g.prosac_rigid(src, dst, np.arange(n), threshold=0.1, iterations=5000, min_inliers=10,
                         rng=np.random.default_rng(0), confidence=0.999)
    assert res.success and res.n_inliers == 100
    # w = 0.5, s = 3 -> about 52 samples needed; one batch of 256 suffices
    assert res.hypotheses <= 256


def test_prosac_samples_start_from_the_top():
    s = g.prosac_samples(50, 400, 3, np.random.default_rng(0))
    assert s.shape == (400, 3)
    assert all(len(set(row)) == 3 for row in s.tolist())
    assert set(s[0]) == {0, 1, 2}
    # the subset grows monotonically: the largest index seen never jumps back
    running = np.maximum.accumulate(s.max(axis=1))
    assert running[10] < running[-1]
    assert s[:20].max() < 20


def test_ransac_fails_cleanly_with_too_few_pairs():
    res = g.ransac_rigid(np.zeros((2, 3)), np.zeros((2, 3)), threshold=1, iterations=10,
                         min_inliers=3, rng=np.random.default_rng(0))
    assert not res.success and res.n_inliers == 0


@pytest.mark.parametrize("dim", [3, 40])
def test_nearest_neighbours_match_brute_force(dim):
    rng = np.random.default_rng(dim)
    a = rng.normal(size=(70, dim))
    b = rng.normal(size=(90, dim))
    full = np.linalg.norm(a[:, None] - b[None], axis=2)
    d, j = g.nearest_neighbours(a, b)
    np.testing.assert_array_equal(j, full.argmin(axis=1))
    np.testing.assert_allclose(d, full.min(axis=1), rtol=1e-9)
    d3, j3 = g.nearest_neighbours(a, b, k=3)
    np.testing.assert_array_equal(j3, np.argsort(full, axis=1)[:, :3])
    np.testing.assert_allclose(d3, np.sort(full, axis=1)[:, :3], rtol=1e-9)


def test_nearest_neighbours_pads_missing():
    d, j = g.nearest_neighbours(np.zeros((2, 3)), np.ones((1, 3)), k=2)
    assert j.tolist() == [[0, -1], [0, -1]]
    assert np.isinf(d[:, 1]).all()


def test_mutual_nearest_hand_computed():
    a = np.array([[0.0, 0], [10, 0], [10.4, 0]])
    b = np.array([[0.1, 0], [10.5, 0]])
    ia, ib, d = g.mutual_nearest(a, b)
    # a1 -> b1 but b1's nearest is a2, so only (0, 0) and (2, 1) are mutual
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 1]
    np.testing.assert_allclose(d, [0.1, 0.1])
    assert len(g.mutual_nearest(a, np.empty((0, 2)))[0]) == 0
