"""PR metrics against tables worked out by hand, and against a slow reference loop.

Hand tables (protocol 1; one row per query: distance, match is true, query is a revisit):

    row  d    true  revisit
    1    0.1  yes   yes
    2    0.2  no    yes      wrong match on a revisit query
    3    0.3  yes   yes
    4    0.4  no    no       a non-revisit query accepted: FP
    5    0.5  yes   yes
    6    0.6  no    no
    7    nan  no    yes      revisit query with no usable match (never accepted)

5 revisit queries (rows 1, 2, 3, 5, 7).

``revisits`` denominator (recall = TP / 5):
    tau   TP FP   P     R
    0.1   1  0    1     0.2
    0.2   1  1    1/2   0.2
    0.3   2  1    2/3   0.4
    0.4   2  2    1/2   0.4
    0.5   3  2    3/5   0.6
    0.6   3  3    1/2   0.6
  AP = 0.2*1 + 0.2*(2/3) + 0.2*(3/5) = 0.453333...
  F1: 1/3, 2/7, 1/2, 4/9, 3/5, 6/11 -> max 3/5 at tau 0.5
  R@100P = 0.2, EP = (1 + 0.2) / 2 = 0.6

``accepted`` denominator (row 2 accepted from tau 0.2 on leaves the denominator: 5 -> 4):
    tau   TP FP den  P     R
    0.1   1  0  5    1     1/5
    0.2   1  1  4    1/2   1/4
    0.3   2  1  4    2/3   1/2
    0.4   2  2  4    1/2   1/2
    0.5   3  2  4    3/5   3/4
    0.6   3  3  4    1/2   3/4
  AP = 0.2*1 + 0.05*(1/2) + 0.25*(2/3) + 0.25*(3/5) = 0.541666...
  F1: 1/3, 1/3, 4/7, 1/2, 2/3, 3/5 -> max 2/3 at tau 0.5
  R@100P = 0.2, EP = 0.6
"""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.evaluation.metrics import pr_curve, reduce_curve, summarize
from lidar_iris_eval.evaluation.protocol1 import score_protocol1
from lidar_iris_eval.evaluation.protocol2 import score_protocol2
from lidar_iris_eval.matching.blocks import Affinity, BestMatches

D = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, np.nan])
TRUE = np.array([1, 0, 1, 0, 1, 0, 0], bool)
REVISIT = np.array([1, 1, 1, 0, 1, 0, 1], bool)

HAND = {
    "revisits": dict(
        precision=[1, 1 / 2, 2 / 3, 1 / 2, 3 / 5, 1 / 2],
        recall=[0.2, 0.2, 0.4, 0.4, 0.6, 0.6],
        ap=0.2 + 0.2 * 2 / 3 + 0.2 * 3 / 5, f1=3 / 5, tau=0.5, r100p=0.2, ep=0.6,
    ),
    "accepted": dict(
        precision=[1, 1 / 2, 2 / 3, 1 / 2, 3 / 5, 1 / 2],
        recall=[1 / 5, 1 / 4, 1 / 2, 1 / 2, 3 / 4, 3 / 4],
        ap=0.2 + 0.05 * 0.5 + 0.25 * 2 / 3 + 0.25 * 3 / 5, f1=2 / 3, tau=0.5, r100p=0.2, ep=0.6,
    ),
}


@pytest.mark.parametrize("denominator", ["revisits", "accepted"])
def test_protocol1_hand_table(denominator):
    discount = (REVISIT & ~TRUE) if denominator == "accepted" else None
    curve = pr_curve(D, TRUE, int(REVISIT.sum()), discount=discount)
    hand = HAND[denominator]
    np.testing.assert_allclose(curve.threshold, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    np.testing.assert_allclose(curve.precision, hand["precision"])
    np.testing.assert_allclose(curve.recall, hand["recall"])
    s = summarize(curve)
    assert s["ap"] == pytest.approx(hand["ap"])
    assert s["f1_max"] == pytest.approx(hand["f1"])
    assert s["f1_threshold"] == pytest.approx(hand["tau"])
    assert s["r100p"] == pytest.approx(hand["r100p"])
    assert s["ep"] == pytest.approx(hand["ep"])


@pytest.mark.parametrize("denominator", ["revisits", "accepted"])
def test_protocol1_scoring_end_to_end_matches_hand_table(denominator):
    """The same table reached through ground truth: frames on a line, 10 m apart."""
    # queries 7..13 (E = 7); query 7+k plays row k+1. Truth is arranged through positions:
    # a true match sits at the query's own place, a wrong one 10 m away.
    n_places = 7
    xs = np.arange(n_places) * 10.0
    revisit_x = np.where(REVISIT, xs, 1000.0 + 10 * np.arange(n_places))  # non-revisits elsewhere
    positions = np.zeros((14, 3))
    positions[:7, 0] = xs
    positions[7:, 0] = revisit_x
    match = np.where(TRUE, np.arange(7), (np.arange(7) + 1) % 7)
    match[6] = -1  # row 7 has no usable match
    matches = BestMatches(query=np.arange(7, 14), match=match,
                          distance=np.where(np.isnan(D), np.inf, D),
                          yaw_deg=np.full(7, np.nan), seconds=0.0, n_evaluations=0,
                          source="hand")
    gt = compute_ground_truth(positions, 4.0, 7, "3d", "camera")
    res = score_protocol1(matches, positions, gt, denominator)
    np.testing.assert_array_equal(res.is_revisit, REVISIT)
    np.testing.assert_array_equal(res.is_true, TRUE)
    assert res.metrics["ap"] == pytest.approx(HAND[denominator]["ap"])
    assert res.metrics["f1_max"] == pytest.approx(HAND[denominator]["f1"])
    assert res.metrics["n_revisits"] == 5 and res.metrics["n_queries"] == 7


def _four_frames():
    """Frames 0,1 together and 2,3 together (positives (0,1), (2,3)), far apart otherwise."""
    return np.array([[0, 0, 0], [1, 0, 0], [50, 0, 0], [51, 0, 0]], float)


def test_protocol2_hand_table_symmetric():
    # unordered: (0,1)=.1 P, (1,2)=.2 N, (2,3)=.25 P, (0,2)=.3 N, (0,3)=.5 N, (1,3)=.6 N
    a = np.full((4, 4), np.nan, np.float32)
    for (i, j), d in {(0, 1): .1, (1, 2): .2, (2, 3): .25, (0, 2): .3, (0, 3): .5,
                      (1, 3): .6}.items():
        a[i, j] = a[j, i] = d
    # ordered counts: tau .1: TP 2 FP 0 (P 1, R .5); .2: 2/2 (.5, .5); .25: 4/2 (2/3, 1)
    # AP = .5*1 + .5*2/3 = 5/6; F1 max = 2*(2/3)/(5/3) = 0.8 at .25; R@100P .5; EP .75
    gt = compute_ground_truth(_four_frames(), 4.0, 1)
    for symmetric in (True, False):
        res = score_protocol2(Affinity(a, 0.0, 0, symmetric), gt)
        s = res.metrics
        assert s["n_positives"] == 4 and s["n_negatives"] == 8 and s["n_pairs"] == 12
        assert s["ap"] == pytest.approx(5 / 6)
        assert s["f1_max"] == pytest.approx(0.8)
        assert s["f1_threshold"] == pytest.approx(0.25)
        assert s["r100p"] == pytest.approx(0.5)
        assert s["ep"] == pytest.approx(0.75)
        np.testing.assert_array_equal(res.curve.tp[:3], [2, 2, 4])
        np.testing.assert_array_equal(res.curve.fp[:3], [0, 2, 2])


def test_protocol2_hand_table_asymmetric():
    # ordered: (0,1)=(1,0)=.1 P P; (3,2)=.15 P; .2 N N; (2,3)=.25 P; .3 N N; .5 N N; .6 N N
    a = np.full((4, 4), np.nan, np.float32)
    for (i, j), d in {(0, 1): .1, (1, 2): .2, (2, 3): .25, (0, 2): .3, (0, 3): .5,
                      (1, 3): .6}.items():
        a[i, j] = a[j, i] = d
    a[3, 2] = 0.15
    # tau .1: 2/0 (1, .5); .15: 3/0 (1, .75); .2: 3/2 (.6, .75); .25: 4/2 (2/3, 1)
    # AP = .5 + .25 + .25*2/3 = 0.91666; F1 max = 2*.75/1.75 = 6/7 at .15; R@100P .75; EP .875
    gt = compute_ground_truth(_four_frames(), 4.0, 1)
    s = score_protocol2(Affinity(a, 0.0, 0, False), gt).metrics
    assert s["ap"] == pytest.approx(0.75 + 0.25 * 2 / 3)
    assert s["f1_max"] == pytest.approx(6 / 7)
    assert s["f1_threshold"] == pytest.approx(0.15)
    assert s["r100p"] == pytest.approx(0.75)
    assert s["ep"] == pytest.approx(0.875)


def test_ties_are_accepted_together():
    # two predictions at the same distance, one right one wrong: no point with P = 1
    curve = pr_curve(np.array([0.3, 0.3, 0.5]), np.array([True, False, True]), 2)
    np.testing.assert_allclose(curve.threshold, [0.3, 0.5])
    np.testing.assert_allclose(curve.precision, [0.5, 2 / 3])
    np.testing.assert_allclose(curve.recall, [0.5, 1.0])
    s = summarize(curve)
    assert s["r100p"] == 0.0
    assert s["ep"] == pytest.approx(0.25)
    assert s["ap"] == pytest.approx(0.5 * 0.5 + 0.5 * 2 / 3)


def test_no_predictions_and_first_prediction_wrong():
    empty = summarize(pr_curve(np.array([np.nan, np.inf]), np.array([True, False]), 1))
    assert empty["ap"] == 0.0 and empty["f1_max"] == 0.0 and empty["r100p"] == 0.0
    wrong_first = summarize(pr_curve(np.array([0.1, 0.2]), np.array([False, True]), 1))
    assert wrong_first["r100p"] == 0.0 and wrong_first["p_at_lowest_recall"] == 0.0
    assert wrong_first["ap"] == pytest.approx(0.5)


def _slow_reference(d, correct, denom, discount):
    """One threshold at a time, straight from the definitions."""
    taus = np.unique(d[np.isfinite(d)])
    rows = []
    for tau in taus:
        acc = d <= tau
        tp = np.sum(acc & correct)
        fp = np.sum(acc & ~correct)
        den = denom - (np.sum(acc & discount) if discount is not None else 0)
        rows.append((tau, tp / (tp + fp), tp / den))
    return np.array(rows)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("accepted", [False, True])
def test_curve_equals_reference_loop_and_reduction_is_lossless(seed, accepted):
    rng = np.random.default_rng(seed)
    n = 300
    d = np.round(rng.random(n), 2)  # many ties
    d[rng.random(n) < 0.05] = np.nan
    correct = rng.random(n) < 0.3
    revisit = correct | (rng.random(n) < 0.3)
    discount = (revisit & ~correct) if accepted else None
    denom = int(revisit.sum()) + 3
    curve = pr_curve(d, correct, denom, discount=discount)
    ref = _slow_reference(d, correct, denom, discount)
    np.testing.assert_allclose(curve.threshold, ref[:, 0])
    np.testing.assert_allclose(curve.precision, ref[:, 1])
    np.testing.assert_allclose(curve.recall, ref[:, 2])
    assert np.all(np.diff(curve.recall) >= 0)  # monotone in both conventions
    reduced = reduce_curve(curve)
    assert len(reduced) <= len(curve)
    assert summarize(reduced) == pytest.approx(summarize(curve), rel=1e-12)


def test_weight_two_equals_ordered_counting():
    rng = np.random.default_rng(9)
    d = rng.random(50)
    correct = rng.random(50) < 0.4
    once = pr_curve(d, correct, 2 * int(correct.sum()), weight=2)
    twice = pr_curve(np.repeat(d, 2), np.repeat(correct, 2), 2 * int(correct.sum()))
    assert summarize(once) == summarize(twice)
    np.testing.assert_array_equal(once.tp, twice.tp)
