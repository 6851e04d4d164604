"""ESM (Tinchev et al., RA-L 2019): learned segment descriptors matched with PROSAC."""

from lidar_iris_eval.descriptors.esm.descriptor import ESM, ESMDatabase, ESMParams
from lidar_iris_eval.descriptors.esm.segmentation import SegmentParams, Segments, segment_scan

__all__ = ["ESM", "ESMDatabase", "ESMParams", "SegmentParams", "Segments", "segment_scan"]
