"""KITTI layout reading: real scans, pose conversion and input errors."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import write_kitti_sequence

from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_kitti_poses, read_tum_poses
from lidar_iris_eval.io.scans import read_kitti_bin


def test_real_scans_point_counts_match_file_sizes(kitti_dir):
    seq = open_sequence(kitti_dir / "samples" / "00")
    assert len(seq) == 4
    assert list(seq.frame_ids) == [94, 95, 198, 199]
    for i, path in enumerate(seq.scan_paths):
        scan = seq.scan(i)
        assert scan.points.shape == (path.stat().st_size // 16, 3)
        assert scan.points.dtype == np.float32
        assert scan.intensity is not None and scan.intensity.shape == (len(scan.points),)
        # KITTI HDL-64E scans hold roughly 120k points
        assert 100_000 < len(scan.points) < 130_000


def test_real_lidar_poses_follow_inv_tr_t_tr(kitti_dir):
    seq = open_sequence(kitti_dir / "samples" / "00")
    tr = read_calib(kitti_dir / "calib" / "00.txt")
    cam = read_kitti_poses(kitti_dir / "samples" / "00" / "poses.txt")
    np.testing.assert_allclose(seq.poses, np.linalg.inv(tr) @ cam @ tr)
    # The LiDAR frame has z up: frames 94 -> 95 (0.47 m apart) move in x-y, not z.
    step = seq.poses[1, :3, 3] - seq.poses[0, :3, 3]
    assert 0.3 < np.linalg.norm(step[:2]) < 1.5
    assert abs(step[2]) < 0.1 * np.linalg.norm(step[:2])


def test_camera_to_lidar_round_trip_hand_case():
    # Tr swaps axes: lidar x -> camera z, lidar y -> -camera x, lidar z -> -camera y.
    tr = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0.5], [0, 0, 0, 1]], dtype=float)
    cam = np.eye(4)[None].repeat(2, axis=0)
    cam[1, :3, 3] = [0, 0, 10]  # 10 m forward along camera z
    lidar = camera_to_lidar(cam, tr)
    np.testing.assert_allclose(lidar[1, :3, 3], [10, 0, 0], atol=1e-12)


def test_tum_reader_quaternion_convention(tmp_path):
    path = tmp_path / "traj.tum"
    # 90 degrees about z: q = (0, 0, sin45, cos45)
    s = np.sqrt(0.5)
    path.write_text(f"0.0 1 2 3 0 0 {s} {s}\n0.1 0 0 0 0 0 0 1\n")
    times, poses = read_tum_poses(path)
    np.testing.assert_allclose(times, [0.0, 0.1])
    np.testing.assert_allclose(poses[0, :3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(poses[0, :3, 3], [1, 2, 3])


def _tiny(tmp_path, n=3):
    scans = [np.random.default_rng(i).normal(size=(50, 4)) for i in range(n)]
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n)
    return write_kitti_sequence(tmp_path / "seq", scans, poses)


def test_sequence_opens_lazily_and_fingerprint_tracks_content(tmp_path):
    root = _tiny(tmp_path)
    seq = open_sequence(root)
    first = seq.fingerprint()
    assert open_sequence(root).fingerprint() == first
    data = np.fromfile(root / "velodyne" / "000001.bin", dtype=np.float32)
    data[0] += 1.0
    data.tofile(root / "velodyne" / "000001.bin")
    assert open_sequence(root).fingerprint() != first


def test_truncated_bin_is_an_error_naming_the_file(tmp_path):
    root = _tiny(tmp_path)
    path = root / "velodyne" / "000001.bin"
    path.write_bytes(path.read_bytes()[:-3])
    seq = open_sequence(root)
    with pytest.raises(LirisError, match=r"000001\.bin.*not a multiple of 16"):
        seq.scan(1)


def test_nan_points_are_dropped_with_a_counting_warning(tmp_path):
    path = tmp_path / "scan.bin"
    data = np.ones((10, 4), dtype=np.float32)
    data[2, 0] = np.nan
    data[7, 2] = np.inf
    data.tofile(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scan = read_kitti_bin(path)
    assert scan.points.shape == (8, 3)
    messages = [str(w.message) for w in caught if issubclass(w.category, LirisWarning)]
    assert any("dropped 2 of 10 points" in m and "scan.bin" in m for m in messages)


def test_empty_scan_is_an_error(tmp_path):
    path = tmp_path / "empty.bin"
    path.write_bytes(b"")
    with pytest.raises(LirisError, match="empty.bin: empty scan"):
        read_kitti_bin(path)


def test_count_mismatch_names_both_files(tmp_path):
    root = _tiny(tmp_path)
    (root / "velodyne" / "000002.bin").unlink()
    with pytest.raises(LirisError, match=r"poses\.txt: 3 poses but 2 scans"):
        open_sequence(root)


def test_malformed_pose_line_names_the_line(tmp_path):
    root = _tiny(tmp_path)
    lines = (root / "poses.txt").read_text().splitlines()
    lines[1] = "1 0 0 0 0 1 0 0 0 0 1"  # 11 numbers
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(LirisError, match=r"poses\.txt:2: malformed KITTI pose line: 11 numbers"):
        open_sequence(root)


def test_poses_beside_sequences_folder_are_found(tmp_path):
    root = _tiny(tmp_path)
    dataset = tmp_path / "dataset"
    (dataset / "sequences").mkdir(parents=True)
    (dataset / "poses").mkdir()
    target = dataset / "sequences" / "07"
    root.rename(target)
    (target / "poses.txt").rename(dataset / "poses" / "07.txt")
    seq = open_sequence(target)
    assert len(seq) == 3 and seq.name == "07"


def test_opening_4541_scans_reads_none_of_them(tmp_path):
    """Opening only lists files: every scan here is truncated, yet opening succeeds."""
    root = tmp_path / "big"
    (root / "velodyne").mkdir(parents=True)
    for i in range(4541):
        (root / "velodyne" / f"{i:06d}.bin").write_bytes(b"\0" * 7)  # not a multiple of 16
    poses = np.tile(np.eye(4)[:3].ravel(), (4541, 1))
    np.savetxt(root / "poses.txt", poses, fmt="%.1f")
    (root / "calib.txt").write_text("Tr: " + " ".join(["1", "0", "0", "0", "0", "1", "0", "0",
                                                       "0", "0", "1", "0"]) + "\n")
    seq = open_sequence(root)
    assert len(seq) == 4541 and seq.poses.shape == (4541, 4, 4)
    with pytest.raises(LirisError, match="004540.bin"):
        seq.scan(4540)
