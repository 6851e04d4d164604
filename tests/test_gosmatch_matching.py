"""GOSMatch retrieval and verification: exact k-NN, compiled RANSAC against geometry.py."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.gosmatch import PrefixKNN
from lidar_iris_eval.descriptors.gosmatch.kernels import (
    _kabsch,
    draw_samples,
    ransac_from_samples,
)
from lidar_iris_eval.matching import geometry
from lidar_iris_eval.matching.geometry import rotation_error_deg, translation_error_m, yaw_pose


def _rigid(rng, yaw_deg=None):
    T = yaw_pose(rng.uniform(0, 360) if yaw_deg is None else yaw_deg)
    tilt = yaw_pose(rng.uniform(-3, 3))[[0, 2, 1, 3]][:, [0, 2, 1, 3]]  # small roll
    T = T @ tilt
    T[:3, 3] = rng.uniform(-5, 5, size=3)
    return T


def test_kabsch_kernel_equals_geometry():
    rng = np.random.default_rng(0)
    out = np.empty((4, 4))
    for n in (3, 4, 7, 30):
        for _ in range(20):
            src = rng.normal(size=(n, 3)) * 10
            dst = rng.normal(size=(n, 3)) * 10  # arbitrary: also reflections must be guarded
            _kabsch(src, dst, np.ones(n, bool), out)
            np.testing.assert_allclose(out, geometry.kabsch(src, dst), atol=1e-9)
            assert np.linalg.det(out[:3, :3]) == pytest.approx(1.0)


def test_ransac_kernel_equals_geometry_given_the_same_samples():
    rng = np.random.default_rng(1)
    for trial in range(60):
        n = int(rng.integers(3, 40))
        src = rng.uniform(-30, 30, size=(n, 3))
        T = _rigid(rng)
        dst = geometry.transform_points(T, src) + rng.normal(scale=0.1, size=(n, 3))
        wrong = rng.random(n) < 0.5
        dst[wrong] += rng.normal(scale=8.0, size=(int(wrong.sum()), 3))
        samples = geometry._distinct_samples(np.random.default_rng(trial), n, 80, 3)
        pose, inl, res = ransac_from_samples(src, dst, samples, 1.0)
        ref = geometry.ransac_rigid(src, dst, threshold=1.0, iterations=80, min_inliers=3,
                                    rng=np.random.default_rng(trial))
        np.testing.assert_array_equal(inl, ref.inliers)
        np.testing.assert_allclose(pose, ref.pose, atol=1e-9)
        np.testing.assert_allclose(res, ref.residuals, atol=1e-9)


def test_samples_are_distinct_uniform_and_seeded():
    s = draw_samples(0, 5, 7, 10, 30000)
    assert s.min() == 0 and s.max() == 9
    assert np.all((s[:, 0] != s[:, 1]) & (s[:, 1] != s[:, 2]) & (s[:, 0] != s[:, 2]))
    counts = np.bincount(s.ravel(), minlength=10)
    assert np.all(np.abs(counts - 9000) < 5 * np.sqrt(9000))  # 5 sigma
    # all 6 orders of the only triple when n = 3
    assert len(np.unique(draw_samples(1, 2, 3, 3, 600), axis=0)) == 6
    np.testing.assert_array_equal(draw_samples(0, 5, 7, 10, 50), s[:50])
    assert not np.array_equal(draw_samples(0, 5, 8, 10, 50), s[:50])
    assert not np.array_equal(draw_samples(1, 5, 7, 10, 50), s[:50])


@pytest.mark.parametrize("leaf", [1, 4, 64])
def test_prefix_knn_is_exact_over_every_prefix(leaf):
    rng = np.random.default_rng(2)
    data = rng.integers(0, 3, size=(300, 8)).astype(float)  # many ties
    knn = PrefixKNN(data, leaf_block=leaf)
    for n in (1, 2, 3, 5, 64, 65, 127, 128, 129, 200, 300):
        for q in rng.integers(0, 300, size=4):
            idx, dist = knn.query(data[q], n, 7)
            full = np.linalg.norm(data[:n] - data[q], axis=1)
            order = np.lexsort((np.arange(n), full))[:7]
            np.testing.assert_array_equal(idx, order)
            np.testing.assert_allclose(dist, full[order], atol=1e-12)
    assert len(knn.query(data[0], 0, 5)[0]) == 0


# ----------------------------------------------------------------- verification


def _scene(rng, n_vehicles=12, n_trunks=6, n_poles=4):
    counts = (n_vehicles, n_trunks, n_poles)
    xyz = rng.uniform(-40, 40, size=(sum(counts), 3)) * [1, 1, 0.03]
    return xyz, np.repeat(np.arange(3, dtype=np.int8), counts)


def _moved(rng, xyz, cls, T, drop=3, add=3, noise=0.05):
    """The scene seen from another pose: ``p_candidate = inv(T) p_query``, some objects
    missed, some new ones, a little noise; returned sorted by class."""
    keep = np.sort(rng.choice(len(xyz), size=len(xyz) - drop, replace=False))
    inv = geometry.invert_pose(T)
    moved = geometry.transform_points(inv, xyz[keep]) + rng.normal(scale=noise,
                                                                   size=(len(keep), 3))
    extra = rng.uniform(-40, 40, size=(add, 3)) * [1, 1, 0.03]
    pts = np.concatenate([moved, extra])
    c = np.concatenate([cls[keep], rng.integers(0, 3, size=add).astype(np.int8)])
    order = np.argsort(c, kind="stable")
    return pts[order], c[order]


@pytest.mark.parametrize("preset", ["reference", "paper"])
def test_verify_recovers_the_pose_of_a_revisit(preset):
    rng = np.random.default_rng(3)
    method = get_descriptor("gosmatch", preset=preset)
    xyz, cls = _scene(rng)
    T = _rigid(rng, yaw_deg=180.0)  # a reverse-direction revisit
    frames = [method.features(*_scene(rng)) for _ in range(3)]
    frames.append(method.features(*_moved(rng, xyz, cls, T)))  # frame 3: the same place
    frames.append(method.features(xyz, cls))  # frame 4: the query
    db = method.prepare(frames)
    ver = method.verify(db, 4, np.arange(4))
    assert np.argmin(ver.score) == 3
    # 3 of the 22 query objects are missing from the candidate and 3 others added: at most
    # those 6 correspondences are outliers, each costing the 1 m threshold
    assert ver.score[3] <= 6 / 22 + 0.05 and ver.inliers[3] >= 22 - 6
    assert translation_error_m(ver.pose[3], T) < 0.1
    assert rotation_error_deg(ver.pose[3], T) < 0.5
    assert np.all(ver.score[:3] > 0.5)  # unrelated scenes: rejected or far worse
    # retrieval finds it too, and the graph distance is rotation invariant
    idx, _ = method.retrieve(db, 4, 4, 1)
    assert idx[0] == 3


def test_verify_is_deterministic_and_per_pair():
    rng = np.random.default_rng(4)
    method = get_descriptor("gosmatch")
    frames = [method.features(*_scene(rng)) for _ in range(6)]
    xyz, cls = _scene(rng)
    frames.append(method.features(*_moved(rng, xyz, cls, _rigid(rng), drop=8, add=8)))
    frames.append(method.features(xyz, cls))
    db = method.prepare(frames)
    a = method.verify(db, 7, np.arange(7))
    b = method.verify(db, 7, np.arange(7)[::-1])
    np.testing.assert_array_equal(a.score, b.score[::-1])
    np.testing.assert_array_equal(a.inliers, b.inliers[::-1])
    c = method.verify(db, 7, np.array([6]))
    assert c.score[0] == a.score[6]
    # the NumPy reference (geometry.ransac_rigid, other samples) agrees on the true pair
    ref = method.verify_reference(db, 7, np.array([6]))
    assert ref.inliers[0] == a.inliers[6]
    np.testing.assert_allclose(ref.pose[0], a.pose[6], atol=1e-9)


def test_scores_and_rejection():
    rng = np.random.default_rng(5)
    xyz, cls = _scene(rng)
    T = _rigid(rng)
    clipped = get_descriptor("gosmatch")
    inlier = get_descriptor("gosmatch", score="inlier-mean")
    strict = get_descriptor("gosmatch", min_inliers=100)
    frames = [clipped.features(*_moved(rng, xyz, cls, T, drop=0, add=6, noise=0.0)),
              clipped.features(xyz, cls)]
    db = clipped.prepare(frames)
    c, i, s = (m.verify(db, 1, np.array([0])) for m in (clipped, inlier, strict))
    # no noise: inliers fit exactly; 6 added objects of 28 may pair up as outliers, each
    # costing the full 1 m threshold in the clipped mean
    assert i.score[0] < 1e-9
    n_corr = len(cls)  # every query vertex has a same-class candidate
    assert c.score[0] == pytest.approx((n_corr - c.inliers[0]) / n_corr, abs=1e-9)
    assert np.isinf(s.score[0]) and np.all(np.isnan(s.pose[0]))


def test_retrieval_pairwise_is_graph_l2():
    rng = np.random.default_rng(6)
    method = get_descriptor("gosmatch")
    frames = [method.features(*_scene(rng)) for _ in range(5)]
    db = method.prepare(frames)
    d = method.retrieval_pairwise(db, np.array([0, 3]), slice(0, 5))
    want = np.linalg.norm(db.graph[[0, 3]][:, None] - db.graph[None], axis=2)
    np.testing.assert_allclose(d, want, atol=1e-9)
    assert d[0, 0] == 0 and d[1, 3] == 0
