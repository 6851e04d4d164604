"""BEVPlace++: BEV image, NumPy vs PyTorch network, checkpoint, CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import KITTI

from lidar_iris_eval.descriptors.bevplace import bev

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
    from lidar_iris_eval.descriptors.bevplace import network

    w = network.random_weights(seed=5)
    torch, net = _torch_net(w)
    x = _inputs()
    with torch.no_grad():
        rem_theirs = net.rem(torch.from_numpy(x)).numpy()  # (B, 128, 50, 50)
        theirs = net(torch.from_numpy(x)).numpy()
    rem_ours = network.rem_features(w, x)
    assert rem_ours.shape == (len(x), 50, 50, 128)
    assert np.max(np.abs(rem_ours - rem_theirs.transpose(0, 2, 3, 1))) <= 1e-5
    ours = network.forward(w, x)
    assert ours.shape == (len(x), 8192)
    assert np.max(np.abs(ours - theirs)) <= 1e-5
    assert np.allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-5)
    d_ours = ((ours[:, None] - ours[None]) ** 2).sum(-1) + np.diag(np.full(len(ours), np.inf))
    d_theirs = ((theirs[:, None] - theirs[None]) ** 2).sum(-1) + np.diag(
        np.full(len(ours), np.inf))
    assert (d_ours.argmin(1) == d_theirs.argmin(1)).all()
    if len(x) > 1:  # images differ by more than the tolerance (random weights: not by much)
        assert np.max(np.abs(ours[0] - ours[1])) > 2e-4


def test_descriptor_is_invariant_to_a_quarter_turn_of_the_image():
    """The eight warps of a quarter-turned image are the same eight images in another
    order; warped back and max-pooled, the map is the turned map, pooled by NetVLAD."""
    from lidar_iris_eval.descriptors.bevplace import network

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
