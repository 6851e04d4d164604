"""The same network in PyTorch, for tests and training only (the ``train`` extra).

Written from the architecture described in :mod:`.network`, with PyTorch's own
``affine_grid`` / ``grid_sample``, convolutions and batch norm (so the NumPy
pass is checked against independent kernels). Parameter names equal the
authors' ``state_dict`` names (``rem.encoder...``, ``pooling...``), so
``torch.save({"state_dict": net.state_dict()}, f)`` makes a checkpoint
:mod:`lidar_iris_eval.descriptors.checkpoint` reads, and :func:`load_numpy`
copies NumPy weights in. No torchvision is needed: the ResNet blocks are
written here with torchvision's layout.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lidar_iris_eval.descriptors.bevplace import network


class _Block(nn.Module):
    """torchvision's ``BasicBlock``: two 3 x 3 convolutions, batch norm, a shortcut."""

    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.downsample = None
        if stride != 1 or c_in != c_out:
            self.downsample = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False),
                                            nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.bn2(self.conv2(self.relu(self.bn1(self.conv1(x)))))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


def _layer(blocks: int, c_in: int, c_out: int, stride: int) -> nn.Sequential:
    return nn.Sequential(*[_Block(c_in if b == 0 else c_out, c_out, stride if b == 0 else 1)
                           for b in range(blocks)])


class _REM(nn.Module):
    def __init__(self, rotations: int):
        super().__init__()
        (_, n1, i1, o1, s1), (_, n2, i2, o2, s2) = network.LAYERS
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1), _layer(n1, i1, o1, s1), _layer(n2, i2, o2, s2))
        self.angles = -torch.arange(0, 359.00001, 360.0 / rotations) / 180 * torch.pi

    @staticmethod
    def _turn(x: torch.Tensor, angle: torch.Tensor, size) -> torch.Tensor:
        c, s = torch.cos(angle), torch.sin(angle)
        theta = torch.zeros(x.shape[0], 2, 3, dtype=x.dtype, device=x.device)
        theta[:, 0, 0], theta[:, 0, 1], theta[:, 1, 0], theta[:, 1, 1] = c, s, -s, c
        grid = F.affine_grid(theta, list(size), align_corners=True)
        return F.grid_sample(x, grid, mode="bicubic", align_corners=True)

    def maximum(self, x: torch.Tensor) -> torch.Tensor:
        """The element-wise maximum of the eight warped-back encoder maps."""
        maps = []
        for angle in self.angles:
            out = self.encoder(self._turn(x, -angle, x.shape))
            maps.append(self._turn(out, angle, out.shape))
        return torch.stack(maps, dim=-1).amax(dim=-1)

    @staticmethod
    def resampled(best: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """``best`` resampled to ``h x w`` (identity grid, bicubic) and normalised per pixel."""
        b = best.shape[0]
        eye = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=best.dtype,
                           device=best.device).expand(b, 2, 3)
        grid = F.affine_grid(eye, [b, best.shape[1], h, w], align_corners=True)
        return F.normalize(F.grid_sample(best, grid, mode="bicubic", align_corners=True), dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _, _, h, w = x.shape
        return self.resampled(self.maximum(x), h // 4, w // 4)

    def local_map(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 128, H, W)``: the REM's second output, the keypoints' local features."""
        _, _, h, w = x.shape
        return self.resampled(self.maximum(x), h, w)


class _NetVLAD(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(network.DIM, network.CLUSTERS, 1, bias=False)
        self.centroids = nn.Parameter(torch.rand(network.CLUSTERS, network.DIM))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c = x.shape[:2]
        flat = x.reshape(n, c, -1)  # (B, C, P)
        assign = F.softmax(self.conv(x).reshape(n, network.CLUSTERS, -1), dim=1)  # (B, K, P)
        # residual form, one cluster at a time (the NumPy pass uses the expanded form)
        vlad = torch.stack([((flat - self.centroids[k][None, :, None]) * assign[:, k:k + 1])
                            .sum(dim=-1) for k in range(network.CLUSTERS)], dim=1)
        vlad = F.normalize(vlad, dim=2).reshape(n, -1)
        return F.normalize(vlad, dim=1)


class BEVPlaceNet(nn.Module):
    """``(B, 3, H, W)`` BEV images -> ``(B, 8192)`` unit global descriptors."""

    def __init__(self, rotations: int = network.ROTATIONS):
        super().__init__()
        self.rem = _REM(rotations)
        self.pooling = _NetVLAD()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pooling(self.rem(x))

    def local_map(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 128, H, W)`` unit local features at every pixel (the REM's second output)."""
        return self.rem.local_map(x)


def load_numpy(net: BEVPlaceNet, weights: dict[str, np.ndarray]) -> None:
    """Copy NumPy weights (the names of :func:`network.shapes`) into ``net``."""
    state = net.state_dict()
    for name in network.shapes():
        state[name] = torch.from_numpy(np.asarray(weights[name], dtype=np.float32).copy())
    net.load_state_dict(state)


def numpy_weights(net: BEVPlaceNet) -> dict[str, np.ndarray]:
    """The weights the NumPy forward pass reads, from ``net``."""
    state = net.state_dict()
    return {name: state[name].detach().cpu().numpy().astype(np.float32)
            for name in network.shapes()}
