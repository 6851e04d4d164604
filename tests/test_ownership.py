"""Issue 40: ``--overwrite`` replaces only what liris wrote; a user's files are never lost.

Each refusal must be one ``liris: error:`` line, exit 2, and leave every byte
of every file under the folder as it was (compared by content, not by count).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from conftest import assert_one_line_error, run_cli
from synthetic_loop import loop_sequence

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.ownership import (
    MANIFEST,
    check_new_files,
    check_replaceable,
    list_files,
    manifest_text,
    replace_folder,
)

FRAMES = 30
EVAL = ["-d", "m2dp", "--protocol", "1", "--exclude", "5", "-q"]


def snapshot(root: Path) -> dict[str, str]:
    """Every file below ``root`` (links included, not followed) and a digest of its bytes."""
    out = {}
    for path in sorted(Path(root).rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.is_symlink():
            out[rel] = "link->" + str(path.readlink())
        elif path.is_file():
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("own")
    seq = loop_sequence(root / "seq", frames=FRAMES)
    code = 0
    try:
        from lidar_iris_eval.cli import main

        main([str(a) for a in ["eval", seq, *EVAL, "--cache-dir", root / "cache",
                                "--out", root / "run"]])
    except SystemExit as exit_:
        code = exit_.code
    assert code == 0
    return root


@pytest.fixture
def seq(base, tmp_path) -> Path:
    return Path(shutil.copytree(base / "seq", tmp_path / "seq", symlinks=True))


@pytest.fixture
def run_dir(base, tmp_path) -> Path:
    return Path(shutil.copytree(base / "run", tmp_path / "run", symlinks=True))


def eval_args(seq: Path, out: Path, tmp_path: Path, *extra) -> list:
    return ["eval", seq, *EVAL, "--cache-dir", tmp_path / "cache", "--out", out, *extra]


# ---- the bar: eval --out S --overwrite and a folder with a foreign file ------------------


def test_eval_out_is_the_input_sequence(seq, tmp_path, capsys):
    before = snapshot(seq)
    assert any(k.startswith("velodyne/") for k in before) and "poses.txt" in before
    code, _, err = run_cli(eval_args(seq, seq, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, str(seq), "not a folder liris wrote")
    assert snapshot(seq) == before


def test_eval_out_is_the_parent_of_the_input(seq, tmp_path, capsys):
    parent = seq.parent
    (parent / "cache").mkdir(exist_ok=True)
    before = snapshot(parent)
    code, _, err = run_cli(eval_args(seq, parent, tmp_path, "--overwrite"), capsys)
    assert code == 2 and "Traceback" not in err
    assert snapshot(parent) == before


def test_eval_overwrite_refuses_a_run_holding_a_foreign_file(seq, run_dir, tmp_path, capsys):
    (run_dir / "protocol1" / "my-notes.txt").write_text("keep me\n")
    before = snapshot(run_dir)
    code, _, err = run_cli(eval_args(seq, run_dir, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, str(run_dir), "protocol1/my-notes.txt")
    assert snapshot(run_dir) == before


def test_eval_overwrite_refuses_a_folder_of_the_users(seq, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("\\section{x}\n")
    before = snapshot(mine)
    code, _, err = run_cli(eval_args(seq, mine, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, str(mine), "not a folder liris wrote")
    assert snapshot(mine) == before


def test_eval_overwrite_refuses_a_forged_manifest_with_extra_files(seq, run_dir, tmp_path, capsys):
    # a manifest that lists less than the folder holds does not vouch for the rest
    manifest = json.loads((run_dir / MANIFEST).read_text())
    manifest["files"] = manifest["files"][1:]
    (run_dir / MANIFEST).write_text(json.dumps(manifest))
    before = snapshot(run_dir)
    code, _, err = run_cli(eval_args(seq, run_dir, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, "which liris did not write")
    assert snapshot(run_dir) == before


def test_eval_overwrite_refuses_a_symlinked_run(seq, run_dir, tmp_path, capsys):
    link = tmp_path / "link"
    link.symlink_to(run_dir, target_is_directory=True)
    before = snapshot(run_dir)
    code, _, err = run_cli(eval_args(seq, link, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, "symbolic link")
    assert snapshot(run_dir) == before and link.is_symlink()


def test_eval_overwrite_replaces_its_own_run_with_figures_and_report(seq, run_dir, tmp_path,
                                                                     capsys):
    # what liris itself adds to a run (figures/, report/) does not block replacing it
    (run_dir / "figures").mkdir()
    (run_dir / "figures" / "pr_protocol1.png").write_bytes(b"\x89PNG")
    report = run_dir / "report"
    report.mkdir()
    (report / "index.html").write_text("<html></html>")
    (report / MANIFEST).write_text(manifest_text("report", ["index.html"]))
    code, _, err = run_cli(eval_args(seq, run_dir, tmp_path, "--overwrite"), capsys)
    assert code == 0, err
    files = list_files(run_dir)
    assert "metrics.json" in files and not any(f.startswith(("figures", "report")) for f in files)
    written = json.loads((run_dir / MANIFEST).read_text())
    assert written["kind"] == "run" and set(written["files"]) == set(files)


def test_a_report_with_a_user_file_inside_a_run_blocks_the_run(seq, run_dir, tmp_path, capsys):
    report = run_dir / "report"
    report.mkdir()
    (report / "index.html").write_text("<html></html>")
    (report / "mine.css").write_text("body{}")
    (report / MANIFEST).write_text(manifest_text("report", ["index.html"]))
    before = snapshot(run_dir)
    code, _, err = run_cli(eval_args(seq, run_dir, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, "report/mine.css")
    assert snapshot(run_dir) == before


# ---- report, export-loops, compare --plot -------------------------------------------------


def test_report_overwrite_keeps_unrelated_files(run_dir, tmp_path, capsys):
    pytest.importorskip("plotly")
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "slides.pdf").write_bytes(b"%PDF-1.4 mine")
    before = snapshot(rep)
    code, _, err = run_cli(["report", run_dir, "--out", rep, "--overwrite"], capsys)
    assert_one_line_error(code, err, str(rep), "not a folder liris wrote")
    assert snapshot(rep) == before
    # its own report it does replace
    rep2 = tmp_path / "rep2"
    assert run_cli(["report", run_dir, "--out", rep2], capsys)[0] == 0
    assert run_cli(["report", run_dir, "--out", rep2, "--overwrite"], capsys)[0] == 0
    assert set(list_files(rep2)) == set(json.loads((rep2 / MANIFEST).read_text())["files"])


def test_export_loops_refuses_an_existing_file(seq, tmp_path, capsys):
    target = tmp_path / "loops.g2o"
    target.write_text("# my pose graph\n")
    code, _, err = run_cli(eval_args(seq, tmp_path / "r1", tmp_path, "--export-loops", target),
                           capsys)
    assert_one_line_error(code, err, str(target), "--overwrite")
    assert target.read_text() == "# my pose graph\n"
    assert not (tmp_path / "r1").exists()  # refused before any work


def test_export_loops_never_replaces_an_input_file(seq, tmp_path, capsys):
    target = seq / "poses.txt"
    before = snapshot(seq)
    code, _, err = run_cli(eval_args(seq, tmp_path / "r2", tmp_path, "--export-loops", target,
                                     "--overwrite"), capsys)
    assert_one_line_error(code, err, "part of the input")
    assert snapshot(seq) == before


def test_compare_plot_refuses_an_existing_image(run_dir, base, tmp_path, capsys):
    image = tmp_path / "pr.png"
    image.write_bytes(b"\x89PNG mine")
    code, _, err = run_cli(["compare", run_dir, base / "run", "--plot", image], capsys)
    assert_one_line_error(code, err, str(image), "--overwrite")
    assert image.read_bytes() == b"\x89PNG mine"
    code, _, err = run_cli(["compare", run_dir, base / "run", "--plot", image, "--overwrite"],
                           capsys)
    assert code == 0, err
    assert image.read_bytes() != b"\x89PNG mine"


# ---- simulate --overwrite ----------------------------------------------------------------


def test_simulate_overwrite_refuses_a_real_sequence(seq, capsys):
    before = snapshot(seq)  # a KITTI-layout sequence liris simulate did not write
    code, _, err = run_cli(["simulate", seq, "--frames", "3", "--overwrite", "-q"], capsys)
    assert_one_line_error(code, err, str(seq), "liris simulate")
    assert snapshot(seq) == before


def test_simulate_overwrite_refuses_a_foreign_file_in_its_own_sequence(tmp_path, capsys):
    out = tmp_path / "sim"
    args = ["simulate", out, "--world", "tiny-same", "--frames", "3", "-q"]
    assert run_cli(args, capsys)[0] == 0
    assert run_cli([*args, "--overwrite"], capsys)[0] == 0  # its own: replaced
    (out / "velodyne" / "notes.md").write_text("mine")
    before = snapshot(out)
    code, _, err = run_cli([*args, "--overwrite"], capsys)
    assert_one_line_error(code, err, "velodyne/notes.md")
    assert snapshot(out) == before


# ---- the mechanism itself ----------------------------------------------------------------


def test_check_replaceable_cases(tmp_path):
    check_replaceable(tmp_path / "absent", ("run",))
    empty = tmp_path / "empty"
    empty.mkdir()
    check_replaceable(empty, ("run",))
    own = tmp_path / "own"
    (own / "a").mkdir(parents=True)
    (own / "a" / "x.csv").write_text("1")
    (own / MANIFEST).write_text(manifest_text("run", ["a/x.csv"]))
    check_replaceable(own, ("run",))
    with pytest.raises(LirisError, match="liris run folder, not a report"):
        check_replaceable(own, ("report",))
    (own / "a" / "y.csv").write_text("2")
    with pytest.raises(LirisError, match="a/y.csv"):
        check_replaceable(own, ("run",))
    (own / MANIFEST).write_text('{"written_by": "someone", "kind": "run", "files": []}')
    with pytest.raises(LirisError, match="not a folder liris wrote"):
        check_replaceable(own, ("run",))


def test_check_new_files_cases(tmp_path):
    check_new_files([tmp_path / "new.g2o"], False, "--export-loops")
    existing = tmp_path / "old.g2o"
    existing.write_text("x")
    with pytest.raises(LirisError, match="already exists"):
        check_new_files([existing], False, "--export-loops")
    check_new_files([existing], True, "--export-loops")
    with pytest.raises(LirisError, match="part of the input"):
        check_new_files([existing], True, "--export-loops", inputs=[tmp_path])
    with pytest.raises(LirisError, match="not a regular file"):
        check_new_files([tmp_path], True, "--export-loops")


def test_replace_folder_keeps_the_old_one_until_the_new_one_is_in(tmp_path):
    old, new = tmp_path / "t", tmp_path / "n"
    old.mkdir()
    (old / "a").write_text("old")
    new.mkdir()
    (new / "a").write_text("new")
    replace_folder(new, old)
    assert (old / "a").read_text() == "new" and not new.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["t"]  # the aside copy is gone
