"""ESM as a two-stage method: votes, PROSAC verification, the shipped network, real KITTI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm import network
from lidar_iris_eval.descriptors.features import RaggedFeatures
from lidar_iris_eval.matching.geometry import rotation_error_deg, translation_error_m, yaw_pose

DATA = Path(__file__).with_name("data") / "esm_golden.npz"


def _need_weights():
    if not (network.WEIGHTS_FILE.is_file() and DATA.is_file()):
        pytest.skip("no ESM weights or golden file")


def _frame(emb, cents, q=None):
    q = np.full(len(emb), 0.9) if q is None else q
    return {"embedding": np.asarray(emb, np.float32), "quality": np.asarray(q, np.float64),
            "centroids": np.asarray(cents, np.float64)}


def _toy(rng, T):
    """Frame 0: 8 segments; frame 1: unrelated; frame 2: frame 0 seen from pose T."""
    emb0 = rng.normal(size=(8, 16))
    c0 = rng.uniform(-20, 20, (8, 3))
    c2 = c0 @ T[:3, :3].T + T[:3, 3]
    f1 = _frame(rng.normal(size=(6, 16)), rng.uniform(-20, 20, (6, 3)))
    return RaggedFeatures.from_list([_frame(emb0, c0), f1, _frame(emb0 + 0.01, c2)])


def test_votes_rank_the_frame_with_the_same_segments_first():
    T = yaw_pose(170.0, (3.0, -1.0, 0.2))
    feats = _toy(np.random.default_rng(0), T)
    # knn 1: each of the 8 query segments votes for its twin only, weight 0.9 * 0.9
    esm = get_descriptor("esm", "single-scan", knn=1)
    idx, dist = esm.retrieve(esm.prepare(feats), 2, 2, 5)
    assert idx.tolist() == [0] and np.isclose(dist[0], 1 / (1 + 8 * 0.81))
    # knn 25 > 14 allowed segments: every query segment votes for all of them
    esm = get_descriptor("esm", "single-scan")
    idx, dist = esm.retrieve(esm.prepare(feats), 2, 2, 5)
    assert idx.tolist() == [0, 1]
    assert np.allclose(dist, [1 / (1 + 64 * 0.81), 1 / (1 + 48 * 0.81)])


def test_prosac_recovers_the_pose_and_rejects_unrelated_frames():
    esm = get_descriptor("esm", "single-scan")
    T = yaw_pose(170.0, (3.0, -1.0, 0.2))
    db = esm.prepare(_toy(np.random.default_rng(1), T))
    esm.retrieve(db, 2, 2, 5)
    v = esm.verify(db, 2, np.array([0, 1]))
    # pose maps the candidate's (frame 0) points into the query's (frame 2)
    assert v.inliers[0] == 8
    assert np.allclose(v.pose[0], T, atol=1e-6)
    assert np.isclose(v.score[0], 1 / 9, atol=1e-3)
    assert not np.isfinite(v.score[1])


def test_parameters_are_checked():
    from lidar_iris_eval.errors import LirisError

    with pytest.raises(LirisError):
        get_descriptor("esm", ground="plane")
    with pytest.raises(LirisError):
        get_descriptor("esm", min_inliers=2)


@pytest.mark.parametrize("weights, golden", [
    (network.WEIGHTS_FILE, DATA),
    (network.LOCALMAP_WEIGHTS_FILE, DATA.with_name("esm_localmap_golden.npz")),
    (network.WEIGHTS_FILE.with_name("esm_localmap_real_weights.npz"),
     DATA.with_name("esm_localmap_real_golden.npz")),
    (network.WEIGHTS_FILE.with_name("esm_localmap_simreal_weights.npz"),
     DATA.with_name("esm_localmap_simreal_golden.npz")),
    (network.WEIGHTS_FILE.with_name("esm_forest_weights.npz"),
     DATA.with_name("esm_forest_golden.npz")),
])
def test_golden_embeddings_of_the_shipped_weights(weights, golden):
    if not weights.is_file():
        pytest.skip(f"no {weights.name}")
    assert golden.is_file(), f"{weights.name} has no golden file: write tests/data/{golden.name}"
    gold = np.load(golden)
    assert str(gold["sha256"]) == network.sha256_of(weights), \
        f"weights changed: regenerate tests/data/{golden.name}"
    w, arch = network.load_weights(weights)
    emb = network.embed(w, arch, gold["points"])
    assert np.allclose(emb, gold["embedding"], atol=1e-5)
    q = network.quality(w, emb)
    assert np.allclose(q, gold["quality"], atol=1e-5)
    assert np.all((q >= 0) & (q <= 1))


def test_numpy_forward_equals_torch_forward():
    _need_weights()
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.esm.torch_net import ESMNet

    gold = np.load(DATA)
    w, arch = network.load_weights()
    net = ESMNet(arch)
    state = net.state_dict()
    for key in state:
        state[key] = _torch_value(key, w, state[key], torch)
    net.load_state_dict(state)
    net.eval()
    pts = gold["points"]
    with torch.no_grad():
        ref = net(torch.from_numpy(pts), network.neighbour_index(pts, arch)).numpy()
    assert np.abs(network.embed(w, arch, pts) - ref).max() < 1e-4


def _torch_value(key, w, like, torch):
    """The numpy weight behind a torch state-dict entry (inverse of ESMNet.export)."""
    parts = key.split(".")
    if parts[0] == "xconvs":
        i = parts[1]
        if parts[2] == "p":
            name = f"x{i}." + parts[3].replace("_", ".")
        else:
            bn = {"weight": "gamma", "bias": "beta", "running_mean": "mean", "running_var": "var"}
            if parts[3] not in bn:
                return like
            name = f"x{i}.bn.{bn[parts[3]]}"
        return torch.from_numpy(w[name].copy())
    if parts[0] == "fcs":
        arr = w[f"fc{parts[1]}.{'w' if parts[2] == 'weight' else 'b'}"]
        return torch.from_numpy((arr.T if parts[2] == "weight" else arr).copy())
    if parts[0] == "quality":
        arr = w[f"q.{'w' if parts[1] == 'weight' else 'b'}"]
        return torch.from_numpy((arr.T if parts[1] == "weight" else arr).copy())
    return like


def test_real_kitti_bar(kitti_dir):
    """95 vs 94 accepted with < 0.5 m and < 3 deg; 198 vs 94 worse than both true pairs."""
    from lidar_iris_eval.io.poses import read_calib, read_kitti_poses

    _need_weights()
    root = kitti_dir / "samples" / "00"
    files = [root / "velodyne" / f"{i:06d}.bin" for i in (94, 95, 198, 199)]
    if not all(f.is_file() for f in files):
        pytest.skip("KITTI sample scans missing")
    esm = get_descriptor("esm", "single-scan")
    feats = [esm.compute(np.fromfile(f, np.float32).reshape(-1, 4)[:, :3]) for f in files]
    db = esm.prepare(RaggedFeatures.from_list(feats))
    tr = read_calib(root / "calib.txt")
    cam = read_kitti_poses(root / "poses.txt")
    lidar = np.linalg.inv(tr) @ cam @ tr
    v95 = esm.verify(db, 1, np.array([0]))
    assert np.isfinite(v95.score[0])
    gt = np.linalg.inv(lidar[1]) @ lidar[0]
    assert translation_error_m(v95.pose[0], gt) < 0.5
    assert rotation_error_deg(v95.pose[0], gt) < 3.0
    v199 = esm.verify(db, 3, np.array([2]))
    v198 = esm.verify(db, 2, np.array([0]))
    assert v198.score[0] > max(v95.score[0], v199.score[0])
