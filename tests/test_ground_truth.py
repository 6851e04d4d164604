"""Ground-truth counts: hand-made cases and the real KITTI figures of PROTOCOLS.md."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.io.poses import read_kitti_poses


def brute_force(positions, radius, exclude):
    n = len(positions)
    positive = 0
    revisit = set()
    for i, j in itertools.permutations(range(n), 2):
        if np.linalg.norm(positions[i] - positions[j]) < radius:
            positive += 1
            if j <= i - exclude:
                revisit.add(i)
    return positive, len(revisit)


def test_hand_case_line_with_a_loop():
    # 0..9 along x, then frames 10..12 come back near frames 0..2.
    positions = np.zeros((13, 3))
    positions[:10, 0] = np.arange(10) * 3.0
    positions[10:, 0] = [0.5, 3.5, 30.0]
    gt = compute_ground_truth(positions, radius=4.0, exclude=5)
    # neighbours 3 m apart along the line: 9 unordered pairs; frame 10 near 0 and 1,
    # frame 11 near 0, 1 and 2, frames 10-11 near each other: 1+2+3+... counted by hand:
    # (10,0) (10,1) (11,0)? |3.5-0|=3.5 yes, (11,1) (11,2), (10,11); (12,9) |30-27|=3 yes
    expected_unordered = 9 + 2 + 3 + 1 + 1
    assert gt.n_positive_pairs == 2 * expected_unordered
    assert gt.n_negative_pairs == 13 * 12 - 2 * expected_unordered
    # frame 12's only partner, 9, is 3 frames back: inside the exclusion window of 5
    assert gt.revisit.nonzero()[0].tolist() == [10, 11]


def test_boundary_is_strictly_below_radius():
    positions = np.array([[0.0, 0, 0], [4.0, 0, 0], [0, 0, 3.999]])
    gt = compute_ground_truth(positions, radius=4.0, exclude=1)
    assert gt.pairs.tolist() == [[0, 2]]


def test_matches_brute_force_on_random_walk():
    rng = np.random.default_rng(3)
    positions = np.cumsum(rng.normal(size=(60, 3)), axis=0)
    for exclude in (1, 5, 20):
        gt = compute_ground_truth(positions, radius=4.0, exclude=exclude)
        assert (gt.n_positive_pairs, gt.n_revisits) == brute_force(positions, 4.0, exclude)


def test_planar_camera_frame_ignores_y_the_down_axis():
    positions = np.array([[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    assert compute_ground_truth(positions, distance="3d").n_positive_pairs == 0
    assert compute_ground_truth(positions, distance="planar", frame="camera").n_positive_pairs == 2
    assert compute_ground_truth(positions, distance="planar", frame="lidar").n_positive_pairs == 0


PROTOCOL_TABLE = {
    # sequence, distance: positives (ordered), revisits at E = 30, 50, 100, 300
    ("00", "3d"): (68_420, [816, 791, 791, 791]),
    ("00", "planar"): (68_644, None),
    ("05", "3d"): (None, [513, 493, 437, 437]),
    ("08", "3d"): (None, [294, 265, 265, 265]),
    ("08", "planar"): (None, [379, 332, 332, 332]),
}


@pytest.mark.parametrize(("sequence", "distance"), list(PROTOCOL_TABLE))
def test_real_kitti_counts_reproduce_protocols_table(kitti_dir, sequence, distance):
    positives, revisits = PROTOCOL_TABLE[(sequence, distance)]
    poses = read_kitti_poses(kitti_dir / "poses" / f"{sequence}.txt")
    counts = [
        compute_ground_truth(poses[:, :3, 3], 4.0, e, distance, "camera")
        for e in (30, 50, 100, 300)
    ]
    if positives is not None:
        assert counts[0].n_positive_pairs == positives
    if sequence == "00" and distance == "3d":
        assert counts[0].n_negative_pairs == 20_547_720
    if revisits is not None:
        assert [g.n_revisits for g in counts] == revisits
