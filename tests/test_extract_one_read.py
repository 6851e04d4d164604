"""extract_many: each scan is read once for every descriptor of a run.

The sequence counts its reads. Several descriptors extracted together must
read every scan exactly once, give bitwise the descriptors of separate
extractions, keep one cache file and their own CPU times each, and skip
descriptors already complete in the cache (which then read nothing).
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from click.testing import CliRunner

from lidar_iris_eval.cache import DescriptorCache
from lidar_iris_eval.cli import cli
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.extract import extract, extract_many
from lidar_iris_eval.io import open_sequence

FRAMES = 12
NAMES = ("m2dp", "scan-context", "lidar-iris")


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("one-read") / "seq"
    result = CliRunner().invoke(cli, ["simulate", str(path), "--frames", str(FRAMES),
                                      "--azimuth-steps", "256", "-q"])
    assert result.exit_code == 0, result.output
    return path


def counting(path):
    """The sequence at ``path``, counting reads per scan index (points and scans)."""
    seq = open_sequence(path)
    reads: Counter = Counter()
    base = type(seq)

    inside = []

    class Counting(base):
        """Counts the outermost call only (``seq[i]`` may call ``scan(i)`` itself)."""

        def __getitem__(self, index):
            if not inside:
                reads[("points", index)] += 1
            inside.append(1)
            try:
                return base.__getitem__(self, index)
            finally:
                inside.pop()

        def scan(self, index):
            if not inside:
                reads[("scan", index)] += 1
            inside.append(1)
            try:
                return base.scan(self, index)
            finally:
                inside.pop()

    seq.__class__ = Counting
    return seq, reads


def test_each_scan_read_once_for_all_descriptors(seq_dir, tmp_path, monkeypatch):
    descs = [get_descriptor(n) for n in NAMES]
    for d in descs:  # input checks sample scans of their own; only extraction is counted
        monkeypatch.setattr(type(d), "check_inputs", lambda self, seq: None)
    seq, reads = counting(seq_dir)
    together = extract_many(seq, descs, cache=DescriptorCache(tmp_path / "cache"))
    assert reads == Counter({("points", i): 1 for i in range(FRAMES)})
    assert [db.descriptor for db in together] == list(NAMES)
    separate = [extract(open_sequence(seq_dir), d) for d in descs]
    for a, b in zip(together, separate, strict=True):
        assert np.array_equal(a.descriptors, b.descriptors)
        assert len(a.extract_s) == FRAMES and np.all(a.extract_s > 0)
    # one shared read per scan, the same value in every descriptor; own CPU times
    for db in together[1:]:
        assert np.array_equal(db.read_s, together[0].read_s)
    assert not np.array_equal(together[0].extract_s, together[2].extract_s)
    # one cache file per descriptor
    paths = {db.cache_path for db in together}
    assert len(paths) == 3 and all(p.is_file() for p in paths)


def test_cached_descriptors_are_skipped_and_read_nothing(seq_dir, tmp_path, monkeypatch):
    for name in ("m2dp", "scan-context"):
        monkeypatch.setattr(type(get_descriptor(name)), "check_inputs", lambda self, seq: None)
    cache = DescriptorCache(tmp_path / "cache")
    first = extract(open_sequence(seq_dir), get_descriptor("m2dp"), cache=cache)
    assert not first.from_cache
    seq, reads = counting(seq_dir)
    dbs = extract_many(seq, [get_descriptor("m2dp"), get_descriptor("scan-context")],
                       cache=cache)
    assert dbs[0].from_cache and not dbs[1].from_cache
    assert np.array_equal(dbs[0].descriptors, first.descriptors)
    assert reads == Counter({("points", i): 1 for i in range(FRAMES)})  # for scan-context
    again, reads_again = counting(seq_dir)
    both = extract_many(again, [get_descriptor("m2dp"), get_descriptor("scan-context")],
                        cache=cache)
    assert all(db.from_cache for db in both)
    assert not [k for k in reads_again if k[0] == "scan"]
    # a cache hit reads no scan for descriptors (the degenerate-output check may sample)
    assert sum(reads_again.values()) < FRAMES


def test_workers_give_the_same_descriptors(seq_dir):
    descs = [get_descriptor(n) for n in NAMES]
    serial = extract_many(open_sequence(seq_dir), descs, chunk_size=4)
    pooled = extract_many(open_sequence(seq_dir), descs, workers=2, chunk_size=4)
    for a, b in zip(serial, pooled, strict=True):
        assert np.array_equal(a.descriptors, b.descriptors)
        assert np.array_equal(a.read_s > 0, b.read_s > 0)
