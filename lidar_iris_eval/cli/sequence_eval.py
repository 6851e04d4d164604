"""``liris eval SEQUENCE``: protocol 1 and/or 2 on one sequence, written to a run folder.

The mode ``sequence`` of :class:`~lidar_iris_eval.cli.eval_request.EvalRequest`;
the evaluation itself is :func:`lidar_iris_eval.evaluation.evaluate.evaluate`.
"""

from __future__ import annotations

import click

from lidar_iris_eval.cli.descriptor_options import build_descriptors, open_input
from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.loop_options import check_odometry_file, read_odometry
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.cli.workflow import extract_all, load_externals
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.evaluate import (
    bind_exclusion,
    check_request,
    evaluate,
    export_loops,
    loop_export_paths,
)
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.ownership import check_new_files
from lidar_iris_eval.runs.table import render_band_table, render_table
from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir, json_ready, write_run
from lidar_iris_eval.sensors import resolve_sensor


def sequence_descriptors(req: EvalRequest) -> tuple[str | None, list]:
    """The sensor preset and the ``--descriptor`` methods of the request's one SEQUENCE.

    Shared by the modes ``sequence`` and ``pairs``: ``--sensor auto`` is
    resolved from the sequence, and a pose file given as ``--odometry`` is
    refused for methods that build local maps.
    """
    sequence = req.sequences[0]
    sensor = resolve_sensor(req.sensor, lambda: open_input(sequence, req.reader_options))
    descriptors = (build_descriptors(req.descriptor_text, req.preset, sensor, req.params,
                                     req.odometry) if req.descriptor_text else [])
    check_odometry_file(req.odometry_path, descriptors)
    return sensor, descriptors


def check_export_path(req: EvalRequest) -> None:
    """``--export-loops`` writes protocol 1's loops to a .g2o, .tum or .txt file."""
    if req.export_path is None:
        return
    if "1" not in req.protocols:
        raise LirisError(f"--export-loops {req.export_path}", "needs --protocol 1")
    if req.export_path.suffix.lower() not in (".g2o", ".tum", ".txt"):
        raise LirisError(f"--export-loops {req.export_path}",
                         "use a .g2o, .tum or .txt file name")


def run_sequence(req: EvalRequest) -> None:
    """Evaluate, write and print one within-sequence run (the mode ``sequence``)."""
    if req.seeds is not None:
        req.refuse_convention_band()  # the band is one matching pass, not one per seed
    settings = req.settings
    sensor, descriptors = sequence_descriptors(req)
    check_request(descriptors, req.protocols, settings)
    check_export_path(req)
    sequence = req.sequences[0]
    seq = open_input(sequence, req.reader_options)
    descriptors += load_externals(req.externals, req.external_metric, seq)
    descriptors = bind_exclusion(descriptors, settings.exclude)  # local maps: window = E
    check_request(descriptors, req.protocols, settings)
    for d in descriptors:
        d.check_inputs(seq)
    vertices = read_odometry(req.odometry_path, seq) if req.odometry_path is not None else None
    out = req.out if req.out is not None else default_run_dir(seq.name)
    check_run_dir(out, req.overwrite)
    if req.export_path is not None:
        check_new_files(loop_export_paths(req.export_path, [d.name for d in descriptors]),
                        req.overwrite, "--export-loops", inputs=[sequence])

    cache = req.cache()
    with open_executor(check_scheduler(req.scheduler), req.workers) as executor:
        def run_once(descs):
            return evaluate(seq, descs, req.protocols, settings, cache=cache,
                            workers=req.workers, progress=not req.quiet, executor=executor,
                            loop_settings=req.loop_settings, ranking=req.ranking,
                            convention_band=req.convention_band,
                            dbs=extract_all(seq, descs, cache, req.workers, req.quiet,
                                            executor))

        if req.seeds is None:
            run = run_once(descriptors)
        else:  # issue 23: stochastic stages once per seed, mean and range in each row
            from lidar_iris_eval.evaluation.seeds import evaluate_seeds

            run = evaluate_seeds(run_once, descriptors, req.seeds)
        engine_info = executor.run_config()
    extra = {**req.config_extra(), "engine": engine_info, "odometry": req.odometry,
             **({"odometry_file": str(req.odometry_path)}
                if req.odometry_path is not None else {}),
             **({"seeds": list(req.seeds)} if req.seeds is not None else {})}
    write_run(run, out, req.overwrite, sensor=sensor, reader_options=req.reader_options,
              **extra)
    if req.export_path is not None and req.odometry != "gt":  # .g2o vertices: same odometry
        from lidar_iris_eval.localmaps.odometry import estimate_odometry

        vertices = estimate_odometry(seq, req.odometry, progress=not req.quiet).poses
    exported = export_loops(run, req.export_path, vertices) if req.export_path is not None \
        else {}
    if req.as_json:
        echo_json(json_ready({**run.header(run.config(sensor=sensor,
                                                      reader_options=req.reader_options,
                                                      **extra)),
                              "results": run.rows}))
        return
    _print_run(req, run, out)
    for name, (path, count) in exported.items():
        click.echo(f"{name}: {count} accepted loops written to {path}")


def _print_run(req: EvalRequest, run, out) -> None:
    """The summary table, the convention band, the conventions line and the loop poses."""
    settings, conv, fmt = req.settings, req.convention, req.fmt
    click.echo(render_table(run.rows, fmt))
    band = render_band_table(run.rows, fmt)
    if band:
        click.echo(band, err=fmt != "table")
    click.echo(  # after a Markdown/LaTeX/CSV table, to stderr: the table stays pasteable
        f"conventions: radius {settings.radius:g} m, exclude "
        + (f"E={settings.exclude} ({settings.exclude_name})" if settings.exclude_seconds is None
           else f"{conv.exclude_seconds:g} s by scan time")
        + f", {settings.distance} distance, {run.pose_frame}-frame poses, "
        f"protocol 1 recall denominator '{settings.recall_denominator}', convention "
        f"{conv.name}; results in {out}", err=fmt != "table")
    print_loop_poses(run, fmt)


def print_loop_poses(run, fmt: str) -> None:
    """The loop-pose table (registration recall, refined errors, registration time), and
    one n/a line per method that has no point clouds to register."""
    from lidar_iris_eval.runs.loop_table import render_loop_table, render_seed_table

    for text in (render_loop_table(run.rows, fmt), render_seed_table(run.rows, fmt)):
        if text:
            click.echo(text, err=fmt != "table")
    for row in run.rows:
        for key in ("refine_note", "gt_pose_note"):
            if row.get(key):
                click.echo(f"{row['descriptor']}: {row[key]}")


__all__ = ["check_export_path", "print_loop_poses", "run_sequence", "sequence_descriptors"]
