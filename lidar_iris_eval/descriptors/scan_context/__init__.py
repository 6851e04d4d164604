"""Scan Context (Kim and Kim, IROS 2018; the authors' C++ as the reference preset).

The descriptor lives in :mod:`.descriptor`; the FFT-domain shift kernels in :mod:`.kernels`.
"""

from lidar_iris_eval.descriptors.scan_context.descriptor import (
    DIVISORS,
    RING_KEYS,
    SEARCHES,
    ScanContext,
    ScanContextMatcher,
    ScanContextParams,
    polar_angle_deg,
    polar_context,
    ring_key,
    sector_key,
    shift_to_yaw,
    voxel_downsample,
    yaw_to_shift,
)

__all__ = [
    "DIVISORS",
    "RING_KEYS",
    "SEARCHES",
    "ScanContext",
    "ScanContextMatcher",
    "ScanContextParams",
    "polar_angle_deg",
    "polar_context",
    "ring_key",
    "sector_key",
    "shift_to_yaw",
    "voxel_downsample",
    "yaw_to_shift",
]
