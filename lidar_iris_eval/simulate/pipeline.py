"""From a :class:`SimConfig` to a sequence on disk.

:func:`build_scenario` makes the world, the ego trajectory and the traffic;
:func:`simulate_sequence` casts every scan and writes the KITTI layout. Each
random part draws from its own stream of the seed, so changing, say, the
number of frames does not reshuffle the world.
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lidar_iris_eval import __version__
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.executor import Executor, SerialExecutor, local_executor
from lidar_iris_eval.lifetime import remove_stale_temps, temp_prefix
from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.presets import SimConfig, manifest_config, resolve_config
from lidar_iris_eval.simulate.raycast import Primitives
from lidar_iris_eval.simulate.revisits import revisit_queries
from lidar_iris_eval.simulate.sensors import SensorModel, get_sensor, simulate_scan
from lidar_iris_eval.simulate.traffic import Traffic, make_traffic
from lidar_iris_eval.simulate.trajectories import (
    RouteParams,
    drive,
    grid_waypoints,
    poses_on_ground,
    read_kitti_poses,
    route_corners,
    street_grid,
    trajectory_from_file,
)
from lidar_iris_eval.simulate.world import World, WorldParams, build_world
from lidar_iris_eval.simulate.world import world_params as style_params
from lidar_iris_eval.simulate.writer import (
    check_out_dir,
    default_tr,
    prepare_out_dir,
    publish,
    read_tr,
    remove_stale,
    write_metadata,
    write_scan,
)

# independent random streams per part of the simulation
_WORLD, _ROUTE, _TRAFFIC, _NOISE = 0, 1, 2, 3
# later sessions of a multi-session world draw from [seed, _SESSION, session, part, ...];
# parts start at 1 so that no key is another key with a trailing zero (SeedSequence pads
# with zeros, so [a, b] and [a, b, 0] would give the same stream)
_SESSION = 4
_S_ROUTE, _S_TRAFFIC, _S_NOISE, _S_PARKED = 1, 2, 3, 4


def stream_key(seed: int, part: int, session: int = 0) -> list[int]:
    """Random-stream key of one part of the simulation of ``session`` (0: the preset's own)."""
    if session == 0:
        return [seed, part]
    session_part = {_ROUTE: _S_ROUTE, _TRAFFIC: _S_TRAFFIC, _NOISE: _S_NOISE}.get(part, part)
    return [seed, _SESSION, session, session_part]


@dataclass(frozen=True)
class Scenario:
    """World, sensor and per-frame sensor-to-world poses of one sequence."""

    config: SimConfig
    sensor: SensorModel
    world: World
    poses: np.ndarray  # (frames, 4, 4) LiDAR poses in the world frame
    traffic: Traffic | None
    tr: np.ndarray  # LiDAR -> camera (4x4)

    def primitives(self, frame: int) -> Primitives:
        """Static primitives near the sensor at ``frame`` plus the moving cars."""
        xy = self.poses[frame, :2, 3]
        near = self.world.near(xy, self.sensor.max_range)
        if self.traffic is None:
            return near
        return Primitives.concat([near, self.traffic.primitives(frame, self.world.ground)])

    def object_ids(self, frame: int, rows: np.ndarray) -> np.ndarray:
        """Per-point object ids from the primitive ``rows`` a scan of ``frame`` hit.

        0 is the ground (row -1); static objects keep the world's ids; a moving
        car ``k`` gets ``n_static + 1 + k``. Stable across frames, so the same
        physical object carries the same id in every scan.
        """
        objects = self.world.objects
        n_static = int(objects.max(initial=0))
        table = objects[self.world.near_rows(self.poses[frame, :2, 3], self.sensor.max_range)]
        if self.traffic is not None:
            moving = self.traffic.primitives(frame, self.world.ground)
            first = self.traffic.first_instance
            extra = n_static + 1 + (moving.instance.astype(np.int64) - first)
            table = np.concatenate([table, extra.astype(np.uint32)])
        table = np.concatenate([table.astype(np.uint32), np.zeros(1, np.uint32)])
        return table[np.where(rows < 0, len(table) - 1, rows)]


def _grid_lines(xs: np.ndarray, ys: np.ndarray, extend: float) -> list[np.ndarray]:
    vertical = [np.array([[x, ys[0] - extend], [x, ys[-1] + extend]]) for x in xs]
    horizontal = [np.array([[xs[0] - extend, y], [xs[-1] + extend, y]]) for y in ys]
    return vertical + horizontal


def build_scenario(cfg: SimConfig, world_params: WorldParams | None = None, session: int = 0,
                   sensor_name: str | None = None) -> Scenario:
    """Generate the world and the trajectory described by ``cfg``.

    ``world_params`` replaces the :class:`WorldParams` of ``cfg.world_style``
    (only in-memory training data of learned methods does this, e.g. for
    ``shape_variety``; start from :func:`~lidar_iris_eval.simulate.world.world_params`
    to keep a style; sequences written by ``liris simulate`` use the style's).

    ``session`` > 0 drives the same world again on another day
    (:mod:`~lidar_iris_eval.simulate.sessions`): the same streets, buildings,
    trees and poles; other parked cars, another drive along the same route
    (lane offsets, speed and tilt noise), other moving cars, optionally
    another sensor (``sensor_name``). Session 0 is exactly the preset's sequence.
    """
    from lidar_iris_eval.simulate.nature import NATURE_STYLES

    if cfg.world_style in NATURE_STYLES:
        return _nature_scenario(cfg, session, sensor_name)
    wp = world_params if world_params is not None else style_params(cfg.world_style)
    sensor = get_sensor(sensor_name or cfg.sensor, cfg.azimuth_steps)
    # the world does not depend on the session's sensor (trajectory worlds take the
    # ground heights under the first session's sensor)
    world_sensor = get_sensor(cfg.sensor, cfg.azimuth_steps)
    rng_world = np.random.default_rng([cfg.seed, _WORLD])
    rng_route = np.random.default_rng(stream_key(cfg.seed, _ROUTE, session))
    if cfg.trajectory is not None:
        tr = read_tr(cfg.calib) if cfg.calib is not None else default_tr()
        cam = read_kitti_poses(cfg.trajectory)
        poses = trajectory_from_file(cam, tr, cfg.frames)
        xy = poses[:, :2, 3]
        ground_pts = poses[:, :3, 3] - world_sensor.mount_height * poses[:, :3, 2]
        world = build_world([xy], rng_world, wp, height_samples=ground_pts)
        line = xy
    else:
        tr = default_tr()
        a, b = cfg.blocks
        xs, ys = street_grid(rng_world, a + 2, b + 2, cfg.block_size)
        world = build_world(_grid_lines(xs, ys, 40.0), rng_world, wp)
        corners = [(i + 1, j + 1) for i, j in route_corners(cfg.route, a, b, laps=1 + cfg.frames)]
        rp = RouteParams(lateral_max=cfg.lateral_max)
        waypoints = grid_waypoints(corners, xs, ys, rng_route, rp, cfg.frames * rp.step * 1.3)
        xy, yaw, _ = drive(waypoints, cfg.frames, rng_route, rp)
        poses = poses_on_ground(world.ground, xy, yaw, sensor.mount_height, rng_route,
                                rp.tilt_noise_deg)
        line = xy
    if session > 0:
        from lidar_iris_eval.simulate.parked import repark

        world = repark(world, np.random.default_rng(stream_key(cfg.seed, _S_PARKED, session)))
    traffic = None
    if cfg.moving_cars and cfg.n_moving_cars > 0:
        first = int(world.prims.instance.max(initial=0)) + 1
        traffic = make_traffic(np.random.default_rng(stream_key(cfg.seed, _TRAFFIC, session)),
                               line, cfg.n_moving_cars, first)
    return Scenario(cfg, sensor, world, poses, traffic, tr)


def _nature_scenario(cfg: SimConfig, session: int, sensor_name: str | None) -> Scenario:
    """A forest or park (:mod:`~lidar_iris_eval.simulate.nature`): the street-grid route on
    bent trails, driven slowly; the same random streams as the urban worlds."""
    from lidar_iris_eval.simulate.nature import (
        Meander,
        build_nature_world,
        nature_params,
        trail_lines,
    )

    p = nature_params(cfg.world_style)
    sensor = get_sensor(sensor_name or cfg.sensor, cfg.azimuth_steps)
    rng_world = np.random.default_rng([cfg.seed, _WORLD])
    rng_route = np.random.default_rng(stream_key(cfg.seed, _ROUTE, session))
    a, b = cfg.blocks
    xs, ys = street_grid(rng_world, a + 2, b + 2, cfg.block_size)
    meander = Meander.draw(rng_world, p)
    lines = trail_lines(xs, ys, meander, 30.0)
    nodes = meander(np.array([[x, y] for x in xs for y in ys]))
    world = build_nature_world(lines, nodes, rng_world, p, cfg.season)
    corners = [(i + 1, j + 1) for i, j in route_corners(cfg.route, a, b, laps=1 + cfg.frames)]
    rp = RouteParams(lateral_max=cfg.lateral_max, step=p.step, tilt_noise_deg=p.tilt_noise_deg,
                     smoothing=p.smoothing, uturn_radius=p.uturn_radius)
    handheld = cfg.platform == "handheld"
    if handheld:
        from lidar_iris_eval.simulate.nature import HANDHELD as h

        rp = dataclasses.replace(rp, step=h.step, tilt_noise_deg=0.0,
                                 heading_noise_deg=h.heading_noise_deg)
    waypoints = grid_waypoints(corners, xs, ys, rng_route, rp, cfg.frames * rp.step * 1.3)
    xy, yaw, _ = drive(meander(waypoints), cfg.frames, rng_route, rp)
    poses = poses_on_ground(world.ground, xy, yaw, h.mount_height if handheld else
                            sensor.mount_height, rng_route, rp.tilt_noise_deg)
    if handheld:  # smooth sway: roll and pitch about the sensor
        from scipy.spatial.transform import Rotation

        from lidar_iris_eval.simulate.trajectories import _smooth_noise

        angles = np.radians(h.sway_deg) * np.stack(
            [_smooth_noise(rng_route, len(poses), h.sway_frames) for _ in range(2)], 1)
        sway = Rotation.from_euler("xy", angles).as_matrix()
        poses[:, :3, :3] = poses[:, :3, :3] @ sway
    return Scenario(cfg, sensor, world, poses, None, default_tr())


@dataclass(frozen=True)
class SimReport:
    """What a simulation wrote, for the CLI's summary line."""

    out_dir: Path
    config: SimConfig
    frames: int
    points: int
    revisit_queries: int
    seconds: float
    revisit_queries_camera: int | None = None  # the same count on camera-frame poses

    def summary(self) -> str:
        route = "trajectory" if self.config.trajectory is not None else self.config.route
        # The two frames' positions differ by the LiDAR-camera lever arm, so a pair
        # near 4 m can count in one and not the other; say which count is which.
        camera = ("" if self.revisit_queries_camera is None else
                  f"; {self.revisit_queries_camera} with camera-frame poses, the default of "
                  "liris gt/eval")
        if self.config.pushbroom is not None:  # frames are swathes (simulate.pushbroom)
            length = self.config.pushbroom
            return (f"wrote {self.frames} push-broom swathes of {length:g} m (lms151 line "
                    f"scanner, {route} route, {self.points / max(self.frames, 1):.0f} "
                    f"points/swathe, {self.revisit_queries} revisit queries at E=1, "
                    f"{length / 2:g} m) to {self.out_dir} in {self.seconds:.1f} s")
        return (
            f"wrote {self.frames} scans ({self.config.sensor}, {route} route, "
            f"{self.points / max(self.frames, 1):.0f} points/scan, {self.revisit_queries} "
            f"revisit queries at E=30, 4 m with LiDAR-frame poses{camera}) to {self.out_dir} "
            f"in {self.seconds:.1f} s"
        )


def run_simulation(
    out_dir: str | Path, cfg: SimConfig, overwrite: bool = False, progress: bool = False,
    preset: str | None = None, workers: int = 1,
) -> SimReport:
    """Simulate ``cfg`` into ``out_dir`` (see :func:`simulate_sequence`).

    ``workers`` processes cast and write the frames (``liris simulate
    --workers``); the files are byte-identical for every count, because each
    frame draws its noise from its own stream ``(seed, part, session, frame)``
    and never from a generator shared with the frames before it.

    The sequence is built in a temporary folder beside ``out_dir``
    (``.<name>.tmp-<host>-<pid>-…``) and moved into place only when complete, so
    an interrupted or failed run leaves no partial sequence under ``out_dir``
    (and its temporary folder is removed by the next run once its process is
    gone). ``manifest.json`` is written last: a folder without it is not a
    finished simulation.
    """
    out_dir = Path(out_dir)
    cfg = with_frames(cfg)
    executor = local_executor(workers)  # a bad count fails before anything is built
    check_out_dir(out_dir, overwrite)
    start = time.perf_counter()
    scen = build_scenario(cfg)  # before any folder exists: a bad option leaves nothing
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out_dir.parent)
    work = Path(tempfile.mkdtemp(prefix=temp_prefix(out_dir.name or "sim"), dir=out_dir.parent))
    try:
        prepare_out_dir(work, overwrite=True)
        if cfg.pushbroom is not None:
            from lidar_iris_eval.simulate.pushbroom import write_swathes

            frames, points, revisits, revisits_camera = write_swathes(
                scen, preset, work, _class_names(cfg.world_style), executor, progress)
            report = SimReport(out_dir, cfg, frames, points, revisits,
                               time.perf_counter() - start, revisits_camera)
        else:
            report = write_scenario(out_dir, scen, preset, start, progress, work=work,
                                    executor=executor)
        publish(work, out_dir)
    except LirisError as err:  # name the file the user asked for, not its temporary folder
        source = err.source or ""
        if source.startswith(str(work)):
            raise LirisError(str(out_dir) + source[len(str(work)):], err.problem) from None
        raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return report


def with_frames(cfg: SimConfig) -> SimConfig:
    """``cfg`` with ``frames`` set to the trajectory file's length when it follows one."""
    if cfg.trajectory is not None and cfg.frames is None:
        cfg = dataclasses.replace(cfg, frames=len(read_kitti_poses(cfg.trajectory)))
    return cfg


def write_scenario(
    out_dir: Path, scen: Scenario, preset: str | None, start: float, progress: bool,
    session: int = 0, origin: np.ndarray | None = None, extra: dict | None = None,
    work: Path | None = None, executor: Executor | None = None,
) -> SimReport:
    """Cast every scan of ``scen`` and write the KITTI layout into a prepared ``out_dir``.

    ``session`` picks the noise streams (0: the preset's own); ``origin`` is
    the LiDAR pose that becomes the identity of ``poses.txt`` (default: the
    first pose of ``scen``; another session's first pose puts both sessions
    in one frame); ``extra`` entries are added to ``manifest.json``; ``work``
    is the folder the files go to (default ``out_dir``; :func:`run_simulation`
    builds in a temporary folder and moves it into place); ``executor`` runs
    :func:`cast_and_write` for every frame (default: serially, in order). The
    scans may finish in any order; ``poses.txt``, ``times.txt``, ``calib.txt``
    and ``manifest.json`` are written here afterwards, each atomically.
    """
    cfg = scen.config
    work = out_dir if work is None else work
    n = len(scen.poses)
    executor = SerialExecutor() if executor is None else executor
    total_points = 0
    desc = "simulate" if session == 0 else f"simulate session {session}"
    with tqdm(total=n, desc=desc, unit="scan", disable=not progress, leave=False) as bar:
        for _, points in executor.imap(cast_and_write, [(i,) for i in range(n)],
                                       shared=(scen, scen.sensor.grid.directions, work,
                                               session)):
            total_points += points
            bar.update(1)
    if work == out_dir:  # written in place (a session folder): drop an older run's extra scans
        remove_stale(work, n)
    revisits = revisit_queries(scen.poses[:, :3, 3])
    camera_poses = scen.tr @ scen.poses @ np.linalg.inv(scen.tr)  # as written to poses.txt
    revisits_camera = revisit_queries(camera_poses[:, :3, 3])
    manifest = {
        "generator": "liris simulate",
        "version": __version__,
        "preset": preset,
        "seed": cfg.seed,
        "config": manifest_config(cfg),
        "sensor": dataclasses.asdict(scen.sensor),
        "frames": n,
        "points": total_points,
        "revisit_queries_E30_4m": int(len(revisits)),
        "revisit_queries_E30_4m_frame": "lidar",
        "revisit_queries_E30_4m_camera_frame": int(len(revisits_camera)),
        "classes": {str(k): v for k, v in _class_names(cfg.world_style).items()},
        "frame_convention": "poses.txt: camera frame, T_cam = Tr T_lidar inv(Tr), frame 0 = I",
    }
    if cfg.world_style != "default":  # the style's object densities, for the record
        manifest["world_params"] = dataclasses.asdict(_style_params(cfg.world_style))
    if extra:
        manifest.update(extra)
    write_metadata(work, scen.poses, scen.tr, manifest, origin)
    return SimReport(out_dir, cfg, n, total_points, len(revisits), time.perf_counter() - start,
                     int(len(revisits_camera)))


def cast_and_write(scen: Scenario, dirs: np.ndarray, work: Path, session: int,
                   frame: int) -> int:
    """Cast scan ``frame`` of ``scen`` and write its files into ``work``; its point count.

    One task of :func:`write_scenario` (run in a worker process with
    ``--workers``; ``dirs`` are the sensor's ray directions, computed once).
    The noise generator is made here from the frame's own key
    ``stream_key(seed, _NOISE, session) + [frame]``, so the scan depends only on
    the scenario and ``frame``, not on which process casts it or when; the
    frame's files have names of their own, so tasks never write the same file.
    """
    rng = np.random.default_rng(stream_key(scen.config.seed, _NOISE, session) + [frame])
    scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(frame),
                         scen.poses[frame], rng, dirs)
    write_scan(work, frame, scan.points, scan.intensity, scan.label,
               scen.object_ids(frame, scan.row))
    return len(scan.points)


def _class_names(style: str) -> dict[int, str]:
    if style == "default":
        return labels.CLASS_NAMES
    if style == "dense":
        return labels.DENSE_CLASS_NAMES
    return labels.NATURE_CLASS_NAMES


def _style_params(style: str):
    from lidar_iris_eval.simulate.nature import NATURE_STYLES

    return NATURE_STYLES[style] if style in NATURE_STYLES else style_params(style)


def simulate_sequence(
    out_dir: str | Path,
    preset: str | None = "tiny-mixed",
    overwrite: bool = False,
    progress: bool = False,
    workers: int = 1,
    **overrides,
) -> Path:
    """Simulate a sequence and write it in KITTI layout to ``out_dir``.

    Parameters
    ----------
    out_dir
        Output folder; must be empty or absent unless ``overwrite``.
    preset
        A name from :data:`~lidar_iris_eval.simulate.presets.PRESETS`, or None
        for the :class:`SimConfig` defaults.
    overwrite
        Replace the contents of a non-empty ``out_dir``.
    progress
        Show a tqdm bar on stderr.
    workers
        Processes that cast and write the frames (1: in this process).
    **overrides
        :class:`SimConfig` fields (``frames``, ``sensor``, ``route``,
        ``azimuth_steps``, ``seed``, ``moving_cars``, ``trajectory``, ...).
        With ``trajectory`` and no ``frames``, every pose of the file is used.

    Returns
    -------
    Path
        ``out_dir``. The same configuration always gives byte-identical files,
        whatever ``workers``.
    """
    cfg = resolve_config(preset, overrides)
    return run_simulation(out_dir, cfg, overwrite, progress, preset, workers).out_dir
