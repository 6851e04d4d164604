"""The figure of ``liris segments``: several segmentation reports side by side.

One row per sequence, three panels: the size distribution of the segments
(voxels, log scale), the repeatability at neighbours and at revisits (bars,
one per configuration) and the cumulative share of repeated query segments
whose true target ranks within k, at revisits (solid) and against the
target map the frame has just left (dotted); the dashed line is the matcher's k.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.plotting.style import context, new_figure

_COLOURS = ("#7F7F7F", "#0072B2", "#D55E00", "#009E73", "#CC79A7")


def build_segment_reports(reports: list[dict]):
    """The figure of ``reports`` (dicts of :func:`~lidar_iris_eval.evaluation.segment_report.
    segment_report`), grouped by sequence in the order given."""
    sequences = list(dict.fromkeys(r["sequence"] for r in reports))
    fig = new_figure(7.2, 2.0 * len(sequences) + 0.3)
    axes = fig.subplots(len(sequences), 3, squeeze=False)
    for row, seq in enumerate(sequences):
        group = [r for r in reports if r["sequence"] == seq]
        ax_size, ax_rep, ax_rank = axes[row]
        bins = np.linspace(1.5, 4.5, 31)
        for c, r in enumerate(group):
            colour = _COLOURS[c % len(_COLOURS)]
            label = r.get("label") or r["preset"]
            sizes = np.asarray(r["segment_voxels"], dtype=np.float64)
            if len(sizes):
                ax_size.hist(np.log10(sizes), bins=bins, histtype="step", color=colour,
                             label=f"{label} ({r['segments_per_map_median'] or 0:.0f}/map)")
            vals = [r["neighbours"]["repeatability"], r["revisits"]["repeatability"]]
            x = np.arange(2) + (c - (len(group) - 1) / 2) * 0.8 / len(group)
            ax_rep.bar(x, [v if v is not None else 0.0 for v in vals],
                       width=0.8 / len(group), color=colour, label=label)
            ranks = np.sort([x for q in r["revisits"]["per_query"] for x in q["ranks"]])
            if len(ranks):
                share = np.arange(1, len(ranks) + 1) / r["revisits"]["query_segments"]
                ax_rank.step(ranks, share, where="post", color=colour, label=f"{label} revisits")
            nt = r.get("neighbours_target") or {}
            ranks = np.sort(nt.get("ranks", []))
            if len(ranks):
                share = np.arange(1, len(ranks) + 1) / nt["query_segments"]
                ax_rank.step(ranks, share, where="post", color=colour, ls=":",
                             label=f"{label} neighbours")
        ax_size.set_xlabel("log10 voxels per segment")
        ax_size.set_title(seq, loc="left")
        ax_size.legend(loc="upper right")
        ax_rep.set_xticks([0, 1], ["neighbours", "revisits"])
        ax_rep.set_ylim(0, 1)
        ax_rep.set_ylabel("repeatability (< 1 m)")
        ax_rank.set_xscale("log")
        ax_rank.axvline(group[0]["knn"], color="k", ls="--", lw=0.6)
        ax_rank.set_xlabel("rank of the true target")
        ax_rank.set_ylabel("share of query segments")
        ax_rank.set_ylim(0, 1)
        ax_rank.legend(loc="upper left")
    return fig


def plot_segment_reports(reports: list[dict], path: Path) -> Path:
    """Write :func:`build_segment_reports` to ``path`` (PNG, PDF or SVG by suffix)."""
    path = Path(path)
    with context():
        build_segment_reports(reports).savefig(path, dpi=150)
    return path
