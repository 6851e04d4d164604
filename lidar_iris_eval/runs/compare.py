"""Comparing finished runs: metrics side by side, their differences, and convention changes.

Two runs are only comparable when they were evaluated under the same
conventions (radius, exclusion window, recall denominator, ...) on the same
scans; :func:`convention_differences` names every such setting that differs,
so a table of differences is never read without that context.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lidar_iris_eval.atomic import atomic_save_figure
from lidar_iris_eval.runs.reader import Run
from lidar_iris_eval.runs.table import RANKING_COLUMNS, table_row

#: the metrics compared, in order
COMPARE_METRICS = ("ap", "f1_max", "r100p", "ep", "n", "positives")

#: settings whose difference changes what the numbers mean: (label, where, key path)
CONVENTION_KEYS = (
    ("convention preset", "conventions", ("convention",)),
    ("radius (m)", "conventions", ("radius",)),
    ("exclusion E (frames)", "conventions", ("exclude",)),
    ("exclusion (seconds)", "conventions", ("exclude_seconds",)),
    ("distance", "conventions", ("distance",)),
    ("pose frame", "conventions", ("pose_frame",)),
    ("recall denominator", "conventions", ("recall_denominator",)),
    ("protocol 1 candidates", "conventions", ("candidates",)),
    ("not-a-revisit band", "conventions", ("not_revisit_band",)),
    ("query range", "conventions", ("query_range",)),
    ("exclusion across sessions", "conventions", ("exclusion",)),
    ("database session", "config", ("database", "name")),
    ("database fingerprint", "config", ("database", "fingerprint")),
    ("sequence", "config", ("sequence", "name")),
    ("scan fingerprint", "config", ("sequence", "fingerprint")),
    ("frames", "config", ("sequence", "n_frames")),
    ("reader options (frame selection, poses)", "config", ("sequence", "reader_options")),
    ("sensor", "config", ("sensor",)),
    ("liris version", "metrics", ("version",)),
)


def run_labels(runs: Sequence[Run]) -> list[str]:
    """Folder names, made unique with ``#k`` when a folder is given twice."""
    labels: list[str] = []
    for run in runs:
        label = run.name
        k = 2
        while label in labels:
            label = f"{run.name}#{k}"
            k += 1
        labels.append(label)
    return labels


def _get(run: Run, where: str, path: tuple[str, ...]) -> Any:
    value: Any = {"conventions": run.conventions, "config": run.config,
                  "metrics": run.metrics}[where]
    for key in path:
        if not isinstance(value, dict):
            return None
        value = value.get(key)
    return value


def convention_differences(runs: Sequence[Run]) -> list[dict[str, Any]]:
    """Settings that differ between the runs: ``{"setting", <label>: value, ...}`` rows.

    Descriptor parameters are compared too, per descriptor present in several runs.
    """
    labels = run_labels(runs)
    out = []
    for name, where, path in CONVENTION_KEYS:
        values = [_get(run, where, path) for run in runs]
        if any(v != values[0] for v in values[1:]):
            out.append({"setting": name, **dict(zip(labels, values, strict=True))})
    params: dict[str, list[Any]] = {}
    for k, run in enumerate(runs):
        for d in run.config.get("descriptors", []) or []:
            params.setdefault(d.get("name"), [None] * len(runs))[k] = (d.get("preset"),
                                                                      d.get("params"))
    for name, values in params.items():
        present = [v for v in values if v is not None]
        if len(present) > 1 and any(v != present[0] for v in present[1:]):
            out.append({"setting": f"{name} preset/params",
                        **{lab: (None if v is None else _short(v))
                           for lab, v in zip(labels, values, strict=True)}})
    return out


def _short(value: tuple[str, dict]) -> str:
    preset, params = value
    return f"{preset} {params}"


def metric_comparison(runs: Sequence[Run]) -> list[dict[str, Any]]:
    """One row per (protocol, descriptor, preset, metric): each run's value and the
    difference of every later run to the first (``None`` where undefined)."""
    labels = run_labels(runs)
    keys: list[tuple] = []
    tables: list[dict[tuple, dict]] = []
    for run in runs:
        rows = {}
        for row in run.rows:
            summary = table_row(row)
            key = (summary["protocol"], summary["descriptor"], summary["preset"])
            rows[key] = summary
            if key not in keys:
                keys.append(key)
        tables.append(rows)
    # ranking metrics (cross-session runs, --ranking) only when some run has them
    ranked = [k for k in RANKING_COLUMNS if any(k in row for t in tables for row in t.values())]
    out = []
    for key in keys:
        for metric in (*COMPARE_METRICS, *ranked):
            values = [t.get(key, {}).get(metric) for t in tables]
            row: dict[str, Any] = {"protocol": key[0], "descriptor": key[1], "preset": key[2],
                                   "metric": metric}
            row.update(dict(zip(labels, values, strict=True)))
            for label, value in zip(labels[1:], values[1:], strict=True):
                row[f"{label} - {labels[0]}"] = _difference(value, values[0])
            out.append(row)
    return out


def _difference(value: Any, base: Any) -> Any:
    if value is None or base is None:
        return None
    diff = value - base
    if isinstance(diff, float) and not math.isfinite(diff):
        return None
    return diff


def count_differences(rows: list[dict[str, Any]], labels: list[str]) -> int:
    """Comparable metric values (defined in both runs) that differ from the first run's."""
    return difference_counts(rows, labels)[0]


def difference_counts(rows: list[dict[str, Any]], labels: list[str]) -> tuple[int, int, int]:
    """``(differ, comparable, one_sided)`` over every later run's values against the first's.

    A value is comparable when both runs define it; one that only one run has (a
    descriptor or protocol the other run lacks, or an undefined metric) is counted
    apart, never as a difference.
    """
    differ = comparable = one_sided = 0
    for row in rows:
        base = row[labels[0]]
        for label in labels[1:]:
            value = row[label]
            if value is None and base is None:
                continue
            if value is None or base is None:
                one_sided += 1
                continue
            comparable += 1
            differ += value != base
    return differ, comparable, one_sided


def difference_summary(rows: list[dict[str, Any]], labels: list[str]) -> str:
    """``"N metric value(s) differ from A (of M comparable; K in one run only)"``."""
    differ, comparable, one_sided = difference_counts(rows, labels)
    text = f"{differ} metric value(s) differ from {labels[0]} (of {comparable} comparable"
    return text + (f"; {one_sided} defined in one run only)" if one_sided else ")")


def plot_pr_overlay(runs: Sequence[Run], out: str | os.PathLike) -> Path:
    """PR curves of every run and descriptor, one panel per protocol, labelled
    ``descriptor/preset/run``; written atomically to ``out`` (format from its suffix)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = run_labels(runs)
    protocols = sorted({r["protocol"] for run in runs for r in run.rows}, key=str)
    fig, axes = plt.subplots(1, max(1, len(protocols)), figsize=(5.5 * max(1, len(protocols)), 4.5),
                             squeeze=False)
    styles = ["-", "--", ":", "-."]
    for ax, protocol in zip(axes[0], protocols, strict=False):
        for k, (run, label) in enumerate(zip(runs, labels, strict=True)):
            for row in run.rows:
                if row["protocol"] != protocol:
                    continue
                curve = run.pr(protocol, row["descriptor"])
                ax.plot(curve["recall"], curve["precision"], styles[k % len(styles)],
                        label=f"{row['descriptor']}/{row['preset']}/{label}")
        ax.set(xlim=(0, 1.02), ylim=(0, 1.02), xlabel="recall", ylabel="precision",
               title=f"protocol {protocol}" if protocol != "cross-session" else
               "cross-session (top-1)")
        ax.grid(alpha=0.3)
    # the legend goes below the panels, never over the curves
    handles, names = axes[0][0].get_legend_handles_labels()
    for ax in axes[0][1:]:
        for h, n in zip(*ax.get_legend_handles_labels(), strict=True):
            if n not in names:
                handles.append(h)
                names.append(n)
    if handles:
        fig.legend(handles, names, fontsize=7, loc="lower center",
                   ncol=max(1, min(3, len(names))), frameon=False)
        rows = math.ceil(len(names) / max(1, min(3, len(names))))
        fig.tight_layout(rect=(0, min(0.5, 0.05 + 0.045 * rows), 1, 1))
    else:
        fig.tight_layout()
    try:
        atomic_save_figure(fig, Path(out), "--plot", dpi=120)
    finally:
        plt.close(fig)
    return Path(out)
