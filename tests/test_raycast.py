"""Ray casting against hand-built worlds, checked against analytic ranges."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.ground import REGION_ROAD, REGION_SIDEWALK, Ground, cast_ground
from lidar_iris_eval.simulate.raycast import (
    BOX,
    CYLINDER,
    ELLIPSOID,
    RayGrid,
    cast_primitives,
    intersect_boxes,
    intersect_cylinders,
    intersect_ellipsoids,
    make_primitives,
)
from lidar_iris_eval.simulate.sensors import SensorModel, simulate_scan


def flat_ground(z: float = 0.0, road_below_x: float | None = None, curb: float = 0.12) -> Ground:
    """A level ground over [-200, 200]^2; road everywhere or only where x < road_below_x."""
    height = np.full((101, 101), z)
    region = np.full((800, 800), REGION_ROAD, dtype=np.uint8)
    if road_below_x is not None:
        xs = -200 + (np.arange(800) + 0.5) * 0.5
        region[:, xs >= road_below_x] = REGION_SIDEWALK
    return Ground((-200.0, -200.0), 4.0, height, 0.5, region, curb)


def one_box_one_cylinder():
    """A 4 x 2 x 3 m box at x = 10 and a vertical cylinder (r = 0.5) at y = 8."""
    return make_primitives([
        (BOX, (12.0, 0.0, 1.5), (2.0, 1.0, 1.5), 0.0, labels.BUILDING, 0, 0.3),
        (CYLINDER, (0.0, 8.0, 2.0), (0.5, 0.5, 2.0), 0.0, labels.POLE, 0, 0.4),
    ])


def test_box_ray_along_x_hits_near_face():
    rel = np.array([[-12.0, 0.0, 0.5]])  # origin (0,0,2) minus centre (12,0,1.5)
    d = np.array([[1.0, 0.0, 0.0]])
    t, axis = intersect_boxes(rel, d, np.array([[2.0, 1.0, 1.5]]), np.array([0.0]))
    assert t[0] == pytest.approx(10.0, abs=1e-9)
    assert axis[0] == 0


def test_rotated_box_hit_distance():
    # a 2 x 2 box turned 45 deg: its corner points at the origin, sqrt(2) from the centre
    rel = np.array([[-10.0, 0.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0]])
    t, _ = intersect_boxes(rel, d, np.array([[1.0, 1.0, 1.0]]), np.array([np.pi / 4]))
    assert t[0] == pytest.approx(10.0 - np.sqrt(2.0), abs=1e-9)


def test_cylinder_oblique_hit_matches_geometry():
    # ray in the xy plane at angle a from the axis direction: chord geometry
    a = np.deg2rad(2.0)
    rel = np.array([[0.0, -8.0, 0.0]])
    d = np.array([[np.sin(a), np.cos(a), 0.0]])
    t, side = intersect_cylinders(rel, d, np.array([[0.5, 0.5, 2.0]]))
    # distance from origin to the axis is 8; perpendicular offset 8 sin(a)
    expected = 8 * np.cos(a) - np.sqrt(0.25 - (8 * np.sin(a)) ** 2)
    assert t[0] == pytest.approx(expected, abs=1e-9)
    assert side[0]


def test_cylinder_top_cap_from_above():
    rel = np.array([[0.0, 0.0, 10.0]])
    d = np.array([[0.0, 0.0, -1.0]])
    t, side = intersect_cylinders(rel, d, np.array([[0.5, 0.5, 2.0]]))
    assert t[0] == pytest.approx(8.0)
    assert not side[0]


def test_sphere_hit_and_miss():
    rel = np.array([[-5.0, 0.0, 0.0], [-5.0, 0.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    t = intersect_ellipsoids(rel, d, np.array([[2.0, 2.0, 1.0]] * 2))
    assert t[0] == pytest.approx(3.0)
    assert np.isinf(t[1])


def _sensor(n_az: int, elev_deg) -> SensorModel:
    return SensorModel("test", tuple(elev_deg), n_az, 2.0, 100.0, 0.1, 0.0, 0.0, 0.0)


def test_scan_of_box_and_cylinder_has_submillimetre_range_error():
    """Every return off the box or the cylinder lies at its analytic range."""
    prims = one_box_one_cylinder()
    sensor = _sensor(720, np.linspace(-10.0, 10.0, 21))
    pose = np.eye(4)
    pose[2, 3] = 2.0
    scan = simulate_scan(sensor, flat_ground(-50.0), prims, pose, rng=None)
    pts = scan.points.astype(np.float64)
    rng_meas = np.linalg.norm(pts, axis=1)
    d = pts / rng_meas[:, None]
    on_box = scan.row == 0
    on_cyl = scan.row == 1
    assert on_box.sum() > 50 and on_cyl.sum() > 10
    # box: the face x = 10 faces the sensor; sensor at z=2, box top at z=3
    t_face = 10.0 / d[on_box, 0]
    assert np.abs(rng_meas[on_box] - t_face).max() < 1e-3
    # cylinder at (0, 8): closed-form nearest root of |o + t d - c|_xy = r
    dx, dy = d[on_cyl, 0], d[on_cyl, 1]
    a = dx**2 + dy**2
    b = -8.0 * dy
    c = 64.0 - 0.25
    t_cyl = (-b - np.sqrt(b * b - a * c)) / a
    assert np.abs(rng_meas[on_cyl] - t_cyl).max() < 1e-3
    # and every ray that geometrically should hit the box does
    az = np.arctan2(d[:, 1], d[:, 0])
    assert np.all(np.abs(az[on_box]) <= np.arctan2(1.0, 10.0) + 1e-9)
    assert (np.asarray(scan.label)[on_box] & 0xFFFF == labels.BUILDING).all()
    assert (np.asarray(scan.label)[on_cyl] & 0xFFFF == labels.POLE).all()


def test_flat_ground_range_matches_height():
    sensor = _sensor(64, [-20.0, -10.0, -5.0])
    pose = np.eye(4)
    pose[2, 3] = 1.73
    scan = simulate_scan(sensor, flat_ground(0.0), make_primitives([]), pose, rng=None)
    r = np.linalg.norm(scan.points, axis=1)
    elev = np.arcsin(scan.points[:, 2] / r)
    assert len(r) == 3 * 64
    np.testing.assert_allclose(r, 1.73 / np.sin(-elev), atol=1e-3)
    assert (scan.label == labels.ROAD).all()


def test_kerb_face_and_raised_sidewalk():
    # road for x < 5, sidewalk 0.12 m higher beyond: a ray along +x sees both
    g = flat_ground(0.0, road_below_x=5.0)
    origin = np.array([0.0, 0.0, 1.0])
    el = np.deg2rad([-30.0, -11.0, -9.0])  # hits road at 1.73, kerb, sidewalk
    dirs = np.stack([np.cos(el), np.zeros(3), np.sin(el)], 1)
    t, region, normal = cast_ground(g, origin, dirs, 100.0)
    hit = origin + t[:, None] * dirs
    assert hit[0, 2] == pytest.approx(0.0, abs=1e-6) and region[0] == REGION_ROAD
    # second ray crosses x = 5 at z = 1 - 5 tan(11 deg) = 0.028, inside the 0.12 m kerb
    assert hit[1, 0] == pytest.approx(5.0, abs=0.01) and region[1] == REGION_SIDEWALK
    assert abs(normal[1, 2]) < 1e-9
    assert hit[2, 2] == pytest.approx(0.12, abs=1e-6) and region[2] == REGION_SIDEWALK


def test_windowed_casting_equals_brute_force():
    """Restricting each primitive to its ray-grid window never loses a hit."""
    rng = np.random.default_rng(5)
    rows = []
    for k in range(40):
        kind = k % 3
        c = (rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-2, 6))
        if np.hypot(c[0], c[1]) < 4:
            continue
        size = tuple(rng.uniform(0.3, 4.0, 3)) if kind != CYLINDER else (0.4, 0.4, 2.0)
        rows.append((kind, c, size, rng.uniform(0, np.pi) if kind == BOX else 0.0, 50, 0, 0.3))
    prims = make_primitives(rows)
    grid = RayGrid(np.deg2rad(np.linspace(-25, 15, 24)), 360)
    # a slightly tilted sensor
    ax = np.deg2rad(3.0)
    rot = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    origin = np.array([0.5, -0.3, 1.8])
    dirs = grid.directions @ rot.T
    t_win, row_win, _ = cast_primitives(prims, origin, rot, grid, dirs, 100.0)
    # brute force: every ray against every primitive
    n = len(dirs)
    best = np.full(n, np.inf)
    for k in range(len(prims)):
        rel = np.broadcast_to(origin - prims.center[k], (n, 3))
        if prims.kind[k] == BOX:
            t, _ = intersect_boxes(rel, dirs, np.broadcast_to(prims.size[k], (n, 3)),
                                   np.full(n, prims.yaw[k]))
        elif prims.kind[k] == CYLINDER:
            t, _ = intersect_cylinders(rel, dirs, np.broadcast_to(prims.size[k], (n, 3)))
        else:
            assert prims.kind[k] == ELLIPSOID
            t = intersect_ellipsoids(rel, dirs, np.broadcast_to(prims.size[k], (n, 3)))
        best = np.minimum(best, t)
    assert np.isfinite(best).sum() > 500
    np.testing.assert_array_equal(np.isfinite(t_win), np.isfinite(best))
    np.testing.assert_allclose(t_win[np.isfinite(best)], best[np.isfinite(best)], rtol=0, atol=1e-9)
