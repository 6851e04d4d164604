"""Writing a run folder (the format is specified in docs/results-format.md).

``runs/`` owns the run folder: this writer, the reader (:mod:`.reader`),
replay, comparison and multi-run plans (:mod:`.plan`).

A run is assembled in a hidden temporary folder next to the target and moved
into place with one rename when everything is written, so a reader (or
``liris plot``) never sees half a run, and a failed or interrupted run leaves
the previous results untouched. An existing run is only replaced when the
caller asks for it (``overwrite=True``).

The temporary folder's name records the host and process that own it
(``.<name>.tmp-<host>-<pid>-<random>``); a writer starting next to it removes
those whose process is gone (killed with SIGKILL, no chance to clean up).
Folders get the permissions the umask allows, like ``mkdir`` would.

Nothing here computes metrics; it only lays out results computed elsewhere.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from lidar_iris_eval.cache import umask
from lidar_iris_eval.errors import LirisError, check_writable_dir, os_error
from lidar_iris_eval.evaluation.evaluate import Evaluation
from lidar_iris_eval.evaluation.metrics import PRCurve, reduce_curve
from lidar_iris_eval.evaluation.protocol1 import Protocol1Result
from lidar_iris_eval.evaluation.protocol2 import Protocol2Result
from lidar_iris_eval.lifetime import remove_stale_temps, temp_prefix
from lidar_iris_eval.ownership import check_replaceable, replace_folder, write_manifest

#: the folder kinds ``liris eval --overwrite`` may replace (see :mod:`lidar_iris_eval.ownership`)
RUN_KINDS = ("run", "multi")


def check_run_dir(out: str | os.PathLike, overwrite: bool) -> Path:
    """Refuse an existing run directory unless ``overwrite``; returns the path.

    ``overwrite`` only ever replaces a folder liris wrote with nothing added
    (:func:`~lidar_iris_eval.ownership.check_replaceable`): an input sequence
    or a folder holding a user's own file is refused, untouched.
    Also checks, before any work starts, that the folder can be created: a
    read-only location or a file in the way fails now, not after extraction.
    """
    out = Path(out)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise LirisError(out, "results directory already exists; pass --overwrite to replace it")
    if overwrite:
        check_replaceable(out, RUN_KINDS)
    elif out.exists() and not out.is_dir():
        raise LirisError(out, "exists and is not a directory")
    check_writable_dir(out, "run folder")
    return out


def default_run_dir(name: str, root: str | os.PathLike = "results") -> Path:
    """``<root>/<name>-<date>-<time>.<microseconds>``, unused at the time of the call.

    Microseconds keep two runs started in the same second apart (seconds did
    not); a name that still exists gets ``-2``, ``-3``... and a run that
    appears while this one works is never replaced (see :meth:`RunWriter.commit`).
    """
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S.%f")
    base = Path(root) / f"{name}-{stamp}"
    out, k = base, 1
    while out.exists():
        k += 1
        out = base.with_name(f"{base.name}-{k}")
    return out


class RunWriter:
    """Collects the files of one run in a temporary folder; :meth:`commit` publishes it.

    Use as a context manager: leaving the block normally commits, an
    exception discards the temporary folder.
    """

    def __init__(self, out: str | os.PathLike, overwrite: bool = False):
        self.out = check_run_dir(out, overwrite)
        self.overwrite = overwrite
        self.out.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(self.out.parent)
        prefix = temp_prefix(self.out.name)
        self.tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=self.out.parent))
        os.chmod(self.tmp, 0o777 & ~umask())  # mkdtemp makes 0700 whatever the umask

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            shutil.rmtree(self.tmp, ignore_errors=True)
            if isinstance(exc, OSError):  # name the run, not an anonymous temporary file
                raise os_error(exc, self.out, "cannot write the run folder") from None

    def path(self, relative: str) -> Path:
        target = self.tmp / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def write_text(self, relative: str, text: str) -> None:
        self.path(relative).write_text(text)

    def write_yaml(self, relative: str, data: Any) -> None:
        self.write_text(relative, yaml.safe_dump(json_ready(data), sort_keys=False))

    def write_json(self, relative: str, data: Any) -> None:
        self.write_text(relative, json.dumps(json_ready(data), indent=2, allow_nan=False) + "\n")

    def write_csv(self, relative: str, columns: dict[str, Any] | pd.DataFrame) -> None:
        table = columns if isinstance(columns, pd.DataFrame) else pd.DataFrame(columns)
        table.to_csv(self.path(relative), index=False)

    def write_npy(self, relative: str, array: np.ndarray) -> None:
        np.save(self.path(relative), np.asarray(array), allow_pickle=False)

    def commit(self) -> Path:
        """Move the finished run into place (replacing the old one if allowed).

        The folder's manifest is written last, listing every file; the old run
        is checked again (a file may have been added to it while this one ran).
        """
        try:
            write_manifest(self.tmp, "run")
            if self.out.exists() or self.out.is_symlink():
                if not self.overwrite:
                    raise LirisError(self.out,
                                     "results directory appeared while running; not replaced")
                check_replaceable(self.out, RUN_KINDS)
            replace_folder(self.tmp, self.out)
        except BaseException:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        return self.out


def pr_table(curve: PRCurve) -> dict[str, np.ndarray]:
    """Columns of ``pr.csv``: the loss-free reduced exact curve (see ``reduce_curve``)."""
    reduced = reduce_curve(curve)
    return {
        "threshold": reduced.threshold,
        "precision": reduced.precision,
        "recall": reduced.recall,
        "tp": reduced.tp,
        "fp": reduced.fp,
        "fn": reduced.fn,
    }


def write_protocol1(run: RunWriter, descriptor: str, result: Protocol1Result,
                    extra: dict[str, np.ndarray] | None = None) -> None:
    """``protocol1/<descriptor>/matches.csv`` (plus ``extra`` columns) and ``pr.csv``."""
    table = {**result.table(), **(extra or {})}
    for key in ("is_revisit", "is_true", "is_reverse"):
        if key in table:
            table[key] = np.asarray(table[key]).astype(np.int8)
    run.write_csv(f"protocol1/{descriptor}/matches.csv", table)
    run.write_csv(f"protocol1/{descriptor}/pr.csv", pr_table(result.curve))


def write_protocol2(run: RunWriter, descriptor: str, result: Protocol2Result) -> None:
    """``protocol2/<descriptor>/affinity.npy`` (when kept) and ``pr.csv``.

    A streamed pass may keep no matrix, or only a decimated one for figures
    (``affinity_decimated.npy``); ``metrics.json`` says which (``affinity_stored``).
    """
    if result.affinity.matrix is not None:
        run.write_npy(f"protocol2/{descriptor}/affinity.npy", result.affinity.matrix)
    decimated = getattr(result.affinity, "decimated", None)
    if decimated is not None:
        run.write_npy(f"protocol2/{descriptor}/affinity_decimated.npy", decimated)
    run.write_csv(f"protocol2/{descriptor}/pr.csv", pr_table(result.curve))


def write_timing(run: RunWriter, descriptor: str, extract_s: np.ndarray,
                 read_s: np.ndarray | None = None) -> None:
    """``timing/<descriptor>.csv``: scan, extract_s (and read_s)."""
    columns: dict[str, Any] = {"scan": np.arange(len(extract_s)), "extract_s": extract_s}
    if read_s is not None:
        columns["read_s"] = read_s
    run.write_csv(f"timing/{descriptor}.csv", columns)


def write_metrics(run: RunWriter, header: dict[str, Any], rows: list[dict[str, Any]]) -> None:
    """``metrics.json`` (header + results) and ``metrics.csv`` (the rows, flattened)."""
    run.write_json("metrics.json", {**header, "results": rows})
    table = pd.DataFrame([_flatten(r) for r in rows])
    run.write_csv("metrics.csv", table)


def _flatten(row: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in row.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        elif isinstance(value, list) and all(isinstance(v, str) for v in value):
            flat[f"{prefix}{key}"] = "; ".join(value)  # e.g. warnings
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def json_ready(value: Any) -> Any:
    """JSON/YAML-safe copy: NumPy scalars to Python, NaN/inf to None, tuples to lists."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_run(evaluation: Evaluation, out: str | os.PathLike, overwrite: bool = False,
              **config_extra) -> Path:
    """Write the run folder (docs/results-format.md) atomically; returns its path."""
    out = Path(out)
    config = evaluation.config(**config_extra)
    seq = evaluation.sequence
    poses = seq.camera_poses if evaluation.pose_frame == "camera" else seq.poses
    with RunWriter(out, overwrite) as run:
        for r in evaluation.results:
            if r.protocol1 is not None:
                write_protocol1(run, r.descriptor.name, r.protocol1,
                                r.loop_poses.columns() if r.loop_poses is not None else None)
            if r.protocol2 is not None:
                write_protocol2(run, r.descriptor.name, r.protocol2)
            write_timing(run, r.descriptor.name, r.db.extract_s, r.db.read_s)
            extra_files = getattr(r, "extra_files", None)  # e.g. a loop file's loops.csv
            for relative, columns in (extra_files() if extra_files is not None else {}).items():
                run.write_csv(relative, columns)
            if r.band is not None:  # --convention-band: each preset's curve, for the PR band
                for preset, curve in r.band[2].items():
                    run.write_csv(f"protocol1/{r.descriptor.name}/pr_convention-{preset}.csv",
                                  pr_table(curve))
        for (protocol, name), curves in evaluation.seed_curves.items():
            for seed, curve in curves:
                run.write_csv(f"protocol{protocol}/{name}/pr_seed{seed}.csv", pr_table(curve))
        run.write_yaml("config.yaml", config)
        write_metrics(run, evaluation.header(config), evaluation.rows)
        run.write_npy("poses.npy", np.asarray(poses, dtype=np.float64))
        run.write_npy("positions.npy", seq.positions(evaluation.pose_frame).astype(np.float64))
        times = getattr(seq, "times", None)
        if evaluation.settings.exclude_seconds is not None and times is not None:
            # a window in seconds: the reader rebuilds the run's queries from these
            run.write_npy("times.npy", np.asarray(times, dtype=np.float64))
    return out
