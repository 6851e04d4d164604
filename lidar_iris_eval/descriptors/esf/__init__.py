"""ESF, the Ensemble of Shape Functions (Wohlkinger and Vincze, 2011), as PCL computes it.
"""

from lidar_iris_eval.descriptors.esf.descriptor import (
    BINS,
    ESF,
    GRID,
    HALF,
    MIN_HERON,
    WEIGHTS,
    ESFParams,
    classify_lines,
    classify_triangles,
    esf_histogram,
    l1_rows,
    normalise,
    occupancy,
    pcl_round,
    sample_triangles,
    trace_lines,
    voxel_coords,
)

__all__ = [
    "BINS",
    "ESF",
    "ESFParams",
    "GRID",
    "HALF",
    "MIN_HERON",
    "WEIGHTS",
    "classify_lines",
    "classify_triangles",
    "esf_histogram",
    "l1_rows",
    "normalise",
    "occupancy",
    "pcl_round",
    "sample_triangles",
    "trace_lines",
    "voxel_coords",
]
