"""Readers of other systems' loop closures (issue 35): one :class:`LoopFile` per file.

Formats (``--loops-format``; detected where the file says which it is):

* ``g2o`` -- a pose graph: ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and
  ``EDGE_SE3:QUAT a b x y z qx qy qz qw [21 information entries]`` (``FIX`` lines
  are skipped). Loop edges are those with ``|a - b| > gap`` (vertex ids;
  ``gap`` 1 by default, so odometry edges between consecutive vertices drop
  out). Each edge's measurement is the pose of ``b`` in ``a``'s frame; a loop
  is stored with the later frame as its query and the pose of the earlier one
  in the query's frame (inverted when ``a < b``). Detected from the ``.g2o``
  suffix or a first record starting with ``VERTEX_`` / ``EDGE_``.
* ``matches`` -- a liris run's ``protocol1/<d>/matches.csv`` (a header with
  ``query``, ``match`` and ``distance``; ``T00..T23`` when present give the
  pose). One row per query; ``match -1`` is a query without a match. Detected
  from that header.
* ``liris-txt`` -- liris's ``--export-loops FILE.txt``: ``i j x y z qx qy qz qw``
  (frame ids, the pose of ``j`` in ``i``'s frame; ``nan`` translation for
  yaw-only loops). Detected from exactly 9 numeric columns on every line.
* ``pairs`` -- ``query match [score]`` per line, whitespace or comma separated,
  optionally ``query match score x y z qx qy qz qw`` (10 columns); a 4th column
  without a pose (the LiDAR Iris authors' demo writes ``query match distance
  flag``) is ignored. Indices are 0-based unless ``index_base=1``. A first line
  whose first field is not a number is a header; ``#`` starts a comment.

Ids are the frames' ids: the scans' frame ids when the sequence has them (what
liris's own exports write), otherwise their indices. Every problem is one
:class:`~lidar_iris_eval.errors.LirisError` naming the file and line.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, read_text, warn
from lidar_iris_eval.io.poses import is_number, quaternion_to_matrix

LOOP_FORMATS = ("g2o", "matches", "liris-txt", "pairs", "tum", "mapclosures")
#: default tolerance (s) of a time stamp matched to a scan's time
TIME_TOLERANCE = 0.05
#: the columns a matches.csv must have
MATCHES_COLUMNS = ("query", "match", "distance")
_T_NAMES = [f"T{r}{c}" for r in range(3) for c in range(4)]
_SPLIT = re.compile(r"[,\s;]+")


@dataclass(frozen=True)
class LoopFile:
    """The loops one file claims, in file order.

    ``query``/``match`` are frame ids (not yet scan indices; see
    :meth:`indices`); ``score`` is lower-is-better (a distance) or None when
    the file has none; ``pose`` ``(K, 4, 4)`` is the match's pose in the
    query's frame (NaN where unknown) or None; ``line`` is each loop's line
    number in the file.
    """

    path: Path
    format: str
    query: np.ndarray
    match: np.ndarray
    score: np.ndarray | None
    pose: np.ndarray | None
    line: np.ndarray
    #: g2o: edges dropped as odometry (|a - b| <= gap)
    n_odometry_edges: int = 0
    #: the rule that picked the loops, for the record
    rule: str = ""
    extra: dict = field(default_factory=dict)
    #: ``query``/``match`` are time stamps (s; the ``tum`` format), not ids
    by_time: bool = False
    #: g2o: the graph (vertex poses by id, odometry and loop edges with information)
    graph: G2OGraph | None = None

    def __len__(self) -> int:
        return len(self.query)

    def indices(self, frame_ids: np.ndarray | None, n_frames: int, *,
                times: np.ndarray | None = None, keyframes: Keyframes | None = None,
                tolerance: float = TIME_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
        """``(query, match)`` as scan indices; an id that is no scan is an error naming
        its line (``match -1``, a query without a match, stays -1).

        Time stamps (``tum``) and keyframes mapped by ``keyframes``
        (:func:`read_keyframes`) are placed on the scan whose time (``times``)
        is nearest, within ``tolerance`` seconds.
        """
        if self.extra.get("map_ids") and keyframes is None:
            raise LirisError(self.path, "MapClosures local-map ids need the maps' scans: "
                                        "--loops-map FILE ('map first_scan [last_scan]' lines)")
        return (place(self.query, self.line, self.path, n_frames, frame_ids, times,
                      keyframes, tolerance, self.by_time),
                place(self.match, self.line, self.path, n_frames, frame_ids, times,
                      keyframes, tolerance, self.by_time, allow_missing=True))


def _pose(values: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = values[:3]
    q = np.asarray(values[3:7], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm == 0:
        T[:3, :3] = np.nan
    else:
        T[:3, :3] = quaternion_to_matrix(q[None] / norm)[0]
    return T


def _invert(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def _numbers(fields: list[str], where: str, what: str) -> list[float]:
    try:
        return [float(v) for v in fields]
    except ValueError:
        raise LirisError(where, f"{what}: expected numbers, got {' '.join(fields)!r}") from None


def _integer(text: str, where: str, what: str) -> int:
    try:
        value = float(text)
    except ValueError:
        raise LirisError(where, f"{what}: expected an integer, got {text!r}") from None
    if not math.isfinite(value) or value != int(value):
        raise LirisError(where, f"{what}: expected an integer, got {text!r}")
    return int(value)


def _records(text: str):
    """(line number, fields) of every non-empty, non-comment line."""
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if line:
            yield number, [f for f in _SPLIT.split(line) if f]


def detect_format(path: Path, text: str) -> str:
    """The format a file's name and content say, or an error asking for ``--loops-format``."""
    if path.suffix.lower() == ".g2o":
        return "g2o"
    if path.suffix.lower() == ".tum":
        return "tum"
    if path.name.lower() == "map_closures.txt":
        return "mapclosures"
    records = list(_records(text))
    if not records:
        raise LirisError(path, "no loops in the file")
    first = records[0][1]
    if all(len(f) in (18, 20) and all(map(is_number, f)) for _, f in records):
        return "mapclosures"
    if first[0].upper().startswith(("VERTEX_", "EDGE_")):
        return "g2o"
    header = [f.strip().lower() for f in first]
    if all(c in header for c in MATCHES_COLUMNS):
        return "matches"
    body = records[1:] if not is_number(first[0]) else records
    if body and all(len(f) == 9 for _, f in body):
        return "liris-txt"
    return "pairs"


def read_loops(path: str | Path, fmt: str | None = None, *, index_base: int = 0,
               gap: int = 1, similarity: bool = False) -> LoopFile:
    """Read a loop file (format ``fmt`` or detected; module docstring).

    ``index_base`` (0 or 1) applies to ``pairs`` files; ``gap`` is the g2o rule
    (an edge is a loop when its vertex ids differ by more than ``gap``);
    ``similarity`` says a ``pairs`` score is higher-is-better (it is negated,
    so every score is a distance).
    """
    path = Path(path)
    if fmt is not None and fmt not in LOOP_FORMATS:
        raise LirisError(f"--loops-format {fmt}", f"choose from {', '.join(LOOP_FORMATS)}")
    if index_base not in (0, 1):
        raise LirisError(f"--loops-index-base {index_base}", "must be 0 or 1")
    if gap < 1:
        raise LirisError(f"--loops-gap {gap}", "must be at least 1")
    text = read_text(path, "loop file")
    fmt = detect_format(path, text) if fmt is None else fmt
    if fmt == "g2o":
        return _read_g2o(path, text, gap)
    if fmt == "matches":
        return _read_matches(path, text)
    if fmt == "tum":
        return _read_tum(path, text)
    if fmt == "mapclosures":
        return _read_mapclosures(path, text)
    return _read_columns(path, text, fmt, index_base if fmt == "pairs" else 0, similarity)


@dataclass(frozen=True)
class G2OGraph:
    """A g2o file's 3-D records: vertex poses by id, edges ``(a, b, T, info)`` (``T`` the
    pose of ``b`` in ``a``'s frame, ``info`` 6x6 in g2o's order x y z qx qy qz; the
    identity when the edge has none), fixed ids, and the line of each vertex and edge."""

    vertices: dict[int, np.ndarray]
    edges: list[tuple[int, int, np.ndarray, np.ndarray]]
    fixed: list[int]
    vertex_lines: dict[int, int] = field(default_factory=dict)
    edge_lines: list[int] = field(default_factory=list)


def parse_g2o(path: str | Path, text: str | None = None, *, need_vertices: bool = False,
              skip_unknown: bool = False) -> G2OGraph:
    """The one reader of g2o's ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` / ``FIX`` records.

    An edge has 7 pose numbers and optionally the 21 upper-triangular entries of
    its information matrix (rebuilt symmetric, must be positive definite). An
    edge naming a vertex the file does not define is an error naming its line
    (when the file defines vertices, or always with ``need_vertices``). Any other
    record is an error, or with ``skip_unknown`` skipped with one warning counting
    them by tag (hdl_graph_slam also writes planes, GPS and IMU priors).
    """
    path = Path(path)
    text = read_text(path, "g2o file") if text is None else text
    vertices: dict[int, np.ndarray] = {}
    vertex_lines: dict[int, int] = {}
    edges, edge_lines, fixed = [], [], []
    skipped: dict[str, int] = {}
    for number, fields in _records(text):
        where = f"{path}:{number}"
        tag, rest = fields[0].upper(), fields[1:]
        if tag == "VERTEX_SE3:QUAT":
            if len(rest) != 8:
                raise LirisError(where, f"VERTEX_SE3:QUAT needs 8 fields, got {len(rest)}")
            vid = _integer(rest[0], where, "vertex id")
            if vid in vertices:
                raise LirisError(where, f"vertex {vid} given twice (first on line "
                                        f"{vertex_lines[vid]})")
            vertices[vid] = _pose(_numbers(rest[1:], where, "vertex pose"))
            vertex_lines[vid] = number
        elif tag == "EDGE_SE3:QUAT":
            if len(rest) not in (9, 30):
                raise LirisError(where, f"EDGE_SE3:QUAT needs 9 or 30 fields (ids, pose, "
                                        f"information), got {len(rest)}")
            a = _integer(rest[0], where, "edge vertex id")
            b = _integer(rest[1], where, "edge vertex id")
            values = _numbers(rest[2:], where, "edge")
            if a == b:
                raise LirisError(where, f"edge {a}-{b} joins a vertex to itself")
            info = np.eye(6)
            if len(values) == 28:
                info = np.zeros((6, 6))
                info[np.triu_indices(6)] = values[7:]
                info = info + np.triu(info, 1).T
                if not np.isfinite(info).all() or np.linalg.eigvalsh(info).min() <= 0:
                    raise LirisError(where, "information matrix is not positive definite")
            edges.append((a, b, _pose(values[:7]), info))
            edge_lines.append(number)
        elif tag == "FIX":
            fixed.extend(_integer(v, where, "fixed vertex id") for v in rest)
        elif skip_unknown:
            skipped[fields[0]] = skipped.get(fields[0], 0) + 1
        else:
            raise LirisError(where, f"unknown record {fields[0]} (liris reads VERTEX_SE3:QUAT, "
                                    "EDGE_SE3:QUAT and FIX)")
    if skipped:
        warn(path, "skipped records liris does not read: " + ", ".join(
            f"{count} {tag}" for tag, count in sorted(skipped.items())))
    if vertices or need_vertices:
        for (a, b, _, _), number in zip(edges, edge_lines, strict=True):
            for vid in (a, b):
                if vid not in vertices:
                    raise LirisError(f"{path}:{number}", f"edge {a}-{b} names a missing "
                                                         f"vertex {vid} (the file does not "
                                                         "define it)")
    return G2OGraph(vertices, edges, fixed, vertex_lines, edge_lines)


def _read_g2o(path: Path, text: str, gap: int) -> LoopFile:
    graph = parse_g2o(path, text, skip_unknown=True)
    if not graph.edges:
        raise LirisError(path, "no EDGE_SE3:QUAT records: not a pose graph with loops")
    query, match, pose, lines, edge_index = [], [], [], [], []
    n_odometry = 0
    for e, ((a, b, T, _), number) in enumerate(zip(graph.edges, graph.edge_lines,
                                                   strict=True)):
        if abs(a - b) <= gap:
            n_odometry += 1
            continue
        edge_index.append(e)
        if a > b:  # T: pose of b (the earlier frame) in a's (the query's) frame
            query.append(a), match.append(b), pose.append(T)
        else:
            query.append(b), match.append(a), pose.append(_invert(T))
        lines.append(number)
    return LoopFile(path, "g2o", np.array(query, dtype=np.int64),
                    np.array(match, dtype=np.int64), None,
                    np.array(pose).reshape(-1, 4, 4), np.array(lines, dtype=np.int64),
                    n_odometry_edges=n_odometry,
                    rule=f"g2o EDGE_SE3:QUAT with |a - b| > {gap} (vertex ids); the later "
                         "vertex is the query", graph=graph,
                    extra={"edge_index": np.array(edge_index, dtype=np.int64)})


def _read_matches(path: Path, text: str) -> LoopFile:
    records = list(_records(text))
    header = [f.strip().lower() for f in records[0][1]]
    missing = [c for c in MATCHES_COLUMNS if c not in header]
    if missing:
        raise LirisError(f"{path}:{records[0][0]}", f"a matches.csv header needs the columns "
                                                    f"{', '.join(missing)}")
    col = {name: header.index(name) for name in header}
    has_pose = all(n.lower() in col for n in _T_NAMES)
    query, match, score, pose, lines = [], [], [], [], []
    text_rows = [(n, [c.strip() for c in raw.split(",")])
                 for n, raw in enumerate(text.splitlines(), start=1)][records[0][0]:]
    for number, cells in text_rows:
        if not any(cells):
            continue
        where = f"{path}:{number}"
        if len(cells) != len(header):
            raise LirisError(where, f"expected {len(header)} columns (the header's), got "
                                    f"{len(cells)}")
        query.append(_integer(cells[col["query"]], where, "query"))
        match.append(_integer(cells[col["match"]], where, "match"))
        value = cells[col["distance"]]
        score.append(_numbers([value or "nan"], where, "distance")[0])
        if has_pose:
            values = _numbers([cells[col[n.lower()]] or "nan" for n in _T_NAMES], where,
                              "T00..T23")
            T = np.eye(4)
            T[:3, :4] = np.reshape(values, (3, 4))
            pose.append(T)
        lines.append(number)
    if not query:
        raise LirisError(path, "no rows after the header")
    return LoopFile(path, "matches", np.array(query, dtype=np.int64),
                    np.array(match, dtype=np.int64), np.array(score, dtype=np.float64),
                    np.array(pose).reshape(-1, 4, 4) if has_pose else None,
                    np.array(lines, dtype=np.int64),
                    rule="liris matches.csv: one best match per query, score = distance")


def _read_columns(path: Path, text: str, fmt: str, base: int, similarity: bool) -> LoopFile:
    records = list(_records(text))
    if records and not is_number(records[0][1][0]):
        records = records[1:]  # a header
    if not records:
        raise LirisError(path, "no loops in the file")
    allowed = (9,) if fmt == "liris-txt" else (2, 3, 4, 10)
    query, match, score, pose, lines = [], [], [], [], []
    for number, fields in records:
        where = f"{path}:{number}"
        if len(fields) not in allowed:
            shape = ("i j x y z qx qy qz qw" if fmt == "liris-txt" else
                     "query match [score] or query match score x y z qx qy qz qw")
            raise LirisError(where, f"expected {shape} ({' or '.join(map(str, allowed))} "
                                    f"columns), got {len(fields)}")
        q = _integer(fields[0], where, "query") - base
        m = _integer(fields[1], where, "match") - base
        if q < 0:
            raise LirisError(where, f"query {fields[0]} is below the index base {base}")
        query.append(q)
        match.append(m if m >= 0 else -1)
        values = _numbers(fields[2:], where, "score/pose") if len(fields) > 2 else []
        if fmt == "liris-txt":
            pose.append(_pose(values))
        elif len(fields) >= 3:
            score.append(-values[0] if similarity else values[0])
            if len(fields) == 10:
                pose.append(_pose(values[1:]))
        lines.append(number)
    with_pose = len(pose) == len(query)
    if pose and not with_pose:
        raise LirisError(path, "some lines carry a pose and others do not")
    if score and len(score) != len(query):
        raise LirisError(path, "some lines carry a score and others do not")
    rule = ("liris --export-loops .txt: accepted loops, no score" if fmt == "liris-txt" else
            f"pair list, {base}-based" + (", score = distance" if score and not similarity
                                          else ", score = similarity (negated)" if score
                                          else ", no score"))
    return LoopFile(path, fmt, np.array(query, dtype=np.int64), np.array(match, dtype=np.int64),
                    np.array(score, dtype=np.float64) if score else None,
                    np.array(pose).reshape(-1, 4, 4) if with_pose else None,
                    np.array(lines, dtype=np.int64), rule=rule)


def _read_tum(path: Path, text: str) -> LoopFile:
    """``t_query t_match [x y z qx qy qz qw]``: loops between time stamps (seconds)."""
    records = list(_records(text))
    if records and not is_number(records[0][1][0]):
        records = records[1:]
    if not records:
        raise LirisError(path, "no loops in the file")
    query, match, pose, lines = [], [], [], []
    for number, fields in records:
        where = f"{path}:{number}"
        if len(fields) not in (2, 9):
            raise LirisError(where, f"expected t_query t_match [x y z qx qy qz qw] (2 or 9 "
                                    f"columns), got {len(fields)}")
        values = _numbers(fields, where, "time pair")
        if not (math.isfinite(values[0]) and math.isfinite(values[1])):
            raise LirisError(where, "time stamps must be finite")
        query.append(values[0]), match.append(values[1])
        if len(fields) == 9:
            pose.append(_pose(values[2:]))
        lines.append(number)
    if pose and len(pose) != len(query):
        raise LirisError(path, "some lines carry a pose and others do not")
    return LoopFile(path, "tum", np.array(query, dtype=np.float64),
                    np.array(match, dtype=np.float64), None,
                    np.array(pose).reshape(-1, 4, 4) if pose else None,
                    np.array(lines, dtype=np.int64), by_time=True,
                    rule="TUM-style time pairs: each stamp placed on the nearest scan time")


@dataclass(frozen=True)
class Keyframes:
    """How a file's keyframe ids become scans: by each keyframe's time (``times``, one per
    keyframe, keyframe ``k`` on line ``lines[k]``) or by an explicit ``keyframe -> scan``
    map (``scans``)."""

    path: Path
    times: np.ndarray | None = None
    lines: np.ndarray | None = None
    scans: dict[int, int] | None = None

    @property
    def rule(self) -> str:
        if self.times is not None:
            return f"keyframe k at the scan nearest the k-th time of {self.path.name}"
        return f"keyframe -> scan map {self.path.name}"


def read_keyframes(times: str | Path | None = None, mapping: str | Path | None = None
                   ) -> Keyframes | None:
    """Keyframe times (one per line, or the first column of a TUM trajectory, as
    SC-LIO-SAM's ``times.txt``) or a ``keyframe scan`` map file; None without either."""
    if times is not None and mapping is not None:
        raise LirisError("--loops-times/--loops-map", "give one way to place keyframes")
    if times is None and mapping is None:
        return None
    path = Path(times if times is not None else mapping)
    text = read_text(path, "keyframe file")
    records = list(_records(text))
    if records and not is_number(records[0][1][0]):
        records = records[1:]
    if not records:
        raise LirisError(path, "no keyframes in the file")
    if times is not None:
        stamps = []
        for number, fields in records:
            value = _numbers(fields[:1], f"{path}:{number}", "keyframe time")[0]
            if not math.isfinite(value):
                raise LirisError(f"{path}:{number}", "keyframe time must be finite")
            stamps.append(value)
        return Keyframes(path, times=np.array(stamps),
                         lines=np.array([n for n, _ in records], dtype=np.int64))
    scans: dict[int, int] = {}
    for number, fields in records:
        where = f"{path}:{number}"
        if len(fields) not in (2, 3):  # 3: a local map's scan range (its frame: the first)
            raise LirisError(where, f"expected 'keyframe scan' or 'map first_scan last_scan' "
                                    f"(2 or 3 columns), got {len(fields)}")
        k = _integer(fields[0], where, "keyframe")
        if k in scans:
            raise LirisError(where, f"keyframe {k} mapped twice")
        scans[k] = _integer(fields[1], where, "scan")
    return Keyframes(path, scans=scans)


def nearest_scan(stamp: float, times: np.ndarray, tolerance: float) -> int | None:
    """Index of the scan time nearest ``stamp`` (sorted ``times``), or None beyond
    ``tolerance`` seconds."""
    k = int(np.searchsorted(times, stamp))
    best = None
    for c in (k - 1, k):
        if 0 <= c < len(times) and (best is None or abs(times[c] - stamp) <
                                    abs(times[best] - stamp)):
            best = c
    if best is None or abs(times[best] - stamp) > tolerance:
        return None
    return best


def place(values: np.ndarray, lines: np.ndarray, path: Path, n_frames: int,
          frame_ids: np.ndarray | None, times: np.ndarray | None, keyframes: Keyframes | None,
          tolerance: float = TIME_TOLERANCE, by_time: bool = False,
          allow_missing: bool = False) -> np.ndarray:
    """Scan index of each keyframe id or time stamp in ``values`` (``lines``: their lines
    in ``path``); one that cannot be placed is an error naming the file and line."""
    needs_times = by_time or (keyframes is not None and keyframes.times is not None)
    if needs_times and times is None:
        raise LirisError(path, "placing loops by time needs the sequence's scan times "
                               "(times.txt or --times)")
    if frame_ids is None or np.array_equal(frame_ids, np.arange(n_frames)):
        ids = None
    else:
        ids = {int(v): k for k, v in enumerate(np.asarray(frame_ids))}
    order = np.argsort(times, kind="stable") if needs_times else None
    sorted_times = times[order] if needs_times else None
    out = np.empty(len(values), dtype=np.int64)
    for k, v in enumerate(values):
        where = f"{path}:{lines[k]}"
        if allow_missing and not by_time and int(v) == -1:
            out[k] = -1
            continue
        if not by_time and keyframes is None:  # frame ids (or indices)
            v = int(v)
            hit = (v if 0 <= v < n_frames else None) if ids is None else ids.get(v)
            if hit is None:
                raise LirisError(where, f"{'frame' if ids is None else 'frame id'} {v} is not "
                                        f"in the sequence ({n_frames} scans"
                                        + (", ids from the scan file names" if ids else
                                           f", indices 0..{n_frames - 1}") + ")")
            out[k] = hit
            continue
        if by_time:
            stamp, what = float(v), f"time {float(v):.9g}"
        elif keyframes.times is not None:
            kf = int(v)
            if not 0 <= kf < len(keyframes.times):
                raise LirisError(where, f"keyframe {kf} has no time in {keyframes.path} "
                                        f"({len(keyframes.times)} keyframes, 0..."
                                        f"{len(keyframes.times) - 1})")
            stamp = float(keyframes.times[kf])
            what = (f"keyframe {kf} (time {stamp:.9g}, {keyframes.path}:"
                    f"{keyframes.lines[kf]})")
        else:
            kf = int(v)
            if kf not in keyframes.scans:
                raise LirisError(where, f"keyframe {kf} is not in the map {keyframes.path}")
            scan = keyframes.scans[kf]
            hit = scan if ids is None else ids.get(scan)
            if hit is None or not 0 <= hit < n_frames:
                raise LirisError(where, f"keyframe {kf} maps to scan {scan}, which is not in "
                                        f"the sequence ({n_frames} scans)")
            out[k] = hit
            continue
        hit = nearest_scan(stamp, sorted_times, tolerance)
        if hit is None:
            raise LirisError(where, f"{what} matches no scan within {tolerance:g} s (scans "
                                    f"span {sorted_times[0]:.9g}..{sorted_times[-1]:.9g} s)")
        out[k] = order[hit]
    return out


def _read_mapclosures(path: Path, text: str) -> LoopFile:
    """MapClosures' ``map_closures.txt``: per closure ``reference_map query_map`` and the
    4x4 pose (18 numbers), or ``reference_map query_map reference_first_scan
    query_first_scan`` and the pose (20, the pipeline of map_closures >= 2). A local map
    is placed on its first scan (the map's frame): from the file's scan columns, or from
    ``--loops-map`` (``map first_scan [last_scan]``) when the file has map ids only."""
    records = list(_records(text))
    if not records:
        raise LirisError(path, "no loops in the file")
    width = len(records[0][1])
    query, match, pose, lines = [], [], [], []
    for number, fields in records:
        where = f"{path}:{number}"
        if len(fields) != width or width not in (18, 20):
            raise LirisError(where, f"expected 18 (maps + 4x4 pose) or 20 (maps, first scans "
                                    f"+ 4x4 pose) columns like the first line ({width}), got "
                                    f"{len(fields)}")
        values = _numbers(fields, where, "closure")
        q_col, m_col = (3, 2) if width == 20 else (1, 0)
        q = _integer(fields[q_col], where, "query")
        m = _integer(fields[m_col], where, "reference")
        if q == m:
            raise LirisError(where, f"closure joins map {q} to itself")
        T = np.reshape(values[width - 16:], (4, 4))
        # the pose is the reference map's in the query map's frame (liris's convention; see
        # descriptors/mapclosures): keep it as is, later frame as the query
        if q < m:
            q, m, T = m, q, _invert(T)
        query.append(q), match.append(m), pose.append(T)
        lines.append(number)
    return LoopFile(path, "mapclosures", np.array(query, dtype=np.int64),
                    np.array(match, dtype=np.int64), None, np.array(pose).reshape(-1, 4, 4),
                    np.array(lines, dtype=np.int64),
                    rule="MapClosures closures between local maps, each map at its first scan"
                         + (" (scan columns of the file)" if width == 20 else
                            " (--loops-map)"),
                    extra={"map_ids": width == 18})
