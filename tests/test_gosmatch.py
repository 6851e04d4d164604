"""GOSMatch descriptors, objects from labels, and the authors' object layout.

Golden values come from a deliberately slow loop written here from the
descriptions of the authors' MATLAB (1-based indices, one pair at a time, a
bin found by walking the bin edges), not from the implementation.
"""

from __future__ import annotations

import math
import tarfile
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.gosmatch import (
    ClusterSettings,
    euclidean_clusters,
    graph_descriptor,
    objects_from_labels,
    vertex_descriptors,
)
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.objects import ObjectScan, is_objects_layout, open_objects, read_centroids

SHARED = Path(__file__).resolve().parents[2] / "shared"
OBJECTS_TAR = SHARED / "data" / "gosmatch" / "kitti00-objects.tar.xz"
KITTI = SHARED / "data" / "kitti"
#: frames of the authors' KITTI 00 objects: all classes, no trunk, no trunk and no pole
GOLDEN_FRAMES = (0, 246, 2814)


# ----------------------------------------------------------------- slow reference


def _bin_of(d: float, bins: int = 61, width: float = 1.0) -> int:
    """1-based bin by walking the edges: [k-1, k) for k = 1..bins, the rest in the last."""
    for k in range(1, bins + 1):
        if (k - 1) * width <= d < k * width:
            return k
        if d >= bins * width:
            return bins
    return bins  # [bins-1, bins) handled above; unreachable for d >= 0


def slow_graph(xyz, counts, ordered=True, bins=61):
    """6 x bins counts, blocks (1,1) (1,2) (1,3) (2,2) (2,3) (3,3), 1-based ranges."""
    ends = [sum(counts[: c + 1]) for c in range(3)]
    starts = [ends[c] - counts[c] + 1 for c in range(3)]
    out = []
    for a in range(3):
        for b in range(a, 3):
            hist = [0] * bins
            for i in range(starts[a], ends[a] + 1):
                for j in range(starts[b], ends[b] + 1):
                    if a == b and not ordered and j <= i:
                        continue
                    hist[_bin_of(math.dist(xyz[i - 1], xyz[j - 1]), bins) - 1] += 1
            out.extend(hist)
    return np.array(out, dtype=float)


def slow_vertex(xyz, counts, bug=True, bins=61):
    """K x 3*bins; neighbour j (1-based) filed under its class, or the code's offset."""
    k = len(xyz)
    ends = [sum(counts[: c + 1]) for c in range(3)]
    out = np.zeros((k, 3 * bins))
    for i in range(1, k + 1):
        for j in range(1, k + 1):
            if i == j:
                continue
            if bug:  # count classes until one with (j - 1) <= cumulative count
                block = 0
                for c in range(3):
                    if j - 1 <= ends[c]:
                        break
                    block += 1
            else:
                block = next(c for c in range(3) if j <= ends[c])
            b = _bin_of(math.dist(xyz[i - 1], xyz[j - 1]), bins)
            out[i - 1, block * bins + b - 1] += 1
    return out


# ----------------------------------------------------------------- hand-computed


def _square():
    """Vehicles V1 (0,0,0), V2 (3,0,0); trunk T (0,4,0); pole P (3,4,0): a 3-4-5 rectangle."""
    xyz = np.array([[0, 0, 0], [3, 0, 0], [0, 4, 0], [3, 4, 0]], dtype=float)
    return xyz, np.array([0, 0, 1, 2], dtype=np.int8)


def _expected_graph(entries):
    out = np.zeros((6, 61))
    for block, b, n in entries:
        out[block, b] = n
    return out.ravel()


def test_graph_hand_computed_reference_and_paper():
    xyz, cls = _square()
    ref = graph_descriptor(xyz, cls, pairs="ordered")
    # vv: two self-pairs (0 m) + V1V2 both ways (3 m); vt: 4, 5; vp: 5, 4; tt, pp: self;
    # tp: 3
    want = _expected_graph([(0, 0, 2), (0, 3, 2), (1, 4, 1), (1, 5, 1), (2, 4, 1), (2, 5, 1),
                            (3, 0, 1), (4, 3, 1), (5, 0, 1)])
    np.testing.assert_array_equal(ref, want)
    assert ref.sum() == 4 + 2 + 2 + 1 + 1 + 1
    paper = graph_descriptor(xyz, cls, pairs="unordered")
    want = _expected_graph([(0, 3, 1), (1, 4, 1), (1, 5, 1), (2, 4, 1), (2, 5, 1), (4, 3, 1)])
    np.testing.assert_array_equal(paper, want)
    assert paper.sum() == 6  # C(4, 2) unordered pairs


def test_vertex_hand_computed_offset_bug():
    xyz, cls = _square()
    exact = vertex_descriptors(xyz, cls, offset="exact")
    ref = vertex_descriptors(xyz, cls, offset="cumcount-bug")
    assert exact.shape == ref.shape == (4, 183)
    # V1: V2 vehicle 3 m, T trunk 4 m, P pole 5 m
    assert set(np.flatnonzero(exact[0])) == {0 * 61 + 3, 1 * 61 + 4, 2 * 61 + 5}
    # counts (2, 1, 1), cumulative (2, 3, 4): T (j = 3) has j-1 = 2 <= 2 -> vehicle block,
    # P (j = 4) has 3 <= 3 -> trunk block
    assert set(np.flatnonzero(ref[0])) == {0 * 61 + 3, 0 * 61 + 4, 1 * 61 + 5}
    # T: V1 4 m and V2 5 m (vehicles either way), P 3 m (pole, or trunk under the bug)
    assert set(np.flatnonzero(exact[2])) == {0 * 61 + 4, 0 * 61 + 5, 2 * 61 + 3}
    assert set(np.flatnonzero(ref[2])) == {0 * 61 + 4, 0 * 61 + 5, 1 * 61 + 3}
    # every vertex sees the other three, once each
    np.testing.assert_array_equal(ref.sum(axis=1), [3, 3, 3, 3])


def test_far_pairs_share_the_last_bin():
    # 59.999 m -> bin 59; 60 m and 75 m -> bin 60 (the last of 61)
    xyz = np.array([[0, 0, 0], [59.999, 0, 0], [0, 60.0, 0], [0, 0, 75.0]])
    cls = np.zeros(4, dtype=np.int8)
    g = graph_descriptor(xyz, cls, pairs="unordered").reshape(6, 61)
    d = [59.999, 60.0, 75.0, math.dist(xyz[1], xyz[2]), math.dist(xyz[1], xyz[3]),
         math.dist(xyz[2], xyz[3])]
    assert g[0, 59] == 1 and g[0, 60] == 5 and g.sum() == len(d)


def test_empty_and_unsorted_objects():
    empty = np.zeros((0, 3))
    assert graph_descriptor(empty, np.zeros(0, np.int8)).shape == (366,)
    assert vertex_descriptors(empty, np.zeros(0, np.int8)).shape == (0, 183)
    with pytest.raises(ValueError):
        graph_descriptor(np.zeros((2, 3)), np.array([1, 0], np.int8))


@pytest.mark.parametrize("seed", range(5))
def test_random_scenes_match_the_slow_loop(seed):
    rng = np.random.default_rng(seed)
    counts = [int(c) for c in rng.integers(0, 6, size=3)]
    counts[0] += 1
    xyz = rng.uniform(-40, 40, size=(sum(counts), 3))
    cls = np.repeat(np.arange(3, dtype=np.int8), counts)
    np.testing.assert_array_equal(graph_descriptor(xyz, cls, "ordered"), slow_graph(xyz, counts))
    np.testing.assert_array_equal(graph_descriptor(xyz, cls, "unordered"),
                                  slow_graph(xyz, counts, ordered=False))
    np.testing.assert_array_equal(vertex_descriptors(xyz, cls, "cumcount-bug"),
                                  slow_vertex(xyz, counts))
    np.testing.assert_array_equal(vertex_descriptors(xyz, cls, "exact"),
                                  slow_vertex(xyz, counts, bug=False))


# ----------------------------------------------------------------- authors' objects


@pytest.fixture(scope="module")
def authors_objects(tmp_path_factory) -> Path:
    """The authors' KITTI 00 objects unpacked into a temporary folder, or skip."""
    if not OBJECTS_TAR.is_file():
        pytest.skip("../shared/data/gosmatch is not available")
    root = tmp_path_factory.mktemp("gosmatch")
    with tarfile.open(OBJECTS_TAR, "r:xz") as tar:
        tar.extractall(root, filter="data")
    return root / "00"


def test_golden_frames_of_the_authors_data(authors_objects):
    method = get_descriptor("gosmatch", preset="reference")
    paper = get_descriptor("gosmatch", preset="paper")
    bow = np.loadtxt(authors_objects / "bow.txt", delimiter=",", dtype=int)
    for frame in GOLDEN_FRAMES:
        counts = [int(c) for c in bow[frame]]
        xyz = np.loadtxt(authors_objects / "centroids" / f"{frame:06d}.txt", ndmin=2)
        scan = read_centroids(authors_objects / "centroids" / f"{frame:06d}.txt", bow[frame])
        feats = method.compute(scan)
        assert feats["graph"].shape == (366,) and feats["vertex"].shape == (len(xyz), 183)
        np.testing.assert_array_equal(feats["graph"], slow_graph(xyz, counts))
        np.testing.assert_array_equal(feats["vertex"], slow_vertex(xyz, counts))
        # reference: n^2 per same-class block, n_a n_b across classes
        n = np.array(counts)
        assert feats["graph"].sum() == (n**2).sum() + n[0] * n[1] + n[0] * n[2] + n[1] * n[2]
        pfeats = paper.compute(scan)
        np.testing.assert_array_equal(pfeats["graph"], slow_graph(xyz, counts, ordered=False))
        np.testing.assert_array_equal(pfeats["vertex"], slow_vertex(xyz, counts, bug=False))
        assert pfeats["graph"].sum() == len(xyz) * (len(xyz) - 1) // 2


def test_open_objects_layout(authors_objects):
    if not KITTI.is_dir():
        pytest.skip("../shared/data/kitti is not available")
    assert is_objects_layout(authors_objects)
    seq = open_objects(authors_objects, poses=KITTI / "poses" / "00.txt",
                       calib=KITTI / "calib" / "00.txt")
    assert len(seq) == 4541 and seq.poses.shape == (4541, 4, 4)
    scan = seq.scan(246)
    assert isinstance(scan, ObjectScan)
    np.testing.assert_array_equal(np.bincount(scan.classes, minlength=3), [8, 0, 1])
    with pytest.raises(LirisError, match="no points"):
        seq[0]
    with pytest.raises(LirisError, match="calibration"):
        open_objects(authors_objects, poses=KITTI / "poses" / "00.txt")


def test_object_files_are_checked(tmp_path):
    root = tmp_path / "seq"
    (root / "centroids").mkdir(parents=True)
    (root / "bow.txt").write_text("1,0,1\n2,0,0\n")
    (root / "centroids" / "000000.txt").write_text("1 2 3\n4 5 6\n")
    (root / "centroids" / "000001.txt").write_text("1 2 3\n")
    scan = read_centroids(root / "centroids" / "000000.txt", np.array([1, 0, 1]))
    np.testing.assert_array_equal(scan.classes, [0, 2])
    with pytest.raises(LirisError, match="1 objects but bow.txt says 2"):
        read_centroids(root / "centroids" / "000001.txt", np.array([2, 0, 0]))
    (root / "bow.txt").write_text("1,0\n")
    with pytest.raises(LirisError, match="expected 3 non-negative counts"):
        open_objects(root, poses=root / "none.txt")


# ----------------------------------------------------------------- objects from labels


def _blob(rng, centre, n, spread=0.3):
    return np.asarray(centre) + rng.normal(scale=spread, size=(n, 3)) * [1, 1, 0.3]


def test_objects_from_labels_classes_and_clusters():
    rng = np.random.default_rng(0)
    parts = [  # (points, semantic id, instance)
        (_blob(rng, (5, 0, 0), 200), 10, 1),      # car
        (_blob(rng, (9, 0, 0), 120), 18, 0),      # truck, 4 m away: separate vehicle
        (_blob(rng, (0, 8, 0), 300), 252, 0),     # moving car: never an object
        (_blob(rng, (0, -6, 0), 60, 0.1), 71, 0),  # trunk
        (_blob(rng, (3, -6, 0), 40, 0.05), 80, 0),  # pole
        (_blob(rng, (-7, -6, 0), 30, 0.05), 81, 0),  # traffic sign
        (_blob(rng, (20, 20, 0), 4, 0.05), 80, 0),  # too small a pole
        (_blob(rng, (55, 0, 0), 100), 10, 2),     # car beyond 50 m
        (rng.uniform(-30, 30, size=(500, 3)), 40, 0),  # road
    ]
    points = np.concatenate([p for p, _, _ in parts]).astype(np.float32)
    labels = np.concatenate([np.full(len(p), sid | (inst << 16), np.uint32)
                             for p, sid, inst in parts])
    settings = ClusterSettings(tolerance=0.5, min_points=10, max_range=50.0)
    centroids, classes = objects_from_labels(points, labels, settings)
    np.testing.assert_array_equal(classes, [0, 0, 1, 2])
    # largest cluster first within a class: the 200-point car, then the truck
    np.testing.assert_allclose(centroids[0], parts[0][0].mean(0), atol=1e-5)
    np.testing.assert_allclose(centroids[1], parts[1][0].mean(0), atol=1e-5)
    np.testing.assert_allclose(centroids[3], parts[4][0].mean(0), atol=1e-5)
    with_signs = ClusterSettings(tolerance=0.5, min_points=10, traffic_signs=True)
    _, classes = objects_from_labels(points, labels, with_signs)
    np.testing.assert_array_equal(classes, [0, 0, 1, 2, 2])
    # a tolerance larger than the 4 m gap merges the car and the truck
    _, classes = objects_from_labels(points, labels, ClusterSettings(tolerance=5.0, min_points=10))
    assert np.count_nonzero(classes == 0) == 1


def test_euclidean_clusters_single_linkage():
    # a chain of points 0.4 m apart is one cluster at 0.5 m, separate points at 0.3 m
    chain = np.array([[0.4 * i, 0, 0] for i in range(10)])
    assert [len(c) for c in euclidean_clusters(chain, 0.5, 1)] == [10]
    assert len(euclidean_clusters(chain, 0.3, 1)) == 10
    assert euclidean_clusters(chain, 0.3, 2) == []


def test_scan_without_labels_is_an_error():
    method = get_descriptor("gosmatch")

    class Plain:
        points = np.zeros((10, 3), np.float32)
        labels = None

    with pytest.raises(LirisError, match="labels"):
        method.compute(Plain())
