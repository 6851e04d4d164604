"""Simulator per-point object ids (object_ids/NNNNNN.npy beside unchanged .label files)."""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.simulate.pipeline import simulate_sequence

GROUND = (40, 44, 48, 49, 60, 72)


def test_object_ids_beside_labels(tmp_path):
    out = simulate_sequence(tmp_path / "s", "tiny-mixed", frames=3)
    per_frame = []
    for i in range(3):
        n = (out / "velodyne" / f"{i:06d}.bin").stat().st_size // 16
        label = np.fromfile(out / "labels" / f"{i:06d}.label", dtype="<u4")
        ids = np.load(out / "object_ids" / f"{i:06d}.npy")
        assert ids.dtype == np.uint32 and len(ids) == len(label) == n
        cls, inst = label & 0xFFFF, label >> 16
        ground = np.isin(cls, GROUND)
        assert np.all(ids[ground] == 0) and np.all(ids[~ground] > 0)
        # cars keep their SemanticKITTI instance; one object id per instance and back
        for k in np.unique(inst[inst > 0]):
            assert len(np.unique(ids[inst == k])) == 1
            assert len(np.unique(inst[ids == ids[inst == k][0]])) == 1
        # "stuff" (instance 0) is now split into several physical objects
        assert len(np.unique(ids[(inst == 0) & ~ground])) > 5
        per_frame.append((cls, ids))
    # an object id means the same thing in every scan: same class set across frames
    classes: dict[int, set] = {}
    for cls, ids in per_frame:
        for o in np.unique(ids[ids > 0]):
            seen = set(np.unique(cls[ids == o]).tolist())
            assert seen <= {70, 71, 80, 81} or len(seen) == 1
            classes.setdefault(int(o), set()).update(seen)
    assert all(len(v) <= 2 for v in classes.values())


def test_labels_unchanged_by_object_ids(tmp_path):
    a = simulate_sequence(tmp_path / "a", "tiny-mixed", frames=2)
    b = simulate_sequence(tmp_path / "b", "tiny-mixed", frames=2)
    for sub, ext in (("labels", "label"), ("velodyne", "bin"), ("object_ids", "npy")):
        assert (a / sub / f"000001.{ext}").read_bytes() == (b / sub / f"000001.{ext}").read_bytes()
