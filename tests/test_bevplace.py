"""BEVPlace++: BEV image, NumPy vs PyTorch network, checkpoint, CLI."""

from __future__ import annotations

import hashlib
import json
import math
import pickle

import numpy as np
import pytest
from conftest import KITTI, assert_one_line_error, run_cli
from test_overlap_transformer import hand_checkpoint  # a torch.save-style zip, torch-free

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.bevplace import bev, network
from lidar_iris_eval.descriptors.learned import weights_digest
from lidar_iris_eval.errors import LirisError

SAMPLES = KITTI / "samples" / "00" / "velodyne"


def _kitti_scans() -> list[np.ndarray]:
    files = sorted(SAMPLES.glob("*.bin")) if SAMPLES.is_dir() else []
    return [np.fromfile(f, np.float32).reshape(-1, 4)[:, :3] for f in files]


def _real_scans() -> list[np.ndarray]:
    scans = _kitti_scans()
    if not scans:
        pytest.skip(f"no KITTI samples in {SAMPLES}")
    return scans


# ------------------------------------------------------------------ BEV image


def test_bev_puts_known_points_at_known_pixels():
    # n = floor(40 / 0.4) = 100; row = 100 - floor(x / 0.4), column = 100 - floor(y / 0.4)
    pts = [(0.12, 0.10, 0.10), (0.17, 0.12, 0.15),  # one voxel -> one mean -> (100, 100)
           (-0.1, -0.1, 0.1),                        # (101, 101)
           (39.9, -39.9, 0.5)]                       # (1, 200): the far corner
    pts += [(5.1, 5.1, 0.05 + 0.4 * k) for k in range(12)]   # 12 voxels: (88, 88), capped 10
    pts += [(10.1, -5.1, 0.05 + 0.4 * k) for k in range(3)]  # (75, 113), 3 voxels
    pts += [(40.0, 0.0, 1.0), (0.0, -40.0, 1.0), (1.0, 1.0, 45.0), (-45.0, 3.0, 1.0)]  # cropped
    img = bev.bev_image(np.array(pts, dtype=np.float32))
    assert bev.image_size() == 201 and img.shape == (201, 201) and img.dtype == np.uint8
    # density: count * 10 / (max count * 10) * 255, rounded as OpenCV: 25.5 -> 26, 76.5 -> 76
    expected = {(100, 100): 26, (101, 101): 26, (1, 200): 26, (88, 88): 255, (75, 113): 76}
    for (r, c), value in expected.items():
        assert img[r, c] == value, (r, c)
    assert np.count_nonzero(img) == len(expected)
    x = bev.network_input(img[None])
    assert x.shape == (1, 3, 201, 201) and x.dtype == np.float32
    assert x[0, 2, 88, 88] == np.float32(255 / 256) and x[0, 0, 75, 113] == np.float32(76 / 256)


def test_voxel_means_follow_open3d_grid():
    """The grid starts half a voxel below the minimum corner: shifting the cloud by
    0.2 m moves which points share a voxel."""
    pts = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.5, 0.0, 0.0]])
    # start -0.2: voxels floor((x + 0.2) / 0.4) = 0, 1, 1 -> means 0 and 0.4
    means = bev.voxel_means(pts)
    assert sorted(means[:, 0].round(9)) == [0.0, 0.4]
    # a point at -0.15 moves the start to -0.35: floor((x + 0.35) / 0.4) = 0, 0, 1, 2
    means = bev.voxel_means(np.vstack([pts, [[-0.15, 0.0, 0.0]]]))
    assert sorted(means[:, 0].round(9)) == [-0.075, 0.3, 0.5]


def test_empty_scan_is_a_black_image():
    assert not bev.bev_image(np.array([[50.0, 0.0, 0.0]], np.float32)).any()


def _authors_loop(points: np.ndarray) -> np.ndarray:
    """The BEV image written point by point from the conventions (an independent check)."""
    pts = points[(np.abs(points[:, 0]) < 40) & (np.abs(points[:, 1]) < 40)
                 & (np.abs(points[:, 2]) < 40)].astype(np.float64)
    start = pts.min(axis=0) - 0.2
    voxels: dict[tuple, list] = {}
    for p in pts:
        voxels.setdefault(tuple(int(v) for v in np.floor((p - start) / 0.4)), []).append(p)
    img = np.zeros((201, 201), dtype=np.uint8)
    for members in voxels.values():
        m = np.mean(members, axis=0)
        r, c = 100 - math.floor(m[0] / 0.4), 100 - math.floor(m[1] / 0.4)
        if img[r, c] < 10:
            img[r, c] += 1
    img = img * 10
    return np.rint(img / img.max() * 255).astype(np.uint8)


def test_bev_of_a_real_scan_equals_a_point_by_point_computation():
    scan = _real_scans()[0]
    ours = bev.bev_image(scan)
    theirs = _authors_loop(scan)
    # voxel means summed in another order may cross a pixel border in the last bit
    assert np.count_nonzero(ours != theirs) <= 2  # 0 on the four samples
    assert np.count_nonzero(ours) > 3000


def test_bev_of_a_rotated_real_scan_is_the_rotated_image():
    """A 90 degree turn (x, y) -> (-y, x) is exact in float32; on the pixel grid it is
    rot90 shifted by one row (floor(-v) = -floor(v) - 1 off the cell borders)."""
    scan = _real_scans()[1]
    keep = (np.mod(scan[:, 0] / 0.4, 1.0) != 0) & (np.mod(scan[:, 1] / 0.4, 1.0) != 0)
    scan = bev.crop(scan[keep])
    turned = np.stack([-scan[:, 1], scan[:, 0], scan[:, 2]], axis=1)
    a = bev.density_counts(scan)
    b = bev.density_counts(turned)
    assert a[:, 0].sum() == 0 and a[0].sum() == 0  # the authors' indexing leaves them empty
    assert np.array_equal(b, np.roll(np.rot90(a), 1, axis=0))
    # the whole pipeline: Open3D's data-anchored voxel grid differs after the turn, so the
    # images agree closely but not exactly; an unrelated scan agrees far less
    full = bev.bev_image(scan).astype(float)
    full_turned = np.roll(np.rot90(full), 1, axis=0)
    other = bev.bev_image(_real_scans()[3]).astype(float)

    def corr(u, v):
        return float(np.corrcoef(u.ravel(), v.ravel())[0, 1])
    assert corr(bev.bev_image(turned).astype(float), full_turned) > 0.9  # 0.966 measured
    assert corr(full, other) < 0.6  # 0.148 measured


# ------------------------------------------------------------------ network vs torch


def _torch_net(weights):
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.bevplace import torch_net

    torch.set_num_threads(1)
    net = torch_net.BEVPlaceNet().eval()
    torch_net.load_numpy(net, weights)
    return torch, net


def _inputs() -> np.ndarray:
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 256, (201, 201)).astype(np.uint8)]
    imgs += [bev.bev_image(s) for s in _kitti_scans()]
    return bev.network_input(np.stack(imgs))


def test_numpy_forward_equals_torch_on_random_weights():
    w = network.random_weights(seed=5)
    torch, net = _torch_net(w)
    x = _inputs()
    with torch.no_grad():  # net(x) is net.pooling(net.rem(x)); one pass gives both
        rem = net.rem(torch.from_numpy(x))  # (B, 128, 50, 50)
        rem_theirs, theirs = rem.numpy(), net.pooling(rem).numpy()
    rem_ours = network.rem_features(w, x)
    assert rem_ours.shape == (len(x), 50, 50, 128)
    assert np.max(np.abs(rem_ours - rem_theirs.transpose(0, 2, 3, 1))) <= 1e-5
    ours = network.netvlad(w, rem_ours.reshape(len(x), -1, 128))  # network.forward's tail
    assert ours.shape == (len(x), 8192)
    assert np.max(np.abs(ours - theirs)) <= 1e-5
    assert np.allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-5)
    d_ours = ((ours[:, None] - ours[None]) ** 2).sum(-1) + np.diag(np.full(len(ours), np.inf))
    d_theirs = ((theirs[:, None] - theirs[None]) ** 2).sum(-1) + np.diag(
        np.full(len(ours), np.inf))
    assert (d_ours.argmin(1) == d_theirs.argmin(1)).all()
    if len(x) > 1:  # images differ by more than the tolerance (random weights: not by much)
        assert np.max(np.abs(ours[0] - ours[1])) > 2e-4


def test_local_features_equal_torch_at_the_fast_keypoints():
    """The pose's local features: the REM's second output (torch: the full 201 x 201 map)
    read at the FAST keypoints, against the NumPy pass that evaluates those pixels only."""
    from lidar_iris_eval.descriptors.bevplace import fast

    w = network.random_weights(seed=5)
    torch, net = _torch_net(w)
    scans = _real_scans()
    image = bev.bev_image(scans[0])
    x = bev.network_input(image[None])
    with torch.no_grad():
        theirs = net.local_map(torch.from_numpy(x)).numpy()[0].transpose(1, 2, 0)
    glob, best = network.forward_with_maximum(w, x)
    px = fast.detect(image)
    assert len(px) > 100
    ours = network.local_features(best[0], px, image.shape)
    assert np.max(np.abs(ours - theirs[px[:, 0], px[:, 1]])) <= 1e-5
    assert np.array_equal(glob, network.forward(w, x))


def test_descriptor_is_invariant_to_a_quarter_turn_of_the_image():
    """The eight warps of a quarter-turned image are the same eight images in another
    order; warped back and max-pooled, the map is the turned map, pooled by NetVLAD."""
    w = network.random_weights(seed=0)
    scans = _kitti_scans()
    if scans:
        img, other = bev.bev_image(scans[0]), bev.bev_image(scans[2])
    else:
        rng = np.random.default_rng(2)
        img, other = (rng.integers(0, 256, (201, 201)).astype(np.uint8) for _ in range(2))
    d = network.forward(w, bev.network_input(np.stack([img, np.rot90(img), other])))
    same = float(((d[0] - d[1]) ** 2).sum())
    far = float(((d[0] - d[2]) ** 2).sum())
    assert same < 1e-3 * far, (same, far)


# ------------------------------------------------------------------ weights files


def test_hand_built_checkpoint_gives_the_same_descriptors_and_its_sha(tmp_path):
    """The authors' layout ({"state_dict": ...} with DataParallel's "module." prefix),
    written without torch, reads back to the very same network; the cache key is the
    file's SHA-256."""
    weights = network.random_weights(seed=2)
    path = tmp_path / "model_best.pth.tar"
    hand_checkpoint(path, {f"module.{k}": v for k, v in weights.items()})
    from_file = get_descriptor("bevplace", weights=str(path))
    generated = get_descriptor("bevplace", weights="random-init", seed=2)
    img = np.random.default_rng(4).integers(0, 256, (1, 201, 201)).astype(np.uint8)
    assert np.array_equal(from_file.compute_images(img), generated.compute_images(img))
    assert from_file.cache_token() == hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    assert generated.cache_token() == weights_digest(weights, network.shapes())[:16]
    assert from_file.run_info() == {"weights": "model_best.pth.tar", "weights_trained": True,
                                    "weights_sha256": from_file.cache_token()}
    np.savez(tmp_path / "w.npz", **weights)
    from_npz = get_descriptor("bevplace", weights=str(tmp_path / "w.npz"))
    assert np.array_equal(from_npz.compute_images(img), generated.compute_images(img))


def test_torch_saved_checkpoint_gives_the_torch_descriptors(tmp_path):
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.bevplace import torch_net

    torch.manual_seed(0)
    net = torch_net.BEVPlaceNet()
    torch_net.load_numpy(net, network.random_weights(3))
    path = tmp_path / "model_best.pth.tar"
    # the authors save {"epoch", "state_dict", "optimizer", ...}; BatchNorm adds
    # num_batches_tracked (int64), which the reader keeps and the network ignores
    torch.save({"epoch": 7, "state_dict": net.state_dict(), "best_score": 0.9}, path)
    desc = get_descriptor("bevplace", preset="paper", weights=str(path))
    img = np.random.default_rng(2).integers(0, 256, (1, 201, 201)).astype(np.uint8)
    with torch.no_grad():
        ref = net.eval()(torch.from_numpy(bev.network_input(img))).numpy()
    assert np.max(np.abs(desc.compute_images(img) - ref)) <= 1e-5


@pytest.mark.parametrize("kind", ["truncated", "not-zip", "missing", "wrong-model", "evil"])
def test_bad_weights_are_one_error_line(tmp_path, capsys, kind):
    path = tmp_path / "w.pth.tar"
    if kind == "truncated":
        hand_checkpoint(path, {"a": np.zeros(1000, np.float32)})
        path.write_bytes(path.read_bytes()[:-300])
    elif kind == "not-zip":
        path.write_text("hello")
    elif kind == "wrong-model":  # an OverlapTransformer layer is not BEVPlace++'s
        hand_checkpoint(path, {"conv1.weight": np.zeros((16, 1, 5, 1), np.float32)})
    elif kind == "evil":  # a pickle that would run a command is refused unrun
        marker = tmp_path / "pwned"
        path.write_bytes(pickle.dumps(_Boom(marker), protocol=2))
    desc = get_descriptor("bevplace", weights=str(path))
    with pytest.raises(LirisError, match="bevplace.weights="):
        desc.cache_token()
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    seq = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=3, azimuth_steps=256)
    code, _, err = run_cli(["extract", seq, "-d", "bevplace", "--param",
                            f"bevplace.weights={path}", "--cache-dir", tmp_path / "c", "-q"],
                           capsys)
    assert_one_line_error(code, err, "bevplace.weights=", str(path))
    if kind == "evil":
        assert "refused" in err and not (tmp_path / "pwned").exists()


class _Boom:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


# ------------------------------------------------------------------ through liris eval


def test_eval_runs_protocol_1(tmp_path, capsys):
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    # the first tiny-mixed frames hold no revisit: a short exclusion window makes
    # neighbouring frames the loops (the run, not the score, is what this checks)
    seq = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=6, azimuth_steps=512)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "-d", "bevplace", "--protocol", "1", "--exclude", "2",
                            "--cache-dir", tmp_path / "cache", "--out", out, "-q"], capsys)
    assert code == 0, err
    # the default is the shipped file liris fitted on simulated worlds: no random-weights warning
    assert "random-init" not in err and "NOT a trained model" not in err
    rows = [r for r in json.loads((out / "metrics.json").read_text())["results"]
            if r["descriptor"] == "bevplace"]
    assert [r["protocol"] for r in rows] == [1]
    assert rows[0]["weights"] == "bevplace_sim_weights.npz" and rows[0]["weights_trained"] is True
    assert rows[0]["weights_sha256"] == get_descriptor("bevplace").cache_token()
    assert 0.0 < rows[0]["f1_max"] <= 1.0
    # every match carries the authors' planar pose (descriptors/bevplace/pose.py)
    assert rows[0]["pose_estimate"] == "full" and rows[0]["rr_kind"] == "full"
    assert rows[0]["rte_m_median"] is not None and rows[0]["rre_deg_median"] is not None
    import pandas as pd

    table = pd.read_csv(out / "protocol1" / "bevplace" / "matches.csv")
    assert {"inliers", "T03", "T13"} <= set(table.columns)
    true = table[table.is_true.astype(bool)]
    assert len(true) and np.isfinite(true[["T03", "T13", "rte_m"]].to_numpy()).all()
    assert (true["T23"] == 0).all()


@pytest.mark.parametrize("metric", ["l2sq", "cosine"])
def test_distances_agree_and_the_method_pickles(metric):
    desc = get_descriptor("bevplace", metric=metric)
    rng = np.random.default_rng(9)
    d = rng.normal(size=(4, 8192))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    clone = pickle.loads(pickle.dumps(desc))
    full, _ = clone.pairwise(d, d)
    for i in range(4):
        assert np.array_equal(desc.distances(d[i], d)[0], full[i])
        assert desc.distance(d[i], d[2])[0] == full[i, 2]
    cos = d @ d.T
    assert np.allclose(full, {"l2sq": 2 - 2 * cos, "cosine": 1 - cos}[metric], atol=1e-9)
