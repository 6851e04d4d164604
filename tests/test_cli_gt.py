"""``liris gt`` end to end, and the one-line, exit-2 contract for bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli, write_kitti_sequence


def test_help_lists_subcommands(capsys):
    code, out, _ = run_cli(["--help"], capsys)
    assert code == 0
    listed = {line.split()[0] for line in out.split("Commands:")[1].splitlines() if line.strip()}
    assert listed == {"bench", "compare", "datasets", "eval", "extract", "gt", "plot", "report",
                      "segments", "show", "simulate"}


@pytest.mark.parametrize(("exclude", "revisits"), [("300", 791), ("reference", 791), ("30", 816)])
def test_gt_reproduces_kitti00_counts(kitti_dir, capsys, exclude, revisits):
    args = ["gt", "--poses", str(kitti_dir / "poses" / "00.txt"), "--radius", "4",
            "--exclude", exclude, "--json"]
    code, out, _ = run_cli(args, capsys)
    assert code == 0
    data = json.loads(out)
    assert data["frames"] == 4541
    assert data["positive_ordered_pairs"] == 68_420
    assert data["negative_ordered_pairs"] == 20_547_720
    assert data["revisit_queries"] == revisits


def test_gt_lidar_frame_needs_calib_and_changes_little(kitti_dir, capsys):
    poses = str(kitti_dir / "poses" / "00.txt")
    code, _, err = run_cli(["gt", "--poses", poses, "--pose-frame", "lidar"], capsys)
    assert_one_line_error(code, err, "--pose-frame lidar", "--calib")
    code, out, _ = run_cli(["gt", "--poses", poses, "--pose-frame", "lidar", "--calib",
                        str(kitti_dir / "calib" / "00.txt"), "--json"], capsys)
    lidar = json.loads(out)["positive_ordered_pairs"]
    # the frames differ by a lever arm of ~0.3 m: a few pairs near 4 m flip, not many
    assert lidar != 68_420 and abs(lidar - 68_420) < 0.05 * 68_420


def test_gt_on_real_scan_folder_reads_scans(kitti_dir, capsys):
    code, out, _ = run_cli(["gt", str(kitti_dir / "samples" / "00"), "--check-scans", "--json"],
                       capsys)
    assert code == 0
    data = json.loads(out)
    sizes = sorted(p.stat().st_size // 16 for p in (kitti_dir / "samples/00/velodyne").iterdir())
    assert data["frames"] == 4 and data["scans_read"] == 4
    assert data["points_min"] == sizes[0] and data["points_max"] == sizes[-1]
    # 94-95 and 198-199 are neighbours; the two places are far apart
    assert data["positive_ordered_pairs"] == 4


@pytest.fixture
def tiny_seq(tmp_path):
    scans = [np.random.default_rng(i).normal(size=(40, 4)) for i in range(4)]
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 2, 3] = np.arange(4) * 2.0
    return write_kitti_sequence(tmp_path / "seq", scans, poses)


def test_error_missing_path(tmp_path, capsys):
    code, _, err = run_cli(["gt", str(tmp_path / "nowhere")], capsys)
    assert_one_line_error(code, err, "nowhere", "no such file or folder")


def test_error_truncated_bin(tiny_seq, capsys):
    path = tiny_seq / "velodyne" / "000002.bin"
    path.write_bytes(path.read_bytes()[:-5])
    code, _, err = run_cli(["gt", str(tiny_seq), "--check-scans"], capsys)
    assert_one_line_error(code, err, "000002.bin", "not a multiple of 16")


def test_error_count_mismatch(tiny_seq, capsys):
    (tiny_seq / "velodyne" / "000003.bin").unlink()
    code, _, err = run_cli(["gt", str(tiny_seq)], capsys)
    assert_one_line_error(code, err, "poses.txt", "4 poses but 3 scans")


def test_nan_points_warn_with_count(tiny_seq, capsys):
    path = tiny_seq / "velodyne" / "000001.bin"
    data = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    data[:3, 1] = np.nan
    data.tofile(path)
    code, out, err = run_cli(["gt", str(tiny_seq), "--check-scans", "--json"], capsys)
    assert code == 0
    assert "000001.bin: dropped 3 of 40 points with NaN or inf" in err
    assert json.loads(out)["points_min"] == 37


def test_error_empty_scan(tiny_seq, capsys):
    (tiny_seq / "velodyne" / "000000.bin").write_bytes(b"")
    code, _, err = run_cli(["gt", str(tiny_seq), "--check-scans"], capsys)
    assert_one_line_error(code, err, "000000.bin", "empty scan")


def test_error_malformed_pose_line(tiny_seq, capsys):
    (tiny_seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 x\n" * 4)
    code, _, err = run_cli(["gt", str(tiny_seq)], capsys)
    assert_one_line_error(code, err, "poses.txt:1", "malformed KITTI pose line")


@pytest.mark.parametrize("args", [["--distance", "sideways"], ["--exclude", "soon"]])
def test_error_unknown_option_value(tiny_seq, capsys, args):
    code, _, err = run_cli(["gt", str(tiny_seq), *args], capsys)
    assert_one_line_error(code, err, args[1])


def test_real_process_prints_one_line_and_exit_2(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "lidar_iris_eval", "gt", "--poses", str(tmp_path / "p.txt")],
        capture_output=True, text=True, check=False,
    )
    assert result.returncode == 2
    expected = f"liris: error: {tmp_path / 'p.txt'}: pose file not found"
    assert result.stderr.strip().splitlines() == [expected]


def test_gt_json_keys_do_not_depend_on_the_options(tmp_path, capsys):
    """Scripts read ``gt --json``; its keys changed with --convention, and the E preset read
    "custom" when the convention had set E (scancontext-eval: 50 frames back)."""
    n = 120
    poses = np.tile(np.eye(4), (n, 1, 1))
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    poses[:, 0, 3], poses[:, 2, 3] = 30 * np.cos(angle), 30 * np.sin(angle)
    path = tmp_path / "poses.txt"
    np.savetxt(path, poses[:, :3, :4].reshape(n, 12))
    outputs = []
    for extra in ([], ["--convention", "scancontext-eval"], ["--exclude", "reference"]):
        code, out, err = run_cli(["gt", "--poses", path, "--json", *extra], capsys)
        assert code == 0, err
        outputs.append(json.loads(out))
    assert {frozenset(o) for o in outputs} == {frozenset(outputs[0])}
    plain, scancontext, reference = outputs
    assert (plain["convention"], plain["queries"], plain["last_frame_query"]) == ("liris", n - 30,
                                                                                  True)
    assert scancontext["exclude_preset"] == "convention scancontext-eval"
    assert scancontext["last_frame_query"] is False
    assert reference["exclude_preset"] == "reference" and reference["queries"] == 0
