"""The settings of a local map, in one frozen object (they enter the cache key)."""

from __future__ import annotations

from dataclasses import dataclass

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.localmaps.filters import INPUT_FILTERS
from lidar_iris_eval.localmaps.odometry import ODOMETRY_SOURCES


@dataclass(frozen=True)
class LocalMapSettings:
    """How the local map of every frame is built.

    Attributes
    ----------
    window : W, the scans of frames ``i - W < j <= i`` form frame ``i``'s map
        (the evaluation's exclusion window E, so a query's map never holds a
        scan of a database frame ``j <= i - E``).
    voxel : voxel edge (m), SegMap's 0.1 m.
    radius : horizontal crop radius around the current pose (m), SegMap's 50 m.
    input_filter : a name of :data:`~lidar_iris_eval.localmaps.filters.INPUT_FILTERS`.
    odometry : a name of :data:`~lidar_iris_eval.localmaps.odometry.ODOMETRY_SOURCES`.
    """

    window: int
    voxel: float = 0.1
    radius: float = 50.0
    input_filter: str = "segmap"
    odometry: str = "gt"

    def __post_init__(self) -> None:
        if int(self.window) < 1:
            raise LirisError("window", f"a local map needs at least 1 frame, got {self.window}")
        if not (0.001 <= self.voxel <= 10.0):
            raise LirisError("voxel", f"must be within [0.001, 10] m, got {self.voxel}")
        if not self.radius > 0:
            raise LirisError("radius", f"must be positive, got {self.radius}")
        if self.input_filter not in INPUT_FILTERS:
            raise LirisError("input_filter", f"unknown input filter {self.input_filter!r}; "
                                             f"choose from {', '.join(INPUT_FILTERS)}")
        if self.odometry not in ODOMETRY_SOURCES:
            raise LirisError("odometry", f"unknown odometry {self.odometry!r}; choose from "
                                         f"{', '.join(ODOMETRY_SOURCES)}")
