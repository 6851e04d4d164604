"""The Recall@N figure: Recall@1..25 of every method of a run, one line each.

Drawn for cross-session runs and for within-sequence runs evaluated with
``--ranking``; undefined values (a two-stage method's Recall@N beyond its K
candidates) are gaps, never 0. Each line is the Line2D with gid
``"recall:<method>"``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from lidar_iris_eval.plotting import style

RECALL_SIZE = (style.COLUMN_WIDTH, 2.6)


def recall_curves(rows: Sequence[Mapping]) -> dict[str, np.ndarray]:
    """``{method: (25,) Recall@N}`` (NaN where undefined) from metrics rows with ``recall_at_n``."""
    out = {}
    for row in rows:
        values = row.get("recall_at_n")
        if not values:
            continue
        out[row["descriptor"]] = np.array([np.nan if v is None else float(v) for v in values])
    return out


def recall_figure(curves: Mapping[str, np.ndarray], title: str = "") -> Figure:
    """Recall@N against N for each method (percent)."""
    with style.context():
        fig = style.new_figure(*RECALL_SIZE)
        ax = fig.add_subplot()
        for name in style.in_method_order(curves):
            values = curves[name]
            n = np.arange(1, len(values) + 1)
            ax.plot(n, 100 * values, color=style.method_color(name), marker="o",
                    markersize=2.0, linewidth=1.0, label=style.method_label(name),
                    gid=f"recall:{name}")
        ax.set_xlim(0.5, 25.5)
        ax.set_ylim(0, 102)
        ax.set_xlabel("N (top-N candidates)")
        ax.set_ylabel("Recall@N [%]")
        ax.grid(True, linewidth=0.3, alpha=0.5)
        if title:
            ax.set_title(title)
        ax.legend(fontsize=6, loc="lower right")
    return fig


def build_recall(run) -> Figure | None:
    """The Recall@N figure of a run, or None when no row has ranking metrics."""
    curves = recall_curves(run.rows)
    if not curves:
        return None
    cross = any(r.get("protocol") == "cross-session" for r in run.rows)
    return recall_figure(curves, "cross-session Recall@N" if cross else
                         "Recall@N (protocol 1 queries)")
