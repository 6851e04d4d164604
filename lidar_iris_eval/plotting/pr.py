"""Precision–recall curves, all methods overlaid (the paper's Fig. 8 and 10).

Each curve is drawn from ``pr.csv`` as written (the exact curve, one point per
threshold); only curves with more points than a PNG can show (protocol 2 on
KITTI has millions) are thinned, by arc length, so every visible corner stays.
The maximum-F1 point is marked, and the legend carries AP and F1max.

The legend sits below the axes, never on the data. When a curve reaches a
recall of 0.9, a second panel zooms on recall ≥ 0.9, where the strong methods
(LiDAR Iris, Scan Context) differ and the full panel shows one vertical line.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from lidar_iris_eval.plotting import style

PR_SIZE = (style.COLUMN_WIDTH, 2.6)
#: with the zoom panel: two panels side by side, a two-column figure
PR_ZOOM_SIZE = (2 * style.COLUMN_WIDTH, 2.6)
#: the zoom panel shows recall from here to 1 (when any curve reaches it)
ZOOM_RECALL = 0.9
#: above this many points a curve is thinned for display
MAX_PLOT_POINTS = 20_000
#: thinning step in (recall, precision) units: far below one pixel at 300 dpi
THIN_STEP = 1.0 / 4000

PROTOCOL_TITLES = {1: "Protocol 1: loop-closure detection", 2: "Protocol 2: all pairs"}


@dataclass(frozen=True)
class PRCurve:
    """One curve and how to draw it."""

    key: str  # identifies the curve (gid of its lines), e.g. "lidar-iris" or "run: lidar-iris"
    label: str
    color: str
    recall: np.ndarray
    precision: np.ndarray
    ap: float = math.nan
    f1_max: float = math.nan
    linestyle: str = "-"
    #: ``--seeds``: (recall grid, lowest, highest interpolated precision over the seeds)
    band: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def f1_scores(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """Pointwise F1 with 0 where precision and recall are both 0."""
    precision = np.asarray(precision, dtype=np.float64)
    recall = np.asarray(recall, dtype=np.float64)
    total = precision + recall
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(total > 0, 2 * precision * recall / total, 0.0)
    return np.nan_to_num(f1, nan=0.0)


def thin_indices(recall: np.ndarray, precision: np.ndarray, step: float = THIN_STEP,
                 keep: Sequence[int] = ()) -> np.ndarray:
    """Indices of a subset that draws the same polyline at screen resolution.

    Keeps the first point of every ``step`` of arc length in the unit
    (recall, precision) square, the last point, and the indices in ``keep``.
    """
    n = len(recall)
    if n <= 2:
        return np.arange(n)
    seg = np.hypot(np.diff(recall), np.diff(precision))
    arc = np.concatenate([[0.0], np.cumsum(np.nan_to_num(seg))])
    bins = np.floor(arc / step).astype(np.int64)
    first = np.flatnonzero(np.diff(bins, prepend=-1) != 0)
    return np.unique(np.concatenate([first, [n - 1], np.asarray(keep, dtype=np.int64)]))


def legend_label(name: str, ap: float, f1_max: float) -> str:
    parts = []
    if not math.isnan(ap):
        parts.append(f"AP {ap:.3f}")
    if not math.isnan(f1_max):
        parts.append(f"F1max {f1_max:.3f}")
    return f"{name} ({', '.join(parts)})" if parts else name


def pr_figure(curves: Sequence[PRCurve], title: str = "", legend_outside: bool = True,
              zoom: bool | None = None) -> Figure:
    """Overlay PR curves; mark each curve's maximum-F1 point.

    The curve of ``c`` is the Line2D with gid ``"pr:" + c.key`` and its
    max-F1 marker has gid ``"f1max:" + c.key``, so tests and callers can find
    the plotted data again. The zoom panel (``zoom=None``: when some curve
    reaches recall :data:`ZOOM_RECALL`) repeats them with gids prefixed
    ``"zoom:"``. The legend is drawn below the axes (``legend_outside``).
    """
    if zoom is None:
        zoom = any(np.nanmax(np.asarray(c.recall, dtype=np.float64), initial=0.0) >= ZOOM_RECALL
                   for c in curves)
    with style.context():
        fig = style.new_figure(*pr_figure_size(len(curves), legend_outside, zoom))
        axes = fig.subplots(1, 2, width_ratios=[1, 1]) if zoom else [fig.add_subplot()]
        main = axes[0]
        for curve in curves:
            recall = np.asarray(curve.recall, dtype=np.float64)
            precision = np.asarray(curve.precision, dtype=np.float64)
            f1 = f1_scores(precision, recall)
            best = int(np.argmax(f1)) if len(f1) else None
            shown = np.arange(len(recall))
            if len(recall) > MAX_PLOT_POINTS:
                shown = thin_indices(recall, precision, keep=[] if best is None else [best])
            for ax, prefix in zip(axes, ("", "zoom:"), strict=False):
                if curve.band is not None:  # the spread over seeds (issue 23)
                    grid, low, high = curve.band
                    ax.fill_between(grid, low, high, color=curve.color, alpha=0.25,
                                    linewidth=0, gid=f"{prefix}band:{curve.key}")
                ax.plot(recall[shown], precision[shown], color=curve.color,
                        linestyle=curve.linestyle, label=curve.label if not prefix else None,
                        gid=f"{prefix}pr:{curve.key}")
                if best is not None:
                    ax.plot([recall[best]], [precision[best]], marker="o", markersize=3.5,
                            markerfacecolor="white", markeredgecolor=curve.color,
                            markeredgewidth=1.0, linestyle="none",
                            gid=f"{prefix}f1max:{curve.key}", zorder=3)
        main.set_xlim(0, 1.02)
        main.set_ylim(0, 1.02)
        for ax in axes:
            ax.set_xlabel("Recall")
            ax.grid(True, linewidth=0.3, alpha=0.5)
        main.set_ylabel("Precision")
        if zoom:
            _zoom_panel(axes[1], main, curves)
        if title:
            if zoom:
                fig.suptitle(title)
            else:
                main.set_title(title)
        if curves:
            # one extra entry explains the marker instead of repeating it per curve
            handles, labels = main.get_legend_handles_labels()
            handles.append(Line2D([], [], marker="o", markersize=3.5, markerfacecolor="white",
                                  markeredgecolor="0.35", linestyle="none"))
            labels.append("max F1")
            if legend_outside:
                fig.legend(handles, labels, loc="outside lower center",
                           ncols=legend_columns(len(labels), zoom))
            else:
                main.legend(handles, labels, loc="lower left")
    return fig


def _zoom_panel(ax, main, curves: Sequence[PRCurve]) -> None:
    """Recall ≥ ZOOM_RECALL, precision down to the lowest point reached there."""
    low = 1.0
    for curve in curves:
        recall = np.asarray(curve.recall, dtype=np.float64)
        precision = np.asarray(curve.precision, dtype=np.float64)
        inside = recall >= ZOOM_RECALL
        if inside.any():
            low = min(low, float(np.nanmin(precision[inside])))
    bottom = max(0.0, low - 0.05 * max(1.0 - low, 0.02))
    ax.set_xlim(ZOOM_RECALL - 0.005, 1.005)
    ax.set_ylim(bottom, 1.0 + 0.02 * (1.0 - bottom) + 0.002)
    ax.set_title(f"zoom: recall ≥ {ZOOM_RECALL:g}", pad=2)
    # show on the full panel where the zoom is
    main.add_patch(Rectangle((ZOOM_RECALL, bottom), 1.0 - ZOOM_RECALL, 1.0 - bottom,
                             fill=False, linewidth=0.5, linestyle="--", edgecolor="0.4",
                             gid="zoom-region"))


def legend_columns(n_entries: int, zoom: bool) -> int:
    return min(n_entries, 3 if zoom else 2)


def pr_figure_size(n_curves: int, legend_outside: bool = True,
                   zoom: bool = False) -> tuple[float, float]:
    """Width and height (inches): fixed, plus the legend rows below the axes."""
    width, height = PR_ZOOM_SIZE if zoom else PR_SIZE
    if legend_outside:
        rows = math.ceil((n_curves + 1) / legend_columns(n_curves + 1, zoom))
        height += 0.13 * rows + 0.1
    return width, round(height, 2)


def run_curves(run, protocol: int, prefix: str = "", linestyle: str = "-") -> list[PRCurve]:
    """The PR curves of every descriptor of ``run`` for ``protocol``."""
    curves = []
    for name in style.in_method_order(run.descriptors(protocol)):
        table = run.pr(protocol, name)
        metric = run.row(protocol, name)
        recall = table["recall"].to_numpy(dtype=np.float64)
        precision = table["precision"].to_numpy(dtype=np.float64)
        ap = _number(metric.get("ap"))
        f1_max = _number(metric.get("f1_max"))
        if math.isnan(f1_max) and len(recall):
            f1_max = float(f1_scores(precision, recall).max())
        shown = f"{prefix}: {style.method_label(name)}" if prefix else style.method_label(name)
        band = seed_band(run.path / f"protocol{protocol}" / name)
        if band is not None:
            shown += f", band: {band[3]} seeds"
        elif protocol == 1:  # --convention-band: the spread over convention presets
            band = seed_band(run.path / "protocol1" / name, pattern="pr_convention-*.csv")
            if band is not None:
                shown += f", band: {band[3]} conventions"
        curves.append(PRCurve(
            key=f"{prefix}: {name}" if prefix else name,
            label=legend_label(shown, ap, f1_max),
            color=style.method_color(name),
            recall=recall,
            precision=precision,
            ap=ap,
            f1_max=f1_max,
            linestyle=linestyle,
            band=None if band is None else band[:3],
        ))
    return curves


def interpolated_precision(recall: np.ndarray, precision: np.ndarray,
                           grid: np.ndarray) -> np.ndarray:
    """The highest precision at recall >= each grid value (NaN beyond the curve's reach)."""
    recall = np.asarray(recall, dtype=np.float64)
    precision = np.asarray(precision, dtype=np.float64)
    order = np.argsort(recall)
    r, p = recall[order], precision[order]
    envelope = np.maximum.accumulate(np.nan_to_num(p, nan=0.0)[::-1])[::-1]
    at = np.searchsorted(r, grid, side="left")
    out = np.full(len(grid), np.nan)
    inside = at < len(r)
    out[inside] = envelope[at[inside]]
    return out


def seed_band(folder, points: int = 201, pattern: str = "pr_seed*.csv"):
    """``(grid, low, high, n_seeds)`` from ``pr_seed*.csv`` in ``folder`` (``--seeds``), or
    None with fewer than two seeds. ``pattern="pr_convention-*.csv"``: the curves of
    ``--convention-band``'s presets instead."""
    import pandas as pd

    files = sorted(folder.glob(pattern)) if folder.is_dir() else []
    if len(files) < 2:
        return None
    grid = np.linspace(0.0, 1.0, points)
    curves = []
    for path in files:
        table = pd.read_csv(path)
        curves.append(interpolated_precision(table["recall"].to_numpy(),
                                             table["precision"].to_numpy(), grid))
    stack = np.vstack(curves)
    reached = np.isfinite(stack).any(axis=0)
    with warnings.catch_warnings():  # all-NaN columns (beyond every curve) are dropped below
        warnings.simplefilter("ignore", RuntimeWarning)
        low, high = np.nanmin(stack, axis=0), np.nanmax(stack, axis=0)
    return grid[reached], low[reached], high[reached], len(files)


def protocol_title(protocol: int, exclude: int | None = None) -> str:
    title = PROTOCOL_TITLES.get(protocol, f"Protocol {protocol}")
    if protocol == 1 and exclude is not None:
        title += f" (E = {exclude})"
    return title


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan
