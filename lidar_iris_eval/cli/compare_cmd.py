"""``liris compare RUN_A RUN_B ...``: metrics side by side, differences, convention changes."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.atomic import figure_format
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.ownership import check_new_files
from lidar_iris_eval.runs import FORMATS, load_run, render_band_table, render_table
from lidar_iris_eval.runs.compare import (
    convention_differences,
    difference_summary,
    metric_comparison,
    plot_pr_overlay,
    run_labels,
)
from lidar_iris_eval.runs.schema import result_warnings


@click.command("compare")
@click.argument("runs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="table", show_default=True,
              help="Output format of the tables.")
@click.option("--plot", "plot_out", type=click.Path(path_type=Path), default=None,
              help="Also write the PR curves of all runs overlaid to this image (.png/.pdf/.svg).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --plot image.")
def command(runs, fmt, plot_out, overwrite):
    """Compare the metrics of two or more run folders.

    Each later run's difference to the first is shown per metric, and every
    convention or setting that differs between the runs (radius, exclusion,
    recall denominator, scans, descriptor parameters, ...) is listed, since
    such a difference changes what the numbers mean.
    """
    if len(runs) < 2:
        raise LirisError("compare", "give at least two run folders")
    if plot_out is not None:
        figure_format(plot_out, "--plot")  # a bad suffix fails before any work
        check_new_files([plot_out], overwrite, "--plot", inputs=runs)
    loaded = [load_run(r) for r in runs]
    labels = run_labels(loaded)
    rows = metric_comparison(loaded)
    columns = ["protocol", "descriptor", "preset", "metric", *labels,
               *[f"{lab} - {labels[0]}" for lab in labels[1:]]]
    click.echo(render_table(rows, fmt, columns=columns, summarize=False))
    click.echo("")
    click.echo(difference_summary(rows, labels))
    for run, label in zip(loaded, labels, strict=True):
        for line in result_warnings(run.rows):  # warnings that qualify a run's numbers
            click.echo(f"warning ({label}): {line}")
    for run, label in zip(loaded, labels, strict=True):  # --convention-band runs
        band = render_band_table(run.rows, fmt)
        if band:
            click.echo(f"{label}: {band}")
    differences = convention_differences(loaded)
    if differences:
        click.echo("conventions and settings that differ (the numbers are not like for like):")
        click.echo(render_table(differences, fmt, columns=["setting", *labels], summarize=False))
    else:
        click.echo("conventions and settings: identical")
    if plot_out is not None:
        click.echo(f"PR curves: {plot_pr_overlay(loaded, plot_out)}")
