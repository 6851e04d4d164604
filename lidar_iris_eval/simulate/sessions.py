"""Multi-session worlds: the same streets driven again on other days.

``liris simulate OUT --world tiny-mixed --sessions 2 --session-sensor vlp16``
writes ``OUT/session0`` (byte-identical to ``liris simulate OUT --world
tiny-mixed``) and ``OUT/session1``, plus ``OUT/sessions.json``. A later
session ``k`` keeps the static world (streets, buildings, trees, poles,
fences, ground) and changes what changes between days:

* **parked cars** – each parked car of the first session is gone with
  probability :data:`PARKED_GONE`; every other one is replaced by a new car
  (new body and cabin size, reflectivity) parked at most
  :data:`PARKED_SHIFT` metres further along the kerb;
* **the drive** – the same route through the same corners, with other lane
  offsets, speed profile and tilt noise (route stream of session ``k``);
  a trajectory-file world follows the same file;
* **moving cars** – another traffic stream;
* **sensor** – ``--session-sensor`` (mounting height and beams differ), same
  azimuth resolution as the preset;
* **noise** – another range-noise and dropout stream.

Poses: every ``poses.txt`` is in one frame, the camera frame of session 0's
first scan (session 0 starts at the identity, the others do not), so no
alignment transform is needed to evaluate one session against another.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate.parked import PARKED_GONE, PARKED_SHIFT, repark
from lidar_iris_eval.simulate.presets import SimConfig
from lidar_iris_eval.simulate.sensors import SENSORS
from lidar_iris_eval.simulate.writer import atomic_write, check_out_dir, prepare_out_dir

#: the most sessions ``liris simulate`` writes
MAX_SESSIONS = 8


__all__ = ["MAX_SESSIONS", "PARKED_GONE", "PARKED_SHIFT", "SessionsReport", "repark",
           "run_sessions", "session_dir", "session_sensors"]


def session_dir(out_dir: Path, session: int) -> Path:
    """``OUT/session<k>``."""
    return Path(out_dir) / f"session{session}"


def session_sensors(cfg: SimConfig, sessions: int, sensors: tuple[str, ...]) -> list[str]:
    """The sensor of every session: the preset's for session 0, then ``sensors`` in
    order (the last one repeats; none given: the preset's)."""
    if not 1 <= sessions <= MAX_SESSIONS:
        raise LirisError("--sessions", f"must be within 1..{MAX_SESSIONS}, got {sessions}")
    for name in sensors:
        if name not in SENSORS:
            raise LirisError("--session-sensor", f"unknown sensor {name!r}; choose from "
                             f"{', '.join(SENSORS)}")
    if sensors and sessions == 1:
        raise LirisError("--session-sensor", "needs --sessions 2 or more")
    if len(sensors) > sessions - 1:
        raise LirisError("--session-sensor",
                         f"{len(sensors)} sensors given for {sessions - 1} later sessions")
    out = [cfg.sensor]
    for k in range(1, sessions):
        out.append(sensors[min(k - 1, len(sensors) - 1)] if sensors else cfg.sensor)
    return out


@dataclass(frozen=True)
class SessionsReport:
    """What a multi-session simulation wrote."""

    out_dir: Path
    sessions: list[dict]
    seconds: float

    def summary(self) -> str:
        parts = [f"session{s['session']}: {s['frames']} scans ({s['sensor']})"
                 + ("" if s["queries_with_positive_in_session0"] is None else
                    f", {s['queries_with_positive_in_session0']} within 4 m of session 0")
                 for s in self.sessions]
        return (f"wrote {len(self.sessions)} sessions to {self.out_dir} in "
                f"{self.seconds:.1f} s; poses in session 0's frame; " + "; ".join(parts))


def cross_positive_queries(query_xyz: np.ndarray, db_xyz: np.ndarray, radius: float) -> int:
    """How many query positions have a database position closer than ``radius`` (3-D)."""
    dist, _ = cKDTree(db_xyz).query(query_xyz, k=1)
    return int(np.count_nonzero(dist < radius))


def session_seasons(cfg: SimConfig, sessions: int, seasons: tuple[str, ...]) -> list[str]:
    """The season of every session of a natural world: ``cfg.season`` for session 0, then
    ``seasons`` in order (the last one repeats; none given: session 0's)."""
    if not seasons:
        return [cfg.season] * sessions
    if cfg.season is None or cfg.world_style in ("default", "dense"):
        raise LirisError("--session-season", "only the natural worlds (forest, park) have "
                                             "seasons")
    if sessions == 1:
        raise LirisError("--session-season", "needs --sessions 2 or more")
    if len(seasons) > sessions - 1:
        raise LirisError("--session-season",
                         f"{len(seasons)} seasons given for {sessions - 1} later sessions")
    return [cfg.season] + [seasons[min(k - 1, len(seasons) - 1)] for k in range(1, sessions)]


def run_sessions(out_dir: str | Path, cfg: SimConfig, sessions: int,
                 sensors: tuple[str, ...] = (), overwrite: bool = False,
                 progress: bool = False, preset: str | None = None,
                 seasons: tuple[str, ...] = (), workers: int = 1) -> SessionsReport:
    """Simulate ``sessions`` drives of one world into ``OUT/session<k>``.

    Session 0 is exactly what :func:`~lidar_iris_eval.simulate.pipeline.run_simulation`
    writes for ``cfg``; ``sessions.json`` lists every session, its sensor and
    the shared pose frame, and how many of its scans lie within 4 m (3-D,
    camera-frame poses) of a session-0 scan. ``workers`` processes cast and
    write each session's frames (byte-identical files for every count; the
    sessions themselves run one after the other).
    """
    from lidar_iris_eval.executor import local_executor
    from lidar_iris_eval.simulate.pipeline import build_scenario, with_frames, write_scenario

    out_dir = Path(out_dir)
    cfg = with_frames(cfg)
    executor = local_executor(workers)
    if cfg.pushbroom is not None:
        raise LirisError("--pushbroom", "writes one sequence; not with --sessions")
    names = session_sensors(cfg, sessions, tuple(sensors))
    season_of = session_seasons(cfg, sessions, tuple(seasons))
    check_out_dir(out_dir, overwrite, sessions=True)
    start = time.perf_counter()
    origin = None
    rows = []
    camera = []
    for k, sensor in enumerate(names):
        cfg_k = cfg if season_of[k] == cfg.season else dataclasses.replace(cfg,
                                                                           season=season_of[k])
        scen = build_scenario(cfg_k, session=k, sensor_name=None if k == 0 else sensor)
        if origin is None:
            origin = scen.poses[0]
        folder = session_dir(out_dir, k)
        prepare_out_dir(folder, overwrite)
        extra = None if k == 0 else {
            "session": k,
            "session_sensor": sensor,
            "session_of": "session0",
            "session_changes": "other parked cars, drive, moving cars, sensor and noise; "
                               "the same static world",
            "frame_convention": "poses.txt: camera frame, T_cam = Tr T_lidar inv(Tr), in the "
                                "frame of session 0's first scan (not identity here)",
        }
        if seasons and k > 0:  # a natural world: the season is what changes
            extra["session_changes"] = (f"season ({season_of[k]}), drive, sensor and noise; "
                                        "the same trees, logs, rocks and terrain")
        report = write_scenario(folder, scen, preset, start, progress, k,
                                None if k == 0 else origin, extra, executor=executor)
        rel = np.linalg.inv(origin) @ scen.poses
        camera.append((scen.tr @ rel @ np.linalg.inv(scen.tr))[:, :3, 3])
        rows.append({"session": k, "dir": folder.name, "sensor": sensor,
                     **({"season": season_of[k]} if seasons else {}),
                     "frames": report.frames, "points": report.points,
                     "queries_with_positive_in_session0": None if k == 0 else
                         cross_positive_queries(camera[-1], camera[0], 4.0)})
    meta = {
        "generator": "liris simulate --sessions",
        "preset": preset,
        "seed": cfg.seed,
        "pose_frame": "every poses.txt is in the camera frame of session 0's first scan",
        "changes_between_sessions": "parked cars (each gone with p = "
                                    f"{PARKED_GONE:g}, else replaced within "
                                    f"{PARKED_SHIFT:g} m), the drive, moving cars, sensor, "
                                    "noise; static world identical",
        "positive_count_rule": "queries_with_positive_in_session0: scans with a session-0 scan "
                               "closer than 4 m (3-D, camera-frame poses)",
        "sessions": rows,
    }
    if seasons:  # a natural world: no parked cars; the season changes
        meta["changes_between_sessions"] = ("the season (leaf-off: no broadleaf foliage, "
                                            "less and smaller undergrowth), the drive, sensor, "
                                            "noise; trunks, branches, conifers, logs, rocks "
                                            "and terrain identical")
    atomic_write(out_dir / "sessions.json",
                 (json.dumps(meta, indent=2, sort_keys=True) + "\n").encode())
    return SessionsReport(out_dir, rows, time.perf_counter() - start)
