"""Issue 41 item 7: a ``--frames`` subset takes its rows from a cached run of a superset.

Only methods whose rows depend on their own scan alone (``per_frame``) share rows;
the rows must be bitwise those of a cold extraction of the subset, a changed scan
must be computed again, and local-map methods (ESM) never share rows.
"""

from __future__ import annotations

import json
import os
import warnings

import numpy as np
import pytest
from conftest import run_cli
from test_protocols import ToyHist

from lidar_iris_eval import extract as extract_module
from lidar_iris_eval.cache import DescriptorCache, scan_identities
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.base import shares_rows
from lidar_iris_eval.errors import LirisWarning
from lidar_iris_eval.extract import extract, extract_many
from lidar_iris_eval.io import open_sequence


class FrameToy(ToyHist):
    """ToyHist declared per-frame (its histogram reads only its own scan)."""

    per_frame = True


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """60 scans of ``tiny-mixed`` at 256 azimuth steps (about 1 s to simulate)."""
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    return simulate_sequence(tmp_path_factory.mktemp("sim") / "seq", "tiny-mixed", frames=60,
                             azimuth_steps=256)


@pytest.fixture
def computed(monkeypatch):
    """Scans computed per descriptor name, counted where extraction computes them."""
    counts: dict[str, int] = {}
    real = extract_module._compute_range

    def counting(seq, descriptors, a, b, tick=None):
        for d in descriptors:
            counts[d.name] = counts.get(d.name, 0) + (b - a)
        return real(seq, descriptors, a, b, tick)

    monkeypatch.setattr(extract_module, "_compute_range", counting)
    return counts


def _bitwise_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_only_scan_by_scan_global_methods_share_rows():
    from lidar_iris_eval.descriptors.mapclosures.descriptor import MapClosures

    for name in ("lidar-iris", "scan-context", "m2dp", "esf"):
        assert shares_rows(get_descriptor(name)), name
    assert not shares_rows(get_descriptor("esm"))  # local maps
    assert not shares_rows(get_descriptor("esm", "single-scan"))  # not declared per-frame
    assert not MapClosures.per_frame
    assert not shares_rows(ToyHist())  # a method that does not say so never shares


@pytest.mark.parametrize("frames", ["7:41", "3:58:3"])
def test_subset_after_full_run_computes_nothing_and_is_bitwise_cold(sim, tmp_path, computed,
                                                                    frames):
    full = open_sequence(sim)
    subset = open_sequence(sim, frames=frames)
    keep = np.arange(60)[slice(*[int(p) for p in frames.split(":")])]
    assert len(subset) == len(keep) < len(full)
    names = ["scan-context", "m2dp"]
    warm = DescriptorCache(tmp_path / "warm")
    extract_many(full, [get_descriptor(n) for n in names], cache=warm, chunk_size=8)
    assert computed == {n: 60 for n in names}
    computed.clear()
    got = extract_many(subset, [get_descriptor(n) for n in names], cache=warm, chunk_size=8)
    assert computed == {}  # every row came from the full run's file
    assert all(db.from_cache and db.reused_rows == len(keep) for db in got)
    cold = extract_many(subset, [get_descriptor(n) for n in names],
                        cache=DescriptorCache(tmp_path / "cold"), chunk_size=8)
    assert computed == {n: len(keep) for n in names}
    for g, c in zip(got, cold, strict=True):
        assert not c.from_cache and c.reused_rows == 0
        assert _bitwise_equal(g.descriptors, c.descriptors)
    # the subset's own file is stored: a third run loads it without the row index
    computed.clear()
    again = extract_many(subset, [get_descriptor(n) for n in names], cache=warm, chunk_size=8)
    assert computed == {} and all(db.from_cache and db.reused_rows == 0 for db in again)
    for g, a in zip(got, again, strict=True):
        assert _bitwise_equal(g.descriptors, a.descriptors)
        np.testing.assert_array_equal(g.extract_s, a.extract_s)


def _metrics(out: str) -> list[dict]:
    """The result rows without timings (the reused rows keep the full run's extract times)."""
    rows = json.loads(out)["results"]
    return [{k: v for k, v in r.items() if "_ms_per_" not in k} for r in rows]


def test_eval_of_a_subset_reuses_and_gives_the_cold_metrics(sim, tmp_path, capsys, computed):
    base = ["eval", sim, "-d", "scan-context,m2dp", "--protocol", "1", "--exclude", "5",
            "--workers", "1", "-q", "--json"]
    code, _, err = run_cli([*base, "--cache-dir", tmp_path / "c", "--out", tmp_path / "r1"],
                           capsys)
    assert code == 0, err
    computed.clear()
    sub = ["--frames", "5:55"]
    code, warm, err = run_cli([*base, *sub, "--cache-dir", tmp_path / "c", "--out",
                               tmp_path / "r2"], capsys)
    assert code == 0, err
    assert computed == {}
    code, cold, err = run_cli([*base, *sub, "--cache-dir", tmp_path / "c2", "--out",
                               tmp_path / "r3"], capsys)
    assert code == 0, err
    assert computed == {"scan-context": 50, "m2dp": 50}
    warm_rows, cold_rows = _metrics(warm), _metrics(cold)
    assert [r["n_queries"] for r in cold_rows] == [r["n_queries"] for r in warm_rows]
    assert all(r["n_positives"] > 0 and r["ap"] is not None for r in cold_rows)
    assert warm_rows == cold_rows
    for name in ("scan-context", "m2dp"):  # every match, distance and pose, byte for byte
        warm_csv = (tmp_path / "r2" / "protocol1" / name / "matches.csv").read_bytes()
        assert warm_csv == (tmp_path / "r3" / "protocol1" / name / "matches.csv").read_bytes()


def test_a_changed_scan_is_computed_again(sim, tmp_path, computed):
    from shutil import copytree

    root = copytree(sim, tmp_path / "seq")
    cache = DescriptorCache(tmp_path / "cache")
    full = extract(open_sequence(root), FrameToy(), cache=cache, chunk_size=4)
    # rewrite scan 10 with other points: same size, new bytes (and a new mtime)
    path = root / "velodyne" / "000010.bin"
    points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    points[:, :2] *= 0.5
    points.tofile(path)
    subset = open_sequence(root, frames="8:20")  # rows 8..19: chunks 8-11, 12-15, 16-19
    computed.clear()
    got = extract(subset, FrameToy(), cache=cache, chunk_size=4)
    assert computed == {"toy": 4}  # only the chunk holding scan 10 (subset row 2)
    assert got.reused_rows == 8 and not got.from_cache
    fresh = FrameToy()
    expect = np.stack([fresh.compute(subset[i]) for i in range(len(subset))])
    assert _bitwise_equal(got.descriptors, expect)
    assert not np.array_equal(got.descriptors[2], full.descriptors[10])  # really new numbers
    np.testing.assert_array_equal(got.descriptors[4:], full.descriptors[12:20])


def test_identity_follows_the_scan_content(sim, tmp_path):
    from shutil import copytree

    from lidar_iris_eval.io.sequence import full_scan_hashing

    root = copytree(sim, tmp_path / "seq")
    seq = open_sequence(root)
    points = frozenset({"points"})
    before = scan_identities(seq, points)
    with full_scan_hashing():
        every_byte = scan_identities(seq, points)
    assert before.shape == (60, 16) and len({bytes(r) for r in before}) == 60
    assert not (every_byte == before).all(axis=1).any()  # the two kinds never mix
    np.testing.assert_array_equal(scan_identities(open_sequence(root, frames="10:20"), points),
                                  before[10:20])
    path = root / "velodyne" / "000003.bin"
    stat = path.stat()
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # the middle of the file: outside the sampled 2 x 4 KiB
    path.write_bytes(bytes(data))
    changed = np.flatnonzero((scan_identities(seq, points) != before).any(axis=1))
    np.testing.assert_array_equal(changed, [3])  # its new mtime gives it a new identity
    # with the old mtime put back only the every-byte identity sees it (the same limit as
    # Sequence.fingerprint, whose --verify-scans is the answer)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    np.testing.assert_array_equal(scan_identities(seq, points), before)
    with full_scan_hashing():
        changed = np.flatnonzero((scan_identities(seq, points) != every_byte).any(axis=1))
    np.testing.assert_array_equal(changed, [3])


def test_a_corrupt_superset_file_is_not_served(sim, tmp_path, computed):
    cache = DescriptorCache(tmp_path / "cache")
    full = extract(open_sequence(sim), FrameToy(), cache=cache)
    data = bytearray(full.cache_path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    full.cache_path.write_bytes(bytes(data))
    computed.clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = extract(open_sequence(sim, frames="0:30"), FrameToy(), cache=cache)
    assert any(issubclass(w.category, LirisWarning) and "corrupt" in str(w.message)
               for w in caught)
    assert computed == {"toy": 30} and got.reused_rows == 0
    assert not full.cache_path.exists()
    assert _bitwise_equal(got.descriptors, full.descriptors[:30])


def test_other_parameters_never_share_rows(sim, tmp_path, computed):
    from test_protocols import ToyParams

    cache = DescriptorCache(tmp_path / "cache")
    extract(open_sequence(sim), FrameToy(), cache=cache)
    computed.clear()
    got = extract(open_sequence(sim, frames="0:30"), FrameToy(ToyParams(bins=8)), cache=cache)
    assert computed == {"toy": 30} and got.reused_rows == 0 and got.descriptors.shape[1] == 8


def test_esm_on_local_maps_does_not_reuse(sim, tmp_path, computed):
    from lidar_iris_eval.descriptors.esm import network

    if not network.WEIGHTS_FILE.is_file():
        pytest.skip("no ESM weights shipped")
    cache = DescriptorCache(tmp_path / "cache")
    short = open_sequence(sim, frames="0:16")
    extract(short, get_descriptor("esm", window=5), cache=cache, chunk_size=8)
    assert computed == {"esm": 16}
    computed.clear()
    got = extract(open_sequence(sim, frames="4:12"), get_descriptor("esm", window=5),
                  cache=cache, chunk_size=8)
    # frame 4's local map holds no frames before 4 here: its row must be computed again
    assert computed == {"esm": 8} and got.reused_rows == 0 and not got.from_cache
    assert not any(p.name.startswith("esm-") and p.suffix == ".rows"
                   for p in (tmp_path / "cache").iterdir())


def test_an_unwritable_row_index_is_a_warning_not_a_failure(sim, tmp_path, computed):
    from lidar_iris_eval.extract import cache_key

    seq = open_sequence(sim, frames="0:20")
    cache = DescriptorCache(tmp_path / "cache")
    key = cache_key(seq, FrameToy())
    folder = cache.rows_dir(key, key.family(frozenset({"points"})))
    folder.parent.mkdir(parents=True)
    folder.write_text("not a folder")  # the index cannot be written there
    with pytest.warns(LirisWarning, match="cannot write the cache row index"):
        db = extract(seq, FrameToy(), cache=cache)
    assert db.cache_path.is_file() and folder.read_text() == "not a folder"
    computed.clear()
    with pytest.warns(LirisWarning, match="cannot write the cache row index"):
        again = extract(open_sequence(sim, frames="5:15"), FrameToy(), cache=cache)
    assert computed == {"toy": 10} and again.reused_rows == 0  # no index: computed, correct
    assert _bitwise_equal(again.descriptors, db.descriptors[5:15])


def test_liris_extract_reports_the_reused_rows(sim, tmp_path, capsys):
    base = ["extract", sim, "-d", "m2dp", "--cache-dir", tmp_path / "c", "--workers", "1",
            "-q", "--json"]
    code, out, err = run_cli(base, capsys)
    assert code == 0, err
    (row,) = json.loads(out)["results"]
    assert row["scans"] == 60 and row["reused_rows"] == 0 and not row["from_cache"]
    code, out, err = run_cli([*base, "--frames", "20:45"], capsys)
    assert code == 0, err
    (row,) = json.loads(out)["results"]
    assert row["scans"] == 25 and row["reused_rows"] == 25 and row["from_cache"]
