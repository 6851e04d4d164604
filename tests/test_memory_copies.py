"""Extraction → evaluation holds the descriptors once: no hidden whole-stack copies.

A plain ``liris eval`` of LiDAR Iris at 4541 frames peaked at ~3 GiB, most of it
temporaries of checks around the descriptors rather than the descriptors
(0.4 GiB) or the matching. These tests pin the results of the rewritten pieces
against independent references, and the memory of the degenerate-descriptor
check with tracemalloc (NumPy reports its buffers to it).
"""

from __future__ import annotations

import hashlib
import tracemalloc

import numpy as np
import pytest

from lidar_iris_eval.cache import arrays_checksum
from lidar_iris_eval.descriptors import sanity
from lidar_iris_eval.extract import _Joiner, chunk_ranges


def constant_by_loop(stack: np.ndarray) -> np.ndarray:
    """Per scan: every numeric field holds one finite value at most (a plain loop)."""
    out = []
    for row in stack:
        fields = [row[n] for n in stack.dtype.names] if stack.dtype.names else [row]
        flags = []
        for f in fields:
            values = [float(v) for v in np.ravel(f) if np.isfinite(float(v))]
            flags.append(len(set(values)) <= 1)
        out.append(all(flags))
    return np.array(out)


def iris_like_stack(n: int, rng) -> np.ndarray:
    dtype = np.dtype([("image", "u1", (4, 6)), ("T", "<u8", (2, 6)), ("spec", "<f4", (3,))])
    stack = np.zeros(n, dtype=dtype)
    stack["image"] = rng.integers(0, 3, stack["image"].shape)
    stack["T"] = rng.integers(0, 2, stack["T"].shape)
    stack["spec"] = rng.normal(size=stack["spec"].shape)
    stack[1] = 0  # empty scan: constant everywhere
    stack["spec"][2] = np.nan  # all-NaN field counts as constant ...
    stack["image"][2] = 7
    stack["T"][2] = 1  # ... so scan 2 is constant
    stack["image"][3] = 7
    stack["T"][3] = 0
    stack["spec"][3] = [1.0, np.nan, 1.0]  # NaN ignored: still constant
    stack["spec"][4] = [1.0, np.nan, 2.0]  # varies
    return stack


@pytest.mark.parametrize("chunk", [1, 7, 24, 10_000])
def test_constant_rows_in_chunks_equals_a_plain_loop(monkeypatch, chunk):
    monkeypatch.setattr(sanity, "CHECK_VALUES_PER_CHUNK", chunk)
    stack = iris_like_stack(37, np.random.default_rng(0))
    got = sanity.constant_rows(stack)
    np.testing.assert_array_equal(got, constant_by_loop(stack))
    assert got[1] and got[2] and got[3] and not got[4]
    plain = np.random.default_rng(1).normal(size=(13, 5))
    plain[[0, 6]] = 2.5
    np.testing.assert_array_equal(sanity.constant_rows(plain), constant_by_loop(plain))


def test_degenerate_check_costs_a_bounded_amount_of_memory():
    """400 LiDAR-Iris-sized uint8 images (11.5 MB): a float64 copy of the stack alone is
    92 MB; the check now converts at most CHECK_VALUES_PER_CHUNK values at a time."""
    images = np.random.default_rng(2).integers(0, 255, (400, 80, 360), dtype=np.uint8)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        constant = sanity.constant_rows(images)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert not constant.any()
    chunk_bytes = 8 * sanity.CHECK_VALUES_PER_CHUNK
    assert peak < 4 * chunk_bytes, f"{peak / 2**20:.1f} MiB traced"


def test_checksum_equals_sha256_of_the_bytes_without_copying_them():
    rng = np.random.default_rng(3)
    arrays = {
        "descriptors": iris_like_stack(9, rng),
        "transposed": rng.normal(size=(5, 4)).T,  # not contiguous: hashed in C order
        "scalar": np.array(3.5),
        "empty": np.zeros((0, 3), dtype=np.float32),
    }
    reference = hashlib.sha256()
    for name in sorted(arrays):
        arr = np.ascontiguousarray(arrays[name])
        reference.update(f"{name}|{arr.dtype.descr!r}|{arr.shape!r}|".encode())
        reference.update(arr.tobytes())
    assert arrays_checksum(arrays) == reference.hexdigest()


def test_chunks_are_joined_in_place_in_any_order():
    rng = np.random.default_rng(4)
    stack = iris_like_stack(23, rng)
    ranges = chunk_ranges(23, 5)
    joined = _Joiner(ranges, "toy")
    for a, b in reversed(ranges):  # a pool finishes chunks in any order
        part = stack[a:b].copy()
        joined.add(a, b, {"descriptors": part, "extract_s": np.arange(a, b) * 1.0,
                          "read_s": np.zeros(b - a)})
        assert not np.shares_memory(joined.dense, part)  # copied: the chunk can go
    out = joined.arrays()
    assert out["descriptors"].dtype == stack.dtype
    assert out["descriptors"].tobytes() == stack.tobytes()
    np.testing.assert_array_equal(out["extract_s"], np.arange(23.0))
    with pytest.raises(RuntimeError, match="inconsistent outputs"):
        joined.add(0, 5, {"descriptors": np.zeros((5, 3)), "extract_s": np.zeros(5),
                          "read_s": np.zeros(5)})


def test_lidar_iris_database_in_slices_gives_the_same_bits(monkeypatch):
    """compare_blocks copies the database to kernel inputs DATABASE_CHUNK descriptors at a
    time; every pair is computed on its own, so any slicing gives identical results."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.descriptors.lidar_iris import descriptor as iris

    rng = np.random.default_rng(5)
    desc = get_descriptor("lidar-iris")
    place = rng.uniform(-30, 30, (3000, 3)) * [1, 1, 0.1]
    scans = []
    for k in range(11):  # one place turned and thinned, and other places
        turn = 0.4 * k
        rot = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0],
                        [0, 0, 1]])
        pts = place @ rot.T if k % 3 else rng.uniform(-30, 30, (3000, 3)) * [1, 1, 0.1]
        pts = pts[rng.random(len(pts)) < 0.9]
        scans.append(np.c_[pts, np.zeros(len(pts))].astype(np.float32))
    stack = np.stack([desc.compute(p) for p in scans])
    whole_d, whole_s = iris.compare_blocks(stack[:4], stack, desc.params)
    for chunk in (1, 3, 10):
        monkeypatch.setattr(iris, "DATABASE_CHUNK", chunk)
        d, s = iris.compare_blocks(stack[:4], stack, desc.params)
        np.testing.assert_array_equal(d, whole_d)
        np.testing.assert_array_equal(s, whole_s)
    assert np.isfinite(whole_d).all() and (whole_d[np.arange(4), np.arange(4)] == 0).all()
    assert whole_d[1, 2] < whole_d[1, 3]  # same place (turned) closer than another place
    empty_d, _ = iris.compare_blocks(stack[:2], stack[:0], desc.params)
    assert empty_d.shape == (2, 0)
