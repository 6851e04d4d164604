"""What a dataset reader declares to the registry (:class:`DatasetSpec`) and its cue helpers.

Each reader module of this package ends with ``SPECS``, its datasets'
specs, beside the reader and the cheap detection cue each spec names;
:mod:`lidar_iris_eval.io.datasets` collects them. An external reader
(entry point ``liris.datasets``) declares one spec the same way.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class DatasetSpec:
    """One registered dataset (or generic format).

    Attributes
    ----------
    name : the ``--dataset`` name.
    title : the dataset's own name.
    layout : the path to give and what must be around it.
    pose_frame : the frame of the dataset's poses as distributed.
    converts : what liris does to them (extrinsic, time matching, interpolation).
    sensor : the ``--sensor`` preset of its LiDAR, or None where liris has none.
    looks_for : the short cue detection tests, for error messages.
    detect : ``detect(path) -> bool``.
    opener : ``"module:function"`` under this package, called as
        ``opener(path, poses=..., calib=..., **options)``.
    generic : detected only when no specific dataset matches.
    frame : the frame of the scans as stored, and what liris turns it into:
        every reader returns z-up scans (x forward, y left, z up, as KITTI).
    intensity : what the reader returns as a scan's intensity (field, unit, range).
    """

    name: str
    title: str
    layout: str
    pose_frame: str
    converts: str
    sensor: str | None
    looks_for: str
    detect: Callable[[Path], bool]
    opener: str
    generic: bool = False
    frame: str = ""
    intensity: str = ""

    def open(self, path: Path, **options):
        """Open ``path`` with this dataset's reader.

        ``opener`` names a module of this package (``"mulran:open_mulran"``), or,
        for a reader outside it, any importable module (``"liris_mine.reader:open"``).
        """
        module_name, func_name = self.opener.split(":")
        if (Path(__file__).parent / f"{module_name}.py").is_file():
            module_name = f"lidar_iris_eval.io.datasets.{module_name}"
        module = importlib.import_module(module_name)
        return getattr(module, func_name)(Path(path), **options)


# --- detection cues (cheap: a few stat calls each) ----------------------------


def has_dir(path: Path, *parts: str) -> bool:
    """True when ``path/parts...`` is a folder."""
    return path.joinpath(*parts).is_dir()


def has_file(path: Path, *parts: str) -> bool:
    """True when ``path/parts...`` is a file."""
    return path.joinpath(*parts).is_file()


__all__ = ["DatasetSpec", "has_dir", "has_file"]
