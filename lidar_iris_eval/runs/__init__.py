"""Reading finished run folders (docs/results-format.md) without recomputing anything.

``liris show``, ``liris compare`` and ``liris report`` are thin layers over
this package, so a researcher's own script can do the same::

    from lidar_iris_eval.runs import load_run, render_table
    run = load_run("results/kitti00")
    print(render_table(run.rows, "markdown"))
"""

from lidar_iris_eval.runs.reader import Run, load_run
from lidar_iris_eval.runs.table import (
    FORMATS,
    TABLE_COLUMNS,
    conventions_lines,
    render_band_table,
    render_table,
    table_row,
)

__all__ = [
    "FORMATS",
    "TABLE_COLUMNS",
    "Run",
    "conventions_lines",
    "load_run",
    "render_band_table",
    "render_table",
    "table_row",
]
