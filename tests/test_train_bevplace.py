"""scripts/train_bevplace.py on tiny worlds: it trains, resumes from its checkpoint, and
writes weights the method reads (needs the ``train`` extra)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.bevplace import network

pytestmark = pytest.mark.slow

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "train_bevplace.py"


def _script():
    spec = importlib.util.spec_from_file_location("train_bevplace", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["train_bevplace"] = module
    spec.loader.exec_module(module)
    return module


def test_train_resume_and_load(tmp_path, capsys):
    pytest.importorskip("torch")
    script = _script()
    common = ["--work", str(tmp_path), "--worlds", "1", "--frames", "40", "--select-frames",
              "24", "--bn-images", "4", "--skip-baseline", "--eval-minutes", "1000"]
    script.main(common + ["--steps", "1"])
    first = capsys.readouterr().out
    assert "kept as" in first and (tmp_path / "checkpoint.pth.tar").is_file()
    script.main(common + ["--steps", "2"])
    second = capsys.readouterr().out
    assert "resumed at step 1" in second and "done: 2 steps" in second
    history = json.loads((tmp_path / "selection.json").read_text())
    assert [h["weights"] for h in history] == ["init", "trained", "trained"]
    out = tmp_path / "bevplace_sim.npz"
    with np.load(out) as z:
        assert {k: z[k].shape for k in z.files} == network.shapes()
    desc = get_descriptor("bevplace", weights=str(out))
    img = np.random.default_rng(0).integers(0, 256, (1, 201, 201)).astype(np.uint8)
    assert np.isfinite(desc.compute_images(img)).all()
