"""BEVPlace++'s bird's-eye-view density image, as the authors' code makes it.

Restated from ``datasets/gen_bev_images.py`` and ``kitti_dataset.py`` of
zjuluolun/BEVPlace2 (MIT; read for the conventions only). With the authors'
constants ``voxel_size = 0.4`` m and ``bev_range = 40`` m:

1. **crop**: points with ``|x| < 40``, ``|y| < 40`` and ``|z| < 40`` (strict, in
   the scan's float32) are kept: a square of 80 m around the sensor, not a disc;
2. **voxel averaging**: Open3D's ``voxel_down_sample(0.4)``: voxel
   ``floor((p - b) / 0.4)`` with ``b`` the cropped cloud's minimum corner minus
   half a voxel (so the 3-D grid moves with the data, in float64), each occupied
   voxel replaced by the mean of its points;
3. **binning**: ``n = floor(40 / 0.4) = 100``; the mean point ``(x, y)`` falls in
   row ``n - floor(x / 0.4)`` and column ``n - floor(y / 0.4)`` of a
   ``(2n + 1) x (2n + 1) = 201 x 201`` image: forward (+x) is up, left (+y) is
   to the left, the sensor in pixel (100, 100)'s lower-right corner. The crop
   leaves row 0 and column 0 always empty (the authors' indexing);
4. **density**: the count of voxel means per pixel, capped at 10, times 10,
   divided by the image's maximum and times 255 (the densest pixel is 255
   whatever its count; an empty image stays 0 here, where the authors' code
   divides by zero);
5. **8-bit round trip**: the authors write that float image with
   ``cv2.imwrite`` to a PNG (OpenCV rounds to the nearest integer, ties to
   even) and their data loader reads it back as ``uint8 / 256`` (not 255), the
   same value in each of 3 channels, with no mean/std normalisation.

:func:`bev_image` returns step 4's rounded 8-bit image; :func:`network_input`
turns it into what the network reads.
"""

from __future__ import annotations

import math

import numpy as np

#: the authors' constants (gen_bev_images.py)
VOXEL_SIZE, BEV_RANGE, COUNT_CAP = 0.4, 40.0, 10


def image_size(bev_range: float = BEV_RANGE, voxel_size: float = VOXEL_SIZE) -> int:
    """Side of the square image: ``2 floor(bev_range / voxel_size) + 1`` (201)."""
    return 2 * math.floor(bev_range / voxel_size) + 1


def crop(points: np.ndarray, bev_range: float = BEV_RANGE) -> np.ndarray:
    """The float32 points with ``|x|``, ``|y|`` and ``|z|`` all below ``bev_range``."""
    pts = np.asarray(points)[:, :3].astype(np.float32, copy=False)
    r = np.float32(bev_range)
    keep = (np.abs(pts[:, 0]) < r) & (np.abs(pts[:, 1]) < r) & (np.abs(pts[:, 2]) < r)
    return pts[keep]


def voxel_means(points: np.ndarray, voxel_size: float = VOXEL_SIZE) -> np.ndarray:
    """Open3D's ``voxel_down_sample``: the float64 mean of each occupied voxel.

    The grid starts half a voxel below the cloud's minimum corner, as Open3D's
    does, so it depends on the data (a shifted or turned scan is voxelised on
    another grid). Row order is not Open3D's (it does not matter for counts).
    """
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    if len(pts) == 0:
        return np.zeros((0, 3))
    start = pts.min(axis=0) - voxel_size * 0.5
    keys = np.floor((pts - start) / voxel_size).astype(np.int64)  # >= 0 per axis
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]  # one int64 per voxel
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=pts[:, a], minlength=len(counts))
                     for a in range(3)], axis=1)
    return sums / counts[:, None]


def density_counts(means: np.ndarray, bev_range: float = BEV_RANGE,
                   voxel_size: float = VOXEL_SIZE, cap: int = COUNT_CAP) -> np.ndarray:
    """``(S, S)`` int64 counts of points per pixel (step 3), capped at ``cap``."""
    n = math.floor(bev_range / voxel_size)
    side = 2 * n + 1
    pts = np.asarray(means, dtype=np.float64)
    rows = n - np.floor(pts[:, 0] / voxel_size).astype(np.int64)
    cols = n - np.floor(pts[:, 1] / voxel_size).astype(np.int64)
    inside = (rows >= 0) & (rows < side) & (cols >= 0) & (cols < side)
    counts = np.bincount(rows[inside] * side + cols[inside], minlength=side * side)
    return np.minimum(counts, cap).reshape(side, side)


def normalise(counts: np.ndarray) -> np.ndarray:
    """Step 4 and the PNG's rounding: ``uint8`` image, the densest pixel 255.

    Computed in the authors' order (``counts * 10 / max(counts * 10) * 255`` in
    float64), so ties (e.g. 127.5 for one count against two) round as theirs.
    """
    scaled = np.minimum(np.asarray(counts, dtype=np.int64) * 10, 255).astype(np.float64)
    top = scaled.max() if scaled.size else 0.0
    if top == 0:
        return np.zeros(np.shape(counts), dtype=np.uint8)
    return np.clip(np.rint(scaled / top * 255), 0, 255).astype(np.uint8)


def bev_image(points: np.ndarray, bev_range: float = BEV_RANGE,
              voxel_size: float = VOXEL_SIZE, cap: int = COUNT_CAP) -> np.ndarray:
    """The ``(201, 201)`` ``uint8`` BEV image of a scan (steps 1-5, module docstring)."""
    means = voxel_means(crop(points, bev_range), voxel_size)
    return normalise(density_counts(means, bev_range, voxel_size, cap))


def network_input(images: np.ndarray) -> np.ndarray:
    """``(B, 3, S, S)`` float32 network input of ``(B, S, S)`` 8-bit images (``/ 256``)."""
    x = np.asarray(images, dtype=np.float32) / np.float32(256.0)
    return np.ascontiguousarray(np.repeat(x[:, None], 3, axis=1))
