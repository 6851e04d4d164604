"""Scan folders with KITTI or TUM pose files: frames, time matching, keyframes, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.folder import open_folder

# A Velodyne -> camera transform like KITTI's: axes permuted plus an offset.
TR = np.array([[0.0, -1.0, 0.0, 0.02], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27],
               [0.0, 0.0, 0.0, 1.0]])
VELOCITY = np.array([2.0, -1.0, 0.1])  # m/s
YAW_RATE = 0.3  # rad/s about +z


def trajectory(times: np.ndarray) -> np.ndarray:
    """Constant velocity and yaw rate: linear and slerp interpolation are exact on it."""
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(times * YAW_RATE, [0, 0, 1])).as_matrix()
    poses[:, :3, 3] = np.outer(times, VELOCITY)
    return poses


def write_scans(folder: Path, names: list[str], seed: int = 0) -> list[np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    clouds = []
    for name in names:
        data = rng.normal(scale=10, size=(50, 4)).astype(np.float32)
        data.tofile(folder / f"{name}.bin")
        clouds.append(data)
    return clouds


def write_kitti(path: Path, poses: np.ndarray) -> Path:
    np.savetxt(path, poses[:, :3, :4].reshape(len(poses), 12), fmt="%.17g")
    return path


def write_tum(path: Path, times: np.ndarray, poses: np.ndarray) -> Path:
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    np.savetxt(path, np.column_stack([times, poses[:, :3, 3], quat]), fmt="%.17g")
    return path


def write_calib(path: Path) -> Path:
    row = " ".join(f"{v:.17g}" for v in TR[:3].ravel())
    path.write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {row}\n")
    return path


def frame_names(n: int) -> list[str]:
    return [f"{i:06d}" for i in range(n)]


def test_camera_poses_converted_with_calib(tmp_path):
    scans = tmp_path / "scans"
    clouds = write_scans(scans, frame_names(6))
    camera = trajectory(np.arange(6) * 0.1)
    write_kitti(scans / "poses.txt", camera)
    write_calib(scans / "calib.txt")
    seq = open_folder(scans)
    assert len(seq) == 6
    np.testing.assert_allclose(seq.poses, np.linalg.inv(TR) @ camera @ TR, atol=1e-12)
    np.testing.assert_allclose(seq.camera_poses, camera, atol=1e-12)
    np.testing.assert_array_equal(seq[4], clouds[4][:, :3])
    np.testing.assert_array_equal(seq.frame_ids, np.arange(6))


def test_lidar_frame_poses_skip_calib_and_tum_matches_kitti(tmp_path):
    times = np.arange(8) * 0.1
    lidar = trajectory(times)
    a, b = tmp_path / "a", tmp_path / "b"
    write_scans(a, frame_names(8))
    write_scans(b, frame_names(8))
    write_kitti(a / "poses.txt", lidar)
    write_tum(b / "poses_tum.txt", times + 1.6e9, lidar)
    seq_kitti = open_folder(a, lidar_frame=True)
    seq_tum = open_folder(b, lidar_frame=True)
    assert seq_kitti.camera_poses is None and seq_kitti.calib is None
    np.testing.assert_allclose(seq_tum.poses, seq_kitti.poses, atol=1e-12)
    np.testing.assert_allclose(seq_tum.poses, lidar, atol=1e-12)
    # with a calib, LiDAR poses also give camera poses Tr·T·inv(Tr)
    write_calib(b / "calib.txt")
    seq = open_folder(b, lidar_frame=True)
    np.testing.assert_allclose(seq.camera_poses, TR @ lidar @ np.linalg.inv(TR), atol=1e-12)


def test_camera_frame_without_calib_is_a_clear_error(tmp_path):
    write_scans(tmp_path / "s", frame_names(3))
    write_kitti(tmp_path / "s" / "poses.txt", trajectory(np.arange(3.0)))
    with pytest.raises(LirisError, match=r"poses\.txt.*calib.*--lidar-frame-poses"):
        open_folder(tmp_path / "s")


def test_count_mismatch_names_the_files(tmp_path):
    write_scans(tmp_path / "s", frame_names(5))
    write_kitti(tmp_path / "s" / "poses.txt", trajectory(np.arange(4.0)))
    with pytest.raises(LirisError, match=r"poses\.txt.*4 poses but 5 scans"):
        open_folder(tmp_path / "s", lidar_frame=True)
    # TUM poses but no way to time the scans: still a count error, saying why
    write_tum(tmp_path / "s" / "x.tum", np.arange(4.0), trajectory(np.arange(4.0)))
    with pytest.raises(LirisError, match=r"x\.tum.*cannot be timed"):
        open_folder(tmp_path / "s", poses=tmp_path / "s" / "x.tum", lidar_frame=True)


def test_tum_poses_matched_by_time(tmp_path):
    scans = tmp_path / "s"
    write_scans(scans, frame_names(21))
    scan_times = np.arange(21) * 0.1
    np.savetxt(scans / "times.txt", scan_times)
    # 50 Hz odometry, 7 ms off the scan clock, starting only at 0.507 s
    pose_times = 0.507 + np.arange(125) * 0.02
    write_tum(scans / "traj.tum", pose_times, trajectory(pose_times))
    with pytest.warns(LirisWarning, match="dropped 5 of 21 scans"):
        seq = open_folder(scans, lidar_frame=True, tolerance=0.1)
    # scans at t <= 0.4 s are more than 0.1 s before the first pose
    np.testing.assert_array_equal(seq.frame_ids, np.arange(5, 21))
    np.testing.assert_allclose(seq.times, scan_times[5:])
    # t = 0.5 s is 7 ms before the first pose: within tolerance, it takes that
    # pose (no extrapolation); the others are interpolated, exactly on this path
    np.testing.assert_allclose(seq.poses[0], trajectory(pose_times[:1])[0], atol=1e-12)
    np.testing.assert_allclose(seq.poses[1:], trajectory(scan_times[6:]), atol=1e-9)


def test_file_name_stamps_time_the_scans(tmp_path):
    scans = tmp_path / "s"
    stamps_ns = 1_600_000_000_000_000_000 + np.arange(6) * 100_000_000
    names = [str(s) for s in stamps_ns[::-1]]  # written out of order
    write_scans(scans, names)
    stamp_s = 1.6e9 + np.arange(6) * 0.1
    pose_times = 1.6e9 + np.arange(30) * 0.02
    write_tum(tmp_path / "poses_tum.txt", pose_times, trajectory(pose_times - 1.6e9))
    seq = open_folder(scans, lidar_frame=True)  # pose file found in the parent
    assert [p.name for p in seq.scan_paths] == [f"{s}.bin" for s in stamps_ns]
    np.testing.assert_allclose(seq.times, stamp_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(seq.poses, trajectory(np.arange(6) * 0.1), atol=1e-5)


def test_keyframes_every_and_min_distance(tmp_path):
    scans = tmp_path / "s"
    write_scans(scans, frame_names(21))
    poses = np.tile(np.eye(4), (21, 1, 1))
    poses[:, 0, 3] = 0.4 * np.arange(21)  # 0.4 m between scans
    write_kitti(scans / "poses.txt", poses)
    seq = open_folder(scans, lidar_frame=True, min_distance=1.0)
    np.testing.assert_array_equal(seq.frame_ids, [0, 3, 6, 9, 12, 15, 18])
    seq = open_folder(scans, lidar_frame=True, min_distance=1.0, every=2)
    np.testing.assert_array_equal(seq.frame_ids, [0, 6, 12, 18])
    assert [p.name for p in seq.scan_paths] == ["000000.bin", "000006.bin", "000012.bin",
                                                "000018.bin"]
    np.testing.assert_array_equal(seq.poses[:, 0, 3], poses[[0, 6, 12, 18], 0, 3])
    with pytest.raises(LirisError, match="--every 0"):
        open_folder(scans, lidar_frame=True, every=0)


def test_opening_is_lazy(tmp_path):
    # 4541 zero-byte scans: opening must not read them, reading one must fail
    scans = tmp_path / "s"
    scans.mkdir()
    for name in frame_names(4541):
        (scans / f"{name}.bin").touch()
    write_kitti(scans / "poses.txt", np.tile(np.eye(4), (4541, 1, 1)))
    seq = open_folder(scans, lidar_frame=True)
    assert len(seq) == 4541
    with pytest.raises(LirisError, match=r"004540\.bin.*empty"):
        seq.scan(4540)


def test_pose_file_discovery_errors(tmp_path):
    scans = tmp_path / "s"
    write_scans(scans, frame_names(2))
    with pytest.raises(LirisError, match="no pose file.*--poses"):
        open_folder(scans, lidar_frame=True)
    for name in ("a.tum", "b.tum"):
        write_tum(scans / name, np.arange(2.0), trajectory(np.arange(2.0)))
    with pytest.raises(LirisError, match=r"several \*\.tum"):
        open_folder(scans, lidar_frame=True)
    with pytest.raises(LirisError, match="--topic"):
        open_folder(scans, poses=scans / "a.tum", lidar_frame=True, topic="/points")


def test_open_sequence_reads_a_pcd_folder(tmp_path):
    scans = tmp_path / "pcd"
    scans.mkdir()
    for i in range(3):
        rows = "\n".join(f"{i + k} {k} {-k} 0.5" for k in range(4))
        (scans / f"{i:06d}.pcd").write_text(
            "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
            f"WIDTH 4\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n{rows}\n"
        )
    write_kitti(scans / "poses.txt", trajectory(np.arange(3.0)))
    seq = open_sequence(scans, lidar_frame=True)
    np.testing.assert_array_equal(seq[2][:, 0], [2, 3, 4, 5])
    np.testing.assert_array_equal(seq.scan(1).intensity, [0.5] * 4)


# ---------------------------------------------------------------- time matching helpers
def test_select_keyframes_skips_a_long_stop():
    from lidar_iris_eval.io.timematch import select_keyframes

    # parked for 600 frames (longer than the search window), then 1 m per frame
    x = np.concatenate([np.zeros(600), np.arange(1.0, 11.0)])
    positions = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    np.testing.assert_array_equal(select_keyframes(positions, min_distance=0.5),
                                  [0, *range(600, 610)])
    np.testing.assert_array_equal(select_keyframes(positions, min_distance=2.5), [0, 602, 605, 608])
    assert len(select_keyframes(positions[:600], min_distance=0.5)) == 1


def test_stamps_from_names_units():
    from lidar_iris_eval.io.timematch import stamps_from_names

    def names(*stems):
        return [Path(f"{s}.pcd") for s in stems]

    np.testing.assert_allclose(stamps_from_names(names("1600000000123", "1600000000223")),
                               [1600000000.123, 1600000000.223])
    np.testing.assert_allclose(stamps_from_names(names("1600000000.5", "1600000001.25")),
                               [1600000000.5, 1600000001.25])
    assert stamps_from_names(names("000001", "000002")) is None  # frame numbers
    assert stamps_from_names(names("1600000000.5", "scan")) is None


def test_slerp_takes_the_shortest_arc_and_keeps_samples_exact():
    from lidar_iris_eval.io.timematch import interpolate_poses

    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, :3] = Rotation.from_rotvec(np.deg2rad(350) * axis).as_matrix()  # = -10°
    poses[1, :3, 3] = [4.0, 0.0, -2.0]
    out, valid = interpolate_poses(np.array([0.0, 1.0]), poses, np.array([0.0, 0.5, 1.0, 1.3]),
                                   tolerance=0.5)
    np.testing.assert_array_equal(valid, [True, True, True, True])
    half = Rotation.from_rotvec(np.deg2rad(-5) * axis).as_matrix()
    np.testing.assert_allclose(out[1, :3, :3], half, atol=1e-12)
    np.testing.assert_allclose(out[1, :3, 3], [2.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_array_equal(out[[0, 2]], poses)  # on a sample: bit-for-bit
    np.testing.assert_array_equal(out[3], poses[1])  # after the end: held, not extrapolated
    _, valid = interpolate_poses(np.array([0.0, 1.0]), poses, np.array([1.6, -0.2]), 0.5)
    np.testing.assert_array_equal(valid, [False, True])


def test_sequence_options_pass_only_given_values(tmp_path):
    import click
    from click.testing import CliRunner

    from lidar_iris_eval.cli.sequence_options import sequence_options

    seen = {}

    @click.command()
    @click.argument("path")
    @sequence_options
    def cmd(path, reader_options):
        seen.update(reader_options)
        open_sequence(path, **reader_options)

    scans = tmp_path / "s"
    write_scans(scans, frame_names(9))
    poses = np.tile(np.eye(4), (9, 1, 1))
    poses[:, 0, 3] = np.arange(9.0)
    write_kitti(scans / "poses.txt", poses)
    result = CliRunner().invoke(cmd, [str(scans), "--lidar-frame-poses", "--every", "4",
                                      "--pose-format", "kitti"])
    assert result.exit_code == 0, result.output
    assert seen == {"lidar_frame": True, "every": 4, "pose_format": "kitti"}
    result = CliRunner().invoke(cmd, [str(scans), "--topic", "/points"])
    assert isinstance(result.exception, LirisError) and "--topic" in str(result.exception)
