"""Scan Context's compiled paths equal the NumPy / batched ones bitwise.

The voxel grid's hash-table pass must give the sort-based centroids exactly,
and the one-pair comparison must give :meth:`ScanContext.pairwise`'s
distances and yaws exactly, for every search and divisor.
"""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors.scan_context import ScanContext, ScanContextParams
from lidar_iris_eval.descriptors.scan_context.descriptor import (
    voxel_downsample,
    voxel_downsample_numpy,
)
from lidar_iris_eval.descriptors.scan_context.voxel import voxel_centroids


def street_cloud(rng: np.random.Generator, n: int = 30_000) -> np.ndarray:
    """A ground plane, walls and poles around the origin, float32 (KITTI-like layout)."""
    ground = np.c_[rng.uniform(-70, 70, (n // 2, 2)), rng.normal(-1.73, 0.03, n // 2)]
    wall_x = rng.uniform(-60, 60, n // 4)
    side = np.where(rng.random(n // 4) < 0.5, -8.0, 9.5)
    walls = np.c_[wall_x, side, rng.uniform(-1.7, 6, n // 4)]
    m = n - len(ground) - len(walls)
    poles = np.c_[rng.integers(-30, 30, (m, 2)) * 2.0 + rng.normal(0, 0.1, (m, 2)),
                  rng.uniform(-1.7, 4, m)]
    return np.concatenate([ground, walls, poles]).astype(np.float32)


def test_voxel_hash_equals_sort_based_bitwise():
    rng = np.random.default_rng(3)
    for trial in range(4):
        pts = street_cloud(rng)
        if trial == 1:  # points straddling voxel faces and the origin
            pts = (rng.integers(-40, 40, (20_000, 3)) * 0.5).astype(np.float32)
            pts += rng.choice([0.0, 1e-7, -1e-7], pts.shape).astype(np.float32)
        if trial == 2:  # more voxels than the first hash table holds (it is retried larger)
            pts = rng.uniform(-100, 100, (60_000, 3)).astype(np.float32)
        got, ref = voxel_downsample(pts, 0.5), voxel_downsample_numpy(pts, 0.5)
        assert got.dtype == np.float32 and got.shape == ref.shape
        assert np.array_equal(got, ref)
    # the x-y reach filter is the one compute() applied before the NumPy route
    pts = street_cloud(rng)
    x, y = pts[:, 0].astype(np.float64), pts[:, 1].astype(np.float64)
    ref = voxel_downsample_numpy(pts[x * x + y * y <= 40.0 * 40.0], 0.5)
    assert np.array_equal(voxel_centroids(pts, 0.5, 40.0), ref)


def test_voxel_absurd_outlier_falls_back():
    pts = np.array([[0.1, 0.2, 0.3], [0.2, 0.1, 0.3], [3e30, 0.0, 0.0]], dtype=np.float32)
    assert voxel_centroids(pts, 0.5) is None
    out = voxel_downsample(pts, 0.5)
    assert np.array_equal(out, voxel_downsample_numpy(pts, 0.5))
    assert len(out) == 2
    np.testing.assert_allclose(out[0], [0.15, 0.15, 0.3], rtol=1e-6)


def _descriptor_set(sc: ScanContext, rng: np.random.Generator, clouds) -> np.ndarray:
    descs = []
    for pts in clouds:
        turn = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0],
                        [0, 0, 1]], dtype=np.float32)
        turned = pts @ rot.T
        descs += [sc.compute(pts), sc.compute(turned), sc.compute(turned[turned[:, 0] > 4])]
    descs.append(sc.compute(np.array([[500.0, 0, 0]], dtype=np.float32)))  # empty context
    below = street_cloud(rng, 3000)
    below[:, 2] -= 5.0  # negative bin values
    descs.append(sc.compute(below))
    return np.stack(descs)


@pytest.mark.parametrize("search", ["sector-key", "exhaustive"])
@pytest.mark.parametrize("divide_by", ["valid", "sectors"])
def test_single_pair_equals_pairwise_bitwise(search, divide_by):
    rng = np.random.default_rng(5)
    sc = ScanContext(ScanContextParams(search=search, divide_by=divide_by))
    descs = _descriptor_set(sc, rng, [street_cloud(rng, 8000) for _ in range(3)])
    dist, yaw = sc.pairwise(descs, descs)
    single = np.array([[sc.distance(a, b) for b in descs] for a in descs])
    np.testing.assert_array_equal(single[..., 0], dist)  # nan == nan here
    np.testing.assert_array_equal(single[..., 1], yaw)
    assert np.isnan(dist[-2]).all()  # the empty context matches nothing
    assert np.isfinite(dist[:-2, :-2]).all()


def test_real_scans_single_pair_and_voxels(kitti_dir):
    files = sorted((kitti_dir / "samples" / "00" / "velodyne").glob("*.bin"))
    if not files:
        pytest.skip("no shared KITTI scans")
    scans = [np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files]
    for pts in scans:
        assert np.array_equal(voxel_downsample(pts, 0.5), voxel_downsample_numpy(pts, 0.5))
    for search in ("sector-key", "exhaustive"):
        sc = ScanContext(ScanContextParams(search=search))
        descs = np.stack([sc.compute(p) for p in scans])
        dist, yaw = sc.pairwise(descs, descs)
        single = np.array([[sc.distance(a, b) for b in descs] for a in descs])
        np.testing.assert_array_equal(single[..., 0], dist)
        np.testing.assert_array_equal(single[..., 1], yaw)
