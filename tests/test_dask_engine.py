"""``--scheduler``: a Dask cluster gives exactly the metrics of the default scheduler.

Starts ``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1 (one
thread each), evaluates a small synthetic sequence through them, and compares
every metric with the default (local processes) run; stops them afterwards.
Skipped when Dask is not installed (``pip install -e ".[dask]"``).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import run_cli
from synthetic_loop import loop_sequence

distributed = pytest.importorskip("distributed")

#: keys that are timings or storage notes, not metrics
NOT_METRICS = {"match_ms_per_query", "match_us_per_pair", "extract_ms_per_scan",
               "affinity_stored"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def metrics(path: Path) -> list[dict]:
    rows = json.loads(path.read_text())["results"]
    return [{k: v for k, v in r.items() if k not in NOT_METRICS} for r in rows]


def test_loopback_cluster_equals_default_scheduler(tmp_path, capsys, monkeypatch):
    seq = loop_sequence(tmp_path / "seq")
    args = ["eval", seq, "--protocol", "1", "--protocol", "2", "-d", "m2dp,scan-context",
            "--exclude", "10", "-q"]
    monkeypatch.setenv("LIRIS_CACHE_DIR", str(tmp_path / "cache-default"))
    code, _, err = run_cli([*args, "--out", tmp_path / "default"], capsys)
    assert code == 0, err

    dask_cli = Path(sys.executable).parent / "dask"
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "NUMBA_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    logs = open(tmp_path / "dask.log", "w")  # noqa: SIM115 - closed in finally
    procs = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], env=env, stdout=logs, stderr=logs)]
    try:
        time.sleep(1.0)
        procs += [subprocess.Popen([dask_cli, "worker", address, "--nthreads", "1",
                                    "--nworkers", "1", "--no-dashboard",
                                    "--local-directory", str(tmp_path / f"w{i}")],
                                   env=env, stdout=logs, stderr=logs) for i in range(2)]
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            assert len(client.scheduler_info()["workers"]) == 2
        monkeypatch.setenv("LIRIS_CACHE_DIR", str(tmp_path / "cache-dask"))  # extract there too
        code, _, err = run_cli([*args, "--out", tmp_path / "cluster", "--scheduler", address],
                               capsys)
        assert code == 0, err
        # protocol 1 alone takes the exhaustive search (its blocks are tasks too)
        only_p1 = ["eval", seq, "--protocol", "1", "-d", "m2dp,scan-context", "--exclude", "10",
                   "-q", "--scheduler", address, "--out", tmp_path / "cluster-p1"]
        code, _, err = run_cli(only_p1, capsys)
        assert code == 0, err
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
        logs.close()

    default = metrics(tmp_path / "default" / "metrics.json")
    cluster = metrics(tmp_path / "cluster" / "metrics.json")
    assert len(default) == 4  # 2 descriptors x 2 protocols
    assert cluster == default  # every metric, count and threshold, exactly
    p1_alone = [{k: v for k, v in r.items() if k != "match_source"}
                for r in metrics(tmp_path / "cluster-p1" / "metrics.json")]
    assert p1_alone == [{k: v for k, v in r.items() if k != "match_source"}
                        for r in default if r["protocol"] == 1]
    p2 = [r for r in default if r["protocol"] == 2]
    assert all(r["n_positives"] > 0 and r["ap"] > 0.05 for r in p2)
    assert (tmp_path / "default" / "protocol2" / "m2dp" / "affinity.npy").is_file()
    assert not (tmp_path / "cluster" / "protocol2" / "m2dp" / "affinity.npy").exists()


def test_unknown_scheduler_is_one_line_error(tmp_path, capsys):
    from conftest import assert_one_line_error

    seq = loop_sequence(tmp_path / "seq", frames=12)
    code, _, err = run_cli(["eval", seq, "--protocol", "2", "-d", "m2dp", "--scheduler",
                            "yarn", "--out", tmp_path / "r", "-q"], capsys)
    assert_one_line_error(code, err, "--scheduler yarn")
