"""Scans with labels, declared inputs, variable-size features through extract and the cache."""

from __future__ import annotations

import importlib
import sys
import textwrap
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli, write_kitti_sequence
from test_protocols import ToyHist, line_poses, random_scan

from lidar_iris_eval import extract as extract_module
from lidar_iris_eval.cache import DescriptorCache
from lidar_iris_eval.descriptors import register_descriptor
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.features import RaggedFeatures
from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.extract import cache_key, extract
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.folder import open_folder
from lidar_iris_eval.io.scans import Scan


def labelled_sequence(root: Path, n: int = 8, seed: int = 0, labels: bool = True) -> Path:
    """A KITTI-layout sequence: labels say ``class = 50 + i % 3`` (SemanticKITTI building,
    fence, other-structure), instance = point index."""
    rng = np.random.default_rng(seed)
    scans = [random_scan(rng, n_points=50 + 7 * i) for i in range(n)]
    write_kitti_sequence(root, scans, line_poses(np.arange(n) * 10.0))
    if labels:
        (root / "labels").mkdir()
        for i, s in enumerate(scans):
            lab = (50 + np.arange(len(s)) % 3) | (np.arange(len(s)) << 16)
            lab.astype("<u4").tofile(root / "labels" / f"{i:06d}.label")
    return root


@dataclass(frozen=True)
class ClassParams:
    classes: tuple = (50, 51, 52)


class ClassCentroids(Descriptor):
    """Per class present: its centroid (a variable number of rows per scan), plus a fixed
    3-bin class histogram."""

    name = "class-centroids"
    params_type = ClassParams
    inputs = frozenset({"points", "labels"})
    #: sizes of the scans computed (every scan of labelled_sequence has its own size), so
    #: counts do not depend on untimed warm-up calls of the extractor
    seen: set = set()
    fail_at_size: int | None = None

    def compute(self, scan):
        if self.fail_at_size is not None and len(scan.points) == self.fail_at_size:
            raise KeyboardInterrupt  # simulated interruption mid-run
        ClassCentroids.seen.add(len(scan.points))
        sem = scan.labels & 0xFFFF
        # keep a varying number of points per scan so K varies: drop class 52 on odd sizes
        present = [c for c in self.params.classes if np.any(sem == c)]
        if len(scan.points) % 2:
            present = present[:2]
        cents = np.array([scan.points[sem == c].mean(axis=0) for c in present], np.float64)
        hist = np.array([np.mean(sem == c) for c in self.params.classes])
        return {"centroids": cents.reshape(-1, 3), "classes": np.array(present, np.int16),
                "hist": hist}


# ----------------------------------------------------------------- labels


def test_kitti_reader_reads_semantickitti_labels(tmp_path):
    seq = open_sequence(labelled_sequence(tmp_path / "s"))
    assert seq.has_labels and "labels" in seq.provides
    scan = seq.scan(3)
    assert scan.labels.dtype == np.uint32 and len(scan.labels) == len(scan.points) == 71
    np.testing.assert_array_equal(scan.labels & 0xFFFF, 50 + np.arange(71) % 3)
    np.testing.assert_array_equal(scan.labels >> 16, np.arange(71))
    np.testing.assert_array_equal(seq[3], scan.points)  # bare points as before


def test_labels_follow_dropped_points(tmp_path):
    root = labelled_sequence(tmp_path / "s", n=2)
    raw = np.fromfile(root / "velodyne" / "000001.bin", dtype=np.float32).reshape(-1, 4)
    raw[[0, 5], 0] = np.nan
    raw.tofile(root / "velodyne" / "000001.bin")
    with pytest.warns(LirisWarning, match="dropped 2 of 57"):
        scan = open_sequence(root).scan(1)
    assert len(scan.labels) == len(scan.points) == 55
    # the surviving points keep their own labels (instance = original index)
    assert (scan.labels >> 16).tolist() == [i for i in range(57) if i not in (0, 5)]


def test_label_count_mismatch_and_missing_file_are_clear_errors(tmp_path):
    root = labelled_sequence(tmp_path / "s", n=3)
    np.zeros(5, "<u4").tofile(root / "labels" / "000002.label")
    with pytest.raises(LirisError, match=r"000002\.label: 5 labels but 64 points"):
        open_sequence(root).scan(2)
    (root / "labels" / "000001.label").unlink()
    with pytest.raises(LirisError, match=r"000001\.label: label file missing \(1 of 3"):
        open_sequence(root)


def test_folder_reader_reads_labels_folder(tmp_path):
    rng = np.random.default_rng(1)
    folder = tmp_path / "scans"
    (folder / "labels").mkdir(parents=True)
    for i in range(3):
        pts = random_scan(rng, 30)
        np.save(folder / f"{i:06d}.npy", pts)
        np.full(30, (40, 44, 48)[i], "<u4").tofile(folder / "labels" / f"{i:06d}.label")
    np.savetxt(folder / "poses.txt", line_poses(np.arange(3.0))[:, :3, :4].reshape(3, 12))
    seq = open_folder(folder, lidar_frame=True)
    assert seq.has_labels
    assert set(seq.scan(2).labels.tolist()) == {48}
    (folder / "labels").rename(tmp_path / "elsewhere")
    assert not open_folder(folder, lidar_frame=True).has_labels


def test_global_descriptors_get_bare_points(tmp_path):
    seq = open_sequence(labelled_sequence(tmp_path / "s"))
    toy = ToyHist()
    scan = seq.scan(4)
    np.testing.assert_array_equal(toy.describe(scan), toy.compute(scan.points))
    assert not ToyHist.wants_scan() and ClassCentroids.wants_scan()


def test_missing_labels_name_the_folder(tmp_path):
    seq = open_sequence(labelled_sequence(tmp_path / "s", labels=False))
    assert not seq.has_labels
    with pytest.raises(LirisError) as err:
        extract(seq, ClassCentroids())
    text = str(err.value)
    assert str(tmp_path / "s" / "labels") in text
    assert "class-centroids needs per-point labels" in text
    # a scan handed over without labels is refused too
    with pytest.raises(LirisError, match="needs per-point labels"):
        ClassCentroids().describe(Scan(np.zeros((3, 3), np.float32), None))


def test_cli_without_labels_is_one_line_exit_2(tmp_path, capsys):
    root = labelled_sequence(tmp_path / "s", n=40, labels=False)
    register_descriptor("class-centroids", "test_scan_inputs:ClassCentroids")
    code, out, err = run_cli(["eval", str(root), "--protocol", "1", "--descriptor",
                              "class-centroids", "--exclude", "5", "--out",
                              str(tmp_path / "run"), "--cache-dir", str(tmp_path / "c"),
                              "--quiet"], capsys)
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "labels" in lines[0] and str(root / "labels") in lines[0]
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------- variable-size features


def expected_features(seq) -> list[dict]:
    d = ClassCentroids()
    return [d.compute(seq.scan(i)) for i in range(len(seq))]


def test_ragged_features_round_trip_through_extract_and_cache(tmp_path):
    seq = open_sequence(labelled_sequence(tmp_path / "s", n=9))
    want = expected_features(seq)
    counts = [len(w["centroids"]) for w in want]
    assert len(set(counts)) > 1  # the point of the test: K varies
    cache = DescriptorCache(tmp_path / "cache")
    ClassCentroids.seen = set()
    db = extract(seq, ClassCentroids(), cache=cache, chunk_size=2)
    assert len(ClassCentroids.seen) == 9 and isinstance(db.descriptors, RaggedFeatures)
    ClassCentroids.seen = set()
    again = extract(seq, ClassCentroids(), cache=cache)
    assert ClassCentroids.seen == set() and again.from_cache
    for feats in (db.descriptors, again.descriptors):
        assert len(feats) == 9
        assert feats.counts("centroids").tolist() == counts
        for i, w in enumerate(want):
            for k in w:
                np.testing.assert_array_equal(feats[i][k], w[k])
                assert feats[i][k].dtype == w[k].dtype
        np.testing.assert_array_equal(feats.stacked("hist"), np.stack([w["hist"] for w in want]))
        with pytest.raises(ValueError, match="varies in size"):
            feats.stacked("centroids")
    sub = db.descriptors[2:5]
    assert len(sub) == 3
    np.testing.assert_array_equal(sub[1]["centroids"], want[3]["centroids"])


def test_ragged_extraction_resumes_after_interruption(tmp_path):
    seq = open_sequence(labelled_sequence(tmp_path / "s", n=10))
    cache = DescriptorCache(tmp_path / "cache")
    interrupted = ClassCentroids()
    interrupted.fail_at_size = len(seq[7])  # chunks [0,3) and [3,6) are stored, [6,9) is not
    with pytest.raises(KeyboardInterrupt):
        extract(seq, interrupted, cache=cache, chunk_size=3)
    key = cache_key(seq, ClassCentroids())
    assert len(list(cache.partial_dir(key).glob("chunk-*.npz"))) == 2
    ClassCentroids.seen = set()
    with warnings.catch_warnings():
        warnings.simplefilter("error", LirisWarning)
        db = extract(seq, ClassCentroids(), cache=cache, chunk_size=3)
    assert ClassCentroids.seen == {len(seq[i]) for i in range(6, 10)}  # only scans 6..9
    want = expected_features(seq)
    for i in range(10):
        np.testing.assert_array_equal(db.descriptors[i]["centroids"], want[i]["centroids"])


def test_inconsistent_feature_sets_are_reported():
    with pytest.raises(ValueError, match="feature 'a' of scan 1 is float32"):
        RaggedFeatures.from_list([{"a": np.zeros((2, 3))}, {"a": np.zeros((1, 3), np.float32)}])
    with pytest.raises(ValueError, match="trailing shape"):
        RaggedFeatures.from_list([{"a": np.zeros((2, 3))}, {"a": np.zeros((2, 4))}])
    with pytest.raises(ValueError, match="scalar"):
        RaggedFeatures.from_list([{"a": np.float64(1.0)}])
    empty_ok = RaggedFeatures.from_list([{"a": np.zeros((0, 3))}, {"a": np.ones((2, 3))}])
    assert empty_ok.counts("a").tolist() == [0, 2] and empty_ok[0]["a"].shape == (0, 3)


# ----------------------------------------------------------------- cache key covers helpers


PLUGIN_INIT = "from .descriptor import Scaled  # noqa: F401\n"
PLUGIN_DESCRIPTOR = textwrap.dedent("""
    from dataclasses import dataclass
    import numpy as np
    from lidar_iris_eval.descriptors.base import Descriptor
    from . import kernels

    @dataclass(frozen=True)
    class P:
        pass

    class Scaled(Descriptor):
        name = "scaled"
        params_type = P
        seen = set()  # sizes of the scans computed

        def compute(self, points):
            Scaled.seen.add(len(points))
            return kernels.describe(points)

        def distance(self, a, b):
            return float(np.abs(a - b).sum()), float("nan")
""")


def test_editing_a_helper_module_of_a_method_package_changes_the_key(tmp_path, monkeypatch):
    pkg = tmp_path / "plugins" / "scaled_method"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(PLUGIN_INIT)
    (pkg / "descriptor.py").write_text(PLUGIN_DESCRIPTOR)
    (pkg / "kernels.py").write_text("def describe(points):\n    return points.mean(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path / "plugins"))
    register_descriptor("scaled", "scaled_method:Scaled")
    from lidar_iris_eval.descriptors import get_descriptor

    seq = open_sequence(labelled_sequence(tmp_path / "s", n=4))
    cache = tmp_path / "cache"
    desc = get_descriptor("scaled")
    cls = type(desc)
    extract_module._source_hash.cache_clear()
    before = cache_key(seq, desc).digest()
    extract(seq, desc, cache=cache)
    assert len(cls.seen) == 4
    cls.seen = set()
    assert extract(seq, desc, cache=cache).from_cache and cls.seen == set()

    # edit only the helper module (not the descriptor's own file)
    (pkg / "kernels.py").write_text("def describe(points):\n    return 2 * points.mean(0)\n")
    extract_module._source_hash.cache_clear()  # a new process would hash afresh
    after = cache_key(seq, desc).digest()
    assert after != before
    importlib.reload(sys.modules["scaled_method.kernels"])  # what a new process would run
    db = extract(seq, desc, cache=cache)
    assert not db.from_cache and len(cls.seen) == 4  # rebuilt, not served stale
    np.testing.assert_allclose(db.descriptors[0], 2 * seq[0].mean(0), rtol=1e-6)
    for name in [m for m in sys.modules if m.startswith("scaled_method")]:
        monkeypatch.delitem(sys.modules, name)


def test_ragged_features_from_a_process_pool_equal_one_process(tmp_path):
    seq = open_sequence(labelled_sequence(tmp_path / "s", n=7))
    one = extract(seq, ClassCentroids(), cache=None).descriptors
    two = extract(seq, ClassCentroids(), cache=tmp_path / "cache", workers=2,
                  chunk_size=2).descriptors
    for key in one.keys:
        np.testing.assert_array_equal(one.offsets[key], two.offsets[key])
        np.testing.assert_array_equal(one.values[key], two.values[key])
