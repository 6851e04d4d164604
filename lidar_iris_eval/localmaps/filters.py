"""Input filters applied to each scan, in its sensor frame, before it enters a local map.

Two named filters:

* ``segmap``: SegMap's outdoor input filter (ethz-asl/segmap
  ``input_filters_outdoor.yaml``): every 9th point, ``z >= -1.0 m`` in the
  sensor frame (its ground rule for KITTI's 1.73 m mount), horizontal range
  ``<= 50 m``;
* ``all``: the same height and range rules on every point (no decimation),
  for sensors sparser than a 64-beam KITTI scan;
* ``range``: every point within 50 m, no height rule (the ground is removed
  later, on the local map: ESM's ``ground_cell``), for sensors whose mount
  height and tilt the sensor-frame rule does not fit (handheld, other cars).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.errors import LirisError


@dataclass(frozen=True)
class InputFilter:
    """Keep every ``every``-th point with ``z >= min_z`` and horizontal range ``<= max_range``."""

    every: int = 9
    min_z: float = -1.0
    max_range: float = 50.0

    def apply(self, points: np.ndarray) -> np.ndarray:
        """The kept ``(M, 3)`` float64 points of ``(N, 3+)`` sensor-frame points."""
        pts = np.asarray(points, dtype=np.float64)[:, :3]
        return np.compress(self.mask(pts), pts, axis=0)  # pts[mask], faster on (n, 3) rows

    def mask(self, points: np.ndarray) -> np.ndarray:
        """``(N,)`` True for the points :meth:`apply` keeps (in their order)."""
        pts = np.asarray(points, dtype=np.float64)[:, :3]
        keep = np.zeros(len(pts), bool)
        keep[:: max(1, int(self.every))] = True
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]  # column by column: no (n, 3) reduction
        keep &= np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        keep &= z >= self.min_z
        keep &= np.hypot(x, y) <= self.max_range
        return keep


#: the named filters (module docstring)
INPUT_FILTERS: dict[str, InputFilter] = {
    "segmap": InputFilter(every=9, min_z=-1.0, max_range=50.0),
    "all": InputFilter(every=1, min_z=-1.0, max_range=50.0),
    "range": InputFilter(every=1, min_z=-np.inf, max_range=50.0),
}


def input_filter(name: str) -> InputFilter:
    """The named filter; a LirisError for an unknown name."""
    try:
        return INPUT_FILTERS[name]
    except KeyError:
        raise LirisError("input_filter", f"unknown input filter {name!r}; choose from "
                                         f"{', '.join(INPUT_FILTERS)}") from None
