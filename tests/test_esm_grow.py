"""ESM's consistent sets grown most-consistent-first (``esm.grow=degree``).

A seed's set grows by the candidate consistent with most of the others still
allowed instead of the first in PROSAC order. Checked against the dense NumPy
oracle of tests/test_esm_localise.py (``reference_sets(..., "degree")``: the
same members in the same order) on random scenes, for the clique property, and
on a hand-built scene where one wrong correspondence early in the order blocks
the first-in-order rule but not this one.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_esm_localise import dense_consistency, reference_sets

from lidar_iris_eval.descriptors.esm.descriptor import ESMParams
from lidar_iris_eval.descriptors.esm.target_map import _consistent_sets
from lidar_iris_eval.errors import LirisError


def _random_scene(seed: int, nq: int = 30, nt: int = 60, k: int = 8):
    rng = np.random.default_rng(seed)
    q_cent = rng.uniform(-20, 20, (nq, 3)) * [1, 1, 0.1]
    yaw = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    t_world = np.concatenate([q_cent[: nt // 2] @ rot.T + [5, -3, 0.2]
                              + rng.normal(0, 0.1, (nt // 2, 3)),
                              rng.uniform(-20, 20, (nt - nt // 2, 3)) * [1, 1, 0.1]])
    qa = np.repeat(np.arange(nq), k)
    tb = rng.integers(0, nt, len(qa))
    tb[::k] = np.minimum(np.arange(nq), nt // 2 - 1)  # one true candidate per query
    order = rng.permutation(len(qa))
    return qa[order], tb[order], t_world, q_cent


@pytest.mark.parametrize("seed", range(6))
def test_degree_sets_equal_the_dense_oracle(seed):
    qa, tb, t_world, q_cent = _random_scene(seed)
    got = _consistent_sets(qa, tb, t_world, q_cent, 0.6, 4, len(qa), "degree")
    want = reference_sets(qa, tb, t_world, q_cent, 0.6, 4, len(qa), "degree")
    assert len(want) > 0
    assert [s for s, _ in got] == [s for s, _ in want]
    for (_, a), (_, b) in zip(got, want, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("seed", range(4))
def test_degree_sets_are_cliques_without_repeated_segments(seed):
    qa, tb, t_world, q_cent = _random_scene(100 + seed)
    ok = dense_consistency(qa, tb, t_world, q_cent, 0.6)
    sets = _consistent_sets(qa, tb, t_world, q_cent, 0.6, 3, len(qa), "degree")
    assert sets
    for _, members in sets:
        sub = ok[np.ix_(members, members)]
        assert sub[~np.eye(len(members), dtype=bool)].all()
        assert len(set(qa[members].tolist())) == len(members)
        assert len(set(tb[members].tolist())) == len(members)


def test_an_early_wrong_correspondence_blocks_order_but_not_degree():
    # eight true correspondences (query i -> target i) under a known rigid motion; a wrong
    # one (query 1 -> target 8) comes second in PROSAC order: consistent with the seed
    # (same distance to it) but placed 90 degrees round it, so consistent with no other
    rng = np.random.default_rng(3)
    q_cent = np.column_stack([rng.uniform(-15, 15, 8), rng.uniform(-15, 15, 8), np.zeros(8)])
    q_cent[0] = 0.0
    yaw = np.radians(35.0)
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    t_true = q_cent @ rot.T + [10.0, 4.0, 0.0]
    quarter = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    wrong = t_true[0] + (t_true[1] - t_true[0]) @ quarter.T
    t_world = np.vstack([t_true, wrong])
    qa = np.array([0, 1, 1, 2, 3, 4, 5, 6, 7])
    tb = np.array([0, 8, 1, 2, 3, 4, 5, 6, 7])
    ok = dense_consistency(qa, tb, t_world, q_cent, 0.6)
    assert ok[0, 1] and ok[1, 2:].sum() <= 1  # the premise: wrong joins the seed, little else

    order = _consistent_sets(qa, tb, t_world, q_cent, 0.6, 6, 1, "order")
    degree = _consistent_sets(qa, tb, t_world, q_cent, 0.6, 6, 1, "degree")
    assert order == []  # the seed's set took the wrong one second and stalled below 6
    assert len(degree) == 1
    seed, members = degree[0]
    assert seed == 0
    assert sorted(tb[members].tolist()) == list(range(8))  # the eight true ones


def test_grow_rule_is_checked():
    assert ESMParams(grow="degree").grow == "degree"
    with pytest.raises(LirisError, match="esm.grow"):
        ESMParams(grow="largest")
