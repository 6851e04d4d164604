"""liris bench's per-scan comparison with the authors' C++ figures."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_iris_eval.bench.extraction import CPP_FIGURES, cpp_rows, measure_against_cpp
from lidar_iris_eval.descriptors import get_descriptor


def test_ratios_against_cpp_figures_in_process():
    rng = np.random.default_rng(0)
    scans = [np.c_[rng.uniform(-30, 30, (4000, 2)), rng.uniform(-1.7, 3, 4000)].astype(np.float32)
             for _ in range(3)]
    descs = [get_descriptor("scan-context", preset="reference"),
             get_descriptor("m2dp", preset="reference")]
    result = measure_against_cpp(descs, scans, repeats=2, pair_repeats=12, isolate=False)
    sc = result["descriptors"]["scan-context:reference"]
    m2dp = result["descriptors"]["m2dp:reference"]
    assert result["scans"] == 3 and result["points_median"] == 4000
    assert sc["cpp_extract_ms"] == 3.5 and sc["cpp_pair_us"] == 31.0
    assert sc["extract_ratio_to_cpp"] == pytest.approx(sc["extract_ms"] / 3.5)
    assert sc["pair_ratio_to_cpp"] == pytest.approx(sc["pair_us"] / 31.0)
    assert sc["extract_ms"] > 0 and sc["pair_us"] > 0 and len(sc["extract_ms_per_scan"]) == 3
    # no C++ for M2DP: no ratio, shown as '-'
    assert m2dp["cpp_extract_ms"] is None and m2dp["extract_ratio_to_cpp"] is None
    rows = {r["descriptor"]: r for r in cpp_rows(result)}
    assert rows["m2dp:reference"]["extract_x_C++"] == "-"
    assert rows["scan-context:reference"]["C++_us"] == "31"
    assert set(CPP_FIGURES) == {"lidar-iris", "scan-context", "m2dp", "esf"}


def test_in_process_measurement_restores_cpu_affinity():
    import os

    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("no CPU affinity on this platform")
    before = os.sched_getaffinity(0)
    scans = [np.random.default_rng(1).normal(size=(500, 3)).astype(np.float32)]
    measure_against_cpp([get_descriptor("m2dp")], scans, repeats=1, pair_repeats=1,
                        isolate=False)
    assert os.sched_getaffinity(0) == before
