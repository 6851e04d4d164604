"""``liris eval`` on several sequences (or a ``--plan`` file): one folder, one summary.

The plan format and the summary are described in :mod:`lidar_iris_eval.runs.plan`.
Each sequence gets an ordinary run folder inside the parent (written by
:func:`~lidar_iris_eval.runs.writer.write_run`), so ``liris show`` and
``liris plot`` read them as usual. The parent is assembled in a temporary
folder and renamed into place at the end; an existing folder is replaced
only with ``--overwrite``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import click

from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.output import format_table
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.runs.plan import (
    SUMMARY_COLUMNS,
    PlannedRun,
    run_folder_names,
    summary_csv,
    summary_markdown,
    summary_rows,
    write_text_atomic,
)


def run_many(req: EvalRequest) -> Path:
    """SEQUENCE... or ``--plan``: every planned run into one folder (the mode ``many``)."""
    from lidar_iris_eval.runs.plan import read_plan, runs_from_sequences

    req.refuse_convention_band()
    if req.loop_settings.registers or req.odometry_path is not None or req.seeds is not None:
        raise LirisError("--refine/--gt-pose/--odometry/--seeds",
                         "apply to a single sequence only")
    if req.plan is not None and req.sequences:
        raise LirisError("--plan", "give either sequences or --plan FILE, not both")
    if req.plan is None and not req.sequences:
        raise LirisError("SEQUENCE", "give a sequence, several, or --plan FILE")
    if req.export_path is not None or req.as_json:
        raise LirisError("--export-loops/--json", "apply to a single sequence only")
    if req.pairs_text is not None or req.ranking:  # were ignored without a word
        raise LirisError("--pairs/--ranking", "apply to a single sequence only")
    runs = (read_plan(req.plan, req.descriptor_text, req.protocols) if req.plan is not None
            else runs_from_sequences(req.sequences, req.descriptor_text, req.protocols))
    return evaluate_many(runs, req)


def evaluate_many(runs: list[PlannedRun], req: EvalRequest) -> Path:
    """Evaluate every planned run under one scheduler; returns the parent folder."""
    from lidar_iris_eval.cli.descriptor_options import build_descriptors, open_input
    from lidar_iris_eval.cli.workflow import extract_all
    from lidar_iris_eval.evaluation.evaluate import bind_exclusion, check_request, evaluate
    from lidar_iris_eval.ownership import check_replaceable, replace_folder, write_manifest
    from lidar_iris_eval.runs.writer import RUN_KINDS, check_run_dir, default_run_dir, write_run

    settings, cache, workers, quiet = req.settings, req.cache(), req.workers, req.quiet
    scheduler, sensor, reader_options = req.scheduler, req.sensor, req.reader_options
    overwrite, odometry = req.overwrite, req.odometry
    check_scheduler(scheduler)
    # everything is validated before any work: paths, descriptors, protocols, inputs
    prepared = []
    for run in runs:
        if not run.sequence.exists():
            raise LirisError(str(run.sequence), "no such sequence")
        seq = open_input(run.sequence, reader_options)
        descriptors = build_descriptors(run.descriptors, req.preset, sensor, req.params,
                                        odometry)
        protocols = check_request(descriptors, run.protocols, settings)
        for d in descriptors:
            d.check_inputs(seq)
        prepared.append((seq, descriptors, protocols))
    out = Path(req.out) if req.out is not None else default_run_dir("multi")
    check_run_dir(out, overwrite)
    names = run_folder_names(runs, [seq.name for seq, _, _ in prepared])
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    per_run = []
    try:
        with open_executor(scheduler, workers) as executor:
            engine_info = executor.run_config()
            for name, (seq, descriptors, protocols) in zip(names, prepared, strict=True):
                if not quiet:
                    click.echo(f"{name}: {', '.join(d.name for d in descriptors)}, "
                               f"protocol {' and '.join(map(str, protocols))}", err=True)
                descriptors = bind_exclusion(descriptors, settings.exclude)
                result = evaluate(seq, descriptors, protocols, settings, cache=cache,
                                  workers=workers, progress=not quiet, executor=executor,
                                  dbs=extract_all(seq, descriptors, cache, workers, quiet,
                                                  executor))
                write_run(result, tmp / name, sensor=sensor, reader_options=reader_options,
                          engine=engine_info, odometry=odometry)
                per_run.append((name, result.rows))
        rows = summary_rows(per_run)
        write_text_atomic(tmp / "summary.csv", summary_csv(rows))
        write_text_atomic(tmp / "summary.md", summary_markdown(rows))
        write_manifest(tmp, "multi")
        if out.exists() or out.is_symlink():  # check_run_dir allowed it: --overwrite was given
            check_replaceable(out, RUN_KINDS)  # again: a file may have been added meanwhile
        replace_folder(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    click.echo(format_table([{c: _short(r.get(c)) for c in SUMMARY_COLUMNS} for r in rows]))
    click.echo(f"{len(runs)} sequence runs in {out} (summary.csv, summary.md)", err=True)
    return out


def _short(value):
    if value is None or (isinstance(value, float) and value != value):
        return "n/a"
    return round(value, 3) if isinstance(value, float) else value
