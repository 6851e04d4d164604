"""The peers' presets of issue 25: each reproduces a count computed here with plain loops."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import KITTI

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.conventions import (
    BEVPLACE_SPLITS,
    CROSS_SESSION_PRESETS,
    PRESETS,
    convention_counts,
    get_convention,
)
from lidar_iris_eval.evaluation.cross_session import cross_positives


def _trajectory(n: int, seed: int = 0) -> np.ndarray:
    """Camera-like positions (x, height, z) of a drive that loops a 60 m circle 3 times."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6 * np.pi, n)
    r = 60 + rng.normal(0, 1.5, n)
    return np.c_[r * np.cos(t), rng.normal(0, 0.3, n), r * np.sin(t)]


def _lidar(cam: np.ndarray) -> np.ndarray:
    """The same points as LiDAR-frame positions (x, y, z up), for presets on LiDAR poses."""
    return np.c_[cam[:, 2], -cam[:, 0], -cam[:, 1]]


def test_wild_places_intra_counts_revisits_like_its_script():
    # Wild-Places intra-sequence.py, written out: skip until 300 s passed; database up to
    # and including the first scan later than t_q - 300 s; revisit if any is < 5 m planar
    n = 2400
    cam = _trajectory(n, 1)
    xyz = _lidar(cam)
    times = np.arange(n) * 0.5  # 2 Hz submaps: 1200 s
    revisits = queries = 0
    for q in range(n):
        if times[q] - times[0] - 300 < 0:
            continue
        tt = next(k for k, t in enumerate(times) if t > times[q] - 300)
        tt = min(tt, q - 1)  # never the query itself
        queries += 1
        d = np.linalg.norm(xyz[: tt + 1, :2] - xyz[q, :2], axis=1)
        revisits += bool(np.any(d < 5))
    got = convention_counts(xyz, PRESETS["wild-places-intra"], times)
    assert (got["queries"], got["revisit_queries"]) == (queries, revisits)
    assert revisits > 100


def test_contour_context_counts_revisits_like_its_script():
    n = 900
    xyz = _lidar(_trajectory(n, 2))
    # pr_mpe.py: gt_positive[i] = any j < i - 150 within 5 m (3-D); strict here (see preset)
    expected = sum(bool(np.any(np.linalg.norm(xyz[: max(i - 150, 0)] - xyz[i], axis=1) < 5))
                   for i in range(n))
    got = convention_counts(xyz, PRESETS["contour-context"])
    assert got["revisit_queries"] == expected > 100
    assert got["queries"] == n - 151


@pytest.mark.parametrize("seq", sorted(BEVPLACE_SPLITS))
def test_bevplace_counts_queries_with_a_positive_like_its_script(seq):
    split = BEVPLACE_SPLITS[seq]
    n = split + 900
    cam = _trajectory(n, 3)
    # evaluateResults: queries from split + 200, positives among the first split frames,
    # squared 3-D distance of pose columns 3, 7, 11 < 25
    expected = 0
    for q in range(split + 200, n):
        expected += bool(np.any(np.sum((cam[:split] - cam[q]) ** 2, axis=1) < 5 ** 2))
    got = convention_counts(cam, PRESETS[f"bevplace-{seq}"])
    assert got["queries"] == n - split - 200
    assert got["revisit_queries"] == expected > 50


def _kitti_camera_positions(seq: str) -> np.ndarray:
    path = KITTI / "poses" / f"{seq}.txt"
    if not path.is_file():
        pytest.skip(f"../shared KITTI poses {seq} not available")
    return np.loadtxt(path)[:, [3, 7, 11]]


def test_bevplace_on_real_kitti00_poses():
    cam = _kitti_camera_positions("00")
    split = BEVPLACE_SPLITS["00"]
    q = np.arange(split + 200, len(cam))
    d2 = ((cam[q, None, :] - cam[None, :split, :]) ** 2).sum(axis=2)
    expected = int(np.count_nonzero((d2 < 25).any(axis=1)))
    got = convention_counts(cam, PRESETS["bevplace-00"])
    assert got["revisit_queries"] == expected


@pytest.mark.parametrize("name, radius", [("wild-places-inter", 3.0), ("pointnetvlad", 25.0)])
def test_cross_session_presets_count_positives_like_a_query_radius(name, radius):
    conv = CROSS_SESSION_PRESETS[name]
    a = _lidar(_trajectory(500, 4))
    b = _lidar(_trajectory(400, 5))
    # sklearn's KDTree.query_radius on (easting, northing): planar, inclusive
    expected = [np.nonzero(np.hypot(*(b[:, :2] - p[:2]).T) <= radius)[0] for p in a]
    got = cross_positives(a[:, :2], b[:, :2], conv.radius, conv.inclusive_radius)
    assert conv.distance == "planar" and conv.radius == radius
    assert all(np.array_equal(x, y) for x, y in zip(got, expected, strict=True))
    assert sum(len(x) > 0 for x in got) > 100


def test_cross_session_presets_need_two_sessions():
    with pytest.raises(LirisError, match="--query and --database"):
        get_convention("wild-places-inter")
    assert get_convention("pointnetvlad", cross_session=True).radius == 25.0
