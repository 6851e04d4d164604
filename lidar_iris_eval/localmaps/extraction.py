"""The extraction of methods that declare the ``local_map`` input (called by extract.py).

For the scans ``[a, b)`` of a chunk, the local map of each frame is built by
:func:`lidar_iris_eval.localmaps.local_maps` (the scans of the ``W - 1`` frames
before ``a`` are fed first, so a chunk's maps equal those of a run from frame
0) and handed to ``descriptor.compute``. ``extract_s`` of a frame is the CPU
time of its local-map update plus ``compute``; ``read_s`` the wall time spent
reading the scans it added (the first frame of a chunk also reads the window
before it). A descriptor that keeps state from frame to frame (ESM's segment
tracking) is told where each chunk starts (``begin_local_maps(a)``, when it
has one), so a chunk computes the same features in any process and order.

The poses come from :func:`lidar_iris_eval.localmaps.odometry.estimate_odometry`
(``--odometry``): with ``kiss-icp`` they are estimated from the scans alone,
once per process for the whole sequence, and each frame's feature set gets
``odometry_s`` (shape ``(1,)``), the CPU time KISS-ICP spent on its scan
(0 with ``gt``); it is not part of ``extract_s``.
"""

from __future__ import annotations

import functools
import hashlib
import time
from pathlib import Path

import numpy as np


def describe_local_maps(seq, descriptor, a: int, b: int, extract_s: np.ndarray,
                        read_s: np.ndarray, tick, warm_up) -> list:
    """Feature sets of frames ``[a, b)``; fills ``extract_s`` and ``read_s`` in place."""
    from lidar_iris_eval.localmaps import local_maps
    from lidar_iris_eval.localmaps.odometry import estimate_odometry

    settings = descriptor.local_map_settings()
    odometry = estimate_odometry(seq, settings.odometry, progress=tick is not None)
    poses = odometry.poses
    reading = [0.0]

    def read(j: int) -> np.ndarray:
        t0 = time.perf_counter()
        points = seq[j]
        reading[0] += time.perf_counter() - t0
        return points

    begin = getattr(descriptor, "begin_local_maps", None)
    if begin is not None:
        begin(a)
    outputs = []
    for k, (frame, update_s) in enumerate(local_maps(read, poses, settings, a, b)):
        read_s[k], reading[0] = reading[0], 0.0
        warm_up(descriptor, frame, True)
        c1 = time.thread_time()
        out = dict(descriptor.compute(frame))
        extract_s[k] = time.thread_time() - c1 + update_s
        out["odometry_s"] = np.array([odometry.seconds[frame.frame]], dtype=np.float64)
        outputs.append(out)
        if tick is not None:
            tick(1)
    return outputs


@functools.cache
def local_map_code_hash() -> str:
    """SHA-256 (16 hex) of the localmaps package (this module included): part of the cache key."""
    files = sorted(Path(__file__).resolve().parent.rglob("*.py"))
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
