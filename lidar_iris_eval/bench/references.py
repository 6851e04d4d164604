"""The per-pair reference loops, each owned by its descriptor's sub-package.

Every built-in descriptor has a ``reference_loop`` module beside its kernels
with ``prepare(record, params)`` (per-frame work a database would store once,
not timed) and ``reference_distance(a, b, params) -> (distance, shift)``, a
slow, obvious implementation written independently of the kernels. This
module only looks them up and times them; the descriptor tests use the same
functions, so there is one copy of each.
"""

from __future__ import annotations

import importlib
import time
from types import ModuleType

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError


def reference_module(name: str) -> ModuleType | None:
    """The ``reference_loop`` module in descriptor ``name``'s folder, or None if it has none."""
    from lidar_iris_eval.descriptors import method_module

    module = method_module(name, "reference_loop")
    return importlib.import_module(module) if module else None


def reference_loop(desc: Descriptor, descs: np.ndarray, pairs: np.ndarray):
    """Distances of ``pairs`` by the reference per-pair implementation, and its time.

    Per-frame preparation that a real database would store once (LiDAR Iris's
    unpacked maps) is done before the clock starts; the timed part is a plain
    Python loop calling the single-pair formula.

    Returns
    -------
    (distances, seconds, cpu_seconds) or None when no reference exists for
    this descriptor.
    """
    module = reference_module(desc.name)
    if module is None:
        return None
    prepared = {int(i): module.prepare(descs[int(i)], desc.params) for i in np.unique(pairs)}
    one = module.reference_distance
    wall, cpu = time.perf_counter(), time.process_time()
    out = np.array([one(prepared[int(i)], prepared[int(j)], desc.params)[0] for i, j in pairs],
                   dtype=np.float64)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def reference_distance(desc: Descriptor, a, b) -> float:
    """The reference per-pair distance of two descriptors (no yaw), for spot checks."""
    module = reference_module(desc.name)
    if module is None:
        raise LirisError(f"descriptor {desc.name}", "no reference per-pair implementation")
    prep = module.prepare
    return module.reference_distance(prep(a, desc.params), prep(b, desc.params), desc.params)[0]


def lidar_iris_reference(a, b, features_a, features_b, params) -> float:
    """LiDAR Iris reference distance from records and their ``binary_features`` maps."""
    module = reference_module("lidar-iris")
    return module.reference_distance((a, features_a), (b, features_b), params)[0]


def scan_context_reference(q, c, params) -> float:
    """Scan Context reference distance of two records (nan when no shift is usable)."""
    module = reference_module("scan-context")
    return module.reference_distance(module.prepare(q, params), module.prepare(c, params),
                                     params)[0]


def m2dp_reference(a, b, params=None) -> float:
    """Euclidean distance of two M2DP vectors."""
    return reference_module("m2dp").reference_distance(a, b, params)[0]


def esf_reference(a, b, params=None) -> float:
    """L1 distance of two ESF histograms."""
    return reference_module("esf").reference_distance(a, b, params)[0]
