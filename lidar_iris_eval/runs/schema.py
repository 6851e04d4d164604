"""What a run's ``metrics.json`` must hold: one check, applied when a run is read.

``show``, ``compare``, ``plot`` and ``report`` all read runs through
:func:`lidar_iris_eval.runs.reader.load_run`, which calls :func:`check_metrics`
first, so a hand-edited or foreign file (``"ap": "high"``, ``"protocol":
"one"``) is one error naming the file and the key, not a traceback deep in a
table or a figure.

Rules:

* ``results`` is a list of mappings, each with ``protocol`` 1, 2 or
  ``"cross-session"`` and a
  non-empty text ``descriptor`` (``preset`` is text when present);
* a metric (:data:`NUMBER_KEYS`, or a key with a prefix of
  :data:`NUMBER_PREFIXES`) is a finite number or null (undefined, never 0);
* ``conventions`` and ``sequence`` are mappings when present;
* a result's ``convention_band`` (``liris eval --convention-band``), when
  present, is a mapping whose ``metrics`` map each metric to ``own``, ``min``
  and ``max`` numbers (or null, in the metric's range) and whose ``values``
  map each preset to its metrics; runs without it read as before;
* a result's ``warnings`` (the warnings that qualify its numbers, e.g. a
  degenerate descriptor, see :mod:`lidar_iris_eval.descriptors.sanity`) is a
  list of text when present; :func:`result_warnings` lists them for ``show``,
  ``compare`` and ``report``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from lidar_iris_eval.errors import LirisError

#: result keys that hold a number (or null)
NUMBER_KEYS = frozenset({
    "ap", "f1_max", "f1_threshold", "r100p", "ep", "p_at_lowest_recall",
    "extract_ms_per_scan", "match_ms_per_query", "match_us_per_pair",
})
#: result keys starting with one of these hold a number (or null) too
NUMBER_PREFIXES = ("n_", "top1_", "recall_at_", "rre_", "rte_")
#: result keys that hold a list of numbers (or nulls): the Recall@1..N curve
NUMBER_LIST_KEYS = frozenset({"recall_at_n"})


#: number keys that are fractions in [0, 1] (precision, recall, F1 and their kin)
FRACTION_KEYS = frozenset({"ap", "f1_max", "r100p", "ep", "p_at_lowest_recall"})
FRACTION_PREFIXES = ("recall_at_", "top1_")
#: number keys (and prefixes) that are counts, times or errors: never negative
NONNEGATIVE_KEYS = frozenset({"extract_ms_per_scan", "match_ms_per_query", "match_us_per_pair"})
NONNEGATIVE_PREFIXES = ("n_", "rre_", "rte_")


def range_problem(key: str, value: Any) -> str | None:
    """Why number ``value`` of result key ``key`` is out of its range, or None."""
    if value is None:
        return None
    if not math.isfinite(value):
        return f"{value!r} is not a finite number"
    if key in FRACTION_KEYS or key in NUMBER_LIST_KEYS or key.startswith(FRACTION_PREFIXES):
        if not 0.0 <= value <= 1.0:
            return f"{value!r} is outside [0, 1]"
    elif (key in NONNEGATIVE_KEYS or key.startswith(NONNEGATIVE_PREFIXES)) and value < 0:
        return f"{value!r} is negative"
    return None


#: what a result row's ``protocol`` may be (cross-session: docs/cross-session.md)
PROTOCOLS = (1, 2, "cross-session")


def is_number_key(key: str) -> bool:
    """True for the result keys that must hold a number or null."""
    return key in NUMBER_KEYS or key.startswith(NUMBER_PREFIXES)


def check_metrics(metrics: Any, path: str | Path) -> None:
    """Raise one :class:`LirisError` naming ``path`` and the key when ``metrics`` is malformed."""
    if not isinstance(metrics, dict) or not isinstance(metrics.get("results"), list):
        raise LirisError(path, "no 'results' list; not written by liris eval")
    for k, row in enumerate(metrics["results"]):
        where = f"results[{k}]"
        if not isinstance(row, dict) or "protocol" not in row or "descriptor" not in row:
            raise LirisError(path, "every result needs 'protocol' and 'descriptor'")
        protocol = row["protocol"]
        if isinstance(protocol, bool) or protocol not in PROTOCOLS:
            raise LirisError(path, f"{where}.protocol: expected 1, 2 or 'cross-session', "
                                   f"got {protocol!r}")
        if not isinstance(row["descriptor"], str) or not row["descriptor"]:
            raise LirisError(path, f"{where}.descriptor: expected a name, got "
                                   f"{row['descriptor']!r}")
        if "preset" in row and not isinstance(row["preset"], (str, type(None))):
            raise LirisError(path, f"{where}.preset: expected text, got {row['preset']!r}")
        warnings = row.get("warnings", [])
        if not isinstance(warnings, list) or not all(isinstance(w, str) for w in warnings):
            raise LirisError(path, f"{where}.warnings: expected a list of text, got "
                                   f"{warnings!r}")
        for key, value in row.items():
            if key in NUMBER_LIST_KEYS:
                if not isinstance(value, list) or not all(map(_number_or_null, value)):
                    raise LirisError(path, f"{where}.{key}: expected a list of numbers or "
                                           f"nulls, got {value!r}")
                values = value
            elif is_number_key(key):
                if not _number_or_null(value):
                    raise LirisError(path, f"{where}.{key}: expected a number or null, got "
                                           f"{value!r}")
                values = [value]
            else:
                continue
            for item in values:
                problem = range_problem(key, item)
                if problem is not None:
                    raise LirisError(path, f"{where}.{key}: {problem} (not written by liris "
                                           "eval, or edited)")
        if "convention_band" in row:
            _check_band(row["convention_band"], path, f"{where}.convention_band")
    for key in ("conventions", "sequence"):
        if key in metrics and not isinstance(metrics[key], dict):
            raise LirisError(path, f"{key}: expected a mapping, got {metrics[key]!r}")


def _check_band(band: Any, path: str | Path, where: str) -> None:
    """The ``convention_band`` entry of a result row (see the module docstring)."""
    if not isinstance(band, dict) or not isinstance(band.get("metrics"), dict) \
            or not isinstance(band.get("values", {}), dict):
        raise LirisError(path, f"{where}: expected a mapping with 'metrics' and 'values'")
    checks = [(f"{where}.metrics.{metric}.{part}", metric, entry.get(part) if
               isinstance(entry, dict) else entry)
              for metric, entry in band["metrics"].items() for part in ("own", "min", "max")]
    checks += [(f"{where}.values.{preset}.{metric}", metric, value)
               for preset, values in band.get("values", {}).items()
               for metric, value in (values.items() if isinstance(values, dict)
                                     else [("?", values)])]
    for at, metric, value in checks:
        if not _number_or_null(value):
            raise LirisError(path, f"{at}: expected a number or null, got {value!r}")
        problem = range_problem(metric, value)
        if problem is not None:
            raise LirisError(path, f"{at}: {problem} (not written by liris eval, or edited)")


def result_warnings(rows: list[dict[str, Any]]) -> list[str]:
    """``"<descriptor>: <warning>"`` once per descriptor and warning, in row order."""
    out: list[str] = []
    for row in rows:
        for text in row.get("warnings") or []:
            line = f"{row.get('descriptor')}: {text}"
            if line not in out:
                out.append(line)
    return out


def _number_or_null(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return math.isfinite(value)
