"""The network's neighbour search (a compiled sweep, the k-d tree on ties) against the
k-d tree it replaced: the same neighbours up to equal points, the same output bits."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors.esm import network


def _segments(n: int, seed: int = 0) -> np.ndarray:
    """Resampled segments as the network gets them: 256 points drawn from 30-600 points
    (so many repeats), a third on a 0.25 lattice (distinct points at equal distances)."""
    rng = np.random.default_rng(seed)
    out = []
    for s in range(n):
        m = int(rng.integers(30, 600))
        base = rng.standard_normal((m, 3)).astype(np.float32)
        if s % 3 == 0:
            base = np.round(base * 4) / 4
        out.append(base[rng.choice(m, 256, replace=m < 256)])
    return np.stack(out).astype(np.float32)


def test_sweep_gives_the_stable_sort_order_and_flags_ties_between_distinct_points():
    arch = network.Arch()
    pts = np.ascontiguousarray(_segments(24, seed=1), np.float64)
    prev = pts.shape[1]
    flagged = 0
    for r, k, d in zip(arch.reps, arch.k, arch.dilation, strict=True):
        idx = np.empty((len(pts), r, k), np.int64)
        amb = np.zeros(len(pts), bool)
        network._brute_layer(pts, pts.view(np.uint64), prev, r, k, d, idx, amb)
        diff = pts[:, :r, None, :] - pts[:, None, :prev, :]
        d2 = (diff[..., 0] ** 2 + diff[..., 1] ** 2) + diff[..., 2] ** 2
        order = np.argsort(d2, axis=2, kind="stable")
        assert np.array_equal(idx, order[:, :, :k * d:d])
        # a segment is flagged iff two consecutive neighbours (up to the cut) tie but differ
        near = np.take_along_axis(d2, order[:, :, :k * d + 1], 2)
        pts_near = pts[np.arange(len(pts))[:, None, None], order[:, :, :k * d + 1]]
        tie = (np.diff(near, axis=2) <= network.TIE_RTOL * near[:, :, 1:]) & np.any(
            pts_near[:, :, 1:] != pts_near[:, :, :-1], axis=3)
        assert np.array_equal(amb, tie.any(axis=(1, 2)))
        flagged += int(amb.sum())
        prev = r
    assert flagged > 0  # the lattice segments exercise the fallback


@pytest.mark.parametrize("seed", [0, 1])
def test_neighbours_and_output_bits_equal_the_kdtree_route(seed):
    path = network.resolve_weights("esm_localmap_simreal_weights.npz")
    if not path.is_file():
        pytest.skip(f"no {path.name}")
    w, arch = network.load_weights(path)
    pts = _segments(30, seed)
    new, old = network.neighbour_index(pts, arch), network.neighbour_index_kdtree(pts, arch)
    s = np.arange(len(pts))[:, None, None]
    for a, b in zip(new, old, strict=True):  # indices may differ only between equal points
        assert np.array_equal(pts[s, a], pts[s, b])
    assert any(not np.array_equal(a, b) for a, b in zip(new, old, strict=True))
    f_new = network.per_point_features(w, arch, pts, new)
    f_old = network.per_point_features(w, arch, pts, old)
    assert f_new.tobytes() == f_old.tobytes()
