"""M2DP's and ESF's compiled kernels equal their NumPy routes bitwise."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors.esf.descriptor import (
    GRID,
    normalise,
    occupancy,
    sample_triangles,
    trace_lines,
    trace_lines_numpy,
    voxel_coords,
)
from lidar_iris_eval.descriptors.m2dp.descriptor import (
    M2DPParams,
    pca_align,
    signature_matrix,
    signature_matrix_numpy,
)


def cloud(rng: np.random.Generator, n: int = 20_000) -> np.ndarray:
    """A street-like float32 cloud: ground, two walls and scattered clutter."""
    ground = np.c_[rng.uniform(-50, 50, (n // 2, 2)), rng.normal(-1.7, 0.05, n // 2)]
    walls = np.c_[rng.uniform(-50, 50, n // 4), np.where(rng.random(n // 4) < 0.5, -7.0, 8.0),
                  rng.uniform(-1.7, 5, n // 4)]
    clutter = rng.normal(0, 15, (n - len(ground) - len(walls), 3))
    return np.concatenate([ground, walls, clutter]).astype(np.float32)


@pytest.mark.parametrize("params", [M2DPParams(), M2DPParams(azimuths=3, elevations=5,
                                                             angular_bins=7, radial_bins=5)])
def test_m2dp_signature_equals_numpy_bitwise(params):
    rng = np.random.default_rng(11)
    for n in (5, 1500, 20_000):
        aligned = pca_align(cloud(rng, n) if n > 5 else rng.normal(size=(n, 3)))
        got = signature_matrix(aligned, params)
        np.testing.assert_array_equal(got, signature_matrix_numpy(aligned, params))
        assert got.shape == (params.azimuths * params.elevations,
                             params.angular_bins * params.radial_bins)
        np.testing.assert_allclose(got.sum(axis=1), 1.0)  # every point in one bin per plane


def test_esf_trace_equals_numpy_bitwise():
    rng = np.random.default_rng(12)
    pts = normalise(cloud(rng))
    vox = voxel_coords(pts)
    occupied = occupancy(vox)
    idx, *_ = sample_triangles(pts, 3000, np.random.default_rng(0))
    starts = vox[idx[:, [0, 0, 1]]].reshape(-1, 3)
    ends = vox[idx[:, [1, 2, 2]]].reshape(-1, 3)
    # plus random lines across the whole grid, single voxels and axis-parallel lines
    a = rng.integers(0, GRID, (2000, 3))
    b = rng.integers(0, GRID, (2000, 3))
    b[:100] = a[:100]
    b[100:200, 1:] = a[100:200, 1:]
    starts, ends = np.concatenate([starts, a]), np.concatenate([ends, b])
    inside, count = trace_lines(starts, ends, occupied)
    ref_inside, ref_count = trace_lines_numpy(starts, ends, occupied)
    np.testing.assert_array_equal(inside, ref_inside)
    np.testing.assert_array_equal(count, ref_count)
    assert (count[:len(idx) * 3] >= 1).all() and (count[-1900:-1800] == np.abs(
        a[100:200, 0] - b[100:200, 0]).clip(1)).all()


def test_real_scans_bitwise(kitti_dir):
    files = sorted((kitti_dir / "samples" / "00" / "velodyne").glob("*.bin"))
    if not files:
        pytest.skip("no shared KITTI scans")
    for f in files:
        pts = np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3]
        aligned = pca_align(pts.astype(np.float64))
        np.testing.assert_array_equal(signature_matrix(aligned, M2DPParams()),
                                      signature_matrix_numpy(aligned, M2DPParams()))
        unit = normalise(pts)
        vox = voxel_coords(unit)
        idx, *_ = sample_triangles(unit, 2000, np.random.default_rng(0))
        s, e = vox[idx[:, [0, 0, 1]]].reshape(-1, 3), vox[idx[:, [1, 2, 2]]].reshape(-1, 3)
        for got, ref in zip(trace_lines(s, e, occupancy(vox)),
                            trace_lines_numpy(s, e, occupancy(vox)), strict=True):
            np.testing.assert_array_equal(got, ref)


def test_esf_voxel_coords_equal_numpy():
    from lidar_iris_eval.descriptors.esf.descriptor import voxel_coords_numpy

    rng = np.random.default_rng(13)
    pts = normalise(cloud(rng))
    edge = np.array([[-0.0, 0.0, 32.0], [-32.0, 31.5, -31.99], [np.float32(32.000004), -1, 1]],
                    dtype=np.float32)  # faces, the grid limits and just beyond them
    for p in (pts, edge, rng.normal(0, 40, (5000, 3)).astype(np.float32)):
        got = voxel_coords(p)
        np.testing.assert_array_equal(got, voxel_coords_numpy(p))
        assert got.min() >= 0 and got.max() <= GRID - 1
    np.testing.assert_array_equal(voxel_coords(edge), [[31, 31, 63], [0, 63, 0], [63, 31, 32]])
