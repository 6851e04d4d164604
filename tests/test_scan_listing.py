"""Scan listings and the count checks that pair scans with poses and times.

Faults from the issue-40 audit: a scan that is a symbolic-link loop was
dropped without a word (``Path.is_file`` is False for it, so every later scan
shifted against its pose); a count mismatch did not say which scan was
missing; a times file's mismatch was reported as "poses"; and the time-window
check named ``times.txt`` whatever file the user had given.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import run_cli, write_kitti_sequence

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import database_limits
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.datasets.base import list_files
from lidar_iris_eval.io.sequence import first_gap, read_times


def _seq(tmp_path, n=5):
    scans = [np.random.default_rng(i).normal(size=(40, 4)) for i in range(n)]
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n)
    return write_kitti_sequence(tmp_path / "seq", scans, poses)


def test_symlink_loop_scan_is_an_error_naming_it(tmp_path):
    root = _seq(tmp_path)
    loop = root / "velodyne" / "000005.bin"
    loop.symlink_to(loop)
    with pytest.raises(LirisError, match=r"000005\.bin: scan is a broken symbolic link"):
        open_sequence(root)


def test_broken_symlink_in_a_dataset_folder_is_an_error(tmp_path):
    folder = tmp_path / "Ouster"
    folder.mkdir()
    (folder / "100.bin").write_bytes(np.zeros(8, np.float32).tobytes())
    (folder / "200.bin").symlink_to(tmp_path / "gone.bin")
    with pytest.raises(LirisError, match=r"200\.bin: scan is a broken symbolic link"):
        list_files(folder, ".bin", "MulRan Ouster scan")


def test_symlink_loop_through_the_cli_is_one_line(tmp_path, capsys):
    root = _seq(tmp_path)
    loop = root / "velodyne" / "000005.bin"
    loop.symlink_to(loop)
    code, _, err = run_cli(["gt", str(root)], capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2
    assert lines == [f"liris: error: {loop}: scan is a broken symbolic link or a "
                     "symbolic-link loop"]


def test_count_mismatch_names_the_missing_scan(tmp_path):
    root = _seq(tmp_path)
    (root / "velodyne" / "000002.bin").unlink()
    with pytest.raises(LirisError, match=r"5 poses but 4 scans .*no scan numbered 000002"):
        open_sequence(root)


def test_times_mismatch_says_times_not_poses(tmp_path):
    root = _seq(tmp_path)
    np.savetxt(root / "times.txt", np.arange(6) * 0.1)
    with pytest.raises(LirisError, match=r"times\.txt: 6 times but 5 scans"):
        open_sequence(root)


def test_non_finite_time_names_its_line(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("0.0\n0.1\nnan\n0.3\n")
    with pytest.raises(LirisError, match=r"t\.txt: time 3 is nan"):
        read_times(path)


def test_first_gap_keeps_the_padding():
    from pathlib import Path

    names = [Path(f"{i:06d}.bin") for i in (0, 1, 2, 4, 7)]
    assert first_gap(names) == "000003"
    assert first_gap([Path("a.bin"), Path("b.bin")]) is None
    assert first_gap([Path("000000.bin"), Path("000001.bin")]) is None


def test_time_window_error_does_not_invent_a_file_name():
    settings = Settings(exclude_seconds=30.0)
    with pytest.raises(LirisError) as raised:
        database_limits(3, settings, np.array([0.0, 2.0, 1.0]))
    assert "times.txt" not in str(raised.value)
    assert "non-decreasing" in str(raised.value)
