"""Exact ray casting against boxes, vertical cylinders and ellipsoids.

All rays of one scan share one origin (the sensor) and form a regular grid of
``n_beams x n_azimuth`` directions in the sensor frame. Instead of testing every
ray against every primitive, each primitive is projected into that grid: the
azimuth columns and beam rows its bounding box can cover form a small window,
and only the rays in the window are tested. The work is then proportional to
the rays each primitive covers (the depth complexity of the scene, a few per
ray), not to rays x primitives, and it stays vectorised: all (ray, primitive)
pairs of a scan are generated and intersected in a handful of array operations.

Primitive kinds (one :class:`Primitives` table holds all of them):

- ``BOX``: oriented about +z; ``center`` is the box centre, ``size`` the half
  extents along its own axes, ``yaw`` its heading;
- ``CYLINDER``: vertical; ``center`` is the axis midpoint, ``size`` is
  ``(radius, radius, half height)``;
- ``ELLIPSOID``: axis aligned; ``size`` holds the three radii.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BOX, CYLINDER, ELLIPSOID = 0, 1, 2

#: hits closer than this along a ray are ignored (the sensor's own housing).
T_MIN = 1e-6


@dataclass(frozen=True)
class Primitives:
    """A table of primitives, one row each (see the module docstring for kinds)."""

    kind: np.ndarray  # (n,) int8
    center: np.ndarray  # (n, 3) float64
    size: np.ndarray  # (n, 3) float64
    yaw: np.ndarray  # (n,) float64
    label: np.ndarray  # (n,) uint16 SemanticKITTI class
    instance: np.ndarray  # (n,) uint16, 0 for "stuff"
    reflectivity: np.ndarray  # (n,) float32

    def __len__(self) -> int:
        return len(self.kind)

    def take(self, index: np.ndarray) -> Primitives:
        """The rows ``index`` as a new table."""
        return Primitives(
            self.kind[index],
            self.center[index],
            self.size[index],
            self.yaw[index],
            self.label[index],
            self.instance[index],
            self.reflectivity[index],
        )

    @staticmethod
    def concat(parts: list[Primitives]) -> Primitives:
        """Stack several tables (e.g. the static world and this frame's moving cars)."""
        parts = [p for p in parts if len(p)] or parts[:1]
        return Primitives(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS)
        )

    @property
    def bounding_radius(self) -> np.ndarray:
        """Radius of a sphere about ``center`` that contains each primitive."""
        s = self.size
        box_r = np.sqrt((s**2).sum(axis=1))
        return np.where(self.kind == ELLIPSOID, s.max(axis=1), box_r)


_FIELDS = ("kind", "center", "size", "yaw", "label", "instance", "reflectivity")


def empty_primitives() -> Primitives:
    """A table with no rows."""
    return Primitives(
        np.zeros(0, np.int8),
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros(0),
        np.zeros(0, np.uint16),
        np.zeros(0, np.uint16),
        np.zeros(0, np.float32),
    )


def make_primitives(rows: list[tuple]) -> Primitives:
    """Build a table from rows ``(kind, center3, size3, yaw, label, instance, refl)``."""
    if not rows:
        return empty_primitives()
    kind, center, size, yaw, label, inst, refl = zip(*rows, strict=True)
    return Primitives(
        np.asarray(kind, np.int8),
        np.asarray(center, np.float64).reshape(-1, 3),
        np.asarray(size, np.float64).reshape(-1, 3),
        np.asarray(yaw, np.float64),
        np.asarray(label, np.uint16),
        np.asarray(inst, np.uint16),
        np.asarray(refl, np.float32),
    )


# --------------------------------------------------------------------------
# Analytic intersections of one origin with many (ray, primitive) pairs.
# Each returns the entry distance t along the unit ray (inf for a miss).
# --------------------------------------------------------------------------


def intersect_boxes(rel: np.ndarray, d: np.ndarray, half: np.ndarray, yaw: np.ndarray):
    """Slab test; ``rel`` = origin minus box centre (P,3), ``d`` unit rays (P,3).

    Returns ``(t, axis)`` where ``axis`` (0,1,2) is the slab the ray entered
    through, used for the surface normal.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    # rotate into the box frame (by -yaw about z)
    lo = np.stack([c * rel[:, 0] + s * rel[:, 1], c * rel[:, 1] - s * rel[:, 0], rel[:, 2]], 1)
    ld = np.stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], d[:, 2]], 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / ld
        t1 = (-half - lo) * inv
        t2 = (half - lo) * inv
    tmin = np.fmin(t1, t2)
    tmax = np.fmax(t1, t2)
    axis = np.argmax(tmin, axis=1)
    t_near = np.take_along_axis(tmin, axis[:, None], 1)[:, 0]
    t_far = tmax.min(axis=1)
    hit = (t_near <= t_far) & (t_near > T_MIN)
    return np.where(hit, t_near, np.inf), axis


def intersect_cylinders(rel: np.ndarray, d: np.ndarray, size: np.ndarray):
    """Vertical capped cylinders; returns ``(t, on_side)``."""
    r, hh = size[:, 0], size[:, 2]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = rel[:, 0] * d[:, 0] + rel[:, 1] * d[:, 1]
    cc = rel[:, 0] ** 2 + rel[:, 1] ** 2 - r**2
    disc = b * b - a * cc
    with np.errstate(divide="ignore", invalid="ignore"):
        t_side = (-b - np.sqrt(disc)) / a
        z_side = rel[:, 2] + t_side * d[:, 2]
        side_ok = (disc >= 0) & (a > 0) & (t_side > T_MIN) & (np.abs(z_side) <= hh)
        # caps: the one facing the origin
        cap_z = np.where(rel[:, 2] > 0, hh, -hh)
        t_cap = (cap_z - rel[:, 2]) / d[:, 2]
        px = rel[:, 0] + t_cap * d[:, 0]
        py = rel[:, 1] + t_cap * d[:, 1]
        cap_ok = (t_cap > T_MIN) & (px * px + py * py <= r * r) & (np.abs(rel[:, 2]) > hh)
    t = np.where(side_ok, t_side, np.inf)
    t = np.where(cap_ok & (t_cap < t), t_cap, t)
    return t, side_ok & (t == t_side)


def intersect_ellipsoids(rel: np.ndarray, d: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Axis-aligned ellipsoids: scale to the unit sphere and solve the quadratic."""
    ro = rel / radii
    rd = d / radii
    a = (rd * rd).sum(1)
    b = (ro * rd).sum(1)
    c = (ro * ro).sum(1) - 1.0
    disc = b * b - a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (t > T_MIN) & (c > 0), t, np.inf)


def surface_normals(prims: Primitives, rows: np.ndarray, points: np.ndarray, aux: np.ndarray):
    """Outward unit normals at ``points`` on primitives ``rows``.

    ``aux`` is the box entry axis (boxes) or the on-side flag (cylinders).
    """
    n = np.zeros_like(points)
    kind = prims.kind[rows]
    center = prims.center[rows]
    size = prims.size[rows]
    rel = points - center
    # boxes: the entry slab's axis, rotated back to the world
    m = kind == BOX
    if m.any():
        yaw = prims.yaw[rows[m]]
        c, s = np.cos(yaw), np.sin(yaw)
        ax = aux[m]
        lx = c * rel[m, 0] + s * rel[m, 1]
        ly = c * rel[m, 1] - s * rel[m, 0]
        local = np.stack([lx, ly, rel[m, 2]], 1)
        sign = np.sign(np.take_along_axis(local, ax[:, None], 1)[:, 0])
        nl = np.zeros_like(local)
        nl[np.arange(len(ax)), ax] = sign
        n[m] = np.stack([c * nl[:, 0] - s * nl[:, 1], s * nl[:, 0] + c * nl[:, 1], nl[:, 2]], 1)
    m = kind == CYLINDER
    if m.any():
        side = aux[m].astype(bool)
        nn = np.zeros((m.sum(), 3))
        nn[side, :2] = rel[m][side, :2]
        nn[~side, 2] = np.sign(rel[m][~side, 2])
        n[m] = nn
    m = kind == ELLIPSOID
    if m.any():
        n[m] = rel[m] / size[m] ** 2
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


# --------------------------------------------------------------------------
# Windows in the ray grid and nearest hits
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class RayGrid:
    """The sensor's ray directions: ``beams`` elevations x ``n_azimuth`` columns.

    Column ``c`` points at azimuth ``2*pi*c/n_azimuth`` (counter-clockwise from
    +x); ray index is ``beam * n_azimuth + column``.
    """

    elevation: np.ndarray  # (B,) radians, ascending
    n_azimuth: int

    @property
    def directions(self) -> np.ndarray:
        """(B*A, 3) unit directions in the sensor frame."""
        az = 2 * np.pi * np.arange(self.n_azimuth) / self.n_azimuth
        ce, se = np.cos(self.elevation)[:, None], np.sin(self.elevation)[:, None]
        d = np.stack(
            np.broadcast_arrays(ce * np.cos(az), ce * np.sin(az), se + 0 * az), axis=-1
        )
        return d.reshape(-1, 3)


def primitive_windows(
    prims: Primitives, origin: np.ndarray, rotation: np.ndarray, grid: RayGrid
) -> tuple[np.ndarray, ...]:
    """Ray-grid windows ``(col0, n_cols, beam0, n_beams)`` bounding each primitive.

    The primitive's oriented bounding box is moved into the sensor frame; its
    corners bound the azimuth span (exact for a convex hull seen from outside)
    and its vertical extent with the nearest/farthest horizontal distance bounds
    the elevation span. A one-column, small-angle margin absorbs rounding.
    """
    signs = np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
    )
    c, s = np.cos(prims.yaw), np.sin(prims.yaw)
    local = signs[None, :, :] * prims.size[:, None, :]  # (n,8,3)
    world = np.stack(
        [
            c[:, None] * local[..., 0] - s[:, None] * local[..., 1],
            s[:, None] * local[..., 0] + c[:, None] * local[..., 1],
            local[..., 2],
        ],
        -1,
    ) + prims.center[:, None, :]
    sensor = (world - origin) @ rotation  # rows: R^T (p - o)
    center = sensor.mean(axis=1)
    az_c = np.arctan2(center[:, 1], center[:, 0])
    az = np.arctan2(sensor[..., 1], sensor[..., 0]) - az_c[:, None]
    az = (az + np.pi) % (2 * np.pi) - np.pi
    horiz = np.hypot(center[:, 0], center[:, 1])
    offset = sensor[..., :2] - center[:, None, :2]
    reach = np.hypot(offset[..., 0], offset[..., 1]).max(1)
    step = 2 * np.pi / grid.n_azimuth
    inside = horiz <= reach + 1e-9
    lo = np.where(inside, -np.pi, az.min(1) + az_c)
    hi = np.where(inside, np.pi, az.max(1) + az_c)
    col0 = np.floor(lo / step).astype(np.int64) - 1
    ncol = np.ceil(hi / step).astype(np.int64) + 1 - col0 + 1
    ncol = np.minimum(ncol, grid.n_azimuth)
    col0 = np.where(ncol >= grid.n_azimuth, 0, col0 % grid.n_azimuth)

    zmin, zmax = sensor[..., 2].min(1), sensor[..., 2].max(1)
    r_near = np.maximum(horiz - reach, 1e-3)
    r_far = horiz + reach
    el_hi = np.arctan2(zmax, np.where(zmax > 0, r_near, r_far))
    el_lo = np.arctan2(zmin, np.where(zmin < 0, r_near, r_far))
    el_lo = np.where(inside & (zmin < 0), -np.pi / 2, el_lo)
    el_hi = np.where(inside & (zmax > 0), np.pi / 2, el_hi)
    margin = 1e-4
    beam0 = np.searchsorted(grid.elevation, el_lo - margin, side="left")
    beam1 = np.searchsorted(grid.elevation, el_hi + margin, side="right")
    nbeam = np.maximum(beam1 - beam0, 0)
    return col0, ncol, beam0, nbeam


def cast_primitives(
    prims: Primitives,
    origin: np.ndarray,
    rotation: np.ndarray,
    grid: RayGrid,
    dirs_world: np.ndarray,
    max_range: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest primitive hit of every ray.

    Returns ``(t, row, aux)`` per ray: distance (inf when nothing is hit within
    ``max_range``), the hit primitive's row in ``prims`` (-1 if none) and the
    normal hint from the intersection routine.
    """
    n_rays = len(dirs_world)
    best_t = np.full(n_rays, np.inf)
    best_row = np.full(n_rays, -1, dtype=np.int64)
    best_aux = np.zeros(n_rays, dtype=np.int64)
    if len(prims) == 0:
        return best_t, best_row, best_aux
    col0, ncol, beam0, nbeam = primitive_windows(prims, origin, rotation, grid)
    count = ncol * nbeam
    keep = count > 0
    rows = np.nonzero(keep)[0]
    count = count[keep]
    total = int(count.sum())
    if total == 0:
        return best_t, best_row, best_aux
    start = np.cumsum(count) - count
    pair_prim = np.repeat(rows, count)
    local = np.arange(total, dtype=np.int64) - np.repeat(start, count)
    nb = np.repeat(nbeam[keep], count)
    col = (np.repeat(col0[keep], count) + local // nb) % grid.n_azimuth
    beam = np.repeat(beam0[keep], count) + local % nb
    ray = beam * grid.n_azimuth + col

    kinds = prims.kind[pair_prim]
    t = np.full(total, np.inf)
    aux = np.zeros(total, dtype=np.int64)
    for kind in (BOX, CYLINDER, ELLIPSOID):
        sel = np.nonzero(kinds == kind)[0]
        if len(sel) == 0:
            continue
        pr = pair_prim[sel]
        rel = origin - prims.center[pr]
        d = dirs_world[ray[sel]]
        if kind == BOX:
            t[sel], aux[sel] = intersect_boxes(rel, d, prims.size[pr], prims.yaw[pr])
        elif kind == CYLINDER:
            tk, side = intersect_cylinders(rel, d, prims.size[pr])
            t[sel], aux[sel] = tk, side
        else:
            t[sel] = intersect_ellipsoids(rel, d, prims.size[pr])
    hit = np.nonzero(t <= max_range)[0]
    if len(hit) == 0:
        return best_t, best_row, best_aux
    t, ray, pair_prim, aux = t[hit], ray[hit], pair_prim[hit], aux[hit]
    np.minimum.at(best_t, ray, t)
    win = t == best_t[ray]
    best_row[ray[win]] = pair_prim[win]
    best_aux[ray[win]] = aux[win]
    return best_t, best_row, best_aux
