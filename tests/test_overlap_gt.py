"""Overlap ground truth: the range-image overlap agrees with pose distance where both are clear."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.evaluation.overlap import (
    OverlapSpec,
    cached_overlap_matrix,
    overlap_ground_truth,
    overlap_matrix,
    pair_overlap,
    range_image,
)
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.pipeline import _NOISE
from lidar_iris_eval.simulate.sensors import simulate_scan


@pytest.fixture(scope="module")
def town():
    cfg = resolve_config("tiny-mixed", {})
    scen = build_scenario(cfg)
    cache: dict[int, np.ndarray] = {}

    def scan(i: int) -> np.ndarray:
        if i not in cache:
            rng = np.random.default_rng([cfg.seed, _NOISE, i])
            cache[i] = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i),
                                     scen.poses[i], rng, scen.sensor.grid.directions).points
        return cache[i]

    return scen.poses, scan


def _pairs(poses, lo, hi, min_gap, count, seed):
    xyz = poses[:, :3, 3]
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    i, j = np.nonzero((d >= lo) & (d < hi) & (np.arange(len(d))[:, None] - np.arange(len(d))
                                                 >= min_gap))
    pick = np.random.default_rng(seed).choice(len(i), size=min(count, len(i)), replace=False)
    return list(zip(i[pick].tolist(), j[pick].tolist(), strict=True))


def test_overlap_agrees_with_pose_distance_below_2m_and_beyond_30m(town):
    poses, scan = town
    spec = OverlapSpec()
    near = _pairs(poses, 0.0, 2.0, 30, 25, 0)  # revisits closer than 2 m
    far = _pairs(poses, 30.0, np.inf, 1, 25, 1)
    assert len(near) >= 10 and len(far) >= 10
    images = {}

    def overlap(i, j):
        for k in (i, j):
            if k not in images:
                images[k] = range_image(scan(k), spec)
        return pair_overlap(images[i][0], images[j][1], np.linalg.inv(poses[i]) @ poses[j], spec)

    near_o = [overlap(i, j) for i, j in near]
    far_o = [overlap(i, j) for i, j in far]
    assert min(near_o) >= spec.threshold, near_o
    assert max(far_o) < spec.threshold, far_o


def test_hand_made_scene_overlap():
    # a ring wall 10 m around the sensor: the same place overlaps fully, a place 120 m
    # away (beyond 2 x 50 m) not at all
    ang = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
    zs = np.linspace(-3, 0.4, 40)
    a, z = np.meshgrid(ang, zs)
    wall = np.stack([10 * np.cos(a).ravel(), 10 * np.sin(a).ravel(), z.ravel()], 1)
    image, vert = range_image(wall)
    assert pair_overlap(image, vert, np.eye(4)) == 1.0
    poses = np.stack([np.eye(4)] * 3)
    poses[1, 0, 3] = 0.2
    poses[2, 0, 3] = 120.0
    m = overlap_matrix([wall, wall, wall], poses)
    assert m[0, 1] > 0.9 and m[1, 0] > 0.9
    assert m[0, 2] == 0.0 and m[2, 0] == 0.0
    gt = overlap_ground_truth(m, exclude=1)
    assert gt.pairs.tolist() == [[0, 1]]
    assert gt.revisit.tolist() == [False, True, False]


class _FakeSequence:
    def __init__(self, scans, poses):
        self.scans, self.poses = scans, poses
        self.calls = 0

    def __getitem__(self, i):
        self.calls += 1
        return self.scans[i]

    def __len__(self):
        return len(self.scans)

    def fingerprint(self):
        return "fake"


def test_overlap_matrix_is_cached(tmp_path):
    rng = np.random.default_rng(0)
    scans = [rng.normal(0, 8, (500, 3)) for _ in range(3)]
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    seq = _FakeSequence(scans, poses)
    first, hit = cached_overlap_matrix(seq, tmp_path)
    assert not hit and seq.calls == 3
    again, hit = cached_overlap_matrix(seq, tmp_path)
    assert hit and seq.calls == 3
    np.testing.assert_array_equal(first, again)
    moved = _FakeSequence(scans, poses.copy())
    moved.poses[2, 0, 3] = 5.0  # other poses: another key
    _, hit = cached_overlap_matrix(moved, tmp_path)
    assert not hit
