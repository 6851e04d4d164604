"""``liris datasets check`` (issue 38 item 5): each planted fault found, a clean sequence clean.

A tiny simulated sequence is written once; every test copies its files and plants one
fault (a stationary span, a 2 s gap, a 20 m pose jump, poses at half the scan rate, a
duplicate stamp). Expectations come from what was planted, not from the checker.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

FRAMES = 60


@pytest.fixture(scope="module")
def clean_sim(tmp_path_factory):
    from lidar_iris_eval.simulate import simulate_sequence

    root = tmp_path_factory.mktemp("sim") / "clean"
    simulate_sequence(root, "tiny-mixed", frames=FRAMES, azimuth_steps=128)
    for extra in ("labels", "object_ids"):  # the checks read times and poses only
        shutil.rmtree(root / extra, ignore_errors=True)
    return root


def _copy(clean, tmp_path, name="seq"):
    out = tmp_path / name
    shutil.copytree(clean, out)
    return out


def _poses(seq):
    rows = np.loadtxt(seq / "poses.txt")
    mats = np.tile(np.eye(4), (len(rows), 1, 1))
    mats[:, :3, :4] = rows.reshape(-1, 3, 4)
    return mats


def _write_poses(seq, mats):
    np.savetxt(seq / "poses.txt", mats[:, :3, :4].reshape(len(mats), 12), fmt="%.9e")


def _write_times(seq, times):
    np.savetxt(seq / "times.txt", times, fmt="%.6f")


def _check(capsys, *args):
    code, out, err = run_cli(["datasets", "check", *map(str, args), "--json"], capsys)
    assert code == 0, err
    return json.loads(out)


def _found(report):
    return {name for name, count in report["checks"].items() if count}


def test_clean_simulated_sequence_reports_nothing(clean_sim, capsys, tmp_path):
    report = _check(capsys, clean_sim, "--plot", tmp_path / "check.png")
    assert report["clean"] and report["findings"] == [] and _found(report) == set()
    assert report["scans"] == FRAMES and report["scan_rate_hz"] == pytest.approx(10.0)
    assert report["scans_listed"] == FRAMES
    assert (tmp_path / "check.png").read_bytes()[:4] == b"\x89PNG"
    code, out, _ = run_cli(["datasets", "check", clean_sim], capsys)
    assert code == 0 and "clean: no finding" in out


def test_stationary_span_and_its_pseudo_revisits(clean_sim, capsys, tmp_path):
    seq = _copy(clean_sim, tmp_path)
    hold, extra = 20, 30  # the sensor waits 3 s at frame 20
    mats = _poses(seq)
    order = np.r_[np.arange(hold), np.full(extra, hold), np.arange(hold, FRAMES)]
    velodyne = seq / "velodyne"
    scans = sorted(velodyne.iterdir())
    data = [p.read_bytes() for p in scans]
    for p in scans:
        p.unlink()
    for k, src in enumerate(order):
        (velodyne / f"{k:06d}.bin").write_bytes(data[src])
    _write_poses(seq, mats[order])
    _write_times(seq, np.arange(len(order)) * 0.1)
    report = _check(capsys, seq)
    assert _found(report) == {"stationary span", "pseudo-revisit"}
    span = next(f for f in report["findings"] if f["check"] == "stationary span")
    assert span["frames"][0] <= hold and span["frames"][1] >= hold + extra
    assert span["value"] == pytest.approx(extra * 0.1, abs=0.15)
    # frames hold + 30 .. hold + extra sit on frame hold's pose >= 30 frames later
    assert report["pseudo_revisit_queries"] >= 1
    assert report["pseudo_revisit_queries"] == report["revisit_queries_at_exclude"]


def test_two_second_gap(clean_sim, capsys, tmp_path):
    seq = _copy(clean_sim, tmp_path)
    times = np.arange(FRAMES) * 0.1
    times[30:] += 2.0
    _write_times(seq, times)
    report = _check(capsys, seq)
    assert _found(report) == {"scan gap"}
    (gap,) = report["findings"]
    assert gap["frames"] == [29, 30] and gap["value"] == pytest.approx(2.1, abs=1e-6)


def test_twenty_metre_pose_jump(clean_sim, capsys, tmp_path):
    seq = _copy(clean_sim, tmp_path)
    mats = _poses(seq)
    mats[40:, 0, 3] += 20.0  # camera x: 20 m sideways from frame 40 on
    _write_poses(seq, mats)
    report = _check(capsys, seq)
    assert _found(report) == {"speed jump"}
    (jump,) = report["findings"]
    assert jump["frames"] == [39, 40] and jump["value"] > 150.0
    # a slower platform limit is named in the finding, a looser one hides the jump
    assert _found(_check(capsys, seq, "--max-speed", 1000)) == set()


def test_pose_rate_mismatch(clean_sim, capsys, tmp_path):
    from scipy.spatial.transform import Rotation

    from lidar_iris_eval.io import open_sequence

    lidar = open_sequence(clean_sim).poses
    folder = tmp_path / "scans"
    shutil.copytree(clean_sim / "velodyne", folder)
    times = np.arange(FRAMES) * 0.1
    _write_times(folder, times)
    keep = np.arange(0, FRAMES, 2)  # poses at 5 Hz, scans at 10 Hz
    quat = Rotation.from_matrix(lidar[keep, :3, :3]).as_quat()
    rows = np.c_[times[keep], lidar[keep, :3, 3], quat]
    np.savetxt(folder / "poses_tum.txt", rows, fmt="%.9f")
    report = _check(capsys, folder, "--lidar-frame-poses")
    assert "pose rate" in _found(report)
    assert report["pose_rate_hz"] == pytest.approx(5.0) and report["scan_rate_hz"] == \
        pytest.approx(10.0)
    assert report["matched_by"].startswith("time")
    # the same folder with every pose: matched by time, no rate finding
    quat = Rotation.from_matrix(lidar[:, :3, :3]).as_quat()
    rows = np.c_[times[:-1], lidar[:-1, :3, 3], quat[:-1]]  # one pose short: time-matched
    np.savetxt(folder / "poses_tum.txt", rows, fmt="%.9f")
    assert "pose rate" not in _found(_check(capsys, folder, "--lidar-frame-poses"))


def test_duplicate_stamp(clean_sim, capsys, tmp_path):
    seq = _copy(clean_sim, tmp_path)
    times = np.arange(FRAMES) * 0.1
    times[25] = times[24]
    _write_times(seq, times)
    report = _check(capsys, seq)
    assert _found(report) == {"duplicate stamp"}
    assert report["findings"][0]["frames"] == [24, 25]


def test_kitti00_pseudo_revisits_are_the_e30_e50_difference(kitti_dir, capsys):
    cam = np.loadtxt(kitti_dir / "poses" / "00.txt")[:, [3, 7, 11]]

    def brute(exclude):
        out = np.zeros(len(cam), bool)
        for start in range(0, len(cam), 512):
            rows = np.arange(start, min(len(cam), start + 512))
            d = np.linalg.norm(cam[rows, None] - cam[None], axis=2)
            ok = np.arange(len(cam))[None] <= rows[:, None] - exclude
            out[rows] = np.any((d < 4.0) & ok, axis=1)
        return out

    at30, at50 = brute(30), brute(50)
    report = _check(capsys, "--poses", kitti_dir / "poses" / "00.txt", "--rate", 10)
    assert report["revisit_queries_at_exclude"] == int(at30.sum()) == 816
    assert report["pseudo_revisit_queries"] == int((at30 & ~at50).sum()) == 25
    (finding,) = [f for f in report["findings"] if f["check"] == "pseudo-revisit"]
    stop = np.flatnonzero(at30 & ~at50)
    assert finding["frames"] == [int(stop[0]), int(stop[-1])]
    assert _found(report) == {"pseudo-revisit"}  # no jump, gap or stationary span >= 2 s


def test_bad_input_is_one_line(clean_sim, capsys, tmp_path):
    code, _, err = run_cli(["datasets", "check"], capsys)
    assert_one_line_error(code, err, "SEQUENCE")
    code, _, err = run_cli(["datasets", "check", clean_sim, "--rate", "-1"], capsys)
    assert_one_line_error(code, err, "--rate")
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"not liris'")
    code, _, err = run_cli(["datasets", "check", clean_sim, "--plot", mine], capsys)
    assert_one_line_error(code, err, "already exists")
    assert mine.read_bytes() == b"not liris'"


def test_dataset_reader_dropped_scans_are_counted(tmp_path, capsys):
    from dataset_writers import loop_case, write_mulran

    case = loop_case(1)
    seq = write_mulran(tmp_path, case)  # one scan 5 s after the last pose: no pose
    report = _check(capsys, seq)
    assert report["scans"] == len(case.times) and report["scans_listed"] == len(case.times) + 1
    assert "scans without poses" in _found(report)
    dropped = next(f for f in report["findings"] if f["check"] == "scans without poses")
    assert dropped["value"] == 1 and report["matched_by"].startswith("the dataset reader")
    clean = write_mulran(tmp_path / "clean", case, extra_scan=False)
    assert "scans without poses" not in _found(_check(capsys, clean))
