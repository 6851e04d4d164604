"""FAST-9 corners of an 8-bit image, in NumPy: the keypoints of BEVPlace++'s pose.

The authors detect keypoints on the 8-bit BEV image with OpenCV's
``cv2.FastFeatureDetector_create()`` at its defaults (``kitti_dataset.py``
line 85 of zjuluolun/BEVPlace2): threshold 10, non-maximum suppression on,
the 9-of-16 test. OpenCV is not a liris dependency, so the detector is written
here from the published definition (Rosten and Drummond, 2006) and OpenCV's
documented behaviour:

* **test**: pixel ``p`` of value ``v`` is a corner when 9 contiguous pixels of
  the 16 on the Bresenham circle of radius 3 are all brighter than ``v + t``
  or all darker than ``v - t`` (strict inequalities);
* **border**: only pixels at least 3 from every edge are tested (the circle
  must fit);
* **score**: the largest ``m`` over the 16 arcs of 9 contiguous pixels and
  both signs of the smallest ``|circle - v|`` on the arc (a corner has
  ``m > t``; OpenCV stores ``m - 1``, the same order);
* **non-maximum suppression**: a corner is kept when its score is strictly
  larger than the score of each of its 8 neighbours (non-corners score 0), so
  two equal neighbouring maxima both go, as in OpenCV.

Keypoints are returned in raster order (row, then column), the order OpenCV
emits them; ``(row, col)`` integer pixels (OpenCV's ``pt`` is ``(col, row)``
as floats, which the authors truncate back to integers). Checked against
OpenCV 5.1.0 (``opencv-python-headless``, in a separate environment): the same
keypoints in the same order on the four KITTI sample BEV images and on a
dense and a sparse random image (recorded in ``tests/test_bevplace_pose.py``).
"""

from __future__ import annotations

import numpy as np

#: OpenCV's FastFeatureDetector default threshold (kitti_dataset.py line 85: no argument)
THRESHOLD = 10
#: contiguous pixels of the 16 that make a corner (TYPE_9_16, OpenCV's default)
ARC = 9
#: the 16 pixels of the radius-3 Bresenham circle, (row, col) offsets in circular order
CIRCLE = ((-3, 0), (-3, 1), (-2, 2), (-1, 3), (0, 3), (1, 3), (2, 2), (3, 1),
          (3, 0), (3, -1), (2, -2), (1, -3), (0, -3), (-1, -3), (-2, -2), (-3, -1))


def corner_scores(image: np.ndarray, threshold: int = THRESHOLD) -> np.ndarray:
    """``(H, W)`` int32 score of each corner pixel, 0 elsewhere (module docstring)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"expected a 2-D 8-bit image, got shape {img.shape}")
    h, w = img.shape
    scores = np.zeros((h, w), dtype=np.int32)
    if h < 7 or w < 7:
        return scores
    v = img.astype(np.int32)
    centre = v[3:h - 3, 3:w - 3]
    # (16, H-6, W-6): circle minus centre, in circular order, then the first 8 repeated
    diff = np.stack([v[3 + dr:h - 3 + dr, 3 + dc:w - 3 + dc] - centre for dr, dc in CIRCLE])
    ring = np.concatenate([diff, diff[:ARC - 1]])
    best = np.full(centre.shape, np.iinfo(np.int32).min, dtype=np.int32)
    for start in range(len(CIRCLE)):
        arc = ring[start:start + ARC]
        np.maximum(best, arc.min(axis=0), out=best)     # all brighter by at least this
        np.maximum(best, -arc.max(axis=0), out=best)    # all darker by at least this
    scores[3:h - 3, 3:w - 3] = np.where(best > threshold, best, 0)
    return scores


def detect(image: np.ndarray, threshold: int = THRESHOLD,
           nonmax: bool = True) -> np.ndarray:
    """``(K, 2)`` int64 ``(row, col)`` FAST-9 keypoints of ``image``, raster order."""
    scores = corner_scores(image, threshold)
    corner = scores > 0
    if nonmax:
        padded = np.pad(scores, 1)
        h, w = scores.shape
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if dr or dc:
                    corner &= scores > padded[1 + dr:1 + dr + h, 1 + dc:1 + dc + w]
    return np.argwhere(corner).astype(np.int64)
