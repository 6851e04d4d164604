"""One run folder as a Python object: config, metrics rows and per-descriptor files.

The one reader of run folders (docs/results-format.md): ``liris show``,
``compare``, ``report`` and ``plot`` all open runs through :func:`load_run`.
Files are read lazily (an affinity matrix can be hundreds of megabytes), and a
missing or malformed file is a :class:`~lidar_iris_eval.errors.LirisError`
naming it, so the CLI reports it in one line. Files a run may lack (matches,
timing, affinity) can be asked for with ``required=False``, which returns
``None`` instead of raising, so a figure or page can skip that part.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from lidar_iris_eval.errors import LirisError, warn
from lidar_iris_eval.runs.schema import check_metrics

#: columns a reader of each table relies on (more may be present)
PR_COLUMNS = ("threshold", "precision", "recall")
MATCH_COLUMNS = ("query", "match", "distance", "is_revisit", "is_true")
TIMING_COLUMNS = ("scan", "extract_s")


@dataclass
class Run:
    """A finished run folder.

    Attributes
    ----------
    path : the run folder.
    config : ``config.yaml`` as a dict (empty when the file is absent).
    metrics : ``metrics.json`` as a dict (header, conventions and ``results``).
    name : the run's label; the folder name unless set (``liris plot --compare``
        sets ``parent/folder`` when two runs share a folder name).
    """

    path: Path
    config: dict[str, Any]
    metrics: dict[str, Any]
    name: str = ""
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if not self.name:
            self.name = self.path.name

    # ---- metrics.json --------------------------------------------------------------
    @property
    def rows(self) -> list[dict[str, Any]]:
        """One metrics row per protocol and descriptor, as written by ``liris eval``."""
        return list(self.metrics.get("results", []))

    @property
    def conventions(self) -> dict[str, Any]:
        """The ground-truth and metric conventions the run was evaluated under."""
        return dict(self.metrics.get("conventions", {}))

    def protocols(self) -> list[int]:
        """The protocols the run has results for, ascending."""
        return sorted({int(r["protocol"]) for r in self.rows})

    def descriptors(self, protocol: int | None = None) -> list[str]:
        """Descriptors that have results (for ``protocol``, or any), in run order."""
        names: list[str] = []
        for r in self.rows:
            if (protocol is None or r.get("protocol") == protocol) and \
                    r["descriptor"] not in names:
                names.append(r["descriptor"])
        return names

    def row(self, protocol: int, descriptor: str) -> dict[str, Any]:
        """The metrics row of ``descriptor`` under ``protocol``."""
        for r in self.rows:
            if r.get("protocol") == protocol and r.get("descriptor") == descriptor:
                return r
        raise LirisError(self.path / "metrics.json",
                         f"no protocol {protocol} result for {descriptor}")

    # ---- per-descriptor files ----------------------------------------------------------
    def pr(self, protocol: int, descriptor: str) -> pd.DataFrame:
        """``protocolN/<descriptor>/pr.csv``: threshold, precision, recall (tp, fp, fn).

        ``protocol`` ``"cross-session"`` reads ``cross_session/<descriptor>/pr.csv``
        (the top-1 curve of a query/database run).
        """
        if protocol == "cross-session":
            return self._csv(f"cross_session/{descriptor}/pr.csv", PR_COLUMNS)
        if protocol == "pairs":
            return self._csv(f"pairs/{descriptor}/pr.csv", PR_COLUMNS)
        return self._csv(f"protocol{protocol}/{descriptor}/pr.csv", PR_COLUMNS)

    def matches(self, descriptor: str, required: bool = True) -> pd.DataFrame | None:
        """``protocol1/<descriptor>/matches.csv``: the best match of every query."""
        return self._csv(f"protocol1/{descriptor}/matches.csv", MATCH_COLUMNS, required)

    def timing(self, descriptor: str, required: bool = True) -> pd.DataFrame | None:
        """``timing/<descriptor>.csv``: per-scan extraction seconds."""
        return self._csv(f"timing/{descriptor}.csv", TIMING_COLUMNS, required)

    def affinity(self, descriptor: str, required: bool = True) -> np.ndarray | None:
        """``protocol2/<descriptor>/affinity.npy``, memory-mapped (not read until used).

        Checked to be ``(N, N)`` for the run's N frames when ``positions.npy``
        is present.
        """
        relative = f"protocol2/{descriptor}/affinity.npy"
        if not required and not self.has(relative):
            return None
        return self._square_npy(relative, step=1, what="affinity")

    def affinity_decimated(self, descriptor: str,
                           required: bool = True) -> tuple[np.ndarray, int] | None:
        """``protocol2/<descriptor>/affinity_decimated.npy`` and its frame step ``k``.

        Above 8192 frames protocol 2 keeps, for figures, only the distances
        between frames ``0, k, 2k, …`` (float16, memory-mapped here); the
        metrics still count every pair. ``k`` is read from the row's
        ``affinity_stored`` note (``"… every kth frame (M x M) …"``) and checked
        against the matrix side, ``ceil(N / k)``.
        """
        relative = f"protocol2/{descriptor}/affinity_decimated.npy"
        if not required and not self.has(relative):
            return None
        note = str(self.row(2, descriptor).get("affinity_stored") or "")
        found = re.search(r"every (\d+)", note)
        if found is None or int(found.group(1)) < 1:
            raise LirisError(self.path / "metrics.json",
                             f"{descriptor}: affinity_stored does not give the frame step of "
                             f"{relative} (got {note!r})")
        step = int(found.group(1))
        matrix = self._square_npy(relative, step, "decimated affinity",
                                  f" (every {step}th frame)")
        return matrix, step

    def affinity_for_figures(self, descriptor: str) -> tuple[np.ndarray, int] | None:
        """The affinity a figure can draw, with its frame step, or None when the run has none.

        ``(affinity.npy, 1)`` when the full matrix was kept, else
        ``(affinity_decimated.npy, k)`` (runs above 8192 frames), else None.
        """
        full = self.affinity(descriptor, required=False)
        if full is not None:
            return full, 1
        return self.affinity_decimated(descriptor, required=False)

    # ---- trajectory and ground truth --------------------------------------------------
    def positions(self) -> np.ndarray:
        """``positions.npy``: the ``(N, 3)`` float64 translations used for ground truth."""
        if "positions.npy" not in self._cache:
            positions = self._npy("positions.npy")
            if positions.ndim != 2 or positions.shape[1] != 3:
                raise LirisError(self.path / "positions.npy",
                                 f"expected an (N, 3) array, got shape {positions.shape}")
            self._cache["positions.npy"] = positions.astype(np.float64)
        return self._cache["positions.npy"]

    @property
    def n_frames(self) -> int:
        """Frames of the run (rows of ``positions.npy``)."""
        return len(self.positions())

    def poses(self) -> np.ndarray:
        """``poses.npy``: the ``(N, 4, 4)`` poses in the run's pose frame."""
        return self._npy("poses.npy")

    def gt_settings(self):
        """The run's conventions as one :class:`~lidar_iris_eval.evaluation.settings.Settings`.

        Rebuilt from the ``convention`` block of config.yaml
        (``Settings.to_dict``); runs written before it are read from their
        flat keys (config.yaml, then metrics.json), liris defaults when absent.
        """
        from lidar_iris_eval.evaluation.settings import Settings

        block = self.config.get("convention")
        try:
            if isinstance(block, dict) and "radius" in block:
                return Settings.from_dict(block)
            merged = {**_flat(self.conventions), **_flat(self.config)}
            defaults = Settings()
            seconds = merged.get("exclude_seconds")
            if seconds is None and isinstance(merged.get("exclude"), dict):
                seconds = merged["exclude"].get("seconds")
            return Settings(
                radius=float(merged.get("radius", defaults.radius)),
                exclude=None if seconds is not None else
                int(_scalar(merged.get("exclude", defaults.exclude))),
                exclude_seconds=seconds,
                distance=str(merged.get("distance", defaults.distance)),
                pose_frame=str(merged.get("pose_frame", defaults.pose_frame)),
                recall_denominator=str(merged.get("recall_denominator",
                                                  defaults.recall_denominator)),
            )
        except (TypeError, ValueError, LirisError) as err:
            raise LirisError(self.path / "config.yaml",
                             f"bad ground-truth setting: {_one_line(err)}") from None

    def times(self) -> np.ndarray | None:
        """``times.npy`` (seconds per scan; written when the window is in seconds), or None."""
        return self._npy("times.npy") if self.has("times.npy") else None

    def ground_truth(self, step: int = 1):
        """Ground truth recomputed from ``positions.npy`` exactly as the run defined it.

        The run's own conventions (:meth:`gt_settings`): radius, window in
        frames or seconds (from ``times.npy``), skipped queries. ``step`` > 1
        keeps frames ``0, step, 2·step, …`` only (the frames of a decimated
        affinity): their positive pairs are those of the full run, but
        ``revisit`` then counts the exclusion window in kept frames.
        """
        from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth, ground_truth_for

        s = self.gt_settings()
        positions = self.positions()
        if step > 1:  # decimated figures: the frame rule of the kept frames
            window = s.exclude if s.exclude_seconds is None else 1
            return compute_ground_truth(positions[::step], s.radius, window, s.distance,
                                        s.pose_frame)
        times = self.times()
        if s.exclude_seconds is not None and times is None:
            raise LirisError(self.path / "times.npy",
                             "missing: the run's exclusion window is in seconds")
        return ground_truth_for(positions, s, times)

    # ---- config.yaml -------------------------------------------------------------------
    @property
    def sequence_path(self) -> Path | None:
        """Where the scans of this run live, if the config or metrics record it."""
        value = self.config.get("sequence")
        if isinstance(value, dict):
            value = value.get("path")
        if not value:
            value = (self.metrics.get("sequence") or {}).get("path")
        return Path(value) if value else None

    def descriptor_params(self, descriptor: str) -> tuple[str | None, dict]:
        """``(preset, params)`` recorded for ``descriptor`` in config.yaml."""
        entries = self.config.get("descriptors") or {}
        if isinstance(entries, list):  # [{"name": ..., "preset": ..., "params": {...}}]
            entries = {e.get("name"): e for e in entries if isinstance(e, dict)}
        entry = entries.get(descriptor) or {}
        return entry.get("preset"), dict(entry.get("params") or {})

    # ---- files -------------------------------------------------------------------------
    def has(self, relative: str) -> bool:
        return (self.path / relative).is_file()

    def loop_tables(self, kind: str = "loops") -> dict[str, pd.DataFrame]:
        """``{loop source: loops/<name>/<kind>.csv}`` (``kind`` ``loops`` or ``posegraph``)
        of a ``liris eval --loops`` run, for the sources that have the file."""
        columns = {"loops": ("query", "match", "status"),
                   "posegraph": ("graph", "ape_rmse_m", "added_m")}[kind]
        out = {}
        for name in self.descriptors(1):
            table = self._csv(f"loops/{name}/{kind}.csv", columns, required=False)
            if table is not None:
                out[name] = table
        return out

    def _csv(self, relative: str, columns: tuple[str, ...] = (),
             required: bool = True) -> pd.DataFrame | None:
        if relative not in self._cache:
            target = self.path / relative
            if not target.is_file():
                if not required:
                    return None
                raise LirisError(target, "missing from the run folder")
            try:
                table = pd.read_csv(target)
            except (OSError, ValueError, pd.errors.ParserError) as err:
                raise LirisError(target, f"not a readable CSV ({err})") from None
            missing = [c for c in columns if c not in table.columns]
            if missing:
                raise LirisError(target, f"missing column(s) {', '.join(missing)}")
            self._cache[relative] = table
        return self._cache[relative]

    def _square_npy(self, relative: str, step: int, what: str, note: str = "") -> np.ndarray:
        """A memory-mapped square matrix over every ``step``-th frame of the run.

        Its side must be ``ceil(N / step)`` when ``positions.npy`` gives N.
        """
        matrix = self._npy(relative, mmap=True)
        side = math.ceil(self.n_frames / step) if self.has("positions.npy") else None
        if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or \
                (side is not None and matrix.shape[0] != side):
            expected = f"({side}, {side})" if side is not None else "a square matrix"
            raise LirisError(self.path / relative,
                             f"{what} has shape {matrix.shape}, expected {expected}{note}")
        return matrix

    def _npy(self, relative: str, mmap: bool = False) -> np.ndarray:
        target = self.path / relative
        if not target.is_file():
            raise LirisError(target, "missing from the run folder")
        try:
            return np.load(target, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (ValueError, OSError) as err:
            raise LirisError(target, f"not a readable .npy file ({err})") from None


def load_run(path: str | Path) -> Run:
    """Open a run folder written by ``liris eval``.

    ``metrics.json`` is required (it holds the results); ``config.yaml`` is
    read when present. Anything that is not a run folder is a one-line
    :class:`~lidar_iris_eval.errors.LirisError` naming the file at fault.
    """
    folder = Path(path)
    if not folder.exists():
        raise LirisError(folder, "run folder not found")
    if not folder.is_dir():
        raise LirisError(folder, "not a run folder (a file; expected a folder written by "
                                 "liris eval)")
    metrics_path = folder / "metrics.json"
    if not metrics_path.is_file():
        if (folder / "summary.csv").is_file():  # liris eval SEQ1 SEQ2 / --plan
            raise LirisError(folder, "a multi-sequence run (summary.csv, no metrics.json): "
                                     "give one of its NN-<sequence>/ run folders")
        raise LirisError(folder, "not a run folder: no metrics.json (written by liris eval)")
    metrics = _load_json(metrics_path)
    check_metrics(metrics, metrics_path)  # one schema check (runs/schema.py)
    config: dict[str, Any] = {}
    config_path = folder / "config.yaml"
    if config_path.is_file():
        try:
            config = yaml.safe_load(config_path.read_text()) or {}
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
            raise LirisError(config_path, f"not valid YAML ({_one_line(err)})") from None
        if not isinstance(config, dict):
            raise LirisError(config_path, "expected a mapping of settings")
    else:
        # every liris writer leaves one; without it the run shows with liris's
        # default conventions and cannot be replayed, which must not pass unsaid
        warn(config_path, "missing: the run's settings are unknown, shown with liris's "
                          "default conventions, and it cannot be replayed with --config")
    return Run(path=folder, config=config, metrics=metrics)


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise LirisError(path, f"not valid JSON ({err})") from None


def _one_line(err: Exception) -> str:
    """YAML errors span several lines (a caret under the column); keep one."""
    return " ".join(str(err).split())


def _flat(settings: dict) -> dict:
    """Lift ground-truth keys out of an optional ``ground_truth:`` section."""
    if not isinstance(settings, dict):
        return {}
    flat = dict(settings)
    for section in ("ground_truth", "gt", "conventions"):
        if isinstance(settings.get(section), dict):
            flat.update(settings[section])
    return flat


def _scalar(value: Any) -> Any:
    """``exclude`` is stored as a number or as ``{value: 30, preset: paper}``."""
    if isinstance(value, dict):
        for key in ("value", "frames", "exclude"):
            if key in value:
                return value[key]
    return value
