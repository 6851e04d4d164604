"""``liris show RUN``: a finished run's metrics table and conventions, nothing recomputed."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.runs import (
    FORMATS,
    conventions_lines,
    load_run,
    render_band_table,
    render_table,
)
from lidar_iris_eval.runs.schema import result_warnings


@click.command("show")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="table", show_default=True,
              help="Aligned table, or a Markdown / LaTeX / CSV table for a paper.")
@click.option("--no-conventions", is_flag=True,
              help="Print the metrics table only, without the loop-pose and seed tables and the "
                   "conventions (e.g. to paste it or pipe the CSV).")
def command(run, fmt, no_conventions):
    """Print the metrics table and the conventions of the run folder RUN.

    The table is the one `liris eval` printed for that run (same columns and
    rounding); CSV keeps full precision.
    """
    from lidar_iris_eval.runs.loop_table import (
        render_loop_table,
        render_loops_table,
        render_seed_table,
    )

    loaded = load_run(run)
    if not loaded.rows:
        from lidar_iris_eval.errors import LirisError

        raise LirisError(loaded.path / "metrics.json", "the run holds no results (an empty "
                         "'results' list): nothing to show")
    click.echo(render_table(loaded.rows, fmt))
    prefix = {"markdown": "- ", "latex": "% ", "csv": "# "}.get(fmt, "")
    for line in result_warnings(loaded.rows):  # stored with the numbers they qualify
        click.echo(f"{prefix}warning: {line}", err=fmt != "table")
    if no_conventions:  # the metrics table (and its warnings) only
        return
    loop_table = render_loop_table(loaded.rows, fmt)  # registration recall (issue 23)
    seed_table = render_seed_table(loaded.rows, fmt)  # --seeds: mean [min, max]
    loops_table = render_loops_table(loaded.rows, fmt)  # --loops files (docs/loops.md)
    band_table = render_band_table(loaded.rows, fmt)  # --convention-band: own [min–max]
    for extra in (loops_table, loop_table, seed_table, band_table):
        if extra:
            click.echo("")
            click.echo(extra)
    click.echo("")
    for line in conventions_lines(loaded.conventions, loaded.config):
        click.echo(prefix + line)
