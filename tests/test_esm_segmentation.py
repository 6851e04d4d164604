"""ESM segmentation: hand-made scenes with known segments, and the real KITTI scans."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors.esm.segmentation import (
    SegmentParams,
    euclidean_clusters,
    grid_clusters,
    normalise,
    segment_scan,
    voxelise,
)


def _box(rng, centre, size, n):
    return np.asarray(centre) + (rng.random((n, 3)) - 0.5) * np.asarray(size)


def _scene(rng):
    """Ground at z=-1.73, a 'car' and a 'pole' (kept) and a 30-point speck (dropped)."""
    g = np.c_[rng.uniform(-30, 30, (20000, 2)), np.full(20000, -1.73)]
    car = _box(rng, (8.0, 3.0, -1.0), (4.0, 1.8, 1.4), 6000)
    pole = _box(rng, (-5.0, -6.0, 1.0), (0.3, 0.3, 6.0), 3000)
    speck = _box(rng, (0.0, 12.0, 0.0), (0.2, 0.2, 0.2), 30)
    far = _box(rng, (60.0, 0.0, 0.0), (3.0, 3.0, 3.0), 5000)  # beyond 50 m
    return np.concatenate([g, car, pole, speck, far])


def test_voxelise_one_centroid_per_cell():
    pts = np.array([[0.01, 0.01, 0.01], [0.09, 0.09, 0.09], [0.15, 0.0, 0.0]])
    vox, inv = voxelise(pts, 0.1)
    assert len(vox) == 2
    assert np.allclose(vox[inv[0]], [0.05, 0.05, 0.05])
    assert inv[0] == inv[1] != inv[2]


def test_euclidean_clusters_join_within_radius_only():
    line = np.c_[np.arange(10) * 0.15, np.zeros(10), np.zeros(10)]
    comp = euclidean_clusters(np.concatenate([line, line + [1.65, 0, 0]]), 0.2)
    # the two lines are 0.3 m apart at their closest points: two components
    assert len(np.unique(comp)) == 2 and len(np.unique(comp[:10])) == 1


def test_geometric_scene_gives_the_two_objects():
    rng = np.random.default_rng(0)
    segs = segment_scan(_scene(rng))
    assert len(segs) == 2
    cents = segs.centroids[np.argsort(segs.centroids[:, 0])]
    # the car's lower part (z <= -1.0 m) is removed with the ground by the height rule
    assert np.allclose(cents[0][:2], [-5.0, -6.0], atol=0.1)
    assert np.allclose(cents[1][:2], [8.0, 3.0], atol=0.2)
    assert cents[1][2] > -1.0
    assert segs.points.shape == (2, 256, 3)
    assert np.all((segs.sizes >= 100) & (segs.sizes <= 15000))


def test_labels_replace_the_height_rule():
    rng = np.random.default_rng(1)
    pts = _scene(rng)
    labels = np.full(len(pts), 10, np.uint32)
    labels[:20000] = 40  # road
    segs = segment_scan(pts, labels)
    car = segs.centroids[np.argmax(segs.centroids[:, 0])]
    assert abs(car[2] - (-1.0)) < 0.1  # the whole car kept: centroid at its middle


def test_normalisation_zero_mean_unit_rms_and_seeded():
    rng = np.random.default_rng(2)
    segs = segment_scan(_scene(rng))
    p = segs.points.astype(np.float64)
    assert np.allclose(p.mean(axis=1), 0, atol=1e-5)
    assert np.allclose(np.sqrt((p**2).sum(2).mean(1)), 1.0, atol=1e-5)
    again = segment_scan(_scene(np.random.default_rng(2)))
    assert np.array_equal(segs.points, again.points)
    other = segment_scan(_scene(np.random.default_rng(2)), params=SegmentParams(seed=5))
    assert not np.array_equal(segs.points, other.points)


def test_normalise_keeps_the_aspect_ratio():
    pts = np.c_[np.linspace(-5, 5, 101), np.zeros(101), np.linspace(-1, 1, 101)]
    out, scale = normalise(pts)
    assert np.isclose(np.ptp(out[:, 0]) / np.ptp(out[:, 2]), 5.0)
    assert np.isclose(scale, np.sqrt((pts**2).sum(1).mean()))


def test_real_kitti_scans_segment_within_limits(kitti_dir):
    files = sorted((kitti_dir / "samples" / "00" / "velodyne").glob("*.bin"))
    if not files:
        pytest.skip("no KITTI sample scans")
    for f in files:
        pts = np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3]
        segs = segment_scan(pts)
        # a real KITTI scan has tens of segments (cars, trunks, facades pieces)
        assert 20 <= len(segs) <= 60
        assert np.all(np.hypot(segs.centroids[:, 0], segs.centroids[:, 1]) <= 50)
        members = np.concatenate(segs.members)
        assert len(np.unique(members)) == len(members)
        assert np.all(pts[members, 2] > -1.0)


def test_fixed_normalisation_keeps_size():
    rng = np.random.default_rng(3)
    small = rng.normal(size=(300, 3)) * 0.5
    big = small * 3.0
    a, rms_a = normalise(small, 0.9)
    b, rms_b = normalise(big, 0.9)
    assert np.isclose(rms_b / rms_a, 3.0)
    assert np.allclose(b, 3.0 * a, atol=1e-5)  # size survives; per-segment RMS would equalise
    assert np.isclose(np.sqrt((a.astype(float) ** 2).sum(1).mean()), rms_a / 0.9, rtol=1e-5)


def test_yaw_alignment_removes_the_heading():
    from lidar_iris_eval.descriptors.esm.segmentation import yaw_align

    rng = np.random.default_rng(3)
    # an asymmetric L-shaped blob: 3 m along x, 1 m along y, a heavier end at +x
    pts = np.concatenate([rng.uniform([0, 0, 0], [3, 1, 1.5], (300, 3)),
                          rng.uniform([2.4, 1, 0], [3, 2, 1.5], (80, 3))])
    ref, _ = normalise(pts, 0.9, align_yaw=True)
    for yaw in (0.4, 1.9, -2.7, np.pi):
        c, s = np.cos(yaw), np.sin(yaw)
        turned = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [5.0, -2.0, 0.3]
        out, _ = normalise(turned, 0.9, align_yaw=True)
        assert np.allclose(out, ref, atol=1e-5)
    # the major axis ends on x (largest spread) and the longer tail on +x
    assert ref[:, 0].var() > ref[:, 1].var() and (ref[:, 0] ** 3).sum() > 0
    # heights untouched, and a rotation only: distances to the centroid kept
    centred = pts - pts.mean(axis=0)
    assert np.allclose(yaw_align(centred)[:, 2], centred[:, 2])
    assert np.allclose(np.linalg.norm(yaw_align(centred), axis=1),
                       np.linalg.norm(centred, axis=1))


def test_euclidean_clusters_are_scipys_components_and_numbering():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    # hand case: points 0-1-3 chained, 2 alone, 4-5 a pair: numbered by smallest index
    pts = np.array([[0, 0, 0], [0.15, 0, 0], [5, 0, 0], [0.3, 0, 0], [9, 0, 0], [9.1, 0, 0]])
    assert euclidean_clusters(pts, 0.2).tolist() == [0, 0, 1, 0, 2, 2]
    rng = np.random.default_rng(4)
    for _ in range(50):  # the oracle: scipy's sparse-graph components, same labels
        n = int(rng.integers(1, 300))
        p = rng.uniform(0, rng.uniform(0.5, 8.0), (n, 3))
        pairs = cKDTree(p).query_pairs(0.4, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        assert np.array_equal(euclidean_clusters(p, 0.4),
                              connected_components(graph, directed=False)[1])


def _in_cells(p: np.ndarray, cell: float):
    """Points sorted as local_map_clusters gives its coarse centroids: by cell, (i, j, k)."""
    absolute = np.floor(p / cell).astype(np.int64)
    origin = absolute.min(0)
    cells = absolute - origin
    order = np.lexsort((cells[:, 2], cells[:, 1], cells[:, 0]))
    return p[order], cells[order], origin


@pytest.mark.parametrize("radius, cell", [(0.4, 0.2), (0.3, 0.2), (0.2, 0.1), (0.5, 0.25)])
def test_grid_clusters_equal_the_kdtree_clusters(radius, cell):
    rng = np.random.default_rng(7)
    for trial in range(30):
        n = int(rng.integers(1, 1500))
        p = rng.uniform(-3, rng.uniform(-2, 9.0), (n, 3)) + rng.uniform(-200, 200, 3)
        if trial % 3 == 0:  # cell centres of a lattice: many pairs at exactly the radius
            p = (np.floor(p / cell) + 0.5) * cell
            p = np.unique(p, axis=0)
            rng.shuffle(p)
        p, cells, origin = _in_cells(p, cell)
        assert np.array_equal(grid_clusters(p, cells, cell, radius, origin),
                              euclidean_clusters(p, radius))
    assert len(grid_clusters(np.zeros((0, 3)), np.zeros((0, 3), np.int64), cell, radius,
                             np.zeros(3, np.int64))) == 0


def test_grid_clusters_fall_back_on_a_huge_sparse_grid(monkeypatch):
    from lidar_iris_eval.descriptors.esm import segmentation

    p, cells, origin = _in_cells(np.array([[0.0, 0, 0], [0.1, 0, 0], [5e4, 5e4, 0]]), 0.2)
    calls = []
    monkeypatch.setattr(segmentation, "euclidean_clusters",
                        lambda *a: calls.append(a) or euclidean_clusters(*a))
    assert segmentation.grid_clusters(p, cells, 0.2, 0.4, origin).tolist() == [0, 0, 1]
    assert len(calls) == 1
