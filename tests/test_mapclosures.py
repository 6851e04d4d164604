"""MapClosures (the optional extra): local-map rule, pose convention, E, native mode.

Skipped without ``map_closures`` (a base install); CI runs it in a second venv
with the extra (.ci/run). The worlds are synthetic: a ground grid and boxes,
no occlusion, so every expectation below comes from the poses alone.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("map_closures")

from lidar_iris_eval.descriptors import get_descriptor  # noqa: E402
from lidar_iris_eval.descriptors.mapclosures import (  # noqa: E402
    LocalMapSettings,
    MapClosuresParams,
    run_closures,
)
from lidar_iris_eval.descriptors.mapclosures.localmap import frame_local_map  # noqa: E402
from lidar_iris_eval.descriptors.mapclosures.native import (  # noqa: E402
    NativeSettings,
    evaluate_native,
    overlap,
    pr_by_inliers,
)
from lidar_iris_eval.errors import LirisError  # noqa: E402


def box_world(seed: int = 0, half: float = 45.0, n_boxes: int = 70) -> np.ndarray:
    """A ground grid (0.5 m) and axis-aligned box walls of random size and height."""
    rng = np.random.default_rng(seed)
    g = np.mgrid[-half:half:0.5, -half:half:0.5].reshape(2, -1).T
    parts = [np.c_[g, np.zeros(len(g))]]
    t = np.arange(0.0, 1.0, 0.04)
    for _ in range(n_boxes):
        (cx, cy), (w, h), top = rng.uniform(-half, half, 2), rng.uniform(0.5, 6, 2), \
            rng.uniform(1, 5)
        z = np.arange(0.0, top, 0.3)
        tt, zz = np.meshgrid(t, z)
        tt, zz = tt.ravel(), zz.ravel()
        for x, y in ((cx + w * tt, cy + 0 * tt), (cx + w * tt, cy + h + 0 * tt),
                     (cx + 0 * tt, cy + h * tt), (cx + w + 0 * tt, cy + h * tt)):
            parts.append(np.c_[x, y, zz])
    return np.vstack(parts)


def planar_pose(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def scan_of(world: np.ndarray, pose: np.ndarray, reach: float = 30.0) -> np.ndarray:
    pts = (world - pose[:3, 3]) @ pose[:3, :3]
    return pts[np.linalg.norm(pts[:, :2], axis=1) < reach].astype(np.float32)


@pytest.fixture(scope="module")
def revisit():
    """8 frames east along y = 0, then 6 frames back west, turned by pi + 0.3."""
    world = box_world()
    poses = np.array([planar_pose(-20 + 4 * k, 0, 0) for k in range(8)]
                     + [planar_pose(8 - 4 * k, 1.5, np.pi + 0.3) for k in range(6)])
    feats = [{"points": scan_of(world, T)} for T in poses]
    return world, poses, feats


def _rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


# ------------------------------------------------------------------ local maps
def test_local_map_holds_exactly_the_window_frames_within_the_radius():
    # one point per frame, 10 m ahead of it: frame j's point sits at x = 10 j + 10
    poses = np.array([planar_pose(10.0 * j, 0, 0) for j in range(8)])
    scans = [np.array([[10.0, 0.2, 0.3]]) for _ in range(8)]
    lm = frame_local_map(scans, poses, 6, LocalMapSettings(window=3, radius=50.0))
    # frames 4, 5, 6 in frame 6: x = 10 (j - 6) + 10
    np.testing.assert_allclose(np.sort(lm[:, 0]), [-10.0, 0.0, 10.0], atol=1e-9)
    lm = frame_local_map(scans, poses, 6, LocalMapSettings(window=3, radius=5.0))
    np.testing.assert_allclose(lm[:, 0], [0.0], atol=1e-9)  # only frame 5's point is in 5 m
    lm = frame_local_map(scans, poses, 1, LocalMapSettings(window=3, radius=50.0))
    assert len(lm) == 2  # frames 0 and 1 only: nothing before the sequence starts


# ------------------------------------------------------------------ closures
def test_closure_pose_maps_the_candidate_frame_into_the_query_frame(revisit):
    _, poses, feats = revisit
    table = run_closures(feats, poses, MapClosuresParams(window=1), progress=False)
    assert len(table.query) > 0 and np.all(table.ref < table.query - 3)
    strong = table.inliers >= 10
    assert strong.sum() >= 3
    errs = []
    for q, r, T in zip(table.query[strong], table.ref[strong], table.pose[strong], strict=True):
        truth = np.linalg.inv(poses[q]) @ poses[r]
        d = np.linalg.inv(truth) @ T
        errs.append((np.linalg.norm(d[:3, 3]), _rot_deg(d[:3, :3])))
    errs = np.array(errs)
    # the reverse pass is turned by ~180 deg: the inverse pose would be metres off
    assert np.median(errs[:, 0]) < 1.0 and np.median(errs[:, 1]) < 2.0


def test_protocol1_only_matches_frames_outside_the_window(revisit):
    _, poses, feats = revisit
    desc = get_descriptor("mapclosures", window=2)
    desc.bind_poses(poses)
    db = desc.prepare(feats)
    assert desc.prepare(feats) is db  # protocols 1 and 2 read one run
    for i in range(4, len(poses)):
        for exclude in (2, 5):
            cand, dist = desc.retrieve(db, i, i - exclude + 1, 100)
            assert np.all(cand <= i - exclude)
            assert np.all(np.diff(dist) >= 0)  # most inliers first
            ver = desc.verify(db, i, cand)
            np.testing.assert_array_equal(ver.score, dist)
            assert np.all(ver.inliers == -dist)
    with pytest.raises(LirisError, match="mapclosures.window"):
        desc.retrieve(db, 10, 10, 5)  # E = 1 < window = 2


def test_protocol2_pairs_come_from_either_direction(revisit):
    _, poses, feats = revisit
    desc = get_descriptor("mapclosures", window=1)
    desc.bind_poses(poses)
    db = desc.prepare(feats)
    r, q = int(db.ref[0]), int(db.query[0])
    back, _ = desc.retrieve(db, r, len(poses), 100)
    assert q in back  # r never queried q (q is later), but q verified r
    ver = desc.verify(db, r, np.array([q]))
    np.testing.assert_allclose(ver.pose[0] @ db.pose[0], np.eye(4), atol=1e-9)


def test_prepare_without_poses_is_an_error(revisit):
    desc = get_descriptor("mapclosures")
    with pytest.raises(LirisError, match="poses"):
        desc.prepare(revisit[2])


# ------------------------------------------------------------------ native mode
def test_overlap_and_pr_rows_by_hand():
    assert overlap({(0, 0, 0), (1, 0, 0)}, {(1, 0, 0), (2, 0, 0), (3, 0, 0)}) == 0.5
    assert overlap(set(), {(0, 0, 0)}) == 0.0
    closures = np.array([[0, 5, 9], [1, 6, 4], [0, 7, 3]])
    rows = pr_by_inliers(closures, {(0, 5), (1, 6), (2, 8)})
    by_t = {r["inliers_threshold"]: r for r in rows}
    assert (by_t[3]["tp"], by_t[3]["fp"], by_t[3]["fn"]) == (2, 1, 1)
    assert (by_t[5]["tp"], by_t[5]["fp"], by_t[5]["fn"]) == (1, 0, 2)
    assert by_t[9]["precision"] == 1.0 and by_t[9]["recall"] == pytest.approx(1 / 3)
    assert max(by_t) == 9
    assert pr_by_inliers(np.empty((0, 3), np.int64), set())[0]["precision"] is None


def test_native_mode_finds_the_revisit_between_distance_split_maps():
    world = box_world()
    # 2 m steps out and back along y = 0; a map closes 15 m from its first pose
    out = [planar_pose(-30 + 2 * k, 0, 0) for k in range(30)]
    back = [planar_pose(28 - 2 * k, 1.0, np.pi) for k in range(30)]
    poses = np.array(out + back)
    scans = [scan_of(world, T) for T in poses]
    res = evaluate_native(scans, poses, settings=NativeSettings(map_range=15.0, max_range=30.0))
    # a map closes at the first pose > 15 m away: every 8 scans (16 m); the turn adds one
    assert 5 <= res["n_maps"] <= 7
    ranges = np.asarray(res["scan_ranges"])
    assert ranges[0, 0] == 0 and ranges[-1, 1] == len(poses)
    assert np.all(ranges[1:, 0] == ranges[:-1, 1] - 1)  # next map starts at the closing scan
    pairs = {tuple(p) for p in res["ground_truth"]["pairs"]}
    assert {(0, 4), (0, 5)} <= pairs  # the first map's ground, driven back over
    assert all(b - a > 3 for a, b in pairs)
    assert res["f1_max"] is not None and res["f1_max"] > 0
    # a closure's pose maps the reference map's frame into the query map's (the inverse
    # would be tens of metres off); 0.5 m pixels bound the accuracy
    assert res["median_rte_m"] < 1.5 and res["median_rre_deg"] < 3.0


# ------------------------------------------------------------------ end to end
def test_liris_eval_records_the_local_maps_and_respects_e(tmp_path, capsys, revisit):
    import json

    from conftest import run_cli, write_kitti_sequence

    _, poses, feats = revisit
    # KITTI layout with Tr = identity: camera poses are the LiDAR poses
    scans = [np.c_[f["points"], np.zeros(len(f["points"]))] for f in feats]
    seq = write_kitti_sequence(tmp_path / "seq", scans, poses)
    code, _, err = run_cli(["eval", seq, "-d", "mapclosures", "--protocol", "1", "--protocol",
                            "2", "--exclude", "4", "--param", "mapclosures.window=4",
                            "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run",
                            "--quiet"], capsys)
    assert code == 0, err
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    rows = [r for r in metrics["results"] if r["descriptor"] == "mapclosures"]
    assert {r["protocol"] for r in rows} == {1, 2}
    for r in rows:
        assert (r["local_map_window"], r["local_map_radius_m"], r["local_map_voxel_m"],
                r["local_map_odometry"]) == (4, 50.0, 0.5, "gt")
        assert r["map_closures_version"] == "2.2.0"
        # the timing and sizes describe the run's maps, not the pipeline's 2-frame warm-up
        assert r["local_maps"] == len(feats) and r["local_map_points_median"] > 0
    import pandas as pd

    m = pd.read_csv(tmp_path / "run" / "protocol1" / "mapclosures" / "matches.csv")
    hit = m[m["match"] >= 0]
    assert len(hit) > 0 and (hit["match"] <= hit["query"] - 4).all()
    assert (hit["inliers"] > 2).all() and hit["T03"].notna().all()
    code, _, err = run_cli(["eval", seq, "-d", "mapclosures", "--protocol", "1",
                            "--exclude", "3", "--param", "mapclosures.window=4",
                            "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run2",
                            "--quiet"], capsys)
    assert code == 2 and "mapclosures.window" in err and "Traceback" not in err


def test_native_mode_with_kiss_icp_odometry_splits_maps_as_the_true_poses_do():
    # KISS-ICP locks onto a regular 0.5 m ground grid (it stays at the origin): scatter it
    world = box_world()
    rng = np.random.default_rng(3)
    ground = rng.uniform(-45, 45, (30000, 2))
    world = np.vstack([world[world[:, 2] > 0.01], np.c_[ground, np.zeros(len(ground))]])
    poses = np.array([planar_pose(-30 + 2 * k, 0, 0) for k in range(30)])  # no turn: ICP
    scans = [scan_of(world, T) for T in poses]
    runs = {odo: evaluate_native(scans, poses, settings=NativeSettings(
        map_range=15.0, max_range=30.0, odometry=odo)) for odo in ("gt", "kiss-icp")}
    assert runs["kiss-icp"]["odometry"] == "kiss-icp"
    gt_ranges = np.asarray(runs["gt"]["scan_ranges"])
    kiss_ranges = np.asarray(runs["kiss-icp"]["scan_ranges"])
    # a map closes every 8 scans (16 m > 15 m); odometry may lag a scan at a boundary
    assert len(gt_ranges) == len(kiss_ranges) == 4
    assert np.abs(kiss_ranges - gt_ranges).max() <= 1
    with pytest.raises(LirisError, match="odometry"):
        NativeSettings(odometry="imu")


# ------------------------------------------------------------------ fast paths
def test_window_points_equal_the_matrix_route(revisit):
    """The compiled transform-and-crop against ``pts @ R.T + t`` and a norm test."""
    from lidar_iris_eval.descriptors.mapclosures.localmap import window_points

    _, poses, feats = revisit
    scans = [f["points"] for f in feats]
    settings = LocalMapSettings(window=4, radius=20.0)
    for i in (0, 5, 11):
        parts = []
        for j in range(max(0, i - 3), i + 1):
            T = np.linalg.inv(poses[i]) @ poses[j]
            p = np.asarray(scans[j], np.float64) @ T[:3, :3].T + T[:3, 3]
            parts.append(p[np.hypot(p[:, 0], p[:, 1]) <= 20.0])
        expected = np.vstack(parts)
        got = window_points(scans, poses, i, settings)
        assert got.shape == expected.shape and len(got) > 1000
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
