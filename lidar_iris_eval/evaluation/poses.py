"""Relative poses of loop closures: ground truth, errors and ``T`` columns (loop export:
``evaluation/loop_export.py``).

Convention (see ``descriptors/base.py``): the pose ``T`` of a match
``(query i, match j)`` maps points of scan ``j``'s LiDAR frame into scan
``i``'s LiDAR frame. With LiDAR-frame poses ``P`` (``Sequence.poses``, i.e.
KITTI camera poses converted with ``Tr``) the ground truth is
``T_gt = inv(P_i) @ P_j``.

Errors, per match with an estimate:

* ``rre_deg`` – rotation error in degrees. For a *yaw-only* estimate
  (rotation known, translation NaN: LiDAR Iris, Scan Context) it is the
  wrapped heading difference, because roll and pitch are not the method's to
  recover; for a full pose it is the geodesic angle of ``R_est^T R_gt``.
* ``rte_m`` – translation error in metres, only for full poses.

Summaries (median, 90th percentile) are taken over the *true* top-1 matches
(protocol 1's ``is_true``), whatever their distance: the pose quality of the
loops a method finds, independent of the threshold. Undefined -> None.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.matching.geometry import (
    invert_pose,
    rotation_error_deg,
    translation_error_m,
    yaw_error_deg,
)

#: names of the 12 matches.csv columns: row-major 3x4 of T
T_COLUMNS = tuple(f"T{r}{c}" for r in range(3) for c in range(4))
POSE_ERROR_RULE = (
    "over true top-1 matches; rre_deg = heading difference for yaw-only estimates "
    "(translation unknown), geodesic rotation angle for full poses; rte_m = translation "
    "error of full poses; ground truth inv(P_query) @ P_match with LiDAR-frame poses"
)


def relative_ground_truth(lidar_poses: np.ndarray, query: np.ndarray,
                          match: np.ndarray) -> np.ndarray:
    """``(Q, 4, 4)`` ``inv(P_query) @ P_match``; NaN rows where ``match < 0``."""
    query = np.asarray(query, dtype=np.int64)
    match = np.asarray(match, dtype=np.int64)
    out = np.full((len(query), 4, 4), np.nan)
    ok = match >= 0
    if ok.any():
        P = np.asarray(lidar_poses, dtype=np.float64)
        out[ok] = invert_pose(P[query[ok]]) @ P[match[ok]]
    return out


def pose_errors(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rre_deg, rte_m)`` per row (rules in the module docstring); NaN where undefined."""
    est = np.asarray(est, dtype=np.float64)
    n = len(est)
    rre = np.full(n, np.nan)
    rte = np.full(n, np.nan)
    if n == 0:
        return rre, rte
    rot_ok = np.isfinite(est[:, :3, :3]).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    full = rot_ok & np.isfinite(est[:, :3, 3]).all(axis=1)
    yaw_only = rot_ok & ~full
    if full.any():
        rre[full] = rotation_error_deg(est[full], gt[full])
        rte[full] = translation_error_m(est[full], gt[full])
    if yaw_only.any():
        rre[yaw_only] = yaw_error_deg(est[yaw_only], gt[yaw_only])
    return rre, rte


def summarize_pose_errors(rre: np.ndarray, rte: np.ndarray, mask: np.ndarray) -> dict:
    """Median and 90th percentile of the errors of rows in ``mask`` (None if none)."""
    out: dict = {}
    for name, values in (("rre_deg", rre), ("rte_m", rte)):
        v = np.asarray(values)[np.asarray(mask, bool)]
        v = v[np.isfinite(v)]
        out[f"{name}_median"] = float(np.median(v)) if len(v) else None
        out[f"{name}_p90"] = float(np.percentile(v, 90)) if len(v) else None
        out[f"n_{name}"] = int(len(v))
    return out


def t_columns(pose: np.ndarray) -> dict[str, np.ndarray]:
    """The 12 ``T00..T23`` columns (row-major 3x4) of ``(Q, 4, 4)`` poses."""
    pose = np.asarray(pose, dtype=np.float64)
    return {name: pose[:, int(name[1]), int(name[2])] for name in T_COLUMNS}
