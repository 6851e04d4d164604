"""The same network in PyTorch, for tests and training only (the ``train`` extra).

Written from the architecture described in :mod:`.network`; its parameter
names equal the authors' ``state_dict`` names for every weight the forward
pass reads, so ``torch.save({"state_dict": net.state_dict()}, f)`` makes a
checkpoint :mod:`.checkpoint` reads, and :func:`load_numpy` copies NumPy
weights in.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lidar_iris_eval.descriptors.overlap_transformer import network


class _NetVLAD(nn.Module):
    def __init__(self):
        super().__init__()
        f, k, o = network.FEATURE, network.CLUSTERS, network.OUTPUT
        self.cluster_weights = nn.Parameter(torch.randn(f, k) / f ** 0.5)
        self.cluster_biases = nn.Parameter(torch.randn(k) / f ** 0.5)
        self.cluster_weights2 = nn.Parameter(torch.randn(1, f, k) / f ** 0.5)
        self.hidden1_weights = nn.Parameter(torch.randn(f * k, o) / f ** 0.5)
        self.context_gating = nn.Module()
        self.context_gating.gating_weights = nn.Parameter(torch.randn(o, o) / o ** 0.5)
        self.context_gating.gating_biases = nn.Parameter(torch.randn(o) / o ** 0.5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x (B, S, F), unit rows
        a = torch.softmax(x @ self.cluster_weights + self.cluster_biases, dim=2)
        v = x.transpose(1, 2) @ a - a.sum(dim=1, keepdim=True) * self.cluster_weights2
        v = F.normalize(v, dim=1).reshape(x.shape[0], -1)
        v = F.normalize(v, dim=1) @ self.hidden1_weights
        g = torch.sigmoid(v @ self.context_gating.gating_weights
                          + self.context_gating.gating_biases)
        return v * g


class OverlapTransformerNet(nn.Module):
    """``(B, 1, 64, W)`` depth images -> ``(B, 256)`` unit descriptors."""

    def __init__(self):
        super().__init__()
        for n, (c_in, c_out, k, s) in enumerate(network.CONVS, start=1):
            setattr(self, f"conv{n}", nn.Conv2d(c_in, c_out, (k, 1), stride=(s, 1), bias=False))
        self.convLast1 = nn.Conv2d(128, network.D_MODEL, 1, bias=False)
        self.convLast2 = nn.Conv2d(2 * network.D_MODEL, network.FEATURE, 1, bias=False)
        layer = nn.TransformerEncoderLayer(network.D_MODEL, network.HEADS, network.FEED_FORWARD,
                                           dropout=0.0, activation="relu",
                                           layer_norm_eps=network.LN_EPS, norm_first=False)
        self.transformer_encoder = nn.TransformerEncoder(layer, 1, enable_nested_tensor=False)
        self.net_vlad = _NetVLAD()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for n in range(1, len(network.CONVS) + 1):
            x = torch.relu(getattr(self, f"conv{n}")(x))
        first = torch.relu(self.convLast1(x))[:, :, 0, :].transpose(1, 2)  # (B, W, 256)
        mixed = self.transformer_encoder(first.transpose(0, 1)).transpose(0, 1)
        both = torch.cat([first, mixed], dim=2).transpose(1, 2)[:, :, None, :]
        feat = F.normalize(torch.relu(self.convLast2(both)), dim=1)[:, :, 0, :].transpose(1, 2)
        return F.normalize(self.net_vlad(feat), dim=1)


def load_numpy(net: OverlapTransformerNet, weights: dict[str, np.ndarray]) -> None:
    """Copy NumPy weights (the names of :func:`network.shapes`) into ``net``."""
    state = net.state_dict()
    for name in network.shapes():
        state[name] = torch.from_numpy(np.asarray(weights[name], dtype=np.float32).copy())
    net.load_state_dict(state)


def numpy_weights(net: OverlapTransformerNet) -> dict[str, np.ndarray]:
    """The weights the NumPy forward pass reads, from ``net``."""
    state = net.state_dict()
    return {name: state[name].detach().cpu().numpy().astype(np.float32)
            for name in network.shapes()}
