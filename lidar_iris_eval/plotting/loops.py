"""Figures of scored loop files (issue 35): loops on the trajectory, and the pose-graph APE.

* :func:`loops_figure`: one panel per ``--loops`` file: the path (grey), the
  ground-truth revisit stretches (yellow) and each loop drawn as a segment
  between its two poses, green when true, red when false, grey dashed when the
  convention does not score it (not a query, inside the exclusion window).
* :func:`posegraph_figure`: the APE RMSE of the graph optimised with no
  loops, the true loops only and all loops, and the error each false loop
  adds on its own (``posegraph.csv``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from lidar_iris_eval.plotting import style
from lidar_iris_eval.plotting.trajectory import AXIS_NAMES

TRUE_COLOR = "#2E7D32"
FALSE_COLOR = "#C62828"
OTHER_COLOR = "0.55"


def _status(table: pd.DataFrame) -> np.ndarray:
    return table["status"].astype(str).str.lower().to_numpy()


def loops_figure(positions: np.ndarray, axes_idx: tuple[int, int], revisit: np.ndarray,
                 tables: Mapping[str, pd.DataFrame], frame: str = "") -> Figure:
    """Each file's loops as segments on the path (``tables``: ``loops.csv`` per file)."""
    xy = np.asarray(positions, dtype=np.float64)[:, list(axes_idx)]
    names = list(tables)
    n = max(len(names), 1)
    cols = 1 if n == 1 else 2
    rows = math.ceil(n / cols)
    band = np.where(np.asarray(revisit, dtype=bool)[:, None], xy, np.nan)
    with style.context():
        fig = style.new_figure(3.4 * cols, 3.0 * rows + 0.4)
        axes = fig.subplots(rows, cols, squeeze=False)
        for k, ax in enumerate(axes.flat):
            if k >= len(names):
                ax.set_axis_off()
                continue
            name, table = names[k], tables[names[k]]
            ax.plot(xy[:, 0], xy[:, 1], color="0.7", linewidth=0.7, gid="path")
            ax.plot(band[:, 0], band[:, 1], color="#F0B400", linewidth=2.4, alpha=0.5,
                    solid_capstyle="round", gid="revisits", zorder=1.5)
            status = _status(table)
            q = table["query"].to_numpy(dtype=np.int64)
            m = table["match"].to_numpy(dtype=np.int64)
            has = m >= 0
            for kind, color, style_, width, z in (
                    ("other", OTHER_COLOR, "--", 0.6, 2),
                    ("true", TRUE_COLOR, "-", 0.9, 3),
                    ("false", FALSE_COLOR, "-", 1.3, 4)):
                pick = has & ((status == kind) if kind != "other"
                              else ~np.isin(status, ("true", "false")))
                if not pick.any():
                    continue
                segments = np.stack([xy[q[pick]], xy[m[pick]]], axis=1)
                ax.add_collection(LineCollection(segments, colors=color, linestyles=style_,
                                                 linewidths=width, zorder=z,
                                                 gid=f"loops-{kind}:{name}"))
            n_true = int(np.count_nonzero(status == "true"))
            n_false = int(np.count_nonzero(status == "false"))
            ax.set_title(f"{name}\n{n_true} true · {n_false} false loops", fontsize=6, pad=2,
                         linespacing=1.1)
            ax.set_aspect("equal", adjustable="datalim")
            ax.tick_params(labelsize=6, length=2)
            where = f" ({frame})" if frame else ""
            ax.set_xlabel(f"{AXIS_NAMES[axes_idx[0]]} [m]{where}", fontsize=6)
            ax.set_ylabel(f"{AXIS_NAMES[axes_idx[1]]} [m]{where}", fontsize=6)
        handles = [Line2D([], [], color="0.7", linewidth=0.7, label="path"),
                   Line2D([], [], color="#F0B400", linewidth=2.4, alpha=0.5,
                          label="revisits (ground truth)"),
                   Line2D([], [], color=TRUE_COLOR, label="true loop"),
                   Line2D([], [], color=FALSE_COLOR, linewidth=1.3, label="false loop"),
                   Line2D([], [], color=OTHER_COLOR, linestyle="--", label="not scored")]
        fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=6,
                   handlelength=1.4, columnspacing=0.8)
    return fig


def posegraph_figure(tables: Mapping[str, pd.DataFrame]) -> Figure:
    """APE RMSE bars (none / true / all) and each false loop's added error, per file."""
    names = list(tables)
    with style.context():
        fig = style.new_figure(6.4, 2.3 * len(names) + 0.3)
        axes = fig.subplots(len(names), 2, squeeze=False)
        for row, name in enumerate(names):
            table = tables[name]
            graph = table["graph"].astype(str).to_numpy()
            ape = table["ape_rmse_m"].to_numpy(dtype=np.float64)
            main = [np.flatnonzero(graph == g)[0] for g in ("none", "true", "all")]
            ax = axes[row, 0]
            bars = ax.bar(["no loops", "true loops", "all loops"], ape[main],
                          color=["0.6", TRUE_COLOR, FALSE_COLOR], gid=f"ape:{name}")
            ax.bar_label(bars, fmt="%.3f", fontsize=6, padding=1)
            ax.set_ylabel("APE RMSE [m]", fontsize=6)
            ax.set_title(f"{name}: pose graph optimised with", fontsize=6, pad=2)
            ax.tick_params(labelsize=6, length=2)
            ax.margins(y=0.15)
            ax = axes[row, 1]
            single = np.flatnonzero(np.char.startswith(graph.astype(str), "true+"))
            if len(single):
                added = table["added_m"].to_numpy(dtype=np.float64)[single]
                labels = [f"loop {int(v)}" for v in table["loop"].to_numpy()[single]]
                if "query" in table.columns:
                    labels = [f"{int(a)}–{int(b)}" for a, b in
                              zip(table["query"].to_numpy()[single],
                                  table["match"].to_numpy()[single], strict=True)]
                bars = ax.bar(labels, added, color=FALSE_COLOR, gid=f"added:{name}")
                ax.bar_label(bars, fmt="%+.3f", fontsize=6, padding=1)
                ax.set_title("APE added by each false loop alone (vs true loops)",
                             fontsize=6, pad=2)
                ax.set_ylabel("added APE [m]", fontsize=6)
                ax.set_xlabel("false loop (query–match frame)", fontsize=6)
                ax.tick_params(axis="x", labelrotation=45 if len(labels) > 6 else 0)
                ax.margins(y=0.15)
            else:
                ax.text(0.5, 0.5, "no false loops", ha="center", va="center", fontsize=7,
                        transform=ax.transAxes)
                ax.set_axis_off()
            ax.tick_params(labelsize=6, length=2)
    return fig
