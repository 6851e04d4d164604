"""Extraction and matching time per method (the paper's Fig. 11).

Extraction has one time per scan (``timing/<descriptor>.csv``), so it is shown
as a box plot: the spread matters, because a method that is fast on average
but slow on dense scans stalls an online system. Matching time is a single
figure per method in metrics.json, shown as a bar with its value. Both axes
switch to log scale when methods differ by more than a factor of 10, which
is common (ESF vs Scan Context).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from lidar_iris_eval.plotting import style

TIMING_SIZE = (style.COLUMN_WIDTH, 2.2)
LOG_RATIO = 10.0


def timing_figure(extract_ms: Mapping[str, np.ndarray], match: Mapping[str, float],
                  match_label: str = "matching [ms / query]", note: str = "") -> Figure:
    """Box plot of per-scan extraction times (ms) beside bars of matching time.

    ``match`` maps method → one number in the unit given by ``match_label``;
    either mapping may be empty (its panel then says so).
    """
    with style.context():
        fig = style.new_figure(*TIMING_SIZE)
        left, right = fig.subplots(1, 2)
        _extraction_panel(left, extract_ms)
        _matching_panel(right, match, match_label)
        if note:  # the conditions: wall-clock matching slows on a busy machine
            fig.supxlabel(note, fontsize=5.5, color="0.35")
    return fig


def _extraction_panel(ax, extract_ms: Mapping[str, np.ndarray]) -> None:
    names = [n for n, v in extract_ms.items() if len(v)]
    if not names:
        _empty(ax, "no timing/*.csv")
        return
    data = [np.asarray(extract_ms[n], dtype=np.float64) for n in names]
    boxes = ax.boxplot(data, widths=0.6, patch_artist=True, showfliers=True,
                       medianprops={"color": "black", "linewidth": 0.8},
                       whiskerprops={"linewidth": 0.6}, capprops={"linewidth": 0.6},
                       flierprops={"marker": ".", "markersize": 1.5, "alpha": 0.5})
    for patch, name in zip(boxes["boxes"], names, strict=True):
        patch.set_facecolor(style.method_color(name))
        patch.set_alpha(0.75)
        patch.set_linewidth(0.6)
        patch.set_gid(f"extract:{name}")
    for median, name in zip(boxes["medians"], names, strict=True):
        median.set_gid(f"median:{name}")
    ax.set_xticks(range(1, len(names) + 1), [_short(n) for n in names])
    _maybe_log(ax, [d[d > 0] for d in data])
    ax.set_ylabel("extraction, CPU [ms / scan]")
    ax.grid(True, axis="y", linewidth=0.3, alpha=0.5)


def _matching_panel(ax, match: Mapping[str, float], label: str) -> None:
    names = [n for n, v in match.items() if v is not None and np.isfinite(v)]
    if not names:
        _empty(ax, "no matching times")
        return
    values = np.array([match[n] for n in names], dtype=np.float64)
    x = np.arange(1, len(names) + 1)
    bars = ax.bar(x, values, width=0.6, color=[style.method_color(n) for n in names], alpha=0.75)
    for bar, name in zip(bars, names, strict=True):
        bar.set_gid(f"match:{name}")
    ax.set_xticks(x, [_short(n) for n in names])
    _maybe_log(ax, [values[values > 0]])
    for xi, v in zip(x, values, strict=True):
        ax.annotate(_fmt(v), (xi, v), xytext=(0, 1.5), textcoords="offset points",
                    ha="center", va="bottom", fontsize=5.5)
    ax.margins(y=0.15)
    ax.set_ylabel(label)
    ax.grid(True, axis="y", linewidth=0.3, alpha=0.5)


def _maybe_log(ax, groups) -> None:
    positive = [g for g in groups if len(g)]
    if not positive:
        return
    lo = min(float(np.min(g)) for g in positive)
    hi = max(float(np.max(g)) for g in positive)
    if lo > 0 and hi / lo > LOG_RATIO:
        ax.set_yscale("log")
        # plain numbers (2, 5, 10, 20), not 2×10⁰
        plain = FuncFormatter(lambda v, _: f"{v:g}")
        ax.yaxis.set_major_formatter(plain)
        ax.yaxis.set_minor_formatter(FuncFormatter(
            lambda v, _: f"{v:g}" if f"{v:g}"[0] in "25" else ""))


def _short(name: str) -> str:
    """Tick labels short enough for a 1.6 in panel."""
    return {"lidar-iris": "Iris", "scan-context": "SC"}.get(name, style.method_label(name))


def _fmt(value: float) -> str:
    if value >= 100:
        return f"{value:.0f}"
    if value >= 1:
        return f"{value:.1f}"
    return f"{value:.2g}"


def _empty(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, fontsize=7,
            color="0.4")
    ax.set_xticks([])
    ax.set_yticks([])
