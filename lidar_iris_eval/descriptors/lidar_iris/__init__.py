"""LiDAR Iris (Wang et al., IROS 2020): iris image, log-Gabor binary maps, masked Hamming distance.

The descriptor lives in :mod:`.descriptor`; the numba kernels beside it in :mod:`.kernels`.
"""

from lidar_iris_eval.descriptors.lidar_iris.descriptor import (
    LidarIris,
    LidarIrisParams,
    align,
    band_spectra,
    binary_features,
    compare_blocks,
    describe_image,
    descriptor_dtype,
    distance_curve,
    estimated_shift,
    iris_image,
    log_gabor_response,
    pack_features,
    row_spectra,
    unpack_features,
)

__all__ = [
    "LidarIris",
    "LidarIrisParams",
    "align",
    "band_spectra",
    "binary_features",
    "compare_blocks",
    "describe_image",
    "descriptor_dtype",
    "distance_curve",
    "estimated_shift",
    "iris_image",
    "log_gabor_response",
    "pack_features",
    "row_spectra",
    "unpack_features",
]
