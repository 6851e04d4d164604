"""OverlapTransformer (Ma et al., RA-L 2022): range image, transformer, NetVLAD; NumPy inference."""

from lidar_iris_eval.descriptors.overlap_transformer.descriptor import (
    OverlapTransformer,
    OverlapTransformerParams,
)

__all__ = ["OverlapTransformer", "OverlapTransformerParams"]
