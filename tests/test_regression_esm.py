"""CI regression: ESM in both modes on the built-in ``small-mixed`` sequence.

Pins the README's ESM table (protocol 1, E = 30, gt poses): AP, F1max and
R@100P to 3 decimals and the median loop-pose errors of the true matches, so
a change of the local-map pipeline, the segment tracking, the embedding cache
or either shipped network shows up here and must update the README with it.
The independent checks beside the pins: the local-map mode finds the
reverse-direction revisits and beats the single-scan mode, which is not the
authors' setting.
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

#: the README's ESM table: (AP, F1max, R@100P, median translation m, median rotation deg)
README_ESM = {
    "local-maps": (0.992, 0.990, 0.759, 0.155, 0.19),
    "single-scan": (0.211, 0.349, 0.034, 0.096, 0.73),
}


@pytest.fixture(scope="module")
def esm_rows(tmp_path_factory):
    root = tmp_path_factory.mktemp("esm-small-mixed")
    seq = simulate_sequence(root / "seq", preset="small-mixed")
    rows = {}
    for name in ("esm", "esm:single-scan"):  # one preset of a method per run
        run = root / name.replace(":", "-")
        main(["eval", str(seq), "--protocol", "1", "--descriptor", name,
              "--cache-dir", str(root / "cache"), "--out", str(run), "--quiet"])
        metrics = json.loads((run / "metrics.json").read_text())
        rows.update({r["preset"]: r for r in metrics["results"]})
    return rows


def _pinned(row) -> tuple:
    return (round(row["ap"], 3), round(row["f1_max"], 3), round(row["r100p"], 3),
            round(row["rte_m_median"], 3), round(row["rre_deg_median"], 2))


@pytest.mark.parametrize("preset", sorted(README_ESM))
def test_esm_figures_equal_the_readme(esm_rows, preset):
    assert _pinned(esm_rows[preset]) == README_ESM[preset]


@pytest.mark.parametrize("preset", sorted(README_ESM))
def test_the_readme_prints_the_pinned_row(preset):
    ap, f1, r100, rte, rre = README_ESM[preset]
    row = next(line for line in README.read_text().splitlines()
               if line.startswith(f"| `{preset}`"))
    cells = re.findall(r"\d+\.\d+", row)
    assert cells[:5] == [f"{ap:.3f}", f"{f1:.3f}", f"{r100:.3f}", f"{rte:.3f}", f"{rre:.2f}"]


def test_local_maps_find_reverse_revisits_and_beat_single_scans(esm_rows):
    lm, ss = esm_rows["local-maps"], esm_rows["single-scan"]
    assert lm["f1_max"] >= 0.8 and lm["top1_reverse"] >= 0.9
    # the loop-pose bar on simulated sequences
    assert lm["rte_m_median"] < 0.3 and lm["rre_deg_median"] < 2.0
    assert lm["f1_max"] > ss["f1_max"] + 0.3
    assert lm["weights"] == "esm_localmap_simreal_weights.npz"
    assert ss["weights"] == "esm_weights.npz"
