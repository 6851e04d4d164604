"""Shared machines and clusters: permissions, other users' files, killed runs, stale caches."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_protocols import ToyHist, two_pass_sequence

from lidar_iris_eval import cache as cache_module
from lidar_iris_eval.cache import DescriptorCache
from lidar_iris_eval.descriptors import _REGISTRY
from lidar_iris_eval.errors import LirisWarning
from lidar_iris_eval.extract import extract
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.sequence import full_scan_hashing
from lidar_iris_eval.runs.writer import RunWriter, default_run_dir

TESTS = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def toys(monkeypatch):
    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")


@pytest.fixture
def seq_dir(tmp_path):
    return two_pass_sequence(tmp_path / "seq", n_per_pass=6)


@pytest.fixture
def umask_002():
    old = os.umask(0o002)
    yield
    os.umask(old)


# --------------------------------------------------------------------------- umask
def test_cache_files_and_run_folders_follow_the_umask(seq_dir, tmp_path, capsys, umask_002):
    code, _, err = run_cli(["eval", seq_dir, "--protocol", "1", "-d", "toy", "--exclude", "3",
                            "-q", "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run"],
                           capsys)
    assert code == 0, err
    cached = list((tmp_path / "cache").glob("*.npz"))
    assert cached and all(p.stat().st_mode & 0o777 == 0o664 for p in cached)
    assert (tmp_path / "run").stat().st_mode & 0o777 == 0o775
    assert (tmp_path / "run" / "metrics.json").stat().st_mode & 0o777 == 0o664


def test_a_private_umask_stays_private(seq_dir, tmp_path):
    old = os.umask(0o077)
    try:
        extract(open_sequence(seq_dir), ToyHist(), cache=tmp_path / "cache")
        with RunWriter(tmp_path / "run") as run:
            run.write_text("a.txt", "x")
    finally:
        os.umask(old)
    assert all(p.stat().st_mode & 0o777 == 0o600 for p in (tmp_path / "cache").glob("*.npz"))
    assert (tmp_path / "run").stat().st_mode & 0o777 == 0o700


# --------------------------------------------------------------------------- other users' files
def test_unreadable_cache_file_is_reported_kept_and_bypassed(seq_dir, tmp_path, monkeypatch):
    seq = open_sequence(seq_dir)
    cache = DescriptorCache(tmp_path / "cache")
    first = extract(seq, ToyHist(), cache=cache)
    path = first.cache_path
    before = path.read_bytes()
    real = cache_module.read_arrays

    def other_users(p):  # what np.load raises on a file owned by someone else, mode 0600
        if Path(p) == path:
            raise PermissionError(13, "Permission denied", str(p))
        return real(p)

    monkeypatch.setattr(cache_module, "read_arrays", other_users)
    again = DescriptorCache(tmp_path / "cache")
    with pytest.warns(LirisWarning, match="not readable .* leaving it in place"):
        db = extract(seq, ToyHist(), cache=again)
    assert not db.from_cache and db.cache_path is None
    np.testing.assert_array_equal(db.descriptors, first.descriptors)
    assert path.read_bytes() == before  # neither deleted nor replaced


# --------------------------------------------------------------------------- killed runs
class PidSleeper(ToyHist):
    """Records the pid of the process computing it, then works slowly."""

    name = "toy-pid"

    def compute(self, points):
        Path(os.environ["LIRIS_TEST_PID_DIR"], str(os.getpid())).touch()
        time.sleep(0.2)
        return super().compute(points)


def run_pool(seq_dir: str) -> None:
    """Child process of the test below: extraction with two workers."""
    extract(open_sequence(seq_dir), PidSleeper(), workers=2, chunk_size=1)


def _gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return True
    return state in ("Z", "X")  # a zombie computes nothing


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_die_with_a_sigkilled_parent(seq_dir, tmp_path):
    pids = tmp_path / "pids"
    pids.mkdir()
    code = f"import sys; sys.path.insert(0, {str(TESTS)!r}); " \
           f"import test_shared_machines as t; t.run_pool({str(seq_dir)!r})"
    parent = subprocess.Popen([sys.executable, "-c", code],
                              env={**os.environ, "LIRIS_TEST_PID_DIR": str(pids)})
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        workers = {int(p.name) for p in pids.iterdir()} - {parent.pid}
        if len(workers) >= 2:
            break
        time.sleep(0.05)
    else:
        parent.kill()
        pytest.fail("the workers never started")
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and not all(_gone(pid) for pid in workers):
        time.sleep(0.05)
    alive = [pid for pid in workers if not _gone(pid)]
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    assert not alive, f"workers {alive} outlived their parent"


def _dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    return int(done.stdout)


def test_stale_temporary_runs_are_removed_live_ones_kept(tmp_path):
    from lidar_iris_eval.lifetime import HOST as host
    stale = tmp_path / f".old.tmp-{host}-{_dead_pid()}-abc123"
    live = tmp_path / f".busy.tmp-{host}-{os.getpid()}-def456"
    elsewhere = tmp_path / f".far.tmp-otherhost-{_dead_pid()}-ghi789"
    mine = tmp_path / "results-of-mine"
    for folder in (stale, live, elsewhere, mine):
        folder.mkdir()
        (folder / "metrics.json").write_text("{}")
    with RunWriter(tmp_path / "run") as run:
        run.write_text("a.txt", "x")
    assert not stale.exists()
    assert live.exists() and elsewhere.exists() and mine.exists()


def test_stale_cache_temporaries_are_removed(seq_dir, tmp_path):
    from lidar_iris_eval.lifetime import HOST

    cache = tmp_path / "cache"
    cache.mkdir()
    stale = cache / f".x.npz.tmp-{HOST}-{_dead_pid()}-k2j3h4"  # a writer killed mid-write
    live = cache / f".y.npz.tmp-{HOST}-{os.getpid()}-a1b2c3"
    stale.write_bytes(b"PK half")
    live.write_bytes(b"PK busy")
    extract(open_sequence(seq_dir), ToyHist(), cache=cache)
    assert not stale.exists() and live.exists()
    assert not [p for p in cache.iterdir() if ".tmp-" in p.name and p != live]


def test_default_run_names_do_not_collide(tmp_path):
    names = {default_run_dir("seq", tmp_path) for _ in range(50)}
    assert len(names) == 50
    taken = default_run_dir("seq", tmp_path)
    taken.mkdir()
    assert default_run_dir("seq", tmp_path) != taken
    assert "." in taken.name.rsplit("-", 1)[-1]  # sub-second resolution in the name


# --------------------------------------------------------------------------- stale caches
def test_in_place_edit_changes_the_fingerprint(seq_dir):
    scan = sorted((seq_dir / "velodyne").glob("*.bin"))[3]
    np.random.default_rng(3).normal(0, 10, (2000, 4)).astype(np.float32).tofile(scan)
    data = bytearray(scan.read_bytes())
    assert len(data) > 3 * 4096
    seq = open_sequence(seq_dir)
    sampled, full = seq.fingerprint(), None
    with full_scan_hashing():
        full = seq.fingerprint()
    assert full != sampled  # the two modes key the cache apart
    stat = scan.stat()
    data[len(data) // 2] ^= 0xFF  # same size, same first and last 4 KiB
    scan.write_bytes(bytes(data))
    os.utime(scan, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert open_sequence(seq_dir).fingerprint() != sampled  # the modification time
    os.utime(scan, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # an editor that keeps mtime
    assert open_sequence(seq_dir).fingerprint() == sampled  # sampling cannot see it...
    with full_scan_hashing():
        assert open_sequence(seq_dir).fingerprint() != full  # ...--verify-scans does


def test_verify_scans_flag(seq_dir, tmp_path, capsys):
    args = ["extract", seq_dir, "-d", "toy", "-q", "--cache-dir", tmp_path / "c", "--json"]
    assert run_cli(args, capsys)[0] == 0
    code, out, err = run_cli([*args, "--verify-scans"], capsys)
    assert code == 0, err
    assert '"from_cache": false' in out  # verified keys are separate from sampled ones
    assert len(list((tmp_path / "c").glob("*.npz"))) == 2


# --------------------------------------------------------------------------- config boundary
@pytest.mark.parametrize("args, fragment", [
    (["--radius", "nan"], "'nan' is not a finite number"),
    (["--radius", "inf"], "'inf' is not a finite number"),
    (["--param", "toy.bins=2.5"], "bins: must be a whole number"),
    (["--param", "toy.max_range=.nan"], "max_range: must be a finite number"),
    (["--param", "toy.bins=many"], "bins: expected a number"),
])
def test_config_values_are_validated(seq_dir, tmp_path, capsys, args, fragment):
    code, _, err = run_cli(["eval", seq_dir, "--protocol", "1", "-d", "toy", "-q",
                            "--out", tmp_path / "run", *args], capsys)
    assert_one_line_error(code, err, fragment)
    assert not (tmp_path / "run").exists()
