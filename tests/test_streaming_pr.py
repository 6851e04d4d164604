"""The streamed protocol 2 curve is exactly the reduced curve of ``pr_curve``."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.evaluation.metrics import pr_curve, reduce_curve, summarize
from lidar_iris_eval.evaluation.streaming_pr import (
    StreamingPR,
    positive_predictions,
    positive_values,
)

FIELDS = ("threshold", "precision", "recall", "tp", "fp", "fn")


def assert_same_curve(got, ref):
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(got, field), getattr(ref, field), err_msg=field)


def streamed(d, correct, denominator, weight, blocks, rng):
    acc = StreamingPR(d[correct], weight)
    negatives = d[~correct]
    cuts = np.sort(rng.integers(0, len(negatives) + 1, blocks - 1))
    for part in np.split(negatives, cuts):
        acc.add_negatives(part)
    return acc


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("weight", [1, 2])
def test_streamed_equals_reduced_exact_curve_with_ties(seed, weight):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 3000))
    decimals = int(rng.integers(1, 4))  # coarse rounding: many ties, also across classes
    d = np.round(rng.random(n) * rng.uniform(0.5, 3), decimals).astype(np.float32)
    d[rng.random(n) < 0.03] = np.nan
    d[rng.random(n) < 0.01] = np.inf
    correct = rng.random(n) < rng.uniform(0.01, 0.5)
    correct[: int(rng.integers(0, 3))] = True  # sometimes a positive ties the smallest value
    denominator = int(correct.sum()) * weight + int(rng.integers(0, 5))
    ref = reduce_curve(pr_curve(d, correct, denominator, weight=weight))
    acc = streamed(d, correct, denominator, weight, int(rng.integers(1, 8)), rng)
    got = acc.curve(denominator)
    assert_same_curve(got, ref)
    assert summarize(got) == summarize(ref)  # the same floats, not just close
    assert acc.n_negatives == int(np.isfinite(d[~correct]).sum())


def test_edge_cases_first_point_and_no_negatives():
    d = np.array([0.1, 0.1, 0.2, 0.5, 0.5, 0.9], dtype=np.float32)
    cases = [
        np.array([False, True, False, True, False, False]),  # first threshold is a tie
        np.array([True, True, True, True, True, True]),  # no negatives
        np.array([False, False, False, False, False, True]),  # positive is the last value
        np.array([True, False, False, False, False, False]),
    ]
    for correct in cases:
        ref = reduce_curve(pr_curve(d, correct, 8))
        acc = StreamingPR(d[correct])
        acc.add_negatives(d[~correct])
        assert_same_curve(acc.curve(8), ref)
    # a hand-computed case: positives 0.2 and 0.5, negatives 0.1, 0.3, 0.5, 0.7
    acc = StreamingPR(np.array([0.2, 0.5]))
    acc.add_negatives(np.array([0.7, 0.1]))
    acc.add_negatives(np.array([0.5, 0.3, np.nan]))
    c = acc.curve(4)
    np.testing.assert_array_equal(c.threshold, [0.1, 0.2, 0.3, 0.5, 0.7])
    np.testing.assert_array_equal(c.tp, [0, 1, 1, 2, 2])
    np.testing.assert_array_equal(c.fp, [1, 1, 2, 3, 4])
    np.testing.assert_array_equal(c.fn, [4, 3, 3, 2, 2])


def test_no_positives_keeps_first_and_last_point():
    d = np.array([0.3, 0.1, 0.2], dtype=np.float32)
    acc = StreamingPR(np.array([]))
    acc.add_negatives(d)
    c = acc.curve(0)
    np.testing.assert_array_equal(c.threshold, np.array([0.1, 0.3], dtype=np.float32))
    np.testing.assert_array_equal(c.fp, [1, 3])
    assert np.isnan(c.recall).all()


def test_merge_equals_one_accumulator():
    rng = np.random.default_rng(4)
    pos = np.round(rng.random(40), 2)
    neg = np.round(rng.random(500), 2)
    whole = StreamingPR(pos, 2)
    whole.add_negatives(neg)
    left, right = StreamingPR(pos, 2), StreamingPR(pos, 2)
    left.add_negatives(neg[:123])
    right.add_negatives(neg[123:])
    left.merge(right)
    assert_same_curve(left.curve(90), whole.curve(90))


class _Toy:
    """Distance |a - b| of scalar descriptors (symmetric)."""

    def pairwise(self, q, db):
        d = np.abs(np.asarray(q)[:, None] - np.asarray(db)[None, :])
        return d, np.full(d.shape, np.nan)


@pytest.mark.parametrize("symmetric", [True, False])
def test_positive_predictions_and_values(symmetric):
    pairs = np.array([[0, 3], [1, 2], [0, 1], [2, 5]])
    pp = positive_predictions(pairs, symmetric)
    if symmetric:
        assert pp.weight == 2
        np.testing.assert_array_equal(pp.row, [1, 2, 3, 5])
        np.testing.assert_array_equal(pp.col, [0, 1, 0, 2])
    else:
        assert pp.weight == 1 and len(pp.row) == 8
        assert set(zip(pp.row.tolist(), pp.col.tolist(), strict=True)) == {
            (0, 3), (3, 0), (1, 2), (2, 1), (0, 1), (1, 0), (2, 5), (5, 2)}
    descs = np.array([0.0, 1.5, 4.0, 7.25, 9.0, 10.0])
    values = positive_values(_Toy(), descs, pp, chunk=2)
    np.testing.assert_array_equal(values, np.abs(descs[pp.row] - descs[pp.col]).astype(np.float32))


class _Asym:
    """A non-symmetric toy distance: |a - b| + 0.01 * (a > b)."""

    name = "asym"
    symmetric = False

    def pairwise(self, q, db):
        q, db = np.asarray(q)[:, None], np.asarray(db)[None, :]
        d = np.abs(q - db) + 0.01 * (q > db)
        return d, np.full(d.shape, np.nan)


@pytest.mark.parametrize("symmetric", [True, False])
def test_streamed_pass_equals_matrix_scoring_and_storage(symmetric, monkeypatch):
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.evaluation import streaming_pr
    from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
    from lidar_iris_eval.evaluation.protocol2 import score_protocol2
    from lidar_iris_eval.matching.blocks import affinity_matrix

    rng = np.random.default_rng(3)
    n = 157
    if symmetric:
        desc = get_descriptor("m2dp")
        descs = np.round(rng.normal(size=(n, 192)), 1)  # coarse: tied distances
    else:
        desc, descs = _Asym(), np.round(rng.random(n) * 5, 2)
    t = np.linspace(0, 4 * np.pi, n)
    positions = np.c_[20 * np.cos(t), np.zeros(n), 20 * np.sin(t)]
    gt = compute_ground_truth(positions, 4.0, 5)
    full, _ = affinity_matrix(desc, descs, None, 2000)
    reference = score_protocol2(full, gt)  # the N x N scoring
    for storage in ("float32", "float16", "decimated", "none"):
        monkeypatch.setattr(streaming_pr, "DECIMATED_SIDE", 40)
        affinity, curve, matches = streaming_pr.stream_protocol2(
            desc, descs, gt.pairs, gt.n_positive_pairs, 5, 2000, None, storage)
        result = score_protocol2(affinity, gt, curve=curve)
        assert_same_curve(result.curve, reduce_curve(reference.curve))
        for key in ("ap", "f1_max", "f1_threshold", "r100p", "ep", "n_positives"):
            assert result.metrics[key] == reference.metrics[key], key
        assert affinity.storage == storage and affinity.passes == 1
        assert len(matches.query) == n - 5
        if storage == "float32":
            np.testing.assert_array_equal(affinity.matrix, full.matrix)
        elif storage == "float16":
            np.testing.assert_array_equal(affinity.matrix, full.matrix.astype(np.float16))
        elif storage == "decimated":
            step = affinity.step
            assert step == 4 and affinity.matrix is None
            np.testing.assert_array_equal(affinity.decimated,
                                          full.matrix[::step, ::step].astype(np.float16))
        else:
            assert affinity.matrix is None and affinity.decimated is None
