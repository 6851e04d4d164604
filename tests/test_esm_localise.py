"""ESM's local-map verification: the lazy consistency search against the dense one.

``localise`` forms only the consistency rows its greedy sets read.
:func:`reference_sets` is the straightforward search it replaced (the
whole ``(n, n)`` matrix with ``np.linalg.norm``, kept here as the oracle;
:func:`reference_localise` is ``localise`` with it swapped in,
used by ``scripts/bench_esm_localmaps.py time`` as the timing baseline). Every
case asks for the same outcome to the bit: frame, inliers, hypotheses, pose
and residual. The cases are random scenes and adversarial ones: tied
embeddings and qualities (PROSAC order decided by the tie-breakers), duplicate
centroids, and centroids on a grid where many ``|d_target - d_query|`` equal
the threshold exactly or differ from it by one rounding.
"""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest

from lidar_iris_eval.descriptors.esm import target_map
from lidar_iris_eval.descriptors.esm.target_map import (
    Localisation,
    _centroid_distances,
    _consistent_sets,
    localise,
)
from lidar_iris_eval.matching.geometry import yaw_pose


def dense_consistency(qa, tb, t_world, q_cent, threshold) -> np.ndarray:
    """The whole ``(n, n)`` consistency matrix, as the search before the lazy one formed it."""
    src, dst = t_world[tb], q_cent[qa]
    ds = np.linalg.norm((src[:, None] - src[None]).astype(np.float32), axis=2)
    dd = np.linalg.norm((dst[:, None] - dst[None]).astype(np.float32), axis=2)
    ok = np.abs(ds - dd) <= threshold
    ok &= qa[:, None] != qa[None, :]
    ok &= tb[:, None] != tb[None, :]
    return ok


def reference_sets(qa, tb, t_world, q_cent, threshold, min_consistent, seeds,
                   grow: str = "order") -> list:
    """The dense consistency matrix and the greedy sets read from it (``_consistent_sets``).

    ``grow="order"``: the next member is the first allowed one; ``"degree"``: the allowed
    one consistent with most of the others still allowed, degrees recounted at every step
    (ties: the first), the oracle of ``target_map._grow_degree``.
    """
    ok = dense_consistency(qa, tb, t_world, q_cent, threshold)
    degree = ok.sum(1)
    out = []
    for seed in range(seeds):
        if degree[seed] + 1 < min_consistent:
            continue
        members = [seed]
        alive = np.flatnonzero(ok[seed])
        while len(alive):
            if grow == "degree":
                c = int(alive[int(np.argmax(ok[np.ix_(alive, alive)].sum(1)))])
            else:
                c = int(alive[0])
            members.append(c)
            alive = alive[ok[c, alive]]
        if len(members) >= min_consistent:
            out.append((seed, np.asarray(members)))
    return out


def reference_localise(*args, **kwargs) -> Localisation:
    """``localise`` with the dense set search (:func:`reference_sets`) in place of the lazy one.

    The k-NN, the PROSAC order, the fits and the frame choice are ``localise``'s own
    (unchanged by the lazy search), so a difference can only come from the sets;
    the CPU-time split is ``localise``'s (the set search counts as matching).
    """
    with mock.patch.object(target_map, "_consistent_sets", reference_sets):
        return target_map.localise(*args, **kwargs)


def same_sets(a: list, b: list) -> bool:
    """The same seeds with the same members in the same order."""
    return len(a) == len(b) and all(sa == sb and np.array_equal(ma, mb)
                                    for (sa, ma), (sb, mb) in zip(a, b, strict=True))


def same_outcome(a: Localisation, b: Localisation) -> bool:
    """Equal to the bit (NaN equal to NaN); CPU times are not compared."""
    return (a.frame == b.frame and a.inliers == b.inliers and a.hypotheses == b.hypotheses
            and np.array_equal(a.world_to_query, b.world_to_query, equal_nan=True)
            and np.array_equal(np.float64(a.residual), np.float64(b.residual), equal_nan=True))


def _scene(rng, nq: int, nt: int, *, grid: float | None, levels: int | None,
           tied_quality: bool, seen_share: float = 2 / 3, line: bool = False):
    """A query local map partly seen again in a target map, plus clutter.

    ``grid``: centroids (and the pose's translation) on multiples of ``grid``
    with a quarter-turn rotation, so distances repeat and many differences sit
    on the threshold; ``levels``: embeddings quantised to that many values per
    dimension (tied k-NN distances); ``tied_quality``: all qualities 1;
    ``seen_share``: the share of query segments that are in the target;
    ``line``: every centroid on the x axis at multiples of ``grid`` and half
    the seen target segments moved by one ``grid`` step after the query saw
    them, so that with ``threshold == grid`` most consistency decisions are
    ``|d_target - d_query| == threshold`` (or one rounding from it).
    """
    if line:
        t_world = np.zeros((nt, 3))
        t_world[:, 0] = rng.integers(-40, 41, nt) * grid
        T = np.diag([*(1.0, -1.0)[rng.integers(2)] * np.ones(2), 1.0, 1.0])
        T[0, 3] = rng.integers(-3, 4) * grid
    elif grid is None:
        t_world = rng.uniform(-25, 25, (nt, 3)) * [1, 1, 0.2]
        T = yaw_pose(rng.uniform(-180, 180), rng.uniform(-5, 5, 3))
    else:
        t_world = rng.integers(-8, 9, (nt, 3)) * grid * np.array([1, 1, 0.5])
        T = yaw_pose(90.0 * rng.integers(4), rng.integers(-3, 4, 3) * grid)
        T[:3, :3] = np.round(T[:3, :3])
    t_emb = rng.normal(size=(nt, 16))
    if levels is not None:
        t_emb = np.round(t_emb * levels / 4) * 4 / levels
    seen = rng.choice(nt, size=max(1, int(min(nq, nt) * seen_share)), replace=False)
    q_cent = t_world[seen] @ T[:3, :3].T + T[:3, 3]
    q_emb = t_emb[seen] + (0 if levels is not None else rng.normal(0, 0.05, (len(seen), 16)))
    extra = nq - len(seen)  # segments of the query not in the target
    if line:
        clutter = np.zeros((extra, 3))
        clutter[:, 0] = rng.integers(-40, 41, extra) * grid
        t_world[seen[rng.random(len(seen)) < 0.5], 0] += grid
    else:
        clutter = (rng.uniform(-25, 25, (extra, 3)) if grid is None else
                   rng.integers(-8, 9, (extra, 3)) * grid)
    q_cent = np.vstack([q_cent, clutter])
    q_emb = np.vstack([q_emb, t_emb[rng.integers(nt, size=extra)]])  # look-alikes elsewhere
    if rng.random() < 0.5:  # duplicate centroids: a segment seen twice in the target
        t_world[rng.integers(nt)] = t_world[rng.integers(nt)]
    q_qual = np.ones(nq) if tied_quality else rng.uniform(0.2, 1, nq)
    t_qual = np.ones(nt) if tied_quality else rng.uniform(0.2, 1, nt)
    if not tied_quality and rng.random() < 0.5:
        q_qual = np.round(q_qual, 1)  # a few ties
        t_qual = np.round(t_qual, 1)
    t_ids = rng.permutation(10 * nt)[:nt]
    where = np.linalg.inv(T)[:3, 3]
    positions = np.vstack([rng.uniform(-30, 30, (6, 3)), where + rng.uniform(-3, 3, 3)])
    return (q_emb.astype(np.float32), q_qual, q_cent, t_emb.astype(np.float32), t_qual, t_world,
            t_ids, positions)


CASES = [  # (grid, levels, tied_quality, threshold, line)
    (None, None, False, 0.6, False),
    (None, 3, True, 0.6, False),
    (0.2, None, False, 0.6, False),  # multiples of 0.2: |d - d'| rounds to either side of 0.6
    (0.2, 2, True, 0.6, False),
    (1.0, 2, True, 1.0, False),  # integer distances: |d - d'| == 1.0 exactly
    (0.5, None, True, 0.5, False),
    (1.0, None, False, 1.0, True),  # on a line: the threshold decides most pairs
    (0.6, 3, True, 0.6, True),  # ... or one float32 rounding does
    (0.5, None, True, 0.5, True),
]


def _exact_ties(args, knn: int, threshold: float) -> int:
    """How many dense-matrix pairs sit exactly on the threshold (the case is adversarial)."""
    q_emb, _, q_cent, t_emb, _, t_world, *_ = args
    d2 = ((q_emb[:, None].astype(np.float64) - t_emb[None]) ** 2).sum(2)
    k = min(knn, len(t_emb) - 1)
    nn = np.argsort(d2, axis=1, kind="stable")[:, :k]
    qa = np.repeat(np.arange(len(q_emb)), k)
    src, dst = t_world[nn.ravel()], q_cent[qa]
    ds = np.linalg.norm((src[:, None] - src[None]).astype(np.float32), axis=2)
    dd = np.linalg.norm((dst[:, None] - dst[None]).astype(np.float32), axis=2)
    return int((np.abs(ds - dd) == np.float32(threshold)).sum())


@pytest.mark.parametrize("grow", ["order", "degree"])
@pytest.mark.parametrize("case", range(len(CASES)))
def test_localise_equals_the_dense_reference(case, grow):
    grid, levels, tied, threshold, line = CASES[case]
    rng = np.random.default_rng(100 + case)
    accepted = rejected = ties = 0
    for trial in range(12):
        nq, nt = int(rng.integers(8, 30)), int(rng.integers(10, 80))
        knn = int(rng.choice([1, 3, 5, 25]))
        few = trial % 3 == 2  # few segments seen again: mostly rejected
        args = _scene(rng, nq, nt, grid=grid, levels=levels, tied_quality=tied,
                      seen_share=0.1 if few else 2 / 3, line=line)
        kw = dict(knn=knn, threshold=threshold,
                  min_consistent=6 if few else int(rng.choice([3, 4, 6])),
                  iterations=int(rng.choice([1, 7, 70, 300])),  # 70 > one seed block
                  frame_rule=("estimate", "segments")[trial % 2], max_offset=4.0, grow=grow)
        new, ref = localise(*args, **kw), reference_localise(*args, **kw)
        assert same_outcome(new, ref), (case, trial, new, ref)
        accepted += new.frame >= 0
        rejected += new.frame < 0
        if grid is not None:
            ties += _exact_ties(args, knn, threshold)
    assert accepted and rejected  # both outcomes were compared
    if grid is not None:
        assert ties > 0  # some consistency decisions were made exactly on the threshold


def test_localise_equals_the_reference_on_degenerate_inputs():
    rng = np.random.default_rng(7)
    args = list(_scene(rng, 10, 12, grid=None, levels=None, tied_quality=False))
    kw = dict(knn=25, threshold=0.6, min_consistent=3, iterations=300)
    for nq, nt in [(0, 12), (10, 1), (10, 2), (1, 12)]:
        a = list(args)
        a[0], a[1], a[2] = a[0][:nq], a[1][:nq], a[2][:nq]
        a[3], a[4], a[5], a[6] = a[3][:nt], a[4][:nt], a[5][:nt], a[6][:nt]
        assert same_outcome(localise(*a, **kw), reference_localise(*a, **kw)), (nq, nt)
    same = list(args)  # every target at one place: all target distances 0
    same[5] = np.zeros_like(args[5])
    assert same_outcome(localise(*same, **kw), reference_localise(*same, **kw))


def test_centroid_distances_are_the_dense_norm_bit_for_bit():
    rng = np.random.default_rng(3)
    for scale in (0.01, 1.0, 40.0, 1e4):
        pts = rng.normal(size=(300, 3)) * scale
        dense = np.linalg.norm((pts[:, None] - pts[None]).astype(np.float32), axis=2)
        assert np.array_equal(_centroid_distances(pts[:, None], pts[None]), dense)
        for i in (0, 17, 299):  # one row, as a member's row is formed
            assert np.array_equal(_centroid_distances(pts[i], pts[5:]), dense[i, 5:])
    # the summation order matters for these: (x + y) + z is what the dense norm did
    d = rng.normal(size=(20000, 3)).astype(np.float32) * 30
    s = d * d
    other = np.sqrt(s[:, 0] + (s[:, 1] + s[:, 2]))
    assert (other != np.linalg.norm(d, axis=1)).any()
    assert np.array_equal(_centroid_distances(d.astype(np.float64), 0.0),
                          np.linalg.norm(d, axis=1))


@pytest.mark.parametrize("grow", ["order", "degree"])
@pytest.mark.parametrize("grid", [None, 0.6, 1.0])
def test_consistent_sets_equal_the_dense_sets(grid, grow):
    """Every seed's set, winning or not, over correspondence lists longer than a seed block."""
    rng = np.random.default_rng(11)
    for _ in range(6):
        nq, nt = int(rng.integers(5, 25)), int(rng.integers(5, 60))
        n = int(rng.integers(1, 400))
        qa, tb = rng.integers(nq, size=n), rng.integers(nt, size=n)
        if grid is None:
            q_cent, t_world = rng.normal(size=(nq, 3)) * 5, rng.normal(size=(nt, 3)) * 5
            threshold = 0.6
        else:  # on a line, the target a shifted copy: |d - d'| on the threshold
            q_cent, t_world = np.zeros((nq, 3)), np.zeros((nt, 3))
            q_cent[:, 0] = rng.integers(-20, 21, nq) * grid
            t_world[:, 0] = q_cent[rng.integers(nq, size=nt), 0] + rng.integers(2, size=nt) * grid
            threshold = grid
        for seeds, min_consistent in [(n, 3), (min(n, 300), 6), (min(n, 70), 1)]:
            new = _consistent_sets(qa, tb, t_world, q_cent, threshold, min_consistent, seeds,
                                   grow)
            ref = reference_sets(qa, tb, t_world, q_cent, threshold, min_consistent, seeds,
                                 grow)
            assert same_sets(new, ref)
            assert len(ref) > 0 or min_consistent > 1


def test_comparison_limit_is_the_threshold_numpy_compares_float32_with():
    from lidar_iris_eval.descriptors.esm.target_map import _comparison_limit

    below = np.float32(0.6)  # 0.60000002384..., above the float64 0.6
    assert float(below) > 0.6
    # a Python float meets a float32 array as float32 (NEP 50): the float32 0.6 passes
    assert bool(np.array([below]) <= 0.6) and _comparison_limit(0.6) == float(below)
    # a float64 scalar does not: the float32 0.6 is above it
    assert not bool(np.array([below]) <= np.float64(0.6))
    assert _comparison_limit(np.float64(0.6)) == 0.6
