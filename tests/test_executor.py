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

    def run_blocks(self, fn, tasks, shared=(), warm_up=None):
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


def test_executors_from_the_options():
    assert local_executor(1).serial and local_executor(3).workers == 3
    with open_executor("processes", 2) as ex:
        assert not ex.distributes_blocks and ex.workers == 2
