"""Issue 41: the GOSMatch front end's union-find numbers components as SciPy does."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lidar_iris_eval.descriptors.gosmatch import semantics


def scipy_components(n, pairs):
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])),
                       shape=(n, n))
    return connected_components(graph, directed=False)[1]


@pytest.mark.parametrize("seed", range(6))
def test_components_equal_scipys_numbering(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    m = int(rng.integers(0, 2 * n))
    pairs = np.sort(rng.integers(0, n, size=(m, 2)), axis=1).astype(np.int64)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    assert np.array_equal(semantics._components(n, pairs), scipy_components(n, pairs))


def test_objects_equal_those_of_scipy_components(monkeypatch):
    """Clustered objects of a labelled cloud with touching, separate and tiny clusters."""
    rng = np.random.default_rng(3)
    blobs = [rng.normal(c, 0.15, size=(k, 3)) for c, k in
             (((5, 0, 0), 60), ((5.6, 0, 0), 40), ((-8, 3, 0), 30), ((20, -4, 1), 5))]
    points = np.concatenate(blobs + [rng.uniform(-30, 30, size=(200, 3))])
    labels = np.concatenate([np.full(60, 10), np.full(40, 10), np.full(30, 71), np.full(5, 80),
                             rng.choice([10, 71, 80, 40], size=200)]).astype(np.uint32)
    settings = semantics.ClusterSettings()
    now = semantics.objects_from_labels(points, labels, settings)
    monkeypatch.setattr(semantics, "_components", scipy_components)
    before = semantics.objects_from_labels(points, labels, settings)
    assert len(now[0]) >= 2
    assert all(np.array_equal(a, b) for a, b in zip(now, before, strict=True))
