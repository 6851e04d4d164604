"""Where the poses that place scans in a local map come from (``--odometry``).

* ``gt``: the sequence's own LiDAR-frame poses (an oracle odometry: no drift);
* ``kiss-icp``: poses estimated from the scans alone by KISS-ICP (Vizzo et al.,
  RA-L 2023; the optional extra ``odometry``: ``pip install -e ".[odometry]"``,
  kiss-icp 1.3.0), as MapClosures does. KISS-ICP's first pose is the identity,
  so its world frame is the first scan's LiDAR frame, not the ground truth's:
  everything built from it (local maps, target map, the matched frame's
  position) stays in that frame, and a method reports relative poses only.

KISS-ICP is configured by :func:`kiss_icp_config` (its defaults for a 100 m
sensor; the choices not given by KISS-ICP are named there). Its poses depend on
the scans only: :func:`estimate_odometry` never reads ``seq.poses``. They are
computed once per process and sequence (:data:`_MEMO`), for the whole
sequence, so every chunk of an extraction sees the same poses.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from lidar_iris_eval.errors import LirisError

#: the pose sources (module docstring)
ODOMETRY_SOURCES = ("gt", "kiss-icp")
#: the kiss-icp release the ``odometry`` extra pins (pyproject.toml)
KISS_ICP_VERSION = "1.3.0"
#: KISS-ICP settings that are our choice, not its defaults (see kiss_icp_config);
#: ``max_range`` "auto" is :func:`data_max_range`; the voxel stays KISS-ICP's default 1 m
KISS_ICP_SETTINGS = {"max_range": "auto", "min_range": 0.0, "deskew": False, "threads": 1,
                     "voxel": 1.0}
#: the data-derived range: this percentile of the point ranges of RANGE_SAMPLE_SCANS scans
#: spread over the sequence, within [RANGE_FLOOR_M, RANGE_CAP_M] (the cap is KISS-ICP's default)
RANGE_PERCENTILE = 99.0
RANGE_SAMPLE_SCANS = 10
RANGE_FLOOR_M = 10.0
RANGE_CAP_M = 100.0

_MISSING = ('needs the optional extra "odometry" (kiss-icp): '
            'pip install -e ".[odometry]"')


@dataclass(frozen=True)
class OdometryRun:
    """The poses of one sequence from one source.

    Attributes
    ----------
    source : a name of :data:`ODOMETRY_SOURCES`.
    poses : ``(N, 4, 4)`` world-from-LiDAR poses (KISS-ICP: world = first scan).
    seconds : ``(N,)`` CPU seconds of this thread per scan (reading excluded;
        zeros for ``gt``).
    version : the odometry's version (``""`` for ``gt``).
    settings : what KISS-ICP ran with, data-derived values included
        (``max_range_m``, ``voxel_m``); empty for ``gt``.
    """

    source: str
    poses: np.ndarray
    seconds: np.ndarray
    version: str = ""
    settings: dict = field(default_factory=dict)


#: (scan fingerprint, number of scans, source, settings) -> OdometryRun, per process
_MEMO: dict[tuple, OdometryRun] = {}


def check_odometry(source: str, flag: str = "--odometry") -> str:
    """``source`` when it is known and usable here, else a LirisError naming ``flag``."""
    if source not in ODOMETRY_SOURCES:
        raise LirisError(f"{flag} {source}", f"unknown odometry; choose from "
                                             f"{', '.join(ODOMETRY_SOURCES)}")
    if source == "kiss-icp":
        kiss_icp_version(flag)
    return source


def kiss_icp_version(flag: str = "--odometry kiss-icp") -> str:
    """The installed kiss-icp version; a LirisError naming ``flag`` when it is missing."""
    try:
        from importlib.metadata import version

        import kiss_icp.kiss_icp  # noqa: F401
    except ImportError:
        raise LirisError(flag if flag.endswith("kiss-icp") else f"{flag} kiss-icp",
                         _MISSING) from None
    try:
        return version("kiss-icp")
    except Exception:  # an unpackaged checkout: no metadata
        return "unknown"


def odometry_key(seq, source: str) -> str:
    """What the poses of ``source`` depend on beyond the scans, for a cache key.

    ``gt``: a hash of the sequence's poses (editing poses.txt changes every
    local map); ``kiss-icp``: its version and settings, never the ground truth.
    """
    import hashlib

    if source == "gt":
        poses = np.ascontiguousarray(np.asarray(seq.poses, dtype=np.float64))
        return "gt-poses:" + hashlib.sha256(poses.tobytes()).hexdigest()[:16]
    settings = ",".join(f"{k}={v}" for k, v in sorted(KISS_ICP_SETTINGS.items()))
    settings += (f",range=p{RANGE_PERCENTILE:g}/{RANGE_SAMPLE_SCANS}/"
                 f"{RANGE_FLOOR_M:g}-{RANGE_CAP_M:g}")
    return f"kiss-icp-{kiss_icp_version()}:{settings}"


def odometry_poses(seq, source: str = "gt", progress: bool = False) -> np.ndarray:
    """``(N, 4, 4)`` world-from-LiDAR poses of every scan of ``seq`` from ``source``."""
    return estimate_odometry(seq, source, progress).poses


def estimate_odometry(seq, source: str = "gt", progress: bool = False) -> OdometryRun:
    """The :class:`OdometryRun` of ``seq`` (KISS-ICP: computed once per process)."""
    if source == "gt":
        poses = np.asarray(seq.poses, dtype=np.float64)
        return OdometryRun("gt", poses, np.zeros(len(poses)))
    check_odometry(source)
    key = (_fingerprint(seq), len(seq), source, tuple(sorted(KISS_ICP_SETTINGS.items())))
    if key not in _MEMO:
        _MEMO.clear()  # one sequence at a time: bounded memory
        _MEMO[key] = _kiss_icp(seq, progress)
    return _MEMO[key]


def _fingerprint(seq) -> str:
    fingerprint = getattr(seq, "fingerprint", None)
    return fingerprint() if callable(fingerprint) else str(id(seq))


def data_max_range(seq) -> float:
    """KISS-ICP's ``max_range`` for ``seq``, from the scans: the range of nearly all returns.

    KISS-ICP keeps returns up to ``max_range`` (100 m by default, a car-mounted
    sensor's). On a short-range sequence (a handheld Livox, an Ouster in narrow
    streets: 95 % of returns within 15-25 m) the last percent of far, sparse
    returns then weigh in its registration and it drifts. So ``max_range`` is
    the :data:`RANGE_PERCENTILE` percentile of the point ranges of
    :data:`RANGE_SAMPLE_SCANS` scans spread over the sequence, rounded up to a metre and kept within
    [:data:`RANGE_FLOOR_M`, :data:`RANGE_CAP_M`]. It depends on the scans only.
    """
    n = len(seq)
    ranges = []
    for i in np.unique(np.linspace(0, n - 1, min(n, RANGE_SAMPLE_SCANS)).astype(int)):
        pts = np.asarray(seq[int(i)], dtype=np.float64)[:, :3]
        pts = pts[np.isfinite(pts).all(axis=1)]
        ranges.append(np.linalg.norm(pts, axis=1))
    ranges = np.concatenate(ranges) if ranges else np.empty(0)
    if len(ranges) == 0:
        return RANGE_CAP_M
    # up to the next metre; a millimetre over one (float32 coordinates) does not count
    value = float(np.ceil(np.percentile(ranges, RANGE_PERCENTILE) - 1e-3))
    return float(min(max(value, RANGE_FLOOR_M), RANGE_CAP_M))


def kiss_icp_config(max_range: float = RANGE_CAP_M):
    """KISS-ICP's configuration as we run it, for a sequence whose ``max_range`` is given.

    KISS-ICP's own defaults (``load_config(None)``): ``max_range`` 100 m,
    ``min_range`` 0 m, voxel ``max_range / 100``, 20 points per voxel,
    adaptive threshold from 2 m. Our choices (:data:`KISS_ICP_SETTINGS`):
    ``max_range`` from the data (:func:`data_max_range`); the voxel stays at
    the default's 1 m rather than following ``max_range`` (measured on the real
    Livox keyframes of ``../shared``: ATE 3.89 m with KISS-ICP's defaults, 1.09 m
    with the derived 34 m range and 1 m voxels, 11.9 m with 0.34 m voxels),
    ``deskew`` off (the readers give points without
    per-point times), one registration thread (identical poses on every run
    and no oversubscription of a shared machine).
    """
    from kiss_icp.config import load_config

    s = KISS_ICP_SETTINGS
    config = load_config(None)
    config.data.max_range = float(max_range)
    config.data.min_range = float(s["min_range"])
    config.data.deskew = bool(s["deskew"])
    config.mapping.voxel_size = float(s["voxel"])
    config.registration.max_num_threads = int(s["threads"])
    return config


def _kiss_icp(seq, progress: bool) -> OdometryRun:
    """Run KISS-ICP over every scan of ``seq`` (points only; ``seq.poses`` is never read)."""
    version = kiss_icp_version()
    from kiss_icp.kiss_icp import KissICP

    max_range = data_max_range(seq)
    config = kiss_icp_config(max_range)
    odom = KissICP(config=config)
    n = len(seq)
    poses = np.empty((n, 4, 4))
    seconds = np.empty(n)
    for i in tqdm(range(n), desc="kiss-icp odometry", unit="scan", file=sys.stderr,
                  disable=not progress, leave=False):
        pts = np.ascontiguousarray(np.asarray(seq[i], dtype=np.float64)[:, :3])
        pts = pts[np.isfinite(pts).all(axis=1)]
        t0 = time.thread_time()
        odom.register_frame(pts, np.zeros(0))
        seconds[i] = time.thread_time() - t0
        poses[i] = odom.last_pose
    settings = {"max_range_m": max_range, "voxel_m": float(config.mapping.voxel_size),
                "max_range_rule": f"p{RANGE_PERCENTILE:g} of {RANGE_SAMPLE_SCANS} scans' "
                                  f"ranges in [{RANGE_FLOOR_M:g}, {RANGE_CAP_M:g}] m"}
    return OdometryRun("kiss-icp", poses, seconds, version, settings)
