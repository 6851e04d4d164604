"""Multi-session simulation: one static world, other days, poses in one frame."""

from __future__ import annotations

import json

import numpy as np
from conftest import assert_one_line_error, run_cli
from scipy.spatial import cKDTree

from lidar_iris_eval.io.poses import read_kitti_poses
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.labels import CAR
from lidar_iris_eval.simulate.sessions import PARKED_SHIFT


def _files(folder):
    return {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_session0_is_the_plain_sequence_and_poses_share_one_frame(tmp_path, capsys):
    code, out, err = run_cli(["simulate", tmp_path / "ms", "--world", "tiny-mixed", "--frames",
                              "30", "--sessions", "2", "--session-sensor", "vlp16", "-q"], capsys)
    assert code == 0, err
    assert "2 sessions" in out
    code, _, err = run_cli(["simulate", tmp_path / "plain", "--world", "tiny-mixed", "--frames",
                            "30", "-q"], capsys)
    assert code == 0, err
    assert _files(tmp_path / "ms" / "session0") == _files(tmp_path / "plain")
    meta = json.loads((tmp_path / "ms" / "sessions.json").read_text())
    assert [s["sensor"] for s in meta["sessions"]] == ["hdl64", "vlp16"]
    manifest = json.loads((tmp_path / "ms" / "session1" / "manifest.json").read_text())
    assert manifest["sensor"]["name"] == "vlp16" and manifest["session"] == 1
    p0 = read_kitti_poses(tmp_path / "ms" / "session0" / "poses.txt")
    p1 = read_kitti_poses(tmp_path / "ms" / "session1" / "poses.txt")
    assert np.allclose(p0[0], np.eye(4), atol=1e-9)
    assert not np.allclose(p1[0], np.eye(4), atol=1e-3)  # not re-based to its own start
    # the same route driven again (at another speed, so the ends differ): the start of
    # session 1 lies on the session-0 drive
    dist, _ = cKDTree(p0[:, :3, 3]).query(p1[:, :3, 3])
    assert dist[:15].max() < 2.0
    assert meta["sessions"][1]["queries_with_positive_in_session0"] == int(np.sum(dist < 4.0))
    # the vlp16 scans are sparser than the hdl64 ones
    n0 = (tmp_path / "ms" / "session0" / "velodyne" / "000005.bin").stat().st_size
    n1 = (tmp_path / "ms" / "session1" / "velodyne" / "000005.bin").stat().st_size
    assert n1 < n0 / 2


def test_later_session_keeps_the_static_world_and_moves_the_parked_cars():
    cfg = resolve_config("tiny-mixed", {"frames": 20})
    a = build_scenario(cfg)
    b = build_scenario(cfg, session=1)
    pa, pb = a.world.prims, b.world.prims
    static_a, static_b = pa.label != CAR, pb.label != CAR
    np.testing.assert_array_equal(pa.center[static_a], pb.center[static_b])
    np.testing.assert_array_equal(pa.size[static_a], pb.size[static_b])
    cars_a = set(np.unique(pa.instance[~static_a]).tolist())
    cars_b = set(np.unique(pb.instance[~static_b]).tolist())
    assert cars_b < cars_a and 0 < len(cars_b) < len(cars_a)  # some gone, some stay
    for inst in cars_b:  # a replacing car stands within PARKED_SHIFT of the old one's place
        ra = np.nonzero(~static_a & (pa.instance == inst))[0][0]
        rb = np.nonzero(~static_b & (pb.instance == inst))[0][0]
        assert np.linalg.norm(pa.center[ra, :2] - pb.center[rb, :2]) <= PARKED_SHIFT + 1e-9
    assert not np.allclose(a.poses, b.poses)  # another drive
    assert b.world.objects.shape == (len(pb),)


def test_same_sensor_session_draws_other_noise():
    cfg = resolve_config("tiny-mixed", {"frames": 5})
    a = build_scenario(cfg, session=1)
    b = build_scenario(cfg, session=2)
    assert not np.allclose(a.poses, b.poses)
    again = build_scenario(cfg, session=1)
    np.testing.assert_array_equal(a.poses, again.poses)  # deterministic


def test_session_options_are_checked(tmp_path, capsys):
    code, _, err = run_cli(["simulate", tmp_path / "x", "--session-sensor", "vlp16"], capsys)
    assert_one_line_error(code, err, "--session-sensor", "--sessions 2")
    code, _, err = run_cli(["simulate", tmp_path / "y", "--sessions", "0"], capsys)
    assert_one_line_error(code, err, "--sessions")
