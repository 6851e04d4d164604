"""``liris eval`` on several sequences or a --plan file: one folder, one summary table."""

from __future__ import annotations

import json

import pytest
from conftest import assert_one_line_error, run_cli
from synthetic_loop import loop_sequence

from lidar_iris_eval.runs.plan import read_plan


@pytest.fixture(scope="module")
def two_sequences(tmp_path_factory):
    root = tmp_path_factory.mktemp("many")
    return loop_sequence(root / "a", frames=40), loop_sequence(root / "b", frames=30)


def test_several_sequences_one_folder_with_summary(two_sequences, tmp_path, capsys,
                                                   monkeypatch):
    monkeypatch.setenv("LIRIS_CACHE_DIR", str(tmp_path / "cache"))
    a, b = two_sequences
    out = tmp_path / "runs"
    code, stdout, err = run_cli(["eval", a, b, "--protocol", "1", "--protocol", "2", "-d",
                                 "m2dp", "--exclude", "10", "-q", "--out", out], capsys)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == [".liris-manifest.json", "01-a", "02-b",
                                                     "summary.csv", "summary.md"]
    lines = (out / "summary.csv").read_text().splitlines()
    assert lines[0] == "sequence,protocol,descriptor,preset,ap,f1_max,r100p,ep,n_positives"
    assert len(lines) == 1 + 2 * 2  # 2 sequences x 1 descriptor x 2 protocols
    # each row is exactly the metrics of that sequence's own run folder
    for folder in ("01-a", "02-b"):
        rows = json.loads((out / folder / "metrics.json").read_text())["results"]
        for r in rows:
            want = f"{folder},{r['protocol']},m2dp,{r['preset']},{r['ap']!r}"
            assert any(line.startswith(want) for line in lines), (want, lines)
    assert "01-a" in stdout and "02-b" in stdout
    # a second run into the same folder is refused without --overwrite
    code, _, err = run_cli(["eval", a, b, "--protocol", "2", "-d", "m2dp", "-q", "--out", out],
                           capsys)
    assert_one_line_error(code, err, "already exists")


def test_plan_file_cross_product_and_runs(two_sequences, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("LIRIS_CACHE_DIR", str(tmp_path / "cache"))
    a, b = two_sequences
    plan = tmp_path / "plan.yaml"
    plan.write_text(f"protocols: [2]\nruns:\n  - {{sequence: {a}, descriptors: [m2dp, esf]}}\n"
                    f"  - {{sequence: {b.name}, protocols: [1, 2]}}\n")
    (tmp_path / b.name).symlink_to(b)  # relative paths are read next to the plan
    runs = read_plan(plan, "scan-context", ("1",))
    assert [(r.descriptors, r.protocols) for r in runs] == [("m2dp,esf", ("2",)),
                                                            ("scan-context", ("1", "2"))]
    assert runs[1].sequence == tmp_path / b.name
    out = tmp_path / "planned"
    code, _, err = run_cli(["eval", "--plan", plan, "-d", "scan-context", "--protocol", "1",
                            "--exclude", "10", "-q", "--out", out], capsys)
    assert code == 0, err
    rows = (out / "summary.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 + 2  # m2dp and esf on protocol 2; scan-context on 1 and 2
    cross = tmp_path / "cross.yaml"
    cross.write_text(f"sequences: [{a}, {b}]\ndescriptors: m2dp\nprotocols: 2\n")
    assert [r.protocols for r in read_plan(cross, None, ())] == [("2",), ("2",)]


@pytest.mark.parametrize("text, fragment", [
    ("sequences: []\n", "sequences"),
    ("runs:\n  - {descriptors: m2dp}\n", "needs a sequence"),
    ("sequences: [x]\nfoo: 1\n", "unknown key"),
    ("sequences: [x]\nprotocols: [3]\n", "protocols must be"),
    (": : :\n", "not valid YAML"),
])
def test_bad_plans_are_one_line_errors(tmp_path, capsys, text, fragment):
    plan = tmp_path / "plan.yaml"
    plan.write_text(text)
    code, _, err = run_cli(["eval", "--plan", plan, "-d", "m2dp", "--protocol", "2", "-q"],
                           capsys)
    assert_one_line_error(code, err, fragment)
