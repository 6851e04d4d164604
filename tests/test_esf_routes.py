"""ESF's compiled normalisation and single-geometry sampling equal the routes they replaced.

Both are bitwise: the normalisation keeps NumPy's float64 centroid and forms
every other value in float64 in the same order; the sampler keeps each
batch's geometry instead of recomputing it for the accepted triplets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esf import descriptor as esf
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.sensors import simulate_scan

_HERE = Path(__file__).resolve()
_SHARED = next((p / "shared" for p in _HERE.parents[2:4] if (p / "shared" / "data").is_dir()),
               None)


def _clouds():
    cfg = resolve_config("tiny-mixed", dict(sensor="hdl64", azimuth_steps=1024))
    scen = build_scenario(cfg)
    rng = np.random.default_rng(2)
    out = [simulate_scan(scen.sensor, scen.world.ground, scen.primitives(f), scen.poses[f],
                         rng).points for f in (0, len(scen.poses) // 2)]
    if _SHARED is not None:
        folder = _SHARED / "data" / "kitti" / "samples" / "00" / "velodyne"
        out += [np.fromfile(f, np.float32).reshape(-1, 4)[:, :3].copy()
                for f in sorted(folder.glob("*.bin"))]
    out += [rng.normal(size=(2000, 3)) * scale for scale in (1e-3, 1.0, 1e4)]  # float64 too
    return out


@pytest.fixture(scope="module")
def clouds():
    return _clouds()


def test_normalise_equals_numpy_route(clouds):
    for cloud in clouds:
        assert np.array_equal(esf.normalise(cloud), esf.normalise_numpy(cloud))
    with pytest.raises(LirisError, match="not all identical"):
        esf.normalise(np.ones((5, 3), np.float32))


def test_descriptor_equals_previous_sampling_route(clouds, monkeypatch):
    desc = get_descriptor("esf")
    new = [desc.compute(c) for c in clouds[:4]]
    monkeypatch.setattr(esf, "sample_triangles", esf.sample_triangles_previous)
    monkeypatch.setattr(esf, "normalise", esf.normalise_numpy)
    old = [desc.compute(c) for c in clouds[:4]]
    for a, b in zip(new, old, strict=True):
        assert np.array_equal(a, b) and a.shape == (640,)


@pytest.mark.parametrize("seed", [0, 11])
def test_compiled_histogram_equals_numpy_route(clouds, seed):
    """The one-pass kernel (tracing + four histograms) is bitwise the NumPy route."""
    for cloud in clouds:
        pts = np.asarray(cloud)
        got = esf.esf_histogram(pts, 20000, np.random.default_rng(seed))
        want = esf.esf_histogram_numpy(pts, 20000, np.random.default_rng(seed))
        assert got.dtype == np.float32 and got.shape == (640,)
        assert np.array_equal(got, want)


def test_compiled_histogram_small_clouds():
    """Few points: many sides inside one voxel (count 1) and repeated corner voxels."""
    rng = np.random.default_rng(5)
    for n in (4, 12, 60):
        cloud = rng.uniform(-1, 1, size=(n, 3)).astype(np.float32)
        for samples in (1, 7, 500):
            got = esf.esf_histogram(cloud, samples, np.random.default_rng(n))
            want = esf.esf_histogram_numpy(cloud, samples, np.random.default_rng(n))
            assert np.array_equal(got, want)
            assert abs(float(got.sum(dtype=np.float64)) - 1.0) < 1e-5


def test_column_means_equal_numpy(clouds):
    """The compiled centroid is NumPy's ``astype(float64).mean(axis=0)`` bit for bit."""
    from lidar_iris_eval.descriptors.esf import kernels

    for cloud in clouds:
        pts = np.ascontiguousarray(cloud)
        assert np.array_equal(kernels.column_means(pts), pts.astype(np.float64).mean(axis=0))


def test_descriptor_equals_all_previous_routes(clouds, monkeypatch):
    """Every compiled step replaced by its reference at once: the same descriptors."""
    desc = get_descriptor("esf")
    new = [desc.compute(c) for c in clouds]
    monkeypatch.setattr(esf, "sample_triangles", esf.sample_triangles_previous)
    monkeypatch.setattr(esf, "normalise", esf.normalise_numpy)
    monkeypatch.setattr(esf, "esf_histogram", esf.esf_histogram_numpy)
    old = [desc.compute(c) for c in clouds]
    for a, b in zip(new, old, strict=True):
        assert np.array_equal(a, b)


def test_compiled_triangle_geometry_equals_numpy(clouds):
    """Sides, areas and angle bins of random triplets (degenerate ones included)."""
    rng = np.random.default_rng(3)
    for cloud in clouds:
        pts = esf.normalise(cloud)
        idx = rng.integers(0, len(pts), size=(5000, 3))
        idx[:50, 1] = idx[:50, 0]  # repeated corners: zero sides, NaN angles
        got = esf._triangle_geometry_compiled(pts, idx)
        want = esf._triangle_geometry(*(pts[idx[:, j]] for j in range(3)))
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype == np.float32 and g.shape == w.shape
            assert np.array_equal(g, w, equal_nan=True)
        assert np.isnan(got[2][:50]).any()
