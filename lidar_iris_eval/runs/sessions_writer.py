"""The run folder of a cross-session run (``liris eval --query A --database B``).

``metrics.json`` (rows with ``protocol: "cross-session"``), ``config.yaml``,
``cross_session/<method>/ranks.csv`` and ``pr.csv``; see
docs/results-format.md and :mod:`lidar_iris_eval.evaluation.sessions_run`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.evaluation.sessions_run import SessionsEvaluation
from lidar_iris_eval.runs.writer import RunWriter, pr_table, write_metrics


def write_cross_session(run: SessionsEvaluation, out, overwrite: bool = False, **extra) -> Path:
    """Write the run folder (module docstring) atomically; returns its path."""
    out = Path(out)
    config = run.config(**extra)
    with RunWriter(out, overwrite) as writer:
        for desc, _, _, res in run.results:
            base = f"cross_session/{desc.name}"
            writer.write_csv(f"{base}/ranks.csv", {
                "query": np.arange(len(res.match)), "match": res.match,
                "distance": res.distance, "is_true": res.is_true,
                "has_positive": res.ranks.has_positive, "rank": res.ranks.rank,
            })
            writer.write_csv(f"{base}/pr.csv", pr_table(res.curve))
        writer.write_yaml("config.yaml", config)
        write_metrics(writer, run.header(config), run.rows)
    return out
