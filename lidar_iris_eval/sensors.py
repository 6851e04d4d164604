"""Sensor presets: the makers' data-sheet geometry of today's LiDARs, in one table.

One :class:`SensorSpec` per ``--sensor`` name feeds both the simulator
(:mod:`lidar_iris_eval.simulate.sensors`: beam layout, fields of view, range,
point rate) and LiDAR Iris's height range (the ``sensors:`` block of
``lidar_iris_eval/descriptors/lidar_iris/presets.yaml``). Values come from the makers' data
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
        # the first-generation OS1-64 of MulRan (2019) and Newer College (2020): the
        # 2018-2019 OS1 data sheet gives +16.6 .. -16.6 deg (33.2) for 64 channels
        SensorSpec("os1-64-gen1", "Ouster OS1-64 (Gen 1)", "Ouster OS1 data sheet (2018-2019)",
                   _even(-16.6, 16.6, 64), 360.0, 1024, 120.0, 0.8, None, 1.8),
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


# ------------------------------------------------------------ recognising a sensor

#: scans read to guess the sensor and to check a preset against the data
SAMPLE_SCANS = 3
#: degrees of lowest-beam mismatch that cost as much as a factor 2 in beam count
_EDGE_SCALE = 1.5


@dataclass(frozen=True)
class ScanGeometry:
    """What the guess looks at in one scan (degrees)."""

    lowest: float  # elevation of the lowest beam (0.2nd percentile of all points)
    highest_far: float  # 99.8th percentile of the elevation of points beyond 20 m
    beams: int  # peaks of the elevation histogram of points beyond 3 m (0.05 deg bins)
    coverage: int  # degrees of azimuth: 360 minus the widest empty sector

    def describe(self) -> str:
        return (f"elevations {self.lowest:+.1f}..{self.highest_far:+.1f} deg, about "
                f"{self.beams} beams, {self.coverage} deg of azimuth")


def scan_geometry(points: np.ndarray) -> ScanGeometry:
    """Elevation range, beam count and azimuth coverage of one scan (sensor frame)."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) < 100:
        return ScanGeometry(0.0, 0.0, 0, 0)
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    elevation = np.degrees(np.arctan2(xyz[:, 2], r))
    lowest = float(np.percentile(elevation, 0.2))
    far = elevation[r > 20.0]
    highest = float(np.percentile(far if len(far) > 50 else elevation, 99.8))
    beams = 0
    mid = elevation[r > 3.0]
    if len(mid) > 100:
        counts, _ = np.histogram(mid, bins=np.arange(lowest - 0.5, mid.max() + 0.5, 0.05))
        smooth = np.convolve(counts, np.ones(3) / 3, mode="same")
        floor = 0.1 * np.percentile(smooth[smooth > 0], 90)
        peak = (smooth > np.roll(smooth, 1)) & (smooth >= np.roll(smooth, -1)) & (smooth > floor)
        beams = int(peak.sum())
    # coverage: the full turn minus the widest empty sector (coarse azimuth
    # steps leave small gaps everywhere; a partial field leaves one big one)
    azimuth = np.sort(np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])))
    gaps = np.diff(np.r_[azimuth, azimuth[0] + 360.0])
    return ScanGeometry(lowest, highest, beams, int(round(360.0 - gaps.max())))


def sensor_score(spec: SensorSpec, geo: ScanGeometry) -> float:
    """Mismatch of a preset with a scan's geometry (0 = perfect; lower is better).

    The lowest beam always hits the ground near the vehicle, so its elevation
    is the strongest cue (1.5 deg of difference costs 1); the beam count
    separates presets with the same lowest beam (a factor 2 costs 1; not used
    for non-repetitive scanners, which have no beams); far points above the
    preset's top beam (0.5 deg allowed for laser offsets) and a horizontal
    field that does not match the coverage (under 300 deg) rule a preset out.
    """
    low, high = spec.vertical_fov
    score = abs(geo.lowest - low) / _EDGE_SCALE
    score += max(0.0, geo.highest_far - high - 0.5) / _EDGE_SCALE
    # an empty top of the field is weak evidence (open sky), but streets have
    # walls and trees that rise above the sensor within 20-80 m
    score += max(0.0, high - 0.5 - geo.highest_far) / 8.0
    if spec.pattern == "spinning" and geo.beams > 0:
        score += abs(np.log2(geo.beams / spec.channels))
    if (geo.coverage < 300) != (spec.horizontal_fov < 300):
        score += 10.0
    return float(score)


def guess_sensor(scans: list[np.ndarray]) -> tuple[str, str]:
    """The preset that fits the scans best, and a one-line reason.

    Scores (:func:`sensor_score`) are summed over the scans.
    """
    geos = [scan_geometry(s) for s in scans]
    totals = {name: sum(sensor_score(spec, g) for g in geos) for name, spec in SENSORS.items()}
    ranked = sorted(totals, key=totals.get)
    best, second = ranked[0], ranked[1]
    reason = (f"{geos[0].describe()} in the first scan; best fit {SENSORS[best].model} "
              f"(mismatch {totals[best] / len(geos):.2f}, next {second} "
              f"{totals[second] / len(geos):.2f})")
    return best, reason


def fit_warnings(scans: list[np.ndarray], z_low: float, z_high: float,
                 outside_limit: float = 0.10) -> list[str]:
    """Problems of a preset with these scans: points outside the height range, partial turns.

    LiDAR Iris clips heights outside ``z_low..z_high`` into its end bins, so a
    wrong range loses the height code silently; a scan covering less than a
    full turn leaves image columns empty (the yaw search still works, on fewer
    columns).
    """
    problems = []
    outside = []
    coverage = []
    for scan in scans:
        z = np.asarray(scan)[:, 2]
        z = z[np.isfinite(z)]
        outside.append(float(np.mean((z < z_low) | (z > z_high))) if len(z) else 0.0)
        coverage.append(scan_geometry(scan).coverage)
    worst = max(outside, default=0.0)
    if worst > outside_limit:
        problems.append(
            f"{worst:.0%} of a scan's points lie outside the LiDAR Iris height range "
            f"{z_low:g}..{z_high:g} m (more than {outside_limit:.0%}): pick the --sensor "
            f"preset of your LiDAR or set lidar-iris.z_low/z_high"
        )
    if min(coverage, default=360) < 315:
        problems.append(
            f"the scans cover only about {min(coverage)} of 360 degrees of azimuth: yaw-"
            f"invariant descriptors see a partial turn (fine for a forward-looking sensor "
            f"such as the Livox Avia, wrong for a spinning one)"
        )
    return problems


def sample_scans(seq, count: int = SAMPLE_SCANS) -> list[np.ndarray]:
    """The first ``count`` scans of a sequence as (N, 3) arrays."""
    return [np.asarray(seq[i])[:, :3] for i in range(min(count, len(seq)))]


def resolve_sensor(sensor: str | None, open_sequence) -> str | None:
    """``sensor`` itself, or for ``"auto"`` the preset guessed from the first scans.

    ``open_sequence`` is called (only for ``"auto"``) to get the sequence; the
    choice and its reason are reported as a warning line.
    """
    if sensor != "auto":
        return sensor
    from lidar_iris_eval.errors import LirisError, warn

    scans = sample_scans(open_sequence())
    if not scans:
        raise LirisError("--sensor auto", "the sequence has no scans to look at")
    name, reason = guess_sensor(scans)
    warn("--sensor auto", f"chose {name} ({reason})")
    return name
