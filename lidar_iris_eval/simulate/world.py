"""Procedural urban world built around a set of road centre lines.

Whatever the source of the roads (a street grid or a recorded trajectory), the
world is generated the same way:

1. rasterise the distance to the nearest road centre line; road, sidewalk and
   terrain follow from it (:mod:`~lidar_iris_eval.simulate.ground`);
2. walk along each side of every road and place, with irregular spacing, parked
   cars at the kerb, street lights and signs on the sidewalk, street trees, and
   behind a setback buildings of varied frontage, depth, height and shape,
   sometimes with a hedge or fence in front or a yard with trees instead;
3. reject anything that would overlap a road or an already placed object.

Every object is a few primitives with a SemanticKITTI class, so the per-point
labels of a scan follow from the primitive each ray hits. The world is static:
revisits see exactly the same geometry (moving cars are added per frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.ground import (
    REGION_ROAD,
    REGION_SIDEWALK,
    REGION_TERRAIN,
    Ground,
)
from lidar_iris_eval.simulate.raycast import BOX, CYLINDER, ELLIPSOID, Primitives, make_primitives


@dataclass(frozen=True)
class WorldParams:
    """Dimensions and densities of the generated world (metres, probabilities)."""

    road_half_width: float = 6.5
    sidewalk_width: float = 3.0
    curb: float = 0.12
    max_grade: float = 0.015
    undulation: float = 0.5
    margin: float = 90.0
    region_cell: float = 0.25
    height_cell: float = 4.0
    empty_lot: float = 0.15
    hedge: float = 0.3
    tree_spacing: tuple[float, float] = (6.0, 30.0)
    light_spacing: tuple[float, float] = (18.0, 45.0)
    parked_run: float = 0.45
    # -- the ranges below were constants; their defaults are those constants, so a world
    # -- built with them draws the same random numbers (every preset stays byte-identical)
    #: building frontage along the street, depth, and setback behind the sidewalk (m)
    building_front: tuple[float, float] = (8.0, 32.0)
    building_depth: tuple[float, float] = (8.0, 24.0)
    setback: tuple[float, float] = (1.0, 9.0)
    #: probability that the next lot starts right after a building, else a gap drawn from
    #: ``building_gap`` (m)
    no_gap: float = 0.3
    building_gap: tuple[float, float] = (2.0, 14.0)
    #: a hedge or fence in front of a building needs at least this setback (m)
    hedge_setback: float = 2.5
    #: probability that a street tree keeps ``tree_spacing`` (else three times it)
    tree_regular: float = 0.7
    #: fraction of the kerb poles that are signs (the rest are street lights)
    sign_fraction: float = 0.3
    #: parked cars per run (integers, high end excluded), spacing within a run and gaps
    #: between runs (m)
    parked_run_cars: tuple[int, int] = (1, 7)
    parked_spacing: tuple[float, float] = (5.0, 8.0)
    parked_gap: tuple[float, float] = (10.0, 50.0)
    # -- additions of the dense world; off by default (no random number is drawn for them)
    #: bushes on the strip between sidewalk and façades: spacing range (m), None: none
    bush_spacing: tuple[float, float] | None = None
    #: probability that the gap between two buildings gets a wall or fence across its front
    gap_fence: float = 0.0
    #: probability that a building gets an entrance porch (steps and canopy, a small box)
    #: in front of its façade
    porch: float = 0.0
    #: street furniture on the sidewalk (advertising columns, waste containers, utility
    #: cabinets, bus shelters): spacing range (m), None: none
    furniture_spacing: tuple[float, float] | None = None
    #: place the buildings of every street before any street object (trees, cars, ...), so
    #: that the objects of one street do not take the lots of the next; off: street by
    #: street, as the older presets were built
    buildings_first: bool = False
    #: street-tree trunk height range (m), up to the crown
    trunk_height: tuple[float, float] = (1.5, 3.5)
    #: opt-in (off for every preset and sequence): parked cars drawn from five body types
    #: (hatchback, sedan, estate, SUV, van) and trees with multi-lobed or conifer crowns.
    #: Off, no extra random number is drawn, so the default worlds stay byte-identical.
    #: Training data of learned segment descriptors turns it on (objects of one class must
    #: differ in shape for the same-object task to be learnable).
    shape_variety: bool = False


#: the dense urban world (preset ``urban-dense``): near-continuous façades (narrower
#: frontages, small setbacks and gaps, porches, walls across gaps), long runs of parked
#: cars, more street trees and poles, bushes. The values were chosen so that segments per
#: simulated HDL-64E scan (720 azimuth steps) and their sizes come near those of real
#: KITTI 00 scans (docs/esm.md "Segments"); no method parameter was changed for it.
DENSE = WorldParams(
    # narrower street (carriageway with parking lanes) and sidewalk
    road_half_width=5.5, sidewalk_width=2.5,
    # row houses: narrow, shallow (the blocks of small-mixed are 30-38 m), close to the
    # sidewalk, often wall to wall; porches; walls or fences across most gaps
    building_front=(5.0, 12.0), building_depth=(4.0, 7.0), setback=(0.3, 2.0),
    no_gap=0.5, building_gap=(1.5, 5.0), empty_lot=0.0, hedge=0.6, hedge_setback=1.5,
    porch=0.4, gap_fence=0.6, buildings_first=True,
    # street trees every 5-12 m with lower crowns, bushes every 2-6 m, furniture
    tree_spacing=(5.0, 12.0), tree_regular=1.0, trunk_height=(1.0, 2.5),
    bush_spacing=(2.0, 6.0), furniture_spacing=(8.0, 20.0),
    light_spacing=(12.0, 25.0), sign_fraction=0.4,
    # kerbs nearly full of parked cars of five body types
    parked_run=0.95, parked_run_cars=(4, 12), parked_spacing=(5.2, 7.5),
    parked_gap=(1.0, 6.0), shape_variety=True,
)

#: named worlds (``SimConfig.world_style``): "default" is every older preset's
WORLD_STYLES: dict[str, WorldParams] = {"default": WorldParams(), "dense": DENSE}


def world_params(style: str) -> WorldParams:
    """The :class:`WorldParams` of a world style (see :data:`WORLD_STYLES`)."""
    if style not in WORLD_STYLES:
        raise LirisError(None, f"unknown world style {style!r}; choose from "
                               f"{', '.join(WORLD_STYLES)}")
    return WORLD_STYLES[style]


@dataclass(frozen=True)
class World:
    """Ground plus static primitives."""

    ground: Ground
    prims: Primitives
    #: per primitive row, the id (1, 2, ...) of the physical object it belongs to
    objects: np.ndarray | None = None

    def near_rows(self, xy: np.ndarray, radius: float) -> np.ndarray:
        """Rows of the primitives whose bounding sphere reaches within ``radius`` of ``xy``."""
        p = self.prims
        dist = np.hypot(p.center[:, 0] - xy[0], p.center[:, 1] - xy[1])
        return np.nonzero(dist - p.bounding_radius <= radius)[0]

    def near(self, xy: np.ndarray, radius: float) -> Primitives:
        """Primitives whose bounding sphere reaches within ``radius`` of ``xy``."""
        return self.prims.take(self.near_rows(xy, radius))


def resample_polyline(points: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` metres along a 2-D polyline (keeps both ends)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return points[:1].copy()
    n = max(int(np.ceil(s[-1] / step)), 1)
    q = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(q, s, points[:, 0]), np.interp(q, s, points[:, 1])], 1)


def road_distance(
    lines: list[np.ndarray], origin: np.ndarray, shape: tuple[int, int], cell: float, band: float
) -> np.ndarray:
    """Distance (float32) from each cell centre to the nearest centre line.

    Only cells within ``band`` of a line get exact values; the rest stay at
    ``band`` (they are "far", which is all the callers need to know).
    """
    dist = np.full(shape, band, dtype=np.float32)
    for line in lines:
        for a, b in zip(line[:-1], line[1:], strict=True):
            lo = np.floor((np.minimum(a, b) - band - origin) / cell).astype(int)
            hi = np.ceil((np.maximum(a, b) + band - origin) / cell).astype(int)
            lo = np.maximum(lo, 0)
            hi = np.minimum(hi, [shape[1], shape[0]])
            if np.any(hi <= lo):
                continue
            xs = origin[0] + (np.arange(lo[0], hi[0]) + 0.5) * cell
            ys = origin[1] + (np.arange(lo[1], hi[1]) + 0.5) * cell
            ab = b - a
            L2 = float(ab @ ab)
            px = xs[None, :] - a[0]
            py = ys[:, None] - a[1]
            if L2 > 0:
                u = np.clip((px * ab[0] + py * ab[1]) / L2, 0.0, 1.0)
            else:
                u = np.zeros((len(ys), len(xs)))
            dx = px - u * ab[0]
            dy = py - u * ab[1]
            d = np.sqrt(dx * dx + dy * dy).astype(np.float32)
            view = dist[lo[1] : hi[1], lo[0] : hi[0]]
            np.minimum(view, d, out=view)
    return dist


def _height_raster(
    origin: np.ndarray, shape: tuple[int, int], cell: float, params: WorldParams,
    rng: np.random.Generator, samples: np.ndarray | None,
) -> np.ndarray:
    """Road-surface heights at the raster corners.

    Procedural worlds get a random gentle grade plus a long-wavelength
    undulation; worlds built around a recorded trajectory interpolate the
    ground heights under the trajectory (``samples``: (n, 3) x, y, z).
    """
    ys = origin[1] + np.arange(shape[0]) * cell
    xs = origin[0] + np.arange(shape[1]) * cell
    if samples is None:
        grade = rng.uniform(0.3, 1.0) * params.max_grade
        heading = rng.uniform(0, 2 * np.pi)
        gx, gy = grade * np.cos(heading), grade * np.sin(heading)
        lx, ly = rng.uniform(250, 500, 2)
        px, py = rng.uniform(0, 2 * np.pi, 2)
        X, Y = np.meshgrid(xs - xs.mean(), ys - ys.mean())
        return gx * X + gy * Y + params.undulation * np.sin(2 * np.pi * X / lx + px) * np.sin(
            2 * np.pi * Y / ly + py
        )
    acc = np.zeros(shape)
    cnt = np.zeros(shape)
    i = np.clip(np.round((samples[:, 0] - origin[0]) / cell).astype(int), 0, shape[1] - 1)
    j = np.clip(np.round((samples[:, 1] - origin[1]) / cell).astype(int), 0, shape[0] - 1)
    np.add.at(acc, (j, i), samples[:, 2])
    np.add.at(cnt, (j, i), 1.0)
    known = cnt > 0
    mean = np.where(known, acc / np.maximum(cnt, 1), 0.0)
    _, (jj, ii) = ndimage.distance_transform_edt(~known, return_indices=True)
    filled = mean[jj, ii]
    return ndimage.gaussian_filter(filled, sigma=1.5, mode="nearest")


class _Placer:
    """Accumulates primitives while checking a coarse occupancy raster."""

    def __init__(self, world_ground: Ground, dist: np.ndarray, params: WorldParams, rng):
        self.g = world_ground
        self.dist = dist
        self.p = params
        self.rng = rng
        self.rows: list[tuple] = []
        self.cell = 0.5
        sh = dist.shape
        f = world_ground.region_cell / self.cell
        self.occ = np.zeros((int(sh[0] * f) + 1, int(sh[1] * f) + 1), dtype=bool)
        self.next_instance = 1
        self.object_starts: list[int] = []  # first row of each placed object

    def _new_object(self) -> None:
        """Mark the rows appended from now on as one new physical object."""
        self.object_starts.append(len(self.rows))

    # -- raster helpers --------------------------------------------------
    def _footprint(self, cx, cy, hx, hy, yaw, step):
        nu = max(int(np.ceil(2 * hx / step)), 1) + 1
        nv = max(int(np.ceil(2 * hy / step)), 1) + 1
        u, v = np.meshgrid(np.linspace(-hx, hx, nu), np.linspace(-hy, hy, nv))
        c, s = np.cos(yaw), np.sin(yaw)
        return cx + c * u - s * v, cy + s * u + c * v

    def _dist_at(self, x, y):
        g = self.g
        i = np.clip(((x - g.origin[0]) / g.region_cell).astype(int), 0, self.dist.shape[1] - 1)
        j = np.clip(((y - g.origin[1]) / g.region_cell).astype(int), 0, self.dist.shape[0] - 1)
        inside = (x >= g.origin[0]) & (y >= g.origin[1])
        inside &= (i < self.dist.shape[1] - 1) & (j < self.dist.shape[0] - 1)
        return np.where(inside, self.dist[j, i], -1.0)

    def _occ_idx(self, x, y):
        g = self.g
        i = np.clip(((x - g.origin[0]) / self.cell).astype(int), 0, self.occ.shape[1] - 1)
        j = np.clip(((y - g.origin[1]) / self.cell).astype(int), 0, self.occ.shape[0] - 1)
        return j, i

    def free(self, cx, cy, hx, hy, yaw, min_dist, max_dist=np.inf, pad=0.3) -> bool:
        """Footprint keeps ``min_dist..max_dist`` from every road and hits nothing placed."""
        x, y = self._footprint(cx, cy, hx + pad, hy + pad, yaw, 0.5)
        d = self._dist_at(x, y)
        if d.min() < min_dist or d.max() > max_dist:
            return False
        return not self.occ[self._occ_idx(x, y)].any()

    def claim(self, cx, cy, hx, hy, yaw) -> None:
        x, y = self._footprint(cx, cy, hx, hy, yaw, 0.4)
        self.occ[self._occ_idx(x, y)] = True

    def base(self, x, y) -> float:
        """Height of the raised (off-road) ground at a point."""
        return float(self.g.elevation(np.array([x]), np.array([y]))[0][0]) + self.g.curb

    # -- objects ---------------------------------------------------------
    def building(self, cx, cy, hx, hy, yaw) -> None:
        self._new_object()
        rng = self.rng
        h = rng.uniform(4.0, 11.0) if rng.random() < 0.55 else rng.uniform(11.0, 30.0)
        z0 = self.base(cx, cy) - 1.0
        refl = rng.uniform(0.2, 0.55)
        self.rows.append(
            (BOX, (cx, cy, z0 + (h + 1) / 2), (hx, hy, (h + 1) / 2), yaw, labels.BUILDING, 0, refl)
        )
        c, s = np.cos(yaw), np.sin(yaw)
        if rng.random() < 0.35:  # a lower or higher wing at the back or a side
            wx = hx * rng.uniform(0.3, 0.7)
            wy = hy * rng.uniform(0.4, 0.9)
            ou = rng.choice([-1, 1]) * (hx - wx)
            ov = hy + wy * rng.uniform(0.5, 1.0)  # behind (away from the road)
            wcx, wcy = cx + c * ou - s * ov, cy + s * ou + c * ov
            if self.free(wcx, wcy, wx, wy, yaw, self.min_building):
                wh = h * rng.uniform(0.4, 1.5)
                self.rows.append(
                    (BOX, (wcx, wcy, z0 + (wh + 1) / 2), (wx, wy, (wh + 1) / 2), yaw,
                     labels.BUILDING, 0, refl)
                )
                self.claim(wcx, wcy, wx, wy, yaw)
        if rng.random() < 0.25:  # a rooftop block (stair house, machinery)
            rx, ry = hx * rng.uniform(0.2, 0.5), hy * rng.uniform(0.2, 0.5)
            rh = rng.uniform(1.5, 4.0)
            self.rows.append(
                (BOX, (cx, cy, z0 + h + 1 + rh / 2), (rx, ry, rh / 2), yaw, labels.BUILDING, 0,
                 refl)
            )
        if self.p.porch > 0 and rng.random() < self.p.porch:  # an entrance porch
            pw, pd = rng.uniform(1.5, 3.0), rng.uniform(0.8, 1.8)
            ou = rng.uniform(-1, 1) * max(hx - pw, 0.0)
            ov = -hy - pd / 2  # in front of the façade (towards the road)
            pcx, pcy = cx + c * ou - s * ov, cy + s * ou + c * ov
            if self.free(pcx, pcy, pw / 2, pd / 2, yaw, self.p.road_half_width
                         + self.p.sidewalk_width + 0.2, pad=0.0):
                ph = rng.uniform(2.4, 3.2)
                self.rows.append((BOX, (pcx, pcy, z0 + 1 + ph / 2), (pw / 2, pd / 2, ph / 2),
                                  yaw, labels.BUILDING, 0, refl))
                self.claim(pcx, pcy, pw / 2, pd / 2, yaw)
        self.claim(cx, cy, hx, hy, yaw)

    def tree(self, x, y) -> None:
        self._new_object()
        rng = self.rng
        z0 = self.base(x, y)
        trunk_h = rng.uniform(*self.p.trunk_height)
        tr = rng.uniform(0.12, 0.35)
        rh = rng.uniform(1.5, 4.0)
        rv = rh * rng.uniform(0.8, 1.5)
        self.rows.append((CYLINDER, (x, y, z0 + trunk_h / 2 - 0.2), (tr, tr, trunk_h / 2 + 0.2),
                          0.0, labels.TRUNK, 0, 0.35))
        if self.p.shape_variety:
            self.rows.extend(crown_rows(rng, x, y, z0 + trunk_h, rh, rv))
        else:
            self.rows.append((ELLIPSOID, (x, y, z0 + trunk_h + 0.8 * rv), (rh, rh, rv), 0.0,
                              labels.VEGETATION, 0, 0.45))
        self.claim(x, y, 0.6, 0.6, 0.0)

    def bush(self, x, y, r, h) -> None:
        """A bush: one ellipsoid of radius ``r`` and half height ``h``, sunk a little."""
        self._new_object()
        rng = self.rng
        rx, ry = r * rng.uniform(0.7, 1.0), r * rng.uniform(0.7, 1.0)
        self.rows.append((ELLIPSOID, (x, y, self.base(x, y) + 0.7 * h), (rx, ry, h), 0.0,
                          labels.VEGETATION, 0, 0.45))
        self.claim(x, y, r, r, 0.0)

    def furniture(self, x, y, yaw) -> None:
        """A piece of street furniture: an advertising column, a waste container, a
        utility cabinet or a bus shelter (a box open to the road is one thin back wall)."""
        self._new_object()
        rng = self.rng
        z0 = self.base(x, y)
        kind = int(rng.integers(4))
        refl = rng.uniform(0.2, 0.6)
        if kind == 0:  # advertising column
            r, h = rng.uniform(0.5, 0.7), rng.uniform(2.5, 3.5)
            self.rows.append((CYLINDER, (x, y, z0 + h / 2 - 0.1), (r, r, h / 2 + 0.1), 0.0,
                              labels.OTHER_STRUCTURE, 0, refl))
            self.claim(x, y, r, r, 0.0)
            return
        if kind == 1:  # waste container
            hx, hy, h = rng.uniform(0.6, 0.9), rng.uniform(0.45, 0.6), rng.uniform(1.2, 1.5)
        elif kind == 2:  # utility cabinet
            hx, hy, h = rng.uniform(0.4, 0.8), rng.uniform(0.2, 0.35), rng.uniform(1.2, 1.6)
        else:  # bus shelter: back wall and roof as one slab
            hx, hy, h = rng.uniform(1.5, 2.5), rng.uniform(0.05, 0.1), rng.uniform(2.3, 2.6)
        a = yaw + rng.uniform(-0.05, 0.05)
        self.rows.append((BOX, (x, y, z0 + h / 2 - 0.1), (hx, hy, h / 2 + 0.1), a,
                          labels.OTHER_STRUCTURE, 0, refl))
        self.claim(x, y, hx, hy, a)

    def pole(self, x, y, yaw, sign: bool) -> None:
        self._new_object()
        rng = self.rng
        z0 = self.base(x, y)
        h = rng.uniform(2.6, 3.2) if sign else rng.uniform(6.0, 10.0)
        r = rng.uniform(0.05, 0.09) if sign else rng.uniform(0.08, 0.15)
        self.rows.append((CYLINDER, (x, y, z0 + h / 2 - 0.2), (r, r, h / 2 + 0.2), 0.0,
                          labels.POLE, 0, 0.4))
        if sign:
            w, hh = rng.uniform(0.3, 0.5), rng.uniform(0.3, 0.5)
            self.rows.append((BOX, (x, y, z0 + h + hh), (0.03, w, hh), yaw + rng.uniform(-0.3, 0.3),
                              labels.TRAFFIC_SIGN, 0, 0.9))
        self.claim(x, y, 0.3, 0.3, 0.0)

    def car(self, x, y, yaw, label=labels.CAR) -> None:
        self._new_object()
        make = varied_car_rows if self.p.shape_variety else car_rows
        self.rows.extend(make(self.rng, x, y, self.base(x, y) - self.g.curb, yaw, label,
                              self.next_instance))
        self.next_instance += 1
        self.claim(x, y, 2.4, 1.0, yaw)

    def wall(self, x, y, hx, hy, yaw, hedge: bool) -> None:
        self._new_object()
        h = self.rng.uniform(0.9, 1.9)
        z0 = self.base(x, y) - 0.3
        cls = labels.VEGETATION if hedge else labels.FENCE
        self.rows.append((BOX, (x, y, z0 + (h + 0.3) / 2), (hx, hy, (h + 0.3) / 2), yaw, cls, 0,
                          0.45 if hedge else 0.3))
        self.claim(x, y, hx, hy, yaw)

    @property
    def min_building(self) -> float:
        return self.p.road_half_width + self.p.sidewalk_width + 0.5


def car_rows(rng, x, y, z_road, yaw, label, instance) -> list[tuple]:
    """A car as a body box and a cabin box (length 3.9-4.9 m)."""
    length = rng.uniform(3.9, 4.9)
    width = rng.uniform(1.7, 1.9)
    body_h = rng.uniform(0.6, 0.8)
    cab_h = rng.uniform(0.45, 0.65)
    refl = rng.uniform(0.1, 0.6)
    shift = rng.uniform(-0.4, 0.1) * length / 2
    c, s = np.cos(yaw), np.sin(yaw)
    return [
        (BOX, (x, y, z_road + 0.3 + body_h / 2), (length / 2, width / 2, body_h / 2), yaw, label,
         instance, refl),
        (BOX, (x + c * shift, y + s * shift, z_road + 0.3 + body_h + cab_h / 2),
         (length * 0.27, width * 0.45, cab_h / 2), yaw, label, instance, refl),
    ]


#: body types for ``shape_variety``: (length, width, body height, cabin height) ranges in
#: metres, cabin length and width as fractions of the body's, cabin shift range (fraction
#: of half the length, + towards the front)
CAR_TYPES = {
    "hatchback": ((3.5, 4.1), (1.65, 1.8), (0.55, 0.7), (0.55, 0.7), (0.6, 0.75), 0.45,
                  (-0.5, -0.2)),
    "sedan": ((4.3, 4.9), (1.7, 1.85), (0.6, 0.75), (0.45, 0.6), (0.45, 0.55), 0.45,
              (-0.2, 0.1)),
    "estate": ((4.4, 4.9), (1.75, 1.9), (0.6, 0.75), (0.5, 0.62), (0.7, 0.8), 0.46,
               (-0.35, -0.15)),
    "suv": ((4.3, 4.9), (1.8, 2.0), (0.8, 1.0), (0.6, 0.8), (0.6, 0.75), 0.46, (-0.3, -0.1)),
    "van": ((4.6, 5.2), (1.85, 2.0), (1.0, 1.25), (0.7, 0.95), (0.75, 0.85), 0.48,
            (-0.2, -0.1)),
}


def varied_car_rows(rng, x, y, z_road, yaw, label, instance) -> list[tuple]:
    """A parked car of a random body type (``WorldParams.shape_variety``): body and cabin boxes."""
    names = list(CAR_TYPES)
    length_r, width_r, body_r, cab_r, cab_len_r, cab_w, shift_r = CAR_TYPES[
        names[int(rng.integers(len(names)))]]
    length, width = rng.uniform(*length_r), rng.uniform(*width_r)
    body_h, cab_h = rng.uniform(*body_r), rng.uniform(*cab_r)
    cab_len = rng.uniform(*cab_len_r) * length / 2
    shift = rng.uniform(*shift_r) * length / 2
    clearance = rng.uniform(0.15, 0.35)
    refl = rng.uniform(0.1, 0.6)
    c, s = np.cos(yaw), np.sin(yaw)
    return [
        (BOX, (x, y, z_road + clearance + body_h / 2), (length / 2, width / 2, body_h / 2), yaw,
         label, instance, refl),
        (BOX, (x + c * shift, y + s * shift, z_road + clearance + body_h + cab_h / 2),
         (cab_len, width * cab_w, cab_h / 2), yaw, label, instance, refl),
    ]


def crown_rows(rng, x, y, z_top_trunk, rh, rv) -> list[tuple]:
    """A tree crown for ``WorldParams.shape_variety``: one to three lobes, or a conifer."""
    refl = 0.45
    if rng.random() < 0.25:  # conifer: a slim, tall crown starting low, with a narrower top
        rh2 = rh * rng.uniform(0.35, 0.6)
        rv2 = rh * rng.uniform(1.6, 2.6)
        zc = z_top_trunk - 0.5 + rv2
        return [(ELLIPSOID, (x, y, zc), (rh2, rh2, rv2), 0.0, labels.VEGETATION, 0, refl),
                (ELLIPSOID, (x, y, zc + 0.8 * rv2), (0.5 * rh2, 0.5 * rh2, 0.5 * rv2), 0.0,
                 labels.VEGETATION, 0, refl)]
    ax, ay = rh * rng.uniform(0.75, 1.25), rh * rng.uniform(0.75, 1.25)
    rows = [(ELLIPSOID, (x, y, z_top_trunk + 0.8 * rv), (ax, ay, rv), 0.0, labels.VEGETATION, 0,
             refl)]
    for _ in range(int(rng.integers(0, 3))):  # side lobes
        ang = rng.uniform(0, 2 * np.pi)
        off = rh * rng.uniform(0.5, 0.9)
        r = rh * rng.uniform(0.45, 0.75)
        rows.append((ELLIPSOID, (x + off * np.cos(ang), y + off * np.sin(ang),
                                 z_top_trunk + 0.8 * rv + rv * rng.uniform(-0.4, 0.3)),
                     (r, r, r * rng.uniform(0.7, 1.2)), 0.0, labels.VEGETATION, 0, refl))
    return rows


def _side_frame(line: np.ndarray, side: int):
    """``(frame, total)``: the street frame at arc length s along one side (+1 left, -1
    right) of a centre line (point, direction, outward normal, heading), and its length."""
    seg = np.diff(line, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    s_cum = np.concatenate([[0.0], np.cumsum(seglen)])

    def frame(s):
        k = int(np.clip(np.searchsorted(s_cum, s, side="right") - 1, 0, len(seg) - 1))
        u = seg[k] / max(seglen[k], 1e-9)
        pt = line[k] + u * (s - s_cum[k])
        n = np.array([-u[1], u[0]]) * side
        return pt, u, n, np.arctan2(u[1], u[0])

    return frame, float(s_cum[-1])


def _walk_side(placer: _Placer, line: np.ndarray, side: int, part: str = "all") -> None:
    """Place objects along one side (+1 left, -1 right) of a centre line.

    ``part``: "all", or only the "buildings" (with their yards, hedges and walls) or only
    the "street" (trees, poles, parked cars and the rest) for
    :attr:`WorldParams.buildings_first`.
    """
    frame, total = _side_frame(line, side)
    if total < 5:
        return
    if part != "street":
        _walk_buildings(placer, frame, total)
    if part != "buildings":
        _walk_street(placer, frame, total, side)


def _walk_buildings(placer: _Placer, frame, total: float) -> None:
    """Buildings, yards, hedges and walls along one side of a street."""
    rng, p = placer.rng, placer.p
    w, sw = p.road_half_width, p.sidewalk_width
    s = rng.uniform(0, 10)
    while s < total:
        front = rng.uniform(*p.building_front)
        depth = rng.uniform(*p.building_depth)
        setback = rng.uniform(*p.setback)
        pt, u, n, yaw = frame(s + front / 2)
        off = w + sw + setback + depth / 2
        cx, cy = pt + n * off
        byaw = yaw + rng.uniform(-0.08, 0.08)
        if rng.random() < p.empty_lot:
            for _ in range(rng.integers(1, 5)):
                tx, ty = pt + u * rng.uniform(-front / 2, front / 2) + n * (
                    w + sw + rng.uniform(1.5, setback + depth))
                if placer.free(tx, ty, 0.8, 0.8, 0.0, placer.min_building):
                    placer.tree(tx, ty)
        elif placer.free(cx, cy, front / 2, depth / 2, byaw, placer.min_building):
            placer.building(cx, cy, front / 2, depth / 2, byaw)
            if setback > p.hedge_setback and rng.random() < p.hedge:
                hx, hy = pt + n * (w + sw + 0.6)
                if placer.free(hx, hy, front / 2, 0.3, yaw, w + sw + 0.2, pad=0.0):
                    placer.wall(hx, hy, front / 2, rng.uniform(0.15, 0.5), yaw, rng.random() < 0.5)
        gap = 0.0 if rng.random() < p.no_gap else rng.uniform(*p.building_gap)
        if p.gap_fence > 0 and gap > 1.5 and rng.random() < p.gap_fence:
            # a wall or fence across the gap, on the line of this building's façade
            gpt, _, _, gyaw = frame(s + front + gap / 2)
            gx, gy = gpt + n * (w + sw + setback)
            half = gap / 2 - 0.5
            if placer.free(gx, gy, half, 0.2, gyaw, w + sw + 0.2, pad=0.0):
                placer.wall(gx, gy, half, rng.uniform(0.1, 0.3), gyaw, rng.random() < 0.4)
        s += front + gap


def _walk_street(placer: _Placer, frame, total: float, side: int) -> None:
    """Street trees, poles, parked cars (and the dense world's bushes and street furniture)
    along one side of a street."""
    rng, p = placer.rng, placer.p
    w, sw = p.road_half_width, p.sidewalk_width
    # street trees (density varies along the street)
    s = rng.uniform(0, 10)
    while s < total:
        pt, u, n, yaw = frame(s)
        x, y = pt + n * (w + sw - rng.uniform(0.6, 1.2))
        if placer.free(x, y, 0.5, 0.5, 0.0, w + 0.5, w + sw + 0.5, pad=0.0):
            placer.tree(x, y)
        s += rng.uniform(*p.tree_spacing) * (1.0 if rng.random() < p.tree_regular else 3.0)
    # street lights and signs near the kerb
    s = rng.uniform(0, 20)
    while s < total:
        pt, u, n, yaw = frame(s)
        x, y = pt + n * (w + rng.uniform(0.3, 0.7))
        if placer.free(x, y, 0.2, 0.2, 0.0, w + 0.2, w + sw, pad=0.0):
            placer.pole(x, y, yaw, sign=rng.random() < p.sign_fraction)
        s += rng.uniform(*p.light_spacing)
    # parked cars in irregular runs
    s = rng.uniform(0, 30)
    while s < total:
        if rng.random() < p.parked_run:
            for _ in range(rng.integers(*p.parked_run_cars)):
                pt, u, n, yaw = frame(s)
                x, y = pt + n * (w - 1.2)
                if placer.free(x, y, 2.4, 1.0, yaw, w - 2.3, w + 0.2, pad=0.0):
                    placer.car(x, y, yaw + rng.uniform(-0.04, 0.04) + (np.pi if side < 0 else 0))
                s += rng.uniform(*p.parked_spacing)
        s += rng.uniform(*p.parked_gap)
    # bushes on the strip between the sidewalk and the façades (dense worlds only)
    if p.bush_spacing is not None:
        s = rng.uniform(0, 5)
        while s < total:
            pt, u, n, yaw = frame(s)
            r = rng.uniform(0.6, 1.5)
            x, y = pt + n * (w + sw + r + rng.uniform(0.1, 1.5))
            if placer.free(x, y, r, r, 0.0, w + sw, pad=0.0):
                placer.bush(x, y, r, rng.uniform(0.6, 1.2))
            s += rng.uniform(*p.bush_spacing)
    # street furniture on the sidewalk (dense worlds only)
    if p.furniture_spacing is not None:
        s = rng.uniform(0, 10)
        while s < total:
            pt, u, n, yaw = frame(s)
            x, y = pt + n * (w + rng.uniform(0.8, max(sw - 0.6, 0.9)))
            if placer.free(x, y, 0.8, 0.8, yaw, w + 0.3, w + sw, pad=0.0):
                placer.furniture(x, y, yaw)
            s += rng.uniform(*p.furniture_spacing)


def build_world(
    lines: list[np.ndarray],
    rng: np.random.Generator,
    params: WorldParams | None = None,
    height_samples: np.ndarray | None = None,
) -> World:
    """Generate the ground and static objects around road centre ``lines`` ((n,2) each)."""
    p = params or WorldParams()
    lines = [resample_polyline(np.asarray(li, float), 4.0) for li in lines]
    pts = np.concatenate(lines)
    lo = pts.min(0) - p.margin
    hi = pts.max(0) + p.margin
    origin = np.floor(lo)
    shape_r = tuple(int(v) for v in np.ceil((hi - origin) / p.region_cell)[::-1])
    shape_h = tuple(int(v) + 2 for v in np.ceil((hi - origin) / p.height_cell)[::-1])
    band = p.road_half_width + p.sidewalk_width + 2.0
    dist = road_distance(lines, origin, shape_r, p.region_cell, band)
    region = np.full(shape_r, REGION_TERRAIN, dtype=np.uint8)
    region[dist < p.road_half_width + p.sidewalk_width] = REGION_SIDEWALK
    region[dist < p.road_half_width] = REGION_ROAD
    height = _height_raster(origin, shape_h, p.height_cell, p, rng, height_samples)
    ground = Ground((float(origin[0]), float(origin[1])), p.height_cell, height,
                    p.region_cell, region, p.curb)
    placer = _Placer(ground, dist, p, rng)
    parts = ("buildings", "street") if p.buildings_first else ("all",)
    for part in parts:
        for line in lines:
            for side in (1, -1):
                _walk_side(placer, line, side, part)
    starts = np.asarray(placer.object_starts, dtype=np.int64)
    objects = np.searchsorted(starts, np.arange(len(placer.rows)), side="right").astype(np.uint32)
    return World(ground, make_primitives(placer.rows), objects)
