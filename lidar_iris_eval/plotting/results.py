"""Read a results directory written by ``liris eval`` (docs/results-format.md).

Only this module knows file names inside a run; figure modules receive arrays
and tables. Missing *required* pieces (``metrics.json``, ``pr.csv`` of a
listed result) are :class:`~lidar_iris_eval.errors.LirisError`; optional ones
(timing, affinity, matches) return ``None`` so the caller can skip a panel
with a warning.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.plotting.style import method_sort_key

PR_COLUMNS = ("threshold", "precision", "recall")
MATCH_COLUMNS = ("query", "match", "distance", "is_revisit", "is_true")
TIMING_COLUMNS = ("scan", "extract_s")


@dataclass(frozen=True)
class GtSettings:
    """The ground-truth conventions a run was evaluated with."""

    radius: float = 4.0
    exclude: int = 30
    distance: str = "3d"
    pose_frame: str = "camera"


@dataclass
class RunResults:
    """Lazy view of one run directory."""

    path: Path
    config: dict
    metrics: dict
    name: str = field(default="")

    def __post_init__(self) -> None:
        if not self.name:
            self.name = self.path.name

    # ---- metrics -----------------------------------------------------------------
    @property
    def results(self) -> list[dict]:
        return list(self.metrics.get("results", []))

    def descriptors(self, protocol: int | None = None) -> list[str]:
        """Descriptor names with a result (for ``protocol``), in registry order."""
        names = {
            r["descriptor"]
            for r in self.results
            if protocol is None or int(r.get("protocol", -1)) == protocol
        }
        return sorted(names, key=method_sort_key)

    def protocols(self) -> list[int]:
        return sorted({int(r["protocol"]) for r in self.results})

    def metric(self, protocol: int, descriptor: str) -> dict:
        for row in self.results:
            if int(row.get("protocol", -1)) == protocol and row.get("descriptor") == descriptor:
                return row
        raise LirisError(self.path / "metrics.json",
                         f"no protocol {protocol} result for {descriptor}")

    # ---- per-descriptor tables -----------------------------------------------------
    def pr(self, protocol: int, descriptor: str) -> pd.DataFrame:
        """The exact PR curve (required for every listed result)."""
        path = self.path / f"protocol{protocol}" / descriptor / "pr.csv"
        if not path.is_file():
            raise LirisError(path, "missing PR curve listed in metrics.json")
        return _read_csv(path, PR_COLUMNS)

    def matches(self, descriptor: str) -> pd.DataFrame | None:
        path = self.path / "protocol1" / descriptor / "matches.csv"
        return _read_csv(path, MATCH_COLUMNS) if path.is_file() else None

    def affinity(self, descriptor: str) -> np.ndarray | None:
        path = self.path / "protocol2" / descriptor / "affinity.npy"
        if not path.is_file():
            return None
        matrix = _load_npy(path, mmap=True)
        n = self.n_frames
        if matrix.shape != (n, n):
            raise LirisError(path, f"affinity has shape {matrix.shape}, expected ({n}, {n})")
        return matrix

    def timing(self, descriptor: str) -> pd.DataFrame | None:
        path = self.path / "timing" / f"{descriptor}.csv"
        return _read_csv(path, TIMING_COLUMNS) if path.is_file() else None

    # ---- trajectory and ground truth ----------------------------------------------------
    @cached_property
    def positions(self) -> np.ndarray:
        path = self.path / "positions.npy"
        if not path.is_file():
            raise LirisError(path, "missing positions (needed for ground truth and trajectory)")
        positions = _load_npy(path)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise LirisError(path, f"expected an (N, 3) array, got shape {positions.shape}")
        return positions.astype(np.float64)

    @property
    def n_frames(self) -> int:
        return len(self.positions)

    @cached_property
    def gt_settings(self) -> GtSettings:
        """Conventions from config.yaml, falling back to metrics.json ``conventions``."""
        merged = {**_flat(self.metrics.get("conventions", {})), **_flat(self.config)}
        defaults = GtSettings()
        try:
            return GtSettings(
                radius=float(merged.get("radius", defaults.radius)),
                exclude=int(_scalar(merged.get("exclude", defaults.exclude))),
                distance=str(merged.get("distance", defaults.distance)),
                pose_frame=str(merged.get("pose_frame", defaults.pose_frame)),
            )
        except (TypeError, ValueError) as err:
            raise LirisError(self.path / "config.yaml",
                             f"bad ground-truth setting: {err}") from None

    def ground_truth(self):
        """Recompute ground truth exactly as the run defined it."""
        from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth

        s = self.gt_settings
        return compute_ground_truth(self.positions, s.radius, s.exclude, s.distance, s.pose_frame)

    @property
    def sequence_path(self) -> Path | None:
        """Where the scans of this run live, if the config records it."""
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


def load_run(path: str | Path) -> RunResults:
    """Open a run directory; anything that is not one is a one-line LirisError."""
    path = Path(path)
    if not path.exists():
        raise LirisError(path, "no such results directory")
    if not path.is_dir():
        raise LirisError(path, "not a results directory (expected a folder written by liris eval)")
    metrics_path = path / "metrics.json"
    if not metrics_path.is_file():
        raise LirisError(path, "not a results directory: no metrics.json (run liris eval first)")
    try:
        metrics = json.loads(metrics_path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise LirisError(metrics_path, f"unreadable metrics: {err}") from None
    if not isinstance(metrics, dict) or not isinstance(metrics.get("results"), list):
        raise LirisError(metrics_path, "expected an object with a 'results' list")
    for row in metrics["results"]:
        if not isinstance(row, dict) or "protocol" not in row or "descriptor" not in row:
            raise LirisError(metrics_path, "every result needs 'protocol' and 'descriptor'")
    if not metrics["results"]:
        raise LirisError(metrics_path, "no results to plot")
    config: dict = {}
    config_path = path / "config.yaml"
    if config_path.is_file():
        try:
            config = yaml.safe_load(config_path.read_text()) or {}
        except yaml.YAMLError as err:
            raise LirisError(config_path, f"unreadable config: {err}") from None
        if not isinstance(config, dict):
            raise LirisError(config_path, "expected a mapping")
    return RunResults(path=path, config=config, metrics=metrics)


def _read_csv(path: Path, columns: tuple[str, ...]) -> pd.DataFrame:
    try:
        table = pd.read_csv(path)
    except (OSError, ValueError) as err:
        raise LirisError(path, f"unreadable table: {err}") from None
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise LirisError(path, f"missing column(s) {', '.join(missing)}")
    return table


def _load_npy(path: Path, mmap: bool = False) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise LirisError(path, f"unreadable array: {err}") from None


def _flat(config: dict) -> dict:
    """Lift ground-truth keys out of an optional ``ground_truth:`` section."""
    if not isinstance(config, dict):
        return {}
    flat = dict(config)
    for section in ("ground_truth", "gt", "conventions"):
        if isinstance(config.get(section), dict):
            flat.update(config[section])
    return flat


def _scalar(value):
    """``exclude`` is stored as a number or as ``{value: 30, preset: paper}``."""
    if isinstance(value, dict):
        for key in ("value", "frames", "exclude"):
            if key in value:
                return value[key]
    return value
