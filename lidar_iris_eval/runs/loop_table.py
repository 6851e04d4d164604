"""The loop-pose table of a run (issue 23): registration recall beside the pose medians.

Printed by ``liris eval`` after the metrics table and by ``liris show``, from
the protocol 1 rows of ``metrics.json``; columns that no row fills (no
``--refine``, no ``--gt-pose refined``, no ``--seeds``) are left out, and an
undefined value is ``n/a``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from lidar_iris_eval.runs.table import render_table

#: (column, metrics.json key) in order
LOOP_COLUMNS = (
    ("descriptor", "descriptor"),
    ("pose", "pose_estimate"),
    ("rr", "rr"),
    ("rr_kind", "rr_kind"),
    ("rte_m_median", "rte_m_median"),
    ("rre_deg_median", "rre_deg_median"),
    ("rr_rte_m_mean", "rr_rte_m_mean"),
    ("rr_rre_deg_mean", "rr_rre_deg_mean"),
    ("refined_rr", "refined_rr"),
    ("refined_rte_m_median", "refined_rte_m_median"),
    ("refined_rre_deg_median", "refined_rre_deg_median"),
    ("register_ms_per_loop", "registration_ms_per_loop"),
    ("rejected", "n_rejected_by_registration"),
    ("rte_m_median_refined_gt", "rte_m_median_refined_gt"),
    ("refined_rte_m_median_refined_gt", "refined_rte_m_median_refined_gt"),
    ("gt_moved_m_median", "gt_refinement_m_median"),
)
#: always shown (the rest only when some row has a value)
_ALWAYS = {"descriptor", "pose", "rr", "rr_kind", "rte_m_median", "rre_deg_median"}


def loop_rows(rows: Sequence[Mapping[str, Any]]) -> list[dict]:
    """The protocol 1 rows that carry registration recall, reduced to the table's keys."""
    return [{col: r.get(key) for col, key in LOOP_COLUMNS} for r in rows
            if r.get("protocol") == 1 and "rr" in r]


def render_loop_table(rows: Sequence[Mapping[str, Any]], fmt: str = "table") -> str:
    """The loop-pose table in ``fmt`` (as :func:`~lidar_iris_eval.runs.table.render_table`),
    or ``""`` when no row has registration recall (runs before issue 23)."""
    table = loop_rows(rows)
    if not table:
        return ""
    columns = [c for c, _ in LOOP_COLUMNS
               if c in _ALWAYS or any(r.get(c) is not None for r in table)]
    return render_table(table, fmt, columns, summarize=False)


#: metrics of the seed table, in order (those some row has)
SEED_COLUMNS = ("ap", "f1_max", "r100p", "ep", "rr", "rte_m_median", "refined_rr",
                "refined_rte_m_median")


def _mean_range(block: Mapping[str, Any] | None) -> str | None:
    if not block or block.get("mean") is None:
        return None
    return f"{block['mean']:.4f} [{block['min']:.4f}, {block['max']:.4f}]"


def render_seed_table(rows: Sequence[Mapping[str, Any]], fmt: str = "table") -> str:
    """``--seeds``: each metric as ``mean [min, max]`` over the seeds, or ``""`` without."""
    seeded = [r for r in rows if isinstance(r.get("seeds"), Mapping)]
    if not seeded:
        return ""
    metrics = [m for m in SEED_COLUMNS if any(m in r["seeds"] for r in seeded)]
    table = []
    for r in seeded:
        block = r["seeds"]
        entry = {"protocol": r.get("protocol"), "descriptor": r.get("descriptor"),
                 "seeds": ",".join(str(s) for s in block.get("seeds", [])),
                 "stochastic": block.get("stochastic")}
        entry.update({m: _mean_range(block.get(m)) for m in metrics})
        table.append(entry)
    return render_table(table, fmt, ["protocol", "descriptor", "seeds", "stochastic", *metrics],
                        summarize=False)


#: (column, metrics.json key) of the table of scored loop files (``liris eval --loops``)
LOOPS_COLUMNS = (
    ("descriptor", "descriptor"),
    ("loops", "n_loops"),
    ("scored", "n_loops_scored"),
    ("tp", "loops_tp"),
    ("fp", "loops_fp"),
    ("precision", "loops_precision"),
    ("recall", "loops_recall"),
    ("coverage", "revisit_coverage"),
    ("stretches", "n_revisit_stretches_covered"),
    ("of", "n_revisit_stretches"),
    ("rr", "loops_rr"),
    ("ape_none_m", "posegraph_ape_none_m"),
    ("ape_true_m", "posegraph_ape_true_m"),
    ("ape_all_m", "posegraph_ape_all_m"),
    ("worst_false_m", "posegraph_worst_false_added_m"),
)
_LOOPS_ALWAYS = {"descriptor", "loops", "scored", "tp", "fp", "precision", "recall",
                 "coverage"}


def render_loops_table(rows: Sequence[Mapping[str, Any]], fmt: str = "table") -> str:
    """The loop files' TP/FP, precision, coverage and pose-graph APE (docs/loops.md), or
    ``""`` when no row is a scored loop file."""
    table = [{col: r.get(key) for col, key in LOOPS_COLUMNS} for r in rows
             if "loops_tp" in r]
    if not table:
        return ""
    columns = [c for c, _ in LOOPS_COLUMNS
               if c in _LOOPS_ALWAYS or any(r.get(c) is not None for r in table)]
    return render_table(table, fmt, columns, summarize=False)
