"""``liris bench``: the report's structure and its equality checks (no timing assertions).

The smoke test simulates 60 frames, benchmarks two descriptors with every
protocol in fresh processes, and checks counts that follow from the sequence
length alone, plus that the batched-vs-single and reference-loop checks ran
and passed. The reference formulas are checked on hand-computed cases.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from lidar_iris_eval.bench import (
    BenchSettings,
    MatchingJob,
    esf_reference,
    m2dp_reference,
    run_benchmark,
    run_isolated,
    sample_pairs,
    scan_context_reference,
    simulated_sequence,
)
from lidar_iris_eval.cli import cli
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io import open_sequence

FRAMES = 60
EXCLUDE = 30


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    work = tmp_path_factory.mktemp("bench")
    path, seconds = simulated_sequence(work, "tiny-mixed", FRAMES, 256)
    assert seconds > 0
    return work, path


def test_sample_pairs_are_distinct_off_diagonal_and_in_pool():
    rng = np.random.default_rng(5)
    pairs = sample_pairs(1000, 500, 30, rng)
    assert pairs.shape == (500, 2)
    assert np.all(pairs[:, 0] != pairs[:, 1])
    assert len({tuple(p) for p in pairs}) == 500
    assert len(np.unique(pairs)) <= 30
    # a pool of 4 frames has only 12 ordered pairs: all of them, once each
    small = sample_pairs(10, 100, 4, rng)
    assert len(small) == 12 and len({tuple(p) for p in small}) == 12


def test_reference_formulas_hand_computed():
    assert m2dp_reference(np.array([0.0, 0.0]), np.array([3.0, 4.0])) == 5.0
    assert esf_reference(np.array([0.5, 0.5, 0.0]), np.array([0.0, 0.25, 0.75])) == 1.5
    params = get_descriptor("scan-context", "exhaustive").params
    rng = np.random.default_rng(0)
    dtype = np.dtype([("sc", np.float32, (3, 6))])
    q = np.zeros((), dtype)
    q["sc"] = rng.uniform(0.5, 2.0, (3, 6))
    rolled = np.zeros((), dtype)
    rolled["sc"] = np.roll(q["sc"], 2, axis=1)
    assert scan_context_reference(q, rolled, params) == pytest.approx(0.0, abs=1e-12)
    # two columns: q = (1,0),(0,1); c = (1,1),(1,0) -> best shift pairs (1,0)-(1,0) and
    # (0,1)-(1,1): 1 - mean(1, 1/sqrt 2)
    q2 = np.zeros((), np.dtype([("sc", np.float32, (2, 2))]))
    c2 = np.zeros((), q2.dtype)
    q2["sc"] = [[1, 0], [0, 1]]
    c2["sc"] = [[1, 1], [1, 0]]
    expected = 1 - (1 + 1 / np.sqrt(2)) / 2
    assert scan_context_reference(q2, c2, params) == pytest.approx(expected, abs=1e-12)


def test_bench_report_structure_and_checks(sequence_dir):
    work, path = sequence_dir
    seq = open_sequence(path)
    descs = [get_descriptor("lidar-iris"), get_descriptor("scan-context", "exhaustive")]
    settings = BenchSettings(exclude=EXCLUDE, loop_pairs=300, loop_pool=40, kernel_queries=8,
                             kernel_repeats=1)
    report = run_benchmark(seq, descs, work, settings)
    assert report["sequence"]["frames"] == FRAMES
    assert report["bars"] == []  # bars only apply to 4541 frames
    assert len(report["load_average"]["start"]) == 3
    assert [e["descriptor"] for e in report["descriptors"]] == ["lidar-iris", "scan-context"]
    for e in report["descriptors"]:
        ex = e["extraction"]
        assert ex["scans"] == FRAMES and ex["q1_ms"] <= ex["median_ms"] <= ex["q3_ms"]
        assert e["kernel"]["pairs"] == 8 * FRAMES
        loop = e["loop"]
        assert loop["pairs"] == 300
        assert loop["batched_equals_single"] and loop["batched_yaw_equals_single"]
        assert loop["reference"]["nan_mismatches"] == 0
        p1, p2 = e["protocol1"], e["protocol2"]
        assert p1["isolated"] and p2["isolated"]
        # protocol 1: queries 30..59, each against j <= i - 30: at least 1 + ... + 30 pairs
        assert p1["metrics"]["n_queries"] == FRAMES - EXCLUDE
        assert p1["evaluations"] >= (FRAMES - EXCLUDE) * (FRAMES - EXCLUDE + 1) // 2
        assert p2["ordered_pairs"] == FRAMES * (FRAMES - 1)
        assert p2["metrics"]["n_pairs"] == FRAMES * (FRAMES - 1)
        for p in (p1, p2):
            assert p["peak_rss_bytes"] >= p["rss_after_load_bytes"] > 0
    iris, sc = report["descriptors"]
    assert iris["loop"]["reference"]["identical"]
    assert iris["symmetric"] and sc["symmetric"]
    # Scan Context's kernel quantises unit columns to 2**-16 (documented ~2e-6)
    assert sc["loop"]["reference"]["max_abs_diff"] < 1e-5
    json.dumps(report, allow_nan=True)  # serialisable as is


def test_cli_json_on_existing_sequence_and_bad_options(sequence_dir):
    work, path = sequence_dir
    runner = CliRunner()
    args = ["bench", "--sequence", str(path), "--work-dir", str(work), "-d", "m2dp", "-q",
            "--skip-protocol1", "--skip-protocol2", "--loop-pairs", "50", "--json", "-"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    start = result.stdout.index("{")
    report = json.loads(result.stdout[start:])
    (entry,) = report["descriptors"]
    assert entry["descriptor"] == "m2dp" and "protocol1" not in entry
    assert entry["loop"]["batched_equals_single"]
    bad = runner.invoke(cli, ["bench", "--sequence", str(path), "--frames", "10"])
    assert isinstance(bad.exception, LirisError)


def test_isolated_peak_memory_is_the_childs_own(tmp_path):
    """A fresh process must not report its parent's memory as its own peak.

    The parent holds 600 MB; the child matches 50 small M2DP descriptors, which
    needs far less than that (the interpreter and imports are ~100 MB).
    """
    held = np.ones(600 * 2**20 // 8)  # touched, so resident
    rng = np.random.default_rng(2)
    path = tmp_path / "m2dp.npy"
    np.save(path, rng.normal(size=(50, 192)))
    job = MatchingJob(get_descriptor("m2dp"), str(path), rng.uniform(0, 100, (50, 3)), "lidar",
                      2, 5, 4.0, 1 << 20, False)
    result = run_isolated(job)
    assert held[-1] == 1.0
    assert result["ordered_pairs"] == 50 * 49
    assert 0 < result["peak_rss_bytes"] < 400 * 2**20


def test_bench_runs_the_learned_methods(tmp_path):
    """BEVPlace++ keeps feature sets (global vector, keypoints, local features), not a
    stacked array: the report sizes them, hands them to the matching process as .npz, and
    the Gram distances agree with the reference loop to rounding (1e-13)."""
    frames = 16
    path, _ = simulated_sequence(tmp_path, "tiny-mixed", frames, 256)
    seq = open_sequence(path)
    descs = [get_descriptor("overlap-transformer"), get_descriptor("bevplace")]
    settings = BenchSettings(exclude=4, loop_pairs=40, loop_pool=12, kernel_queries=8,
                             kernel_repeats=1)
    report = run_benchmark(seq, descs, tmp_path, settings)  # the shipped trained weights
    ot, bev = report["descriptors"]
    assert ot["extraction"]["descriptor_bytes"] == 256 * 4
    assert bev["extraction"]["descriptor_bytes"] > 8192 * 4  # + keypoints, local features
    for e in (ot, bev):
        assert e["loop"]["batched_equals_single"]
        assert e["loop"]["reference"]["max_abs_diff"] <= 1e-13
        assert e["protocol1"]["isolated"] and e["protocol2"]["isolated"]
        assert e["protocol2"]["ordered_pairs"] == frames * (frames - 1)
