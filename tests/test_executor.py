"""The executor is passed down: a block pass gives the same results whichever runs it.

A fake executor that distributes blocks and finishes them in reverse order
stands in for Dask (the real cluster is tests/test_dask_engine.py); the
results must equal the serial pass exactly, under the standard window and
under per-query limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from test_protocols import ToyHist

from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.evaluation.streaming_pr import stream_protocol2
from lidar_iris_eval.executor import SerialExecutor, local_executor, open_executor
from lidar_iris_eval.matching.blocks import best_matches


@dataclass(frozen=True)
class ReversedExecutor(SerialExecutor):
    """Runs block tasks as a cluster would: no warm-up, reductions only, last task first."""

    def run_blocks(self, fn, tasks, shared=(), warm_up=None, threaded=False):
        self.calls.append(len(tasks))
        return ((index, fn(*shared, *tasks[index])) for index in reversed(range(len(tasks))))

    def returns_blocks(self):
        return False

    @property
    def calls(self):
        return _CALLS


_CALLS: list[int] = []


@pytest.fixture
def data():
    rng = np.random.default_rng(11)
    descs = rng.random((90, 12))
    descs[5] = np.nan
    t = np.linspace(0, 4 * np.pi, 90)
    positions = np.stack([10 * np.cos(t), np.zeros(90), 10 * np.sin(t)], 1)
    limits = np.arange(90) - 7
    limits[::9] = -1  # some frames are not queries
    limits = np.where(limits >= 0, limits, -1)
    return descs, positions, limits


@pytest.mark.parametrize("window", ["E", "limits"])
def test_distributed_best_matches_equal_serial(data, window):
    descs, _, limits = data
    w = 7 if window == "E" else limits
    _CALLS.clear()
    ref = best_matches(ToyHist(), descs, w, pair_budget=200)
    got = best_matches(ToyHist(), descs, w, pair_budget=200, executor=ReversedExecutor())
    assert _CALLS and _CALLS[0] > 1  # several blocks went through the executor
    for key in ("query", "match", "distance", "yaw_deg"):
        np.testing.assert_array_equal(getattr(got, key), getattr(ref, key))
    assert got.n_evaluations == ref.n_evaluations


def test_distributed_stream_equals_serial(data):
    descs, positions, limits = data
    gt = compute_ground_truth(positions, 4.0, 1)
    args = (ToyHist(), descs, gt.pairs, gt.n_positive_pairs, limits, 300)
    _, ref_curve, ref = stream_protocol2(*args, storage="none")
    _, curve, got = stream_protocol2(*args, storage="none", executor=ReversedExecutor())
    np.testing.assert_array_equal(curve.precision, ref_curve.precision)
    np.testing.assert_array_equal(curve.recall, ref_curve.recall)
    np.testing.assert_array_equal(got.query, np.flatnonzero(limits >= 0))
    np.testing.assert_array_equal(got.match, ref.match)
    np.testing.assert_array_equal(got.distance, ref.distance)


class _ThreadedHist(ToyHist):
    """ToyHist whose blocks a local executor may run on threads (as Scan Context's)."""

    threaded_blocks = True


def test_threaded_blocks_equal_serial_in_task_order(data):
    descs, positions, limits = data
    gt = compute_ground_truth(positions, 4.0, 1)
    args = (descs, gt.pairs, gt.n_positive_pairs, limits, 300)
    ref_aff, ref_curve, ref = stream_protocol2(ToyHist(), *args, storage="float32")
    for executor in (local_executor(1), local_executor(2), local_executor(3)):
        aff, curve, got = stream_protocol2(_ThreadedHist(), *args, storage="float32",
                                           executor=executor)
        np.testing.assert_array_equal(aff.matrix, ref_aff.matrix)
        np.testing.assert_array_equal(curve.precision, ref_curve.precision)
        np.testing.assert_array_equal(curve.recall, ref_curve.recall)
        for key in ("query", "match", "distance", "yaw_deg"):
            np.testing.assert_array_equal(getattr(got, key), getattr(ref, key))
        assert got.n_evaluations == ref.n_evaluations


def test_thread_map_keeps_task_order_and_bounds_its_lead():
    import threading
    import time

    from lidar_iris_eval.executor import _thread_map

    started: list[int] = []
    lock = threading.Lock()

    def task(i):
        with lock:
            started.append(i)
        time.sleep(0.02 if i % 3 == 0 else 0.0)  # later tasks often finish first
        return i * i

    seen = []
    for index, value in _thread_map(task, [(i,) for i in range(12)], (), 2):
        assert len(started) <= index + 1 + 2 * 2  # never more than 2 x threads ahead
        seen.append((index, value))
    assert seen == [(i, i * i) for i in range(12)]
    with pytest.raises(ZeroDivisionError):
        list(_thread_map(lambda i: 1 // (i - 3), [(i,) for i in range(8)], (), 2))


def test_executors_from_the_options():
    assert local_executor(1).concurrency() == 1 and local_executor(3).concurrency() == 3
    with open_executor("processes", 2) as ex:
        assert ex.returns_blocks() and ex.workers == 2
        assert ex.run_config() == {"scheduler": "processes"}


class _SlowCount:
    """An untimed reducer whose part takes 50 ms: a bookkeeping cost, not matching cost."""

    timed = False

    def __init__(self):
        self.rows = 0

    def part(self, rows, d, y):
        import time

        time.sleep(0.05)
        return len(rows)

    def merge(self, part):
        self.rows += part


def test_untimed_parts_run_here_are_not_matching_time(data):
    from lidar_iris_eval.matching.blocks import BestInRow, block_pass

    descs, _, _ = data
    best, slow = BestInRow(len(descs), 7), _SlowCount()
    blocks = best.blocks(200)  # 200 pairs a block: several blocks
    evaluations, seconds = block_pass(ToyHist(), descs, blocks, [best, slow])
    assert slow.rows == sum(len(rows) for rows, _ in blocks) and len(blocks) >= 4
    assert evaluations == sum(len(rows) * width for rows, width in blocks)
    assert 0 <= seconds < 0.05 * len(blocks) / 2  # the sleeps (>= 0.2 s) are not counted


# --- progress: scan by scan in this process, task by task from a pool -----------------------

def _count_units(n, tick=None):
    """A task of ``n`` units that ticks once per unit when it may (in this process)."""
    for _ in range(n):
        if tick is not None:
            tick(1)
    return 10 * n


@pytest.mark.parametrize("make", [SerialExecutor, lambda: local_executor(2)])
def test_imap_progress_ticks_per_unit_here_and_per_task_from_a_pool(make):
    sizes = [3, 5, 2]
    ticks: list[int] = []
    got = dict(make().imap_progress(_count_units, [(n,) for n in sizes], tick=ticks.append,
                                    sizes=sizes))
    assert got == {0: 30, 1: 50, 2: 20}
    if isinstance(make(), type(local_executor(2))):  # the pool: one tick per finished task
        assert sorted(ticks) == [2, 3, 5]
    else:  # here: one tick per unit, as the task does them
        assert ticks == [1] * 10


class _Bar:
    def __init__(self):
        self.ticks: list[int] = []

    def update(self, k):
        self.ticks.append(k)


@pytest.mark.parametrize("workers", [1, 2])
def test_extraction_bar_moves_scan_by_scan_only_in_this_process(tmp_path, workers):
    from synthetic_loop import loop_sequence

    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.extract import _compute_chunks
    from lidar_iris_eval.io import open_sequence

    seq = open_sequence(loop_sequence(tmp_path / "seq", frames=12))
    bar = _Bar()
    todo = [(0, 5), (5, 12)]
    done = dict(_compute_chunks(seq, [get_descriptor("m2dp")], todo, workers, bar))
    assert sorted(done) == todo
    assert sorted(bar.ticks) == ([1] * 12 if workers == 1 else [5, 7])


# --- a LirisError raised in a worker arrives as the same LirisError ----------------------------

def test_a_liris_error_crosses_dask_as_itself():
    pytest.importorskip("distributed")
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.executor import check_scheduler

    with open_executor("local", 1) as ex:
        assert not ex.returns_blocks() and ex.concurrency() == 1
        assert ex.run_config() == {"scheduler": "local", "workers": 1}
        with pytest.raises(LirisError) as info:
            list(ex.imap(check_scheduler, [("bogus",)]))
    assert type(info.value) is LirisError
    assert info.value.source == "--scheduler bogus"
    assert info.value.problem.startswith("choose processes, local or")


def test_a_local_cluster_leaves_this_process_environment_alone(monkeypatch):
    """The workers get one numba/BLAS thread; this process keeps its own values, during
    the run and after it (distributed's nanny wrote them into os.environ, and numba then
    refused to compile once the value changed back)."""
    pytest.importorskip("distributed")
    import os

    from lidar_iris_eval.executor import ONE_THREAD_ENV

    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    mine = {name: os.environ.get(name) for name in ONE_THREAD_ENV}
    with open_executor("local", 1) as ex:
        assert {name: os.environ.get(name) for name in ONE_THREAD_ENV} == mine
        seen = list(ex.client.run(lambda: os.environ.get("NUMBA_NUM_THREADS")).values())
        assert seen == ["1"]
    assert {name: os.environ.get(name) for name in ONE_THREAD_ENV} == mine


@pytest.mark.parametrize("engine", [["--workers", "2"], ["--scheduler", "local", "--workers", "1"]])
def test_a_bad_scan_in_a_worker_is_one_line_exit_2(tmp_path, capsys, monkeypatch, engine):
    from conftest import run_cli
    from synthetic_loop import loop_sequence

    if "local" in engine:
        pytest.importorskip("distributed")
    monkeypatch.setenv("LIRIS_CACHE_DIR", str(tmp_path / "cache"))
    seq = loop_sequence(tmp_path / "seq")  # 70 scans: chunks [0, 50) and [50, 70)
    (seq / "velodyne" / "000060.bin").write_bytes(b"\0" * 17)  # truncated, in the 2nd chunk
    code, _, err = run_cli(["eval", seq, "-d", "m2dp", "--protocol", "1", "-q",
                            "--out", tmp_path / "run", *engine], capsys)
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("liris: error: "), err[-500:]
    assert "000060.bin" in lines[0] and "Traceback" not in err
