"""Block driver and protocols 1 / 2 on inputs whose answer is known by construction.

Also defines the toy descriptors used by test_cache.py and test_eval_cli.py
(a histogram of ranges with L1 distance, and an asymmetric variant).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import write_kitti_sequence

from lidar_iris_eval.descriptors import Descriptor, available_descriptors, get_descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.evaluation.protocol1 import protocol1, reverse_revisits
from lidar_iris_eval.evaluation.protocol2 import protocol2, protocols_1_and_2
from lidar_iris_eval.extract import extract
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.matching.blocks import affinity_matrix, best_matches
from lidar_iris_eval.matching.retrieval import two_stage_matches as retrieval_matches


# --------------------------------------------------------------------------- toys
@dataclass(frozen=True)
class ToyParams:
    bins: int = 16
    max_range: float = 20.0
    delay: float = 0.0  # seconds slept per compute, to make extraction interruptible


class ToyHist(Descriptor):
    """Normalised histogram of horizontal ranges; L1 distance; no yaw."""

    name = "toy"
    params_type = ToyParams
    symmetric = True
    warm_up = False  # nothing to compile; keeps ``calls`` equal to the scans computed

    def __init__(self, params=None, preset="custom"):
        super().__init__(params, preset)
        self.calls = 0

    def compute(self, points):
        self.calls += 1
        if self.params.delay:
            time.sleep(self.params.delay)
        r = np.hypot(points[:, 0], points[:, 1])
        hist, _ = np.histogram(r, bins=self.params.bins, range=(0, self.params.max_range))
        return (hist / max(1, len(r))).astype(np.float64)

    def pairwise(self, queries, database):
        d = np.abs(queries[:, None, :] - database[None, :, :]).sum(-1)
        return d, np.full(d.shape, np.nan)

    def distances(self, query, database):
        d, y = self.pairwise(query[None], database)
        return d[0], y[0]

    def distance(self, query, candidate):
        d, y = self.pairwise(query[None], candidate[None])
        return float(d[0, 0]), float(y[0, 0])


@dataclass(frozen=True)
class SlowParams(ToyParams):
    delay: float = 0.05


class SlowToyHist(ToyHist):
    """ToyHist that sleeps 50 ms per scan, so a test can kill it mid-run."""

    params_type = SlowParams


class ToyAsym(ToyHist):
    """Asymmetric: over-shoot costs twice under-shoot. Yaw from the histogram peaks."""

    name = "toy-asym"
    symmetric = False

    def pairwise(self, queries, database):
        diff = queries[:, None, :] - database[None, :, :]
        d = (2 * np.maximum(diff, 0) - np.minimum(diff, 0)).sum(-1)
        yaw = (10.0 * (np.argmax(queries, 1)[:, None] - np.argmax(database, 1)[None, :])) % 360
        return d, yaw.astype(np.float64)


class ToyRetrieval(ToyHist):
    """ToyHist with a retrieval stage: the k nearest by the first two bins only."""

    name = "toy-retrieval"

    def retrieve(self, db, query, n_allowed, k):
        d = np.abs(db[query, :2] - db[:n_allowed, :2]).sum(-1)
        idx = np.argsort(d, kind="stable")[: min(k, n_allowed)]
        return idx.astype(np.int64), np.full(len(idx), np.nan)


# --------------------------------------------------------------------------- builders
def random_scan(rng: np.random.Generator, n_points: int = 400) -> np.ndarray:
    """A random (n, 4) scan with a random range profile, distinct from any other."""
    r = rng.uniform(0.5, 1.0) * 20 * rng.random(n_points) ** rng.uniform(0.3, 3.0)
    a = rng.uniform(0, 2 * np.pi, n_points)
    z = rng.normal(0, 1, n_points)
    return np.stack([r * np.cos(a), r * np.sin(a), z, np.ones(n_points)], 1).astype(np.float32)


def line_poses(xs: np.ndarray, heading_deg: np.ndarray | float = 0.0) -> np.ndarray:
    """Camera-frame poses along the camera x axis (y down, z forward) at positions ``xs``."""
    n = len(xs)
    heading = np.broadcast_to(np.radians(heading_deg), (n,))
    poses = np.tile(np.eye(4), (n, 1, 1))
    c, s = np.cos(heading), np.sin(heading)
    # rotation about the camera y axis (vertical)
    poses[:, 0, 0], poses[:, 0, 2], poses[:, 2, 0], poses[:, 2, 2] = c, s, -s, c
    poses[:, 0, 3] = xs
    return poses


def two_pass_sequence(root: Path, n_per_pass: int = 12, seed: int = 0) -> Path:
    """Two passes over the same places with byte-identical scans.

    Places are 10 m apart, so the only positives are (k, n + k), at 0 m.
    """
    rng = np.random.default_rng(seed)
    scans = [random_scan(rng) for _ in range(n_per_pass)]
    xs = np.arange(n_per_pass) * 10.0
    poses = line_poses(np.concatenate([xs, xs]))
    return write_kitti_sequence(root, scans + scans, poses)


def brute_force_best(desc, descs, exclude):
    """Reference protocol 1 search with single-pair distances and Python loops."""
    out = {}
    for i in range(exclude, len(descs)):
        best = (np.inf, -1, np.nan)
        for j in range(0, i - exclude + 1):
            d, y = desc.distance(descs[i], descs[j])
            if not np.isnan(d) and d < best[0]:
                best = (d, j, y)
        out[i] = best
    return out


# --------------------------------------------------------------------------- block driver
@pytest.mark.parametrize("toy", [ToyHist, ToyAsym])
@pytest.mark.parametrize("budget", [1, 50, 10_000])
def test_best_matches_equal_brute_force(toy, budget):
    rng = np.random.default_rng(1)
    desc = toy()
    descs = np.stack([desc.compute(random_scan(rng)[:, :3]) for _ in range(40)])
    descs[7] = descs[2]  # an exact repeat: distance 0
    exclude = 5
    got = best_matches(desc, descs, exclude, pair_budget=budget)
    ref = brute_force_best(desc, descs, exclude)
    assert got.query.tolist() == list(range(exclude, 40))
    for q, i in enumerate(got.query):
        d, j, y = ref[i]
        assert got.match[q] == j
        assert got.distance[q] == d
        assert (np.isnan(y) and np.isnan(got.yaw_deg[q])) or got.yaw_deg[q] == y
    assert got.match[7 - exclude] == 2 and got.distance[7 - exclude] == 0.0


@pytest.mark.parametrize("toy", [ToyHist, ToyAsym])
def test_affinity_matches_single_pairs_and_reuses_for_protocol1(toy):
    rng = np.random.default_rng(2)
    desc = toy()
    descs = np.stack([desc.compute(random_scan(rng)[:, :3]) for _ in range(23)])
    aff, p1 = affinity_matrix(desc, descs, exclude=4, pair_budget=30)  # many blocks
    n = len(descs)
    expected = np.array([[desc.distance(descs[i], descs[j])[0] for j in range(n)]
                         for i in range(n)], dtype=np.float32)
    np.fill_diagonal(expected, np.nan)
    np.testing.assert_array_equal(aff.matrix, expected)
    assert aff.symmetric == toy.symmetric
    if toy.symmetric:  # lower triangle only, plus the small diagonal blocks
        assert aff.n_evaluations < n * n
    alone = best_matches(desc, descs, 4)
    np.testing.assert_array_equal(p1.match, alone.match)
    np.testing.assert_array_equal(p1.distance, alone.distance)
    np.testing.assert_array_equal(p1.yaw_deg, alone.yaw_deg)


def test_nan_distances_never_win():
    class NanToy(ToyHist):
        def pairwise(self, queries, database):
            d, y = super().pairwise(queries, database)
            return np.where(d < 0.5, np.nan, d), y

    rng = np.random.default_rng(3)
    desc = NanToy()
    descs = np.stack([desc.compute(random_scan(rng)[:, :3]) for _ in range(10)])
    descs[6] = descs[0]  # its zero distance becomes NaN
    got = best_matches(desc, descs, 3)
    assert got.match[6 - 3] != 0
    assert np.all(np.isfinite(got.distance) | (got.match == -1))


def test_retrieval_with_all_candidates_equals_exhaustive():
    rng = np.random.default_rng(4)
    desc = ToyRetrieval()
    descs = np.stack([desc.compute(random_scan(rng)[:, :3]) for _ in range(20)])
    full = retrieval_matches(desc, descs, exclude=3, k=1000)
    exhaustive = best_matches(desc, descs, 3)
    np.testing.assert_array_equal(full.match, exhaustive.match)
    # with k = 1 the match is the nearest in the first two bins, restricted to j <= i - 3
    one = retrieval_matches(desc, descs, exclude=3, k=1)
    for q, i in enumerate(one.query):
        key = np.abs(descs[: i - 2, :2] - descs[i, :2]).sum(1)
        assert one.match[q] == int(np.argmin(key))
    assert one.n_evaluations == len(one.query)


def test_retrieval_needs_a_candidates_method():
    with pytest.raises(LirisError, match="no retrieval"):
        retrieval_matches(ToyHist(), np.zeros((5, 16)), exclude=1, k=3)


# --------------------------------------------------------------------------- protocols
@pytest.fixture
def two_pass(tmp_path):
    return open_sequence(two_pass_sequence(tmp_path / "seq", n_per_pass=12))


@pytest.mark.parametrize("toy", [ToyHist, ToyAsym])
@pytest.mark.parametrize("denominator", ["revisits", "accepted"])
def test_two_identical_passes_are_perfect(two_pass, toy, denominator):
    desc = toy()
    db = extract(two_pass, desc)
    positions = two_pass.positions("camera")
    p1, p2 = protocols_1_and_2(desc, db.descriptors, positions, exclude=5,
                               recall_denominator=denominator)
    # queries 5..23; revisits are the 12 frames of pass two
    assert p1.metrics["n_queries"] == 19 and p1.metrics["n_skipped"] == 5
    assert p1.metrics["n_revisits"] == 12
    assert p1.metrics["n_true_top1"] == 12
    assert p1.metrics["f1_max"] == 1.0 and p1.metrics["f1_threshold"] == 0.0
    assert p1.metrics["ap"] == 1.0 and p1.metrics["r100p"] == 1.0 and p1.metrics["ep"] == 1.0
    second = p1.matches.query >= 12
    np.testing.assert_array_equal(p1.matches.match[second], p1.matches.query[second] - 12)
    assert p2.metrics["ap"] == 1.0 and p2.metrics["r100p"] == 1.0
    assert p2.metrics["n_positives"] == 24 and p2.metrics["n_pairs"] == 24 * 23


@pytest.mark.parametrize("name", ["lidar-iris", "scan-context", "m2dp", "esf"])
def test_two_identical_passes_are_perfect_for_real_descriptors(tmp_path, name):
    if name not in available_descriptors():
        pytest.skip(f"{name} is not in the tree")
    seq = open_sequence(two_pass_sequence(tmp_path / "seq", n_per_pass=6))
    desc = get_descriptor(name)
    db = extract(seq, desc)
    p1, p2 = protocols_1_and_2(desc, db, seq.positions("camera"), exclude=3)
    assert p1.metrics["n_revisits"] == 6 and p1.metrics["n_true_top1"] == 6
    assert p1.metrics["f1_max"] == 1.0 and p1.metrics["ap"] == 1.0
    assert p2.metrics["ap"] == 1.0


def test_protocol_functions_agree_with_combined_pass(two_pass):
    desc = ToyAsym()
    descs = extract(two_pass, desc).descriptors
    pos = two_pass.positions("camera")
    both1, both2 = protocols_1_and_2(desc, descs, pos, exclude=3, recall_denominator="accepted")
    alone1 = protocol1(desc, descs, pos, exclude=3, recall_denominator="accepted")
    alone2 = protocol2(desc, descs, pos)
    np.testing.assert_array_equal(both1.matches.match, alone1.matches.match)
    assert both1.metrics == alone1.metrics
    np.testing.assert_array_equal(both2.affinity.matrix, alone2.affinity.matrix)
    assert both2.metrics == alone2.metrics


def test_protocol2_counts_are_ordered_ground_truth_pairs():
    rng = np.random.default_rng(5)
    positions = np.cumsum(rng.normal(0, 1.5, (60, 3)), axis=0)
    desc = ToyHist()
    descs = rng.random((60, 16))
    result = protocol2(desc, descs, positions, radius=4.0)
    gt = compute_ground_truth(positions, 4.0, 1)
    dense = np.linalg.norm(positions[:, None] - positions[None], axis=2) < 4.0
    np.fill_diagonal(dense, False)
    assert result.metrics["n_positives"] == gt.n_positive_pairs == int(dense.sum())
    assert result.metrics["n_negatives"] == 60 * 59 - int(dense.sum())


def test_protocol1_revisits_and_truth_follow_the_radius():
    # a loop: out along x for 20 frames (2 m apart), back along the same line
    xs = np.concatenate([np.arange(20) * 2.0, np.arange(19, -1, -1) * 2.0 + 0.5])
    positions = np.stack([xs, np.zeros(40), np.zeros(40)], 1)
    rng = np.random.default_rng(6)
    desc = ToyHist()
    descs = rng.random((40, 16))
    res = protocol1(desc, descs, positions, exclude=10, radius=4.0, frame="camera")
    near = np.abs(xs[:, None] - xs[None, :]) < 4.0
    for q, i in enumerate(res.matches.query):
        assert res.is_revisit[q] == bool(near[i, : i - 10 + 1].any())
        assert res.is_true[q] == bool(near[i, res.matches.match[q]])
        assert res.match_dist_m[q] == pytest.approx(abs(xs[i] - xs[res.matches.match[q]]))


def test_reverse_revisits_from_headings():
    # out along +x (heading 0), back along the same line (heading 180)
    xs = np.concatenate([np.arange(10) * 3.0, np.arange(9, -1, -1) * 3.0])
    positions = np.stack([xs, np.zeros(20), np.zeros(20)], 1)
    forward = np.zeros((20, 3))
    forward[:10, 0], forward[10:, 0] = 1.0, -1.0
    gt = compute_ground_truth(positions, 4.0, 3, "3d", "lidar")
    rev = reverse_revisits(positions, gt, forward)
    assert np.array_equal(rev, gt.revisit & (np.arange(20) >= 10))
    assert rev.sum() > 0
    same = reverse_revisits(positions, gt, np.tile([1.0, 0, 0], (20, 1)))
    assert not same.any()


def test_scan_context_candidates_on_the_two_stage_path_equal_the_former_loop():
    """--candidates K through retrieve/verify gives exactly what the dedicated loop gave:
    ring-key candidates among j <= i - E, sorted, full distance, smallest wins."""
    from lidar_iris_eval.descriptors import get_descriptor

    rng = np.random.default_rng(12)
    desc = get_descriptor("scan-context")
    base = [random_scan(rng, 3000) for _ in range(6)]
    scans = [b + rng.normal(scale=0.05, size=b.shape).astype(np.float32)
             for b in base for _ in range(4)]  # 4 noisy visits of 6 places
    descs = np.stack([desc.compute(s) for s in scans])
    got = retrieval_matches(desc, descs, exclude=3, k=4)
    assert got.source == "candidates:4" and got.inliers is None
    assert (got.match >= 0).all() and len(got.query) == 21
    for q, i in enumerate(got.query):
        database = descs[: i - 3 + 1]
        cand = np.unique(desc.retrieve(descs, int(i), len(database), 4)[0])
        d, y = desc.distances(descs[i], database[cand])
        d = np.where(np.isnan(d), np.inf, d)
        best = int(np.argmin(d))
        assert got.match[q] == cand[best] and got.distance[q] == d[best]
        assert got.yaw_deg[q] == y[best]
