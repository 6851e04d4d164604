"""OverlapTransformer's network, inference in NumPy (no deep-learning package at run time).

Architecture (Ma et al., RA-L 2022; sizes as in the authors' published model,
``modules/overlap_transformer.py`` and ``modules/netvlad.py`` of
haomo-ai/OverlapTransformer, read for the numbers only):

* input ``(B, 1, 64, 900)``: one depth channel of the range image;
* eleven convolutions with ``(k x 1)`` kernels, no padding, no bias, each
  followed by ReLU (the model defines batch-norm layers but its forward pass
  never applies them, so neither does this one):

  ====  ======  ======  ========  ========
  conv  in      out     kernel    stride
  ====  ======  ======  ========  ========
  1     1       16      5 x 1     1
  2     16      32      3 x 1     2
  3     32      64      3 x 1     2
  4     64      64      3 x 1     2
  5     64      128     2 x 1     2
  6-11  128     128     1 x 1     2
  ====  ======  ======  ========  ========

  The height goes 64 -> 60 -> 29 -> 14 -> 6 -> 3 -> 2 -> 1 (and stays 1);
  the width (900 azimuth columns) is never mixed, so each column becomes one
  128-d token;
* ``convLast1``: 1 x 1 convolution 128 -> 256 (no bias) and ReLU;
* one transformer encoder layer over the 900 tokens: d = 256, 4 heads,
  feed-forward 1024 with ReLU, no dropout, post-norm (residual, then layer
  norm, eps 1e-5), no positional encoding;
* the 256-d tokens before and after the transformer concatenated (512),
  ``convLast2`` 1 x 1 to 1024 (no bias), ReLU, L2 normalisation per token;
* NetVLAD with 64 clusters on the 900 tokens: soft assignment
  ``softmax(x W + b)`` (no batch norm), residuals to the cluster centres
  summed, intra-normalised per cluster, flattened feature-major (index
  ``f * 64 + k``), L2 normalised, projected to 256 by a bias-free matrix,
  then context gating ``v * sigmoid(v G + g)``;
* a final L2 normalisation: a 256-d unit vector.

No column is treated differently from another and NetVLAD sums over columns,
so a circular shift of the range image's columns (a yaw turn by a multiple of
360/900 = 0.4 degrees) leaves the descriptor unchanged up to float rounding.

Weights are a dict of float32 arrays under the authors' ``state_dict`` names
(``conv1.weight``, ``transformer_encoder.layers.0.self_attn.in_proj_weight``,
``net_vlad.cluster_weights``, ...), so a user's checkpoint is read as is.
"""

from __future__ import annotations

import numpy as np

#: (in, out, kernel height, stride) of the eleven convolutions
CONVS = ((1, 16, 5, 1), (16, 32, 3, 2), (32, 64, 3, 2), (64, 64, 3, 2), (64, 128, 2, 2),
         (128, 128, 1, 2), (128, 128, 1, 2), (128, 128, 1, 2), (128, 128, 1, 2),
         (128, 128, 1, 2), (128, 128, 1, 2))
D_MODEL, HEADS, FEED_FORWARD = 256, 4, 1024
FEATURE, CLUSTERS, OUTPUT = 1024, 64, 256
LN_EPS, NORM_EPS = 1e-5, 1e-12
_TF = "transformer_encoder.layers.0."
_VLAD = "net_vlad."


def shapes(height: int = 64, width: int = 900) -> dict[str, tuple[int, ...]]:
    """Every weight the forward pass reads and its shape (the authors' names)."""
    out: dict[str, tuple[int, ...]] = {}
    for n, (c_in, c_out, k, _) in enumerate(CONVS, start=1):
        out[f"conv{n}.weight"] = (c_out, c_in, k, 1)
    out["convLast1.weight"] = (D_MODEL, 128, 1, 1)
    out["convLast2.weight"] = (FEATURE, 2 * D_MODEL, 1, 1)
    out[_TF + "self_attn.in_proj_weight"] = (3 * D_MODEL, D_MODEL)
    out[_TF + "self_attn.in_proj_bias"] = (3 * D_MODEL,)
    out[_TF + "self_attn.out_proj.weight"] = (D_MODEL, D_MODEL)
    out[_TF + "self_attn.out_proj.bias"] = (D_MODEL,)
    out[_TF + "linear1.weight"] = (FEED_FORWARD, D_MODEL)
    out[_TF + "linear1.bias"] = (FEED_FORWARD,)
    out[_TF + "linear2.weight"] = (D_MODEL, FEED_FORWARD)
    out[_TF + "linear2.bias"] = (D_MODEL,)
    for norm in ("norm1", "norm2"):
        out[_TF + f"{norm}.weight"] = (D_MODEL,)
        out[_TF + f"{norm}.bias"] = (D_MODEL,)
    out[_VLAD + "cluster_weights"] = (FEATURE, CLUSTERS)
    out[_VLAD + "cluster_biases"] = (CLUSTERS,)
    out[_VLAD + "cluster_weights2"] = (1, FEATURE, CLUSTERS)
    out[_VLAD + "hidden1_weights"] = (FEATURE * CLUSTERS, OUTPUT)
    out[_VLAD + "context_gating.gating_weights"] = (OUTPUT, OUTPUT)
    out[_VLAD + "context_gating.gating_biases"] = (OUTPUT,)
    return out


def conv_height(height: int) -> int:
    """Height of the feature map after the eleven convolutions (1 for 64 rows)."""
    for _, _, k, s in CONVS:
        height = (height - k) // s + 1
        if height < 1:
            return 0
    return height


def random_weights(seed: int = 0) -> dict[str, np.ndarray]:
    """Deterministic random weights: NOT a trained model (see MODEL_CARD.md).

    Gaussian draws scaled by ``1/sqrt(fan_in)`` (``sqrt(2/fan_in)`` before a
    ReLU), layer-norm scales 1 and shifts 0, biases small. The network then
    computes a fixed random projection of the range image: it runs, is
    yaw-invariant by construction, and retrieves places only as well as such
    a projection can.
    """
    rng = np.random.default_rng(seed)
    w: dict[str, np.ndarray] = {}
    for name, shape in shapes().items():
        if name.endswith(("norm1.weight", "norm2.weight")):
            arr = np.ones(shape)
        elif name.endswith(("norm1.bias", "norm2.bias")):
            arr = np.zeros(shape)
        elif len(shape) == 1:
            arr = rng.standard_normal(shape) * 0.01
        else:
            if name.startswith(_VLAD):  # stored (in, out)
                fan = shape[-2]
            else:  # stored (out, in, ...), as torch does
                fan = int(np.prod(shape[1:]))
            gain = 2.0 if name.startswith("conv") or name.endswith("linear1.weight") else 1.0
            arr = rng.standard_normal(shape) * np.sqrt(gain / fan)
        w[name] = arr.astype(np.float32)
    return w


# ------------------------------------------------------------------ frozen projection

#: the NetVLAD projection liris' own trained weights keep frozen (65,536 x 256: 16.8 M of
#: the 18.5 M weights); a weights file may hold its seed and SHA-256 instead of the matrix
FROZEN_NAME = _VLAD + "hidden1_weights"
FROZEN_SEED = "liris.frozen_hidden1_seed"
FROZEN_SHA256 = "liris.frozen_hidden1_sha256"


def frozen_projection(seed: int) -> np.ndarray:
    """The frozen ``(65536, 256)`` float32 NetVLAD projection of seed ``seed``.

    Standard normal float32 draws of NumPy's ``default_rng(seed)`` (row-major),
    divided by 32 = ``sqrt(1024)``: the scale of the authors' initialisation of
    this matrix (``randn / sqrt(feature_size)``). Files that store the seed also
    store the SHA-256 of these bytes, checked by :func:`expand_frozen`, so a
    NumPy whose generator drew other numbers fails loudly instead of silently.
    """
    rng = np.random.default_rng(int(seed))
    arr = rng.standard_normal((FEATURE * CLUSTERS, OUTPUT), dtype=np.float32)
    arr *= np.float32(1.0 / 32.0)
    return arr


def array_sha256(arr: np.ndarray) -> str:
    """SHA-256 of an array's little-endian float32 C-order bytes."""
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(arr, dtype="<f4").tobytes()).hexdigest()


def expand_frozen(weights: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``weights`` with the frozen projection regenerated when the file stores its seed.

    Files without :data:`FROZEN_SEED` (the authors' checkpoint, a full ``.npz``)
    come back unchanged. Raises ``ValueError`` when the seed is there but the
    SHA-256 is missing or differs from the regenerated matrix's, or when the
    file holds both the seed and a matrix.
    """
    if FROZEN_SEED not in weights:
        return weights
    if FROZEN_NAME in weights:
        raise ValueError(f"holds both {FROZEN_NAME!r} and {FROZEN_SEED!r}")
    if FROZEN_SHA256 not in weights:
        raise ValueError(f"holds {FROZEN_SEED!r} but no {FROZEN_SHA256!r}")
    matrix = frozen_projection(int(np.asarray(weights[FROZEN_SEED])))
    want = str(np.asarray(weights[FROZEN_SHA256]))
    got = array_sha256(matrix)
    if got != want:
        raise ValueError(f"the frozen projection of seed {int(np.asarray(weights[FROZEN_SEED]))} "
                         f"has SHA-256 {got[:16]}..., the file expects {want[:16]}... "
                         "(this NumPy draws other random numbers)")
    out = {k: v for k, v in weights.items() if k not in (FROZEN_SEED, FROZEN_SHA256)}
    out[FROZEN_NAME] = matrix
    return out


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, np.float32(0.0), out=x)


def _l2(x: np.ndarray, axis: int) -> np.ndarray:
    """x / max(||x||, 1e-12) along ``axis`` (F.normalize's rule)."""
    norm = np.sqrt(np.sum(x * x, axis=axis, keepdims=True))
    return x / np.maximum(norm, np.float32(NORM_EPS))


def _softmax(x: np.ndarray, axis: int) -> np.ndarray:
    z = np.exp(x - x.max(axis=axis, keepdims=True))
    return z / z.sum(axis=axis, keepdims=True)


def _layer_norm(x: np.ndarray, gamma: np.ndarray, beta: np.ndarray) -> np.ndarray:
    mean = x.mean(axis=-1, keepdims=True)
    var = ((x - mean) ** 2).mean(axis=-1, keepdims=True)
    return (x - mean) / np.sqrt(var + np.float32(LN_EPS)) * gamma + beta


def column_tokens(w: dict, images: np.ndarray) -> np.ndarray:
    """``(B, W, 128)`` per-column features after the eleven convolutions and ReLUs."""
    x = np.asarray(images, dtype=np.float32)  # (B, C, H, W)
    if x.ndim != 4:
        raise ValueError(f"expected (B, C, H, W) range images, got shape {x.shape}")
    x = np.ascontiguousarray(x.transpose(0, 3, 2, 1))  # (B, W, H, C)
    for n, (c_in, c_out, k, s) in enumerate(CONVS, start=1):
        kern = w[f"conv{n}.weight"][:, :, :, 0]  # (out, in, k)
        h_out = (x.shape[2] - k) // s + 1
        # rows h*s + i for each tap i: (B, W, H_out, k, C) against (k, C, out)
        taps = np.stack([x[:, :, i: i + s * (h_out - 1) + 1: s, :] for i in range(k)], axis=3)
        flat = taps.reshape(-1, k * c_in)  # one 2-D product (a 4-D one loops over small ones)
        out = flat @ np.ascontiguousarray(kern.transpose(2, 1, 0).reshape(k * c_in, c_out))
        x = _relu(out).reshape(*taps.shape[:3], c_out)
    if x.shape[2] != 1:
        raise ValueError(f"range images of height {images.shape[2]} leave {x.shape[2]} rows "
                         "after the convolutions; the network needs 1 (64 rows)")
    return x[:, :, 0, :]


def encoder_layer(w: dict, x: np.ndarray) -> np.ndarray:
    """One post-norm transformer encoder layer on ``(B, S, 256)`` tokens."""
    b, s, d = x.shape
    hd = d // HEADS
    qkv = x @ w[_TF + "self_attn.in_proj_weight"].T + w[_TF + "self_attn.in_proj_bias"]
    q, k, v = (qkv[..., i * d:(i + 1) * d].reshape(b, s, HEADS, hd).transpose(0, 2, 1, 3)
               for i in range(3))
    scores = (q @ k.transpose(0, 1, 3, 2)) / np.float32(np.sqrt(hd))
    att = _softmax(scores, axis=-1) @ v  # (B, heads, S, hd)
    att = att.transpose(0, 2, 1, 3).reshape(b, s, d)
    att = att @ w[_TF + "self_attn.out_proj.weight"].T + w[_TF + "self_attn.out_proj.bias"]
    x = _layer_norm(x + att, w[_TF + "norm1.weight"], w[_TF + "norm1.bias"])
    ff = _relu(x @ w[_TF + "linear1.weight"].T + w[_TF + "linear1.bias"])
    ff = ff @ w[_TF + "linear2.weight"].T + w[_TF + "linear2.bias"]
    return _layer_norm(x + ff, w[_TF + "norm2.weight"], w[_TF + "norm2.bias"])


def netvlad(w: dict, x: np.ndarray) -> np.ndarray:
    """NetVLAD with context gating: ``(B, S, 1024)`` unit tokens to ``(B, 256)``."""
    assign = _softmax(x @ w[_VLAD + "cluster_weights"] + w[_VLAD + "cluster_biases"], axis=2)
    centres = assign.sum(axis=1)[:, None, :] * w[_VLAD + "cluster_weights2"]  # (B, F, K)
    vlad = x.transpose(0, 2, 1) @ assign - centres  # (B, F, K)
    vlad = _l2(vlad, axis=1).reshape(len(x), -1)  # feature-major, as the authors flatten
    vlad = _l2(vlad, axis=1) @ w[_VLAD + "hidden1_weights"]
    gates = vlad @ w[_VLAD + "context_gating.gating_weights"] + \
        w[_VLAD + "context_gating.gating_biases"]
    return vlad * (1.0 / (1.0 + np.exp(-gates)))


def forward(w: dict, images: np.ndarray) -> np.ndarray:
    """``(B, 256)`` float32 unit descriptors of ``(B, 1, H, W)`` range images."""
    tokens = column_tokens(w, images)  # (B, W, 128)
    first = _relu(tokens @ w["convLast1.weight"][:, :, 0, 0].T)  # (B, W, 256)
    mixed = encoder_layer(w, first)
    both = np.concatenate([first, mixed], axis=2)  # channels: before, then after
    feat = _l2(_relu(both @ w["convLast2.weight"][:, :, 0, 0].T), axis=2)
    return _l2(netvlad(w, feat), axis=1).astype(np.float32)
