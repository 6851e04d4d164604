"""The ESM weights fine-tuned on simulated + Riverside segments: reachable by name, not a preset's.

``esm_localmap_real_weights.npz`` (model card, "esm_localmap_real_weights.npz") is opt-in
(``--param esm.weights=esm_localmap_real_weights.npz``); the `local-maps` preset uses its
network with a refit quality branch (``esm_localmap_simreal_weights.npz``,
tests/test_esm_simreal_weights.py). On real KITTI segments the file must give a usable
embedding that differs from the weights it was fine-tuned from (else the training did nothing).
"""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm import network
from lidar_iris_eval.descriptors.esm.segmentation import segment_scan

NAME = "esm_localmap_real_weights.npz"
REAL = network.WEIGHTS_FILE.with_name(NAME)


def test_named_weights_resolve_to_the_shipped_file_and_are_not_the_default():
    if not REAL.is_file():
        pytest.skip(f"no {NAME}")
    assert network.resolve_weights(NAME) == REAL
    for preset in ("local-maps", "single-scan"):
        assert get_descriptor("esm", preset).weights_path.name != NAME
    # same architecture as the file it was fine-tuned from (a fine-tune, not a new network)
    _, arch = network.load_weights(REAL)
    _, base = network.load_weights(network.LOCALMAP_WEIGHTS_FILE)
    assert arch == base


def test_real_kitti_segments_get_a_valid_but_different_embedding(kitti_dir):
    if not REAL.is_file():
        pytest.skip(f"no {NAME}")
    scan = kitti_dir / "samples" / "00" / "velodyne" / "000094.bin"
    if not scan.is_file():
        pytest.skip("KITTI sample scan missing")
    points = np.fromfile(scan, np.float32).reshape(-1, 4)[:, :3]
    new = get_descriptor("esm", "local-maps", weights=NAME)
    old = get_descriptor("esm", "local-maps", weights=network.LOCALMAP_WEIGHTS_FILE.name)
    assert new.segment_params == old.segment_params  # same resampling and normalisation
    segs = segment_scan(points, None, new.segment_params)
    assert len(segs.points) >= 10, "the KITTI scan should give many segments"
    e_new, q_new = new.describe_segments(segs.points)
    e_old, _ = old.describe_segments(segs.points)
    assert e_new.shape == e_old.shape == (len(segs.points), 16)
    assert np.isfinite(e_new).all()
    assert np.all((q_new >= 0) & (q_new <= 1))
    # the network does not normalise its output: "valid" means finite, not collapsed (distinct
    # segments get distinct embeddings) and reproducible
    d = np.linalg.norm(e_new[:, None] - e_new[None], axis=2)[np.triu_indices(len(e_new), 1)]
    assert np.median(d) > 1e-2
    assert np.array_equal(e_new, new.describe_segments(segs.points)[0])
    # different from the weights it was fine-tuned from by more than rounding
    diff = np.linalg.norm(e_new - e_old, axis=1)
    scale = np.linalg.norm(e_old, axis=1)
    assert np.median(diff / scale) > 1e-3
