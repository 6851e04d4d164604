"""Local maps: the accumulated, cropped voxel map SegMap (and ESM) segments at every frame.

At frame ``i`` the local map holds the scans of frames ``i - W < j <= i``
(``W`` = the window, the evaluation's exclusion window E by default), each
passed through an input filter (:mod:`.filters`) in its sensor frame and
placed in the world frame by a pose source (:mod:`.odometry`), in a 0.1 m
voxel grid cropped to a 50 m cylinder around pose ``i`` (:mod:`.grid`).

This package is io level: it reads scans and poses, never descriptors or
evaluation code.
"""

from lidar_iris_eval.localmaps.filters import INPUT_FILTERS, InputFilter, input_filter
from lidar_iris_eval.localmaps.grid import LocalMap, LocalMapFrame, VoxelWindow
from lidar_iris_eval.localmaps.odometry import ODOMETRY_SOURCES, odometry_poses
from lidar_iris_eval.localmaps.settings import LocalMapSettings
from lidar_iris_eval.localmaps.stream import local_maps

__all__ = [
    "INPUT_FILTERS", "InputFilter", "input_filter", "LocalMap", "LocalMapFrame", "VoxelWindow",
    "ODOMETRY_SOURCES", "odometry_poses", "LocalMapSettings", "local_maps",
]
