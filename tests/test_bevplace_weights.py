"""BEVPlace++'s shipped weights: the file liris fitted on simulated worlds (MODEL_CARD.md).

A golden test pins the file's SHA-256 and a few descriptor values of a real
KITTI scan, so a retrained or re-saved file cannot slip in unnoticed: retraining
(``scripts/train_bevplace.py``) must update these numbers, the model card and
the README together.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from conftest import KITTI

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.bevplace import network
from lidar_iris_eval.descriptors.bevplace.descriptor import (
    SHIPPED_WEIGHTS,
    WEIGHTS_DIR,
    resolve_weights,
)
from lidar_iris_eval.descriptors.learned import RANDOM_INIT, weights_digest

SAMPLES = KITTI / "samples" / "00" / "velodyne"
SHIPPED = WEIGHTS_DIR / SHIPPED_WEIGHTS

#: SHA-256 of bevplace_sim_weights.npz (MODEL_CARD.md)
SHA256 = "087ac4d1c274cb99a50eb9d104a3ca7b750bf87633fd5c4028eba98c48157933"
#: the shipped weights' global descriptor of KITTI 00 scan 000094 (the first sample): the
#: entries at GOLDEN_AT, and its squared L2 distance to scan 000095 (random-init: 5.2e-5)
GOLDEN_AT = (6, 7, 8, 9, 22, 23, 4096, 8191)
GOLDEN = (0.0155602070, 0.0109888222, -0.0100552319, -0.0180234592, 0.0223037265,
          0.0198169053, 0.0155130951, 0.0236440748)
GOLDEN_D01 = 0.229236


def test_the_shipped_file_is_the_pinned_one():
    assert SHIPPED.is_file(), f"{SHIPPED} is missing: the package ships it (pyproject)"
    assert hashlib.sha256(SHIPPED.read_bytes()).hexdigest() == SHA256
    with np.load(SHIPPED, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    assert {k: v.shape for k, v in arrays.items()} == network.shapes()
    assert all(v.dtype == np.float32 and np.isfinite(v).all() for v in arrays.values())


def test_the_shipped_encoder_is_the_seed_0_random_one_and_netvlad_is_fitted():
    """What the file is (MODEL_CARD.md): the random-init encoder, bit for bit (gradient
    training made it worse and was not kept), and a NetVLAD layer fitted by k-means."""
    with np.load(SHIPPED, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    rand = network.random_weights(0)
    fitted = {k for k in arrays if not np.array_equal(arrays[k], rand[k])}
    assert fitted == {"pooling.conv.weight", "pooling.centroids"}
    conv = arrays["pooling.conv.weight"][:, :, 0, 0].astype(np.float64)
    unit = conv / np.linalg.norm(conv, axis=1, keepdims=True)
    cent = arrays["pooling.centroids"].astype(np.float64)
    cosine = np.sum(unit * cent, axis=1) / np.linalg.norm(cent, axis=1)
    assert np.allclose(cosine, 1.0, atol=1e-5)  # assignment = alpha x the unit centres


@pytest.mark.parametrize("preset", ["paper", "reference"])
def test_the_default_presets_use_the_trained_file(preset):
    desc = get_descriptor("bevplace", preset=preset)
    assert desc.params.weights == SHIPPED_WEIGHTS
    assert resolve_weights(desc.params.weights) == SHIPPED
    sha = hashlib.sha256(SHIPPED.read_bytes()).hexdigest()
    assert desc.cache_token() == sha[:16]  # the file's SHA-256 keys the cache
    assert desc.run_info() == {"weights": SHIPPED_WEIGHTS, "weights_trained": True,
                               "weights_sha256": sha[:16]}
    assert get_descriptor("bevplace").params == desc.params  # paper is the default


def test_random_init_stays_reachable_by_preset_and_by_param():
    by_preset = get_descriptor("bevplace", preset="random-init")
    by_param = get_descriptor("bevplace", weights=RANDOM_INIT)
    for desc in (by_preset, by_param):
        assert desc.run_info()["weights"] == RANDOM_INIT
        assert desc.run_info()["weights_trained"] is False
        assert desc.cache_token() == weights_digest(network.random_weights(0),
                                                    network.shapes())[:16]
    assert by_preset.cache_token() != get_descriptor("bevplace").cache_token()
    img = np.random.default_rng(3).integers(0, 256, (1, 201, 201)).astype(np.uint8)
    assert not np.allclose(by_param.compute_images(img),
                           get_descriptor("bevplace").compute_images(img), atol=1e-3)


def test_a_bare_name_not_shipped_is_a_path(tmp_path):
    assert resolve_weights("no_such_weights.npz") == resolve_weights("no_such_weights.npz")
    assert resolve_weights("no_such_weights.npz").parent != WEIGHTS_DIR
    assert resolve_weights(str(tmp_path / SHIPPED_WEIGHTS)) == tmp_path / SHIPPED_WEIGHTS


def test_golden_descriptors_of_real_kitti_scans():
    files = sorted(SAMPLES.glob("*.bin")) if SAMPLES.is_dir() else []
    if len(files) < 2:
        pytest.skip(f"no KITTI samples in {SAMPLES}")
    desc = get_descriptor("bevplace")
    scans = [np.fromfile(f, np.float32).reshape(-1, 4)[:, :3] for f in files[:2]]
    glob = np.stack([desc.compute(s)["global"] for s in scans])
    assert np.allclose(glob[0][list(GOLDEN_AT)], GOLDEN, atol=2e-5)
    assert float(np.sum((glob[0] - glob[1]) ** 2)) == pytest.approx(GOLDEN_D01, abs=2e-5)
