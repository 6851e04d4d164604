"""Bring your own descriptors: external vectors or distance matrices evaluated like ours."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.external import (
    load_external,
    parse_external_spec,
)
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.protocol2 import protocols_1_and_2
from lidar_iris_eval.extract import external_database


def unit_rows(rng, n, d=192):
    x = rng.normal(size=(n, d))
    return x / np.linalg.norm(x, axis=1, keepdims=True) * np.sqrt(2)


def loop_positions(n):
    t = np.linspace(0, 2.2 * np.pi, n)
    return np.stack([15 * np.cos(t), np.zeros(n), 15 * np.sin(t)], 1)


def test_l2_vectors_give_m2dp_distances_bit_for_bit(tmp_path):
    rng = np.random.default_rng(0)
    descs = unit_rows(rng, 50)
    np.save(tmp_path / "m.npy", descs)
    ext = load_external("mine", tmp_path / "m.npy", 50)
    m2dp = get_descriptor("m2dp")
    d_ext, _ = ext.pairwise(descs[:7], descs)
    d_ref, _ = m2dp.pairwise(descs[:7], descs)
    assert np.array_equal(d_ext, d_ref)
    assert ext.distance(descs[3], descs[9])[0] == m2dp.distance(descs[3], descs[9])[0]
    assert np.array_equal(ext.distances(descs[3], descs)[0], m2dp.distances(descs[3], descs)[0])


def test_external_m2dp_vectors_reproduce_the_metrics_exactly(tmp_path):
    rng = np.random.default_rng(1)
    n = 80
    positions = loop_positions(n)
    descs = unit_rows(rng, n)
    descs[60:] = descs[:20] + rng.normal(scale=0.05, size=(20, 192))  # revisits look alike
    np.save(tmp_path / "m.npy", descs)
    ext = load_external("m2dp-file", tmp_path / "m.npy", n, "l2")
    db = external_database(ext)
    kw = dict(exclude=10, radius=4.0)
    ref1, ref2 = protocols_1_and_2(get_descriptor("m2dp"), descs, positions, **kw)
    got1, got2 = protocols_1_and_2(ext, db.descriptors, positions, **kw)
    assert got1.metrics == ref1.metrics and got2.metrics == ref2.metrics
    assert ref1.metrics["n_revisits"] > 0
    assert np.array_equal(got2.affinity.matrix, ref2.affinity.matrix, equal_nan=True)


def test_distance_matrix_is_looked_up(tmp_path):
    rng = np.random.default_rng(2)
    n = 30
    vecs = rng.normal(size=(n, 5))
    matrix = np.linalg.norm(vecs[:, None] - vecs[None], axis=-1)
    np.save(tmp_path / "d.npy", matrix)
    ext = load_external("dm", tmp_path / "d.npy", n)
    assert ext.params.kind == "matrix" and ext.symmetric
    idx = ext.stacked()
    d, yaw = ext.pairwise(idx[[3, 4]], idx[:10])
    np.testing.assert_array_equal(d, matrix[[3, 4]][:, :10])
    assert np.isnan(yaw).all()
    asym = matrix.copy()
    asym[0, 1] += 1
    np.save(tmp_path / "a.npy", asym)
    assert not load_external("dm", tmp_path / "a.npy", n).symmetric


@pytest.mark.parametrize("metric", ["cosine", "l1"])
def test_other_metrics_by_hand(tmp_path, metric):
    a = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    np.save(tmp_path / "v.npy", a)
    ext = load_external("v", tmp_path / "v.npy", 3, metric)
    d, _ = ext.pairwise(a, a)
    if metric == "cosine":
        expected = [[0, 1 - 1 / np.sqrt(2), 1], [1 - 1 / np.sqrt(2), 0, 1], [1, 1, 0]]
    else:
        expected = [[0, 1, 3], [1, 0, 4], [3, 4, 0]]
    np.testing.assert_allclose(d, expected, atol=1e-15)
    assert np.array_equal(d, d.T)


def test_bad_files_are_one_line_errors(tmp_path):
    np.save(tmp_path / "short.npy", np.zeros((9, 4)))
    with pytest.raises(LirisError, match="9 rows but the sequence has 10 scans"):
        load_external("x", tmp_path / "short.npy", 10)
    bad = np.ones((10, 4))
    bad[4, 2] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(LirisError, match="1 NaN/inf value.*row 4, column 2"):
        load_external("x", tmp_path / "nan.npy", 10)
    np.save(tmp_path / "three.npy", np.zeros((10, 2, 2)))
    with pytest.raises(LirisError, match="expected a numeric"):
        load_external("x", tmp_path / "three.npy", 10)
    with pytest.raises(LirisError, match="not found"):
        load_external("x", tmp_path / "none.npy", 10)
    np.save(tmp_path / "ok.npy", np.ones((10, 4)))
    with pytest.raises(LirisError, match="--external-metric"):
        load_external("x", tmp_path / "ok.npy", 10, "hamming")
    with pytest.raises(LirisError, match="NAME=PATH"):
        parse_external_spec("justapath.npy")
    assert parse_external_spec("net=a/b.npy")[0] == "net"
    with pytest.raises(LirisError, match="not computed"):
        load_external("x", tmp_path / "ok.npy", 10).compute(np.zeros((5, 3)))
