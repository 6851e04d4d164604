"""Frame selection (--frames, --every, --min-distance) the same on every format; TUM for KITTI."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_rosbag import TR, loop_poses, make_clouds, needs_rosbags, write_bag, write_kitti_layout

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.selection import parse_frames
from lidar_iris_eval.io.timematch import select_keyframes


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    root = tmp_path_factory.mktemp("sel")
    n = 60
    return write_kitti_layout(root / "kitti", make_clouds(n, points=40), loop_poses(n)), n


def test_parse_frames():
    assert parse_frames("0:200:2") == slice(0, 200, 2)
    assert parse_frames("10:") == slice(10, None)
    assert parse_frames(":-5") == slice(None, -5)
    for bad in ("5", "a:b", "0:10:0", "1:2:3:4"):
        with pytest.raises(LirisError, match="--frames"):
            parse_frames(bad)


def test_frames_on_kitti_layout_keep_ids_and_poses(kitti):
    path, n = kitti
    full = open_sequence(path)
    seq = open_sequence(path, frames="0:40:2")
    assert len(seq) == 20
    assert seq.frame_ids.tolist() == list(range(0, 40, 2))
    np.testing.assert_array_equal(seq.poses, full.poses[0:40:2])
    np.testing.assert_array_equal(seq.camera_poses, full.camera_poses[0:40:2])
    np.testing.assert_array_equal(seq.times, full.times[0:40:2])
    np.testing.assert_array_equal(seq[3], full[6])
    assert seq.fingerprint() != full.fingerprint()
    assert open_sequence(path, frames="0:40:2").fingerprint() == seq.fingerprint()


def test_every_and_min_distance_on_kitti_layout_follow_the_documented_order(kitti):
    path, n = kitti
    full = open_sequence(path)
    seq = open_sequence(path, frames="5:", min_distance=2.0, every=2)
    expected = np.arange(5, n)[select_keyframes(full.poses[5:, :3, 3], 2, 2.0)]
    assert seq.frame_ids.tolist() == expected.tolist()
    gaps = np.linalg.norm(np.diff(full.poses[expected, :3, 3], axis=0), axis=1)
    assert (gaps >= 2.0).all()


def test_same_selection_on_a_scan_folder(kitti, tmp_path):
    path, n = kitti
    folder = tmp_path / "scans"
    shutil.copytree(path / "velodyne", folder)
    shutil.copy(path / "poses.txt", folder / "poses.txt")
    shutil.copy(path / "calib.txt", folder / "calib.txt")
    a = open_sequence(path, frames="3:50:3", every=2)
    b = open_sequence(folder, frames="3:50:3", every=2)
    assert a.frame_ids.tolist() == b.frame_ids.tolist()
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-9)


@needs_rosbags
def test_same_selection_on_a_bag(kitti, tmp_path):
    path, n = kitti
    clouds = make_clouds(n, points=40)
    bag = write_bag(tmp_path / "rec.bag", "rosbag1", clouds, loop_poses(n),
                    1_600_000_000_000_000_000 + np.arange(n) * 100_000_000 + 5_000)
    a = open_sequence(path, frames="3:50:3", min_distance=1.0)
    b = open_sequence(bag, frames="3:50:3", min_distance=1.0)
    assert a.frame_ids.tolist() == b.frame_ids.tolist()
    np.testing.assert_array_equal(b.scan(2).points, a[2])


def test_tum_pose_file_for_a_kitti_layout(kitti, tmp_path):
    path, n = kitti
    lidar = loop_poses(n)
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(lidar[:, :3, :3]).as_quat()  # x y z w
    rows = np.column_stack([np.arange(n) * 0.1, lidar[:, :3, 3], q])
    tum = tmp_path / "poses.tum"
    np.savetxt(tum, rows, fmt="%.17g")
    seq = open_sequence(path, poses=tum, lidar_frame=True)
    assert seq.name == "kitti" and len(seq) == n
    np.testing.assert_allclose(seq.poses, lidar, atol=1e-9)
    np.testing.assert_allclose(seq.camera_poses, TR @ lidar @ np.linalg.inv(TR), atol=1e-9)
    # a TUM file with times is matched to times.txt even at another rate
    half = rows[::2]
    np.savetxt(tum, half, fmt="%.17g")
    seq = open_sequence(path, poses=tum, lidar_frame=True, tolerance=0.5)
    assert seq.frame_ids[:59].tolist() == list(range(59))
    np.testing.assert_allclose(seq.poses[:59:2, :3, 3], lidar[:59:2, :3, 3], atol=1e-9)


def test_eval_frames_0_200_2_evaluates_100_frames(tmp_path, capsys, monkeypatch):
    from lidar_iris_eval.descriptors import _REGISTRY

    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")
    n = 230
    seq = write_kitti_layout(tmp_path / "seq", make_clouds(n, points=20), loop_poses(n))
    code, out, err = run_cli(["eval", seq, "--frames", "0:200:2", "--protocol", "1", "-d", "toy",
                              "--exclude", "10", "--cache-dir", tmp_path / "c", "--out",
                              tmp_path / "run", "-q", "--json"], capsys)
    assert code == 0, err
    import json

    metrics = json.loads(out)
    assert metrics["sequence"]["n_frames"] == 100
    assert metrics["results"][0]["n_queries"] == 90
    code, _, err = run_cli(["eval", seq, "--frames", "500:600", "--protocol", "1", "-d", "toy",
                            "--out", tmp_path / "r2", "-q"], capsys)
    assert_one_line_error(code, err, "--frames 500:600", "no frame")
