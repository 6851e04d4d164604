"""The simulator: output layout, determinism, ground truth, labels, CLI."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import build_scenario, resolve_config, simulate_sequence
from lidar_iris_eval.simulate.ground import REGION_LABEL
from lidar_iris_eval.simulate.raycast import BOX, CYLINDER
from lidar_iris_eval.simulate.sensors import simulate_scan

SHARED = Path(__file__).resolve().parents[2] / "shared"
FAST = dict(azimuth_steps=96)  # coarse scans keep the tests quick


def read_kitti_lines(path: Path) -> np.ndarray:
    data = np.loadtxt(path, ndmin=2)
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :] = data.reshape(-1, 3, 4)
    return poses


def read_tr(path: Path) -> np.ndarray:
    for line in path.read_text().splitlines():
        if line.startswith("Tr:"):
            tr = np.eye(4)
            tr[:3, :] = np.array(line.split()[1:], float).reshape(3, 4)
            return tr
    raise AssertionError("no Tr line")


def yaw_of(poses: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))


def revisit_pairs(pos: np.ndarray, exclude: int = 30, radius: float = 4.0):
    """(query, nearest earlier frame at least ``exclude`` back) for every revisit query."""
    out = []
    for i in range(exclude, len(pos)):
        d = np.linalg.norm(pos[: i - exclude + 1] - pos[i], axis=1)
        j = int(np.argmin(d))
        if d[j] < radius:
            out.append((i, j))
    return np.array(out, dtype=int).reshape(-1, 2)


@pytest.fixture(scope="module")
def reverse_seq(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "rev"
    return simulate_sequence(out, preset="tiny-reverse", **FAST)


def test_kitti_layout(reverse_seq: Path):
    n = 200
    bins = sorted((reverse_seq / "velodyne").glob("*.bin"))
    lbls = sorted((reverse_seq / "labels").glob("*.label"))
    assert [p.name for p in bins] == [f"{i:06d}.bin" for i in range(n)]
    assert [p.stem for p in lbls] == [p.stem for p in bins]
    for b, lab in zip(bins[::50], lbls[::50], strict=True):
        pts = np.fromfile(b, dtype="<f4").reshape(-1, 4)
        assert b.stat().st_size % 16 == 0 and len(pts) > 1000
        assert lab.stat().st_size == 4 * len(pts)
        assert (pts[:, 3] >= 0).all() and (pts[:, 3] <= 1).all()
    poses = read_kitti_lines(reverse_seq / "poses.txt")
    assert poses.shape == (n, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)
    times = np.loadtxt(reverse_seq / "times.txt")
    np.testing.assert_allclose(np.diff(times), 0.1, atol=1e-9)
    keys = [ln.split(":")[0] for ln in (reverse_seq / "calib.txt").read_text().splitlines()]
    assert keys == ["P0", "P1", "P2", "P3", "Tr"]
    import json

    manifest = json.loads((reverse_seq / "manifest.json").read_text())
    assert manifest["seed"] == 12 and manifest["frames"] == n and "version" in manifest
    assert not list(reverse_seq.rglob(".*tmp*"))


def test_camera_poses_convert_back_to_lidar_trajectory(reverse_seq: Path):
    """poses.txt is in the camera frame: inv(Tr) T_cam Tr must give the LiDAR motion."""
    cfg = resolve_config("tiny-reverse", FAST)
    lidar = build_scenario(cfg).poses
    tr = read_tr(reverse_seq / "calib.txt")
    assert np.abs(tr[:3, :3] - np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]])).max() > 1e-4
    assert np.linalg.norm(tr[:3, 3]) > 0.1  # a real lever arm
    cam = read_kitti_lines(reverse_seq / "poses.txt")
    recovered = np.linalg.inv(tr) @ cam @ tr
    expected = np.linalg.inv(lidar[0]) @ lidar
    np.testing.assert_allclose(recovered, expected, atol=1e-6)
    # camera and LiDAR trajectories differ (lever arm under rotation)
    assert np.abs(cam[:, :3, 3] - expected[:, :3, 3]).max() > 0.1


def test_reader_opens_output(reverse_seq: Path):
    io = pytest.importorskip("lidar_iris_eval.io")
    if not hasattr(io, "open_sequence"):
        pytest.skip("sequence reader not available")
    seq = io.open_sequence(reverse_seq)
    assert len(seq) == 200
    pts = np.fromfile(reverse_seq / "velodyne" / "000007.bin", dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(np.asarray(seq[7]), pts[:, :3])


@pytest.mark.parametrize("route", ["same", "reverse", "mixed"])
def test_routes_have_revisits_in_the_right_direction(route):
    cfg = resolve_config(f"tiny-{route}", FAST)
    poses = build_scenario(cfg).poses
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert 0.4 < np.median(step) < 1.2  # about 1 m per frame at 10 Hz, slower in turns
    pairs = revisit_pairs(poses[:, :3, 3])
    assert len(pairs) >= 40
    yaw = yaw_of(poses)
    diff = np.abs((yaw[pairs[:, 0]] - yaw[pairs[:, 1]] + 180) % 360 - 180)
    opposite = (diff > 150).mean()
    aligned = (diff < 30).mean()
    if route == "same":
        assert aligned > 0.9
    elif route == "reverse":
        assert opposite > 0.6
        assert np.median(diff) > 165
    else:
        assert opposite > 0.2 and aligned > 0.2
    # lateral offsets between passes stay within 0-3 m (pairs at the ends of a revisited
    # stretch are near 4 m apart along the track, or in a turn; hence a percentile)
    delta = poses[pairs[:, 1], :2, 3] - poses[pairs[:, 0], :2, 3]
    left = poses[pairs[:, 0], :2, 1]
    lateral = np.abs((delta * left).sum(1))
    assert np.percentile(lateral, 90) < 3.0


def test_same_seed_gives_identical_bytes(tmp_path):
    a = simulate_sequence(tmp_path / "a", preset="tiny-mixed", frames=6, azimuth_steps=64)
    b = simulate_sequence(tmp_path / "b", preset="tiny-mixed", frames=6, azimuth_steps=64)
    c = simulate_sequence(tmp_path / "c", preset="tiny-mixed", frames=6, azimuth_steps=64, seed=99)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) == 6 * 3 + 4  # velodyne, labels, object_ids per scan; 4 metadata
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    assert (a / "velodyne/000003.bin").read_bytes() != (c / "velodyne/000003.bin").read_bytes()


def _surface_distance(kind, center, size, yaw, p):
    """Independent distance of points p to a primitive's surface (0 on it)."""
    rel = p - center
    if kind == BOX:
        c, s = np.cos(yaw), np.sin(yaw)
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                          rel[:, 2]], 1)
        return np.abs(np.abs(local) - size).min(1) * (np.abs(local) <= size + 1e-3).all(1) + (
            ~(np.abs(local) <= size + 1e-3).all(1)) * 1e3
    if kind == CYLINDER:
        r, hh = size[0], size[2]
        radial = np.hypot(rel[:, 0], rel[:, 1])
        side = np.abs(radial - r) + np.maximum(np.abs(rel[:, 2]) - hh, 0)
        cap = np.abs(np.abs(rel[:, 2]) - hh) + np.maximum(radial - r, 0)
        return np.minimum(side, cap)
    # ellipsoid: |scaled radius - 1| times the smallest radius bounds the distance
    return np.abs(np.linalg.norm(rel / size, axis=1) - 1.0) * size.min()


def test_labels_agree_with_the_surface_hit():
    cfg = resolve_config("tiny-mixed", dict(azimuth_steps=360))
    scen = build_scenario(cfg)
    prims_seen = set()
    for frame in (0, 60, 150):
        prims = scen.primitives(frame)
        pose = scen.poses[frame]
        scan = simulate_scan(scen.sensor, scen.world.ground, prims, pose, rng=None)
        world = scan.points.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        cls = scan.label & 0xFFFF
        on_obj = scan.row >= 0
        for row in np.unique(scan.row[on_obj]):
            sel = scan.row == row
            dist = _surface_distance(prims.kind[row], prims.center[row], prims.size[row],
                                     prims.yaw[row], world[sel])
            assert dist.max() < 1e-3
            assert (cls[sel] == prims.label[row]).all()
            assert ((scan.label[sel] >> 16) == prims.instance[row]).all()
            prims_seen.add(int(prims.label[row]))
        # ground points: on the road surface, or on the raised surface off the road
        g = scen.world.ground
        gp = world[~on_obj]
        z_road = g.elevation(gp[:, 0], gp[:, 1])[0]
        region = g.region_at(gp[:, 0], gp[:, 1])
        flat = (np.abs(gp[:, 2] - z_road) < 1e-3) | (np.abs(gp[:, 2] - z_road - g.curb) < 1e-3)
        assert flat.mean() > 0.97  # the rest are kerb faces, between the two levels
        np.testing.assert_array_equal(cls[~on_obj][flat], REGION_LABEL[region[flat]])
    assert {10, 50, 70, 71, 80} <= prims_seen | {int(c) for c in np.unique(cls)}


def test_vlp16_beams_and_range():
    cfg = resolve_config("tiny-same", dict(sensor="vlp16", azimuth_steps=180))
    scen = build_scenario(cfg)
    scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(10), scen.poses[10],
                         np.random.default_rng(0))
    r = np.linalg.norm(scan.points, axis=1)
    elev = np.degrees(np.arcsin(scan.points[:, 2] / r))
    assert np.abs(elev).max() < 15.5
    assert len(np.unique(np.round(elev))) <= 17
    assert r.max() <= 100.0 + 0.2
    assert scen.poses[10, 2, 3] - scen.world.ground.elevation(
        scen.poses[10, :1, 3], scen.poses[10, 1:2, 3])[0][0] == pytest.approx(2.0, abs=0.01)


def test_moving_cars_appear_and_can_be_disabled():
    cfg = resolve_config("tiny-mixed", dict(azimuth_steps=180))
    scen = build_scenario(cfg)
    labels_seen = set()
    for frame in range(0, 200, 20):
        labels_seen |= set(np.unique(scen.primitives(frame).label).tolist())
    assert 252 in labels_seen
    quiet = build_scenario(dataclasses.replace(cfg, moving_cars=False))
    assert 252 not in set(np.unique(quiet.primitives(40).label).tolist())
    np.testing.assert_array_equal(quiet.poses, scen.poses)  # traffic never moves the ego


def test_refuses_non_empty_dir_and_overwrites_on_request(tmp_path):
    (tmp_path / "keep.txt").write_text("x")
    with pytest.raises(LirisError, match="not empty"):
        simulate_sequence(tmp_path, preset="tiny-same", frames=3, azimuth_steps=32)
    # --overwrite replaces only a simulated sequence, never a folder holding a user's file
    with pytest.raises(LirisError, match="not a sequence liris simulate wrote"):
        simulate_sequence(tmp_path, preset="tiny-same", frames=5, azimuth_steps=32,
                          overwrite=True)
    assert (tmp_path / "keep.txt").read_text() == "x" and len(list(tmp_path.iterdir())) == 1
    (tmp_path / "keep.txt").unlink()
    simulate_sequence(tmp_path, preset="tiny-same", frames=5, azimuth_steps=32)
    simulate_sequence(tmp_path, preset="tiny-same", frames=3, azimuth_steps=32, overwrite=True)
    assert len(list((tmp_path / "velodyne").glob("*.bin"))) == 3  # stale scans removed
    assert len(np.loadtxt(tmp_path / "poses.txt", ndmin=2)) == 3


def test_cli_bad_input_is_one_line_exit_2(tmp_path, capsys):
    from lidar_iris_eval.cli import main

    (tmp_path / "x").write_text("x")
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path), "--frames", "3", "--azimuth-steps", "32", "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not empty" in err[0]
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path / "new"), "--frames", "0"])
    assert exc.value.code == 2


def test_cli_writes_summary(tmp_path, capsys):
    from lidar_iris_eval.cli import main

    main(["simulate", str(tmp_path / "s"), "--preset", "tiny-same", "--frames", "4",
          "--azimuth-steps", "32", "--sensor", "vlp16", "--no-moving-cars", "-q"])
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith("wrote 4 scans (vlp16")


def test_follows_a_kitti_trajectory(tmp_path):
    poses_file = SHARED / "data" / "kitti" / "poses" / "00.txt"
    calib_file = SHARED / "data" / "kitti" / "calib" / "00.txt"
    if not poses_file.is_file():
        pytest.skip("shared KITTI data not available")
    out = simulate_sequence(tmp_path / "k", preset=None, trajectory=str(poses_file),
                            calib=str(calib_file), frames=40, azimuth_steps=64)
    given = read_kitti_lines(poses_file)[:40]
    written = read_kitti_lines(out / "poses.txt")
    # KITTI 00 starts at identity, so re-basing leaves the poses unchanged
    np.testing.assert_allclose(written, given, atol=2e-6)
    np.testing.assert_allclose(read_tr(out / "calib.txt"), read_tr(calib_file), atol=1e-12)
    pts = np.fromfile(out / "velodyne" / "000020.bin", dtype="<f4").reshape(-1, 4)
    assert len(pts) > 1000
    # the sensor sits about 1.73 m above the road it drives on
    road = pts[(np.fromfile(out / "labels" / "000020.label", "<u4") & 0xFFFF) == 40]
    assert np.median(road[:, 2]) == pytest.approx(-1.73, abs=0.15)
