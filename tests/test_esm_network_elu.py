"""The network's vectorised ELU equals the C library's ``expm1f`` bit for bit.

The shipped embeddings (and so every ESM localisation) were fixed with numba's
``np.expm1``, a call into the C library per element; ``network._elu1`` is
glibc's float algorithm written out without branches. All 2**31 negative
float32 bit patterns were compared once (glibc 2.36); here a sample that
covers every branch and its boundaries.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.descriptors.esm import network


def _bits(values) -> np.ndarray:
    return np.asarray(values, np.float32).view(np.uint32)


def test_elu_equals_the_c_library_expm1f_bit_for_bit():
    rng = np.random.default_rng(0)
    # random bit patterns of every exponent (NaNs, infinities, subnormals, both signs)
    raw = rng.integers(0, 2**32, 400_000, dtype=np.uint64).astype(np.uint32).view(np.float32)
    # dense around the branch limits: 2**-25, ln2 / 2, 1.5 ln2, 27 ln2, 88.72, and 0
    edges = np.concatenate([np.array([b], np.uint32).view(np.float32) for b in
                            (0x33000000, 0x3EB17218, 0x3F851592, 0x4195B844, 0x42B17218,
                             0x00000001, 0x3F800000)])
    near = (edges.view(np.uint32)[:, None].astype(np.int64)
            + np.arange(-2000, 2001)[None, :]).clip(0, 0x7F800000).astype(np.uint32)
    near = near.reshape(-1).view(np.float32)
    # the network's range: normal values of a few units
    typical = (rng.standard_normal(400_000) * 4).astype(np.float32)
    x = np.concatenate([raw, near, -near, typical,
                        np.array([-np.inf, np.inf, -0.0, 0.0], np.float32)])
    assert x.dtype == np.float32
    ours, libm = x.copy(), x.copy()
    network._elu_inplace(ours)
    network._elu_inplace_libm(libm)
    nan = np.isnan(x)
    assert np.array_equal(_bits(ours[~nan]), _bits(libm[~nan]))
    assert np.array_equal(_bits(ours[nan]), _bits(x[nan]))  # NaNs pass through untouched
    assert np.array_equal(network.elu(x[~nan]), np.where(x[~nan] < 0, libm[~nan], x[~nan]))
