"""The learned descriptors' distances: the Gram route against the broadcast reference.

``LearnedVectorDescriptor`` (BEVPlace++, OverlapTransformer) computes every
distance with :func:`~lidar_iris_eval.descriptors.vector_common.gram_pairwise`
(``|q|^2 + |r|^2 - 2 q.r``, the cross term a BLAS product on padded blocks).
What is pinned here:

* it equals the broadcast difference :func:`vector_rows` (the previous route,
  kept as the reference) within :data:`TOLERANCE` on random unit vectors and on
  descriptors of real KITTI scans, with the same nearest neighbour per query
  and the same order wherever two distances are further apart than twice the
  tolerance;
* its single-pair, one-query and pairwise routes are bitwise equal, whatever
  the block split, the query subset or the shapes (the project's guarantee,
  which protocol 2's streamed counting relies on: a mismatch forces a second
  pass);
* BEVPlace++'s convolution accumulating inside the GEMM equals product then
  ``+=`` bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import KITTI

from lidar_iris_eval.descriptors import get_descriptor, vector_common
from lidar_iris_eval.descriptors.bevplace import network as bev_network
from lidar_iris_eval.descriptors.vector_common import (
    GRAM_MIN_MNK,
    GRAM_TILE,
    gram_pairwise,
    gram_shape,
    pairwise_blocks,
    vector_rows,
)
from lidar_iris_eval.evaluation.streaming_pr import stream_protocol2

#: largest |Gram - broadcast| allowed for unit vectors (float64; measured: 4e-15 at 8192-d)
TOLERANCE = 1e-13
SAMPLES = KITTI / "samples" / "00" / "velodyne"
METHODS = (("overlap-transformer", 256), ("bevplace", 8192))


def unit_rows(rng, n: int, width: int) -> np.ndarray:
    x = rng.normal(size=(n, width))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def reference(queries, database, metric="l2sq") -> np.ndarray:
    return pairwise_blocks(lambda q, r: vector_rows(q, r, metric), queries, database)[0]


def assert_same_rankings(fast: np.ndarray, ref: np.ndarray) -> None:
    """Same nearest neighbour per row, and the same order of every two entries of a row
    that are more than 2 x TOLERANCE apart."""
    assert np.array_equal(np.argmin(fast, axis=1), np.argmin(ref, axis=1))
    for f_row, r_row in zip(fast, ref, strict=True):
        order = np.argsort(r_row, kind="stable")
        gaps = np.diff(r_row[order]) > 2 * TOLERANCE
        assert (np.diff(f_row[order])[gaps] > 0).all()


@pytest.mark.parametrize("width", [32, 256, 8192])
@pytest.mark.parametrize("metric", ["l2sq", "l2", "cosine"])
def test_gram_equals_broadcast_reference_on_random_unit_vectors(width, metric):
    rng = np.random.default_rng(width)
    queries, database = unit_rows(rng, 37, width), unit_rows(rng, 301, width)
    database[:5] = queries[:5]  # identical pairs: distance 0 up to rounding, never negative
    database[5:10] = queries[5:10] + rng.normal(scale=1e-3, size=(5, width))  # near-duplicates
    fast, ref = gram_pairwise(queries, database, metric), reference(queries, database, metric)
    assert fast.shape == (37, 301) and fast.dtype == np.float64
    assert np.abs(fast - ref).max() <= (np.sqrt(TOLERANCE) if metric == "l2" else TOLERANCE)
    if metric != "cosine":
        assert (fast >= 0).all()
    assert_same_rankings(fast, ref)


@pytest.mark.parametrize(("name", "width"), METHODS)
def test_single_batched_and_pairwise_routes_are_bitwise_equal(name, width, monkeypatch):
    desc = get_descriptor(name)
    rng = np.random.default_rng(7)
    descs = unit_rows(rng, 90, width)
    full, yaws = desc.pairwise(descs, descs)
    assert np.isnan(yaws).all() and desc.symmetric
    single = np.array([[desc.distance(descs[i], descs[j])[0] for j in range(0, 90, 9)]
                       for i in range(0, 90, 13)])
    rows = np.array([desc.distances(descs[i], descs[::9])[0] for i in range(0, 90, 13)])
    assert np.array_equal(single, full[::13, ::9]) and np.array_equal(rows, full[::13, ::9])
    # arbitrary query subsets against arbitrary database subsets, as positive_values asks
    for _ in range(5):
        qi = np.sort(rng.choice(90, rng.integers(1, 20), replace=False))
        di = np.sort(rng.choice(90, rng.integers(1, 90), replace=False))
        assert np.array_equal(desc.pairwise(descs[qi], descs[di])[0], full[np.ix_(qi, di)])
    # and through small blocks of both sides (the memory bound never changes a value)
    monkeypatch.setattr(vector_common, "GRAM_QUERY_ROWS", 7)
    monkeypatch.setattr(vector_common, "GRAM_DATABASE_ROWS", 11)
    assert np.array_equal(desc.pairwise(descs, descs)[0], full)
    assert np.array_equal(full, full.T) or np.abs(full - full.T).max() <= TOLERANCE
    assert desc.distances(descs[0], descs[:0])[0].shape == (0,)


def test_gram_shapes_avoid_small_and_vector_products():
    for n_q, n_m, width in [(1, 1, 256), (1, 1, 8192), (8, 4541, 8192), (230, 1024, 256),
                            (3, 5, 3), (256, 1, 8192)]:
        rows, cols = gram_shape(n_q, n_m, width)
        assert rows >= n_q and cols >= n_m and rows % GRAM_TILE == 0 and cols % GRAM_TILE == 0
        assert rows * cols * width >= GRAM_MIN_MNK


def test_streamed_protocol2_needs_no_second_pass():
    """Protocol 2 computes the positives' distances first, in other blocks than the
    pass; a route whose values depended on the block would be caught there."""
    desc = get_descriptor("bevplace")
    rng = np.random.default_rng(3)
    descs = unit_rows(rng, 120, 8192)
    descs[60:] = descs[:60] + rng.normal(scale=0.02, size=(60, 8192)).astype(np.float32)
    pairs = np.array([(i, i + 60) for i in range(60)])
    affinity, curve, _ = stream_protocol2(desc, descs, pairs, 2 * len(pairs), pair_budget=4000)
    assert affinity.passes == 1
    full = desc.pairwise(descs, descs)[0].astype(np.float32)
    np.fill_diagonal(full, np.nan)
    assert np.array_equal(affinity.matrix, full, equal_nan=True)


# ---------------------------------------------------------------- real KITTI scans


def _perturbed_scans() -> list[np.ndarray]:
    files = sorted(SAMPLES.glob("*.bin")) if SAMPLES.is_dir() else []
    if not files:
        pytest.skip(f"no KITTI samples in {SAMPLES}")
    rng = np.random.default_rng(0)
    out = []
    for f in files:
        pts = np.fromfile(f, np.float32).reshape(-1, 4)[:, :3]
        for turn, shift in ((0.0, 0.0), (0.3, 0.5), (2.0, 2.5)):
            c, s = np.cos(turn), np.sin(turn)
            moved = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32).T
            moved[:, 0] += shift
            keep = rng.random(len(moved)) > 0.1
            out.append(np.ascontiguousarray(moved[keep], dtype=np.float32))
    return out


@pytest.fixture(scope="module")
def real_scans():
    return _perturbed_scans()


@pytest.mark.parametrize(("name", "width"), METHODS)
def test_gram_equals_reference_on_real_scan_descriptors(name, width, real_scans):
    desc = get_descriptor(name)
    vecs = np.stack([np.asarray(desc.vectors(desc.compute(s)) if hasattr(desc, "vectors")
                                else desc.compute(s)) for s in real_scans])
    assert vecs.shape == (len(real_scans), width)
    fast, ref = desc.pairwise(vecs, vecs)[0], reference(vecs, vecs)
    assert np.abs(fast - ref).max() <= TOLERANCE
    np.fill_diagonal(fast, np.inf)
    np.fill_diagonal(ref, np.inf)
    assert_same_rankings(fast, ref)


# ---------------------------------------------------------------- BEVPlace++ convolutions


@pytest.mark.parametrize(("rows", "c_in", "c_out"), [(2000, 3, 64), (5000, 64, 64),
                                                     (1351, 128, 128)])
def test_gemm_add_equals_product_then_add_bitwise(rows, c_in, c_out):
    rng = np.random.default_rng(rows)
    a = rng.standard_normal((rows, c_in)).astype(np.float32)
    b = rng.standard_normal((c_in, c_out)).astype(np.float32)
    start = rng.standard_normal((rows, c_out)).astype(np.float32)
    expected = start.copy()
    expected += a @ b
    got = start.copy()
    bev_network._gemm_add(got, a, b)
    assert np.array_equal(got, expected)
    strided = start.copy()  # a non-contiguous target takes the fallback, same numbers
    target = np.zeros((rows, 2 * c_out), np.float32)[:, ::2]
    target[...] = strided
    bev_network._gemm_add(target, a, b)
    assert np.array_equal(target, expected)
