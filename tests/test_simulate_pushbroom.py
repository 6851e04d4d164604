"""Push-broom line scanner: swathes placed with the poses lie on the simulated surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.pushbroom import LMS151, PushBroomMount, line_poses, swathes
from lidar_iris_eval.simulate.raycast import CYLINDER

SIGMA = LMS151.range_noise


@pytest.fixture(scope="module")
def forest():
    return build_scenario(resolve_config("forest", {"frames": 40}))


@pytest.fixture(scope="module")
def noisy(forest):
    return swathes(forest, swathe_length=6.0, line_spacing=0.1, seed=7)


def _world(swathe, poses=None):
    """Swathe points in the world frame, placed with the swathe's reference pose."""
    ref = swathe.pose if poses is None else poses
    return swathe.points.astype(np.float64) @ ref[:3, :3].T + ref[:3, 3]


def _ground_residual(forest, swathe, world):
    g = swathe.row < 0
    return world[g, 2] - forest.world.ground.surface_height(world[g, 0], world[g, 1])


def _trunk_residual(forest, swathe, world):
    p = forest.world.prims
    rows = swathe.row
    hit = rows >= 0
    trunk = np.zeros(len(rows), bool)
    trunk[hit] = p.kind[rows[hit]] == CYLINDER
    r = rows[trunk]
    rel = world[trunk] - p.center[r]
    side = np.abs(rel[:, 2]) < p.size[r, 2] - 0.05  # not on a cap
    return (np.hypot(rel[:, 0], rel[:, 1]) - p.size[r, 0])[side]


def test_swathes_cover_the_trajectory_in_stretches_of_the_named_length(forest, noisy):
    travelled = np.linalg.norm(np.diff(forest.poses[:, :3, 3], axis=0), axis=1).sum()
    assert len(noisy) == int(travelled // 6.0)
    for s in noisy:
        steps = np.linalg.norm(np.diff(s.line_poses[:, :3, 3], axis=0), axis=1)
        np.testing.assert_allclose(steps, 0.1, atol=0.01)
        assert 5.8 <= steps.sum() + 0.1 <= 6.05
        np.testing.assert_allclose(s.pose, s.line_poses[-1])


def test_points_overlay_the_ground_and_the_trunks_within_the_noise(forest, noisy):
    ground = np.concatenate([_ground_residual(forest, s, _world(s)) for s in noisy])
    trunks = np.concatenate([_trunk_residual(forest, s, _world(s)) for s in noisy])
    assert len(ground) > 2000 and len(trunks) > 200
    for res in (ground, trunks):
        rms = float(np.sqrt(np.mean(res ** 2)))
        assert 0.3 * SIGMA < rms < 1.15 * SIGMA  # the noise is there, and nothing more
        assert np.abs(res).max() < 6 * SIGMA


def test_noise_free_lines_lie_on_the_surfaces(forest):
    clean = swathes(forest, swathe_length=6.0, line_spacing=0.2, seed=None)
    ground = np.concatenate([_ground_residual(forest, s, _world(s)) for s in clean])
    assert np.abs(ground).max() < 1e-3


def test_lines_placed_with_one_pose_do_not_overlay(forest, noisy):
    """The check can fail: a swathe whose lines all used the reference pose is smeared."""
    s = noisy[0]
    # undo the per-line placement: put every line's points in its own line's platform frame,
    # then place them all with the reference pose
    to_line = [np.linalg.inv(s.line_poses[k]) @ s.pose for k in range(len(s.line_poses))]
    local = np.empty_like(s.points, dtype=np.float64)
    for k, t in enumerate(to_line):
        m = s.line_of == k
        local[m] = s.points[m].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
    smeared = local @ s.pose[:3, :3].T + s.pose[:3, 3]
    res = _trunk_residual(forest, s, smeared)
    assert np.sqrt(np.mean(res ** 2)) > 10 * SIGMA


def test_the_line_is_one_tilted_270_degree_fan():
    dirs = LMS151.grid.directions
    assert len(dirs) == 720 and np.allclose(dirs[:, 2], 0.0)  # one line in the line frame
    m = PushBroomMount(tilt_deg=20.0).transform()
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(m[:3, :3]), 1.0)
    axis = m[:3, 2]  # the rotation axis: forward, 20 deg up
    assert np.isclose(np.degrees(np.arctan2(axis[2], axis[0])), 20.0)
    # the field's two ends point down and forward (the line sweeps the ground ahead)
    ends = [np.radians(a) for a in (-135.0, 135.0)]
    for a in ends:
        d = m[:3, :3] @ np.array([np.cos(a), np.sin(a), 0.0])
        assert d[2] < -0.5 and d[0] > 0


def test_bad_lengths_are_named():
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    with pytest.raises(LirisError, match="line_spacing"):
        line_poses(poses, 0.0)
    q, s = line_poses(poses, 0.5)
    np.testing.assert_allclose(s, [0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_allclose(q[:, 0, 3], s)


def test_simulate_pushbroom_writes_one_swathe_per_frame(tmp_path, capsys):
    from conftest import assert_one_line_error, run_cli

    out = tmp_path / "pb"
    code, text, err = run_cli(["simulate", out, "--world", "forest", "--frames", "40",
                               "--azimuth-steps", "64", "--pushbroom", "6", "-q"], capsys)
    assert code == 0, err
    assert "push-broom swathes of 6 m" in text
    travelled = np.linalg.norm(np.diff(build_scenario(resolve_config(
        "forest", {"frames": 40})).poses[:, :3, 3], axis=0), axis=1).sum()
    scans = sorted((out / "velodyne").glob("*.bin"))
    assert len(scans) == int(travelled // 6.0)
    poses = np.loadtxt(out / "poses.txt").reshape(-1, 3, 4)
    steps = np.linalg.norm(np.diff(poses[:, :, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 6.0, atol=0.15)  # one swathe every 6 m travelled
    code, _, err = run_cli(["simulate", tmp_path / "bad", "--world", "forest", "--pushbroom",
                            "0.5", "-q"], capsys)
    assert_one_line_error(code, err, "--pushbroom")
