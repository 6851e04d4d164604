"""Issue 40: KISS-ICP's max_range comes from the data (hand-computed cases; no kiss-icp needed)."""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.localmaps.odometry import (
    RANGE_CAP_M,
    RANGE_FLOOR_M,
    RANGE_SAMPLE_SCANS,
    data_max_range,
)


def shell_scans(radii_per_scan: list[np.ndarray]) -> list[np.ndarray]:
    """Scans whose points lie at exactly the given ranges, in random directions."""
    rng = np.random.default_rng(3)
    scans = []
    for radii in radii_per_scan:
        d = rng.normal(size=(len(radii), 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        scans.append(np.c_[d * radii[:, None], np.zeros(len(radii))].astype(np.float32))
    return scans


def test_short_range_sequence_gets_its_99th_percentile():
    # 990 returns at 20 m and 10 at 150 m per scan: the 99th percentile lies at 20 m
    # (numpy's linear interpolation reaches index 989.01, between 20 and 150: 21.3 m)
    radii = np.r_[np.full(990, 20.0), np.full(10, 150.0)]
    scans = shell_scans([radii] * 30)
    expected = np.ceil(np.percentile(np.tile(radii, RANGE_SAMPLE_SCANS), 99.0))
    assert data_max_range(scans) == expected == 22.0


def test_range_is_clamped_to_floor_and_cap():
    assert data_max_range(shell_scans([np.full(500, 3.0)] * 4)) == RANGE_FLOOR_M
    assert data_max_range(shell_scans([np.full(500, 300.0)] * 4)) == RANGE_CAP_M


def test_only_spread_scans_are_read_and_nan_is_ignored():
    scans = shell_scans([np.full(100, 40.0)] * 50)
    scans[0][:10, :3] = np.nan
    read = []

    class Seq(list):
        def __getitem__(self, i):
            read.append(i)
            return list.__getitem__(self, i)

    assert data_max_range(Seq(scans)) == 40.0
    assert len(read) == RANGE_SAMPLE_SCANS and read[0] == 0 and read[-1] == 49
