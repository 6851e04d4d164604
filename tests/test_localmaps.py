"""Local maps: voxel counts, cropping, the window rule, exactness, chunk independence."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.localmaps import (
    INPUT_FILTERS,
    InputFilter,
    LocalMap,
    LocalMapSettings,
    VoxelWindow,
    local_maps,
)
from lidar_iris_eval.localmaps.grid import decode, encode


def pose_at(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def test_encode_decode_round_trip():
    ijk = np.array([[0, 0, 0], [-5, 7, -1], [1000, -2000, 30]])
    assert np.array_equal(decode(encode(ijk)), ijk)


def test_voxel_counts_and_exact_centroids():
    g = VoxelWindow(window=5, voxel=0.1, radius=50.0)
    # two points in voxel [0, 0.1)^3, one in voxel x in [0.1, 0.2)
    g.add(0, np.array([[0.01, 0.02, 0.03], [0.05, 0.06, 0.07], [0.15, 0.05, 0.05]]))
    assert len(g) == 2
    assert g.counts.tolist() == [2, 1]
    np.testing.assert_array_equal(g.centroids(), [[0.03, 0.04, 0.05], [0.15, 0.05, 0.05]])
    # a second scan feeds the first voxel again: 3 points, and a new voxel
    g.add(1, np.array([[0.09, 0.09, 0.09], [-0.05, 0.0, 0.0]]))
    assert len(g) == 3 and sorted(g.counts.tolist()) == [1, 1, 3]
    # dropping scan 0 leaves exactly scan 1's voxels and centroids
    g.window = 1
    g.drop_before(1)
    assert sorted(g.counts.tolist()) == [1, 1]
    assert sorted(map(tuple, g.centroids().tolist())) == [(-0.05, 0.0, 0.0), (0.09, 0.09, 0.09)]


def test_crop_by_voxel_centre_and_for_good():
    g = VoxelWindow(window=10, voxel=0.1, radius=50.0)
    # voxel centres 49.95 (kept) and 50.05 (cropped) from the origin
    g.add(0, np.array([[49.91, 0.0, 0.0], [50.01, 0.0, 0.0], [-10.0, 0.0, 0.0]]))
    g.crop(np.array([0.0, 0.0]))
    assert len(g) == 2
    # moving to x = 45: the point at x = -10 is 55 m away and goes, for good
    g.crop(np.array([45.0, 0.0]))
    assert len(g) == 1 and g.stored_voxels() == 1
    g.crop(np.array([0.0, 0.0]))
    assert len(g) == 1  # cropped voxels never come back without a new scan


def test_window_rule_on_hand_scans():
    lm = LocalMap(window=3, input_filter=InputFilter(every=1, min_z=-1.0, max_range=50.0))
    for i in range(6):  # scan i: one point at x = i metres (sensor at the origin)
        lm.update(i, np.array([[float(i), 0.0, 0.0]]), np.eye(4))
        f = lm.frame(i, np.eye(4))
        held = sorted(np.round(f.points[:, 0]).astype(int).tolist())
        assert held == list(range(max(0, i - 2), i + 1))
        assert f.frames == tuple(range(max(0, i - 2), i + 1))
        assert f.last_seen.min() > i - 3


def test_input_filters():
    pts = np.array([[1.0, 0, 0], [1.0, 0, -1.5], [60.0, 0, 0], [30.0, 40.0, 0.5],
                    [np.nan, 0, 0], [2.0, 0, -1.0], [3, 0, 0], [4, 0, 0], [5, 0, 0],
                    [6, 0, 0]])
    kept = INPUT_FILTERS["all"].apply(pts)
    # dropped: z < -1 (row 1), 60 m (row 2), NaN (row 4); 30,40 is exactly 50 m: kept
    assert len(kept) == 7
    every9 = INPUT_FILTERS["segmap"].apply(pts)
    assert every9.tolist() == [[1.0, 0.0, 0.0], [6.0, 0.0, 0.0]]  # rows 0 and 9


def test_settings_errors():
    with pytest.raises(LirisError, match="window"):
        LocalMapSettings(window=0)
    with pytest.raises(LirisError, match="input_filter"):
        LocalMapSettings(window=3, input_filter="nope")
    with pytest.raises(LirisError, match="odometry"):
        LocalMapSettings(window=3, odometry="wheel")


def _random_scans(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    scans = [rng.uniform(-30, 30, (400, 3)) * [1, 1, 0.05] for _ in range(n)]
    poses = np.stack([pose_at(2.0 * i, 0.5 * i, 3.0 * i) for i in range(n)])
    return scans, poses


def test_map_of_a_frame_does_not_depend_on_where_building_started():
    scans, poses = _random_scans(12)
    s = LocalMapSettings(window=4, input_filter="all", radius=25.0)
    full = {m.frame: m for m, _ in local_maps(lambda j: scans[j], poses, s, 0, 12)}
    part = {m.frame: m for m, _ in local_maps(lambda j: scans[j], poses, s, 7, 12)}
    for i in range(7, 12):
        np.testing.assert_array_equal(full[i].points, part[i].points)
        np.testing.assert_array_equal(full[i].counts, part[i].counts)
        assert full[i].frames == part[i].frames == tuple(range(i - 3, i + 1))


def test_local_points_are_in_the_frame_of_the_pose():
    lm = LocalMap(window=2, input_filter=InputFilter(every=1))
    P = pose_at(10.0, 5.0, 90.0)
    lm.update(0, np.array([[1.05, 0.05, 0.05]]), P)
    f = lm.frame(0, P)
    np.testing.assert_allclose(f.points, [[9.95, 6.05, 0.05]], atol=1e-9)
    np.testing.assert_allclose(f.local_points(), [[1.05, 0.05, 0.05]], atol=1e-9)


def test_memory_is_bounded_by_the_cylinder():
    # a straight 400 m drive with a 1000-frame window: only voxels within 20 m stay
    s = LocalMapSettings(window=1000, input_filter="all", radius=20.0)
    scans = [np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]) for _ in range(200)]
    poses = np.stack([pose_at(2.0 * i) for i in range(200)])
    sizes = [len(m) for m, _ in local_maps(lambda j: scans[j], poses, s, 0, 200)]
    assert max(sizes) <= 2 * 21  # two points per scan, scans 2 m apart, 20 m behind


def _naive_window(steps, window: int, voxel_mm: int, radius: float):
    """The grid's state rebuilt from raw points after every step (no incremental bookkeeping):
    each stored scan keeps its millimetre points; a crop removes the points of far voxels."""
    stored: list[tuple[int, np.ndarray]] = []
    out = []
    for frame, pts, centre in steps:
        stored.append((frame, np.rint(pts * 1000.0).astype(np.int64)))
        stored = [(f, mm) for f, mm in stored if f > frame - window]
        kept = []
        for f, mm in stored:
            ij = np.floor_divide(mm, voxel_mm)[:, :2]
            c = (ij + 0.5) * (voxel_mm / 1000.0)
            kept.append((f, mm[((c - centre) ** 2).sum(1) <= radius**2]))
        stored = kept
        allmm = np.concatenate([mm for _, mm in stored])
        frames = np.concatenate([np.full(len(mm), f) for f, mm in stored])
        keys = encode(np.floor_divide(allmm, voxel_mm))
        uniq, inv = np.unique(keys, return_inverse=True)
        sums = np.stack([np.bincount(inv, allmm[:, a].astype(float)) for a in range(3)], 1)
        last = np.zeros(len(uniq), np.int64)
        np.maximum.at(last, inv, frames)
        out.append((uniq, np.bincount(inv), sums.astype(np.int64), last))
    return out


@pytest.mark.parametrize("compact", [True, False])
def test_incremental_grid_equals_a_rebuild_from_raw_points(compact):
    # scans overlapping in many voxels, a moving crop centre that cuts voxels of old scans
    # (some of which later scans feed again), a window that drops scans
    rng = np.random.default_rng(3)
    steps = []
    for i in range(14):
        centre = np.array([0.7 * i, -0.3 * i])
        pts = centre + rng.uniform(-6, 6, (300, 2))
        pts = np.column_stack([pts, rng.uniform(-0.5, 0.5, 300)])
        steps.append((i, np.round(pts, 2), centre))
    g = VoxelWindow(window=4, voxel=0.5, radius=5.0)
    cropped_some = False
    for (frame, pts, centre), (keys, counts, sums, last) in zip(
            steps, _naive_window(steps, 4, 500, 5.0), strict=True):
        g.add(frame, pts)
        g.drop_before(frame, compact=compact)  # False: the emptied voxels go at the crop
        before = len(g)
        g.crop(centre)
        cropped_some |= len(g) < before
        assert np.array_equal(g.keys, keys) and np.array_equal(g.counts, counts)
        assert np.array_equal(g.sums, sums) and np.array_equal(g.last, last)
        if frame % 3 == 0:  # stored_voxels compacts the stored scans: only now and then
            assert g.stored_voxels() == sum(len(c.keys) for c in g.scans)
            assert all(np.isin(c.keys, g.keys).all() for c in g.scans)
    assert cropped_some


def test_compiled_crop_test_equals_the_numpy_expression():
    from lidar_iris_eval.localmaps.grid import _BITS, _MASK, _OFFSET, VoxelWindow

    rng = np.random.default_rng(3)
    g = VoxelWindow(5, 0.1, 7.3)
    keys = encode(rng.integers(-120, 120, (20000, 3)))
    keys = np.concatenate([keys, encode(np.array([[73, 0, 0], [-74, 0, 5], [0, 72, 1]]))])
    for centre in (np.array([0.0, 0.0]), np.array([0.35, -1.05])):
        k = keys
        dx = (((k >> (2 * _BITS)) & _MASK) - _OFFSET + 0.5) * 0.1 - centre[0]
        dy = (((k >> _BITS) & _MASK) - _OFFSET + 0.5) * 0.1 - centre[1]
        ref = dx * dx + dy * dy <= 7.3**2
        assert 0 < ref.sum() < len(ref)
        assert np.array_equal(g._inside(keys, centre), ref)
