"""LiDAR models and the per-scan ray caster.

Every sensor preset of :mod:`lidar_iris_eval.sensors` (data-sheet beam layout,
fields of view, range, point rate; a chosen mounting height) becomes a
:class:`SensorModel`. ``hdl64`` mimics the Velodyne HDL-64E of KITTI: two
blocks of 32 lasers, the upper from +2 deg to -8.33 deg (about 1/3 deg apart),
the lower from -8.83 deg to -24.9 deg (about 1/2 deg apart), mounted 1.73 m
above the road, 2048 azimuth steps per turn (KITTI scans have about 120k
points); its range is cut at 80 m like KITTI's scans. ``vlp16``: 16 lasers
every 2 deg over +/-15 deg, 2 m high, 1800 steps per turn at 10 Hz. The Livox
scanners (``mid360``, ``avia``) are non-repetitive: a frame is a random subset
(the data-sheet points per frame) of a fine grid over their field of view,
and the Avia keeps only rays within its 70.4 deg horizontal field. All add
Gaussian range noise, random dropout (heavier at grazing incidence and long
range) and a maximum range.

Points are returned in the sensor frame (x forward, y left, z up), like KITTI
``velodyne/*.bin``. The scan is instantaneous (no motion distortion).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.sensors import SENSORS as SENSOR_SPECS
from lidar_iris_eval.sensors import SensorSpec
from lidar_iris_eval.simulate.ground import REGION_LABEL, Ground, cast_ground
from lidar_iris_eval.simulate.labels import REFLECTIVITY
from lidar_iris_eval.simulate.raycast import (
    Primitives,
    RayGrid,
    cast_primitives,
    surface_normals,
)


@dataclass(frozen=True)
class SensorModel:
    """Geometry and noise of one spinning LiDAR."""

    name: str
    elevation_deg: tuple[float, ...]
    azimuth_steps: int
    mount_height: float
    max_range: float
    min_range: float = 2.0
    range_noise: float = 0.02  # metres, 1 sigma
    dropout: float = 0.02  # base probability of a missing return
    intensity_noise: float = 0.03
    horizontal_fov: float = 360.0  # degrees, centred on +x
    points_per_frame: int | None = None  # non-repetitive scanners: rays kept per frame

    @property
    def grid(self) -> RayGrid:
        return RayGrid(np.deg2rad(np.sort(np.asarray(self.elevation_deg))), self.azimuth_steps)


def _model(spec: SensorSpec) -> SensorModel:
    return SensorModel(
        spec.name, spec.elevation_deg, spec.azimuth_steps, spec.mount_height, spec.max_range,
        spec.min_range, spec.range_noise, 0.02, horizontal_fov=spec.horizontal_fov,
        points_per_frame=spec.points_per_frame,
    )


SENSORS: dict[str, SensorModel] = {name: _model(spec) for name, spec in SENSOR_SPECS.items()}


def get_sensor(name: str, azimuth_steps: int | None = None) -> SensorModel:
    """The named sensor model, optionally at a different azimuth resolution."""
    if name not in SENSORS:
        raise LirisError("--sensor", f"unknown sensor {name!r}; choose from {', '.join(SENSORS)}")
    sensor = SENSORS[name]
    if azimuth_steps is not None:
        if azimuth_steps < 8:
            raise LirisError("--azimuth-steps", f"must be at least 8, got {azimuth_steps}")
        sensor = replace(sensor, azimuth_steps=int(azimuth_steps))
    return sensor


def _frame_rays(sensor: SensorModel, dirs_s: np.ndarray, rng) -> np.ndarray:
    """Rays a limited-field or non-repetitive scanner fires in one frame (bool per ray).

    Rays outside the horizontal field are never fired. A non-repetitive
    scanner fires ``points_per_frame`` rays drawn at random among the rest (a
    uniform stand-in for the rosette); without ``rng``, an even stride.
    """
    fired = np.ones(len(dirs_s), dtype=bool)
    if sensor.horizontal_fov < 360.0:
        azimuth = np.degrees(np.arctan2(dirs_s[:, 1], dirs_s[:, 0]))
        fired &= np.abs(azimuth) <= sensor.horizontal_fov / 2
    if sensor.points_per_frame is not None:
        inside = np.nonzero(fired)[0]
        n = min(sensor.points_per_frame, len(inside))
        if rng is None:
            chosen = inside[np.linspace(0, len(inside) - 1, n).astype(np.int64)]
        else:
            chosen = rng.choice(inside, size=n, replace=False)
        fired[:] = False
        fired[chosen] = True
    return fired


_REFL_LUT = np.zeros(max(REFLECTIVITY) + 1)
for _code, _value in REFLECTIVITY.items():
    _REFL_LUT[_code] = _value


@dataclass(frozen=True)
class ScanResult:
    """One simulated scan in the sensor frame (after noise and dropout)."""

    points: np.ndarray  # (N, 3) float32
    intensity: np.ndarray  # (N,) float32 in [0, 1]
    label: np.ndarray  # (N,) uint32: class | instance << 16
    ray: np.ndarray  # (N,) index into the sensor's ray grid
    row: np.ndarray  # (N,) primitive row hit, -1 for ground


def simulate_scan(
    sensor: SensorModel,
    ground: Ground,
    prims: Primitives,
    pose: np.ndarray,
    rng: np.random.Generator | None,
    directions: np.ndarray | None = None,
) -> ScanResult:
    """Cast every ray of ``sensor`` at ``pose`` (4x4 sensor-to-world).

    ``prims`` should already be culled to the sensor's neighbourhood. With
    ``rng=None`` the scan is noise-free and nothing drops out (for tests).
    ``directions`` may pass precomputed sensor-frame ray directions.
    """
    grid = sensor.grid
    dirs_s = grid.directions if directions is None else directions
    rot = pose[:3, :3]
    origin = pose[:3, 3].astype(np.float64)
    # explicit products: a BLAS call for (N,3)@(3,3) is slower and threads
    dirs_w = dirs_s[:, :1] * rot[:, 0] + dirs_s[:, 1:2] * rot[:, 1] + dirs_s[:, 2:] * rot[:, 2]
    t_g, region, n_g = cast_ground(ground, origin, dirs_w, sensor.max_range)
    t_p, row, aux = cast_primitives(prims, origin, rot, grid, dirs_w, sensor.max_range)
    use_p = t_p < t_g
    t = np.where(use_p, t_p, t_g)
    valid = np.isfinite(t) & (t >= sensor.min_range)
    if sensor.horizontal_fov < 360.0 or sensor.points_per_frame is not None:
        valid &= _frame_rays(sensor, dirs_s, rng)
    idx = np.nonzero(valid)[0]
    t, use_p = t[idx], use_p[idx]
    d_w = dirs_w[idx]
    prow = np.where(use_p, row[idx], -1)

    cls = REGION_LABEL[region[idx]].astype(np.uint32)
    inst = np.zeros(len(idx), dtype=np.uint32)
    refl = np.empty(len(idx), dtype=np.float64)
    refl[:] = 0.3
    normal = n_g[idx]
    pr = prow[use_p]
    if len(pr):
        cls[use_p] = prims.label[pr]
        inst[use_p] = prims.instance[pr]
        hit_w = origin + t[use_p, None] * d_w[use_p]
        normal[use_p] = surface_normals(prims, pr, hit_w, aux[idx][use_p])
        refl[use_p] = prims.reflectivity[pr]
    ground_sel = ~use_p
    refl[ground_sel] = _REFL_LUT[cls[ground_sel]]
    cos_inc = np.abs((normal * d_w).sum(1))

    if rng is not None:
        # dropout: base rate, more at grazing incidence and near max range
        p_drop = sensor.dropout + 0.3 * (cos_inc < 0.1) + 0.2 * (t / sensor.max_range) ** 4
        keep = rng.random(len(t)) >= p_drop
        noise = rng.normal(0.0, sensor.range_noise, len(t))
        inten_noise = rng.normal(0.0, sensor.intensity_noise, len(t))
        keep &= (t + noise) >= sensor.min_range
        t = t + noise
    else:
        keep = np.ones(len(t), dtype=bool)
        inten_noise = np.zeros(len(t))
    intensity = np.clip(refl * (0.35 + 0.65 * cos_inc) + inten_noise, 0.0, 0.99)
    sel = np.nonzero(keep)[0]
    points = (t[sel, None] * dirs_s[idx[sel]]).astype(np.float32)
    return ScanResult(
        points=points,
        intensity=intensity[sel].astype(np.float32),
        label=(cls[sel] | (inst[sel] << np.uint32(16))).astype(np.uint32),
        ray=idx[sel],
        row=prow[sel],
    )
