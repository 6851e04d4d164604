"""esm:segmatch: SegMatch's eigenvalue features inside ESM's segment pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm.descriptor import ESMParams
from lidar_iris_eval.descriptors.esm.segmatch import (
    FEATURES,
    eigenvalue_features,
    normalised_eigenvalues,
)
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate.pipeline import simulate_sequence


def _named(points):
    return dict(zip(FEATURES, eigenvalue_features(points), strict=True))


def _grid(*axes):
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))


def test_a_line():
    # covariance eigenvalues (var, 0, 0): normalised (1, 0, 0)
    x = np.linspace(-2.0, 2.0, 41)
    f = _named(np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1))
    expected = dict(linearity=1, planarity=0, scattering=0, omnivariance=0, anisotropy=1,
                    eigenentropy=0, change_of_curvature=0)
    assert f == pytest.approx(expected, abs=1e-9)


def test_a_square_plane():
    # a symmetric grid in a plane: eigenvalues (v, v, 0), normalised (1/2, 1/2, 0)
    a = np.linspace(-1.0, 1.0, 11)
    pts = np.c_[_grid(a, a), np.zeros(121)]
    f = _named(pts)
    expected = dict(linearity=0, planarity=1, scattering=0, omnivariance=0, anisotropy=1,
                    eigenentropy=np.log(2), change_of_curvature=0)
    assert f == pytest.approx(expected, abs=1e-9)


def test_an_isotropic_blob():
    # the 8 corners of a cube: covariance = I, normalised (1/3, 1/3, 1/3)
    pts = _grid([-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0])
    f = _named(pts)
    expected = dict(linearity=0, planarity=0, scattering=1, omnivariance=1 / 3, anisotropy=0,
                    eigenentropy=np.log(3), change_of_curvature=1 / 3)
    assert f == pytest.approx(expected, abs=1e-9)


def test_a_box_with_known_variances():
    # x in {-1, 1}, y in {-2, 2}, z in {-0.5, 0.5}: variances 1, 4, 0.25 (sum 5.25)
    pts = _grid([-1.0, 1.0], [-2.0, 2.0], [-0.5, 0.5])
    e1, e2, e3 = 4 / 5.25, 1 / 5.25, 0.25 / 5.25
    np.testing.assert_allclose(normalised_eigenvalues(pts), [e1, e2, e3], atol=1e-12)
    expected = dict(linearity=(e1 - e2) / e1, planarity=(e2 - e3) / e1, scattering=e3 / e1,
                    omnivariance=(e1 * e2 * e3) ** (1 / 3), anisotropy=(e1 - e3) / e1,
                    eigenentropy=-(e1 * np.log(e1) + e2 * np.log(e2) + e3 * np.log(e3)),
                    change_of_curvature=e3)
    assert _named(pts) == pytest.approx(expected, abs=1e-9)
    # a rotated, shifted, scaled copy has the same features
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    moved = 3.7 * pts @ q.T + [10.0, -4.0, 2.0]
    np.testing.assert_allclose(eigenvalue_features(moved), eigenvalue_features(pts), atol=1e-9)


def test_the_preset_only_changes_the_descriptor():
    esm = get_descriptor("esm", "segmatch")
    ref = get_descriptor("esm", "local-maps")
    assert esm.params.segment_descriptor == "segmatch"
    assert ref.params.segment_descriptor == "network"
    for name in ("source", "voxel", "radius", "min_points", "max_points", "knn", "consistency",
                 "min_consistent", "min_target", "dedup", "target_view", "frame_rule"):
        assert getattr(esm.params, name) == getattr(ref.params, name), name
    for name in ("input_filter", "ground_cell", "ground_clearance", "cluster_voxel"):
        assert getattr(esm.params, name) == getattr(ref.params, name), name
    assert esm.embedding_dim == 7
    with pytest.raises(LirisError, match="segment_descriptor"):
        ESMParams(segment_descriptor="fpfh")


def test_segmatch_runs_both_protocols_with_pose_errors(tmp_path, capsys):
    seq = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=140)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "-d", "esm:segmatch", "--protocol", "1",
                            "--protocol", "2", "--cache-dir", tmp_path / "cache", "--out", out,
                            "-q"], capsys)
    assert code == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    rows = {r["protocol"]: r for r in metrics["results"] if r["descriptor"] == "esm"}
    assert set(rows) == {1, 2}
    one = rows[1]
    assert one["preset"] == "segmatch" and one["segment_descriptor"] == "segmatch"
    assert one["pose_estimate"] == "full" and one["weights"] is None
    assert one["n_rte_m"] > 0 and np.isfinite(one["rte_m_median"])
    assert one["rte_m_median"] < 1.0 and one["rre_deg_median"] < 2.0
    assert rows[2]["n_pairs"] > 0
