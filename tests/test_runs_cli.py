"""``liris show`` / ``liris compare``: reading run folders back without recomputing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_protocols import two_pass_sequence

from lidar_iris_eval.descriptors import _REGISTRY
from lidar_iris_eval.runs import load_run, render_table, table_row


@pytest.fixture(autouse=True)
def toys(monkeypatch):
    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")
    monkeypatch.setitem(_REGISTRY, "toy-asym", "test_protocols:ToyAsym")


@pytest.fixture
def seq_dir(tmp_path):
    return two_pass_sequence(tmp_path / "seq", n_per_pass=12)


def make_run(seq_dir, tmp_path, capsys, name, *extra):
    args = ["eval", seq_dir, "--protocol", "1", "--protocol", "2", "-d", "toy,toy-asym",
            "--exclude", "5", "--cache-dir", tmp_path / "cache", "--out", tmp_path / name, "-q",
            *extra]
    code, out, err = run_cli(args, capsys)
    assert code == 0, err
    return tmp_path / name, out


def test_show_prints_the_table_eval_printed(seq_dir, tmp_path, capsys):
    run_dir, printed = make_run(seq_dir, tmp_path, capsys, "run")
    code, out, err = run_cli(["show", run_dir, "--no-conventions"], capsys)
    assert code == 0, err
    table = printed.split("\nconventions:")[0]
    assert out.rstrip("\n") == table.rstrip("\n")


def test_show_formats_hold_the_metrics_of_metrics_json(seq_dir, tmp_path, capsys):
    run_dir, _ = make_run(seq_dir, tmp_path, capsys, "run")
    rows = json.loads((run_dir / "metrics.json").read_text())["results"]
    code, out, _ = run_cli(["show", run_dir, "--format", "csv", "--no-conventions"], capsys)
    assert code == 0
    lines = out.strip().splitlines()
    assert lines[0].startswith("protocol,descriptor,preset,ap,f1_max")
    assert len(lines) == 1 + len(rows)
    first = lines[1].split(",")
    assert float(first[3]) == rows[0]["ap"]  # full precision in CSV
    code, out, _ = run_cli(["show", run_dir, "--format", "markdown", "--no-conventions"], capsys)
    md = out.strip().splitlines()
    assert md[0].startswith("| protocol | descriptor |") and set(md[1]) <= set("|-:")
    assert len(md) == 2 + len(rows)
    code, out, _ = run_cli(["show", run_dir, "--format", "latex", "--no-conventions"], capsys)
    assert out.startswith("\\begin{tabular}") and "f1\\_max" in out
    assert out.count("\\\\") == 1 + len(rows)


def test_show_states_the_conventions(seq_dir, tmp_path, capsys):
    run_dir, _ = make_run(seq_dir, tmp_path, capsys, "run", "--recall-denominator", "accepted")
    code, out, _ = run_cli(["show", run_dir], capsys)
    assert "exclusion: E=5 frames" in out
    assert "protocol 1 recall denominator: accepted" in out
    assert "positive: ground-truth distance < 4 m" in out


def test_table_row_is_the_same_from_memory_and_from_json():
    row = {"protocol": 1, "descriptor": "x", "preset": "p", "ap": np.float64(0.5),
           "f1_max": float("nan"), "r100p": 0.25, "ep": 0.1, "n_queries": np.int64(1234),
           "n_positives": 7, "extract_ms_per_scan": 1.0, "match_ms_per_query": 0.5}
    from_json = json.loads(json.dumps({k: (None if isinstance(v, float) and v != v else
                                           (v.item() if hasattr(v, "item") else v))
                                       for k, v in row.items()}))
    assert table_row(row) == table_row(from_json)
    assert render_table([row]) == render_table([from_json])
    assert "1,234" in render_table([row]) and " n/a " in render_table([row])


def test_compare_a_run_with_itself_has_no_difference(seq_dir, tmp_path, capsys):
    run_dir, _ = make_run(seq_dir, tmp_path, capsys, "run")
    code, out, err = run_cli(["compare", run_dir, run_dir, "--plot", tmp_path / "pr.png"],
                             capsys)
    assert code == 0, err
    assert "0 metric value(s) differ from run" in out
    assert "conventions and settings: identical" in out
    assert (tmp_path / "pr.png").stat().st_size > 1000


def test_compare_names_the_differing_conventions(seq_dir, tmp_path, capsys):
    a, _ = make_run(seq_dir, tmp_path, capsys, "a")
    b, _ = make_run(seq_dir, tmp_path, capsys, "b", "--radius", "2", "--recall-denominator",
                    "accepted")
    code, out, _ = run_cli(["compare", a, b, "--format", "csv"], capsys)
    assert code == 0
    assert "radius (m),4.0,2.0" in out
    assert "recall denominator,revisits,accepted" in out
    # the differences are exactly b - a, row by row
    ra, rb = load_run(a), load_run(b)
    for row_a, row_b in zip(ra.rows, rb.rows, strict=True):
        line = f"{row_a['protocol']},{row_a['descriptor']},{row_a['preset']},ap,"
        found = [x for x in out.splitlines() if x.startswith(line)]
        assert len(found) == 1
        diff = float(found[0].split(",")[-1])
        assert diff == pytest.approx(row_b["ap"] - row_a["ap"], abs=0)


def test_show_and_compare_refuse_a_folder_that_is_not_a_run(tmp_path, capsys):
    code, _, err = run_cli(["show", tmp_path], capsys)
    assert_one_line_error(code, err, "no metrics.json")
    code, _, err = run_cli(["compare", tmp_path / "nope", tmp_path], capsys)
    assert_one_line_error(code, err, "run folder not found")
    code, _, err = run_cli(["compare", tmp_path], capsys)
    assert_one_line_error(code, err, "at least two")


#: a broken part of a run folder -> (file written, its content, what the message says)
BROKEN = {
    "metrics-not-json": ("metrics.json", "{results: [", "not valid JSON"),
    "metrics-no-results": ("metrics.json", '{"version": "x"}', "no 'results' list"),
    "row-without-descriptor": ("metrics.json", '{"results": [{"protocol": 1}]}',
                               "every result needs 'protocol' and 'descriptor'"),
    "config-not-mapping": ("config.yaml", "- a\n- b\n", "expected a mapping"),
    "config-not-yaml": ("config.yaml", "a: [1,\n  b: {\n", "not valid YAML"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
@pytest.mark.parametrize("command", ["show", "compare", "report", "plot"])
def test_every_reader_of_runs_words_a_broken_run_alike(tmp_path, capsys, case, command):
    """show, compare, report and plot read run folders through one reader (runs/reader),
    so the same broken file gives the same single line naming it."""
    name, content, problem = BROKEN[case]
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text('{"results": []}')
    (run_dir / name).write_text(content)
    args = {"show": ["show", run_dir], "compare": ["compare", run_dir, run_dir],
            "report": ["report", run_dir, "--out", tmp_path / "page"],
            "plot": ["plot", run_dir, "--out", tmp_path / "figs"]}[command]
    code, _, err = run_cli(args, capsys)
    assert_one_line_error(code, err, f"{run_dir / name}: {problem}")
    assert not (tmp_path / "figs").exists() and not (tmp_path / "page").exists()


@pytest.mark.parametrize("command", ["show", "plot"])
def test_a_file_is_not_a_run_folder(tmp_path, capsys, command):
    target = tmp_path / "metrics.json"
    target.write_text('{"results": []}')
    code, _, err = run_cli([command, target], capsys)
    assert_one_line_error(code, err, f"{target}: not a run folder")


def test_the_parent_of_a_multi_sequence_run_points_to_its_run_folders(tmp_path, capsys):
    parent = tmp_path / "multi"
    (parent / "01-seq").mkdir(parents=True)
    (parent / "summary.csv").write_text("sequence,protocol\n")
    code, _, err = run_cli(["show", parent], capsys)
    assert_one_line_error(code, err, f"{parent}: a multi-sequence run", "NN-<sequence>/")
