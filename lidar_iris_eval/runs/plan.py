"""Several sequences × descriptors × protocols in one run folder, with a summary table.

``liris eval SEQ1 SEQ2 ... --protocol ... -d ...`` evaluates the same
descriptors and protocols on every sequence; ``liris eval --plan plan.yaml``
reads the combinations from a file, either as a cross product::

    sequences: [data/kitti/00, data/kitti/05, data/mulran/dcc01]
    descriptors: [lidar-iris, scan-context:exhaustive, m2dp]
    protocols: [1, 2]

or as a list of runs, each naming its own (missing keys fall back to the
top level, then to the command line)::

    protocols: [2]
    runs:
      - {sequence: data/kitti/00, descriptors: [lidar-iris, scan-context]}
      - {sequence: data/kitti/08, descriptors: lidar-iris, protocols: [1, 2]}

Relative sequence paths are read relative to the plan file. Everything
runs under one scheduler (``--scheduler``: a Dask cluster serves all of
them). The run folder holds one ordinary run folder per sequence
(``NN-<name>/``, as ``liris eval`` writes for one sequence) plus
``summary.csv`` and ``summary.md``: one row per sequence, descriptor and
protocol with AP, F1max, R@100P and EP.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from lidar_iris_eval.atomic import atomic_write
from lidar_iris_eval.errors import LirisError

SUMMARY_COLUMNS = ("sequence", "protocol", "descriptor", "preset", "ap", "f1_max", "r100p", "ep",
                   "n_positives")
_PLAN_KEYS = {"sequences", "descriptors", "protocols", "runs"}
_RUN_KEYS = {"sequence", "descriptors", "protocols"}


@dataclass(frozen=True)
class PlannedRun:
    """One sequence with its descriptors (``--descriptor`` text) and protocols."""

    sequence: Path
    descriptors: str
    protocols: tuple[str, ...]


def _descriptor_text(value: Any, source: str) -> str:
    if isinstance(value, str) and value.strip():
        return value
    if isinstance(value, list) and value and all(isinstance(v, str) for v in value):
        return ",".join(value)
    raise LirisError(source, "descriptors must be a name, a comma list or a list of names")


def _protocols(value: Any, source: str) -> tuple[str, ...]:
    items = value if isinstance(value, list) else [value]
    out = tuple(str(v) for v in items)
    if not out or not set(out) <= {"1", "2"}:
        raise LirisError(source, "protocols must be 1, 2 or a list of them")
    return tuple(sorted(set(out)))


def read_plan(path: str | os.PathLike, descriptors: str | None,
              protocols: tuple[str, ...]) -> list[PlannedRun]:
    """The runs of a plan file; ``descriptors``/``protocols`` are the command line's defaults."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as err:
        raise LirisError(str(path), f"cannot read the plan: {err.strerror or err}") from None
    except yaml.YAMLError as err:
        raise LirisError(str(path), f"not valid YAML: {err}") from None
    if not isinstance(data, dict) or not data:
        raise LirisError(str(path), "a plan is a mapping with sequences/descriptors/protocols "
                                    "or a runs: list")
    unknown = set(data) - _PLAN_KEYS
    if unknown:
        raise LirisError(str(path), f"unknown key(s) {', '.join(sorted(unknown))}; "
                                    f"use {', '.join(sorted(_PLAN_KEYS))}")
    base = path.parent
    top_desc = data.get("descriptors", descriptors)
    top_prot = data.get("protocols", list(protocols) if protocols else None)
    entries: list[dict] = []
    if "runs" in data:
        if "sequences" in data:
            raise LirisError(str(path), "give either sequences: or runs:, not both")
        if not isinstance(data["runs"], list) or not data["runs"]:
            raise LirisError(f"{path}: runs", "must be a non-empty list")
        for i, entry in enumerate(data["runs"]):
            if not isinstance(entry, dict) or "sequence" not in entry:
                raise LirisError(f"{path}: runs[{i}]", "each run needs a sequence:")
            bad = set(entry) - _RUN_KEYS
            if bad:
                raise LirisError(f"{path}: runs[{i}]", f"unknown key(s) {', '.join(sorted(bad))}")
            entries.append(entry)
    else:
        seqs = data.get("sequences")
        if not isinstance(seqs, list) or not seqs:
            raise LirisError(f"{path}: sequences", "must be a non-empty list of paths")
        entries = [{"sequence": s} for s in seqs]
    runs = []
    for i, entry in enumerate(entries):
        where = f"{path}: run {i + 1}"
        desc = entry.get("descriptors", top_desc)
        prot = entry.get("protocols", top_prot)
        if desc is None:
            raise LirisError(where, "no descriptors (in the plan or --descriptor)")
        if prot is None:
            raise LirisError(where, "no protocols (in the plan or --protocol)")
        seq = Path(str(entry["sequence"])).expanduser()
        runs.append(PlannedRun(seq if seq.is_absolute() else base / seq,
                               _descriptor_text(desc, where), _protocols(prot, where)))
    return runs


def runs_from_sequences(sequences, descriptors: str, protocols) -> list[PlannedRun]:
    """The same descriptors and protocols on every sequence of the command line."""
    prot = _protocols(list(protocols), "--protocol")
    return [PlannedRun(Path(s), descriptors, prot) for s in sequences]


def run_folder_names(runs: list[PlannedRun], names: list[str]) -> list[str]:
    """``NN-<sequence name>`` per run (numbered: one sequence may appear twice)."""
    width = max(2, len(str(len(runs))))
    return [f"{i + 1:0{width}d}-{name}" for i, name in enumerate(names)]


def summary_rows(per_run: list[tuple[str, list[dict]]]) -> list[dict]:
    """One row per sequence, descriptor and protocol, from each run's metric rows."""
    rows = []
    for label, metric_rows in per_run:
        for r in metric_rows:
            rows.append({"sequence": label, **{k: r.get(k) for k in SUMMARY_COLUMNS[1:]}})
    return rows


def _cell(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return "n/a" if value != value else f"{value:.3f}"
    return str(value)


def summary_markdown(rows: list[dict]) -> str:
    """The summary as a Markdown table (undefined values as n/a)."""
    lines = ["| " + " | ".join(SUMMARY_COLUMNS) + " |",
             "|" + "---|" * len(SUMMARY_COLUMNS)]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in SUMMARY_COLUMNS) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def summary_csv(rows: list[dict]) -> str:
    """The summary as CSV (full precision, empty cells for undefined values)."""
    def cell(v):
        if v is None or (isinstance(v, float) and v != v):
            return ""
        return repr(v) if isinstance(v, float) else str(v)

    lines = [",".join(SUMMARY_COLUMNS)]
    lines += [",".join(cell(r.get(c)) for c in SUMMARY_COLUMNS) for r in rows]
    return "\n".join(lines) + "\n"


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (:func:`lidar_iris_eval.atomic.atomic_write`)."""
    atomic_write(path, text)
