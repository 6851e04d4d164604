"""How far an odometry drifts from the ground truth (``--odometry kiss-icp``).

Two figures, both independent of the odometry's world frame:

* **ATE RMSE** (m): the estimated positions are aligned to the ground truth by
  the least-squares rigid transform (Kabsch, no scale: a LiDAR odometry is
  metric), then the root mean square of the position residuals;
* **relative translation error** (%, KITTI's odometry metric restricted to
  translation): for every start frame ``i``, the first frame ``j`` whose
  ground-truth path length from ``i`` reaches ``length`` metres; the error is
  the translation of ``inv(G_i^-1 G_j) (E_i^-1 E_j)``, divided by the path
  length from ``i`` to ``j``, in percent, averaged over all such segments.
  ``None`` when no segment is that long.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.matching.geometry import kabsch


def ate_rmse(estimated: np.ndarray, ground_truth: np.ndarray) -> float:
    """ATE RMSE (m) of ``(N, 4, 4)`` poses (or ``(N, 3)`` positions) after rigid alignment."""
    est, gt = _positions(estimated), _positions(ground_truth)
    if len(est) != len(gt) or len(est) < 3:
        raise ValueError("ATE needs the same number (>= 3) of estimated and true poses")
    T = kabsch(est, gt)
    aligned = est @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


def relative_translation_error(estimated: np.ndarray, ground_truth: np.ndarray,
                               length: float = 100.0) -> float | None:
    """Mean relative translation error (%) over segments of ``length`` metres (module doc)."""
    est = np.asarray(estimated, dtype=np.float64)
    gt = np.asarray(ground_truth, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError("relative error needs (N, 4, 4) estimated and true poses")
    if not length > 0:
        raise ValueError("length must be positive")
    steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    ends = np.searchsorted(travelled, travelled + length, side="left")
    errors = []
    for i, j in enumerate(ends):
        if j >= len(gt):
            break
        rel_gt = np.linalg.inv(gt[i]) @ gt[j]
        rel_est = np.linalg.inv(est[i]) @ est[j]
        diff = np.linalg.inv(rel_gt) @ rel_est
        errors.append(np.linalg.norm(diff[:3, 3]) / (travelled[j] - travelled[i]))
    return float(np.mean(errors) * 100.0) if errors else None


def drift_report(estimated: np.ndarray, ground_truth: np.ndarray,
                 lengths: tuple[float, ...] = (100.0,)) -> dict:
    """``{"ate_rmse_m", "rte_pct_<L>m" per length, "path_m"}`` of an odometry."""
    gt = np.asarray(ground_truth, dtype=np.float64)
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    out = {"ate_rmse_m": ate_rmse(estimated, gt), "path_m": path}
    for length in lengths:
        out[f"rte_pct_{length:g}m"] = relative_translation_error(estimated, gt, length)
    return out


def _positions(poses: np.ndarray) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    return arr[:, :3, 3] if arr.ndim == 3 else arr[:, :3]
