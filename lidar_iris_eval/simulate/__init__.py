"""Synthetic LiDAR sequences with exact ground truth, in KITTI layout.

A procedural town (roads with kerbs, buildings, trees, poles, signs, parked
and moving cars) is ray cast by an HDL-64E or VLP-16 model along a route with
known revisits, and written like a KITTI odometry sequence plus SemanticKITTI
labels::

    from lidar_iris_eval.simulate import simulate_sequence
    path = simulate_sequence("/tmp/seq", preset="tiny-mixed")
"""

from lidar_iris_eval.simulate.pipeline import (
    Scenario,
    SimReport,
    build_scenario,
    run_simulation,
    simulate_sequence,
)
from lidar_iris_eval.simulate.presets import PRESETS, SimConfig, resolve_config

__all__ = [
    "PRESETS",
    "Scenario",
    "SimConfig",
    "SimReport",
    "build_scenario",
    "resolve_config",
    "run_simulation",
    "simulate_sequence",
]
