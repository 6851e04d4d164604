"""Filesystem faults and unreadable input end as one line, exit 2, nothing half-written.

Read-only folders are real: ``chmod`` for a normal user, a read-only tmpfs
mount when the tests run as root (root ignores permission bits but not
``EROFS``). A full disk is a tiny tmpfs when it can be mounted, and a mocked
``ENOSPC`` always.
"""

from __future__ import annotations

import errno
import os
import subprocess
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_protocols import two_pass_sequence

from lidar_iris_eval.cache import read_arrays
from lidar_iris_eval.descriptors import _REGISTRY


@pytest.fixture(autouse=True)
def toys(monkeypatch):
    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")


@pytest.fixture
def seq_dir(tmp_path):
    return two_pass_sequence(tmp_path / "seq", n_per_pass=12)


def _mount_tmpfs(folder: Path, options: str) -> bool:
    if os.geteuid() != 0:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                          capture_output=True)
    return done.returncode == 0


@contextmanager
def read_only(folder: Path):
    """``folder`` made unwritable for this process, or the test is skipped."""
    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield folder
        finally:
            folder.chmod(0o755)
        return
    if not _mount_tmpfs(folder, "ro,size=64k"):
        pytest.skip("running as root and cannot mount a read-only tmpfs")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@contextmanager
def tiny_disk(folder: Path, size: str = "24k"):
    folder.mkdir(parents=True, exist_ok=True)
    if not _mount_tmpfs(folder, f"size={size}"):
        pytest.skip("cannot mount a small tmpfs")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@contextmanager
def inside(folder: Path):
    """Work in ``folder``, and leave it again before it is unmounted."""
    old = os.getcwd()
    os.chdir(folder)
    try:
        yield folder
    finally:
        os.chdir(old)


def eval_args(seq, *extra):
    return ["eval", seq, "--protocol", "1", "--protocol", "2", "-d", "toy", "--exclude", "5",
            "-q", *extra]


def files_under(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file())


def test_read_only_cwd_default_cache(seq_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("LIRIS_CACHE_DIR", raising=False)
    with read_only(tmp_path / "ro") as ro, inside(ro):
        code, _, err = run_cli(eval_args(seq_dir, "--out", tmp_path / "run"), capsys)
        assert_one_line_error(code, err, ".liris-cache", "cannot write")
        assert not list(ro.iterdir())
    assert not (tmp_path / "run").exists()


def test_read_only_cwd_default_run_folder(seq_dir, tmp_path, capsys):
    with read_only(tmp_path / "ro") as ro, inside(ro):
        code, _, err = run_cli(eval_args(seq_dir, "--cache-dir", tmp_path / "c"), capsys)
        assert_one_line_error(code, err, "results/", "cannot write the run folder")
    assert not (tmp_path / "c").exists()  # refused before any extraction


@pytest.mark.parametrize("which", ["out", "cache"])
def test_read_only_output_or_cache_folder(seq_dir, tmp_path, capsys, which):
    ro_path = tmp_path / "ro"
    with read_only(ro_path) as ro:
        out = ro / "run" if which == "out" else tmp_path / "run"
        cache = ro / "cache" if which == "cache" else tmp_path / "cache"
        code, _, err = run_cli(eval_args(seq_dir, "--out", out, "--cache-dir", cache), capsys)
        assert_one_line_error(code, err, str(out if which == "out" else cache), "cannot write")
        assert not list(ro.iterdir())
    assert not (tmp_path / "run").exists() and not (tmp_path / "cache").exists()


def test_out_under_a_file(seq_dir, tmp_path, capsys):
    (tmp_path / "note.txt").write_text("mine")
    code, _, err = run_cli(eval_args(seq_dir, "--out", tmp_path / "note.txt" / "run",
                                     "--cache-dir", tmp_path / "c"), capsys)
    assert_one_line_error(code, err, "note.txt is a file")
    assert (tmp_path / "note.txt").read_text() == "mine"
    assert not (tmp_path / "c").exists()


def test_mocked_enospc_names_the_file_and_leaves_no_temporary(seq_dir, tmp_path, capsys,
                                                              monkeypatch):
    def full(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    code, _, err = run_cli(eval_args(seq_dir, "--out", tmp_path / "run",
                                     "--cache-dir", tmp_path / "cache"), capsys)
    assert_one_line_error(code, err, str(tmp_path / "cache"), "no space left")
    assert not [p for p in files_under(tmp_path / "cache") if ".tmp-" in p.name]
    assert not (tmp_path / "run").exists()
    assert not list(tmp_path.glob(".run.tmp-*"))


def test_full_tmpfs_run_folder(seq_dir, tmp_path, capsys):
    with tiny_disk(tmp_path / "disk", "8k") as disk:
        code, _, err = run_cli(eval_args(seq_dir, "--out", disk / "run",
                                         "--cache-dir", tmp_path / "cache"), capsys)
        assert_one_line_error(code, err, str(disk / "run"), "no space left")
        assert not list(disk.iterdir())


def test_full_tmpfs_cache_leaves_nothing(seq_dir, tmp_path, capsys):
    with tiny_disk(tmp_path / "disk", "8k") as disk:
        code, _, err = run_cli(eval_args(seq_dir, "--out", tmp_path / "run",
                                         "--cache-dir", disk / "cache"), capsys)
        assert_one_line_error(code, err, str(disk / "cache"), "no space left")
        left = [p for p in disk.rglob("*") if p.is_file()]
        assert not [p for p in left if ".tmp-" in p.name]  # no half-written file
        for chunk in left:  # only finished chunks, complete and verified, to resume from
            read_arrays(chunk)
        assert not [p for p in disk.rglob("*.partial") if not any(p.iterdir())]
    assert not (tmp_path / "run").exists()


def test_random_bytes_bag(tmp_path, capsys):
    pytest.importorskip("rosbags")
    bag = tmp_path / "noise.bag"
    bag.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    code, _, err = run_cli(["eval", bag, "--protocol", "1", "-d", "toy", "-q",
                            "--out", tmp_path / "run"], capsys)
    assert_one_line_error(code, err, str(bag), "not a readable ROS bag")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("content, kind", [
    ("1 0 0 0 0 1 0 0 0 0 1 0\n".encode("utf-16"), "UTF-16"),
    (bytes(range(256)), "binary"),
    (b"1 0 0 0 \xe9 1 0 0 0 0 1 0\n", "not UTF-8"),
])
def test_undecodable_pose_file(seq_dir, tmp_path, capsys, content, kind):
    poses = tmp_path / "poses.bin"
    poses.write_bytes(content)
    code, _, err = run_cli(eval_args(seq_dir, "--poses", poses, "--out", tmp_path / "run"),
                           capsys)
    assert_one_line_error(code, err, str(poses), kind)
    code, _, err = run_cli(["gt", "--poses", poses], capsys)
    assert_one_line_error(code, err, str(poses), kind)


def test_bench_json_folder_fails_before_the_benchmark(tmp_path, capsys, monkeypatch):
    from lidar_iris_eval.cli import bench_cmd

    def never(*args, **kwargs):
        raise AssertionError("the benchmark ran before the output path was checked")

    monkeypatch.setattr(bench_cmd, "simulated_sequence", never)
    monkeypatch.setattr(bench_cmd, "run_benchmark", never)
    (tmp_path / "out").mkdir()
    code, _, err = run_cli(["bench", "--frames", "10", "-d", "m2dp", "--json-out",
                            tmp_path / "out", "--work-dir", tmp_path / "w", "-q"], capsys)
    assert_one_line_error(code, err, f"--json-out {tmp_path / 'out'}", "is a folder")
    (tmp_path / "f").write_text("x")
    code, _, err = run_cli(["bench", "-d", "m2dp", "--json-out", tmp_path / "f" / "r.json",
                            "--work-dir", tmp_path / "w", "-q"], capsys)
    assert_one_line_error(code, err, "is a file")
    assert not (tmp_path / "w").exists()


def test_messages_name_flags_not_python(seq_dir, tmp_path, capsys):
    code, _, err = run_cli(eval_args(seq_dir, "--pose-topic", "/p", "--topic", "/x"), capsys)
    assert_one_line_error(code, err, "--pose-topic, --topic")
    assert "[" not in err and "'" not in err
    folder = tmp_path / "plain"
    folder.mkdir()
    for i in range(3):
        np.zeros((5, 4), np.float32).tofile(folder / f"{i:06d}.bin")
    np.savetxt(folder / "poses.txt", np.tile(np.eye(4)[:3].ravel(), (3, 1)))
    code, _, err = run_cli(["eval", folder, "--protocol", "1", "-d", "toy", "-q"], capsys)
    assert_one_line_error(code, err, "--lidar-frame-poses", "--calib")
    assert "lidar_frame" not in err


def test_library_messages_name_keywords():
    from lidar_iris_eval.errors import _FLAGS, option, options

    saved = dict(_FLAGS)
    _FLAGS.clear()
    try:
        assert option("lidar_frame", True) == "lidar_frame=True"
        assert options(["every", "topic"]) == "every, topic"
    finally:
        _FLAGS.update(saved)
