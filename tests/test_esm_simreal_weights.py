"""The `local-maps` preset's weights: the real fine-tune with its quality branch refit.

``esm_localmap_simreal_weights.npz`` (model card) is ``esm_localmap_real_weights.npz``'s
network with only the quality branch (``q.w``, ``q.b``) trained again, on the segments
that have a partner (``metrics.quality_examples``). So every embedding tensor must be
the real fine-tune's to the bit and the quality branch must differ; the preset must use
it, and the weights it replaced must stay reachable by name.
"""

from __future__ import annotations

import json

import numpy as np

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm import network

NEW = network.WEIGHTS_FILE.with_name("esm_localmap_simreal_weights.npz")
REAL = network.WEIGHTS_FILE.with_name("esm_localmap_real_weights.npz")


def _arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_only_the_quality_branch_differs_from_the_real_fine_tune():
    new, real = _arrays(NEW), _arrays(REAL)
    assert new.keys() == real.keys()
    quality = {"q.w", "q.b"}
    for key in new.keys() - quality:
        assert np.array_equal(new[key], real[key]), key
    assert not np.allclose(new["q.w"], real["q.w"])


def test_the_preset_uses_it_and_the_old_weights_stay_reachable():
    assert get_descriptor("esm", "local-maps").weights_path == NEW
    assert get_descriptor("esm").weights_path == NEW
    assert get_descriptor("esm", "local-maps").params.grow == "degree"
    for name in ("esm_localmap_weights.npz", "esm_localmap_real_weights.npz"):
        assert network.resolve_weights(name).is_file()
        assert get_descriptor("esm", "local-maps", weights=name).weights_path.name == name


def test_its_validation_record_says_what_was_refit():
    log = json.loads(NEW.with_name("esm_localmap_simreal_validation.json").read_text())
    assert log["sha256"] == network.sha256_of(NEW)
    assert log["quality_refit_only"] is True and log["init"] == REAL.name
    # examples are segments with a partner: the positive rate is not the ~7 % of all
    # segments (most Riverside segments are never seen again) the old labels gave
    assert 0.2 < log["quality_positive_rate"] < 0.8
