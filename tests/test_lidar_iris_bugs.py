"""Bugs found running LiDAR Iris on real non-KITTI data (issue 15), each pinned by a test.

* a folder named ``velodyne`` with LiDAR-frame poses was forced into KITTI
  layout (``--lidar-frame-poses`` refused);
* ``liris plot`` reopened folder/bag runs without the recorded reader options,
  so the LiDAR Iris figures were skipped;
* the cache key hashed the sequence folder's name, so a copied data set
  missed the cache;
* ``liris gt`` warned about missing camera poses although ``--lidar-frame-poses``
  said the poses are LiDAR poses;
* ``config.yaml`` stored ``lidar_frame`` as the string ``'True'``.
"""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import yaml
from conftest import run_cli

from lidar_iris_eval.cache import DescriptorCache
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.extract import cache_key, extract
from lidar_iris_eval.io import open_sequence


def lidar_pose_folder(root, n=8, step=1.0, yaw_turn=False):
    """``root/velodyne/*.bin`` scans and ``root/poses.txt`` LiDAR poses along x (no calib).

    Poses move ``step`` metres along +x; the scans are random street-like clouds.
    """
    rng = np.random.default_rng(4)
    velodyne = root / "velodyne"
    velodyne.mkdir(parents=True)
    rows = []
    for i in range(n):
        pts = np.c_[rng.uniform(-30, 30, (3000, 2)), rng.uniform(-2, 3, 3000), rng.random(3000)]
        pts.astype(np.float32).tofile(velodyne / f"{i:06d}.bin")
        pose = np.eye(4)
        pose[0, 3] = i * step
        rows.append(pose[:3].ravel())
    np.savetxt(root / "poses.txt", np.array(rows), fmt="%.9e")
    return velodyne


def test_velodyne_folder_accepts_lidar_frame_poses(tmp_path):
    velodyne = lidar_pose_folder(tmp_path / "rec")
    seq = open_sequence(velodyne, poses=tmp_path / "rec" / "poses.txt", lidar_frame=True)
    assert len(seq) == 8 and seq.camera_poses is None
    np.testing.assert_allclose(seq.positions("lidar")[:, 0], np.arange(8.0))


def test_gt_with_lidar_frame_poses_does_not_warn_about_camera_poses(tmp_path, capsys):
    velodyne = lidar_pose_folder(tmp_path / "rec", n=40, step=0.5)
    code, out, err = run_cli(["gt", velodyne, "--poses", tmp_path / "rec" / "poses.txt",
                              "--lidar-frame-poses", "--radius", "1.2", "--exclude", "2",
                              "--distance", "planar", "--json"], capsys)
    assert code == 0, err
    assert "camera poses" not in err
    data = json.loads(out)
    assert data["pose_frame"] == "lidar"
    # 40 poses 0.5 m apart on a line: pairs closer than 1.2 m are 1 or 2 steps apart
    assert data["positive_ordered_pairs"] == 2 * (39 + 38)
    # an explicit --pose-frame camera still says that it fell back
    code, _, err = run_cli(["gt", velodyne, "--poses", tmp_path / "rec" / "poses.txt",
                            "--lidar-frame-poses", "--pose-frame", "camera"], capsys)
    assert code == 0 and "no camera poses" in err


def test_config_records_lidar_frame_as_a_boolean_and_plot_reopens_the_folder(tmp_path, capsys):
    velodyne = lidar_pose_folder(tmp_path / "rec", n=12, step=0.3)
    run = tmp_path / "run"
    code, _, err = run_cli(["eval", velodyne, "--poses", tmp_path / "rec" / "poses.txt",
                            "--lidar-frame-poses", "--protocol", "1", "--exclude", "3",
                            "--descriptor", "lidar-iris", "--cache-dir", tmp_path / "cache",
                            "--out", run, "-q"], capsys)
    assert code == 0, err
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["sequence"]["reader_options"]["lidar_frame"] is True
    code, out, err = run_cli(["plot", run], capsys)
    assert code == 0, err
    written = {p.rsplit("/", 1)[-1] for p in out.split()}
    assert {"iris_frame.png", "iris_alignment.png"} <= written, (written, err)
    assert "figures skipped" not in err


def test_copied_sequence_hits_the_cache(tmp_path):
    velodyne = lidar_pose_folder(tmp_path / "first", n=4)
    copy = tmp_path / "another-name"
    shutil.copytree(tmp_path / "first", copy)  # copy2 keeps sizes, contents and mtimes
    desc = get_descriptor("lidar-iris")
    a = open_sequence(velodyne, poses=tmp_path / "first" / "poses.txt", lidar_frame=True)
    b = open_sequence(copy / "velodyne", poses=copy / "poses.txt", lidar_frame=True)
    assert a.name != b.name or a.path != b.path
    assert cache_key(a, desc).digest() == cache_key(b, desc).digest()
    cache = DescriptorCache(tmp_path / "cache")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        first = extract(a, desc, cache=cache)
        second = extract(b, desc, cache=cache)
    assert not first.from_cache and second.from_cache
    assert first.cache_path == second.cache_path
