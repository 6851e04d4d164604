"""BEVPlace++'s global-descriptor network, inference in NumPy (no deep-learning package).

Architecture (``REIN.py`` of zjuluolun/BEVPlace2, MIT; read for the numbers
only), on ``(B, 3, 201, 201)`` BEV images (:mod:`.bev`):

* **rotation-equivariant module (REM)**: for each of ``R = 8`` angles
  ``a_i = -i 360 / R`` degrees, the image is warped by ``affine_grid`` with
  ``theta = [[cos a_i, -sin a_i, 0], [sin a_i, cos a_i, 0]]`` and
  ``grid_sample`` (bicubic, ``align_corners=True``, zeros outside), passed
  through the encoder, and the ``(128, 26, 26)`` feature map warped back with
  the inverse rotation (same sampler); the element-wise maximum over the eight
  maps is kept. The image is turned about its centre in normalised
  coordinates, so the maximum is invariant to turns of the scan by multiples of
  45 degrees up to resampling;
* **encoder**: ResNet-34 up to ``layer2`` (torchvision's ``children()[:-4]``):
  ``conv1`` 7 x 7 / 2 (3 -> 64, pad 3), batch norm, ReLU, max-pool 3 x 3 / 2
  (pad 1), ``layer1`` (3 basic blocks, 64), ``layer2`` (4 basic blocks, 128,
  the first with stride 2 and a 1 x 1 / 2 projection); batch norm in eval mode
  (running statistics, eps 1e-5). 201 -> 101 -> 51 -> 51 -> 26;
* the maximum map resampled to ``(H // 4) x (W // 4) = 50 x 50`` (identity
  ``affine_grid``, bicubic, ``align_corners=True``) and L2-normalised per
  location (``F.normalize``, eps 1e-12);
* **NetVLAD**, 64 clusters of 128-d: soft assignment ``softmax_k(W x)`` (a
  bias-free 1 x 1 convolution), residuals to the centroids summed over the
  2500 locations, intra-normalised per cluster, flattened cluster-major (index
  ``k * 128 + c``) and L2-normalised: an 8192-d unit vector, compared by the
  authors with faiss' ``IndexFlatL2`` (squared L2).

The local-feature branch (the REM's second output: the same maximum map
resampled to the full 201 x 201 and L2-normalised per pixel) is evaluated
at the keypoints only (:func:`local_features`), for the RANSAC pose
(:mod:`.pose`).

Weights are a dict of float32 arrays under the authors' ``state_dict`` names
(``rem.encoder.0.weight``, ``rem.encoder.4.0.bn1.running_var``,
``pooling.centroids``, ...), so their ``model_best.pth.tar`` is read as is.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import sparse
from scipy.linalg import blas

ROTATIONS, CLUSTERS, DIM = 8, 64, 128
BN_EPS, NORM_EPS, CUBIC_A = 1e-5, 1e-12, -0.75
#: (prefix, blocks, channels in, channels out, stride of the first block)
LAYERS = (("rem.encoder.4", 3, 64, 64, 1), ("rem.encoder.5", 4, 64, 128, 2))
_NORM = ("weight", "bias", "running_mean", "running_var")


def shapes() -> dict[str, tuple[int, ...]]:
    """Every weight the forward pass reads and its shape (the authors' names)."""
    out: dict[str, tuple[int, ...]] = {"rem.encoder.0.weight": (64, 3, 7, 7)}
    out.update({f"rem.encoder.1.{n}": (64,) for n in _NORM})
    for prefix, blocks, c_in, c_out, stride in LAYERS:
        for b in range(blocks):
            first_in = c_in if b == 0 else c_out
            p = f"{prefix}.{b}."
            out[p + "conv1.weight"] = (c_out, first_in, 3, 3)
            out.update({p + f"bn1.{n}": (c_out,) for n in _NORM})
            out[p + "conv2.weight"] = (c_out, c_out, 3, 3)
            out.update({p + f"bn2.{n}": (c_out,) for n in _NORM})
            if b == 0 and (stride != 1 or c_in != c_out):
                out[p + "downsample.0.weight"] = (c_out, c_in, 1, 1)
                out.update({p + f"downsample.1.{n}": (c_out,) for n in _NORM})
    out["pooling.conv.weight"] = (CLUSTERS, DIM, 1, 1)
    out["pooling.centroids"] = (CLUSTERS, DIM)
    return out


def random_weights(seed: int = 0) -> dict[str, np.ndarray]:
    """Deterministic random weights (NOT a trained model; see MODEL_CARD.md).

    Convolutions N(0, 2 / fan_in) (He, before a ReLU); batch-norm scales
    U(0.5, 1.5), shifts and running means N(0, 0.1^2), running variances
    U(0.5, 1.5) (not the identity, so the equality tests exercise every term).
    NetVLAD as the authors' ``init_params`` shapes it from k-means centres:
    centroids are random non-negative unit vectors (the features are unit and
    non-negative after the ReLU), the assignment weights ``10 x`` the centroids.
    ``torch.rand`` centroids in [0, 1)^128 would sit far from every unit feature,
    and the residuals, dominated by the centroids, would make all descriptors
    nearly equal.
    """
    rng = np.random.default_rng(seed)
    w: dict[str, np.ndarray] = {}
    for name, shape in shapes().items():
        if name.startswith("pooling"):
            continue
        if name.endswith(".weight") and len(shape) == 4:
            arr = rng.standard_normal(shape) * np.sqrt(2.0 / int(np.prod(shape[1:])))
        elif name.endswith(("running_var", ".weight")):
            arr = rng.uniform(0.5, 1.5, shape)
        else:  # bias, running_mean
            arr = rng.standard_normal(shape) * 0.1
        w[name] = arr.astype(np.float32)
    cent = np.abs(rng.standard_normal((CLUSTERS, DIM)))
    cent /= np.linalg.norm(cent, axis=1, keepdims=True)
    w["pooling.centroids"] = cent.astype(np.float32)
    w["pooling.conv.weight"] = (10.0 * cent)[:, :, None, None].astype(np.float32)
    return w




# ------------------------------------------------------------------ sampling


def angles(rotations: int = ROTATIONS) -> np.ndarray:
    """The authors' float32 angles ``-arange(0, 359.00001, 360 / R) / 180 * pi``."""
    steps = np.arange(0, 359.00001, 360.0 / rotations, dtype=np.float32)
    return (-steps / np.float32(180.0)) * np.float32(np.pi)


def _cubic_weights(t: np.ndarray) -> np.ndarray:
    """(4, ...) Keys cubic-convolution weights (A = -0.75, as PyTorch) of taps -1..2."""
    a = np.float32(CUBIC_A)

    def near(x):  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    one = np.float32(1.0)
    return np.stack([far(t + one), near(t), near(one - t), far(np.float32(2.0) - t)])


@functools.lru_cache(maxsize=64)
def sampler(theta: tuple[float, ...], size_in: tuple[int, int],
            size_out: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``affine_grid`` + bicubic ``grid_sample`` (``align_corners=True``, zero padding)
    as 16 taps per output pixel: ``(16, P)`` flat input indices and float32 weights.

    ``theta`` is the 2 x 3 matrix (row-major, float32 values) mapping output to
    input normalised coordinates; taps outside the input get weight 0.
    """
    t = np.asarray(theta, dtype=np.float32).reshape(2, 3)
    (h_in, w_in), (h_out, w_out) = size_in, size_out
    xs = np.linspace(-1, 1, w_out, dtype=np.float32) if w_out > 1 else np.array([-1.0],
                                                                                np.float32)
    ys = np.linspace(-1, 1, h_out, dtype=np.float32) if h_out > 1 else np.array([-1.0],
                                                                                np.float32)
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    u = t[0, 0] * gx + t[0, 1] * gy + t[0, 2]
    v = t[1, 0] * gx + t[1, 1] * gy + t[1, 2]
    ix = (u + np.float32(1)) / np.float32(2) * np.float32(w_in - 1)
    iy = (v + np.float32(1)) / np.float32(2) * np.float32(h_in - 1)
    x0, y0 = np.floor(ix), np.floor(iy)
    wx, wy = _cubic_weights(ix - x0), _cubic_weights(iy - y0)  # (4, H, W) each
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    index = np.zeros((16, h_out * w_out), dtype=np.int64)
    weight = np.zeros((16, h_out * w_out), dtype=np.float32)
    for i in range(4):
        yy = y0 + (i - 1)
        for j in range(4):
            xx = x0 + (j - 1)
            inside = (yy >= 0) & (yy < h_in) & (xx >= 0) & (xx < w_in)
            k = 4 * i + j
            index[k] = np.where(inside, yy * w_in + xx, 0).reshape(-1)
            weight[k] = np.where(inside, wy[i] * wx[j], 0).reshape(-1)
    index.setflags(write=False)
    weight.setflags(write=False)
    return index, weight


def rotation_theta(angle: np.float32) -> tuple[float, ...]:
    """The authors' ``aff`` for a warp by ``angle`` (float32 cos and sin)."""
    c, s = np.cos(np.float32(angle)), np.sin(np.float32(angle))
    return (float(c), float(s), 0.0, float(-s), float(c), 0.0)


@functools.lru_cache(maxsize=64)
def _sampling_matrix(theta: tuple[float, ...], size_in: tuple[int, int],
                     size_out: tuple[int, int]) -> sparse.csr_matrix:
    """:func:`sampler` as a sparse ``(P_out, P_in)`` matrix (taps outside dropped)."""
    index, weight = sampler(theta, size_in, size_out)
    rows = np.broadcast_to(np.arange(index.shape[1]), index.shape)
    keep = weight != 0
    return sparse.csr_matrix((weight[keep], (rows[keep], index[keep])),
                             shape=(index.shape[1], size_in[0] * size_in[1]),
                             dtype=np.float32)


def warp(x: np.ndarray, theta: tuple[float, ...], size_out: tuple[int, int]) -> np.ndarray:
    """Bicubic resampling of ``(N, H, W, C)`` maps to ``(N, h_out, w_out, C)``.

    One sparse product (16 taps a row) for all maps and channels at once.
    """
    n, h, w, c = x.shape
    mat = _sampling_matrix(tuple(theta), (h, w), tuple(size_out))
    flat = np.ascontiguousarray(x.reshape(n, h * w, c).transpose(1, 0, 2)).reshape(h * w, n * c)
    out = np.asarray(mat @ flat, dtype=np.float32).reshape(-1, n, c).transpose(1, 0, 2)
    return np.ascontiguousarray(out).reshape(n, size_out[0], size_out[1], c)


# ------------------------------------------------------------------ encoder


def _gemm_add(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """``out += a @ b`` for C-contiguous float32 ``out``, ``a``, ``b``, with no temporary.

    BLAS ``sgemm`` with ``beta = 1`` on the transposes (C-contiguous is Fortran
    order transposed, so no copy): ``out.T += b.T @ a.T``. Falls back to the
    product and ``+=`` if the wrapper would have copied ``out``.
    """
    target = out.T
    if out.dtype == a.dtype == b.dtype == np.float32 and target.flags.f_contiguous \
            and a.flags.c_contiguous and b.flags.c_contiguous:
        done = blas.sgemm(1.0, b.T, a.T, beta=1.0, c=target, overwrite_c=True)
        if np.shares_memory(done, out):
            return
    out += a @ b


def _conv(x: np.ndarray, kernel: np.ndarray, stride: int, pad: int) -> np.ndarray:
    """2-D convolution of ``(N, H, W, C)`` by ``(out, C, k, k)``, no bias.

    Stride 1 (14 of the 17 convolutions): one GEMM per tap on contiguous slices
    of the flattened padded batch (a tap is a fixed offset ``i * W_pad + j``
    there), summed, then the valid rows kept: no im2col copy, whose scattered
    writes cost 7x the GEMMs. Each tap's GEMM adds into the output itself
    (:func:`_gemm_add`, BLAS ``beta = 1``): the same sums as a product then
    ``+=`` (bit for bit, tests/test_bevplace.py), without the temporary and its
    extra pass (stride-1 convolutions 1.1-1.2x faster). Strided ones: im2col
    and one GEMM.
    """
    n, h, w, c = x.shape
    c_out, _, k, _ = kernel.shape
    if pad:
        x = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    hp, wp = h + 2 * pad, w + 2 * pad
    h_out, w_out = (hp - k) // stride + 1, (wp - k) // stride + 1
    if stride == 1:
        flat = x.reshape(n * hp * wp, c)
        span = n * hp * wp - ((k - 1) * wp + (k - 1))
        taps = np.ascontiguousarray(kernel.transpose(2, 3, 1, 0))  # (k, k, C, out)
        out = np.zeros((n * hp * wp, c_out), dtype=np.float32)
        for i in range(k):
            for j in range(k):
                off = i * wp + j
                _gemm_add(out[:span], flat[off: off + span], taps[i, j])
        return out.reshape(n, hp, wp, c_out)[:, :h_out, :w_out]
    # im2col: for each output pixel and kernel row, the k pixels of a padded row are
    # k * C contiguous floats, so the copy moves runs of k * C (not C) floats
    x = np.ascontiguousarray(x, dtype=np.float32)
    s_n, s_h, s_w, s_c = x.strides
    view = np.lib.stride_tricks.as_strided(
        x, shape=(n, h_out, w_out, k, k * c),
        strides=(s_n, stride * s_h, stride * s_w, s_h, s_c), writeable=False)
    cols = view.reshape(n * h_out * w_out, k * k * c)  # one copy, (i, j, channel) order
    mat = np.ascontiguousarray(kernel.transpose(2, 3, 1, 0).reshape(k * k * c, c_out))
    return (cols @ mat).reshape(n, h_out, w_out, c_out)


def _conv_norm(w: dict, conv: str, norm: str, x: np.ndarray, stride: int,
               pad: int) -> np.ndarray:
    """Convolution then batch norm in eval mode (running statistics, eps 1e-5).

    The norm's per-channel scale ``gamma / sqrt(var + eps)`` is folded into the
    kernel and its shift ``beta - mean * scale`` added after: one pass over the
    output instead of two.
    """
    scale = w[norm + "weight"] / np.sqrt(w[norm + "running_var"] + np.float32(BN_EPS))
    shift = w[norm + "bias"] - w[norm + "running_mean"] * scale
    out = _conv(x, w[conv] * scale[:, None, None, None], stride, pad)
    out += shift
    return out


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, np.float32(0.0), out=x)


def _maxpool(x: np.ndarray) -> np.ndarray:
    """3 x 3 max-pool, stride 2, padding 1 (padding never wins)."""
    n, h, wd, c = x.shape
    xp = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), constant_values=-np.inf)
    h_out, w_out = (h - 1) // 2 + 1, (wd - 1) // 2 + 1
    out = np.full((n, h_out, w_out, c), -np.inf, dtype=np.float32)
    for i in range(3):
        for j in range(3):
            np.maximum(out, xp[:, i: i + 2 * (h_out - 1) + 1: 2, j: j + 2 * (w_out - 1) + 1: 2],
                       out=out)
    return out


def encoder(w: dict, x: np.ndarray) -> np.ndarray:
    """ResNet-34 up to ``layer2`` on ``(N, H, W, 3)``: ``(N, H/8, W/8, 128)`` (rounded up)."""
    x = _maxpool(_relu(_conv_norm(w, "rem.encoder.0.weight", "rem.encoder.1.", x, 2, 3)))
    for prefix, blocks, _c_in, _c_out, stride in LAYERS:
        for b in range(blocks):
            p = f"{prefix}.{b}."
            s = stride if b == 0 else 1
            y = _relu(_conv_norm(w, p + "conv1.weight", p + "bn1.", x, s, 1))
            y = _conv_norm(w, p + "conv2.weight", p + "bn2.", y, 1, 1)
            if p + "downsample.0.weight" in w:
                x = _conv_norm(w, p + "downsample.0.weight", p + "downsample.1.", x, s, 0)
            y += x
            x = _relu(y)
    return x


# ------------------------------------------------------------------ forward


def _l2(x: np.ndarray, axis: int) -> np.ndarray:
    """x / max(||x||, 1e-12) along ``axis`` (F.normalize's rule)."""
    norm = np.sqrt(np.sum(x * x, axis=axis, keepdims=True))
    return x / np.maximum(norm, np.float32(NORM_EPS))


def rem_features(w: dict, images: np.ndarray, rotations: int = ROTATIONS) -> np.ndarray:
    """``(B, H//4, W//4, 128)`` unit local features for NetVLAD (the REM's first output)."""
    return netvlad_input(rem_maximum(w, images, rotations), np.shape(images)[2:])


def netvlad_input(best: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The maximum map resampled to ``(H//4, W//4)`` and L2-normalised per location."""
    h, wd = size
    grid = warp(best, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0), (h // 4, wd // 4))
    return _l2(grid, axis=3)


def rem_maximum(w: dict, images: np.ndarray, rotations: int = ROTATIONS) -> np.ndarray:
    """``(B, h8, w8, 128)`` element-wise maximum of the warped-back encoder maps.

    What both of the REM's outputs resample: NetVLAD's input (``H//4``) and the
    local features of the keypoints (``H``, :func:`local_features`).
    """
    x = np.asarray(images, dtype=np.float32)
    if x.ndim != 4 or x.shape[1] != 3:
        raise ValueError(f"expected (B, 3, H, W) BEV images, got shape {x.shape}")
    b, _, h, wd = x.shape
    x = np.ascontiguousarray(x.transpose(0, 2, 3, 1))  # (B, H, W, 3)
    turns = angles(rotations)
    warped = np.concatenate([warp(x, rotation_theta(-a), (h, wd)) for a in turns])
    feats = encoder(w, warped)  # (R * B, h8, w8, 128), rotation-major
    size = feats.shape[1:3]
    best = None
    for r, a in enumerate(turns):
        back = warp(feats[r * b:(r + 1) * b], rotation_theta(a), size)
        best = back if best is None else np.maximum(best, back)
    return best


def local_features(best: np.ndarray, pixels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(K, 128)`` float32 unit local features of one scan at ``(K, 2)`` (row, col) pixels.

    The REM's second output is the maximum map ``best`` (``(h8, w8, 128)``)
    resampled to the input's full ``size`` (identity ``affine_grid``, bicubic,
    ``align_corners=True``) and L2-normalised per pixel; the authors then read
    it at the keypoints. Only those pixels are computed here (the same 16
    taps of :func:`sampler` per pixel), not the 201 x 201 x 128 map.
    """
    px = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    h8, w8, c = best.shape
    if len(px) == 0:
        return np.zeros((0, c), dtype=np.float32)
    index, weight = sampler((1.0, 0.0, 0.0, 0.0, 1.0, 0.0), (h8, w8), tuple(size))
    cols = px[:, 0] * int(size[1]) + px[:, 1]
    flat = best.reshape(h8 * w8, c)
    out = np.zeros((len(px), c), dtype=np.float32)
    for k in range(index.shape[0]):
        out += weight[k, cols][:, None] * flat[index[k, cols]]
    return _l2(out, axis=1)


def netvlad(w: dict, x: np.ndarray) -> np.ndarray:
    """NetVLAD on ``(B, N, 128)`` unit features: ``(B, 8192)`` unit vectors."""
    logits = x @ w["pooling.conv.weight"][:, :, 0, 0].T  # (B, N, K)
    z = np.exp(logits - logits.max(axis=2, keepdims=True))
    assign = z / z.sum(axis=2, keepdims=True)
    cent = w["pooling.centroids"]  # (K, C)
    vlad = assign.transpose(0, 2, 1) @ x - assign.sum(axis=1)[:, :, None] * cent  # (B, K, C)
    vlad = _l2(vlad, axis=2).reshape(len(x), -1)  # cluster-major, as the authors flatten
    return _l2(vlad, axis=1)


def forward(w: dict, images: np.ndarray, rotations: int = ROTATIONS) -> np.ndarray:
    """``(B, 8192)`` float32 unit global descriptors of ``(B, 3, H, W)`` BEV images."""
    return forward_with_maximum(w, images, rotations)[0]


def forward_with_maximum(w: dict, images: np.ndarray, rotations: int = ROTATIONS
                         ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`forward`'s descriptors and the REM's maximum map (for :func:`local_features`)."""
    best = rem_maximum(w, images, rotations)
    feats = netvlad_input(best, np.shape(images)[2:])
    b = feats.shape[0]
    return netvlad(w, feats.reshape(b, -1, DIM)).astype(np.float32), best
