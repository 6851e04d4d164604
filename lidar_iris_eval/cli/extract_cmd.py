"""``liris extract``: compute and cache descriptors of every scan of a sequence."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.cli.descriptor_options import (
    build_descriptors,
    descriptor_options,
    odometry_option,
    open_input,
    run_extraction,
)
from lidar_iris_eval.cli.output import echo_json, echo_table
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.extract import DEFAULT_CHUNK_SIZE
from lidar_iris_eval.sensors import resolve_sensor


@click.command("extract")
@click.argument("sequence", type=click.Path(path_type=Path))
@descriptor_options
@odometry_option
@click.option("--chunk-size", type=int, default=DEFAULT_CHUNK_SIZE, show_default=True,
              help="Scans per chunk (the unit saved as it goes, so a killed run resumes).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@click.option("--export-npy", "npy_dir", type=click.Path(path_type=Path), default=None,
              help="Also write each (N, D) descriptor array as DIR/<descriptor>.npy (the "
                   "format liris eval --external reads).")
def command(sequence, descriptor_text, preset, params, sensor, cache_dir, workers, quiet,
            chunk_size, as_json, reader_options, npy_dir, odometry):
    """Compute descriptors of every scan of SEQUENCE and store them in the cache.

    A second run with the same scans, descriptor parameters and liris version
    loads the cache and computes nothing.
    """
    if workers < 1:
        raise LirisError(f"--workers {workers}", "must be at least 1")
    if chunk_size < 1:
        raise LirisError(f"--chunk-size {chunk_size}", "must be at least 1")
    sensor = resolve_sensor(sensor, lambda: open_input(sequence, reader_options))
    descriptors = build_descriptors(descriptor_text, preset, sensor, params, odometry)
    seq = open_input(sequence, reader_options)
    for d in descriptors:  # every method's inputs before any work (e.g. labels/)
        d.check_inputs(seq)
    dbs = run_extraction(seq, descriptors, cache_dir, workers, quiet, chunk_size)
    if npy_dir is not None:  # issue 17: descriptors for --external
        from lidar_iris_eval.cli.workflow import export_npy

        for name, path in export_npy(dbs, npy_dir).items():
            click.echo(f"{name}: descriptors written to {path}", err=as_json)
    rows = [
        {
            "descriptor": db.descriptor,
            "preset": db.preset,
            "scans": len(db),
            "from_cache": db.from_cache,
            "reused_rows": db.reused_rows,  # from another frame selection's cached run
            "extract_ms_per_scan": db.extract_ms_per_scan,
            "cache_file": str(db.cache_path),
        }
        for db in dbs
    ]
    if as_json:
        echo_json({"sequence": str(sequence), "results": rows})
    else:
        echo_table(rows)
