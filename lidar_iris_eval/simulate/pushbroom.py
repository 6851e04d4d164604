"""A push-broom 2-D line scanner and the swathes its lines build along a trajectory.

The ESM paper's Burgess Field data comes from a SICK LMS151 mounted as a
push-broom: one scan line (270 degrees) in a plane tilted across the direction
of travel, swept over the scene by the platform's motion; the paper builds a
source cloud from the lines of every 22 m travelled. Here:

* :data:`LMS151` is a :class:`~lidar_iris_eval.simulate.sensors.SensorModel`
  with one beam: its scan line is the beam's circle in a *line frame* (x the
  centre of the 270 degree field, z the scanner's rotation axis), cast by the
  same ray caster as the spinning sensors (one elevation row, the azimuth grid
  at the angular resolution, the field cut by ``horizontal_fov``);
* :class:`PushBroomMount` places the line frame on the platform: the field's
  centre up, the rotation axis along the direction of travel pitched up by
  ``tilt_deg``, so the line leans: its lower ends reach the ground ahead of the
  platform, its upper part the sides and the canopy behind;
* :func:`swathes` fires a line every ``line_spacing`` metres travelled (poses
  interpolated along the scenario's poses: positions linearly, rotations by
  slerp) and accumulates every ``swathe_length`` metres (the paper: 22 m) of
  lines into one cloud in the platform frame of the swathe's last line.

Data sheet values (SICK LMS151): 270 degree field, 0.5 degree angular
resolution, 50 Hz, 0.5-50 m range (10 % reflectivity: about 18 m; not
modelled), 12 mm statistical error (1 sigma).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate.sensors import SensorModel, simulate_scan

#: SICK LMS151 as a one-beam sensor model (module docstring); ``mount_height`` is unused
#: (the mount sits on the platform's pose)
LMS151 = SensorModel("lms151", (0.0,), 720, 0.0, 50.0, min_range=0.5, range_noise=0.012,
                     dropout=0.02, horizontal_fov=270.0)
#: the ESM paper's swathe length (m travelled per source cloud)
PAPER_SWATHE_LENGTH = 22.0


@dataclass(frozen=True)
class PushBroomMount:
    """Where the line frame sits on the platform (whose x is forward, z up)."""

    tilt_deg: float = 20.0  # the rotation axis pitched up from the direction of travel
    offset: tuple[float, float, float] = (0.3, 0.0, 0.2)  # metres from the platform origin

    def transform(self) -> np.ndarray:
        """4x4 platform-from-line-frame transform."""
        t = np.radians(self.tilt_deg)
        axis = np.array([np.cos(t), 0.0, np.sin(t)])  # line-frame z: forward, pitched up
        centre = np.array([-np.sin(t), 0.0, np.cos(t)])  # line-frame x: up, leaning back
        out = np.eye(4)
        out[:3, 0], out[:3, 1], out[:3, 2] = centre, np.cross(axis, centre), axis
        out[:3, 3] = self.offset
        return out


@dataclass(frozen=True)
class Swathe:
    """The lines of one stretch of ``length`` metres, in the frame of its last line's platform."""

    points: np.ndarray  # (N, 3) float32, platform frame at ``pose``
    label: np.ndarray  # (N,) uint32 SemanticKITTI class | instance << 16
    intensity: np.ndarray  # (N,) float32
    row: np.ndarray  # (N,) row of the world's primitive hit, -1 for ground
    pose: np.ndarray  # (4, 4) world-from-platform of the reference (last) line
    line_poses: np.ndarray  # (L, 4, 4) world-from-platform of every line
    line_of: np.ndarray  # (N,) index into line_poses of each point


def line_poses(poses: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Platform poses every ``spacing`` metres along ``poses`` ((n, 4, 4)), with their arc
    lengths: positions interpolated linearly, rotations by slerp."""
    if not spacing > 0:
        raise LirisError("line_spacing", f"must be positive, got {spacing}")
    pos = poses[:, :3, 3]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    keep = np.concatenate([[True], np.diff(s) > 1e-9])  # standing still: one pose
    s, poses = s[keep], poses[keep]
    q = np.arange(0.0, s[-1] + 1e-9, spacing)
    slerp = Slerp(s, Rotation.from_matrix(poses[:, :3, :3]))
    out = np.tile(np.eye(4), (len(q), 1, 1))
    out[:, :3, :3] = slerp(q).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(q, s, poses[:, k, 3])
    return out, q


def swathes(scenario, swathe_length: float = PAPER_SWATHE_LENGTH, line_spacing: float = 0.05,
            mount: PushBroomMount | None = None, sensor: SensorModel = LMS151,
            seed: int | None = 0) -> list[Swathe]:
    """Push-broom swathes of ``swathe_length`` metres along a scenario's trajectory.

    ``scenario`` is a :class:`~lidar_iris_eval.simulate.pipeline.Scenario`; its
    poses are the platform's (the spinning sensor's frame: x forward, z up).
    ``seed`` None: noise-free lines with nothing dropped (for tests). Only
    complete swathes are returned.
    """
    plan = SwathePlan.along(scenario.poses, swathe_length, line_spacing, mount, sensor)
    return [plan.swathe(scenario, w, seed) for w in range(plan.count)]


@dataclass(frozen=True)
class SwathePlan:
    """Where every line of a push-broom run is fired and which swathe it belongs to.

    Made once from the trajectory (:meth:`along`); :meth:`swathe` then builds
    any one swathe on its own, so the swathes of ``liris simulate --pushbroom``
    can be cast in any order, in several processes, with identical results.
    """

    poses: np.ndarray  # (L, 4, 4) world-from-platform of every line
    arc: np.ndarray  # (L,) metres travelled at every line
    swathe_length: float
    mount: np.ndarray  # (4, 4) platform-from-line-frame
    sensor: SensorModel
    directions: np.ndarray  # the sensor's ray directions, computed once

    @staticmethod
    def along(trajectory: np.ndarray, swathe_length: float, line_spacing: float,
              mount: PushBroomMount | None = None, sensor: SensorModel = LMS151) -> SwathePlan:
        """The lines every ``line_spacing`` metres along ``trajectory`` ((n, 4, 4))."""
        if not swathe_length > 0:
            raise LirisError("swathe_length", f"must be positive, got {swathe_length}")
        m = (mount or PushBroomMount()).transform()
        poses, s = line_poses(trajectory, line_spacing)
        return SwathePlan(poses, s, float(swathe_length), m, sensor, sensor.grid.directions)

    @property
    def count(self) -> int:
        """Complete swathes along the trajectory (a last, shorter stretch is dropped)."""
        return int(self.arc[-1] // self.swathe_length)

    def swathe(self, scenario, w: int, seed: int | None) -> Swathe:
        """Swathe ``w``: its lines, each with noise from its own stream ``[seed, w, line]``
        (``seed`` None: noise-free), so a swathe depends on nothing cast before it."""
        s, poses, sensor = self.arc, self.poses, self.sensor
        length = self.swathe_length
        lines = np.nonzero((s >= w * length) & (s < (w + 1) * length))[0]
        ref = poses[lines[-1]]
        to_ref = np.linalg.inv(ref)
        pts, lab, inten, rows, line_of = [], [], [], [], []
        for li in lines:
            rng = None if seed is None else np.random.default_rng([seed, w, int(li)])
            pose = poses[li] @ self.mount
            near = scenario.world.near_rows(pose[:2, 3], sensor.max_range)
            scan = simulate_scan(sensor, scenario.world.ground, scenario.world.prims.take(near),
                                 pose, rng, self.directions)
            rel = to_ref @ pose
            pts.append(scan.points.astype(np.float64) @ rel[:3, :3].T + rel[:3, 3])
            lab.append(scan.label)
            inten.append(scan.intensity)
            rows.append(np.where(scan.row >= 0, near[np.maximum(scan.row, 0)], -1))
            line_of.append(np.full(len(scan.points), li - lines[0], np.int64))
        return Swathe(np.concatenate(pts).astype(np.float32), np.concatenate(lab),
                      np.concatenate(inten), np.concatenate(rows), ref, poses[lines],
                      np.concatenate(line_of))


#: metres between two lines in ``liris simulate --pushbroom`` (50 Hz at 2.5 m/s)
LINE_SPACING = 0.05


def write_swathe(scen, plan: SwathePlan, work: Path, w: int) -> tuple[int, np.ndarray]:
    """Build swathe ``w`` of ``plan`` and write it as frame ``w`` into ``work``.

    One task of :func:`write_swathes` (run in a worker process with
    ``--workers``). Returns the swathe's point count and its pose; the points
    themselves stay in the worker (only the files carry them).
    """
    from lidar_iris_eval.simulate.writer import write_scan

    sw = plan.swathe(scen, w, scen.config.seed)
    objects = np.concatenate([scen.world.objects, np.zeros(1, np.uint32)])  # last: ground
    ids = objects[np.where(sw.row < 0, len(objects) - 1, sw.row)]
    write_scan(work, w, sw.points, sw.intensity, sw.label, ids)
    return len(sw.points), sw.pose


def write_swathes(scen, preset, work, class_names: dict[int, str], executor=None,
                  progress: bool = False):
    """``liris simulate --pushbroom L``: every swathe of ``L`` metres is one frame (KITTI
    layout: points in the platform frame of the swathe's last line, whose pose is the
    frame's; labels and object ids as for scans). Static world only (no moving cars).

    ``executor`` (an :mod:`~lidar_iris_eval.executor` executor; default serial) runs
    :func:`write_swathe` for every swathe, in any order; the poses and the manifest
    are written here afterwards. Returns ``(frames, points, revisit queries, revisit
    queries on camera poses)`` for the pipeline's
    :class:`~lidar_iris_eval.simulate.pipeline.SimReport`."""
    import dataclasses

    from tqdm import tqdm

    from lidar_iris_eval import __version__
    from lidar_iris_eval.executor import SerialExecutor
    from lidar_iris_eval.simulate.presets import manifest_config
    from lidar_iris_eval.simulate.revisits import revisit_queries
    from lidar_iris_eval.simulate.writer import write_metadata

    cfg = scen.config
    plan = SwathePlan.along(scen.poses, float(cfg.pushbroom), LINE_SPACING)
    n = plan.count
    if n < 2:
        raise LirisError("--pushbroom", f"the route of {len(scen.poses)} frames gives "
                                        f"{n} swathe(s) of {cfg.pushbroom:g} m; "
                                        "give more --frames or a shorter swathe")
    executor = SerialExecutor() if executor is None else executor
    total = 0
    poses = np.empty((n, 4, 4))
    with tqdm(total=n, desc="simulate", unit="swathe", disable=not progress,
              leave=False) as bar:
        for w, (points, pose) in executor.imap(write_swathe, [(w,) for w in range(n)],
                                               shared=(scen, plan, work)):
            total += points
            poses[w] = pose
            bar.update(1)
    revisits = revisit_queries(poses[:, :3, 3], exclude=1, radius=float(cfg.pushbroom) / 2)
    camera = scen.tr @ poses @ np.linalg.inv(scen.tr)
    revisits_camera = revisit_queries(camera[:, :3, 3], exclude=1,
                                      radius=float(cfg.pushbroom) / 2)
    manifest = {
        "generator": "liris simulate --pushbroom", "version": __version__, "preset": preset,
        "seed": cfg.seed, "config": manifest_config(cfg),
        "sensor": dataclasses.asdict(LMS151),
        "pushbroom": {"swathe_length_m": float(cfg.pushbroom), "line_spacing_m": LINE_SPACING,
                      "mount": dataclasses.asdict(PushBroomMount()),
                      "frame": "each frame is one swathe, in the platform frame of its last "
                               "line; its pose is that line's platform pose"},
        "frames": n, "points": total,
        "revisit_queries_E1_half_swathe": int(len(revisits)),
        "classes": {str(k): v for k, v in class_names.items()},
        "frame_convention": "poses.txt: camera frame, T_cam = Tr T_lidar inv(Tr), frame 0 = I",
    }
    write_metadata(work, poses, scen.tr, manifest)
    return n, total, int(len(revisits)), int(len(revisits_camera))
