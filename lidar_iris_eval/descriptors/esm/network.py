"""ESM's segment network, inference in NumPy (no deep-learning package at run time).

Architecture (ESM, Tinchev et al. 2019, after PointCNN's X-Conv; sizes named
here because the paper leaves them blank):

* input: 256 normalised points per segment, no input features;
* four X-Conv layers, (K, dilation) = (8, 1), (12, 3), (16, 3), (16, 4), with
  representative points 256 -> 128 -> 64 -> 32 (the first ``R`` points of the
  seeded, randomly ordered resample, so the choice is deterministic), output
  channels 32, 64, 96, 128 and lifted-coordinate channels 16, 16, 24, 32.
  Each layer, for every representative point:

  1. its ``K * D`` nearest points of the previous layer, sorted by distance,
     every ``D``-th kept (``K`` neighbours), in coordinates relative to it;
  2. the local coordinates lifted by two dense layers (ELU) and concatenated
     with the neighbours' previous features;
  3. a ``K x K`` matrix X from the flattened local coordinates: a dense layer
     to ``K * K`` (ELU), then two per-row ``K x K`` layers (PointCNN's
     depthwise refinement; ELU after the first, linear after the second);
  4. ``X @ F``, then a separable convolution over the K neighbours (depthwise
     with multiplier ``dm``, pointwise to C), batch norm (folded to an affine
     map at inference) and ELU;

* three fully connected layers per point, 64 -> 64 (ELU) -> 32 (ELU, dropout
  0.5 in training) -> 16, averaged over the 32 points: the 16-d embedding;
* quality branch: one dense layer 16 -> 2 with a softmax on the (frozen)
  embedding; the quality is the probability of "a true match is among the
  k nearest neighbours".

Weights are one ``.npz`` (names below); :func:`load_weights` checks its
checksum against the model card when asked.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic
from scipy.spatial import cKDTree

WEIGHTS_FILE = Path(__file__).with_name("esm_weights.npz")
#: the weights trained on local-map segments (scripts/train_esm.py --source local-maps)
LOCALMAP_WEIGHTS_FILE = Path(__file__).with_name("esm_localmap_weights.npz")


@dataclass(frozen=True)
class Arch:
    """Sizes of the network (stored in the weights file)."""

    n_points: int = 256
    reps: tuple = (256, 128, 64, 32)
    k: tuple = (8, 12, 16, 16)
    dilation: tuple = (1, 3, 3, 4)
    channels: tuple = (16, 32, 48, 64)
    lifted: tuple = (8, 8, 12, 16)
    depth_mult: tuple = (1, 1, 1, 1)
    fc: tuple = (64, 32, 16)
    bn_eps: float = 1e-5
    norm_scale: float = 0.0  # segment normalisation the network was trained with (segmentation)
    align_yaw: bool = False  # segments turned to their principal axis (segmentation.yaw_align)

    def to_json(self) -> str:
        return json.dumps({k: list(v) if isinstance(v, tuple) else v
                           for k, v in self.__dict__.items()})

    @classmethod
    def from_json(cls, text: str) -> Arch:
        raw = json.loads(text)
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.items()})


def _f32(bits: int) -> np.float32:
    """The float32 whose IEEE-754 bits are ``bits``."""
    return np.array([bits], np.uint32).view(np.float32)[0]


# glibc's expm1f (sysdeps/ieee754/flt-32/s_expm1f.c, fdlibm's float algorithm), its constants
# by their bits
_ONE, _HALF, _MHALF = np.float32(1.0), np.float32(0.5), np.float32(-0.5)
_THREE, _SIX, _MONE = np.float32(3.0), np.float32(6.0), np.float32(-1.0)
_LN2_HI, _LN2_LO, _INVLN2 = _f32(0x3F317180), _f32(0x3717F7D1), _f32(0x3FB8AA3B)
_Q1, _Q2, _Q3 = _f32(0xBD088889), _f32(0x3AD00D01), _f32(0xB8A670CD)
_Q4, _Q5 = _f32(0x36867E54), _f32(0xB457EDBB)
_SATURATE = _f32(0x4195B844)  # 27 ln2: below -27 ln2, expm1f returns -1
_HALF_LN2, _ONEHALF_LN2 = _f32(0x3EB17218), _f32(0x3F851592)
_TINY = _f32(0x33000000)  # 2**-25: below, expm1f returns x


@intrinsic
def _bits_as_f32(typingctx, bits):  # pragma: no cover - compiled
    """Reinterpret an int32 as a float32 (a bitcast LLVM can vectorise)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return types.float32(types.int32), codegen


@numba.njit(inline="always")
def _elu1(v: np.float32) -> np.float32:  # pragma: no cover - compiled
    """ELU of one float32 whose negative branch is glibc's ``expm1f``, bit for bit.

    The network's bits were fixed with numba's ``np.expm1``, a call into the C
    library per element (about 9 ns, a branch on the sign each). This is the
    same algorithm in the same float32 operations, computed without branches
    (every path, then selects) so the loop vectorises: ~10x faster. Two
    rewrites keep the bits: the reductions for k = 0 and k = -1 are the general
    one with t = 0 and t = -1 (exact products), and adding k to the exponent
    is a product by 2**k (exact: k >= -28, the result stays normal). Equal to
    the C library's on every negative float32 (all 2**31 bit patterns checked
    against numba's ``np.expm1`` with glibc 2.36; tests/test_esm_network_elu.py
    checks a sample), and so independent of the platform's libm.
    """
    x = max(v, -_SATURATE)
    ax = -x
    kr = np.int32(_INVLN2 * x + _MHALF)
    k = np.int32(0) if ax <= _HALF_LN2 else (np.int32(-1) if ax < _ONEHALF_LN2 else kr)
    t = np.float32(k)
    hi = x - t * _LN2_HI
    lo = t * _LN2_LO
    xr = hi - lo
    c = (hi - xr) - lo
    hfx = _HALF * xr
    hxs = xr * hfx
    r1 = _ONE + hxs * (_Q1 + hxs * (_Q2 + hxs * (_Q3 + hxs * (_Q4 + hxs * _Q5))))
    t3 = _THREE - r1 * hfx
    e = hxs * ((r1 - t3) / (_SIX - xr * t3))
    r0 = xr - (xr * e - hxs)  # k == 0
    e2 = (xr * (e - c) - c) - hxs
    rm1 = _HALF * (xr - e2) - _HALF  # k == -1
    y = (_ONE - (e2 - xr)) * _bits_as_f32((k + np.int32(127)) << np.int32(23))
    rk = y - _ONE  # k <= -2
    r = r0 if k == 0 else (rm1 if k == -1 else rk)
    r = x if ax < _TINY else r
    r = _MONE if ax >= _SATURATE else r
    return r if v < 0 else v


# error_model="numpy": no zero-division check in the loop, which would stop it vectorising
@numba.njit(cache=True, error_model="numpy")
def _elu_inplace(flat: np.ndarray) -> None:  # pragma: no cover - compiled
    for i in range(flat.size):
        flat[i] = _elu1(flat[i])


@numba.njit(cache=True)
def _elu_inplace_libm(flat: np.ndarray) -> None:  # pragma: no cover - compiled
    """The reference: the C library's ``expm1f`` per negative element."""
    for i in range(flat.size):
        v = flat[i]
        if v < 0:
            flat[i] = np.expm1(v)


def elu(x: np.ndarray) -> np.ndarray:
    """ELU (alpha 1) of a float32 array, in place when it is contiguous float32; the
    negative branch equals the C library's ``expm1f`` bit for bit (:func:`_elu1`)."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    _elu_inplace(x.reshape(-1))
    return x


def neighbour_index(points: np.ndarray, arch: Arch) -> list[np.ndarray]:
    """Per layer, (S, R, K) indices of each representative point's dilated neighbours.

    Layer ``l``'s representatives are the first ``reps[l]`` points and its
    neighbours are taken among the previous layer's points (the first
    ``reps[l-1]``, all points for the first layer): the ``K * D`` nearest by a
    k-d tree (each point is its own nearest), every ``D``-th kept. This is not
    learned, so training computes it with this same function and feeds the
    indices to the framework; both forwards then differ only by rounding.
    (A k-d tree per segment beat a brute-force float32 search 1.6x here.)
    """
    pts = np.asarray(points, dtype=np.float64)
    out = []
    prev_n = pts.shape[1]
    for r, k, d in zip(arch.reps, arch.k, arch.dilation, strict=True):
        idx = np.empty((len(pts), r, k), dtype=np.int64)
        for s in range(len(pts)):
            _, nn = cKDTree(pts[s, :prev_n]).query(pts[s, :r], k=k * d)
            idx[s] = nn.reshape(r, k * d)[:, ::d]
        out.append(idx)
        prev_n = r
    return out


def _gather(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """a (S, N, C), idx (S, R, K) -> (S, R, K, C)."""
    s = np.arange(a.shape[0])[:, None, None]
    return a[s, idx]


def xconv(w: dict, name: str, arch: Arch, layer: int, prev_pts: np.ndarray,
          prev_feat: np.ndarray | None, idx: np.ndarray) -> tuple:
    """One X-Conv layer; returns (representative points, their features)."""
    r, k = arch.reps[layer], arch.k[layer]
    reps = prev_pts[:, :r]
    local = _gather(prev_pts, idx) - reps[:, :, None, :]  # (S,R,K,3)
    f = elu(local @ w[f"{name}.lift1.w"] + w[f"{name}.lift1.b"])
    f = elu(f @ w[f"{name}.lift2.w"] + w[f"{name}.lift2.b"])
    if prev_feat is not None:
        f = np.concatenate([f, _gather(prev_feat, idx)], axis=3)
    s_ = local.shape[0]
    x = elu(local.reshape(s_, r, k * 3) @ w[f"{name}.xt0.w"] + w[f"{name}.xt0.b"])
    x = x.reshape(s_ * r, k, k).transpose(1, 0, 2)  # (K_i, S*R, K_j)
    x = elu(np.matmul(x, w[f"{name}.xt1.w"]) + w[f"{name}.xt1.b"][:, None, :])
    x = np.matmul(x, w[f"{name}.xt2.w"]) + w[f"{name}.xt2.b"][:, None, :]
    x = x.transpose(1, 0, 2).reshape(s_, r, k, k)
    fx = np.matmul(x, f)  # (S,R,K,C*)
    c_in = fx.shape[3]
    dw = w[f"{name}.dw.w"]  # (K, C*, dm)
    fx = fx.reshape(s_ * r, k, c_in).transpose(2, 0, 1)  # (C*, S*R, K)
    dep = np.matmul(fx, dw.transpose(1, 0, 2))  # (C*, S*R, dm)
    dep = dep.transpose(1, 0, 2).reshape(s_, r, c_in * dw.shape[2])
    out = dep @ w[f"{name}.pw.w"] + w[f"{name}.pw.b"]
    scale = w[f"{name}.bn.gamma"] / np.sqrt(w[f"{name}.bn.var"] + arch.bn_eps)
    out = (out - w[f"{name}.bn.mean"]) * scale + w[f"{name}.bn.beta"]
    return reps, elu(out)


def per_point_features(w: dict, arch: Arch, points: np.ndarray,
                       idx: list[np.ndarray] | None = None) -> np.ndarray:
    """(S, R4, fc[-1]) per-point outputs before the average."""
    pts = np.asarray(points, dtype=np.float32)
    idx = neighbour_index(pts, arch) if idx is None else idx
    feat = None
    for layer in range(4):
        pts, feat = xconv(w, f"x{layer}", arch, layer, pts, feat, idx[layer])
    h = elu(feat @ w["fc0.w"] + w["fc0.b"])
    h = elu(h @ w["fc1.w"] + w["fc1.b"])
    return h @ w["fc2.w"] + w["fc2.b"]


def embed(w: dict, arch: Arch, points: np.ndarray, batch: int = 64) -> np.ndarray:
    """(S, 16) float32 embeddings of (S, 256, 3) normalised segments."""
    out = np.zeros((len(points), arch.fc[-1]), np.float32)
    for i in range(0, len(points), batch):
        out[i:i + batch] = per_point_features(w, arch, points[i:i + batch]).mean(axis=1)
    return out


def quality(w: dict, embeddings: np.ndarray) -> np.ndarray:
    """P(true match in the k-NN) from the quality branch (softmax's second entry)."""
    z = embeddings @ w["q.w"] + w["q.b"]
    z = z - z.max(axis=1, keepdims=True)
    e = np.exp(z)
    return (e[:, 1] / e.sum(axis=1)).astype(np.float64)


def resolve_weights(name: str | Path | None) -> Path:
    """The weights file ``name`` means: a bare file name shipped beside this module
    (``esm_weights.npz``, ``esm_localmap_weights.npz``), else a path; empty: ``WEIGHTS_FILE``.
    """
    if name is None or str(name) == "":
        return WEIGHTS_FILE
    path = Path(name)
    if path.name == str(name) and (WEIGHTS_FILE.parent / path.name).is_file():
        return WEIGHTS_FILE.parent / path.name
    return path


def sha256_of(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_weights(path: Path | None = None) -> tuple[dict, Arch]:
    """Weights (float32 arrays by name) and the architecture stored beside them."""
    path = Path(path) if path is not None else WEIGHTS_FILE
    with np.load(path, allow_pickle=False) as z:
        arch = Arch.from_json(str(z["arch"]))
        w = {k: z[k].astype(np.float32) for k in z.files if k != "arch"}
    return w, arch
