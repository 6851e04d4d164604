"""The same network in PyTorch, for training only (the ``train`` extra).

Parameter names and shapes equal those :mod:`.network` reads, so exporting is a
plain copy (batch norm exported as gamma, beta, running mean and variance).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from lidar_iris_eval.descriptors.esm.network import Arch


def _gather(a: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    b = torch.arange(a.shape[0], device=a.device)[:, None, None]
    return a[b, idx]


def _param(*shape: int, fan_in: int | None = None) -> nn.Parameter:
    if fan_in is None:
        return nn.Parameter(torch.zeros(*shape))
    return nn.Parameter(torch.randn(*shape) * (1.0 / fan_in) ** 0.5)


class XConv(nn.Module):
    def __init__(self, arch: Arch, layer: int, c_prev: int):
        super().__init__()
        k, cd, c, dm = arch.k[layer], arch.lifted[layer], arch.channels[layer], \
            arch.depth_mult[layer]
        self.arch, self.layer = arch, layer
        c_in = cd + c_prev
        self.p = nn.ParameterDict({
            "lift1_w": _param(3, cd, fan_in=3), "lift1_b": _param(cd),
            "lift2_w": _param(cd, cd, fan_in=cd), "lift2_b": _param(cd),
            "xt0_w": _param(3 * k, k * k, fan_in=3 * k), "xt0_b": _param(k * k),
            "xt1_w": _param(k, k, k, fan_in=k), "xt1_b": _param(k, k),
            "xt2_w": _param(k, k, k, fan_in=k), "xt2_b": _param(k, k),
            "dw_w": _param(k, c_in, dm, fan_in=k),
            "pw_w": _param(c_in * dm, c, fan_in=c_in * dm), "pw_b": _param(c),
        })
        self.bn = nn.BatchNorm1d(c, eps=arch.bn_eps)

    def forward(self, prev_pts, prev_feat, idx):
        a, p = self.arch, self.p
        r, k = a.reps[self.layer], a.k[self.layer]
        reps = prev_pts[:, :r]
        local = _gather(prev_pts, idx) - reps[:, :, None, :]
        f = nn.functional.elu(local @ p["lift1_w"] + p["lift1_b"])
        f = nn.functional.elu(f @ p["lift2_w"] + p["lift2_b"])
        if prev_feat is not None:
            f = torch.cat([f, _gather(prev_feat, idx)], dim=3)
        b = local.shape[0]
        x = nn.functional.elu(local.reshape(b, r, k * 3) @ p["xt0_w"] + p["xt0_b"])
        x = x.reshape(b * r, k, k).transpose(0, 1)
        x = nn.functional.elu(torch.matmul(x, p["xt1_w"]) + p["xt1_b"][:, None, :])
        x = torch.matmul(x, p["xt2_w"]) + p["xt2_b"][:, None, :]
        x = x.transpose(0, 1).reshape(b, r, k, k)
        fx = torch.matmul(x, f)
        c_in = fx.shape[3]
        fx = fx.reshape(b * r, k, c_in).permute(2, 0, 1)
        dep = torch.matmul(fx, p["dw_w"].permute(1, 0, 2))
        dep = dep.permute(1, 0, 2).reshape(b, r, -1)
        out = dep @ p["pw_w"] + p["pw_b"]
        out = self.bn(out.reshape(b * r, -1)).reshape(b, r, -1)
        return reps, nn.functional.elu(out)


class ESMNet(nn.Module):
    """Embedding network plus the quality head (trained separately)."""

    def __init__(self, arch: Arch | None = None):
        super().__init__()
        self.arch = arch = arch or Arch()
        prev = [0, *arch.channels[:3]]
        self.xconvs = nn.ModuleList(XConv(arch, i, prev[i]) for i in range(4))
        dims = [arch.channels[3], *arch.fc]
        self.fcs = nn.ModuleList(nn.Linear(dims[i], dims[i + 1]) for i in range(3))
        self.dropout = nn.Dropout(0.5)
        self.quality = nn.Linear(arch.fc[-1], 2)

    def forward(self, points: torch.Tensor, idx: list) -> torch.Tensor:
        """Embeddings of (B, 256, 3) points; ``idx`` from :func:`network.neighbour_index`."""
        pts, feat = points, None
        for xc, ix in zip(self.xconvs, idx, strict=True):
            pts, feat = xc(pts, feat, torch.as_tensor(ix))
        h = nn.functional.elu(self.fcs[0](feat))
        h = self.dropout(nn.functional.elu(self.fcs[1](h)))
        return self.fcs[2](h).mean(dim=1)

    def quality_logits(self, embeddings: torch.Tensor) -> torch.Tensor:
        return self.quality(embeddings)

    def export(self) -> dict[str, np.ndarray]:
        """Weights under the names :mod:`.network` reads (float32)."""
        out: dict[str, np.ndarray] = {"arch": np.array(self.arch.to_json())}
        for i, xc in enumerate(self.xconvs):
            for key, val in xc.p.items():
                out[f"x{i}.{key.replace('_', '.')}"] = val.detach().numpy().astype(np.float32)
            out[f"x{i}.bn.gamma"] = xc.bn.weight.detach().numpy().astype(np.float32)
            out[f"x{i}.bn.beta"] = xc.bn.bias.detach().numpy().astype(np.float32)
            out[f"x{i}.bn.mean"] = xc.bn.running_mean.numpy().astype(np.float32)
            out[f"x{i}.bn.var"] = xc.bn.running_var.numpy().astype(np.float32)
        for i, fc in enumerate(self.fcs):
            out[f"fc{i}.w"] = fc.weight.detach().numpy().T.astype(np.float32).copy()
            out[f"fc{i}.b"] = fc.bias.detach().numpy().astype(np.float32)
        out["q.w"] = self.quality.weight.detach().numpy().T.astype(np.float32).copy()
        out["q.b"] = self.quality.bias.detach().numpy().astype(np.float32)
        return out

    def load_numpy(self, weights: dict[str, np.ndarray]) -> None:
        """Set every parameter and batch-norm statistic from exported weights (:meth:`export`)."""
        def put(dst: torch.Tensor, src: np.ndarray) -> None:
            src = torch.from_numpy(np.asarray(src, dtype=np.float32))
            if tuple(dst.shape) != tuple(src.shape):
                raise ValueError(f"weights shape {tuple(src.shape)} does not fit "
                                 f"{tuple(dst.shape)}: another architecture")
            dst.copy_(src)

        with torch.no_grad():
            for i, xc in enumerate(self.xconvs):
                for key, val in xc.p.items():
                    put(val, weights[f"x{i}.{key.replace('_', '.')}"])
                put(xc.bn.weight, weights[f"x{i}.bn.gamma"])
                put(xc.bn.bias, weights[f"x{i}.bn.beta"])
                put(xc.bn.running_mean, weights[f"x{i}.bn.mean"])
                put(xc.bn.running_var, weights[f"x{i}.bn.var"])
            for i, fc in enumerate(self.fcs):
                put(fc.weight, np.asarray(weights[f"fc{i}.w"]).T)
                put(fc.bias, weights[f"fc{i}.b"])
            put(self.quality.weight, np.asarray(weights["q.w"]).T)
            put(self.quality.bias, weights["q.b"])
