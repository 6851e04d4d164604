"""Natural worlds: a forest and a park around a network of trails with loops.

The ESM paper (Tinchev et al., RA-L 2019) localises in forests and a park as
well as in cities; these worlds are its simulated stand-ins. They reuse the
urban machinery: the trail network is a street grid (``street_grid``) whose
lines are bent by a smooth meander field, the route is a grid route
(``same``/``reverse``/``mixed``, so revisits are known) driven slowly along the
bent trails, the ground is a :class:`~lidar_iris_eval.simulate.ground.Ground`
(no kerb; the trail or path is region "sidewalk", the rest "terrain") and every
object is made of the ray caster's boxes, vertical cylinders and ellipsoids.

``forest``
    uneven terrain (smooth hills of about ``relief`` metres plus small bumps, a
    slope across the whole world); broadleaf trees (a trunk, a vertical leader,
    main branches as thin yawed boxes stepping upwards, a crown of foliage
    clumps) and conifers (trunk, whorls of shrinking ellipsoids, a few dead
    lower branches); undergrowth (bushes and ferns), fallen logs and rocks;
    clearings at trail junctions.
``park``
    gentle lawns, broadleaf tree groups and solitary trees, paths with benches
    and lamp posts, and a few low buildings at the edge of the park.

**Season.** ``leaf-on`` (summer) or ``leaf-off`` (winter). The world is drawn
from the same random numbers in both seasons and then filtered, so two
sessions of one forest in different seasons hold the same trunks, branches,
conifers, logs, rocks and terrain; leaf-off removes every broadleaf foliage
clump and most undergrowth (:data:`UNDERGROWTH_GONE`), and shrinks what stays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.ground import REGION_SIDEWALK, REGION_TERRAIN, Ground
from lidar_iris_eval.simulate.raycast import BOX, CYLINDER, ELLIPSOID, make_primitives
from lidar_iris_eval.simulate.world import World, WorldParams, _Placer, road_distance

SEASONS = ("leaf-on", "leaf-off")
#: leaf-off: the fraction of undergrowth that is gone (the rest shrinks to :data:`LEAF_OFF_SHRINK`)
UNDERGROWTH_GONE = 0.65
LEAF_OFF_SHRINK = 0.6

# season tags of a row
_KEEP, _FOLIAGE, _UNDER = 0, 1, 2


@dataclass(frozen=True)
class NatureParams:
    """Layout, terrain and object densities of a natural world (metres, per 100 m²)."""

    kind: str  # "forest" or "park"
    trail_half_width: float = 1.2
    margin: float = 40.0  # beyond the outermost trail ends
    region_cell: float = 0.5
    height_cell: float = 2.0
    #: terrain: standard deviation of the hills (m), their length scale (m), small bumps
    #: (m, about 3 m across) and the largest grade of the tilt of the whole world
    relief: float = 1.5
    relief_scale: float = 18.0
    roughness: float = 0.12
    max_grade: float = 0.05
    #: trail meander: amplitude (m) and wavelength range (m) of the bending field
    meander: float = 3.0
    meander_wavelength: tuple[float, float] = (40.0, 70.0)
    #: no object within this radius of a trail junction (room for the route's U-turns)
    junction_clearing: float = 5.0
    #: trees per 100 m², the conifer share, trunk clearance from the trail centre
    tree_density: float = 3.0
    conifer_fraction: float = 0.4
    tree_clearance: float = 2.2
    #: park: tree groups per hectare and trees per group (high end excluded)
    tree_groups: float = 0.0
    group_trees: tuple[int, int] = (3, 9)
    undergrowth_density: float = 4.0
    log_density: float = 0.15
    rock_density: float = 0.2
    #: park: benches and lamp posts along the paths (spacing range, m); None: none
    bench_spacing: tuple[float, float] | None = None
    lamp_spacing: tuple[float, float] | None = None
    #: park: low buildings at the edge
    buildings: int = 0
    #: how the platform moves: metres per frame, lane offset is SimConfig.lateral_max,
    #: roll/pitch noise (deg, on top of the slope), corner smoothing and U-turn radius (m)
    step: float = 0.5
    tilt_noise_deg: float = 1.0
    smoothing: float = 2.0
    uturn_radius: float = 2.0
    newton_steps: int = 6


#: platforms of ``SimConfig.platform``
PLATFORMS = ("ugv", "handheld")


@dataclass(frozen=True)
class Handheld:
    """A walking operator: low, slow, swaying (``--platform handheld``)."""

    mount_height: float = 1.5  # sensor above the ground (m), whatever the sensor preset says
    step: float = 0.3  # metres a frame (3 m/s at 10 Hz would be running: a brisk walk at 0.1 s
    #                    frames is 0.15; 0.3 keeps a lap of the small grid within ~250 frames)
    sway_deg: float = 3.0  # roll and pitch, 1 sigma, smooth over ``sway_frames``
    sway_frames: float = 6.0
    heading_noise_deg: float = 4.0


HANDHELD = Handheld()

FOREST = NatureParams(kind="forest")
PARK = NatureParams(
    kind="park", trail_half_width=1.5, relief=0.3, relief_scale=30.0, roughness=0.03,
    max_grade=0.02, meander=2.0, tree_density=0.15, conifer_fraction=0.15,
    tree_clearance=3.0, tree_groups=6.0, undergrowth_density=0.15, log_density=0.0,
    rock_density=0.01, bench_spacing=(20.0, 50.0), lamp_spacing=(25.0, 40.0), buildings=5,
    step=0.6, tilt_noise_deg=0.5, junction_clearing=4.0,
)
#: named natural worlds (``SimConfig.world_style``)
NATURE_STYLES: dict[str, NatureParams] = {"forest": FOREST, "park": PARK}


def nature_params(style: str) -> NatureParams:
    if style not in NATURE_STYLES:
        raise LirisError(None, f"unknown natural world {style!r}; choose from "
                               f"{', '.join(NATURE_STYLES)}")
    return NATURE_STYLES[style]


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True)
class Meander:
    """Smooth bending: ``x += a sin(2 pi y / lx + px)``, ``y += a sin(2 pi x / ly + py)``"""

    amplitude: float
    wavelength: tuple[float, float]
    phase: tuple[float, float]

    @staticmethod
    def draw(rng: np.random.Generator, p: NatureParams) -> Meander:
        lx, ly = rng.uniform(*p.meander_wavelength, 2)
        px, py = rng.uniform(0, 2 * np.pi, 2)
        return Meander(p.meander, (float(lx), float(ly)), (float(px), float(py)))

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        a, (lx, ly), (px, py) = self.amplitude, self.wavelength, self.phase
        return np.stack([xy[:, 0] + a * np.sin(2 * np.pi * xy[:, 1] / lx + px),
                         xy[:, 1] + a * np.sin(2 * np.pi * xy[:, 0] / ly + py)], 1)


def trail_lines(xs: np.ndarray, ys: np.ndarray, meander: Meander,
                extend: float) -> list[np.ndarray]:
    """The grid lines (extended by ``extend`` m past the outer ones), bent, 1 m apart."""
    out = []
    for x in xs:
        y = np.arange(ys[0] - extend, ys[-1] + extend + 0.5, 1.0)
        out.append(meander(np.stack([np.full_like(y, x), y], 1)))
    for y in ys:
        x = np.arange(xs[0] - extend, xs[-1] + extend + 0.5, 1.0)
        out.append(meander(np.stack([x, np.full_like(x, y)], 1)))
    return out


def _terrain(origin, shape, p: NatureParams, rng: np.random.Generator) -> np.ndarray:
    """Heights at the raster corners: hills + bumps + a tilt of the whole world."""
    hills = ndimage.gaussian_filter(rng.normal(size=shape), p.relief_scale / p.height_cell,
                                    mode="wrap")
    hills *= p.relief / max(float(hills.std()), 1e-12)
    bumps = ndimage.gaussian_filter(rng.normal(size=shape), 1.5 / p.height_cell, mode="wrap")
    bumps *= p.roughness / max(float(bumps.std()), 1e-12)
    grade = rng.uniform(0.3, 1.0) * p.max_grade
    heading = rng.uniform(0, 2 * np.pi)
    ys = np.arange(shape[0]) * p.height_cell
    xs = np.arange(shape[1]) * p.height_cell
    X, Y = np.meshgrid(xs - xs.mean(), ys - ys.mean())
    return hills + bumps + grade * (np.cos(heading) * X + np.sin(heading) * Y)


# --------------------------------------------------------------------------- objects


class _NaturePlacer(_Placer):
    """The urban placer's occupancy checks, plus a season tag per row."""

    def __init__(self, ground: Ground, dist: np.ndarray, rng, p: NatureParams):
        super().__init__(ground, dist, WorldParams(curb=0.0), rng)
        self.np = p
        self.tags: list[int] = []
        self.shrink_draw: list[float] = []

    def add(self, row: tuple, tag: int = _KEEP) -> None:
        self.rows.append(row)
        self.tags.append(tag)
        # undergrowth draws whether it survives the winter in every season
        self.shrink_draw.append(float(self.rng.random()) if tag == _UNDER else 1.0)

    # trees --------------------------------------------------------------
    def broadleaf(self, x: float, y: float, scale: float = 1.0) -> None:
        self._new_object()
        rng = self.rng
        z0 = self.base(x, y)
        height = rng.uniform(11.0, 22.0) * scale
        fork = rng.uniform(2.5, 6.0) * scale
        r = rng.uniform(0.15, 0.4) * scale
        self.add((CYLINDER, (x, y, z0 + fork / 2 - 0.3), (r, r, fork / 2 + 0.3), 0.0,
                  labels.TRUNK, 0, 0.35))
        lead_h = height * 0.75 - fork
        rl = r * 0.55
        self.add((CYLINDER, (x, y, z0 + fork + lead_h / 2), (rl, rl, lead_h / 2), 0.0,
                  labels.TRUNK, 0, 0.35))
        spread = rng.uniform(0.25, 0.4) * height
        tips = []
        for _ in range(int(rng.integers(4, 8))):  # main branches, two steps each
            yaw = rng.uniform(0, 2 * np.pi)
            z = z0 + fork + rng.uniform(0.0, 0.5) * lead_h
            length = spread * rng.uniform(0.6, 1.0)
            rise = rng.uniform(0.3, 0.8) * length
            br = max(r * 0.3, 0.05)
            c, s = np.cos(yaw), np.sin(yaw)
            for j in range(2):
                mid = (j + 0.5) * length / 2
                self.add((BOX, (x + c * mid, y + s * mid, z + (j + 0.5) * rise / 2),
                          (length / 4, br * (1 - 0.35 * j), br * (1 - 0.35 * j)), yaw,
                          labels.TRUNK, 0, 0.35))
            tips.append((x + c * length, y + s * length, z + rise))
        top = z0 + height * 0.75
        tips.append((x, y, top))
        for tx, ty, tz in tips:  # leaf-on crown: foliage clumps around the branch tips
            for _ in range(int(rng.integers(1, 4))):
                cr = rng.uniform(0.7, 1.6) * scale
                off = rng.normal(0.0, 0.6, 3) * scale
                self.add((ELLIPSOID, (tx + off[0], ty + off[1], tz + abs(off[2])),
                          (cr, cr * rng.uniform(0.8, 1.2), cr * rng.uniform(0.6, 0.9)), 0.0,
                          labels.VEGETATION, 0, 0.45), _FOLIAGE)
        self.claim(x, y, r + 0.4, r + 0.4, 0.0)

    def conifer(self, x: float, y: float, scale: float = 1.0) -> None:
        self._new_object()
        rng = self.rng
        z0 = self.base(x, y)
        height = rng.uniform(12.0, 26.0) * scale
        r = rng.uniform(0.12, 0.3) * scale
        self.add((CYLINDER, (x, y, z0 + height / 2 - 0.3), (r, r, height / 2 + 0.3), 0.0,
                  labels.TRUNK, 0, 0.35))
        crown_base = height * rng.uniform(0.3, 0.55)
        width = rng.uniform(0.16, 0.24) * height
        whorls = int(rng.integers(5, 9))
        dz = (height - crown_base) / whorls
        for k in range(whorls):  # evergreen: the same in both seasons
            f = 1.0 - k / whorls
            rr = max(width * f, 0.3)
            self.add((ELLIPSOID, (x, y, z0 + crown_base + (k + 0.5) * dz),
                      (rr, rr, 0.55 * dz + 0.2), 0.0, labels.VEGETATION, 0, 0.4))
        for _ in range(int(rng.integers(0, 4))):  # dead lower branches
            yaw = rng.uniform(0, 2 * np.pi)
            length = rng.uniform(0.6, 1.8)
            z = z0 + rng.uniform(1.5, max(crown_base, 1.6))
            c, s = np.cos(yaw), np.sin(yaw)
            self.add((BOX, (x + c * length / 2, y + s * length / 2, z), (length / 2, 0.03, 0.03),
                      yaw, labels.TRUNK, 0, 0.3))
        self.claim(x, y, r + 0.4, r + 0.4, 0.0)

    def tree(self, x: float, y: float, conifer_fraction: float, scale: float = 1.0) -> None:
        if self.rng.random() < conifer_fraction:
            self.conifer(x, y, scale)
        else:
            self.broadleaf(x, y, scale)

    # ground cover -------------------------------------------------------
    def undergrowth(self, x: float, y: float) -> None:
        self._new_object()
        rng = self.rng
        z0 = self.base(x, y)
        if rng.random() < 0.5:  # a bush
            rx, ry, h = rng.uniform(0.4, 1.1), rng.uniform(0.4, 1.1), rng.uniform(0.3, 0.8)
        else:  # a fern or bramble patch: wide and low
            rx, ry, h = rng.uniform(0.5, 1.3), rng.uniform(0.5, 1.3), rng.uniform(0.15, 0.35)
        self.add((ELLIPSOID, (x, y, z0 + 0.5 * h), (rx, ry, h), 0.0, labels.VEGETATION, 0,
                  0.45), _UNDER)

    def log(self, x: float, y: float) -> None:
        rng = self.rng
        length, r = rng.uniform(2.5, 9.0), rng.uniform(0.12, 0.35)
        yaw = rng.uniform(0, np.pi)
        if not self.free(x, y, length / 2, r, yaw, self.np.trail_half_width + 0.5, pad=0.1):
            return
        self._new_object()
        self.add((BOX, (x, y, self.base(x, y) + 0.6 * r), (length / 2, r, r), yaw,
                  labels.TRUNK, 0, 0.3))
        self.claim(x, y, length / 2, r, yaw)

    def rock(self, x: float, y: float) -> None:
        self._new_object()
        rng = self.rng
        big = rng.random() < 0.2
        rx = rng.uniform(0.6, 1.8) if big else rng.uniform(0.2, 0.6)
        ry, rz = rx * rng.uniform(0.6, 1.0), rx * rng.uniform(0.4, 0.8)
        self.add((ELLIPSOID, (x, y, self.base(x, y) + 0.2 * rz), (rx, ry, rz), 0.0,
                  labels.OTHER_OBJECT, 0, 0.3))
        self.claim(x, y, rx, ry, 0.0)

    # park furniture -----------------------------------------------------
    def bench(self, x: float, y: float, yaw: float) -> None:
        self._new_object()
        z0 = self.base(x, y)
        c, s = np.cos(yaw), np.sin(yaw)
        self.add((BOX, (x, y, z0 + 0.23), (0.9, 0.22, 0.23), yaw, labels.OTHER_OBJECT, 0, 0.3))
        self.add((BOX, (x - s * 0.22, y + c * 0.22, z0 + 0.65), (0.9, 0.03, 0.22), yaw,
                  labels.OTHER_OBJECT, 0, 0.3))
        self.claim(x, y, 0.9, 0.3, yaw)

    def lamp(self, x: float, y: float) -> None:
        self._new_object()
        h, r = self.rng.uniform(3.5, 4.5), 0.06
        self.add((CYLINDER, (x, y, self.base(x, y) + h / 2 - 0.2), (r, r, h / 2 + 0.2), 0.0,
                  labels.POLE, 0, 0.4))
        self.claim(x, y, 0.2, 0.2, 0.0)

    def building(self, x: float, y: float, hx: float, hy: float, yaw: float) -> None:
        self._new_object()
        h = self.rng.uniform(3.0, 6.5)
        z0 = self.base(x, y) - 1.0
        self.add((BOX, (x, y, z0 + (h + 1) / 2), (hx, hy, (h + 1) / 2), yaw, labels.BUILDING, 0,
                  float(self.rng.uniform(0.25, 0.5))))
        self.claim(x, y, hx, hy, yaw)


def _scatter(placer: _NaturePlacer, rng, density: float, lo, hi, min_dist: float, radius: float,
             place) -> None:
    """Uniform random candidates (``density`` per 100 m²) placed where there is room."""
    area = float(np.prod(np.asarray(hi) - np.asarray(lo)))
    n = int(rng.poisson(density * area / 100.0))
    xs = rng.uniform(lo[0], hi[0], n)
    ys = rng.uniform(lo[1], hi[1], n)
    for x, y in zip(xs, ys, strict=True):
        if placer.free(x, y, radius, radius, 0.0, min_dist, pad=0.0):
            place(float(x), float(y))


def _along(placer: _NaturePlacer, rng, lines, spacing, offset: float, place) -> None:
    """Objects every ``spacing`` m along both sides of every trail, ``offset`` m from it."""
    for line in lines:
        seg = np.diff(line, axis=0)
        seglen = np.linalg.norm(seg, axis=1)
        s_cum = np.concatenate([[0.0], np.cumsum(seglen)])
        for side in (1, -1):
            s = rng.uniform(0, spacing[1])
            while s < s_cum[-1]:
                k = int(np.clip(np.searchsorted(s_cum, s, side="right") - 1, 0, len(seg) - 1))
                u = seg[k] / max(seglen[k], 1e-9)
                n = np.array([-u[1], u[0]]) * side
                pt = line[k] + u * (s - s_cum[k]) + n * offset
                yaw = float(np.arctan2(u[1], u[0]) + (np.pi if side > 0 else 0.0))
                if placer.free(pt[0], pt[1], 0.9, 0.4, yaw, offset - 0.3, pad=0.0):
                    place(float(pt[0]), float(pt[1]), yaw)
                s += rng.uniform(*spacing)


def build_nature_world(lines: list[np.ndarray], nodes: np.ndarray, rng: np.random.Generator,
                       p: NatureParams, season: str) -> World:
    """The ground and objects of a natural world around trail ``lines`` (module docstring)."""
    if season not in SEASONS:
        raise LirisError("--season", f"must be one of {', '.join(SEASONS)}, got {season!r}")
    pts = np.concatenate(lines)
    lo = pts.min(0) - p.margin
    hi = pts.max(0) + p.margin
    origin = np.floor(lo)
    shape_r = tuple(int(v) for v in np.ceil((hi - origin) / p.region_cell)[::-1])
    shape_h = tuple(int(v) + 2 for v in np.ceil((hi - origin) / p.height_cell)[::-1])
    band = 12.0
    dist = road_distance(lines, origin, shape_r, p.region_cell, band)
    region = np.full(shape_r, REGION_TERRAIN, dtype=np.uint8)
    region[dist < p.trail_half_width] = REGION_SIDEWALK
    height = _terrain(origin, shape_h, p, rng)
    ground = Ground((float(origin[0]), float(origin[1])), p.height_cell, height,
                    p.region_cell, region, 0.0, p.newton_steps)
    # nothing in the junction clearings: their cells count as on the trail for placing
    cy = origin[1] + (np.arange(shape_r[0]) + 0.5) * p.region_cell
    cx = origin[0] + (np.arange(shape_r[1]) + 0.5) * p.region_cell
    place_dist = dist.copy()
    for nx, ny in nodes:
        i0, i1 = np.searchsorted(cx, [nx - p.junction_clearing, nx + p.junction_clearing])
        j0, j1 = np.searchsorted(cy, [ny - p.junction_clearing, ny + p.junction_clearing])
        d = np.hypot(cx[None, i0:i1] - nx, cy[j0:j1, None] - ny)
        view = place_dist[j0:j1, i0:i1]
        view[d < p.junction_clearing] = 0.0
    placer = _NaturePlacer(ground, place_dist, rng, p)
    inner_lo, inner_hi = lo + 1.0, hi - 1.0
    if p.buildings:  # park: low buildings in the outer ring of the world
        tries = 0
        placed = 0
        while placed < p.buildings and tries < 200:
            tries += 1
            hx, hy = rng.uniform(4.0, 10.0), rng.uniform(3.0, 6.0)
            x, y = rng.uniform(inner_lo[0], inner_hi[0]), rng.uniform(inner_lo[1], inner_hi[1])
            edge = min(x - lo[0], hi[0] - x, y - lo[1], hi[1] - y)
            yaw = float(rng.choice([0.0, np.pi / 2]) + rng.uniform(-0.1, 0.1))
            if edge < 25.0 and placer.free(x, y, hx, hy, yaw, p.trail_half_width + 4.0):
                placer.building(x, y, hx, hy, yaw)
                placed += 1
    if p.bench_spacing is not None:
        _along(placer, rng, lines, p.bench_spacing, p.trail_half_width + 0.8,
               lambda x, y, yaw: placer.bench(x, y, yaw))
    if p.lamp_spacing is not None:
        _along(placer, rng, lines, p.lamp_spacing, p.trail_half_width + 0.5,
               lambda x, y, yaw: placer.lamp(x, y))
    if p.tree_groups > 0:  # park: groups of trees on the lawns
        area = float(np.prod(inner_hi - inner_lo))
        for _ in range(int(rng.poisson(p.tree_groups * area / 10_000.0))):
            gx, gy = rng.uniform(inner_lo[0], inner_hi[0]), rng.uniform(inner_lo[1], inner_hi[1])
            for _ in range(int(rng.integers(*p.group_trees))):
                x, y = gx + rng.normal(0, 4.0), gy + rng.normal(0, 4.0)
                if placer.free(x, y, 0.8, 0.8, 0.0, p.tree_clearance, pad=0.0):
                    placer.tree(x, y, p.conifer_fraction, rng.uniform(0.7, 1.1))
    _scatter(placer, rng, p.tree_density, inner_lo, inner_hi, p.tree_clearance, 0.8,
             lambda x, y: placer.tree(x, y, p.conifer_fraction))
    _scatter(placer, rng, p.log_density, inner_lo, inner_hi, p.trail_half_width + 0.5, 0.3,
             placer.log)
    _scatter(placer, rng, p.rock_density, inner_lo, inner_hi, p.trail_half_width + 0.4, 0.6,
             placer.rock)
    _scatter(placer, rng, p.undergrowth_density, inner_lo, inner_hi, p.trail_half_width + 0.3,
             0.4, placer.undergrowth)
    starts = np.asarray(placer.object_starts, dtype=np.int64)
    objects = np.searchsorted(starts, np.arange(len(placer.rows)), side="right").astype(np.uint32)
    rows, keep = _season(placer, season)
    return World(ground, make_primitives(rows), objects[keep])


def _season(placer: _NaturePlacer, season: str) -> tuple[list[tuple], np.ndarray]:
    """The rows standing in ``season`` (leaf-off: no foliage, less and smaller undergrowth)."""
    tags = np.asarray(placer.tags, dtype=np.int64)
    if season == "leaf-on":
        return placer.rows, np.arange(len(tags))
    draw = np.asarray(placer.shrink_draw)
    keep = np.nonzero((tags == _KEEP) | ((tags == _UNDER) & (draw >= UNDERGROWTH_GONE)))[0]
    rows = []
    for k in keep:
        row = placer.rows[k]
        if tags[k] == _UNDER:
            kind, (x, y, z), (rx, ry, rz), yaw, cls, inst, refl = row
            f = LEAF_OFF_SHRINK
            base = z - 0.5 * rz
            row = (kind, (x, y, base + 0.5 * rz * f), (rx * f, ry * f, rz * f), yaw, cls, inst,
                   refl)
        rows.append(row)
    return rows, keep
