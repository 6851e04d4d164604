"""M2DP (He et al., IROS 2016): projection signatures and their first singular vectors.
"""

from lidar_iris_eval.descriptors.m2dp.descriptor import (
    M2DP,
    M2DPParams,
    descriptor_from_signature,
    l2_rows,
    pca_align,
    projection_planes,
    signature_matrix,
)

__all__ = [
    "M2DP",
    "M2DPParams",
    "descriptor_from_signature",
    "l2_rows",
    "pca_align",
    "projection_planes",
    "signature_matrix",
]
