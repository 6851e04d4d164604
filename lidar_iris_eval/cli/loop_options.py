"""``liris eval`` options of issue 23 (loop poses), kept out of eval_cmd.

:func:`loop_pose_options` adds ``--refine``, ``--gt-pose``, ``--rr-thresholds``,
``--min-inlier-ratio``, ``--max-rmse`` and ``--odometry``; the command body
gets them back as one :class:`~lidar_iris_eval.evaluation.loop_poses.LoopPoseSettings`
(``loop_settings``), the local maps' pose source (``odometry``: gt or kiss-icp)
and a pose file or None (``odometry_path``).
"""

from __future__ import annotations

import functools
from pathlib import Path

import click
import numpy as np

from lidar_iris_eval.errors import LirisError, register_flags

register_flags({"refine": "--refine", "gt_pose": "--gt-pose", "rr_thresholds": "--rr-thresholds",
                "min_inlier_ratio": "--min-inlier-ratio", "max_rmse_m": "--max-rmse",
                "seeds": "--seeds"})


def parse_pair(text: str) -> tuple[float, float]:
    """``"2,5"`` -> ``(2.0, 5.0)`` (metres, degrees)."""
    try:
        a, b = (float(v) for v in str(text).split(","))
    except ValueError:
        raise LirisError(f"--rr-thresholds {text}", "expected METRES,DEGREES, e.g. 2,5") from None
    return a, b


def read_odometry(path: Path, sequence) -> np.ndarray:
    """An odometry pose file (KITTI or TUM rows, LiDAR frame), one pose per frame."""
    from lidar_iris_eval.io.poses import read_pose_file

    _, poses = read_pose_file(path)
    if len(poses) != len(sequence):
        raise LirisError(path, f"{len(poses)} odometry poses for {len(sequence)} scans; "
                               "give one per scan")
    return poses


def parse_odometry(text: str) -> tuple[str, Path | None]:
    """``--odometry`` to ``(pose source of local maps, pose file or None)``.

    ``gt`` / ``kiss-icp`` name the source (kiss-icp checked to be installed);
    anything else must be an existing pose file, which sets only the .g2o
    vertices (its local-map source stays ``gt``; :func:`check_odometry_file`
    refuses it for methods that read local maps).
    """
    from lidar_iris_eval.localmaps.odometry import ODOMETRY_SOURCES, check_odometry

    if text in ODOMETRY_SOURCES:
        return check_odometry(text), None
    path = Path(text)
    if not path.is_file():
        raise LirisError(f"--odometry {text}", f"neither {' nor '.join(ODOMETRY_SOURCES)} "
                                               "nor an existing pose file")
    return "gt", path


def check_odometry_file(path: Path | None, descriptors) -> None:
    """A pose file as ``--odometry`` with a method that reads local maps: one error line."""
    if path is None:
        return
    from lidar_iris_eval.descriptors.base import reads_local_maps

    reads = [d.name for d in descriptors if reads_local_maps(d)]
    if reads:
        raise LirisError(f"--odometry {path}", f"{', '.join(reads)} build local maps from "
                         "gt or kiss-icp poses; a pose file sets only the .g2o vertices of "
                         "methods without local maps")


def loop_pose_options(func):
    """The issue 23 options (see module doc); apply below ``@click.command``."""

    @click.option("--refine", type=click.Choice(["gicp", "icp"]), default=None,
                  help="Refine every protocol 1 match by registering the two scans from the "
                       "method's pose (yaw-only: that rotation, zero translation); needs the "
                       "'registration' extra. matches.csv keeps the method's pose.")
    @click.option("--gt-pose", type=click.Choice(["dataset", "refined"]), default="dataset",
                  show_default=True,
                  help="refined: also report pose errors against the ground truth of each true "
                       "match refined by registration (how much error is the dataset's).")
    @click.option("--rr-thresholds", default="2,5", show_default=True, metavar="M,DEG",
                  help="Registration recall: share of true matches with RTE < M and RRE < DEG.")
    @click.option("--min-inlier-ratio", type=float, default=None,
                  help="With --refine: reject a match whose registration inlier ratio is lower.")
    @click.option("--max-rmse", "max_rmse_m", type=float, default=None,
                  help="With --refine: reject a match whose registration RMSE (m) is higher.")
    @click.option("--odometry", "odometry_text", default="gt", show_default=True,
                  metavar="gt|kiss-icp|FILE",
                  help="The run's odometry. gt (the sequence's poses, an oracle) or kiss-icp "
                       "(estimated from the scans alone; the 'odometry' extra): the pose "
                       "source of the local maps of methods that read them (esm; others "
                       "ignore it) and the .g2o vertices. FILE (KITTI/TUM rows, LiDAR frame): "
                       ".g2o vertices only, for methods without local maps.")
    @click.option("--seeds", "seeds_text", default=None, metavar="S1,S2,...",
                  help="Rerun the stochastic stages (RANSAC, PROSAC, ESF's sampling) once per "
                       "seed; metrics.json, liris show and the PR figure report mean and range.")
    @functools.wraps(func)
    def wrapper(*args, refine, gt_pose, rr_thresholds, min_inlier_ratio, max_rmse_m,
                odometry_text, seeds_text, **kwargs):
        from lidar_iris_eval.evaluation.loop_poses import LoopPoseSettings
        from lidar_iris_eval.evaluation.seeds import parse_seeds

        rte, rre = parse_pair(rr_thresholds)
        kwargs["loop_settings"] = LoopPoseSettings(
            refine=refine, gt_pose=gt_pose, rr_rte_m=rte, rr_rre_deg=rre,
            min_inlier_ratio=min_inlier_ratio, max_rmse_m=max_rmse_m)
        if kwargs["loop_settings"].registers:
            from lidar_iris_eval.matching.registration import check_available

            check_available()
        kwargs["odometry"], kwargs["odometry_path"] = parse_odometry(odometry_text)
        kwargs["seeds"] = parse_seeds(seeds_text) if seeds_text is not None else None
        return func(*args, **kwargs)

    return wrapper
