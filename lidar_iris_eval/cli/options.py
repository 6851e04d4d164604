"""Click options shared by several subcommands, so each convention is spelled once."""

from __future__ import annotations

import functools

import click

from lidar_iris_eval.errors import LirisError

#: named exclusion windows (PROTOCOLS.md): the paper's text vs the authors' code
EXCLUDE_PRESETS = {"paper": 30, "reference": 300}


def parse_exclude(value: str) -> tuple[int, str]:
    """``"paper"``, ``"reference"`` or an integer to ``(E, name)``."""
    if value in EXCLUDE_PRESETS:
        return EXCLUDE_PRESETS[value], value
    try:
        frames = int(value)
    except ValueError:
        raise LirisError(
            f"--exclude {value}", "expected a number of frames, 'paper' (30) or 'reference' (300)"
        ) from None
    if frames < 1:
        raise LirisError(f"--exclude {value}", "exclusion window must be at least 1 frame")
    named = {v: k for k, v in EXCLUDE_PRESETS.items()}.get(frames, "custom")
    return frames, named


def ground_truth_options(func):
    """``--radius``, ``--exclude``, ``--distance`` and ``--pose-frame``."""

    @click.option("--radius", type=float, default=4.0, show_default=True,
                  help="A pair is positive when closer than this (metres).")
    @click.option("--exclude", "exclude", default="paper", show_default=True,
                  help="Exclusion window E in frames, or 'paper' (30) / 'reference' (300).")
    @click.option("--distance", type=click.Choice(["3d", "planar"]), default="3d",
                  show_default=True, help="3-D distance, or planar in the ground plane.")
    @click.option("--pose-frame", type=click.Choice(["camera", "lidar"]), default="camera",
                  show_default=True,
                  help="Measure distances between camera poses (KITTI, the paper) or LiDAR poses.")
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        return func(*args, **kwargs)

    return wrapper
