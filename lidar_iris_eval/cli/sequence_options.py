"""Click options for the sequence readers (scan folders and ROS bags).

Add ``@sequence_options`` to a command that opens a sequence; the command then
receives one keyword, ``reader_options``, a dict to pass on as
``open_sequence(path, poses=..., calib=..., **reader_options)``. Only options
the user actually gave are in it, so a KITTI layout (which takes none) still
opens, and an option that does not fit the format is reported by the reader.
"""

from __future__ import annotations

import functools

import click

#: click parameter name -> open_sequence keyword
_KEYWORDS = {
    "pose_format": "pose_format",
    "lidar_frame_poses": "lidar_frame",
    "times_path": "times",
    "topic": "topic",
    "pose_topic": "pose_topic",
    "frames": "frames",
    "every": "every",
    "min_distance": "min_distance",
    "tolerance": "tolerance",
    "stamps": "stamps",
    "dataset": "dataset",
    "scene": "scene",
}


def sequence_options(func):
    """Reader options: dataset, pose format/frame, bag topics, time matching, frame selection."""

    @click.option("--dataset", default=None, metavar="NAME",
                  help="Read SEQUENCE as this dataset (liris datasets lists them); "
                       "default: detected from the folder.")
    @click.option("--scene", default=None, metavar="NAME",
                  help="nuScenes: the scene to read (e.g. scene-0061).")
    @click.option("--pose-format", type=click.Choice(["auto", "kitti", "tum"]), default=None,
                  help="Pose file format (default: detected from the first line).")
    @click.option("--lidar-frame-poses", is_flag=True, default=None,
                  help="Scan folders: the poses are LiDAR poses (no calib.txt Tr applied).")
    @click.option("--times", "times_path", type=click.Path(),
                  help="Scan folders: one scan time (s) per line, instead of times.txt.")
    @click.option("--topic", help="ROS bags: the sensor_msgs/PointCloud2 topic.")
    @click.option("--pose-topic",
                  help="ROS bags: the nav_msgs/Odometry or geometry_msgs/PoseStamped topic.")
    @click.option("--stamps", type=click.Choice(["header", "bag"]), default=None,
                  help="ROS bags: time scans by header stamp (default) or recording time.")
    @click.option("--tolerance", type=float, default=None,
                  help="Seconds; scans with no pose this close in time are dropped [0.1].")
    @click.option("--frames", default=None, metavar="START:STOP[:STEP]",
                  help="A frame RANGE to keep (0-based, STOP excluded), e.g. 0:200 or 0:200:2; "
                       "any format. (In simulate and bench --frames is a count.)")
    @click.option("--every", type=int, default=None,
                  help="Keep every N-th scan (after --frames and --min-distance); any format.")
    @click.option("--min-distance", type=float, default=None,
                  help="Keep a scan only after the sensor moved this many metres; any format.")
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        kwargs["reader_options"] = {
            **kwargs.get("reader_options", {}),
            **reader_options({name: kwargs.pop(name) for name in _KEYWORDS}),
        }
        return func(*args, **kwargs)

    return wrapper


def reader_options(values: dict) -> dict:
    """Keep the options that were given, renamed to ``open_sequence`` keywords."""
    return {_KEYWORDS[name]: value for name, value in values.items() if value is not None}


def pose_file_options(func):
    """``--poses`` and ``--calib`` overriding the files found beside the scans.

    They are added to ``reader_options`` (so use this below ``@sequence_options``).
    """

    @click.option("--poses", "poses_path", type=click.Path(),
                  help="Pose file (KITTI 3x4 or TUM) instead of the one found with the scans.")
    @click.option("--calib", "calib_path", type=click.Path(),
                  help="KITTI calib.txt (Tr) instead of the one found with the scans.")
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        given = {"poses": kwargs.pop("poses_path"), "calib": kwargs.pop("calib_path")}
        kwargs["reader_options"] = {
            **kwargs.get("reader_options", {}),
            **{k: v for k, v in given.items() if v is not None},
        }
        return func(*args, **kwargs)

    return wrapper
