"""ESF's compiled normalisation and single-geometry sampling equal the routes they replaced.

Both are bitwise: the normalisation keeps NumPy's float64 centroid and forms
every other value in float64 in the same order; the sampler keeps each
batch's geometry instead of recomputing it for the accepted triplets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esf import descriptor as esf
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.sensors import simulate_scan

_HERE = Path(__file__).resolve()
_SHARED = next((p / "shared" for p in _HERE.parents[2:4] if (p / "shared" / "data").is_dir()),
               None)


def _clouds():
    cfg = resolve_config("tiny-mixed", dict(sensor="hdl64", azimuth_steps=1024))
    scen = build_scenario(cfg)
    rng = np.random.default_rng(2)
    out = [simulate_scan(scen.sensor, scen.world.ground, scen.primitives(f), scen.poses[f],
                         rng).points for f in (0, len(scen.poses) // 2)]
    if _SHARED is not None:
        folder = _SHARED / "data" / "kitti" / "samples" / "00" / "velodyne"
        out += [np.fromfile(f, np.float32).reshape(-1, 4)[:, :3].copy()
                for f in sorted(folder.glob("*.bin"))]
    out += [rng.normal(size=(2000, 3)) * scale for scale in (1e-3, 1.0, 1e4)]  # float64 too
    return out


@pytest.fixture(scope="module")
def clouds():
    return _clouds()


def test_normalise_equals_numpy_route(clouds):
    for cloud in clouds:
        assert np.array_equal(esf.normalise(cloud), esf.normalise_numpy(cloud))
    with pytest.raises(LirisError, match="not all identical"):
        esf.normalise(np.ones((5, 3), np.float32))


def test_descriptor_equals_previous_sampling_route(clouds, monkeypatch):
    desc = get_descriptor("esf")
    new = [desc.compute(c) for c in clouds[:4]]
    monkeypatch.setattr(esf, "sample_triangles", esf.sample_triangles_previous)
    monkeypatch.setattr(esf, "normalise", esf.normalise_numpy)
    old = [desc.compute(c) for c in clouds[:4]]
    for a, b in zip(new, old, strict=True):
        assert np.array_equal(a, b) and a.shape == (640,)
