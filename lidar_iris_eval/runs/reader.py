"""One run folder as a Python object: config, metrics rows and per-descriptor files.

Files are read lazily (an affinity matrix can be hundreds of megabytes), and a
missing or malformed file is a :class:`~lidar_iris_eval.errors.LirisError`
naming it, so the CLI reports it in one line.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from lidar_iris_eval.errors import LirisError


@dataclass
class Run:
    """A finished run folder.

    Attributes
    ----------
    path : the run folder.
    config : ``config.yaml`` as a dict (empty when the file is absent).
    metrics : ``metrics.json`` as a dict (header, conventions and ``results``).
    """

    path: Path
    config: dict[str, Any]
    metrics: dict[str, Any]
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def name(self) -> str:
        """The folder name, used as the run's label."""
        return self.path.name

    @property
    def rows(self) -> list[dict[str, Any]]:
        """One metrics row per protocol and descriptor, as written by ``liris eval``."""
        return list(self.metrics.get("results", []))

    @property
    def conventions(self) -> dict[str, Any]:
        """The ground-truth and metric conventions the run was evaluated under."""
        return dict(self.metrics.get("conventions", {}))

    def descriptors(self, protocol: int) -> list[str]:
        """Descriptors that have results for ``protocol``, in run order."""
        return [r["descriptor"] for r in self.rows if r.get("protocol") == protocol]

    def row(self, protocol: int, descriptor: str) -> dict[str, Any]:
        for r in self.rows:
            if r.get("protocol") == protocol and r.get("descriptor") == descriptor:
                return r
        raise LirisError(self.path, f"no protocol {protocol} result for {descriptor}")

    def pr(self, protocol: int, descriptor: str) -> pd.DataFrame:
        """``protocolN/<descriptor>/pr.csv``: threshold, precision, recall (tp, fp, fn)."""
        return self._csv(f"protocol{protocol}/{descriptor}/pr.csv")

    def matches(self, descriptor: str) -> pd.DataFrame:
        """``protocol1/<descriptor>/matches.csv``: the best match of every query."""
        return self._csv(f"protocol1/{descriptor}/matches.csv")

    def affinity(self, descriptor: str) -> np.ndarray:
        """``protocol2/<descriptor>/affinity.npy``, memory-mapped (not read until used)."""
        return self._npy(f"protocol2/{descriptor}/affinity.npy", mmap=True)

    def positions(self) -> np.ndarray:
        """``positions.npy``: the ``(N, 3)`` translations used for ground truth."""
        return self._npy("positions.npy")

    def poses(self) -> np.ndarray:
        """``poses.npy``: the ``(N, 4, 4)`` poses in the run's pose frame."""
        return self._npy("poses.npy")

    def has(self, relative: str) -> bool:
        return (self.path / relative).is_file()

    def _csv(self, relative: str) -> pd.DataFrame:
        if relative not in self._cache:
            target = self.path / relative
            if not target.is_file():
                raise LirisError(target, "missing from the run folder")
            try:
                self._cache[relative] = pd.read_csv(target)
            except (ValueError, pd.errors.ParserError) as err:
                raise LirisError(target, f"not a readable CSV ({err})") from None
        return self._cache[relative]

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
    read when present.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise LirisError(folder, "run folder not found")
    metrics_path = folder / "metrics.json"
    if not metrics_path.is_file():
        raise LirisError(folder, "not a run folder: no metrics.json (written by liris eval)")
    try:
        metrics = json.loads(metrics_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise LirisError(metrics_path, f"not valid JSON ({err})") from None
    if not isinstance(metrics, dict) or not isinstance(metrics.get("results"), list):
        raise LirisError(metrics_path, "no 'results' list; not written by liris eval")
    config: dict[str, Any] = {}
    config_path = folder / "config.yaml"
    if config_path.is_file():
        try:
            config = yaml.safe_load(config_path.read_text()) or {}
        except yaml.YAMLError as err:
            raise LirisError(config_path, f"not valid YAML ({err})") from None
    return Run(path=folder, config=config, metrics=metrics)
