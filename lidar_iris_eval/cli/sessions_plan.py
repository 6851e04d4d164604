"""``liris eval --plan sessions.yaml``: many query/database pairs in one run folder.

A plan with ``pairs`` (or ``sessions``) instead of ``sequences``/``runs``::

    descriptors: [lidar-iris, m2dp]
    pairs:
      - {query: W/session1, database: W/session0}
      - {query: W/session2, database: W/session0, align: T_2_0.txt}

or every ordered pair of a list of sessions (Wild-Places' inter-sequence
evaluation: every query sequence against every other)::

    descriptors: lidar-iris
    sessions: [V-01, V-02, V-03]

Relative paths are read relative to the plan file. The run folder holds
one cross-session run folder per pair (``NN-<query>-vs-<database>/``) and
``summary.csv`` / ``summary.md``: one row per pair and method with
Recall@1, Recall@1 %, MRR, AP and F1max, plus the mean over pairs per
method (Wild-Places averages its pairs the same way).
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import yaml

from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.errors import LirisError

SESSION_PLAN_KEYS = {"pairs", "sessions"}
SUMMARY = ("query", "database", "descriptor", "preset", "recall_at_1", "recall_at_1pct", "mrr",
           "ap", "f1_max", "n_queries")


def is_sessions_plan(path: Path) -> bool:
    """True when the plan file lists query/database pairs (``pairs`` or ``sessions``)."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False  # the ordinary reader reports it
    return isinstance(data, dict) and bool(SESSION_PLAN_KEYS & set(data))


def read_sessions_plan(path: Path, descriptors: str | None) -> list[dict]:
    """``[{query, database, align, descriptors}]`` from a sessions plan (module docstring)."""
    path = Path(path)
    data = yaml.safe_load(path.read_text())
    unknown = set(data) - SESSION_PLAN_KEYS - {"descriptors"}
    if unknown:
        raise LirisError(path, f"unknown keys {sorted(unknown)}; a sessions plan has pairs or "
                               "sessions, and descriptors")
    if "pairs" in data and "sessions" in data:
        raise LirisError(path, "give pairs or sessions, not both")
    text = data.get("descriptors", descriptors)
    if isinstance(text, list):
        text = ",".join(str(t) for t in text)
    if not text:
        raise LirisError(path, "no descriptors (in the plan or --descriptor)")

    def resolve(value, where):
        if not isinstance(value, str) or not value:
            raise LirisError(path, f"{where}: expected a path")
        p = Path(value)
        return p if p.is_absolute() else (path.parent / p)

    out = []
    if "sessions" in data:
        names = data["sessions"]
        if not isinstance(names, list) or len(names) < 2:
            raise LirisError(path, "sessions: a list of at least two sessions")
        folders = [resolve(v, f"sessions[{k}]") for k, v in enumerate(names)]
        for q in folders:
            for d in folders:
                if q != d:
                    out.append({"query": q, "database": d, "align": None, "descriptors": text})
        return out
    pairs = data["pairs"]
    if not isinstance(pairs, list) or not pairs:
        raise LirisError(path, "pairs: a non-empty list of {query, database}")
    for k, item in enumerate(pairs):
        if not isinstance(item, dict) or not {"query", "database"} <= set(item) or \
                set(item) - {"query", "database", "align", "descriptors"}:
            raise LirisError(path, f"pairs[{k}]: needs query and database (align, descriptors "
                                   "optional)")
        out.append({"query": resolve(item["query"], f"pairs[{k}].query"),
                    "database": resolve(item["database"], f"pairs[{k}].database"),
                    "align": None if item.get("align") is None
                    else resolve(item["align"], f"pairs[{k}].align"),
                    "descriptors": item.get("descriptors", text) if not isinstance(
                        item.get("descriptors"), list) else ",".join(item["descriptors"])})
    return out


def _mean(values):
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return sum(values) / len(values) if values else None


def run_sessions_plan(req: EvalRequest) -> None:
    """Evaluate every pair of the plan into ``out/NN-<query>-vs-<database>/`` and write the
    summary (the mode ``sessions-plan``)."""
    from lidar_iris_eval.cli.descriptor_options import build_descriptors, open_input
    from lidar_iris_eval.evaluation.cross_session import read_transform
    from lidar_iris_eval.evaluation.sessions_run import evaluate_cross_session
    from lidar_iris_eval.executor import check_scheduler, open_executor
    from lidar_iris_eval.runs.plan import write_text_atomic
    from lidar_iris_eval.runs.sessions_writer import write_cross_session
    from lidar_iris_eval.runs.table import cell
    from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir

    req.refuse_convention_band()
    req.refuse_estimated_odometry()
    if req.protocols:
        raise LirisError("--protocol", "does not apply to a plan of query/database pairs")
    plan = req.plan
    entries = read_sessions_plan(plan, req.descriptor_text)
    out = Path(req.out) if req.out is not None else default_run_dir(Path(plan).stem)
    check_run_dir(out, req.overwrite)
    cache = req.cache()
    rows = []
    with open_executor(check_scheduler(req.scheduler), req.workers) as executor:
        for k, entry in enumerate(entries):
            query = open_input(entry["query"], req.reader_options)
            database = open_input(entry["database"], req.reader_options)
            descriptors = build_descriptors(entry["descriptors"], req.preset, req.sensor,
                                            req.params)
            for d in descriptors:
                d.check_inputs(query)
                d.check_inputs(database)
            transform = read_transform(entry["align"]) if entry["align"] is not None else None
            run = evaluate_cross_session(query, database, descriptors, req.settings,
                                         transform=transform, cache=cache,
                                         workers=req.workers, progress=not req.quiet,
                                         executor=executor)
            folder = out / f"{k:02d}-{query.name}-vs-{database.name}"
            write_cross_session(run, folder, req.overwrite, **req.config_extra(),
                                sensor=req.sensor)
            for row in run.rows:
                rows.append({"query": query.name, "database": database.name,
                             **{c: row.get(c) for c in SUMMARY[2:]}})
    methods = []
    for row in rows:
        if (row["descriptor"], row["preset"]) not in methods:
            methods.append((row["descriptor"], row["preset"]))
    for name, preset_name in methods:
        mine = [r for r in rows if (r["descriptor"], r["preset"]) == (name, preset_name)]
        rows.append({"query": "mean", "database": f"{len(mine)} pairs", "descriptor": name,
                     "preset": preset_name,
                     **{c: _mean([r[c] for r in mine]) for c in SUMMARY[4:]}})
    header = "| " + " | ".join(SUMMARY) + " |\n|" + "---|" * len(SUMMARY) + "\n"
    md = header + "".join("| " + " | ".join(cell(r.get(c)) for c in SUMMARY) + " |\n"
                          for r in rows)
    csv = ",".join(SUMMARY) + "\n" + "".join(
        ",".join("" if r.get(c) is None else str(r.get(c)) for c in SUMMARY) + "\n"
        for r in rows)
    write_text_atomic(out / "summary.md", md)
    write_text_atomic(out / "summary.csv", csv)
    click.echo(md.rstrip("\n"))
    click.echo(f"{len(entries)} query/database pairs; results in {out}")
