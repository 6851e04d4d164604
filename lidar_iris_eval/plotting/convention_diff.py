"""The trajectory with the revisit queries two conventions disagree on (``liris gt --diff``)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from lidar_iris_eval.plotting import style

#: colours of "only under A" and "only under B" (colour-blind safe, as the outcomes)
ONLY_COLORS = ("#D55E00", "#0072B2")


def convention_diff_figure(xy: np.ndarray, revisit_both: np.ndarray, only_a: np.ndarray,
                           only_b: np.ndarray, names: tuple[str, str],
                           axis_labels: tuple[str, str]) -> Figure:
    """Path in the ground plane; queries that only A or only B counts as revisits marked.

    Parameters
    ----------
    xy : ``(N, 2)`` ground-plane coordinates of the path.
    revisit_both : ``(N,)`` bool, revisit queries under both conventions (a faint band).
    only_a, only_b : indices of the revisit queries only A / only B has.
    names : the two convention names.
    axis_labels : x and y axis labels.
    """
    xy = np.asarray(xy, dtype=np.float64)
    band = np.where(np.asarray(revisit_both, dtype=bool)[:, None], xy, np.nan)
    with style.context():
        fig = style.new_figure(style.COLUMN_WIDTH, 3.4)
        ax = fig.subplots()
        ax.plot(xy[:, 0], xy[:, 1], color="0.65", linewidth=0.7, gid="path")
        ax.plot(band[:, 0], band[:, 1], color="#F0B400", linewidth=2.4, alpha=0.45,
                solid_capstyle="round", gid="revisits-both", label="revisit under both")
        ax.plot(xy[:1, 0], xy[:1, 1], marker="s", color="0.2", markersize=3,
                linestyle="none", gid="start", label="start")
        for idx, name, color, shape in ((only_a, names[0], ONLY_COLORS[0], "o"),
                                        (only_b, names[1], ONLY_COLORS[1], "x")):
            idx = np.asarray(idx, dtype=np.int64)
            ax.plot(xy[idx, 0], xy[idx, 1], linestyle="none", marker=shape, markersize=3.2,
                    markeredgewidth=0.8, color=color,
                    markerfacecolor="none", gid=f"only:{name}", zorder=3,
                    label=f"revisit only under {name} ({len(idx)})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=6, length=2)
        ax.set_xlabel(axis_labels[0])
        ax.set_ylabel(axis_labels[1])
        ax.set_title(f"revisit queries: {names[0]} vs {names[1]}", fontsize=7, pad=2)
        fig.legend(loc="outside lower center", ncols=2, fontsize=6, handlelength=1.2,
                   columnspacing=0.8)
    return fig


def plot_convention_diff(diff, path) -> str:
    """Write the figure of a :class:`~lidar_iris_eval.evaluation.explain.ConventionDiff`.

    The path is drawn in convention A's pose frame (its ground plane). Returns the path.
    """
    from lidar_iris_eval.evaluation.ground_truth import ground_plane_axes

    frame = diff.a.conv.pose_frame
    axes = ground_plane_axes(frame)
    xy = diff.a.traj.positions(frame)[:, list(axes)]
    both = diff.a.revisit & diff.b.revisit
    labels = tuple(f"{'xyz'[k]} [m] ({frame})" for k in axes)
    fig = convention_diff_figure(xy, both, diff.queries_only_a, diff.queries_only_b,
                                 (diff.a.conv.name, diff.b.conv.name), labels)
    return str(style.save(fig, path))
