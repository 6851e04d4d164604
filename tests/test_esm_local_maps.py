"""ESM on local maps: target-map lifetimes, localisation, the window binding, the pipeline."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import run_cli

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm import network
from lidar_iris_eval.descriptors.esm.target_map import localise, target_lifetimes
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.matching.geometry import yaw_pose


def test_target_lifetimes_replace_recent_and_keep_old_views():
    world = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [10.0, 0, 0]])
    frame_of = np.array([0, 1, 5, 5])
    alive = target_lifetimes(world, frame_of, 6, dedup=2.0, recent=3)
    inf = np.iinfo(np.int64).max
    # frame 1 is recent to frame 0 (1 > 1 - 3): its segment replaces frame 0's at n = 1
    assert alive[0] == 1
    # frame 5 sees the place again; frame 1 is old (1 <= 5 - 3): the old view stays,
    # the new one never enters; a segment far from all others simply enters
    assert alive[1] == inf and alive[2] == -1 and alive[3] == inf


def test_target_lifetimes_largest_keeps_the_largest_recent_view():
    # one object seen by frames 0..3 (sizes grow, then shrink as its scans leave the
    # window), revisited at frame 9; a second object only at frame 2
    world = np.array([[0.0, 0, 0], [0.3, 0, 0], [0.6, 0, 0], [20.0, 0, 0], [0.9, 0, 0],
                      [0.2, 0, 0]])
    frame_of = np.array([0, 1, 2, 2, 3, 9])
    sizes = np.array([100, 300, 250, 50, 120, 900])
    inf = np.iinfo(np.int64).max
    latest = target_lifetimes(world, frame_of, 10, dedup=2.0, recent=3)
    # latest: each newer view replaces the previous one; the frame-3 view (120 voxels) stays
    assert latest.tolist() == [1, 2, 3, inf, inf, -1]
    largest = target_lifetimes(world, frame_of, 10, dedup=2.0, recent=3, sizes=sizes,
                               keep="largest")
    # largest: 300 replaces 100 at frame 1; 250 (frame 2) and 120 (frame 3) are smaller and
    # never enter; the 300-voxel view stays; at frame 9 it is old (1 <= 9 - 3): a revisit
    # keeps it whatever the new view's size
    assert largest.tolist() == [1, inf, -1, inf, -1, -1]
    with pytest.raises(ValueError):
        target_lifetimes(world, frame_of, 10, dedup=2.0, recent=3, keep="largest")
    with pytest.raises(ValueError):
        target_lifetimes(world, frame_of, 10, dedup=2.0, recent=3, keep="first")
    with pytest.raises(LirisError, match="esm.target_view"):
        get_descriptor("esm", target_view="first")
    assert get_descriptor("esm").params.target_view == "largest"  # the local-maps preset


def _scene(seed=0):
    rng = np.random.default_rng(seed)
    world = rng.uniform(-30, 30, (40, 3)) * [1, 1, 0.1]
    emb = rng.normal(size=(40, 16)).astype(np.float32)
    return world, emb


def test_localise_recovers_the_pose_and_the_nearest_frame():
    world, emb = _scene()
    T = yaw_pose(35.0, (4.0, -2.0, 0.3))  # world -> query
    pick = np.arange(0, 40, 4)  # 10 query segments seen again
    q_cent = world[pick] @ T[:3, :3].T + T[:3, 3]
    q_emb = emb[pick] + 0.01
    positions = np.array([[0.0, 0, 0], [-3.0, 1.0, 0], [50.0, 0, 0]])
    where = np.linalg.inv(T)[:3, 3]
    positions[1] = where + [0.5, 0, 0]
    loc = localise(q_emb, np.ones(10), q_cent, emb, np.ones(40), world, np.arange(40),
                   positions, knn=5, threshold=0.6, min_consistent=6, iterations=300)
    assert loc.inliers == 10
    np.testing.assert_allclose(loc.world_to_query, T, atol=1e-9)
    assert loc.frame == 1
    # the same match with the nearest frame 4 m + away from the estimate is rejected
    positions[1] = where + [4.5, 0, 0]
    far = localise(q_emb, np.ones(10), q_cent, emb, np.ones(40), world, np.arange(40),
                   positions, knn=5, threshold=0.6, min_consistent=6, iterations=300)
    assert far.frame == -1


def test_localise_rejects_fewer_than_min_consistent():
    world, emb = _scene(1)
    T = yaw_pose(-20.0, (1.0, 2.0, 0.0))
    pick = np.arange(5)  # only 5 true pairs: below SegMap's 6
    q_cent = world[pick] @ T[:3, :3].T + T[:3, 3]
    loc = localise(emb[pick], np.ones(5), q_cent, emb, np.ones(40), world, np.arange(40),
                   np.zeros((1, 3)), knn=3, threshold=0.6, min_consistent=6, iterations=300)
    assert loc.frame == -1 and loc.inliers < 6


def test_window_is_bound_to_the_exclusion_window():
    esm = get_descriptor("esm")
    assert esm.local_map and esm.preset == "local-maps" and "local_map" in esm.inputs
    assert esm.bind_exclusion(50).params.window == 50
    small = get_descriptor("esm", window=20)
    assert small.bind_exclusion(50).params.window == 20
    with pytest.raises(LirisError, match="esm.window"):
        get_descriptor("esm", window=60).bind_exclusion(50)
    single = get_descriptor("esm", "single-scan")
    assert not single.local_map and "local_map" not in single.inputs


@pytest.mark.skipif(not network.WEIGHTS_FILE.is_file(), reason="no ESM weights shipped")
def test_esm_local_maps_through_liris_eval(tmp_path, capsys):
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    seq = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=80, azimuth_steps=512)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "-d", "esm", "--protocol", "1", "--exclude", "20",
                            "--cache-dir", tmp_path / "cache", "--out", out, "-q"], capsys)
    assert code == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    row = next(r for r in metrics["results"] if r["descriptor"] == "esm")
    assert row["preset"] == "local-maps"
    assert row["odometry"] == "gt" and row["local_map_window"] == 20
    assert row["input_filter"] == "range"  # the front end for real scans (issue 34)
    assert row["describe_rule"] == "growth" and 0.0 < row["embedding_reuse_rate"] < 1.0
    m = pd.read_csv(out / "protocol1" / "esm" / "matches.csv")
    accepted = m[np.isfinite(m["distance"])]
    # every accepted match: >= 6 consistent segments, a proper rotation, a frame <= i - E
    assert (accepted["inliers"] >= 6).all()
    assert (accepted["match"] <= accepted["query"] - 20).all()
    for _, r in accepted.iterrows():
        R = np.array([[r[f"T{i}{j}"] for j in range(3)] for i in range(3)])
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6)


def test_local_maps_under_a_window_in_seconds_is_one_error_line():
    """A seconds window (LoGG3D's convention) gives no frame count for the local map:
    a LirisError naming --exclude, not a TypeError from int(None)."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.errors import LirisError

    esm = get_descriptor("esm")
    with pytest.raises(LirisError, match="--exclude"):
        esm.bind_exclusion(None)
    assert esm.bind_exclusion(30).window == 30
