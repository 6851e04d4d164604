"""Regression tests for the small defects of issue 39 (D1-D9); each fails on the release."""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]


# --- D3: the docs' runnable snippets run -------------------------------------------------

#: an HTML comment on the line just before a ```python fence marks the block runnable:
#: ``<!-- runnable -->`` executes it; ``<!-- runnable: name.py -->`` saves it as that module
#: (importable by the later blocks of the same page) instead of executing it.
_MARKED = re.compile(r"<!--\s*runnable(?::\s*(?P<file>[\w.]+))?\s*-->\n"
                     r"```python\n(?P<code>.*?)\n```", re.S)


def _runnable_pages():
    return sorted(p for p in (ROOT / "docs").glob("*.md") if _MARKED.search(p.read_text()))


def test_adding_a_method_example_is_marked_runnable():
    assert ROOT / "docs" / "adding-a-method.md" in _runnable_pages()


@pytest.mark.parametrize("page", _runnable_pages(), ids=lambda p: p.name)
def test_docs_runnable_snippets_execute(page, tmp_path, monkeypatch):
    """Run every runnable block of ``page`` in order, in a fresh folder.

    Marker (documented here, used in docs/*.md): ``<!-- runnable -->`` or
    ``<!-- runnable: my_module.py -->`` on the line immediately before a ```python fence.
    The folder holds ``sim/tiny-mixed`` (``liris simulate sim/tiny-mixed --world tiny-mixed``),
    the sequence the docs' examples name.
    """
    from lidar_iris_eval.cli import cli

    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli, ["simulate", "sim/tiny-mixed", "--world", "tiny-mixed"])
    assert result.exit_code == 0, result.output
    monkeypatch.syspath_prepend(str(tmp_path))
    ran = 0
    for m in _MARKED.finditer(page.read_text()):
        if m["file"]:
            (tmp_path / m["file"]).write_text(m["code"] + "\n")
            sys.modules.pop(Path(m["file"]).stem, None)
            continue
        script = tmp_path / f"snippet_{ran}.py"
        script.write_text(m["code"] + "\n")
        runpy.run_path(str(script), run_name="__main__")
        ran += 1
    assert ran >= 1


# --- D5: one definition of the E presets ---------------------------------------------------

def test_exclude_presets_defined_once():
    pattern = re.compile(r"^\s*EXCLUDE_PRESETS\s*(:[^=]*)?=", re.M)
    defining = [p for p in (ROOT / "lidar_iris_eval").rglob("*.py")
                if pattern.search(p.read_text())]
    assert [p.relative_to(ROOT).as_posix() for p in defining] == \
        ["lidar_iris_eval/evaluation/settings.py"]
    resolvers = [p for p in (ROOT / "lidar_iris_eval").rglob("*.py")
                 if re.search(r"^def resolve_exclude\b", p.read_text(), re.M)]
    assert len(resolvers) == 1


def test_cli_exclude_uses_the_settings_presets(monkeypatch):
    from lidar_iris_eval.cli import options
    from lidar_iris_eval.evaluation import settings

    assert options.EXCLUDE_PRESETS is settings.EXCLUDE_PRESETS
    monkeypatch.setitem(settings.EXCLUDE_PRESETS, "tiny", 7)
    assert options.parse_exclude("tiny") == (7, "tiny")
    assert options.parse_exclude("7") == (7, "tiny")
    assert options.parse_exclude("12") == (12, "custom")


# --- D9: every repository path named in a shipped comment or docstring exists --------------

_PATH = re.compile(r"(?P<before>\S*\s)?``?(?P<path>(?:lidar_iris_eval|configs|docs|scripts)/"
                   r"[\w./-]*\.(?:py|yaml|md))\b|(?P<before2>\S*\s)?"
                   r"\b(?P<path2>(?:lidar_iris_eval|configs|docs|scripts)/[\w./-]*\.(?:py|yaml|md))\b")


def _shipped_files():
    for pattern in ("lidar_iris_eval/**/*.py", "lidar_iris_eval/**/*.yaml", "scripts/**/*.py"):
        yield from ROOT.glob(pattern)


def _named_paths(text):
    """Repository paths in ``text``; a path qualified by another repository
    (``owner/repo scripts/x.py`` or ``some-repo scripts/x.py``) names that repository's file."""
    for m in _PATH.finditer(text):
        path = m["path"] or m["path2"]
        before = (m["before"] or m["before2"] or "").strip().strip("`(")
        if "-" in before or re.fullmatch(r"[\w.-]+/[\w.-]+", before):
            continue
        yield path


def test_paths_in_shipped_comments_exist():
    missing = []
    for f in _shipped_files():
        for path in _named_paths(f.read_text()):
            if not (ROOT / path).exists() and not (ROOT / "lidar_iris_eval" / path).exists():
                missing.append(f"{f.relative_to(ROOT)}: {path}")
    assert missing == []


def test_path_scan_sees_the_stale_kind():
    assert list(_named_paths("# See lidar_iris_eval/descriptors/m2dp.py.")) == \
        ["lidar_iris_eval/descriptors/m2dp.py"]
    assert list(_named_paths("contour-context ``scripts/pr_mpe.py``")) == []


def test_blocks_names_the_executor_module():
    text = (ROOT / "lidar_iris_eval" / "matching" / "blocks.py").read_text()
    assert ":mod:`lidar_iris_eval.engine`" not in text



# --- D4: the --convention help lists the presets table -------------------------------------

def test_eval_help_lists_a_new_preset(monkeypatch):
    from lidar_iris_eval.cli import cli as main
    from lidar_iris_eval.evaluation import conventions
    from lidar_iris_eval.evaluation.settings import Settings

    monkeypatch.setitem(conventions.PRESETS, "zz-new-preset", Settings(name="zz-new-preset"))
    result = CliRunner().invoke(main, ["eval", "--help"], terminal_width=400)
    assert result.exit_code == 0, result.output
    assert "zz-new-preset" in result.output
    for name in conventions.CROSS_SESSION_PRESETS:
        assert name in result.output


# --- D6: config_extra uses its convention ---------------------------------------------------

def test_config_extra_uses_its_convention():
    import click

    from lidar_iris_eval.cli.workflow import config_extra
    from lidar_iris_eval.evaluation.settings import Settings

    with click.Context(click.Command("eval")):
        named = config_extra(Settings(name="my-rules"))
        plain = config_extra()
    assert named["command"]["convention"] == "my-rules"
    assert "convention" not in plain["command"]


# --- D8: score_protocol1 takes the recall denominator's value ---------------------------------

def _tiny_scoring_inputs():
    import numpy as np

    from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
    from lidar_iris_eval.matching.blocks import BestMatches

    rng = np.random.default_rng(3)
    n = 80
    t = np.linspace(0, 4 * np.pi, n)
    positions = np.c_[20 * np.cos(t), 20 * np.sin(t), np.zeros(n)] + rng.normal(0, 0.3, (n, 3))
    gt = compute_ground_truth(positions, 4.0, 10, "3d", "lidar")
    query = np.flatnonzero(gt.query_limits() >= 0)
    match = np.array([int(rng.integers(0, max(1, q - 10))) for q in query])
    dist = rng.random(len(query))
    return positions, gt, BestMatches(query=query, match=match, distance=dist,
                                      yaw_deg=np.full(len(query), np.nan), seconds=0.0,
                                      n_evaluations=0, source="exhaustive")


def test_score_protocol1_takes_the_denominator_value_not_settings():
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.evaluation.protocol1 import score_protocol1
    from lidar_iris_eval.evaluation.settings import Settings

    positions, gt, matches = _tiny_scoring_inputs()
    with pytest.raises((LirisError, TypeError)):
        score_protocol1(matches, positions, gt, Settings(recall_denominator="accepted"))
    by_value = score_protocol1(matches, positions, gt, "accepted")
    assert by_value.metrics["n_queries"] == len(matches.query)


# --- D1: protocols_1_and_2 honours candidates for a global descriptor ---------------------------

@pytest.fixture(scope="module")
def tiny_mixed(tmp_path_factory):
    from lidar_iris_eval.cli import cli

    out = tmp_path_factory.mktemp("sim") / "tiny-mixed"
    result = CliRunner().invoke(cli, ["simulate", str(out), "--world", "tiny-mixed"])
    assert result.exit_code == 0, result.output
    return out


def test_protocols_1_and_2_honours_candidates(tiny_mixed, tmp_path):
    import numpy as np

    from lidar_iris_eval.evaluation.evaluate import Settings, evaluate
    from lidar_iris_eval.evaluation.protocol1 import protocol1
    from lidar_iris_eval.evaluation.protocol2 import protocol2, protocols_1_and_2

    settings = Settings(candidates=3)
    run = evaluate(tiny_mixed, ["scan-context"], protocols=(1,), settings=settings,
                   cache=tmp_path / "cache")
    result = run.results[0]
    desc, stacked = result.descriptor, result.db.descriptors
    positions = run.sequence.positions(run.pose_frame)
    alone = protocol1(desc, stacked, positions, settings)
    p1, p2 = protocols_1_and_2(desc, stacked, positions, settings)
    assert alone.matches.source == "candidates:3"
    assert p1.matches.source == alone.matches.source
    np.testing.assert_array_equal(p1.matches.match, alone.matches.match)
    assert p1.metrics["ap"] == alone.metrics["ap"]
    exhaustive = protocol2(desc, stacked, positions, settings.replace(candidates=None))
    assert p2.metrics == exhaustive.metrics


# --- D2: a run written through the API with a custom Settings replays with its conventions ------

def test_api_run_with_custom_settings_replays_with_its_conventions(tiny_mixed, tmp_path):
    import yaml

    from lidar_iris_eval.cli import cli
    from lidar_iris_eval.evaluation.evaluate import Settings, evaluate
    from lidar_iris_eval.runs.reader import load_run
    from lidar_iris_eval.runs.writer import write_run

    custom = Settings(inclusive_radius=True, not_revisit_radius=10.0, last_frame_query=False)
    run = evaluate(tiny_mixed, ["scan-context"], protocols=(1,), settings=custom,
                   cache=tmp_path / "cache")
    write_run(run, tmp_path / "api")
    result = CliRunner().invoke(cli, ["eval", "--config", str(tmp_path / "api" / "config.yaml"),
                                      "--out", str(tmp_path / "replay"), "--cache-dir",
                                      str(tmp_path / "cache"), "--quiet"])
    assert result.exit_code == 0, result.output
    original, replay = load_run(tmp_path / "api"), load_run(tmp_path / "replay")
    assert replay.gt_settings() == original.gt_settings()
    assert replay.gt_settings().name == "custom"
    (row,) = [r for r in replay.rows if r["protocol"] == 1]
    (expected,) = [r for r in run.rows if r["protocol"] == 1]
    assert (row["ap"], row["n_queries"]) == (expected["ap"], expected["n_queries"])
    # the conventions are stored once: the convention block, no flat copy to disagree with it
    config = yaml.safe_load((tmp_path / "replay" / "config.yaml").read_text())
    assert not {"radius", "exclude", "distance", "recall_denominator"} & set(config)
    assert config["convention"]["not_revisit_radius"] == 10.0


def test_old_run_without_convention_block_replays_from_flat_keys(tiny_mixed, tmp_path):
    import yaml

    from lidar_iris_eval.cli import cli
    from lidar_iris_eval.runs.reader import load_run

    base = ["--cache-dir", str(tmp_path / "cache"), "--quiet"]
    result = CliRunner().invoke(cli, ["eval", str(tiny_mixed), "-d", "scan-context",
                                      "--protocol", "1", "--out", str(tmp_path / "new"), *base])
    assert result.exit_code == 0, result.output
    config = yaml.safe_load((tmp_path / "new" / "config.yaml").read_text())
    block = config.pop("convention")
    config.update(radius=7.5, exclude={"value": 40, "preset": "custom"}, distance="planar",
                  recall_denominator="accepted", pose_frame=block["pose_frame"])
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "config.yaml").write_text(yaml.safe_dump(config))
    result = CliRunner().invoke(cli, ["eval", "--config", str(tmp_path / "old"),
                                      "--out", str(tmp_path / "replay"), *base])
    assert result.exit_code == 0, result.output
    s = load_run(tmp_path / "replay").gt_settings()
    assert (s.radius, s.exclude, s.distance, s.recall_denominator) == (7.5, 40, "planar",
                                                                         "accepted")


# --- no import circle in the package (simulate/pipeline.py <-> simulate/sessions.py was one) -----

def _circles(modules, imports_of) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan, iterative)."""
    index, low, on, stack, found = {}, {}, set(), [], []
    for root in modules:
        if root in index:
            continue
        work = [(root, iter(sorted(imports_of(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on.add(child)
                    work.append((child, iter(sorted(imports_of(child)))))
                elif child in on:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    top = stack.pop()
                    on.discard(top)
                    group.append(top)
                    if top == node:
                        break
                if len(group) > 1:
                    found.append(sorted(group))
    return found


def test_circle_finder_sees_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _circles(sorted(graph), graph.__getitem__) == [["a", "b", "c"]]
    assert _circles(["x", "y"], {"x": {"y"}, "y": set()}.__getitem__) == []


def test_no_import_circle_in_the_package():
    grimp = pytest.importorskip("grimp")  # shipped with import-linter (the [test] extra)

    graph = grimp.build_graph("lidar_iris_eval", cache_dir=None)
    assert _circles(sorted(graph.modules), graph.find_modules_directly_imported_by) == []


# --- item 5: each built-in method's presets sit in its folder ------------------------------------

def test_builtin_presets_sit_in_their_method_folders():
    from lidar_iris_eval import descriptors
    from lidar_iris_eval.config import CONFIG_DIR, load_yaml
    from lidar_iris_eval.errors import LirisError

    assert not (CONFIG_DIR / "descriptors").exists()
    for name in descriptors._BUILTIN:
        folder = descriptors.method_folder(name)
        assert folder is not None and (folder / "presets.yaml").is_file(), name
        first = next(iter(load_yaml(folder / "presets.yaml")["presets"]))
        try:
            built = descriptors.get_descriptor(name)
        except LirisError:  # an optional extra (mapclosures' backend) not installed
            continue
        assert built.preset == first, name


# --- D10: one block pass with reducers; the second pass of streamed protocol 2 written once ------

_PASS_MODULES = ("lidar_iris_eval/matching/blocks.py", "lidar_iris_eval/evaluation/streaming_pr.py",
                 "lidar_iris_eval/evaluation/cross_session.py",
                 "lidar_iris_eval/evaluation/protocol2.py")


def _loops_calling_pairwise(source: str) -> set[str]:
    """Names of the functions with a for/while loop whose body calls ``*pairwise``."""
    import ast

    found = set()
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for loop in ast.walk(fn):
            if not isinstance(loop, (ast.For, ast.While)):
                continue
            for node in ast.walk(loop):
                callee = getattr(node, "func", None) if isinstance(node, ast.Call) else None
                name = getattr(callee, "attr", None) or getattr(callee, "id", None)
                if name in ("pairwise", "_pairwise"):
                    found.add(fn.name)
    return found


def test_loop_finder_sees_a_block_loop():
    text = "def walk(d, xs):\n    for a in xs:\n        d.pairwise(a, xs)\n"
    assert _loops_calling_pairwise(text) == {"walk"}
    assert _loops_calling_pairwise("def f(d, x):\n    return d.pairwise(x, x)\n") == set()


def _loops_over_block_tasks(source: str) -> set[str]:
    """Names of the functions with a for/while loop over ``*.run_blocks(_block_task, ...)``."""
    import ast

    found = set()
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        runs = {t.id for node in ast.walk(fn) if isinstance(node, ast.Assign)
                and isinstance(node.value, ast.Call)
                and getattr(node.value.func, "attr", None) == "run_blocks"
                and getattr(node.value.args[0], "id", None) == "_block_task"
                for t in node.targets if isinstance(t, ast.Name)}
        for loop in ast.walk(fn):
            if isinstance(loop, ast.For) and getattr(loop.iter, "id", None) in runs:
                found.add(fn.name)
    return found


def test_one_block_loop():
    loops, over_tasks = set(), set()
    for path in _PASS_MODULES:
        text = (ROOT / path).read_text()
        loops |= _loops_calling_pairwise(text)
        over_tasks |= _loops_over_block_tasks(text)
    # positive_values: protocol 2's positives, computed before the pass (not a block pass);
    # every block's distances come from _block_task, run where the executor decides
    assert loops == {"positive_values"}
    assert over_tasks == {"block_pass"}


class _ShapeDependent:
    """Distances that change with the batch shape (as float32 batched kernels may): the
    positives computed before the pass differ from the block values -> a second pass."""

    name = "shape-dependent"
    symmetric = False

    def pairwise(self, q, db):
        q, db = np.asarray(q)[:, None], np.asarray(db)[None, :]
        d = np.abs(q - db) + 1e-3 * (q.shape[0] % 5)
        return d, np.full(d.shape, np.nan)


def test_streamed_second_pass_is_exact_serial_and_distributed():
    sys.path.insert(0, str(ROOT / "tests"))
    try:
        from test_executor import ReversedExecutor
    finally:
        sys.path.remove(str(ROOT / "tests"))
    from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
    from lidar_iris_eval.evaluation.metrics import reduce_curve
    from lidar_iris_eval.evaluation.protocol2 import score_protocol2
    from lidar_iris_eval.evaluation.streaming_pr import stream_protocol2
    from lidar_iris_eval.matching.blocks import affinity_matrix

    rng = np.random.default_rng(5)
    n = 140
    descs = np.round(rng.random(n) * 5, 2)
    t = np.linspace(0, 4 * np.pi, n)
    gt = compute_ground_truth(np.c_[20 * np.cos(t), np.zeros(n), 20 * np.sin(t)], 4.0, 5)
    desc, budget = _ShapeDependent(), 1500
    full, _ = affinity_matrix(desc, descs, None, budget)  # the same blocks: the block values
    reference = score_protocol2(full, gt)
    results = []
    for executor in (None, ReversedExecutor()):
        with pytest.warns(UserWarning, match="second pass"):
            affinity, curve, matches = stream_protocol2(desc, descs, gt.pairs,
                                                        gt.n_positive_pairs, 5, budget,
                                                        executor=executor, storage="none")
        assert affinity.passes == 2
        result = score_protocol2(affinity, gt, curve=curve)
        ref_curve = reduce_curve(reference.curve)
        np.testing.assert_array_equal(result.curve.precision, ref_curve.precision)
        np.testing.assert_array_equal(result.curve.recall, ref_curve.recall)
        for key in ("ap", "f1_max", "r100p", "ep"):
            assert result.metrics[key] == reference.metrics[key], key
        results.append((curve, matches))
    (c0, m0), (c1, m1) = results
    np.testing.assert_array_equal(c0.precision, c1.precision)
    np.testing.assert_array_equal(c0.recall, c1.recall)
    np.testing.assert_array_equal(m0.match, m1.match)
    np.testing.assert_array_equal(m0.distance, m1.distance)


# --- D7: evaluate._evaluate_one does not branch on the kind of method ------------------------

def test_evaluate_one_leaves_the_kind_to_the_matchers(tiny_mixed, tmp_path, monkeypatch):
    import inspect

    from lidar_iris_eval.evaluation import evaluate as ev

    assert "two_stage" not in inspect.getsource(ev._evaluate_one)
    calls = []
    real = ev.protocols_1_and_2
    monkeypatch.setattr(ev, "protocols_1_and_2",
                        lambda *a, **k: calls.append(a[0].name) or real(*a, **k))
    settings = ev.Settings(candidates=3)
    both = ev.evaluate(tiny_mixed, ["scan-context"], protocols=(1, 2), settings=settings,
                       cache=tmp_path / "cache", progress=False)
    assert calls == ["scan-context"]  # one call; protocols_1_and_2 honours candidates (D1)
    one = ev.evaluate(tiny_mixed, ["scan-context"], protocols=(1,), settings=settings,
                      cache=tmp_path / "cache", progress=False)
    two = ev.evaluate(tiny_mixed, ["scan-context"], protocols=(2,), settings=ev.Settings(),
                      cache=tmp_path / "cache", progress=False)  # candidates: protocol 1 only
    by = {r["protocol"]: r for r in both.rows}
    for key in ("ap", "f1_max", "r100p", "ep"):
        assert by[1][key] == one.rows[0][key], key
        assert by[2][key] == two.rows[0][key], key


# --- item 4: the executor owns the process pool; errors cross processes as LirisError -----------

def _pid_and_sum(offset, a, b):
    import os

    return os.getpid(), offset + a + b


def _fails_in_worker(a):
    from lidar_iris_eval.errors import LirisError

    raise LirisError(f"scan {a}", "bad points")


def test_process_executor_runs_tasks_in_its_pool():
    import os

    from lidar_iris_eval.executor import ProcessExecutor

    tasks = [(i, 10 * i) for i in range(6)]
    got = dict(ProcessExecutor(workers=2).imap(_pid_and_sum, tasks, shared=(100,)))
    assert sorted(got) == list(range(6))
    assert [got[i][1] for i in range(6)] == [100 + 11 * i for i in range(6)]
    assert os.getpid() not in {pid for pid, _ in got.values()}  # not in this process


def test_errors_cross_the_pool_as_liris_errors():
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.executor import ProcessExecutor

    with pytest.raises(LirisError) as info:
        list(ProcessExecutor(workers=2).imap(_fails_in_worker, [(3,), (4,)]))
    assert info.value.problem == "bad points" and info.value.source in ("scan 3", "scan 4")


def test_extraction_through_the_pool_equals_serial(tiny_mixed, tmp_path):
    from lidar_iris_eval.executor import ProcessExecutor, SerialExecutor
    from lidar_iris_eval.extract import extract_many
    from lidar_iris_eval.io import open_sequence

    seq = open_sequence(tiny_mixed)
    from lidar_iris_eval.descriptors import get_descriptor

    descs = [get_descriptor("scan-context"), get_descriptor("m2dp")]
    serial = extract_many(seq, descs, chunk_size=40, executor=SerialExecutor())
    pooled = extract_many(seq, descs, chunk_size=40, executor=ProcessExecutor(workers=2))
    for a, b in zip(serial, pooled, strict=True):
        np.testing.assert_array_equal(a.descriptors, b.descriptors)


# --- item 2: the conventions of a command call are parsed once, by Settings.from_options --------

def test_from_options_without_a_preset():
    from lidar_iris_eval.evaluation.conventions import PRESETS
    from lidar_iris_eval.evaluation.settings import Settings

    assert Settings.from_options(None) is PRESETS["liris"]
    assert Settings.from_options(None, radius=4.0, exclude="paper") is PRESETS["liris"]
    own = Settings.from_options(None, exclude="12", distance="planar")
    assert (own.name, own.exclude, own.exclude_name, own.distance) == ("custom", 12, "custom",
                                                                       "planar")
    assert own.source == "command-line options"
    timed = Settings.from_options(None, exclude="2.5s")
    assert (timed.exclude, timed.exclude_seconds, timed.name) == (None, 2.5, "custom")


def test_from_options_over_a_preset_and_a_replayed_run():
    from lidar_iris_eval.evaluation.conventions import get_convention
    from lidar_iris_eval.evaluation.settings import Settings

    logg3d = get_convention("logg3d")
    assert Settings.from_options(logg3d) is logg3d  # nothing given: the preset itself
    wider = Settings.from_options(logg3d, radius=5.0)
    assert (wider.name, wider.radius, wider.exclude_seconds) == ("logg3d+custom", 5.0, 30.0)
    framed = Settings.from_options(logg3d, exclude="reference")  # frames replace seconds
    assert (framed.exclude, framed.exclude_seconds, framed.window_rule) == (300, None, "logg3d")
    recorded = Settings.from_dict(Settings(inclusive_radius=True, exclude=9).to_dict())
    again = Settings.from_options(recorded, distance="planar")
    assert (again.name, again.exclude, again.inclusive_radius) == ("custom", 9, True)


def test_from_options_refuses_bad_values_and_unknown_options():
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.evaluation.settings import Settings, parse_exclude

    for bad in ("ten", "0", "-3s", "xs"):
        with pytest.raises(LirisError):
            Settings.from_options(None, exclude=bad)
    with pytest.raises(LirisError, match="seconds applies"):
        parse_exclude("30s", seconds=False)
    with pytest.raises(TypeError):
        Settings.from_options(None, candidates=3)


def test_cli_conventions_go_through_from_options(tmp_path, monkeypatch, capsys):
    from conftest import run_cli

    from lidar_iris_eval.evaluation.settings import Settings

    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    poses = np.zeros((40, 12))
    poses[:, [0, 5, 10]] = 1.0
    poses[:, 3], poses[:, 11] = 10 * np.cos(t), 10 * np.sin(t)
    np.savetxt(tmp_path / "poses.txt", poses)
    seen, real = [], Settings.from_options.__func__
    monkeypatch.setattr(Settings, "from_options", classmethod(
        lambda cls, conv=None, **given: seen.append((conv, given)) or real(cls, conv, **given)))
    code, out, err = run_cli(["gt", "--poses", tmp_path / "poses.txt", "--exclude", "12",
                              "--radius", "3", "--json"], capsys)
    assert code == 0, err
    assert seen == [(None, {"radius": 3.0, "exclude": "12"})]


def test_gt_merges_the_sequence_pose_frame_through_from_options(tiny_mixed, capsys):
    """A frame the sequence imposes (LiDAR poses) is merged like an option: a ``custom``
    convention stays ``custom`` (it was ``custom+custom``); a preset becomes ``+custom``."""
    import json

    from conftest import run_cli

    def convention(*args):
        code, out, err = run_cli(["gt", tiny_mixed, *args, "--json"], capsys)
        assert code == 0, err
        return json.loads(out)

    lidar_poses = convention("--radius", "7", "--lidar-frame-poses")
    assert (lidar_poses["convention"], lidar_poses["pose_frame"]) == ("custom", "lidar")
    asked = convention("--radius", "7", "--pose-frame", "lidar")
    assert (asked["convention"], asked["pose_frame"]) == ("custom", "lidar")
    assert convention("--lidar-frame-poses")["convention"] == "liris+custom"
    assert convention()["convention"] == "liris"


def test_pseudo_revisits_parses_its_window_with_from_options():
    """An out-and-back line, 1 m steps: the return frames i >= 63 have a partner j <= i - 30
    within 4 m (i = 63 is at x = 36, frame 33 at x = 33); E = 300 exceeds the 100 frames."""
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.evaluation.sequence_check import pseudo_revisits

    x = np.r_[np.arange(50), np.arange(49, -1, -1)].astype(float)
    positions = np.c_[x, np.zeros(100), np.zeros(100)]
    revisit, pseudo = pseudo_revisits(positions, 30)
    assert np.flatnonzero(revisit).tolist() == list(range(63, 100))
    named, named_pseudo = pseudo_revisits(positions, "paper")
    np.testing.assert_array_equal(named, revisit)
    np.testing.assert_array_equal(named_pseudo, pseudo)
    assert not pseudo_revisits(positions, "reference")[0].any()
    with pytest.raises(LirisError, match="exclude"):
        pseudo_revisits(positions, "often")
