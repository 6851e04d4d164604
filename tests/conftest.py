"""Shared fixtures: the optional ../shared folder and tiny on-disk sequences."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
KITTI = SHARED / "data" / "kitti"


@pytest.fixture
def kitti_dir() -> Path:
    """The real KITTI material in ../shared, or skip."""
    if not KITTI.is_dir():
        pytest.skip("../shared/data/kitti is not available")
    return KITTI


def write_kitti_sequence(
    root: Path, scans: list[np.ndarray], poses: np.ndarray, tr: np.ndarray | None = None
) -> Path:
    """Write scans (N×4 float32) and camera poses in KITTI layout under ``root``."""
    velodyne = root / "velodyne"
    velodyne.mkdir(parents=True)
    for i, scan in enumerate(scans):
        np.asarray(scan, dtype=np.float32).tofile(velodyne / f"{i:06d}.bin")
    rows = poses[:, :3, :4].reshape(len(poses), 12)
    np.savetxt(root / "poses.txt", rows, fmt="%.9e")
    tr = np.eye(4) if tr is None else tr
    (root / "calib.txt").write_text("Tr: " + " ".join(f"{v:.12e}" for v in tr[:3].ravel()) + "\n")
    np.savetxt(root / "times.txt", np.arange(len(scans)) * 0.1, fmt="%.6f")
    return root


def run_cli(args, capsys) -> tuple[int, str, str]:
    """Run ``liris`` in-process; return (exit code, stdout, stderr)."""
    from lidar_iris_eval.cli import main

    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as exit_:
        code = exit_.code
    out = capsys.readouterr()
    return code, out.out, out.err


def assert_one_line_error(code: int, err: str, *fragments: str) -> None:
    """Exit code 2, exactly one line on stderr, no traceback, naming each fragment."""
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


def kill_extract_mid_run(sequence: Path, name: str, target: str, cache_dir: Path,
                         chunk_size: int, script_dir: Path, timeout: float = 60.0) -> int:
    """Run ``liris extract`` with descriptor ``target`` (registered as ``name``) in a child
    process, SIGKILL it once two chunks are stored, and return how many chunks were stored.

    Asserts the child was still running when killed and left no final cache file, so a
    resumed run must really resume.
    """
    tests = Path(__file__).resolve().parent
    script = script_dir / "run_extract.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(tests)!r})
        from lidar_iris_eval.descriptors import register_descriptor
        register_descriptor({name!r}, {target!r})
        from lidar_iris_eval.cli import main
        main(["extract", {str(sequence)!r}, "--descriptor", {name!r}, "--cache-dir",
              {str(cache_dir)!r}, "--chunk-size", {str(chunk_size)!r}, "--quiet"])
    """))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if len(list(cache_dir.glob("*.partial/chunk-*.npz"))) >= 2:
            break
        time.sleep(0.02)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert list(cache_dir.glob("*.npz")) == []  # no final cache file
    return len(list(cache_dir.glob("*.partial/chunk-*.npz")))
