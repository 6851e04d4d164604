"""BEVPlace++'s 3-DoF pose of a retrieved match: FAST keypoints, local features, 2-D RANSAC.

Restated from ``kitti_dataset.py`` (``evaluateResults``, lines 85-123) and
``RANSAC.py`` of zjuluolun/BEVPlace2 (MIT; read for the method, the code here
is written anew). For a query scan and its retrieved database scan:

1. **keypoints**: FAST-9 corners of each 8-bit BEV image (:mod:`.fast`,
   OpenCV's defaults: threshold 10, non-maximum suppression;
   ``kitti_dataset.py`` lines 85-89);
2. **local features**: the REM's second output (the rotation-equivariant
   maximum map resampled to the full image and L2-normalised per pixel) read
   at each keypoint's pixel (lines 92-93; :func:`.network.local_features`);
3. **matching**: each query keypoint to its nearest database keypoint in L2
   (OpenCV's ``BFMatcher`` with ``knnMatch(k=2)``, of which only the first
   neighbour is used: no ratio test, no cross check; lines 98-105);
4. **metres**: pixel ``(row, col)`` to ``((c - row) * 0.4, (c - col) * 0.4)``
   with ``c = side // 2 = 100`` (line 107 and ``RANSAC.py`` lines 27-28):
   LiDAR ``(x, y)`` of the pixel's corner nearest the sensor's (the BEV image
   puts ``x`` in row ``100 - floor(x / 0.4)``, so the pixel spans
   ``[(100 - row) 0.4, (101 - row) 0.4)``);
5. **RANSAC** (``RANSAC.py`` ``rigidRansac``): 1000 iterations (line 32); each
   draws 2 correspondences uniformly with replacement (lines 33-34; a third is
   drawn and never used, line 35), fits a 2-D rotation and translation by the
   SVD (Kabsch) rule (``svdICP``, lines 4-24), counts the correspondences whose
   moved query point lies within 0.5 m of its database point (strict ``<``,
   lines 40-44), and keeps the first hypothesis with the most; the rotation and
   translation are then refitted on its inliers (line 53).

The authors' transform maps query coordinates to database coordinates
(``points2 = R points1 + t``). liris' pose of a match maps the candidate's
(database) LiDAR frame into the query's (``p_i = T p_j``, ground truth
``inv(P_i) P_j``), so the result is the inverse, lifted to SE(3) with zero z,
roll and pitch (as MapClosures' 2-D pose).

Differences, named: OpenCV's FAST and brute-force matcher are restated in
NumPy (:mod:`.fast`; ties in the nearest neighbour go to the first database
keypoint); the random draws come from a NumPy ``Generator`` seeded per pair
``(ransac_seed, query, candidate)`` (the authors use the global
``np.random`` stream, not seeded per pair), so a pose does not depend on which
other pairs were estimated; the local features are stored as int8
(``round(127 v)``) in the cache and matched as such (the authors keep float32);
fewer than 2 keypoints on either side, or a best hypothesis with no inlier,
give no pose (NaN) where the authors' code would fail.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: RANSAC.py line 32
RANSAC_ITERATIONS = 1000
#: RANSAC.py lines 44-45 (metres, strict)
INLIER_THRESHOLD = 0.5
#: int8 scale of the stored unit local features
QUANT_SCALE = 127.0


@dataclass(frozen=True)
class PlanarFit:
    """A 2-D rigid fit: ``dst ~ R(yaw) src + t`` and its inlier count."""

    yaw: float
    t: np.ndarray
    inliers: int

    def matrix(self) -> np.ndarray:
        """``(3, 3)`` homogeneous 2-D transform."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, self.t[0]], [s, c, self.t[1]], [0.0, 0.0, 1.0]])


def quantise(features: np.ndarray) -> np.ndarray:
    """Unit float features to int8 ``round(127 v)`` (components of unit vectors, |v| <= 1)."""
    q = np.rint(np.asarray(features, dtype=np.float32) * np.float32(QUANT_SCALE))
    return np.clip(q, -127, 127).astype(np.int8)


def dequantise(codes: np.ndarray) -> np.ndarray:
    """int8 codes back to float32 ``code / 127``."""
    return np.asarray(codes, dtype=np.float32) / np.float32(QUANT_SCALE)


def pixels_to_metres(pixels: np.ndarray, side: int, voxel_size: float,
                     offset: float = 0.0) -> np.ndarray:
    """``(K, 2)`` LiDAR ``(x, y)`` of ``(row, col)`` pixels of a ``side x side`` BEV image.

    ``((c - row + offset) voxel, (c - col + offset) voxel)`` with ``c = side // 2``:
    ``offset = 0`` is the authors' (the pixel's corner toward the sensor),
    ``0.5`` its centre.
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    c = side // 2
    return np.stack([(c - px[:, 0] + offset) * voxel_size,
                     (c - px[:, 1] + offset) * voxel_size], axis=1)


def nearest(query: np.ndarray, database: np.ndarray) -> np.ndarray:
    """``(Kq,)`` index of each query row's nearest database row in L2 (first on ties)."""
    q = np.asarray(query, dtype=np.float32)
    d = np.asarray(database, dtype=np.float32)
    d2 = (q * q).sum(1)[:, None] + (d * d).sum(1)[None, :] - 2.0 * (q @ d.T)
    return np.argmin(d2, axis=1)


def _rotation(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Angle of the proper 2-D rotation best aligning centred ``src`` to ``dst`` (last axis 2).

    For 2-D points the SVD rule with its determinant correction is the angle
    ``atan2(sum cross, sum dot)``; all-zero sums give 0 (the identity the SVD
    of a zero matrix gives).
    """
    cross = (src[..., 0] * dst[..., 1] - src[..., 1] * dst[..., 0]).sum(-1)
    dot = (src[..., 0] * dst[..., 0] + src[..., 1] * dst[..., 1]).sum(-1)
    return np.arctan2(cross, dot)


def kabsch_2d(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-squares 2-D rotation angle and translation with ``dst ~ R src + t``."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    ms, md = src.mean(0), dst.mean(0)
    yaw = float(_rotation(src - ms, dst - md))
    c, s = np.cos(yaw), np.sin(yaw)
    t = md - np.array([[c, -s], [s, c]]) @ ms
    return yaw, t


def rigid_ransac(src: np.ndarray, dst: np.ndarray, rng: np.random.Generator,
                 iterations: int = RANSAC_ITERATIONS,
                 threshold: float = INLIER_THRESHOLD) -> PlanarFit | None:
    """The authors' 2-point RANSAC of ``dst ~ R src + t`` (module docstring, step 5).

    Returns None with fewer than 2 correspondences or no inlier at all.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    if n < 2 or iterations < 1:
        return None
    picks = rng.integers(0, n, size=(iterations, 2))  # with replacement, as randint
    a, b = src[picks], dst[picks]                      # (I, 2, 2)
    ca, cb = a.mean(1, keepdims=True), b.mean(1, keepdims=True)
    yaw = _rotation(a - ca, b - cb)                    # (I,)
    c, s = np.cos(yaw), np.sin(yaw)
    t = cb[:, 0] - np.stack([c * ca[:, 0, 0] - s * ca[:, 0, 1],
                             s * ca[:, 0, 0] + c * ca[:, 0, 1]], axis=1)
    counts = np.zeros(iterations, dtype=np.int64)
    step = max(1, 2_000_000 // max(n, 1))
    for lo in range(0, iterations, step):
        hi = min(lo + step, iterations)
        mx = c[lo:hi, None] * src[None, :, 0] - s[lo:hi, None] * src[None, :, 1] + t[lo:hi, 0:1]
        my = s[lo:hi, None] * src[None, :, 0] + c[lo:hi, None] * src[None, :, 1] + t[lo:hi, 1:2]
        err = np.hypot(mx - dst[None, :, 0], my - dst[None, :, 1])
        counts[lo:hi] = (err < threshold).sum(1)
    best = int(np.argmax(counts))  # the first of the most, as the strict ">" update
    if counts[best] == 0:
        return None
    moved = src @ np.array([[c[best], s[best]], [-s[best], c[best]]]) + t[best]
    mask = np.hypot(*(moved - dst).T) < threshold
    fit_yaw, fit_t = kabsch_2d(src[mask], dst[mask])
    return PlanarFit(fit_yaw, fit_t, int(counts[best]))


def planar_pose(fit: PlanarFit) -> np.ndarray:
    """``(4, 4)`` SE(3) pose of a 2-D fit: rotation about z, zero z, roll and pitch."""
    T = np.eye(4)
    m = fit.matrix()
    T[:2, :2], T[:2, 3] = m[:2, :2], m[:2, 2]
    return T


def match_pose(query_px: np.ndarray, query_codes: np.ndarray, cand_px: np.ndarray,
               cand_codes: np.ndarray, side: int, voxel_size: float, rng: np.random.Generator,
               iterations: int = RANSAC_ITERATIONS, threshold: float = INLIER_THRESHOLD,
               offset: float = 0.0) -> tuple[np.ndarray, int]:
    """Pose (candidate LiDAR frame -> query's, ``(4, 4)``, NaN if none) and inlier count.

    ``*_px`` are ``(K, 2)`` keypoint pixels, ``*_codes`` their int8 (or float)
    local features.
    """
    nan = np.full((4, 4), np.nan)
    if len(query_px) < 2 or len(cand_px) < 2:
        return nan, 0
    qf = dequantise(query_codes) if np.asarray(query_codes).dtype == np.int8 else query_codes
    cf = dequantise(cand_codes) if np.asarray(cand_codes).dtype == np.int8 else cand_codes
    pair = nearest(qf, cf)
    q_xy = pixels_to_metres(query_px, side, voxel_size, offset)
    c_xy = pixels_to_metres(np.asarray(cand_px)[pair], side, voxel_size, offset)
    fit = rigid_ransac(q_xy, c_xy, rng, iterations, threshold)  # query -> candidate
    if fit is None:
        return nan, 0
    return np.linalg.inv(planar_pose(fit)), fit.inliers
