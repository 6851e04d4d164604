"""The simulated sequence a benchmark runs on, made once and reused."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from lidar_iris_eval import __version__


def simulated_sequence(
    work_dir: str | os.PathLike,
    preset: str = "kitti-scale",
    frames: int | None = None,
    azimuth_steps: int | None = None,
    progress: bool = False,
) -> tuple[Path, float]:
    """A simulated sequence under ``work_dir``, made once and reused afterwards.

    The folder name spells the resolved configuration, and a folder is reused
    only when its ``manifest.json`` (written last by the simulator) records the
    same configuration, so a killed simulation is redone rather than trusted.

    Returns
    -------
    (path, seconds) : the sequence folder and the time spent simulating (0.0
        when an existing one was reused).
    """
    from lidar_iris_eval.simulate import resolve_config, simulate_sequence

    cfg = resolve_config(preset, {"frames": frames, "azimuth_steps": azimuth_steps})
    steps = "full" if cfg.azimuth_steps is None else cfg.azimuth_steps
    path = Path(work_dir) / f"sim-{preset}-n{cfg.frames}-az{steps}"
    if _manifest_matches(path, cfg):
        return path, 0.0
    start = time.perf_counter()
    simulate_sequence(path, preset=preset, overwrite=True, progress=progress,
                      frames=cfg.frames, azimuth_steps=cfg.azimuth_steps)
    return path, time.perf_counter() - start


def _manifest_matches(path: Path, cfg) -> bool:
    manifest = path / "manifest.json"
    if not manifest.is_file():
        return False
    try:
        stored = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return False
    from lidar_iris_eval.simulate.presets import manifest_config

    expected = json.loads(json.dumps(manifest_config(cfg)))  # tuples -> lists
    return stored.get("config") == expected and stored.get("version") == __version__
