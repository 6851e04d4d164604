"""Publication-quality figures from ``liris eval`` results directories.

``plot_run(run_dir, out_dir, fmt)`` writes the paper's figures for one run
(PR curves per protocol, affinity matrices, trajectory with detections,
timing, LiDAR Iris image/features/alignment); ``plot_compare(run_dirs, …)``
overlays the PR curves of several runs. Each figure also has a ``build_*``
function returning the :class:`~matplotlib.figure.Figure` for inspection.
Runs are read by :mod:`lidar_iris_eval.runs.reader` (re-exported here as
``load_run``), the reader ``liris show``, ``compare`` and ``report`` use too.
"""

from lidar_iris_eval.plotting.figures import (
    FILE_STEMS,
    build_affinity,
    build_iris,
    build_pr,
    build_pr_compare,
    build_timing,
    build_trajectory,
    figure_path,
    plot_compare,
    plot_run,
)
from lidar_iris_eval.runs.reader import Run, load_run

__all__ = [
    "FILE_STEMS",
    "Run",
    "build_affinity",
    "build_iris",
    "build_pr",
    "build_pr_compare",
    "build_timing",
    "build_trajectory",
    "figure_path",
    "load_run",
    "plot_compare",
    "plot_run",
]
