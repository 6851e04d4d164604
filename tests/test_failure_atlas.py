"""The failure atlas (issue 38 item 4): ``liris plot RUN --failures N`` and its report section."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from conftest import assert_one_line_error, run_cli

QUICK_START = ("lidar-iris", "scan-context", "m2dp", "esf")
N = 3


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from lidar_iris_eval.cli import main
    from lidar_iris_eval.simulate import simulate_sequence

    tmp = tmp_path_factory.mktemp("atlas")
    seq = simulate_sequence(tmp / "sim", preset="tiny-mixed", frames=110, azimuth_steps=128)
    try:
        main(["eval", str(seq), "--protocol", "1", "--descriptor", ",".join(QUICK_START),
              "--cache-dir", str(tmp / "cache"), "--out", str(tmp / "run"), "-q"])
    except SystemExit as exit_:
        assert not exit_.code, f"eval failed with {exit_.code}"
    return tmp / "run"


def _expected_false_positives(matches: pd.DataFrame, n: int) -> list[tuple[int, int]]:
    """Independently: wrong matches, sorted by descriptor distance (ties: query)."""
    q = matches["query"].to_numpy()
    j = matches["match"].to_numpy()
    d = matches["distance"].to_numpy()
    wrong = (j >= 0) & (matches["is_true"].to_numpy() == 0)
    order = np.lexsort((q[wrong], d[wrong]))[:n]
    return list(zip(q[wrong][order].tolist(), j[wrong][order].tolist(), strict=True))


def _panels(fig, kind: str) -> list[tuple[int, int]]:
    out = []
    for ax in fig.get_axes():
        gid = ax.get_gid() or ""
        parts = gid.split(":")
        if len(parts) == 5 and parts[0] == "failure" and parts[1] == kind and parts[4] == "gt":
            out.append((int(parts[2]), int(parts[3])))
    return out


def test_atlas_panels_are_the_lowest_distance_false_positives(run_dir):
    from lidar_iris_eval.plotting.atlas import build_failures
    from lidar_iris_eval.plotting.figures import open_run_sequence
    from lidar_iris_eval.runs import load_run

    run = load_run(run_dir)
    figures = build_failures(run, N, open_run_sequence)
    assert sorted(figures) == sorted(f"failures_{d}" for d in QUICK_START)
    for name in QUICK_START:
        matches = pd.read_csv(run_dir / "protocol1" / name / "matches.csv")
        want = _expected_false_positives(matches, N)
        assert want, name  # the tiny sequence gives every method some false positive
        assert _panels(figures[f"failures_{name}"], "fp") == want, name
        missed = _panels(figures[f"failures_{name}"], "missed")
        revisit = set(matches.loc[matches["is_revisit"] == 1, "query"].tolist())
        assert len(missed) <= N and all(q in revisit for q, _ in missed)


def test_plot_failures_writes_one_figure_per_quick_start_method(run_dir, capsys, tmp_path):
    code, out, err = run_cli(["plot", run_dir, "--failures", "2", "--out", tmp_path / "f"],
                             capsys)
    assert code == 0, err
    for name in QUICK_START:
        png = tmp_path / "f" / f"failures_{name}.png"
        assert png.stat().st_size > 20_000, name


def test_failures_must_be_positive(run_dir, capsys, tmp_path):
    code, _, err = run_cli(["plot", run_dir, "--failures", "0", "--out", tmp_path / "f"],
                           capsys)
    assert_one_line_error(code, err, "--failures")


def test_report_has_the_atlas_section(run_dir, capsys, tmp_path):
    pytest.importorskip("plotly")
    code, _, err = run_cli(["report", run_dir, "--out", tmp_path / "r", "--failures", "1"],
                           capsys)
    assert code == 0, err
    page = (tmp_path / "r" / "index.html").read_text()
    assert "Failure atlas" in page
    assert page.count("alt='failure atlas ") == len(QUICK_START)
