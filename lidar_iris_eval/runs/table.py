"""The metrics table of a run, in the formats a paper or a spreadsheet wants.

``liris eval`` prints its summary through :func:`render_table` and
``liris show`` prints a finished run through the same function, so the two
cannot drift apart: a row from memory and the same row read back from
``metrics.json`` give the same text (NumPy scalars and NaN are normalised to
what JSON holds before formatting).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

from lidar_iris_eval.errors import LirisError

#: columns of the summary table, in order
TABLE_COLUMNS = ("protocol", "descriptor", "preset", "ap", "f1_max", "r100p", "ep", "n",
                 "positives", "extract_ms_per_scan", "match_time")
#: ranking columns, added when a row has them (cross-session runs, liris eval --ranking)
RANKING_COLUMNS = ("recall_at_1", "recall_at_1pct", "mrr")
#: output formats of :func:`render_table`
FORMATS = ("table", "markdown", "latex", "csv")


def _plain(value: Any) -> Any:
    """NumPy scalars to Python, NaN/inf to None (what ``metrics.json`` holds)."""
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def table_row(row: Mapping[str, Any]) -> dict[str, Any]:
    """The summary columns of one ``metrics.json`` result row."""
    p1 = row.get("protocol") in (1, "cross-session")  # one best match per query
    if p1:
        t = _plain(row.get("match_ms_per_query"))
        match_time = None if t is None else f"{t:.3f} ms/query"
    else:
        t = _plain(row.get("match_us_per_pair"))
        match_time = None if t is None else f"{t:.3f} us/pair"
    out = {k: _plain(row.get(k)) for k in ("protocol", "descriptor", "preset", "ap", "f1_max",
                                            "r100p", "ep")}
    out["n"] = _plain(row.get("n_queries") if p1 else row.get("n_pairs"))
    out["positives"] = _plain(row.get("n_positives"))
    out["extract_ms_per_scan"] = _plain(row.get("extract_ms_per_scan"))
    out["match_time"] = match_time
    # --refine (issue 23): registration time per loop, a column only when some row has it
    out["register_ms_per_loop"] = _plain(row.get("registration_ms_per_loop"))
    for key in RANKING_COLUMNS:
        if key in row:
            out[key] = _plain(row.get(key))
    return out


def cell(value: Any) -> str:
    """Text of one cell: thousands separators, 4 decimals, 'n/a' when undefined."""
    value = _plain(value)
    if value is None:
        return "n/a"  # an undefined metric, never 0 (as cli/output.format_value)
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:.4f}" if abs(value) < 1e4 else f"{value:,.0f}"
    return str(value)


def render_table(rows: Sequence[Mapping[str, Any]], fmt: str = "table",
                 columns: Sequence[str] = TABLE_COLUMNS, summarize: bool = True) -> str:
    """Rows as text in ``fmt``: ``table`` (aligned), ``markdown``, ``latex`` or ``csv``.

    With ``summarize`` (the default) each row is first reduced to the summary
    columns by :func:`table_row`; pass ``summarize=False`` for rows that
    already hold ``columns``. CSV keeps full precision; the other formats
    round as :func:`cell` does.
    """
    if fmt not in FORMATS:
        raise LirisError(f"--format {fmt}", f"choose from {', '.join(FORMATS)}")
    table = [table_row(r) if summarize else {c: _plain(r.get(c)) for c in columns}
             for r in rows]
    standard = summarize and tuple(columns) == TABLE_COLUMNS
    columns = list(columns)
    if summarize and any(r.get("register_ms_per_loop") is not None for r in table):
        columns.append("register_ms_per_loop")
    if standard:
        columns += [k for k in RANKING_COLUMNS if any(k in r for r in table)]
    if fmt == "csv":
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(columns)
        for r in table:
            writer.writerow(["" if r.get(c) is None else r.get(c) for c in columns])
        return buffer.getvalue().rstrip("\n")
    cells = [[cell(r.get(c)) for c in columns] for r in table]
    if fmt == "markdown":
        numeric = [_numeric(table, c) for c in columns]
        lines = ["| " + " | ".join(columns) + " |",
                 "|" + "|".join("---:" if n else "---" for n in numeric) + "|"]
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in cells]
        return "\n".join(lines)
    if fmt == "latex":
        align = "".join("r" if _numeric(table, c) else "l" for c in columns)
        lines = [f"\\begin{{tabular}}{{{align}}}", "\\hline",
                 " & ".join(_latex(c) for c in columns) + " \\\\", "\\hline"]
        lines += [" & ".join(_latex(c) for c in row) + " \\\\" for row in cells]
        lines += ["\\hline", "\\end{tabular}"]
        return "\n".join(lines)
    if not cells:
        return "(no rows)"
    widths = [max(len(c), *(len(r[k]) for r in cells)) for k, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.rjust(w) for v, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(lines)


def _numeric(table: list[dict], column: str) -> bool:
    values = [r.get(column) for r in table if r.get(column) is not None]
    return bool(values) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                for v in values)


_LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#",
                  "_": r"\_", "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}",
                  "^": r"\textasciicircum{}"}


def _latex(text: str) -> str:
    return "".join(_LATEX_SPECIAL.get(ch, ch) for ch in text)


def conventions_lines(conventions: Mapping[str, Any], config: Mapping[str, Any] | None = None
                      ) -> list[str]:
    """The run's conventions in words, one per line (what ``liris show`` prints)."""
    c = dict(conventions)
    config = dict(config or {})
    lines = []
    name = c.get("convention") or config.get("convention")
    if name:
        lines.append(f"convention preset: {name}")
    radius = c.get("radius")
    lines.append("positive: " + (c.get("positive") or f"ground-truth distance < {radius} m"))
    exclude = c.get("exclude")
    window = c.get("exclude_seconds")
    if c.get("exclusion"):  # a cross-session run
        lines.append(f"exclusion: {c['exclusion']}")
    elif window is not None:
        lines.append(f"exclusion: {window:g} s by scan time")
    else:
        lines.append(f"exclusion: E={exclude} frames ({c.get('exclude_preset', 'custom')}); "
                     f"query i searches j <= i - E")
    lines.append(f"distance: {c.get('distance')}, {c.get('pose_frame')}-frame poses")
    lines.append(f"protocol 1 recall denominator: {c.get('recall_denominator')}")
    candidates = c.get("candidates")
    lines.append("protocol 1 search: " + ("exhaustive" if candidates is None
                                          else f"descriptor retrieval, {candidates} candidates"))
    for key in ("not_revisit_band", "query_range", "alignment", "ranking", "top1_pr",
                "threshold_rule", "ap", "ep", "protocol2_counts", "reverse_revisit"):
        if c.get(key) is not None:
            lines.append(f"{key.replace('_', ' ')}: {c[key]}")
    sequence = config.get("sequence") or {}
    if sequence:
        label = "query session" if config.get("database") else "sequence"
        lines.append(f"{label}: {sequence.get('name')} ({sequence.get('n_frames')} frames, "
                     f"fingerprint {sequence.get('fingerprint')})")
    database = config.get("database") or {}
    if database:
        lines.append(f"database session: {database.get('name')} ({database.get('n_frames')} "
                     f"frames, fingerprint {database.get('fingerprint')})")
    return lines


#: metrics shown by :func:`render_band_table` (``--convention-band``)
BAND_COLUMNS = ("ap", "f1_max", "r100p", "ep")


def band_cell(entry: Mapping[str, Any] | None) -> str:
    """``own [min–max]`` of one metric's band entry (``n/a`` parts when undefined)."""
    if not entry:
        return "n/a"
    return f"{cell(entry.get('own'))} [{cell(entry.get('min'))}–{cell(entry.get('max'))}]"


def band_rows(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per protocol 1 result with a ``convention_band``: each metric as
    :func:`band_cell`, the number of presets and the extremes' presets of AP."""
    out = []
    for row in rows:
        band = row.get("convention_band")
        if not isinstance(band, Mapping):
            continue
        metrics = band.get("metrics") or {}
        ap = metrics.get("ap") or {}
        out.append({"descriptor": row.get("descriptor"), "convention": band.get("own_convention"),
                    **{k: band_cell(metrics.get(k)) for k in BAND_COLUMNS},
                    "presets": len(band.get("presets") or []),
                    "ap_min_at": ap.get("min_preset"), "ap_max_at": ap.get("max_preset")})
    return out


def render_band_table(rows: Sequence[Mapping[str, Any]], fmt: str = "table") -> str:
    """The convention band of a run's protocol 1 rows ('' when none has one)."""
    table = band_rows(rows)
    if not table:
        return ""
    columns = ("descriptor", "convention", *BAND_COLUMNS, "presets", "ap_min_at", "ap_max_at")
    text = render_table(table, fmt, columns, summarize=False)
    return text if fmt in ("csv", "latex") else \
        "convention band, protocol 1: own [min–max over presets]\n" + text
