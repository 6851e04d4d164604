"""Accepted loops written as a pose graph a back end loads as is (issue 23).

``.g2o`` (g2o's text format, the ``types_slam3d`` records):

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` for **every** frame: its LiDAR-frame
  pose from the sequence, or from an odometry given by the user;
* ``FIX id`` of the first vertex (the gauge);
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 upper-triangular entries of
  the 6x6 information matrix (row-major), one per accepted loop: the pose of
  ``j`` in ``i``'s frame (``T`` of matches.csv), so ``P_j = P_i @ T``. No
  odometry edges are written: they are the front end's.

The information matrix, in g2o's error order ``(x, y, z, qx, qy, qz)``
(translation, then the quaternion's vector part, which is half the rotation
angle for small rotations), is derived from the registration fitness
(:func:`information_from_fitness`)::

    sigma_t = max(rmse_m, 0.01 m) / sqrt(max(inlier_ratio, 0.01))
    sigma_r = sigma_t / 10 m                     (radians: a lever arm of 10 m)
    info    = diag(1/sigma_t^2 (x3), 4/sigma_r^2 (x3))

i.e. the residual of the inliers, inflated when few points overlap, with the
rotation as certain as the translation at 10 m range. A loop without a
fitness (not refined) gets the identity, a neutral placeholder. Loops
without a translation (yaw-only, not refined) cannot be an SE(3) edge and
are left out with a warning.

``.tum`` (TUM-style text): ``# t_query t_match x y z qx qy qz qw`` then one
loop per line, with the scans' times (frame ids when the sequence has no
times); ``nan`` translation for yaw-only loops.

``.txt``: ``i j x y z qx qy qz qw`` with frame ids (as before).

Every file is written atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, warn
from lidar_iris_eval.io.loops import G2OGraph, parse_g2o
from lidar_iris_eval.matching.geometry import quaternion_xyzw

EXPORT_SUFFIXES = (".g2o", ".tum", ".txt")
#: the lever arm (m) turning the translation sigma into a rotation sigma
LEVER_M = 10.0
FLOOR_M = 0.01
INFORMATION_RULE = (
    "g2o order (x y z qx qy qz); sigma_t = max(rmse_m, 0.01) / sqrt(max(inlier_ratio, 0.01)), "
    "sigma_r = sigma_t / 10 m, info = diag(1/sigma_t^2 x3, 4/sigma_r^2 x3); identity for loops "
    "without a registration fitness"
)


def upper_triangle(info: np.ndarray) -> np.ndarray:
    """The 21 upper-triangular entries (row-major) of a 6x6 matrix."""
    info = np.asarray(info, dtype=np.float64)
    return info[np.triu_indices(6)]


def information_from_fitness(inlier_ratio: float, rmse_m: float) -> np.ndarray:
    """The 6x6 information of one loop (rule in the module docstring)."""
    if not (np.isfinite(inlier_ratio) and np.isfinite(rmse_m)):
        return np.eye(6)
    sigma_t = max(float(rmse_m), FLOOR_M) / np.sqrt(max(float(inlier_ratio), 0.01))
    sigma_r = sigma_t / LEVER_M
    return np.diag([1 / sigma_t**2] * 3 + [4 / sigma_r**2] * 3)


def _atomic_write(path: Path, lines: list[str]) -> None:
    from lidar_iris_eval.atomic import atomic_write

    atomic_write(path, "".join(f"{line}\n" for line in lines), what="loop file")


def _pose_numbers(T: np.ndarray) -> str:
    return " ".join(f"{v:.9g}" for v in (*T[:3, 3], *quaternion_xyzw(T)))


def export_loop_file(path: str | Path, query: np.ndarray, match: np.ndarray, pose: np.ndarray,
                     *, vertex_poses: np.ndarray | None = None,
                     frame_ids: np.ndarray | None = None, times: np.ndarray | None = None,
                     inlier_ratio: np.ndarray | None = None,
                     rmse_m: np.ndarray | None = None) -> int:
    """Write loops (``query``/``match`` frame indices, ``pose (K, 4, 4)``) to ``path``.

    The format follows the suffix (module docstring); ``vertex_poses``
    ``(N, 4, 4)`` are needed for ``.g2o``. Returns the number of loops written.
    """
    path = Path(path)
    kind = path.suffix.lower()
    if kind not in EXPORT_SUFFIXES:
        raise LirisError(path, f"loop export needs a {', '.join(EXPORT_SUFFIXES)} file name")
    query = np.asarray(query, dtype=np.int64)
    match = np.asarray(match, dtype=np.int64)
    pose = np.asarray(pose, dtype=np.float64).reshape(-1, 4, 4)
    n_frames = len(vertex_poses) if vertex_poses is not None else \
        int(max(np.max(query, initial=-1), np.max(match, initial=-1))) + 1
    ids = np.arange(n_frames) if frame_ids is None else np.asarray(frame_ids)
    lines: list[str] = []
    if kind == ".g2o":
        if vertex_poses is None:
            raise LirisError(path, "a .g2o graph needs one pose per frame for its vertices")
        for k, P in enumerate(np.asarray(vertex_poses, dtype=np.float64)):
            lines.append(f"VERTEX_SE3:QUAT {ids[k]} {_pose_numbers(P)}")
        if n_frames:
            lines.append(f"FIX {ids[0]}")
    elif kind == ".tum":
        lines.append("# t_query t_match x y z qx qy qz qw (pose of the match in the query's "
                     "LiDAR frame)")
    stamps = ids if times is None else np.asarray(times, dtype=np.float64)
    written = skipped = 0
    for k, (i, j, T) in enumerate(zip(query, match, pose, strict=True)):
        if not np.isfinite(T[:3, :3]).all() or (kind == ".g2o" and
                                                not np.isfinite(T[:3, 3]).all()):
            skipped += 1
            continue
        nums = _pose_numbers(T)
        if kind == ".g2o":
            ratio = np.nan if inlier_ratio is None else inlier_ratio[k]
            rmse = np.nan if rmse_m is None else rmse_m[k]
            info = " ".join(f"{v:.9g}" for v in
                            upper_triangle(information_from_fitness(ratio, rmse)))
            lines.append(f"EDGE_SE3:QUAT {ids[i]} {ids[j]} {nums} {info}")
        elif kind == ".tum":
            lines.append(f"{stamps[i]:.9g} {stamps[j]:.9g} {nums}")
        else:
            lines.append(f"{ids[i]} {ids[j]} {nums}")
        written += 1
    if skipped:
        warn(path, f"{skipped} accepted loop(s) without a usable pose for this format were "
                   "not written (refine them with --refine gicp)")
    _atomic_write(path, lines)
    return written


def read_g2o(path: str | Path) -> G2OGraph:
    """A g2o file's 3-D records (VERTEX_SE3:QUAT, EDGE_SE3:QUAT, FIX), every edge's
    vertices defined: :func:`lidar_iris_eval.io.loops.parse_g2o`, the one g2o reader."""
    return parse_g2o(path, need_vertices=True)
