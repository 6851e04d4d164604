"""Printing results for people (aligned tables) and machines (JSON)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import click

from lidar_iris_eval.atomic import atomic_write
from lidar_iris_eval.errors import LirisError, check_writable_dir, file_in_the_way


def format_value(value) -> str:
    """Compact text for a table cell: thousands separators, 4 significant decimals."""
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if math.isnan(value):
            return "n/a"  # an undefined metric, never 0
        return f"{value:.4f}" if abs(value) < 1e4 else f"{value:,.0f}"
    return str(value)


def format_table(rows: Sequence[dict], columns: Sequence[str] | None = None) -> str:
    """Rows of dicts as an aligned plain-text table."""
    if not rows:
        return "(no rows)"
    columns = list(columns or rows[0].keys())
    cells = [[format_value(row.get(c, "")) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[k]) for r in cells)) for k, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    for row in cells:
        lines.append("  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)))
    return "\n".join(lines)


def echo_table(rows: Sequence[dict], columns: Sequence[str] | None = None) -> None:
    click.echo(format_table(rows, columns))


def echo_json(data) -> None:
    click.echo(json.dumps(data, indent=2, sort_keys=False))


def check_output_file(path: Path, flag: str) -> Path:
    """Fail now, before any work, if ``path`` cannot be written as a file.

    A folder, a path under a file or a read-only location is reported as one
    line naming ``flag`` and the path as the user typed them.
    """
    path = Path(path)
    if path.is_dir():
        raise LirisError(f"{flag} {path}", "is a folder; give a file name")
    blocker = file_in_the_way(path.parent)
    if blocker is not None:
        raise LirisError(f"{flag} {path}", f"cannot be created: {blocker} is a file")
    check_writable_dir(path.parent, f"folder for {flag}")
    return path


def write_output_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temporary file + rename), umask permissions."""
    atomic_write(path, text)
