"""Issue 23: scan registration, registration recall, registration-checked ground truth."""

from __future__ import annotations

import builtins

import numpy as np
import pytest

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.loop_poses import LoopPoseSettings, registration_recall
from lidar_iris_eval.evaluation.poses import relative_ground_truth
from lidar_iris_eval.matching.geometry import (
    invert_pose,
    rotation_error_deg,
    translation_error_m,
    yaw_deg_of,
    yaw_pose,
)

small_gicp = pytest.importorskip("small_gicp")

from lidar_iris_eval.matching.registration import (  # noqa: E402
    PreparedScan,
    RegistrationSettings,
    fitness,
    initial_guess,
    refine_pairs,
    register_points,
)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A short simulated drive (consecutive scans overlap; ground truth exact)."""
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.simulate import simulate_sequence

    root = tmp_path_factory.mktemp("reg")
    simulate_sequence(root / "seq", preset="tiny-mixed", frames=12, azimuth_steps=384)
    return open_sequence(root / "seq")


def test_known_transform_is_recovered(sim):
    """A scan moved by a known T (20 deg yaw, 1 m, -0.5 m, 0.2 m) registers back to T."""
    pts = sim[3].astype(np.float64)
    T = yaw_pose(20.0, (1.0, -0.5, 0.2))
    source = (pts - T[:3, 3]) @ T[:3, :3]  # inv(T) applied: T maps source into target
    start = yaw_pose(20.0)  # a yaw-only estimate: the rotation, zero translation
    r = register_points(pts, source, start)
    assert r.ok and r.converged
    assert translation_error_m(r.pose[None], T[None])[0] < 0.02
    assert rotation_error_deg(r.pose[None], T[None])[0] < 0.1
    # voxel centroids of a moved cloud differ by up to half a voxel (0.125 m)
    assert r.inlier_ratio > 0.95 and r.rmse_m < 0.125


def test_fitness_of_identical_and_shifted_clouds(sim):
    s = RegistrationSettings()
    scan = PreparedScan(sim[0], s)
    ratio, rmse = fitness(scan.points, scan.kdtree, np.eye(4), s.inlier_m)
    assert ratio == 1.0 and rmse == 0.0
    far = yaw_pose(0.0, (1000.0, 0.0, 0.0))
    ratio, rmse = fitness(scan.points, scan.kdtree, far, s.inlier_m)
    assert ratio == 0.0 and np.isnan(rmse)  # no inlier: undefined, never 0


def test_initial_guess_rules():
    assert np.array_equal(initial_guess(None), np.eye(4))
    yaw_only = yaw_pose(30.0)
    yaw_only[:3, 3] = np.nan
    g = initial_guess(yaw_only)
    assert np.allclose(g[:3, :3], yaw_pose(30.0)[:3, :3]) and np.array_equal(g[:3, 3], [0, 0, 0])
    assert np.array_equal(initial_guess(np.full((4, 4), np.nan)), np.eye(4))
    full = yaw_pose(10.0, (1, 2, 3))
    assert np.array_equal(initial_guess(full), full)


def test_too_few_points_fail_as_nan():
    r = register_points(np.zeros((5, 3)), np.zeros((5, 3)))
    assert not r.ok and np.isnan(r.inlier_ratio) and np.isnan(r.rmse_m)


def test_consecutive_scans_from_yaw_only_guess(sim):
    """Scans 3 frames apart (about a metre) refine from yaw-only guesses to < 5 cm."""
    q = np.arange(3, 12)
    m = q - 3
    gt = relative_ground_truth(sim.poses, q, m)
    start = np.stack([yaw_pose(float(yaw_deg_of(g))) for g in gt])
    start[:, :3, 3] = np.nan
    r = refine_pairs(sim, q, m, start)
    assert r.registered.all()
    assert np.max(translation_error_m(r.pose, gt)) < 0.05
    assert np.max(rotation_error_deg(r.pose, gt)) < 0.5
    assert np.all(r.seconds > 0) and r.prepare_s > 0


def test_gt_refined_changes_exact_ground_truth_little(sim):
    """Simulated ground truth is exact: refining it moves it by < 0.02 m (median)."""
    q = np.arange(2, 12)
    m = q - 2
    gt = relative_ground_truth(sim.poses, q, m)
    r = refine_pairs(sim, q, m, gt)
    moved = translation_error_m(r.pose, gt)
    assert np.median(moved) < 0.02 and np.max(moved) < 0.05  # the bar is on the medians


def test_gt_refined_recovers_a_vertical_offset(sim):
    """Poses of the later frames lifted by 1 m: registration finds the offset within 5 cm."""
    class Lifted:
        has_objects = False

        def __init__(self, seq):
            self.seq = seq
            self.poses = seq.poses.copy()
            self.poses[6:, 2, 3] += 1.0

        def __getitem__(self, i):
            return self.seq[i]

    lifted = Lifted(sim)
    q = np.arange(6, 12)
    m = q - 3  # frames 3..5 unmoved, 6..11 lifted (the LiDAR z axis is the world's up here)
    assert np.allclose(sim.poses[:, :3, 2], [0, 0, 1], atol=0.05)
    wrong = relative_ground_truth(lifted.poses, q, m)
    true = relative_ground_truth(sim.poses, q, m)
    q_mask = m < 6
    assert np.all(translation_error_m(wrong[q_mask], true[q_mask]) > 0.9)
    r = refine_pairs(lifted, q, m, wrong)
    assert np.max(translation_error_m(r.pose, true)) < 0.05
    recovered = translation_error_m(r.pose[q_mask], wrong[q_mask])
    assert np.all(np.abs(recovered - 1.0) < 0.05)


def test_missing_library_is_one_line(monkeypatch):
    real_import = builtins.__import__

    def no_gicp(name, *args, **kwargs):
        if name == "small_gicp":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_gicp)
    with pytest.raises(LirisError, match=r"registration\]"):
        register_points(np.zeros((50, 3)), np.zeros((50, 3)))


def test_objects_sequence_is_refused():
    class Objects:
        has_objects = True

    with pytest.raises(LirisError, match="objects, not point clouds"):
        refine_pairs(Objects(), np.array([1]), np.array([0]), None)


def test_registration_recall_hand_computed():
    # 5 true matches: two succeed (errors 0.5 m/1 deg and 1.5 m/4 deg), one fails on
    # translation (3 m), one on rotation (6 deg), one has no pose; a false match is ignored
    rre = np.array([1.0, 4.0, 1.0, 6.0, np.nan, 0.1])
    rte = np.array([0.5, 1.5, 3.0, 0.1, np.nan, 0.1])
    true = np.array([1, 1, 1, 1, 1, 0], bool)
    out = registration_recall(rre, rte, true)
    assert out["rr"] == pytest.approx(2 / 5) and out["n_rr"] == 5
    assert out["rr_kind"] == "full"
    assert out["rr_rte_m_mean"] == pytest.approx(1.0)
    assert out["rr_rre_deg_mean"] == pytest.approx(2.5)
    # thresholds are configurable: 3.5 m / 7 deg admits rows 2 and 3 as well
    assert registration_recall(rre, rte, true, 3.5, 7.0)["rr"] == pytest.approx(4 / 5)
    # yaw-only: rotation alone, named
    yaw = registration_recall(rre, None, true)
    assert yaw["rr_kind"] == "rotation-only" and yaw["rr"] == pytest.approx(3 / 5)
    assert yaw["rr_rte_m_mean"] is None
    # no estimate at all: n/a, not 0
    none = registration_recall(None, None, true)
    assert none["rr"] is None and none["rr_kind"] is None
    # no true match: undefined
    assert registration_recall(rre, rte, np.zeros(6, bool))["rr"] is None


def test_loop_pose_settings_validation():
    with pytest.raises(LirisError, match="choose from"):
        LoopPoseSettings(refine="ndt")
    with pytest.raises(LirisError, match="needs --refine"):
        LoopPoseSettings(min_inlier_ratio=0.3)
    with pytest.raises(LirisError, match=r"\[0, 1\]"):
        LoopPoseSettings(refine="gicp", min_inlier_ratio=1.5)
    with pytest.raises(LirisError, match="> 0"):
        LoopPoseSettings(rr_rte_m=0.0)
    s = LoopPoseSettings(refine="icp", min_inlier_ratio=0.4, max_rmse_m=0.3)
    assert s.registration.method == "icp"
    assert s.acceptance_rule() == "inlier_ratio >= 0.4 and rmse_m <= 0.3"


def test_relative_pose_convention_of_registration(sim):
    """T_target_source maps the match (source) into the query (target): inv(P_i) @ P_j."""
    i, j = 8, 6
    gt = relative_ground_truth(sim.poses, np.array([i]), np.array([j]))[0]
    assert np.allclose(gt, invert_pose(sim.poses[i]) @ sim.poses[j])
    r = register_points(sim[i], sim[j], np.eye(4))
    assert translation_error_m(r.pose[None], gt[None])[0] < 0.05


def _pairs_with_repeats():
    """Loops reusing scans (scan 0 matched by three queries, scan 5 as query and match)."""
    q = np.array([5, 7, 9, 11, 10, 8])
    m = np.array([0, 0, 0, 5, 5, -1])
    return q, m


def test_parallel_refinement_equals_fresh_per_pair_registration(sim):
    """Prepared once and shared, in one process or two: every pose is the pose of a fresh
    registration of that pair alone (single-threaded small_gicp is deterministic)."""
    from lidar_iris_eval.executor import ProcessExecutor, SerialExecutor

    q, m = _pairs_with_repeats()
    gt = relative_ground_truth(sim.poses, q, np.maximum(m, 0))
    start = np.stack([yaw_pose(float(yaw_deg_of(g))) for g in gt])
    fresh = [register_points(sim[qi], sim[mi], s) if mi >= 0 else None
             for qi, mi, s in zip(q, m, start, strict=True)]
    ticks = []
    serial = refine_pairs(sim, q, m, start, executor=SerialExecutor(), progress=ticks.append)
    parallel = refine_pairs(sim, q, m, start, executor=ProcessExecutor(workers=2))
    assert sum(ticks) == len(q)
    for r in (serial, parallel):
        assert np.isnan(r.pose[5]).all() and not r.registered[5]
        for k, f in enumerate(fresh):
            if f is not None:
                assert np.array_equal(r.pose[k], f.pose), k
                assert r.inlier_ratio[k] == f.inlier_ratio and r.rmse_m[k] == f.rmse_m
    assert np.array_equal(serial.pose, parallel.pose, equal_nan=True)


def test_two_passes_prepare_each_scan_once(sim):
    """Refinement and ground-truth passes in one call: each of the 6 distinct scans once,
    even with room for 3 prepared scans (an LRU of 3 would prepare scan 5 twice)."""
    from lidar_iris_eval.matching.registration import ScanCache, refine_many

    q, m = _pairs_with_repeats()
    settings = RegistrationSettings()
    cache = ScanCache(sim, settings, size=3)
    gt = relative_ground_truth(sim.poses, q, np.maximum(m, 0))
    one, two = refine_many(sim, [(q, m, None), (q, m, gt)], settings, cache=cache)
    assert cache.n_prepared == len(set(q[m >= 0]) | set(m[m >= 0]))
    assert one.registered.sum() == two.registered.sum() == 5
    assert len(cache._items) == 0  # every scan let go after its last loop


def test_pool_stops_at_once_when_the_consumer_stops():
    """A pool left early (an error, Ctrl-C) kills its running tasks instead of waiting."""
    import time

    from lidar_iris_eval.executor import ProcessExecutor

    results = ProcessExecutor(workers=2).imap(time.sleep, [(0.0,), (30.0,), (30.0,)])
    next(results)
    started = time.perf_counter()
    results.close()
    assert time.perf_counter() - started < 5.0


def test_ctrl_c_during_parallel_registration_is_one_line_and_stops_the_workers(tmp_path):
    """SIGINT while two workers register: exit 130, one line, no worker left behind."""
    import subprocess

    from test_faults_mech import assert_interrupted, interrupt

    from lidar_iris_eval.simulate import simulate_sequence

    simulate_sequence(tmp_path / "seq", preset="tiny-mixed", azimuth_steps=512)
    code, err = interrupt(["eval", tmp_path / "seq", "-d", "scan-context", "--protocol", "1",
                           "--refine", "gicp", "--gt-pose", "refined", "--workers", "2",
                           "--out", "O"], tmp_path, "registration")
    assert_interrupted(code, err)
    assert not (tmp_path / "O").exists()
    left = subprocess.run(["pgrep", "-f", str(tmp_path / "seq")], capture_output=True, text=True)
    assert left.stdout.split() == [], left.stdout


def test_methods_share_registrations_and_prepared_scans(sim):
    """Two methods' loops in one call: equal (pair, start) rows registered once, each scan
    prepared once for both, results those of each method alone."""
    from types import SimpleNamespace

    from lidar_iris_eval.evaluation.loop_poses import LoopPoseSettings, refine_loops_many
    from lidar_iris_eval.matching.registration import ScanCache

    q, m = _pairs_with_repeats()
    matches = SimpleNamespace(query=q, match=m, distance=np.zeros(len(q)))
    no_pose = SimpleNamespace(matches=matches, pose=None, is_true=m >= 0)  # M2DP-like
    other = SimpleNamespace(matches=matches, pose=None, is_true=m >= 0)  # ESF-like
    settings = LoopPoseSettings(refine="gicp")
    cache = ScanCache(sim, settings.registration)
    calls = []
    import lidar_iris_eval.matching.registration as reg

    real = reg.register

    def counting(*args):
        calls.append(1)
        return real(*args)

    reg.register = counting
    try:
        both = refine_loops_many([no_pose, other, None], sim, settings, cache=cache)
        n_both = len(calls)
        alone = refine_loops_many([no_pose], sim, settings)[0]
    finally:
        reg.register = real
    assert both[2] is None
    assert n_both == 5 and cache.n_prepared == 6
    for loops in both[:2]:
        assert np.array_equal(loops.refined.pose, alone.refined.pose, equal_nan=True)
