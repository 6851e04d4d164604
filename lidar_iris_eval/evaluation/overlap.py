"""Overlap ground truth (``--gt overlap``): OverlapNet-style overlap of range images.

OverlapNet and OverlapTransformer call a pair a loop when the *overlap* of
the two scans' range images is at least 0.3 (PRBonn/OverlapNet
``src/utils/com_overlap_yaw.py`` and ``utils.py::range_projection``: 64 x 900
pixels, field of view +3 deg .. -25 deg, points beyond 50 m dropped, the
closest point wins a pixel, ranges agree within 1 m). It needs the point
clouds, not only the poses.

Definition used here (every value in :class:`OverlapSpec`, written with
the result):

1. Each scan ``k`` becomes a range image ``R_k`` (LiDAR frame; pixel column
   from the azimuth ``-atan2(y, x)``, row from the elevation within the field
   of view, clamped to the border like OverlapNet; ranges in ``(0, 50) m``;
   the closest point of a pixel wins). Its *vertices* are the points that won
   a pixel.
2. ``overlap(i, j)``: the vertices of scan ``j`` are moved into scan ``i``'s
   frame with the ground-truth LiDAR poses (``inv(T_i) T_j``) and projected
   the same way into ``R_{j->i}``. The overlap is the number of pixels valid
   in both ``R_i`` and ``R_{j->i}`` whose ranges differ by less than 1 m,
   divided by the number of valid pixels of ``R_i``. It is not symmetric;
   ``i`` is the query (OverlapNet's "current" frame).

   OverlapNet's own script compares the current scan's points re-projected
   from the reference pose with the current scan's image, so the reference
   scan itself never enters; here the reference (database) scan is the one
   projected, so the overlap says whether the two *scans* see the same surfaces.
3. A pair farther apart than ``2 * max_range`` cannot share a pixel (every
   projected point lies within ``max_range`` of both sensors), so its overlap
   is exactly 0 and is not computed.
4. Ground truth: ``(i, j)``, ``j < i``, is a positive pair when
   ``overlap(i, j) >= threshold`` (0.3): the later frame is the query.

The overlap matrix is cached (``overlap-<key>.npz`` in the descriptor cache
folder, keyed by the sequence fingerprint, the poses and the spec).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import GroundTruth, revisit_queries

OVERLAP_FORMAT = 1


@dataclass(frozen=True)
class OverlapSpec:
    """Range-image projection and the overlap rule (OverlapNet's values by default)."""

    height: int = 64
    width: int = 900
    fov_up_deg: float = 3.0
    fov_down_deg: float = -25.0
    max_range: float = 50.0
    range_tolerance: float = 1.0
    neighbourhood: int = 1
    threshold: float = 0.3
    source: str = ("PRBonn/OverlapNet src/utils/utils.py range_projection (64 x 900, "
                   "+3/-25 deg, 50 m) and com_overlap_yaw.py (|dr| < 1 m); threshold 0.3 "
                   "as OverlapTransformer test/test_kitti00_PR.py")

    def key(self) -> dict:
        out = asdict(self)
        out.pop("source")
        return out


def _pixels(points: np.ndarray, spec: OverlapSpec) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel index and range of the points within ``(0, max_range)``."""
    depth = np.sqrt(np.einsum("ij,ij->i", points, points))
    keep = (depth > 0) & (depth < spec.max_range)
    p, depth = points[keep], depth[keep]
    up, down = np.radians(spec.fov_up_deg), np.radians(spec.fov_down_deg)
    fov = abs(up) + abs(down)
    yaw = -np.arctan2(p[:, 1], p[:, 0])
    pitch = np.arcsin(np.clip(p[:, 2] / depth, -1.0, 1.0))
    col = np.floor(0.5 * (yaw / np.pi + 1.0) * spec.width)
    row = np.floor((1.0 - (pitch + abs(down)) / fov) * spec.height)
    col = np.clip(col, 0, spec.width - 1).astype(np.int64)
    row = np.clip(row, 0, spec.height - 1).astype(np.int64)
    return row * spec.width + col, depth


def range_image(points: np.ndarray, spec: OverlapSpec = OverlapSpec()
                ) -> tuple[np.ndarray, np.ndarray]:
    """``(H*W,)`` ranges (``inf`` where empty) and the ``(M, 3)`` vertices that won a pixel."""
    points = np.asarray(points, dtype=np.float64)[:, :3]
    flat, depth = _pixels(points, spec)
    image = np.full(spec.height * spec.width, np.inf)
    np.minimum.at(image, flat, depth)
    depth_all = np.linalg.norm(points, axis=1)
    keep = (depth_all > 0) & (depth_all < spec.max_range)
    winners = np.zeros(len(flat), bool)
    # the closest point of each pixel (first of equal ranges): sort by pixel, then range
    order = np.lexsort((depth, flat))
    first = np.ones(len(order), bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    winners[order[first]] = True
    return image, points[keep][winners]


def pair_overlap(image_i: np.ndarray, vertices_j: np.ndarray, j_to_i: np.ndarray,
                 spec: OverlapSpec = OverlapSpec()) -> float:
    """``overlap(i, j)`` of step 2 (``j_to_i`` = ``inv(T_i) T_j``, 4x4)."""
    valid_i = np.isfinite(image_i)
    n_valid = int(np.count_nonzero(valid_i))
    if n_valid == 0 or len(vertices_j) == 0:
        return 0.0
    rot = j_to_i[:3, :3].astype(np.float32)
    moved = vertices_j.astype(np.float32, copy=False) @ rot.T + j_to_i[:3, 3].astype(np.float32)
    flat, depth = _pixels(moved, spec)
    projected = np.full(spec.height * spec.width, np.inf)
    np.minimum.at(projected, flat, depth)
    h, w, k = spec.height, spec.width, spec.neighbourhood
    # empty pixels hold a range no sensor returns, so they never agree (and no inf - inf)
    far = np.float32(1e6)
    image = np.where(valid_i, image_i, -far).astype(np.float32).reshape(h, w)
    padded = np.full((h + 2 * k, w + 2 * k), far, np.float32)
    proj = np.where(np.isfinite(projected), projected, far).astype(np.float32).reshape(h, w)
    padded[k:k + h, k:k + w] = proj
    if k:  # columns wrap around (azimuth)
        padded[k:k + h, :k] = proj[:, w - k:]
        padded[k:k + h, k + w:] = proj[:, :k]
    agree = np.zeros((h, w), bool)
    tol = np.float32(spec.range_tolerance)
    for dr in range(2 * k + 1):
        for dc in range(2 * k + 1):
            agree |= np.abs(image - padded[dr:dr + h, dc:dc + w]) < tol
    return float(np.count_nonzero(agree) / n_valid)


def overlap_matrix(
    scans: Sequence[np.ndarray] | Callable[[int], np.ndarray],
    lidar_poses: np.ndarray,
    spec: OverlapSpec = OverlapSpec(),
    progress: bool = False,
) -> np.ndarray:
    """``(N, N)`` float32, ``[i, j]`` = overlap of query ``i`` with database ``j``.

    ``scans`` are ``(n, >=3)`` LiDAR-frame points, a list or ``index -> points``.
    The diagonal is 1 by definition; pairs farther than ``2 * max_range`` are 0.
    """
    from scipy.spatial import cKDTree
    from tqdm import tqdm

    poses = np.asarray(lidar_poses, dtype=np.float64)
    n = len(poses)
    get = scans if callable(scans) else scans.__getitem__
    images, vertices = [], []
    for k in tqdm(range(n), desc="overlap: range images", unit="scan", disable=not progress,
                  leave=False):
        image, vert = range_image(get(k), spec)
        images.append(image)
        vertices.append(vert)
    out = np.zeros((n, n), np.float32)
    np.fill_diagonal(out, 1.0)
    pairs = cKDTree(poses[:, :3, 3]).query_pairs(2 * spec.max_range, output_type="ndarray")
    inv = np.linalg.inv(poses)
    for a, b in tqdm(pairs, desc="overlap: pairs", unit="pair", disable=not progress,
                     leave=False):
        out[a, b] = pair_overlap(images[a], vertices[b], inv[a] @ poses[b], spec)
        out[b, a] = pair_overlap(images[b], vertices[a], inv[b] @ poses[a], spec)
    return out


def overlap_ground_truth(overlap: np.ndarray, exclude: int,
                         spec: OverlapSpec = OverlapSpec()) -> GroundTruth:
    """Ground truth of step 4 as a :class:`GroundTruth` (radius field: NaN, not used)."""
    overlap = np.asarray(overlap)
    n = len(overlap)
    later, earlier = np.nonzero(np.tril(overlap >= spec.threshold, -1))
    pairs = np.stack([earlier, later], axis=1).astype(np.int64) if len(later) else \
        np.empty((0, 2), np.int64)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    return GroundTruth(n, float("nan"), int(exclude), "overlap", "lidar", pairs,
                       revisit_queries(pairs, n, int(exclude)))


def cache_path(cache_dir: Path, fingerprint: str, lidar_poses: np.ndarray,
               spec: OverlapSpec) -> Path:
    """``<cache_dir>/overlap-<key>.npz``; the key hashes the scans, poses and spec."""
    digest = hashlib.sha256()
    digest.update(json.dumps({"format": OVERLAP_FORMAT, "scans": fingerprint,
                              "spec": spec.key()}, sort_keys=True).encode())
    digest.update(np.ascontiguousarray(lidar_poses, dtype=np.float64).tobytes())
    return Path(cache_dir) / f"overlap-{digest.hexdigest()[:20]}.npz"


def cached_overlap_matrix(sequence, cache_dir: Path | None, spec: OverlapSpec = OverlapSpec(),
                          progress: bool = False) -> tuple[np.ndarray, bool]:
    """The overlap matrix of an opened sequence, from the cache when present.

    Returns ``(matrix, from_cache)``. ``sequence`` needs ``lidar_poses()``
    ``poses`` (LiDAR frame), ``fingerprint()`` and ``sequence[i]`` (points).
    """
    from lidar_iris_eval.cache import default_cache_dir, read_arrays, write_arrays

    poses = lidar_poses_of(sequence)
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = cache_path(root, sequence.fingerprint(), poses, spec)
    if path.is_file():
        try:
            arrays, meta = read_arrays(path)
            if meta.get("spec") == spec.key() and arrays["overlap"].shape == (len(poses),) * 2:
                return arrays["overlap"], True
        except (ValueError, KeyError, OSError):
            pass  # damaged or unreadable: rebuilt below
    matrix = overlap_matrix(lambda k: points_of(sequence, k), poses, spec, progress)
    root.mkdir(parents=True, exist_ok=True)
    write_arrays(path, {"overlap": matrix}, {"spec": spec.key(), "format": OVERLAP_FORMAT})
    return matrix, False


def lidar_poses_of(sequence) -> np.ndarray:
    """``(N, 4, 4)`` LiDAR-frame poses of an opened sequence."""
    poses = getattr(sequence, "poses", None)
    if poses is None:
        raise LirisError("--gt overlap", "the sequence has no LiDAR-frame poses")
    return np.asarray(poses, dtype=np.float64)


def points_of(sequence, index: int) -> np.ndarray:
    """``(n, 3)`` points of scan ``index`` of an opened sequence."""
    return np.asarray(sequence[index])[:, :3]
