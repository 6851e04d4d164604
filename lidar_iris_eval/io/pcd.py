"""Reading PCL ``.pcd`` scans: ascii, binary and binary_compressed encodings.

Only the fields liris uses are decoded: ``x y z`` and, when present,
``intensity``. Other fields (``rgb``, ``normal_x``, ``ring``, PCL's ``_``
padding …) are skipped by their byte offsets, so any PCL point type reads.

``binary_compressed`` stores the points *field-major* (all x, then all y, …)
and LZF-compresses the whole block. LZF is a tiny byte-oriented LZ77 variant;
its token stream must be walked in order, but the copies it describes are
resolved here with NumPy (see :func:`lzf_decompress`), so no C extension is
needed.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.scans import Scan, clean_points

#: (PCD TYPE letter, SIZE) -> little-endian NumPy type
PCD_TYPES = {
    ("F", 4): "<f4", ("F", 8): "<f8",
    ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
    ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
}
WANTED_FIELDS = ("x", "y", "z", "intensity")
PADDING_FIELD = "_"  # PCL's name for alignment bytes; not written in ascii/compressed data
ENCODINGS = ("ascii", "binary", "binary_compressed")
MAX_HEADER_LINES = 64
LZF_LITERAL_LIMIT = 32  # control bytes below this start a literal run


@dataclass(frozen=True)
class PcdHeader:
    """The parsed header: one entry per field in file order, plus the layout."""

    fields: tuple[str, ...]
    sizes: tuple[int, ...]
    types: tuple[str, ...]
    counts: tuple[int, ...]
    points: int
    encoding: str
    data_offset: int  # byte offset of the first data byte

    @property
    def point_bytes(self) -> int:
        """Bytes of one point record, padding fields included (binary layout)."""
        return sum(s * c for s, c in zip(self.sizes, self.counts, strict=True))

    def span(self, index: int, packed: bool) -> int:
        """Bytes (or, for ascii, values) of one field; padding ``_`` is absent when packed."""
        if packed and self.fields[index] == PADDING_FIELD:
            return 0
        return self.sizes[index] * self.counts[index]

    def field_dtype(self, index: int, source: Path) -> np.dtype:
        key = (self.types[index], self.sizes[index])
        if key not in PCD_TYPES:
            raise LirisError(
                source, f"field {self.fields[index]!r}: unsupported TYPE {key[0]} SIZE {key[1]}"
            )
        return np.dtype(PCD_TYPES[key])


def read_pcd(path: str | Path) -> Scan:
    """Read a ``.pcd`` scan into points ``(N, 3)`` float32 and optional intensity.

    Non-finite points (PCL marks invalid returns with NaN) are dropped with a
    warning; an empty, truncated or malformed file raises :class:`LirisError`
    naming it.
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "scan file not found")
    raw = path.read_bytes()
    header = parse_header(raw, path)
    columns = _decode(raw, header, path)
    points = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
    return clean_points(points, columns.get("intensity"), path)


def parse_header(raw: bytes, source: Path) -> PcdHeader:
    """Parse the text header up to and including the ``DATA`` line."""
    entries: dict[str, list[str]] = {}
    pos = 0
    for _ in range(MAX_HEADER_LINES):
        end = raw.find(b"\n", pos)
        if end < 0:
            raise LirisError(source, "truncated or not a PCD file: no DATA line in the header")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        entries[key.upper()] = values
        if key.upper() == "DATA":
            break
    else:
        raise LirisError(source, "not a PCD file: no DATA line in the first header lines")
    return _header_from_entries(entries, pos, source)


def _header_from_entries(entries: dict[str, list[str]], offset: int, source: Path) -> PcdHeader:
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in entries:
            raise LirisError(source, f"malformed PCD header: no {key} line")
    fields = tuple(entries["FIELDS"])
    n = len(fields)
    try:
        sizes = tuple(int(v) for v in entries["SIZE"])
        counts = tuple(int(v) for v in entries.get("COUNT", ["1"] * n))
        width = int(entries.get("WIDTH", ["-1"])[0])
        height = int(entries.get("HEIGHT", ["1"])[0])
        points = int(entries["POINTS"][0]) if "POINTS" in entries else width * height
    except (ValueError, IndexError):
        raise LirisError(
            source, "malformed PCD header: SIZE/COUNT/WIDTH/POINTS not integers"
        ) from None
    types = tuple(v.upper() for v in entries["TYPE"])
    if not (len(sizes) == len(types) == len(counts) == n):
        raise LirisError(source, "malformed PCD header: FIELDS, SIZE, TYPE, COUNT lengths differ")
    if points < 0:
        raise LirisError(source, "malformed PCD header: no POINTS or WIDTH")
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise LirisError(source, f"PCD has no {'/'.join(missing)} field(s); fields are {fields}")
    for name in WANTED_FIELDS:
        if name in fields and (count := counts[fields.index(name)]) != 1:
            raise LirisError(source, f"field {name!r} has COUNT {count}, expected 1")
    encoding = entries["DATA"][0].lower() if entries["DATA"] else ""
    if encoding not in ENCODINGS:
        raise LirisError(source, f"unsupported PCD DATA {encoding!r}; expected one of {ENCODINGS}")
    return PcdHeader(fields, sizes, types, counts, points, encoding, offset)


def _decode(raw: bytes, header: PcdHeader, source: Path) -> dict[str, np.ndarray]:
    """The wanted fields as 1-D arrays, whatever the encoding."""
    if header.points == 0:
        raise LirisError(source, "empty scan (POINTS 0)")
    if header.encoding == "ascii":
        return _decode_ascii(raw, header, source)
    if header.encoding == "binary":
        return _decode_binary(raw, header, source)
    return _decode_compressed(raw, header, source)


def _wanted(header: PcdHeader) -> list[int]:
    return [i for i, name in enumerate(header.fields) if name in WANTED_FIELDS]


def _decode_ascii(raw: bytes, header: PcdHeader, source: Path) -> dict[str, np.ndarray]:
    # One column per value: a field with COUNT c occupies c columns. PCL does
    # not print padding fields, but accept files whose rows include them.
    try:
        values = np.array(raw[header.data_offset:].split(), dtype=np.float64)
    except ValueError:
        raise LirisError(source, "malformed ascii PCD data (non-numeric value)") from None
    layouts = []
    for packed in (True, False):
        widths = [c if header.span(i, packed) else 0 for i, c in enumerate(header.counts)]
        layouts.append((sum(widths), np.cumsum([0, *widths[:-1]])))
    for n_cols, starts in layouts:
        if values.size == header.points * n_cols:
            table = values.reshape(header.points, n_cols)
            return {header.fields[i]: table[:, starts[i]] for i in _wanted(header)}
    raise LirisError(
        source,
        f"truncated or malformed ascii PCD: {values.size} values, expected "
        f"{header.points} points × {layouts[0][0]}",
    )


def _decode_binary(raw: bytes, header: PcdHeader, source: Path) -> dict[str, np.ndarray]:
    # Point-major records: a structured dtype picks the wanted fields by offset.
    need = header.points * header.point_bytes
    have = len(raw) - header.data_offset
    if have < need:
        raise LirisError(source, f"truncated binary PCD: {have} data bytes, expected {need}")
    offsets = np.concatenate([[0], np.cumsum(np.multiply(header.sizes, header.counts))[:-1]])
    wanted = _wanted(header)
    dtype = np.dtype({
        "names": [header.fields[i] for i in wanted],
        "formats": [header.field_dtype(i, source) for i in wanted],
        "offsets": [int(offsets[i]) for i in wanted],
        "itemsize": header.point_bytes,
    })
    records = np.frombuffer(raw, dtype=dtype, count=header.points, offset=header.data_offset)
    return {name: records[name] for name in dtype.names}


def _decode_compressed(raw: bytes, header: PcdHeader, source: Path) -> dict[str, np.ndarray]:
    # Two uint32 sizes, then the LZF stream of the field-major block.
    start = header.data_offset
    if len(raw) < start + 8:
        raise LirisError(source, "truncated binary_compressed PCD: no size words after DATA")
    compressed_size, raw_size = struct.unpack_from("<II", raw, start)
    need = header.points * sum(header.span(i, True) for i in range(len(header.fields)))
    if raw_size != need:
        raise LirisError(
            source, f"binary_compressed PCD: uncompressed size {raw_size}, expected {need} bytes"
        )
    stream = raw[start + 8 : start + 8 + compressed_size]
    if len(stream) < compressed_size:
        raise LirisError(
            source,
            f"truncated binary_compressed PCD: {len(stream)} of {compressed_size} compressed bytes",
        )
    block = lzf_decompress(stream, raw_size, source)
    out = {}
    field_start = 0
    for i, name in enumerate(header.fields):
        span = header.points * header.span(i, True)
        if name in WANTED_FIELDS:
            dtype = header.field_dtype(i, source)
            out[name] = np.frombuffer(block, dtype=dtype, count=header.points, offset=field_start)
        field_start += span
    return out


def lzf_decompress(
    data: bytes, size: int, source: str | Path = "LZF stream", engine: str = "auto"
) -> bytes:
    """Decompress an LZF stream whose decompressed ``size`` is known.

    LZF tokens: a control byte ``c < 32`` starts a literal run of ``c + 1``
    bytes; otherwise ``c >> 5`` is a length (7 means "add the next byte") and
    the low 5 bits plus the next byte give a back-reference distance, and
    ``length + 2`` bytes are copied from that far back (possibly overlapping
    the bytes being written, which repeats a pattern).

    ``engine``: ``"numpy"`` walks the tokens in a Python loop (one step per
    token, not per byte) and does the copies vectorised: every copied byte
    points at an earlier byte, and chains are collapsed by pointer jumping in
    ``log2(depth)`` NumPy passes. ``"numba"`` runs the plain byte loop
    compiled, 25-50× faster on a real 120k-point KITTI scan (13-16 ms vs
    400-650 ms, loaded 2-core machine); ``"auto"`` uses numba when installed.
    """
    if engine not in ("auto", "numpy", "numba"):
        raise ValueError(f"unknown LZF engine {engine!r}")
    kernel = _numba_kernel() if engine != "numpy" else None
    if engine == "numba" and kernel is None:
        raise RuntimeError("numba is not installed")
    if kernel is not None:
        out = np.empty(size, dtype=np.uint8)
        status = kernel(np.frombuffer(data, dtype=np.uint8), out)
        if status < 0:
            raise LirisError(source, f"corrupt LZF data: {_KERNEL_ERRORS[status]}")
        if status != size:
            raise LirisError(
                source, f"corrupt or truncated LZF data: {status} bytes decoded, expected {size}"
            )
        return out.tobytes()
    return _lzf_numpy(data, size, source)


def _lzf_numpy(data: bytes, size: int, source: str | Path) -> bytes:
    lit_out, lit_in, lit_len, ref_out, ref_dist, ref_len = _lzf_tokens(data, size, source)
    inp = np.frombuffer(data, dtype=np.uint8)
    out = np.zeros(size, dtype=np.uint8)
    if lit_len.size:
        out[_expand(lit_out, lit_len)] = inp[_expand(lit_in, lit_len)]
    if ref_len.size:
        pos = _expand(ref_out, ref_len)
        # Each copied byte repeats the byte `dist` back (byte-wise LZ77 copy).
        src = pos - np.repeat(ref_dist, ref_len)
        # Follow pointers until they land on literal bytes: `parent` maps a
        # copied position to its source, literal positions to themselves.
        parent = np.arange(size, dtype=np.int64)
        parent[pos] = src
        while True:
            src = parent[src]
            if not np.any(parent[src] != src):
                break
            parent[pos] = src
        out[pos] = out[src]
    return out.tobytes()


_KERNEL_ERRORS = {
    -1: "literal run or copy past the end of the output",
    -2: "stream ends inside a back-reference",
    -3: "back-reference before the start",
    -4: "literal run past the end of the stream",
}


@functools.lru_cache(maxsize=1)
def _numba_kernel():
    """The compiled byte loop, or None without numba (compiled once, cached on disk)."""
    try:
        import numba
    except ImportError:
        return None
    return numba.njit(cache=True, nogil=True)(_lzf_byte_loop)


def _lzf_byte_loop(inp: np.ndarray, out: np.ndarray) -> int:
    """Plain LZF decoding into ``out``; returns bytes written or a negative error code.

    Only ever run compiled by numba (see :func:`_numba_kernel`).
    """
    n = inp.size
    size = out.size
    i = 0
    op = 0
    while i < n:
        ctrl = inp[i]
        i += 1
        if ctrl < 32:
            run = ctrl + 1
            if i + run > n:
                return -4
            if op + run > size:
                return -1
            for k in range(run):
                out[op + k] = inp[i + k]
            i += run
            op += run
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                return -2
            length += inp[i]
            i += 1
        if i >= n:
            return -2
        ref = op - (((ctrl & 0x1F) << 8) + inp[i] + 1)
        i += 1
        length += 2
        if ref < 0:
            return -3
        if op + length > size:
            return -1
        for k in range(length):
            out[op + k] = out[ref + k]
        op += length
    return op


def _lzf_tokens(data: bytes, size: int, source: str | Path) -> tuple[np.ndarray, ...]:
    """Walk the token stream: literal (out, in, len) and reference (out, dist, len) runs."""
    lit_out: list[int] = []
    lit_in: list[int] = []
    lit_len: list[int] = []
    ref_out: list[int] = []
    ref_dist: list[int] = []
    ref_len: list[int] = []
    n = len(data)
    i = 0
    op = 0
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < LZF_LITERAL_LIMIT:
            run = ctrl + 1
            if i + run > n:
                raise LirisError(source, "corrupt LZF data: literal run past the end of the stream")
            lit_out.append(op)
            lit_in.append(i)
            lit_len.append(run)
            i += run
            op += run
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                raise LirisError(source, "corrupt LZF data: stream ends inside a back-reference")
            length += data[i]
            i += 1
        if i >= n:
            raise LirisError(source, "corrupt LZF data: stream ends inside a back-reference")
        dist = ((ctrl & 0x1F) << 8) + data[i] + 1
        i += 1
        if dist > op:
            raise LirisError(source, "corrupt LZF data: back-reference before the start")
        ref_out.append(op)
        ref_dist.append(dist)
        ref_len.append(length + 2)
        op += length + 2
    if op != size:
        raise LirisError(
            source, f"corrupt or truncated LZF data: {op} bytes decoded, expected {size}"
        )
    as_array = [np.asarray(v, dtype=np.int64) for v in (lit_out, lit_in, lit_len)]
    as_array += [np.asarray(v, dtype=np.int64) for v in (ref_out, ref_dist, ref_len)]
    return tuple(as_array)


def _expand(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenate ``arange(s, s + l)`` for each run, without a Python loop."""
    total = int(lengths.sum())
    run_starts = np.cumsum(lengths) - lengths
    return np.repeat(starts - run_starts, lengths) + np.arange(total, dtype=np.int64)
