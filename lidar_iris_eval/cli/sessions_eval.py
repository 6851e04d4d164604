"""``liris eval --query A --database B``: parsing and printing of a cross-session run.

The evaluation is :func:`lidar_iris_eval.evaluation.sessions_run.evaluate_cross_session`.
"""

from __future__ import annotations

import click

from lidar_iris_eval.cache import DescriptorCache, default_cache_dir
from lidar_iris_eval.cli.descriptor_options import build_descriptors, open_input
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.cli.workflow import config_extra, table_format
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.cross_session import read_transform
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.runs.table import render_table
from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir, json_ready
from lidar_iris_eval.sensors import resolve_sensor


def evaluate_sessions_cli(sequence, query_path, database_path, align_path, protocols,
                          descriptor_text, preset, params, sensor, cache_dir, workers, quiet,
                          settings, conv, out, overwrite, as_json, reader_options, plan,
                          export_path, scheduler) -> None:
    """Run, write and print one query/database evaluation."""
    from lidar_iris_eval.evaluation.sessions_run import evaluate_cross_session
    from lidar_iris_eval.runs.sessions_writer import write_cross_session

    if query_path is None or database_path is None:
        raise LirisError("--query/--database", "a cross-session run needs both")
    if sequence or plan is not None:
        raise LirisError("--query/--database", "give either SEQUENCE / --plan or "
                                               "--query and --database, not both")
    if protocols:
        raise LirisError("--protocol", "does not apply to --query/--database (the run ranks "
                                       "the whole database for every query)")
    if export_path is not None:
        raise LirisError("--export-loops", "applies to a within-sequence run only")
    if not descriptor_text:
        raise LirisError("--descriptor", "give at least one method")
    transform = read_transform(align_path) if align_path is not None else None
    query = open_input(query_path, reader_options)
    database = open_input(database_path, reader_options)
    sensor = resolve_sensor(sensor, lambda: query)
    descriptors = build_descriptors(descriptor_text, preset, sensor, params)
    for d in descriptors:
        if settings.candidates is not None and not d.has_retrieval():
            raise LirisError(f"--candidates {settings.candidates}",
                             f"{d.name} has no retrieval stage")
        d.check_inputs(query)
        d.check_inputs(database)
    if out is None:
        out = default_run_dir(f"{query.name}-vs-{database.name}")
    check_run_dir(out, overwrite)
    cache = DescriptorCache(cache_dir if cache_dir is not None else default_cache_dir())
    with open_executor(check_scheduler(scheduler), workers) as executor:
        run = evaluate_cross_session(query, database, descriptors, settings,
                                     transform=transform, cache=cache, workers=workers,
                                     progress=not quiet, executor=executor)
    extra = {**config_extra(conv), "sensor": sensor}
    write_cross_session(run, out, overwrite, **extra)
    if as_json:
        echo_json(json_ready({**run.header(run.config(**extra)), "results": run.rows}))
        return
    click.echo(render_table(run.rows, table_format()))
    click.echo(f"cross-session: queries {query.name} ({len(query)}) against database "
               f"{database.name} ({len(database)}); radius {settings.radius:g} m, "
               f"{settings.distance} distance, {run.pose_frame}-frame poses, convention "
               f"{conv.name}; no exclusion window across sessions; results in {out}",
               err=table_format() != "table")
