"""``liris eval --query A --database B``: parsing and printing of a cross-session run.

The mode ``sessions`` of :class:`~lidar_iris_eval.cli.eval_request.EvalRequest`;
the evaluation is :func:`lidar_iris_eval.evaluation.sessions_run.evaluate_cross_session`.
"""

from __future__ import annotations

import click

from lidar_iris_eval.cli.descriptor_options import build_descriptors, open_input
from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.cross_session import read_transform
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.runs.table import render_table
from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir, json_ready
from lidar_iris_eval.sensors import resolve_sensor


def check_sessions_request(req: EvalRequest) -> None:
    """Refuse what a query/database run does not take, before any file is read."""
    req.refuse_convention_band()
    req.refuse_estimated_odometry()
    if req.query is None or req.database is None:
        raise LirisError("--query/--database", "a cross-session run needs both")
    if req.sequences or req.plan is not None:
        raise LirisError("--query/--database", "give either SEQUENCE / --plan or "
                                               "--query and --database, not both")
    if req.protocols:
        raise LirisError("--protocol", "does not apply to --query/--database (the run ranks "
                                       "the whole database for every query)")
    if req.export_path is not None:
        raise LirisError("--export-loops", "applies to a within-sequence run only")
    if not req.descriptor_text:
        raise LirisError("--descriptor", "give at least one method")


def run_sessions(req: EvalRequest) -> None:
    """Run, write and print one query/database evaluation (the mode ``sessions``)."""
    from lidar_iris_eval.evaluation.sessions_run import evaluate_cross_session
    from lidar_iris_eval.runs.sessions_writer import write_cross_session

    check_sessions_request(req)
    settings = req.settings
    transform = read_transform(req.align) if req.align is not None else None
    query = open_input(req.query, req.reader_options)
    database = open_input(req.database, req.reader_options)
    sensor = resolve_sensor(req.sensor, lambda: query)
    descriptors = build_descriptors(req.descriptor_text, req.preset, sensor, req.params)
    for d in descriptors:
        if settings.candidates is not None and not d.has_retrieval():
            raise LirisError(f"--candidates {settings.candidates}",
                             f"{d.name} has no retrieval stage")
        d.check_inputs(query)
        d.check_inputs(database)
    out = req.out if req.out is not None else default_run_dir(f"{query.name}-vs-{database.name}")
    check_run_dir(out, req.overwrite)
    with open_executor(check_scheduler(req.scheduler), req.workers) as executor:
        run = evaluate_cross_session(query, database, descriptors, settings,
                                     transform=transform, cache=req.cache(),
                                     workers=req.workers, progress=not req.quiet,
                                     executor=executor)
    extra = {**req.config_extra(), "sensor": sensor}
    write_cross_session(run, out, req.overwrite, **extra)
    if req.as_json:
        echo_json(json_ready({**run.header(run.config(**extra)), "results": run.rows}))
        return
    click.echo(render_table(run.rows, req.fmt))
    click.echo(f"cross-session: queries {query.name} ({len(query)}) against database "
               f"{database.name} ({len(database)}); radius {settings.radius:g} m, "
               f"{settings.distance} distance, {run.pose_frame}-frame poses, convention "
               f"{req.convention.name}; no exclusion window across sessions; results in {out}",
               err=req.fmt != "table")
