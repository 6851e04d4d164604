"""The descriptor cache: keys, verified reads, atomic writes, resuming, interruption."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from conftest import kill_extract_mid_run
from test_protocols import SlowToyHist, ToyHist, ToyParams, two_pass_sequence

from lidar_iris_eval.cache import CacheKey, DescriptorCache, read_arrays, write_arrays
from lidar_iris_eval.errors import LirisWarning
from lidar_iris_eval.extract import cache_key, extract
from lidar_iris_eval.io import open_sequence


@pytest.fixture
def seq(tmp_path):
    return open_sequence(two_pass_sequence(tmp_path / "seq", n_per_pass=10))


def test_second_run_loads_and_computes_nothing(seq, tmp_path):
    cache = DescriptorCache(tmp_path / "cache")
    first = ToyHist()
    db1 = extract(seq, first, cache=cache, chunk_size=3)
    assert first.calls == len(seq) == 20 and not db1.from_cache
    again = ToyHist()
    db2 = extract(seq, again, cache=cache)
    assert again.calls == 0 and db2.from_cache
    np.testing.assert_array_equal(db1.descriptors, db2.descriptors)
    np.testing.assert_array_equal(db1.extract_s, db2.extract_s)
    assert db1.cache_path == db2.cache_path and db1.cache_path.is_file()
    # only the final file is left: no chunks, no temporary files
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [db1.cache_path.name]
    # the stored numbers are what compute returns
    expected = np.stack([ToyHist().compute(seq[i]) for i in range(len(seq))])
    np.testing.assert_array_equal(db2.descriptors, expected)


def test_key_depends_on_params_version_and_scans(seq, tmp_path):
    base = cache_key(seq, ToyHist())
    assert cache_key(seq, ToyHist()).digest() == base.digest()
    assert cache_key(seq, ToyHist(ToyParams(bins=8))).digest() != base.digest()
    other_version = CacheKey(**{**base.__dict__, "version": "9.9.9"})
    assert other_version.digest() != base.digest()
    assert base.version.endswith(f"+numpy-{np.__version__}")  # ESF's random stream
    # change one scan's bytes: the fingerprint and the key change, and the cache recomputes
    cache = DescriptorCache(tmp_path / "cache")
    extract(seq, ToyHist(), cache=cache)
    path = seq.scan_paths[3]
    data = np.fromfile(path, dtype=np.float32)
    data[0] += 1.0
    data.tofile(path)
    changed = open_sequence(seq.path)
    assert cache_key(changed, ToyHist()).digest() != base.digest()
    desc = ToyHist()
    extract(changed, desc, cache=cache)
    assert desc.calls == len(seq)


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage", "empty"])
def test_corrupt_cache_is_detected_and_rebuilt(seq, tmp_path, damage):
    cache = DescriptorCache(tmp_path / "cache")
    good = extract(seq, ToyHist(), cache=cache)
    path = good.cache_path
    raw = bytearray(path.read_bytes())
    if damage == "truncate":
        raw = raw[: len(raw) // 2]
    elif damage == "flip":  # a byte inside the descriptor array's data
        arrays, _ = read_arrays(path)
        needle = arrays["descriptors"].tobytes()[:32]
        at = bytes(raw).find(needle)
        assert at > 0
        raw[at + 5] ^= 0x40
    elif damage == "garbage":
        raw = bytearray(b"not a cache file at all")
    else:
        raw = bytearray()
    path.write_bytes(bytes(raw))
    desc = ToyHist()
    with pytest.warns(LirisWarning, match="corrupt cache file"):
        db = extract(seq, desc, cache=cache)
    assert desc.calls == len(seq) and not db.from_cache
    np.testing.assert_array_equal(db.descriptors, good.descriptors)
    read_arrays(path)  # rebuilt and valid again


def test_checksum_and_key_are_verified(tmp_path):
    path = tmp_path / "x.npz"
    arrays = {"a": np.arange(5.0)}
    write_arrays(path, arrays, {"digest": "k1"})
    loaded, meta = read_arrays(path)
    np.testing.assert_array_equal(loaded["a"], arrays["a"])
    assert meta["digest"] == "k1"
    # a file written for another key is not used (e.g. renamed by hand)
    cache = DescriptorCache(tmp_path / "c")
    key = CacheKey.build("s", "f", "toy", {"bins": 1}, "0", 5)
    cache.root.mkdir()
    os.replace(path, cache.path(key))
    with pytest.warns(LirisWarning, match="different key"):
        assert cache.load(key) is None
    assert not cache.path(key).exists()


def test_structured_descriptors_round_trip(tmp_path):
    dtype = np.dtype([("img", np.uint8, (4, 6)), ("key", np.float32, (3,))])
    rec = np.zeros(3, dtype)
    rec["img"] = np.arange(72).reshape(3, 4, 6)
    rec["key"] = 1.5
    write_arrays(tmp_path / "r.npz", {"descriptors": rec}, {})
    back, _ = read_arrays(tmp_path / "r.npz")
    assert back["descriptors"].dtype == dtype
    np.testing.assert_array_equal(back["descriptors"]["img"], rec["img"])


def test_resumes_from_stored_chunks(seq, tmp_path):
    cache = DescriptorCache(tmp_path / "cache")
    desc = ToyHist()
    key = cache_key(seq, desc)
    # pretend an earlier run finished chunks [0, 4) and [8, 12), then died
    for a, b in [(0, 4), (8, 12)]:
        part = np.stack([desc.compute(seq[i]) for i in range(a, b)])
        cache.store_chunk(key, a, b, {"descriptors": part, "extract_s": np.zeros(b - a),
                                      "read_s": np.zeros(b - a)})
    # and left a half-written temporary file behind
    (cache.partial_dir(key) / ".tmp-deadbeef.npz").write_bytes(b"PK\x03\x04partial")
    fresh = ToyHist()
    db = extract(seq, fresh, cache=cache, chunk_size=4)
    assert fresh.calls == len(seq) - 8
    expected = np.stack([ToyHist().compute(seq[i]) for i in range(len(seq))])
    np.testing.assert_array_equal(db.descriptors, expected)
    assert not cache.partial_dir(key).exists()


def test_pool_gives_the_same_descriptors(seq, tmp_path):
    one = extract(seq, ToyHist(), cache=None)
    two = extract(seq, ToyHist(), cache=tmp_path / "cache", workers=2, chunk_size=3)
    np.testing.assert_array_equal(one.descriptors, two.descriptors)
    assert np.all(two.extract_s > 0) and len(two.extract_s) == len(seq)


def test_killed_extract_resumes_to_identical_descriptors(tmp_path):
    """SIGKILL ``liris extract`` mid-run, rerun it, compare with an uninterrupted run."""
    root = two_pass_sequence(tmp_path / "seq", n_per_pass=20, seed=3)
    cache_dir = tmp_path / "cache"
    done = kill_extract_mid_run(root, "toy", "test_protocols:SlowToyHist", cache_dir, 4,
                                tmp_path)
    assert 2 <= done < 10

    seq = open_sequence(root)
    resumed = SlowToyHist()
    with warnings.catch_warnings():
        warnings.simplefilter("error", LirisWarning)  # no chunk may be corrupt
        db = extract(seq, resumed, cache=cache_dir, chunk_size=4)
    assert resumed.calls == len(seq) - 4 * done
    clean = extract(seq, ToyHist(), cache=None)
    np.testing.assert_array_equal(db.descriptors, clean.descriptors)

