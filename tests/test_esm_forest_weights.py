"""The ESM weights trained on simulated forests (issue 37 item 4): by name only, never the default.

``esm_forest_weights.npz`` (model card, "esm_forest_weights.npz") is opt-in
(``--param esm.weights=esm_forest_weights.npz``); no preset names it, so every pinned
figure keeps the urban-trained weights. Its figures live in ``esm_forest_validation.json``,
written by the training run; the file must be the one those figures were measured on.
Its embeddings are pinned by ``tests/data/esm_forest_golden.npz``
(``test_esm_descriptor.py::test_golden_embeddings_of_the_shipped_weights``).
"""

from __future__ import annotations

import json

import pytest
import yaml

from lidar_iris_eval.cli.descriptor_options import build_descriptors
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm import network

NAME = "esm_forest_weights.npz"
FOREST = network.WEIGHTS_FILE.with_name(NAME)
FIGURES = network.WEIGHTS_FILE.with_name("esm_forest_validation.json")
PRESETS = network.WEIGHTS_FILE.with_name("presets.yaml")


@pytest.fixture
def forest():
    assert FOREST.is_file(), f"{NAME} is shipped in the package folder (model card)"
    return FOREST


def test_the_param_loads_the_shipped_file_by_name(forest):
    (esm,) = build_descriptors("esm", None, params=(f"esm.weights={NAME}",))
    assert esm.weights_path == forest
    assert esm.run_info()["weights"] == NAME
    assert esm.cache_token() == network.sha256_of(forest)[:16]
    w, arch = esm.weights()
    assert arch.align_yaw  # trained with --align-yaw, as the other local-map weights
    assert w.keys() == network.load_weights(network.LOCALMAP_WEIGHTS_FILE)[0].keys()


def test_no_preset_uses_the_forest_weights(forest):
    presets = yaml.safe_load(PRESETS.read_text())["presets"]
    assert {"local-maps", "single-scan"} <= presets.keys()
    for name in presets:
        assert get_descriptor("esm", name).weights_path != forest, name
    (default,) = build_descriptors("esm", None)
    # the default is the local-map preset's network (docs/esm.md), not the forest one
    assert default.weights_path == network.WEIGHTS_FILE.with_name(
        "esm_localmap_simreal_weights.npz")


def test_the_figures_belong_to_this_file_and_follow_the_selection_rule(forest):
    log = json.loads(FIGURES.read_text())
    assert log["sha256"] == network.sha256_of(forest)
    assert log["init"] is None  # trained from scratch (model card)
    checks = log["selection_checks"]
    assert len(checks) >= 3
    # the kept checkpoint is the best selection-set AUC, never a test-set figure
    assert log["selected_step"] == max(checks, key=lambda c: c["auc"])["step"]
    assert 0.5 < log["validation"]["auc"] <= 1.0
