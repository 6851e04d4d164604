"""Sensor presets: the makers' data-sheet geometry of today's LiDARs, in one table.

One :class:`SensorSpec` per ``--sensor`` name feeds both the simulator
(:mod:`lidar_iris_eval.simulate.sensors`: beam layout, fields of view, range,
point rate) and LiDAR Iris's height range (the ``sensors:`` block of
``configs/descriptors/lidar-iris.yaml``). Values come from the makers' data
sheets (named in :attr:`SensorSpec.datasheet`); the mounting height is not a
sensor property but a platform choice, named as such.

Spinning sensors have fixed beams (``elevation_deg``) swept over 360 degrees.
The two Livox sensors scan a non-repetitive rosette: we model a frame as a
random subset, of the data-sheet point count per frame, of a fine
elevation x azimuth grid that covers the field of view (0.5 degree pitch), so
the density is uniform over the field instead of the rosette's
denser-in-the-centre pattern; the Avia keeps only the rays inside its
70.4 degree horizontal field.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorSpec:
    """Data-sheet geometry of one LiDAR (angles in degrees, distances in metres)."""

    name: str
    model: str
    datasheet: str
    #: beam elevations of a spinning sensor; for a non-repetitive scanner, the
    #: rows of the fine grid the frame is drawn from
    elevation_deg: tuple[float, ...]
    #: horizontal field of view, centred on +x
    horizontal_fov: float
    #: rays per beam over a full turn (the simulator's azimuth resolution)
    azimuth_steps: int
    max_range: float
    min_range: float
    #: points per frame (non-repetitive scanners only: the subset drawn per frame)
    points_per_frame: int | None
    #: mounting height above the road: a platform choice, not a data-sheet value
    mount_height: float
    pattern: str = "spinning"
    range_noise: float = 0.02

    @property
    def channels(self) -> int:
        return len(self.elevation_deg)

    @property
    def vertical_fov(self) -> tuple[float, float]:
        return min(self.elevation_deg), max(self.elevation_deg)


def _even(low: float, high: float, n: int) -> tuple[float, ...]:
    return tuple(float(v) for v in np.linspace(low, high, n))


def _hdl64() -> tuple[float, ...]:
    # two blocks of 32 lasers: +2 .. -8.33 (about 1/3 deg apart), -8.83 .. -24.9 (about 1/2 deg)
    return _even(2.0, -8.33, 32) + _even(-8.83, -24.9, 32)


#: VLP-32C (Ultra Puck) laser elevations from its user manual's channel table:
#: dense (1/3 deg) around the horizon, sparse towards -25 and +15 deg
_VLP32C = (
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333,
    -3.0, -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667,
    1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0,
)  # fmt: skip

SENSORS: dict[str, SensorSpec] = {
    s.name: s
    for s in (
        SensorSpec("hdl64", "Velodyne HDL-64E", "Velodyne HDL-64E S2/S3 data sheet",
                   _hdl64(), 360.0, 2048, 80.0, 2.5, None, 1.73, range_noise=0.02),
        SensorSpec("hdl32", "Velodyne HDL-32E", "Velodyne HDL-32E data sheet",
                   _even(-30.67, 10.67, 32), 360.0, 2048, 100.0, 1.0, None, 1.8),
        SensorSpec("vlp16", "Velodyne VLP-16 (Puck)", "Velodyne VLP-16 data sheet",
                   _even(-15.0, 15.0, 16), 360.0, 1800, 100.0, 1.0, None, 2.0,
                   range_noise=0.03),
        SensorSpec("vlp32", "Velodyne VLP-32C (Ultra Puck)",
                   "Velodyne Ultra Puck VLP-32C data sheet and user manual",
                   _VLP32C, 360.0, 1800, 200.0, 1.0, None, 1.8),
        SensorSpec("os0-128", "Ouster OS0-128", "Ouster OS0 Rev 6 data sheet",
                   _even(-45.0, 45.0, 128), 360.0, 1024, 50.0, 0.5, None, 1.0),
        SensorSpec("os1-64", "Ouster OS1-64", "Ouster OS1 Rev 6 data sheet",
                   _even(-22.5, 22.5, 64), 360.0, 1024, 120.0, 0.5, None, 1.8),
        SensorSpec("os1-128", "Ouster OS1-128", "Ouster OS1 Rev 6 data sheet",
                   _even(-22.5, 22.5, 128), 360.0, 1024, 120.0, 0.5, None, 1.8),
        SensorSpec("os2-128", "Ouster OS2-128", "Ouster OS2 Rev 6 data sheet",
                   _even(-11.25, 11.25, 128), 360.0, 1024, 240.0, 1.0, None, 1.8),
        SensorSpec("mid360", "Livox Mid-360", "Livox Mid-360 user manual / specs",
                   _even(-7.0, 52.0, 119), 360.0, 720, 70.0, 0.1, 20_000, 1.0,
                   pattern="non-repetitive"),
        SensorSpec("avia", "Livox Avia", "Livox Avia user manual / specs",
                   _even(-38.6, 38.6, 155), 70.4, 1440, 190.0, 1.0, 24_000, 1.5,
                   pattern="non-repetitive"),
    )
}


def get_spec(name: str) -> SensorSpec:
    """The named sensor preset (a :class:`~lidar_iris_eval.errors.LirisError` if unknown)."""
    from lidar_iris_eval.errors import LirisError

    if name not in SENSORS:
        raise LirisError("--sensor", f"unknown sensor {name!r}; choose from {', '.join(SENSORS)}")
    return SENSORS[name]
