"""The compiled all-pairs distances of M2DP and ESF equal the NumPy broadcast route bit for bit.

``vector_kernels.pair_distances`` replays NumPy's pairwise summation; the
previous route (``pairwise_blocks`` with ``l2_rows`` / ``l1_rows``) is the
reference, on random rows of the real widths (192, 640) and on widths that
exercise every branch of the summation (under 8, one block, several levels).
"""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esf.descriptor import l1_rows
from lidar_iris_eval.descriptors.m2dp.descriptor import l2_rows
from lidar_iris_eval.descriptors.vector_common import pairwise_blocks, vector_rows
from lidar_iris_eval.descriptors.vector_kernels import pair_distances, summation_plan


def _rows(rng, n, width, dtype):
    """Non-negative normalised rows (histogram-like), with a duplicate and a zero row."""
    x = rng.random((n, width)) ** 3 * rng.uniform(1e-3, 1e3, (n, 1))
    x[1] = x[0]
    x[2] = 0.0
    return (x / np.maximum(x.sum(axis=1, keepdims=True), 1e-300)).astype(dtype)


@pytest.mark.parametrize("width", [1, 5, 8, 13, 128, 129, 192, 300, 640, 1000])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_equals_numpy_rows(width, dtype):
    rng = np.random.default_rng(width)
    q, d = _rows(rng, 37, width, dtype), _rows(rng, 53, width, dtype)
    d[:5] = q[:5]  # identical pairs: distance exactly 0
    for metric, rows in (("l2", l2_rows), ("l1", l1_rows),
                         ("l2sq", lambda a, b: vector_rows(a, b, "l2sq"))):
        got = pair_distances(q, d, metric)
        assert np.array_equal(got, pairwise_blocks(rows, q, d)[0]), (metric, width)
        # any block of it is the same values (one pair at a time too)
        assert np.array_equal(pair_distances(q[3:4], d[10:30], metric), got[3:4, 10:30])


def test_serial_and_parallel_launches_equal(monkeypatch):
    from lidar_iris_eval.descriptors import vector_kernels

    rng = np.random.default_rng(3)
    q, d = _rows(rng, 70, 640, np.float32), _rows(rng, 90, 640, np.float32)
    monkeypatch.setattr(vector_kernels, "PARALLEL_MIN_PAIRS", 0)
    par = pair_distances(q, d, "l1")
    monkeypatch.setattr(vector_kernels, "PARALLEL_MIN_PAIRS", 1 << 30)
    assert np.array_equal(par, pair_distances(q, d, "l1"))
    assert np.array_equal(par, pairwise_blocks(l1_rows, q, d)[0])


def test_descriptors_use_it_and_agree_with_distance():
    rng = np.random.default_rng(7)
    for name, width, dtype in (("m2dp", 192, np.float64), ("esf", 640, np.float32)):
        desc = get_descriptor(name)
        x = _rows(rng, 40, width, dtype)
        dist, yaw = desc.pairwise(x, x)
        assert np.isnan(yaw).all()
        for i in (0, 3, 39):
            assert np.array_equal(dist[i], desc.distances(x[i], x)[0])
            assert dist[i, 7] == desc.distance(x[i], x[7])[0]


def test_plan_is_numpy_recursion():
    leaves, program = summation_plan(640)
    assert leaves[:, 1].sum() == 640 and (leaves[:, 1] <= 128).all()
    assert list(leaves[:, 1]) == [80] * 8 and (program == -1).sum() == 7
    assert summation_plan(100)[0].tolist() == [[0, 100]]
