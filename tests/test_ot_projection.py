"""OverlapTransformer's projection gives the same pixels on every machine.

NumPy's float32 ``arctan2``/``arcsin`` differ by an ulp between CPUs, and a scan
whose azimuths sit on the 900 column edges (as simulated scans do) then lands
points in other columns. The projection takes the angles in float64, rounded to
float32; the expectation here is the same rule computed point by point with
Python's ``math`` (the C library, not NumPy's kernels).
"""

from __future__ import annotations

import math

import numpy as np

from lidar_iris_eval.descriptors.overlap_transformer.projection import pixel_coordinates


def _edge_scan() -> np.ndarray:
    """Rings at 2048 and 900 azimuth steps (the second on every column edge)."""
    rng = np.random.default_rng(3)
    rows = []
    for steps in (2048, 900):
        az = np.arange(steps) * (2 * np.pi / steps)
        for elev in np.radians(np.linspace(2.0, -24.0, 16)):
            r = rng.uniform(3.0, 70.0, steps)
            rows.append(np.c_[r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                              r * np.sin(elev)])
    return np.vstack(rows).astype(np.float32)


def test_pixels_follow_the_float64_angles_point_by_point():
    pts = _edge_scan()
    rows, cols, depth = pixel_coordinates(pts)
    assert len(rows) == len(pts)  # all within 80 m
    f32 = np.float32
    up, down = f32(3.0 / 180.0 * np.pi), f32(-25.0 / 180.0 * np.pi)
    fov = abs(down) + abs(up)
    for k in range(0, len(pts), 7):
        x, y, z = (float(v) for v in pts[k])
        yaw = f32(-math.atan2(y, x))
        pitch = f32(math.asin(max(-1.0, min(1.0, z / float(depth[k])))))
        u = math.floor(f32(0.5) * (yaw / f32(np.pi) + f32(1.0)) * f32(900))
        v = math.floor((f32(1.0) - (pitch + abs(down)) / fov) * f32(64))
        assert cols[k] == min(max(u, 0), 899), k
        assert rows[k] == min(max(v, 0), 63), k

