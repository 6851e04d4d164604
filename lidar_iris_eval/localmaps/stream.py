"""The local maps of a range of frames, built from the scans the window needs."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from lidar_iris_eval.localmaps.filters import input_filter
from lidar_iris_eval.localmaps.grid import LocalMap, LocalMapFrame
from lidar_iris_eval.localmaps.settings import LocalMapSettings


def local_maps(read, poses: np.ndarray, settings: LocalMapSettings, start: int, stop: int,
               ) -> Iterator[tuple[LocalMapFrame, float]]:
    """Yield ``(map of frame i, seconds of its update)`` for ``start <= i < stop``.

    ``read(j)`` returns scan ``j``'s sensor-frame points; ``poses`` holds the
    world-from-LiDAR pose of every frame. The scans of frames
    ``start - W < j < start`` are fed first (not yielded), so the map of every
    frame is the same whatever ``start`` is. The update time is the CPU time
    of this thread (filter, place, add, drop, crop), reading excluded.
    """
    lm = LocalMap(settings.window, settings.voxel, settings.radius,
                  input_filter(settings.input_filter))
    for j in range(max(0, start - settings.window + 1), stop):
        points = read(j)
        t0 = time.thread_time()
        lm.update(j, points, poses[j])
        seconds = time.thread_time() - t0
        if j >= start:
            yield lm.frame(j, poses[j]), seconds
