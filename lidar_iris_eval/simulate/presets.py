"""Named built-in sequences and the settings every simulation is made from.

A preset is a partial :class:`SimConfig`; options given by the caller override
its values. The ``tiny-*`` presets (about 200 frames, reduced azimuth
resolution) are for tests and CI, ``small-mixed`` is the CI regression
sequence (both same- and reverse-direction revisits), ``urban-dense`` drives
small-mixed's route through a dense urban world (for ESM's segment-based
evaluation), ``kitti-scale`` matches KITTI 00's 4541 frames for benchmarks;
``forest`` and ``park`` are the natural worlds (:mod:`~lidar_iris_eval.simulate.nature`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate.sensors import SENSORS
from lidar_iris_eval.simulate.trajectories import ROUTES


@dataclass(frozen=True)
class SimConfig:
    """Everything that determines a simulated sequence (with the package version)."""

    frames: int | None = 200  # None with a trajectory: all of its poses
    sensor: str = "hdl64"
    route: str = "mixed"
    azimuth_steps: int | None = None  # None: the sensor's full resolution
    seed: int = 0
    moving_cars: bool = True
    n_moving_cars: int = 6
    blocks: tuple[int, int] = (1, 1)  # route rectangle, in street blocks
    block_size: tuple[float, float] = (26.0, 34.0)  # metres, min/max
    lateral_max: float = 1.5  # lane offset range right of the centre line
    trajectory: str | None = None  # KITTI pose file (camera frame) to follow
    calib: str | None = None  # calib.txt with the Tr that goes with it
    #: which objects line the streets: a name from ``simulate.world.WORLD_STYLES``
    #: ("default": today's world; "dense": :data:`~lidar_iris_eval.simulate.world.DENSE`).
    #: Left out of ``manifest.json`` when "default", so older sequences stay byte-identical.
    world_style: str = "default"
    #: natural worlds only (``forest``, ``park``): "leaf-on" or "leaf-off" crowns and
    #: undergrowth (:mod:`~lidar_iris_eval.simulate.nature`); left out of the manifest of
    #: the urban worlds
    season: str = "leaf-on"
    #: push-broom mode (:mod:`~lidar_iris_eval.simulate.pushbroom`): each frame is the swathe
    #: of an LMS151-like line scanner over this many metres travelled (the ESM paper: 22 m);
    #: None: the spinning sensor's scans. Left out of the manifest when None.
    pushbroom: float | None = None
    #: natural worlds: who carries the sensor; None or "ugv": the preset's ground robot (slow,
    #: pitch and roll from the slopes); "handheld": walking (see ``simulate.nature.HANDHELD``).
    #: Left out of the manifest when None.
    platform: str | None = None


PRESETS: dict[str, dict] = {
    "tiny-same": dict(frames=200, route="same", azimuth_steps=512, seed=11,
                      block_size=(18.0, 24.0)),
    "tiny-reverse": dict(frames=200, route="reverse", azimuth_steps=512, seed=12,
                         block_size=(18.0, 24.0)),
    "tiny-mixed": dict(frames=220, route="mixed", azimuth_steps=512, seed=13,
                       block_size=(18.0, 24.0)),
    # blocks small enough that 400 frames reach the U-turn: 203 revisit queries at
    # E = 30, 118 of them in the reverse direction. Light traffic (2 moving cars):
    # with the default 6, cars near the sensor dominate global descriptors such
    # as M2DP (same-direction top-1 0.53 -> about 0.3 measured).
    "small-mixed": dict(frames=400, route="mixed", azimuth_steps=720, seed=21,
                        block_size=(30.0, 38.0), n_moving_cars=2),
    "kitti-scale": dict(frames=4541, route="mixed", azimuth_steps=1024, seed=31,
                        blocks=(7, 5), block_size=(55.0, 100.0)),
    # small-mixed's streets, route and traffic (same seed: the same street grid and the
    # same drive, 203 revisit queries at E = 30) in a dense urban world: near-continuous
    # façades with gaps, porches and walls, long runs of parked cars, street trees,
    # bushes, poles (simulate.world.DENSE, chosen so that single-scan segment statistics
    # come near real KITTI 00's; docs/esm.md "Segments")
    "urban-dense": dict(frames=400, route="mixed", azimuth_steps=720, seed=21,
                        block_size=(30.0, 38.0), n_moving_cars=2, world_style="dense"),
    # natural worlds (simulate.nature): a slow platform (0.5-0.6 m a frame, pitch and roll
    # from the slopes) on a bent trail grid; one lap of the small blocks is about 140
    # frames, so a 200-frame sequence revisits its start (same direction, then the U-turn
    # of the mixed route). HDL-32E in the forest (Cornbury Park in the ESM paper),
    # VLP-16 in the park; no traffic.
    "forest": dict(frames=200, route="mixed", sensor="hdl32", azimuth_steps=720, seed=41,
                   block_size=(15.0, 20.0), moving_cars=False, lateral_max=0.3,
                   world_style="forest"),
    "park": dict(frames=200, route="mixed", sensor="vlp16", azimuth_steps=900, seed=51,
                 block_size=(18.0, 24.0), moving_cars=False, lateral_max=0.4,
                 world_style="park"),
}
#: the urban world styles (their manifests leave the season out)
URBAN_STYLES = ("default", "dense")


#: the finest azimuth grid accepted: 0.01 deg (36,000 rays a beam and turn; real sensors
#: use 512..4096); beyond it one scan would need gigabytes of rays
MAX_AZIMUTH_STEPS = 36_000
#: the longest sequence accepted (KITTI 00 has 4,541 scans)
MAX_FRAMES = 1_000_000
#: NumPy's generators take non-negative seeds
MAX_SEED = 2**63 - 1


def resolve_config(preset: str | None, overrides: dict) -> SimConfig:
    """The preset's values with ``overrides`` (``None`` values are ignored) on top."""
    if preset is not None and preset not in PRESETS:
        raise LirisError(f"--world {preset}", f"unknown world; choose from {', '.join(PRESETS)}")
    values = dict(PRESETS.get(preset, {}) if preset else {})
    fields = {f.name for f in dataclasses.fields(SimConfig)}
    for key, value in overrides.items():
        if key not in fields:
            raise LirisError(None, f"unknown simulation option {key!r}")
        if value is not None:
            values[key] = value
    if values.get("trajectory") is not None and overrides.get("frames") is None:
        values["frames"] = None  # follow the whole trajectory file
    for key in ("blocks", "block_size"):
        if key in values:
            values[key] = tuple(values[key])
    cfg = SimConfig(**values)
    _check(cfg)
    return cfg


def _check(cfg: SimConfig) -> None:
    if cfg.frames is None and cfg.trajectory is None:
        raise LirisError("--frames", "is required without --trajectory")
    if cfg.frames is not None and cfg.frames < 1:
        raise LirisError("--frames", f"must be positive, got {cfg.frames}")
    if cfg.sensor not in SENSORS:
        raise LirisError("--sensor", f"unknown sensor {cfg.sensor!r}; choose from "
                         f"{', '.join(SENSORS)}")
    if cfg.route not in ROUTES:
        raise LirisError("--route", f"unknown route {cfg.route!r}; choose from {', '.join(ROUTES)}")
    if cfg.azimuth_steps is not None and not 8 <= cfg.azimuth_steps <= MAX_AZIMUTH_STEPS:
        raise LirisError("--azimuth-steps", f"must be within 8..{MAX_AZIMUTH_STEPS} (0.01 deg "
                                            f"steps), got {cfg.azimuth_steps}")
    if cfg.frames is not None and cfg.frames > MAX_FRAMES:
        raise LirisError("--frames", f"at most {MAX_FRAMES:,} scans, got {cfg.frames:,}")
    if not 0 <= cfg.seed <= MAX_SEED:
        raise LirisError("--seed", f"must be within 0..2**63-1 (NumPy seeds are non-negative), "
                                   f"got {cfg.seed}")
    if min(cfg.blocks) < 1 or cfg.block_size[0] < 15 or cfg.block_size[1] < cfg.block_size[0]:
        raise LirisError(None, "blocks must be >= 1 and block sizes at least 15 m (min <= max)")
    if not 0 <= cfg.lateral_max <= 3:
        raise LirisError(None, f"lateral_max must be within 0..3 m, got {cfg.lateral_max}")
    if cfg.calib is not None and cfg.trajectory is None:
        raise LirisError("--calib", "only used together with --trajectory")
    from lidar_iris_eval.simulate.nature import NATURE_STYLES, SEASONS
    from lidar_iris_eval.simulate.world import WORLD_STYLES

    styles = [*WORLD_STYLES, *NATURE_STYLES]
    if cfg.world_style not in styles:
        raise LirisError(None, f"unknown world style {cfg.world_style!r}; choose from "
                               f"{', '.join(styles)}")
    if cfg.pushbroom is not None and not 1.0 <= cfg.pushbroom <= 500.0:
        raise LirisError("--pushbroom", f"swathe length must be within 1..500 m, got "
                                        f"{cfg.pushbroom}")
    if cfg.season not in SEASONS:
        raise LirisError("--season", f"must be one of {', '.join(SEASONS)}, got {cfg.season!r}")
    if cfg.world_style in NATURE_STYLES:
        if cfg.trajectory is not None:
            raise LirisError("--trajectory", f"the natural world {cfg.world_style!r} is built "
                                             "around its own trail network; give an urban world")
    elif cfg.season != "leaf-on":
        raise LirisError("--season", "only the natural worlds (forest, park) have seasons")
    if cfg.platform is not None:
        from lidar_iris_eval.simulate.nature import PLATFORMS

        if cfg.platform not in PLATFORMS:
            raise LirisError("--platform", f"must be one of {', '.join(PLATFORMS)}, got "
                                           f"{cfg.platform!r}")
        if cfg.world_style not in NATURE_STYLES:
            raise LirisError("--platform", "only the natural worlds (forest, park) have "
                                           "platforms")


def manifest_config(cfg: SimConfig) -> dict:
    """``cfg`` as ``manifest.json`` records it: its fields, without ``world_style`` when it
    is "default" (the key is newer than the pinned sequences, whose bytes must not change).
    """
    out = dataclasses.asdict(cfg)
    if out["world_style"] in URBAN_STYLES:
        del out["season"]
    if out["pushbroom"] is None:
        del out["pushbroom"]
    if out["platform"] is None:
        del out["platform"]
    if out["world_style"] == "default":
        del out["world_style"]
    return out
