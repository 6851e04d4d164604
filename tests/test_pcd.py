"""PCD reading: the three encodings, field types, LZF, and bad files.

The PCD files are written here by a small independent writer (including an
LZF compressor), then read back and compared with the arrays written.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.io import pcd
from lidar_iris_eval.io.pcd import lzf_decompress, read_pcd

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL_SCAN = SHARED / "data" / "kitti" / "samples" / "00" / "velodyne" / "000094.bin"
HAVE_NUMBA = pcd._numba_kernel() is not None
# both LZF engines must decode identically; numba is optional
ENGINES = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(not HAVE_NUMBA,
                                                                   reason="numba missing"))]


# ---------------------------------------------------------------- test writer
def lzf_literal_only(data: bytes) -> bytes:
    """A valid LZF stream made only of literal runs (at most 32 bytes each)."""
    out = bytearray()
    for start in range(0, len(data), 32):
        chunk = data[start : start + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def lzf_compress(data: bytes) -> bytes:
    """A greedy LZF compressor: 3-byte hash table, matches up to 264 bytes, 8 KiB back."""
    out = bytearray()
    literal = bytearray()
    table: dict[bytes, int] = {}
    i, n = 0, len(data)

    def flush():
        for start in range(0, len(literal), 32):
            chunk = literal[start : start + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        literal.clear()

    while i < n:
        key = data[i : i + 3]
        ref = table.get(key) if len(key) == 3 else None
        table[key] = i
        if ref is not None and 0 < i - ref <= 8192:
            length = 3
            while i + length < n and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            flush()
            dist = i - ref - 1
            code = length - 2
            if code < 7:
                out.append((code << 5) | (dist >> 8))
            else:
                out.append((7 << 5) | (dist >> 8))
                out.append(code - 7)
            out.append(dist & 0xFF)
            i += length
        else:
            literal.append(data[i])
            i += 1
    flush()
    return bytes(out)


def write_pcd(path: Path, columns: dict[str, np.ndarray], encoding: str,
              pad_bytes: int = 0, compressor=lzf_compress) -> Path:
    """Write ``columns`` (name -> 1-D array, dtype sets TYPE/SIZE) as a PCD file.

    ``pad_bytes`` adds a PCL padding field ``_`` to the header; as in PCL, only
    the binary encoding stores its bytes (ascii and compressed data omit it).
    """
    names = list(columns)
    arrays = [np.asarray(columns[k]) for k in names]
    n = len(arrays[0])
    letter = {"f": "F", "u": "U", "i": "I"}
    sizes = [a.dtype.itemsize for a in arrays]
    types = [letter[a.dtype.kind] for a in arrays]
    counts = [1] * len(names)
    if pad_bytes:
        names.append("_")
        sizes.append(1)
        types.append("U")
        counts.append(pad_bytes)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {encoding}\n"
    ).encode()
    if encoding == "ascii":
        rows = [" ".join(repr(v.item()) for v in row) for row in zip(*arrays, strict=True)]
        body = ("\n".join(rows) + "\n").encode()
    elif encoding == "binary":
        fmt = [(f"f{k}", a.dtype.newbyteorder("<")) for k, a in enumerate(arrays)]
        if pad_bytes:
            fmt.append(("pad", f"V{pad_bytes}"))
        rec = np.zeros(n, dtype=fmt)
        for k, a in enumerate(arrays):
            rec[f"f{k}"] = a
        body = rec.tobytes()
    else:
        block = b"".join(a.astype(a.dtype.newbyteorder("<")).tobytes() for a in arrays)
        packed = compressor(block)
        body = struct.pack("<II", len(packed), len(block)) + packed
    path.write_bytes(header + body)
    return path


def cloud(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-50, 50, size=(n, 3)).astype(np.float32)
    return {
        "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
        "intensity": rng.uniform(0, 1, n).astype(np.float32),
        "ring": (np.arange(n) % 16).astype(np.uint16),
    }


# ---------------------------------------------------------------- LZF
@pytest.fixture(params=ENGINES)
def engine(request, monkeypatch):
    """Run a test with the given LZF engine, also inside read_pcd."""
    if request.param == "numpy":
        monkeypatch.setattr(pcd, "_numba_kernel", lambda: None)
    return request.param


def test_lzf_hand_built_back_references(engine):
    # literal "abc", then copy 5 bytes from 3 back (overlapping: repeats "abc")
    stream = bytes([2]) + b"abc" + bytes([(3 << 5) | 0, 2])
    assert lzf_decompress(stream, 8, engine=engine) == b"abcabcab"
    # long match (length code 7 + extra byte): 1 literal "z", copy 20 bytes at distance 1
    stream = bytes([0]) + b"z" + bytes([(7 << 5) | 0, 20 - 2 - 7, 0])
    assert lzf_decompress(stream, 21, engine=engine) == b"z" * 21
    # a reference into a reference, and a distance needing the high 5 bits (300 back)
    head = bytes(range(256)) + bytes(range(44))  # 300 literal bytes
    literal = b"".join(bytes([31]) + head[i : i + 32] for i in range(0, 288, 32))
    literal += bytes([11]) + head[288:300]
    dist = 300 - 1
    stream = literal + bytes([(2 << 5) | (dist >> 8), dist & 0xFF])  # copy 4 from 300 back
    stream += bytes([(1 << 5), 3])  # then copy 3 from 4 back (inside the previous copy)
    expected = head + head[:4] + head[:3]
    assert lzf_decompress(stream, len(expected), engine=engine) == expected


def test_lzf_compressor_round_trip_and_literal_only(engine):
    rng = np.random.default_rng(1)
    data = (bytes(rng.integers(0, 4, 3000, dtype=np.uint8)) + b"\x00" * 5000
            + bytes(rng.integers(0, 256, 700, dtype=np.uint8)) * 3)
    packed = lzf_compress(data)
    assert len(packed) < len(data) // 2  # the stream really uses back-references
    assert lzf_decompress(packed, len(data), engine=engine) == data
    assert lzf_decompress(lzf_literal_only(data), len(data), engine=engine) == data


@pytest.mark.parametrize(
    "stream, size",
    [
        (bytes([5]) + b"abc", 6),  # literal run past the end
        (bytes([0]) + b"a" + bytes([(1 << 5) | 0, 5]), 4),  # reference before the start
        (bytes([1]) + b"ab", 5),  # too short for the declared size
        (bytes([0]) + b"a" + bytes([(7 << 5)]), 12),  # ends inside a reference
    ],
)
def test_lzf_corrupt_streams_raise(stream, size, engine):
    with pytest.raises(LirisError, match="LZF"):
        lzf_decompress(stream, size, engine=engine)


# ---------------------------------------------------------------- encodings
@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_round_trip_each_encoding(tmp_path, encoding):
    cols = cloud(300)
    path = write_pcd(tmp_path / f"s_{encoding}.pcd", cols, encoding, pad_bytes=3)
    scan = read_pcd(path)
    expected = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    np.testing.assert_array_equal(scan.points, expected)
    np.testing.assert_array_equal(scan.intensity, cols["intensity"])
    assert scan.points.dtype == np.float32 and scan.points.flags.c_contiguous


def test_literal_only_compressed_file(tmp_path, engine):
    cols = cloud(50, seed=3)
    path = write_pcd(tmp_path / "lit.pcd", cols, "binary_compressed", compressor=lzf_literal_only)
    np.testing.assert_array_equal(read_pcd(path).points[:, 1], cols["y"])


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_field_types_and_order(tmp_path, encoding):
    # F8 coordinates in unusual order, U1 intensity, an I4 field before them
    n = 40
    rng = np.random.default_rng(4)
    cols = {
        "label": rng.integers(-5, 5, n).astype(np.int32),
        "z": rng.normal(size=n), "intensity": rng.integers(0, 255, n).astype(np.uint8),
        "x": rng.normal(size=n), "y": rng.normal(size=n),
    }
    scan = read_pcd(write_pcd(tmp_path / "t.pcd", cols, encoding))
    expected = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)
    np.testing.assert_array_equal(scan.points, expected)
    np.testing.assert_array_equal(scan.intensity, cols["intensity"].astype(np.float32))


def test_no_intensity_field(tmp_path):
    cols = {k: v for k, v in cloud(10).items() if k in "xyz"}
    scan = read_pcd(write_pcd(tmp_path / "xyz.pcd", cols, "binary"))
    assert scan.intensity is None and scan.points.shape == (10, 3)


def test_real_kitti_scan_through_compressed_pcd(tmp_path, engine):
    if not REAL_SCAN.is_file():
        pytest.skip("shared KITTI samples not available")
    data = np.fromfile(REAL_SCAN, dtype=np.float32).reshape(-1, 4)[:4000]
    cols = {"x": data[:, 0], "y": data[:, 1], "z": data[:, 2], "intensity": data[:, 3]}
    scan = read_pcd(write_pcd(tmp_path / "000094.pcd", cols, "binary_compressed"))
    np.testing.assert_array_equal(scan.points, data[:, :3])
    np.testing.assert_array_equal(scan.intensity, data[:, 3])


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_nan_points_dropped_with_warning(tmp_path, encoding):
    cols = cloud(20)
    cols["x"][[2, 7, 11]] = np.nan
    cols["z"][7] = np.inf
    path = write_pcd(tmp_path / "nan.pcd", cols, encoding)
    with pytest.warns(LirisWarning, match=r"nan\.pcd.*dropped 3 of 20"):
        scan = read_pcd(path)
    keep = np.setdiff1d(np.arange(20), [2, 7, 11])
    np.testing.assert_array_equal(scan.points[:, 1], cols["y"][keep])
    np.testing.assert_array_equal(scan.intensity, cols["intensity"][keep])


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_all_nan_or_zero_points_is_an_error(tmp_path, encoding):
    cols = cloud(5)
    cols["y"][:] = np.nan
    path = write_pcd(tmp_path / "allnan.pcd", cols, encoding)
    with pytest.warns(LirisWarning), pytest.raises(LirisError, match=r"allnan\.pcd.*empty"):
        read_pcd(path)
    empty = {k: v[:0] for k, v in cloud(5).items()}
    path = write_pcd(tmp_path / "zero.pcd", empty, "binary")
    with pytest.raises(LirisError, match=r"zero\.pcd.*empty"):
        read_pcd(path)


@pytest.mark.parametrize("encoding, cut", [("ascii", 30), ("binary", 5), ("binary_compressed", 9)])
def test_truncated_file_names_the_file(tmp_path, encoding, cut):
    path = write_pcd(tmp_path / "cut.pcd", cloud(100), encoding)
    path.write_bytes(path.read_bytes()[:-cut])
    with pytest.raises(LirisError, match=r"cut\.pcd.*(truncated|corrupt)"):
        read_pcd(path)


def test_header_problems(tmp_path):
    bad = tmp_path / "bad.pcd"
    bad.write_bytes(b"VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 1\nDATA ascii\n1 2\n")
    with pytest.raises(LirisError, match=r"bad\.pcd.*no z"):
        read_pcd(bad)
    bad.write_bytes(b"garbage without newline")
    with pytest.raises(LirisError, match=r"bad\.pcd.*DATA"):
        read_pcd(bad)
    bad.write_bytes(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA binary_lz4\n")
    with pytest.raises(LirisError, match="unsupported PCD DATA"):
        read_pcd(bad)
    bad.write_bytes(b"FIELDS x y z\nSIZE 2 4 4\nTYPE U F F\nPOINTS 1\nDATA binary\n" + bytes(10))
    np.testing.assert_array_equal(read_pcd(bad).points, np.zeros((1, 3)))  # integer x is fine
    bad.write_bytes(b"FIELDS x y z\nSIZE 3 4 4\nTYPE F F F\nPOINTS 1\nDATA binary\n" + bytes(11))
    with pytest.raises(LirisError, match="unsupported TYPE F SIZE 3"):
        read_pcd(bad)
