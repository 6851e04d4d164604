"""The path in the ground plane with revisits and detections (the paper's Fig. 9).

One panel per method. Grey is the path; a thick band marks the revisit
queries (ground truth); markers show protocol 1 at the method's max-F1
threshold τ: a query is *accepted* when its best match has distance ≤ τ, a
true positive when that match is within the radius, and otherwise a *wrong
match* when the query is a revisit (a loop existed, the method closed it to
the wrong place) or a *false alarm* when it is not. A revisit query whose
best match was rejected is *missed*. Every revisit query is exactly one of
true positive, wrong match or missed, and each panel's title counts them
against the number of revisits, so TP + wrong + missed = revisits.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from lidar_iris_eval.plotting import style

PANEL_HEIGHT = 1.85
SINGLE_SIZE = (style.COLUMN_WIDTH, 3.0)
LEGEND_HEIGHT = 0.42
AXIS_NAMES = "xyz"

#: the protocol 1 outcomes, as trajectory.png and the HTML report both name and count them
OUTCOME_LABELS = {
    "tp": "true positive",
    "wrong": "wrong match (revisit)",
    "missed": "missed revisit",
    "false_alarm": "false alarm (no revisit)",
}


@dataclass(frozen=True)
class Outcomes:
    """Query indices by protocol 1 outcome at one threshold (see the module docstring)."""

    tp: np.ndarray
    wrong: np.ndarray  # accepted, wrong place, on a revisit query
    false_alarm: np.ndarray  # accepted, on a query with no revisit
    missed: np.ndarray
    threshold: float
    n_revisits: int = -1

    @property
    def fp(self) -> np.ndarray:
        """Every accepted wrong match (wrong matches and false alarms)."""
        return np.sort(np.concatenate([self.wrong, self.false_alarm]))


def outcome_counts(result: Outcomes) -> dict[str, int]:
    """Queries per outcome (:data:`OUTCOME_LABELS` order); TP + wrong + missed = revisits."""
    return {kind: int(len(getattr(result, kind))) for kind in OUTCOME_LABELS}


def as_bool(column: pd.Series) -> np.ndarray:
    """CSV booleans written as True/False, true/false or 1/0."""
    if column.dtype == bool:
        return column.to_numpy()
    text = column.astype(str).str.strip().str.lower()
    return text.isin(("true", "1", "1.0", "yes")).to_numpy()


def outcomes(matches: pd.DataFrame, threshold: float) -> Outcomes:
    """Classify protocol 1 queries at threshold τ (accepted when distance ≤ τ)."""
    query = matches["query"].to_numpy(dtype=np.int64)
    dist = matches["distance"].to_numpy(dtype=np.float64)
    accepted = np.isfinite(dist) & (dist <= threshold)
    is_true = as_bool(matches["is_true"])
    revisit = as_bool(matches["is_revisit"])
    return Outcomes(
        tp=query[accepted & is_true],
        wrong=query[accepted & ~is_true & revisit],
        false_alarm=query[accepted & ~is_true & ~revisit],
        missed=query[revisit & ~accepted],
        threshold=float(threshold),
        n_revisits=int(np.count_nonzero(revisit)),
    )


def trajectory_figure_size(n_methods: int) -> tuple[float, float]:
    if n_methods <= 1:
        return SINGLE_SIZE
    rows = math.ceil(n_methods / 2)
    return style.COLUMN_WIDTH, round(rows * PANEL_HEIGHT + LEGEND_HEIGHT, 2)


def trajectory_figure(positions: np.ndarray, axes_idx: tuple[int, int], revisit: np.ndarray,
                      results: Mapping[str, Outcomes], frame: str = "") -> Figure:
    """Draw the path of ``positions`` (N, 3) on the plane ``axes_idx``.

    ``revisit`` is the (N,) ground-truth revisit mask; ``results`` maps a
    method name to its :class:`Outcomes` (empty mapping: path and revisits only).
    """
    xy = np.asarray(positions, dtype=np.float64)[:, list(axes_idx)]
    names = list(results) or [""]
    n = len(names)
    cols = 1 if n == 1 else 2
    rows = math.ceil(n / cols)
    band = np.where(np.asarray(revisit, dtype=bool)[:, None], xy, np.nan)
    # true positives are the common case: small on long runs so the rare misses and
    # false positives, drawn on top of them, stay visible
    tp_size = 2.2 if len(xy) <= 500 else 1.2
    marker = {"tp": ("o", tp_size), "wrong": ("^", 2.8), "false_alarm": ("x", 3.0),
              "missed": ("o", 2.8)}
    with style.context():
        fig = style.new_figure(*trajectory_figure_size(n))
        axes = fig.subplots(rows, cols, squeeze=False)
        for k, ax in enumerate(axes.flat):
            if k >= n:
                ax.set_axis_off()
                continue
            name = names[k]
            ax.plot(xy[:, 0], xy[:, 1], color="0.65", linewidth=0.7, gid="path")
            ax.plot(band[:, 0], band[:, 1], color="#F0B400", linewidth=2.6, alpha=0.55,
                    solid_capstyle="round", gid="revisits", zorder=1.5)
            ax.plot(xy[:1, 0], xy[:1, 1], marker="s", color="0.2", markersize=3,
                    linestyle="none", gid="start")
            if name:
                result = results[name]
                for kind in ("tp", "missed", "wrong", "false_alarm"):
                    idx = getattr(result, kind)
                    shape, size = marker[kind]
                    filled = kind == "tp"
                    ax.plot(xy[idx, 0], xy[idx, 1], linestyle="none", marker=shape,
                            markersize=size, markeredgewidth=0.6,
                            color=style.OUTCOME_COLORS[kind],
                            markerfacecolor=style.OUTCOME_COLORS[kind] if filled else "none",
                            gid=f"{kind}:{name}", zorder=3)
                revisits = (f"of {result.n_revisits} revisits · " if result.n_revisits >= 0
                            else "")
                ax.set_title(f"{style.method_label(name)}\nTP {len(result.tp)} · wrong "
                             f"{len(result.wrong)} · missed {len(result.missed)}\n{revisits}"
                             f"false alarms {len(result.false_alarm)}", fontsize=6,
                             pad=2, linespacing=1.1)
            ax.set_aspect("equal", adjustable="datalim")
            ax.tick_params(labelsize=6, length=2)
            row, col = divmod(k, cols)
            if col == 0:
                ax.set_ylabel(_axis_label(axes_idx[1], frame))
            if row == rows - 1 or k + cols >= n:
                ax.set_xlabel(_axis_label(axes_idx[0], frame))
        fig.legend(handles=_legend_handles(bool(results)), loc="outside lower center",
                   ncols=3, fontsize=6, handlelength=1.2, columnspacing=0.8)
    return fig


def _axis_label(axis: int, frame: str) -> str:
    where = f" ({frame})" if frame else ""
    return f"{AXIS_NAMES[axis]} [m]{where}"


def _legend_handles(with_detections: bool) -> list[Line2D]:
    handles = [
        Line2D([], [], color="0.65", linewidth=0.7, label="path"),
        Line2D([], [], color="#F0B400", linewidth=2.6, alpha=0.55, label="revisit"),
        Line2D([], [], color="0.2", marker="s", markersize=3, linestyle="none", label="start"),
    ]
    if with_detections:
        c = style.OUTCOME_COLORS
        handles += [
            Line2D([], [], color=c["tp"], marker="o", markersize=2.5, linestyle="none",
                   label="true positive"),
            Line2D([], [], color=c["wrong"], marker="^", markerfacecolor="none",
                   markersize=2.8, linestyle="none", label="wrong match (revisit)"),
            Line2D([], [], color=c["missed"], marker="o", markerfacecolor="none",
                   markersize=2.5, linestyle="none", label="missed revisit"),
            Line2D([], [], color=c["false_alarm"], marker="x", markersize=3, linestyle="none",
                   label="false alarm (no revisit)"),
        ]
    return handles
