"""A small synthetic loop sequence for CLI tests (fast: no ray casting)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import write_kitti_sequence


def loop_sequence(root: Path, frames: int = 70) -> Path:
    """A car driving 1.3 laps of a 20 m circle through a fixed random world of boxes."""
    rng = np.random.default_rng(8)
    centres = rng.uniform(-45, 45, (160, 2))
    sizes = rng.uniform(0.5, 4.0, (160, 3))
    world = []
    for (cx, cy), (sx, sy, sz) in zip(centres, sizes, strict=True):
        n = 120
        world.append(np.c_[cx + rng.uniform(-sx, sx, n), cy + rng.uniform(-sy, sy, n),
                           rng.uniform(-1.7, sz, n)])
    ground = np.c_[rng.uniform(-60, 60, (6000, 2)), np.full(6000, -1.73)]
    world = np.concatenate(world + [ground])
    angles = np.linspace(0, 2.6 * np.pi, frames)
    poses, scans = [], []
    for a in angles:
        x, y, yaw = 20 * np.cos(a), 20 * np.sin(a), a + np.pi / 2
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                        [0, 0, 1]])
        local = (world - [x, y, 0]) @ rot  # world -> sensor frame
        local = local[np.linalg.norm(local[:, :2], axis=1) < 50]
        local += rng.normal(0, 0.02, local.shape)
        scans.append(np.c_[local, np.zeros(len(local))].astype(np.float32))
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot, [x, y, 0]
        poses.append(pose)
    return write_kitti_sequence(root, scans, np.array(poses))
