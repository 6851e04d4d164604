"""CI regression: BEVPlace++ on the built-in ``small-mixed`` sequence, shipped and random weights.

Pins the README's BEVPlace++ row (E = 30, gt poses): protocol 1 AP, F1max,
R@100P and the median pose errors of the true top-1 matches, protocol 2 AP and
F1max, for the shipped simulated-world weights, so a change of the BEV image,
the network, the pose or the shipped file shows up here and must update the
README (and MODEL_CARD.md) with it. About 3-4 minutes on one thread; the
``random-init`` figures (model card) are not run here, to keep CI's time
(the shipped file's golden descriptors are pinned in test_bevplace_weights.py).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.cli import main
from lidar_iris_eval.simulate import simulate_sequence

pytestmark = pytest.mark.slow

README = Path(__file__).resolve().parents[1] / "README.md"

#: the README's BEVPlace++ table: protocol 1 (AP, F1max, R@100P, RR, median translation m,
#: median rotation deg), then protocol 2 (AP, F1max)
README_BEVPLACE = {
    "paper": (0.794, 0.826, 0.369, 0.976, 0.66, 0.88, 0.567, 0.529),
}


@pytest.fixture(scope="module")
def bevplace_rows(tmp_path_factory):
    root = tmp_path_factory.mktemp("bevplace-small-mixed")
    seq = simulate_sequence(root / "seq", preset="small-mixed")
    rows = {}
    for name in ("bevplace",):
        run = root / name.replace(":", "-")
        main(["eval", str(seq), "--protocol", "1", "--protocol", "2", "--descriptor", name,
              "--cache-dir", str(root / "cache"), "--out", str(run), "--quiet"])
        metrics = json.loads((run / "metrics.json").read_text())
        rows.update({(r["preset"], r["protocol"]): r for r in metrics["results"]})
    return rows


def _pinned(p1, p2) -> tuple:
    return (round(p1["ap"], 3), round(p1["f1_max"], 3), round(p1["r100p"], 3),
            round(p1["rr"], 3), round(p1["rte_m_median"], 2), round(p1["rre_deg_median"], 2),
            round(p2["ap"], 3), round(p2["f1_max"], 3))


@pytest.mark.parametrize("preset", sorted(README_BEVPLACE))
def test_bevplace_figures_equal_the_readme(bevplace_rows, preset):
    got = _pinned(bevplace_rows[(preset, 1)], bevplace_rows[(preset, 2)])
    want = README_BEVPLACE[preset]
    assert got[:4] + got[6:] == want[:4] + want[6:]
    # the pose medians sit near a rounding edge: the same code printed 0.66 m on an
    # AVX-512 machine and 0.67 m on an AVX2 one (2026-12-07), so one unit of the
    # printed digit is allowed there
    np.testing.assert_allclose(got[4:6], want[4:6], rtol=0, atol=0.0101)


@pytest.mark.parametrize("preset", sorted(README_BEVPLACE))
def test_the_readme_prints_the_pinned_row(preset):
    row = next(line for line in README.read_text().splitlines()
               if line.startswith(f"| `{preset}`") and "bevplace" in line)
    cells = re.findall(r"\d+\.\d+", row)
    want = README_BEVPLACE[preset]
    fmt = (".3f", ".3f", ".3f", ".3f", ".2f", ".2f", ".3f", ".3f")
    assert cells[:8] == [format(v, f) for v, f in zip(want, fmt, strict=True)]


def test_the_shipped_weights_say_what_they_are(bevplace_rows):
    shipped = bevplace_rows[("paper", 1)]
    assert shipped["weights"] == "bevplace_sim_weights.npz" and shipped["weights_trained"]
