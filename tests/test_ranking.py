"""Ranking metrics: hand-computed ranks, ties, undefined values, agreement of the two inputs."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.evaluation.ranking import (
    MAX_N,
    one_percent_n,
    ranking_metrics,
    ranks_from_distances,
    ranks_from_lists,
    within_sequence_valid,
)


def test_hand_computed_ranks_and_metrics():
    inf = np.inf
    d = np.array([
        [0.1, 0.5, 0.3, 0.2, 0.9],   # positive at 2 -> order 0,3,2 -> rank 3
        [0.4, 0.4, 0.4, 0.1, 0.2],   # positive at 1 (tie with 0 and 2): 3,4,0,1 -> rank 4
        [0.7, 0.6, 0.5, 0.4, 0.3],   # no positive: not evaluated
        [inf, 0.2, 0.3, 0.1, 0.6],   # positive at 0 is rejected (inf): never ranked
        [0.3, 0.3, 0.8, 0.8, 0.8],   # positives 1 and 4: first is 1, tie with 0 -> rank 2
    ])
    pos = np.zeros(d.shape, bool)
    pos[0, 2] = pos[1, 1] = pos[3, 0] = pos[4, 1] = pos[4, 4] = True
    r = ranks_from_distances(d, pos)
    assert r.rank.tolist() == [3, 4, 0, 0, 2]
    assert r.has_positive.tolist() == [True, True, False, True, True]
    m = ranking_metrics(r)
    assert m["n_ranking_queries"] == 4
    assert m["recall_at_1"] == 0.0
    assert m["recall_at_n"][:5] == [0.0, 0.25, 0.5, 0.75, 0.75]
    assert m["recall_at_n"][-1] == 0.75  # the rejected positive is never found
    assert len(m["recall_at_n"]) == MAX_N
    assert m["mrr"] == pytest.approx((1 / 3 + 1 / 4 + 0 + 1 / 2) / 4)
    assert m["mrr_top25_found"] == pytest.approx((1 / 3 + 1 / 4 + 1 / 2) / 3)
    assert m["recall_1pct_n"] == 1  # D = 5
    assert m["recall_at_1pct"] == m["recall_at_1"]


def test_exclusion_window_limits_the_database():
    # query i may use j <= i - 2; positive of query 3 is frame 2 (excluded) and 0
    d = np.array([[0.0, 0.1, 0.2, 0.3],
                  [0.1, 0.0, 0.5, 0.5],
                  [0.2, 0.5, 0.0, 0.9],
                  [0.6, 0.5, 0.05, 0.0]])
    pos = np.zeros((4, 4), bool)
    pos[3, 2] = pos[3, 0] = True
    pos[2, 0] = True
    valid = within_sequence_valid(np.array([-1, -1, 0, 1]))
    r = ranks_from_distances(d, pos, valid)
    assert r.database_size.tolist() == [0, 0, 1, 2]
    assert r.rank.tolist() == [0, 0, 1, 2]  # query 3: frame 1 (0.5) before frame 0 (0.6)
    assert ranking_metrics(r)["recall_at_n"][:2] == [0.5, 1.0]


def test_one_percent_uses_half_to_even_rounding():
    assert one_percent_n([50, 149, 150, 250, 251, 4541]).tolist() == [1, 1, 2, 2, 3, 45]


def test_no_evaluated_query_gives_undefined_not_zero():
    r = ranks_from_distances(np.ones((3, 4)), np.zeros((3, 4), bool))
    m = ranking_metrics(r)
    assert m["n_ranking_queries"] == 0
    assert m["recall_at_1"] is None and m["mrr"] is None and m["recall_at_1pct"] is None
    assert all(v is None for v in m["recall_at_n"])


def test_lists_and_block_agree_on_random_data():
    rng = np.random.default_rng(5)
    d = np.round(rng.random((40, 30)), 2)  # rounding makes ties
    pos = rng.random((40, 30)) < 0.08
    block = ranks_from_distances(d, pos)
    lists = [np.arange(30)] * 40
    scores = list(d)
    from_lists = ranks_from_lists(lists, [np.nonzero(p)[0] for p in pos], [30] * 40, scores)
    np.testing.assert_array_equal(block.rank, from_lists.rank)
    assert ranking_metrics(block) == ranking_metrics(from_lists)
    # Recall@1 is the share of evaluated queries whose argmin (first index on ties) is positive
    ev = pos.any(1)
    top1 = np.argmin(d, axis=1)
    assert ranking_metrics(block)["recall_at_1"] == pytest.approx(
        np.mean(pos[np.arange(40), top1][ev]))
    curve = [v for v in ranking_metrics(block)["recall_at_n"]]
    assert all(a <= b for a, b in zip(curve, curve[1:], strict=False))


def test_short_candidate_lists_leave_deep_recall_undefined():
    # K = 3 candidates out of a database of 100
    ranked = [np.array([5, 7, 9]), np.array([1, 2, 3])]
    scores = [np.array([0.3, 0.1, np.inf]), np.array([0.2, 0.1, 0.3])]
    positives = [{5}, {40}]
    r = ranks_from_lists(ranked, positives, [100, 100], scores)
    assert r.rank.tolist() == [2, 0]  # 9 rejected; 7 before 5
    assert r.ranked.tolist() == [2, 3]
    m = ranking_metrics(r)
    assert m["recall_at_n"][:3] == [0.0, 0.5, 0.5]
    # query 1's list ends at 3 without its positive: its rank beyond 3 is unknown
    assert all(v is None for v in m["recall_at_n"][3:])
    assert m["recall_at_1pct"] == 0.0  # N = 1 is within every list
    assert m["mrr"] == pytest.approx(0.25)


def test_candidate_list_that_finds_its_positive_is_fully_defined():
    r = ranks_from_lists([np.array([3, 1])], [{1}], [50])
    m = ranking_metrics(r)
    assert m["recall_at_n"] == [0.0] + [1.0] * (MAX_N - 1)
    assert m["mrr"] == 0.5


def test_rejected_candidates_are_known_misses_up_to_the_retrieval_depth():
    # K = 5: query 0's candidates were all rejected, query 1 found its positive at rank 1
    r = ranks_from_lists([np.array([4, 9]), np.array([2])], [{4}, {2}], [100, 100],
                         [np.array([np.inf, np.nan]), np.array([0.1])], depth=[5, 5])
    m = ranking_metrics(r)
    assert m["recall_at_n"][:5] == [0.5] * 5
    assert all(v is None for v in m["recall_at_n"][5:])
    assert m["mrr"] == 0.5
