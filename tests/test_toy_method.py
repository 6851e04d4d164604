"""A new method is one folder plus one registry line (issue 22).

The test writes a toy global descriptor as a package of its own in a temp
folder (class with its label and colour, its presets next to it), adds one
registry line, and runs it through ``liris extract``, ``liris eval`` with both
protocols, ``liris show`` and ``liris plot`` with no other edit.
"""

from __future__ import annotations

import json
import textwrap

import pytest
from conftest import run_cli
from synthetic_loop import loop_sequence

PACKAGE = "liris_toy_ranges"
NAME = "toy-ranges"
COLOR = "#123456"

INIT = '''
"""A toy global descriptor: the histogram of point ranges, L1 distance."""

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor


@dataclass(frozen=True)
class ToyRangesParams:
    bins: int = 8
    max_range: float = 40.0


class ToyRanges(Descriptor):
    name = "toy-ranges"
    label = "Toy Ranges"
    color = "#123456"
    params_type = ToyRangesParams
    symmetric = True

    def compute(self, points):
        r = np.linalg.norm(points[:, :2], axis=1)
        hist, _ = np.histogram(r, bins=self.params.bins, range=(0.0, self.params.max_range))
        return (hist / max(1, len(r))).astype(np.float32)

    def distance(self, a, b):
        return float(np.abs(a - b).sum()), float("nan")

    def pairwise(self, queries, database):
        d = np.abs(queries[:, None, :].astype(np.float64) - database[None, :, :]).sum(-1)
        return d, np.full(d.shape, np.nan)
'''

PRESETS = """
presets:
  coarse: {bins: 6}
  fine: {bins: 12}
"""


@pytest.fixture
def toy_method(tmp_path, monkeypatch):
    from lidar_iris_eval import descriptors

    folder = tmp_path / "pkgs" / PACKAGE
    folder.mkdir(parents=True)
    (folder / "__init__.py").write_text(textwrap.dedent(INIT))
    (folder / "presets.yaml").write_text(PRESETS)
    monkeypatch.syspath_prepend(str(tmp_path / "pkgs"))
    monkeypatch.setattr(descriptors, "_REGISTRY", dict(descriptors._REGISTRY))
    descriptors.register_descriptor(NAME, f"{PACKAGE}:ToyRanges")  # the one registry line
    return folder


def test_a_toy_method_is_one_folder_and_one_registry_line(toy_method, tmp_path, capsys):
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.plotting.style import in_method_order, method_color, method_label

    frames, exclude = 70, 10
    seq = loop_sequence(tmp_path / "seq", frames)
    cache = tmp_path / "cache"
    # its presets come from its own folder: the first one is the default
    assert get_descriptor(NAME).params.bins == 6
    assert get_descriptor(NAME, "fine").params.bins == 12

    code, _, err = run_cli(["extract", seq, "-d", NAME, "--cache-dir", cache, "-q"], capsys)
    assert code == 0, err
    run = tmp_path / "run"
    code, out, err = run_cli(["eval", seq, "--protocol", "1", "--protocol", "2", "-d",
                              f"{NAME},m2dp", "--exclude", str(exclude), "--out", run,
                              "--cache-dir", cache, "-q", "--json"], capsys)
    assert code == 0, err
    rows = {(r["protocol"], r["descriptor"]): r for r in json.loads(out)["results"]}
    assert rows[(1, NAME)]["n_queries"] == frames - exclude
    assert rows[(2, NAME)]["n_pairs"] == frames * (frames - 1)
    assert rows[(1, NAME)]["preset"] == "coarse"

    code, out, err = run_cli(["show", run], capsys)
    assert code == 0, err
    assert NAME in out

    figures = tmp_path / "figures"
    code, _, err = run_cli(["plot", run, "--out", figures], capsys)
    assert code == 0, err
    assert any(figures.rglob("*.png"))
    # its label and colour come from its class; it is listed after the built-ins
    assert method_label(NAME) == "Toy Ranges" and method_color(NAME) == COLOR
    assert in_method_order([NAME, "m2dp"]) == ["m2dp", NAME]
