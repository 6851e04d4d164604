"""CI regression: OverlapTransformer on the built-in ``small-mixed`` sequence, shipped and
random weights.

Pins the README's OverlapTransformer row (E = 30, gt poses): protocol 1 and protocol 2
AP, F1max and R@100P for liris' simulated-world weights (``ot_sim_weights.npz``), so a
change of the range image, the network or the shipped file shows up here and must update
the README (and MODEL_CARD.md) with it. The independent check beside the pins: the
trained weights beat the model card's ``random-init`` figures (AP 0.140 / 0.164), which
are not rerun here to keep CI's time.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from lidar_iris_eval.cli import main
from lidar_iris_eval.simulate import simulate_sequence

pytestmark = pytest.mark.slow

README = Path(__file__).resolve().parents[1] / "README.md"

#: the README's OverlapTransformer row: protocol 1 (AP, F1max, R@100P), then protocol 2
README_OT = {
    "paper": (0.447, 0.540, 0.044, 0.381, 0.393, 0.006),
}


@pytest.fixture(scope="module")
def ot_rows(tmp_path_factory):
    root = tmp_path_factory.mktemp("ot-small-mixed")
    seq = simulate_sequence(root / "seq", preset="small-mixed")
    rows = {}
    for preset, extra in (("paper", []),):
        run = root / preset
        main(["eval", str(seq), "--protocol", "1", "--protocol", "2", "--descriptor",
              "overlap-transformer", *extra, "--cache-dir", str(root / "cache"),
              "--out", str(run), "--quiet"])
        metrics = json.loads((run / "metrics.json").read_text())
        rows.update({(preset, r["protocol"]): r for r in metrics["results"]})
    return rows


def _pinned(p1, p2) -> tuple:
    return tuple(round(r[k], 3) for r in (p1, p2) for k in ("ap", "f1_max", "r100p"))


@pytest.mark.parametrize("preset", sorted(README_OT))
def test_overlap_transformer_figures_equal_the_readme(ot_rows, preset):
    assert _pinned(ot_rows[(preset, 1)], ot_rows[(preset, 2)]) == README_OT[preset]


@pytest.mark.parametrize("preset", sorted(README_OT))
def test_the_readme_prints_the_pinned_row(preset):
    row = next(line for line in README.read_text().splitlines()
               if line.startswith(f"| OverlapTransformer `{preset}`"))
    cells = re.findall(r"\d+\.\d+", row)
    assert cells[:6] == [format(v, ".3f") for v in README_OT[preset]]


#: the model card's random-init figures on the same sequence: (P1, P2) AP and F1max
RANDOM_INIT = {1: (0.140, 0.339), 2: (0.164, 0.223)}


def test_trained_weights_beat_the_random_ones_and_say_so(ot_rows):
    for protocol, (ap, f1) in RANDOM_INIT.items():
        trained = ot_rows[("paper", protocol)]
        assert trained["ap"] > ap and trained["f1_max"] > f1
    assert ot_rows[("paper", 1)]["weights"] == "ot_sim_weights.npz"
    assert ot_rows[("paper", 1)]["weights_trained"]
