"""``liris eval --query A --database B``: a cross-session run as a library call.

:func:`evaluate_cross_session` extracts (or loads) both sessions'
descriptors, builds the positives across sessions under the run's
:class:`~lidar_iris_eval.evaluation.settings.Settings` (radius, distance,
pose frame, inclusive radius; the exclusion window does not apply) and
scores every method with
:func:`~lidar_iris_eval.evaluation.cross_session.evaluate_sessions`.
:func:`lidar_iris_eval.runs.sessions_writer.write_cross_session` writes a run
folder ``liris show``, ``compare``,
``plot`` and ``report`` read: ``metrics.json`` (rows with ``protocol:
"cross-session"``, Recall@N, Recall@1 %, MRR and a top-1 PR curve),
``config.yaml``, ``cross_session/<method>/ranks.csv`` and ``pr.csv``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lidar_iris_eval import __version__
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.evaluation import metrics as m
from lidar_iris_eval.evaluation.cross_session import (
    EXCLUSION_RULE,
    CrossSessionResult,
    align_poses,
    cross_positives,
    evaluate_sessions,
)
from lidar_iris_eval.evaluation.evaluate import run_header
from lidar_iris_eval.evaluation.ground_truth import gt_coordinates
from lidar_iris_eval.evaluation.metrics import SUMMARY_KEYS
from lidar_iris_eval.evaluation.ranking import RANKING_DEFINITION
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.extract import extract

PROTOCOL = "cross-session"


def session_positions(seq, pose_frame: str, transform: np.ndarray | None) -> np.ndarray:
    """``(N, 3)`` positions of ``seq`` in ``pose_frame``, moved by ``transform`` when given.

    The transform acts on LiDAR-frame poses (query world -> database world);
    camera-frame positions follow as ``Tr A inv(Tr)`` applied to camera poses.
    """
    if transform is None:
        return seq.positions(pose_frame)
    if pose_frame == "lidar" or seq.camera_poses is None:
        return align_poses(seq.poses, transform)[:, :3, 3]
    tr = seq.calib if seq.calib is not None else np.eye(4)
    return align_poses(seq.camera_poses, tr @ transform @ np.linalg.inv(tr))[:, :3, 3]


@dataclass(frozen=True)
class SessionsEvaluation:
    """Results of :func:`evaluate_cross_session`."""

    query: Any
    database: Any
    settings: Settings
    pose_frame: str
    transform: np.ndarray | None
    results: list[tuple[Any, Any, Any, CrossSessionResult]]  # (descriptor, q_db, d_db, result)
    rows: list[dict]
    wall_s: float
    created: str = field(default_factory=lambda: datetime.now().isoformat(timespec="seconds"))

    def config(self, **extra) -> dict:
        s = self.settings

        def seq_info(seq):
            return {"path": str(Path(seq.path).resolve()), "name": seq.name,
                    "n_frames": len(seq), "fingerprint": seq.fingerprint()}

        config = {
            "version": __version__,
            "kind": PROTOCOL,
            "sequence": seq_info(self.query),
            "database": seq_info(self.database),
            "descriptors": [{"name": d.name, "preset": d.preset, "params": params_dict(d.params)}
                            for d, *_ in self.results],
            "protocols": [PROTOCOL],
            "pose_frame": self.pose_frame,  # the frame used; the rules: `convention`
            "candidates": s.candidates,
            "align": None if self.transform is None else self.transform.tolist(),
            "convention": s.to_dict(),
        }
        config.update(extra)
        return config

    def header(self, config: dict | None = None) -> dict:
        config = self.config() if config is None else config
        s = self.settings
        op = "<=" if s.inclusive_radius else "<"
        return {
            **run_header(self, config),
            "database": config["database"],
            "conventions": {
                "kind": PROTOCOL,
                "convention": s.name,
                "convention_source": s.source,
                "radius": float(s.radius),
                "exclude": None,
                "exclude_preset": PROTOCOL,
                "exclusion": EXCLUSION_RULE,
                "distance": s.distance,
                "pose_frame": self.pose_frame,
                "recall_denominator": "revisits",
                "candidates": s.candidates,
                "positive": f"a database frame of the other session at ground-truth distance "
                            f"{op} {s.radius:g} m",
                "alignment": ("query poses moved into the database frame by the given "
                              "transform" if self.transform is not None else
                              "both sessions' poses in one world frame (no transform)"),
                "ranking": RANKING_DEFINITION,
                "top1_pr": "each query's best database match, accepted when distance <= tau, "
                           "true when a positive; recall over queries with a positive",
                "threshold_rule": m.THRESHOLD_RULE,
                "ap": m.AP_DEFINITION,
                "ep": m.EP_DEFINITION,
            },
        }


def _row(desc, q_db, d_db, res: CrossSessionResult) -> dict:
    met = res.metrics
    n_q = max(1, met["n_queries"])
    extract_ms = np.concatenate([np.asarray(q_db.extract_s), np.asarray(d_db.extract_s)])
    return {
        "protocol": PROTOCOL, "descriptor": desc.name, "preset": desc.preset,
        **{k: met[k] for k in SUMMARY_KEYS},
        "n_queries": met["n_queries"], "n_database": met["n_database"],
        "n_positives": met["n_revisits"], "n_revisits": met["n_revisits"],
        "n_true_top1": met["n_true_top1"], "top1_accuracy": met["top1_accuracy"],
        "recall_at_1": met["recall_at_1"], "recall_at_1pct": met["recall_at_1pct"],
        "recall_1pct_n": met["recall_1pct_n"], "mrr": met["mrr"],
        "mrr_top25_found": met["mrr_top25_found"], "recall_at_n": met["recall_at_n"],
        "n_ranking_queries": met["n_ranking_queries"],
        "extract_ms_per_scan": float(np.mean(extract_ms) * 1e3) if len(extract_ms) else None,
        "match_ms_per_query": met.get("match_s", float("nan")) / n_q * 1e3,
        "ranking_rule": met["ranking_rule"],
        "exclusion": met["exclusion"],
    }


def evaluate_cross_session(query, database, descriptors, settings: Settings, *,
                           transform: np.ndarray | None = None, cache=None, workers: int = 1,
                           progress: bool = False, executor=None) -> SessionsEvaluation:
    """Evaluate ``descriptors`` (objects) with queries from ``query`` against ``database``."""
    pose_frame = settings.pose_frame
    if pose_frame == "camera" and (query.camera_poses is None or database.camera_poses is None):
        pose_frame = "lidar"  # the run records the frame the numbers are computed in
        settings = settings.replace(pose_frame="lidar")
    q_xyz = session_positions(query, pose_frame, transform)
    d_xyz = database.positions(pose_frame)
    positives = cross_positives(gt_coordinates(q_xyz, pose_frame, settings.distance),
                                gt_coordinates(d_xyz, pose_frame, settings.distance),
                                settings.radius, settings.inclusive_radius)
    started = time.perf_counter()
    results, rows = [], []
    for desc in descriptors:
        q_db = extract(query, desc, cache=cache, workers=workers, progress=progress,
                       executor=executor)
        d_db = extract(database, desc, cache=cache, workers=workers, progress=progress,
                       executor=executor)
        t0 = time.perf_counter()
        with tqdm(total=len(query), desc=f"{desc.name} cross-session", unit="query",
                  file=sys.stderr, disable=not progress, leave=False) as bar:
            res = evaluate_sessions(desc, q_db, d_db, positives, candidates=settings.candidates,
                                    pair_budget=settings.pair_budget, progress=bar.update)
        res.metrics["match_s"] = time.perf_counter() - t0
        results.append((desc, q_db, d_db, res))
        rows.append(_row(desc, q_db, d_db, res))
    return SessionsEvaluation(query, database, settings, pose_frame, transform, results, rows,
                              time.perf_counter() - started)
