"""ESM's training data from local maps, the in-batch negative rule, resumable training,
the weights parameter in the cache key and the segment-retrieval AUC command."""

from __future__ import annotations

import argparse
import json
import shutil
from collections import deque

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm import network
from lidar_iris_eval.descriptors.esm.dataset import (
    SegmentSet,
    negative_candidates,
    simulate_local_map_segments,
    true_pairs,
)
from lidar_iris_eval.errors import LirisError

WINDOW = 30
TINY = dict(frames=100, seed=5, sensor="hdl64", azimuth_steps=360, route="mixed",
            block_size=(18.0, 24.0), n_moving_cars=0)


@pytest.fixture(scope="module")
def tiny_local_maps():
    return simulate_local_map_segments(TINY, every=10, window=WINDOW, progress=False)


def test_local_map_segments_and_pairs_on_a_tiny_world(tiny_local_maps):
    d = tiny_local_maps
    assert len(d) > 20 and set(np.unique(d.frame) % 10) == {0}
    assert np.all((d.purity > 0) & (d.purity <= 1)) and np.all(d.object_id >= 0)
    # the run-time segmenter's size limits (stored points are capped at 1024)
    sizes = np.diff(d.offsets)
    assert sizes.min() >= 100 and sizes.max() <= 1024
    pairs = true_pairs(d, min_frame_gap=WINDOW)
    assert len(pairs) > 0
    a, b = pairs[:, 0], pairs[:, 1]
    # positives: the same object, the same piece (centroids <= 2 m), local maps >= E apart
    assert np.all(d.object_id[a] == d.object_id[b]) and np.all(d.object_id[a] > 0)
    assert np.all(np.abs(d.frame[a] - d.frame[b]) >= WINDOW)
    assert np.all(np.linalg.norm(d.world[a] - d.world[b], axis=1) <= 2.0)


def test_local_map_tags_agree_with_the_nearest_simulated_points(tiny_local_maps):
    """Independent tagging: each segment voxel takes the object id of the nearest
    filtered point of the window's scans (a KD-tree); the majority equals the tag."""
    from scipy.spatial import cKDTree

    from lidar_iris_eval.localmaps import input_filter
    from lidar_iris_eval.simulate.pipeline import _NOISE, build_scenario
    from lidar_iris_eval.simulate.presets import resolve_config
    from lidar_iris_eval.simulate.sensors import simulate_scan

    cfg = resolve_config(None, TINY)
    scen = build_scenario(cfg)
    filt = input_filter("all")
    target = 60
    window: deque = deque()
    for i in range(target - WINDOW + 1, target + 1):
        rng = np.random.default_rng([cfg.seed, _NOISE, i])
        scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i), scen.poses[i],
                             rng, scen.sensor.grid.directions)
        keep = filt.mask(scan.points)
        pose = scen.poses[i]
        window.append((scan.points[keep, :3] @ pose[:3, :3].T + pose[:3, 3],
                       scen.object_ids(i, scan.row)[keep]))
    tree = cKDTree(np.concatenate([w[0] for w in window]))
    ids = np.concatenate([w[1] for w in window])
    d = tiny_local_maps
    rows = np.nonzero(d.frame == target)[0]
    assert len(rows) > 3
    agree = 0
    for s in rows:
        _, nn = tree.query(d.segment(s).astype(np.float64))
        vals, counts = np.unique(ids[nn], return_counts=True)
        agree += int(vals[np.argmax(counts)] == d.object_id[s])
    assert agree == len(rows)


def test_a_negative_is_another_object_of_the_same_class():
    coarse = np.array([1, 1, 2, 2, 3])
    objects = np.array([10, 11, 20, 20, 30])
    m = negative_candidates(coarse, objects)
    # anchor 0 (car 10): only car 11; anchor 2 (building 20): pair 3 shows the same
    # building, so no same-class negative: any other object (10, 11, 30)
    assert m[0].tolist() == [False, True, False, False, False]
    assert m[2].tolist() == [True, True, False, False, True]
    # anchor 4 has no other object of its class: every other object
    assert m[4].tolist() == [True, True, True, True, False]
    assert not m[np.arange(5), np.arange(5)].any()


def _toy_set(rng) -> SegmentSet:
    """4 objects (2 cars, 2 poles), each seen in frames 0 and 40 near the same place."""
    pts, offs, obj, coarse, frame, world = [], [0], [], [], [], []
    for o in range(4):
        shape = rng.normal(size=(150, 3)) * [1.0 + o, 0.5, 0.3 + 0.2 * o]
        for f in (0, 40):
            view = shape + rng.normal(scale=0.02, size=shape.shape)
            pts.append(view.astype(np.float32))
            offs.append(offs[-1] + len(view))
            obj.append(o + 1)
            coarse.append(1 if o < 2 else 4)
            frame.append(f)
            world.append([10.0 * o, 0.0, 0.0])
    n = len(obj)
    return SegmentSet(points=np.concatenate(pts), offsets=np.asarray(offs),
                      object_id=np.asarray(obj), coarse=np.asarray(coarse, np.int8),
                      frame=np.asarray(frame), world=np.asarray(world), purity=np.ones(n),
                      world_id=np.zeros(n, np.int64))


def _args(work, steps):
    return argparse.Namespace(work=work, threads=1, seed=3, steps=steps, batch=4, lr=1e-3,
                              minutes=60.0, eval_every=60.0, checkpoint_every=60.0,
                              norm_scale=1.0, align_yaw=False, init=None, compare=None,
                              quality_steps=1, out=None, min_frame_gap=WINDOW)


def test_training_resumes_where_it_stopped(tmp_path):
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.esm import training

    data = _toy_set(np.random.default_rng(0))
    assert len(true_pairs(data, min_frame_gap=WINDOW)) == 4
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    training.run(data, None, _args(a, 1), {"train"}, 0.0)  # stopped after 1 step
    training.run(data, None, _args(a, 2), {"train"}, 0.0)  # the same command continues
    training.run(data, None, _args(b, 2), {"train"}, 0.0)  # 2 steps in one go
    sa = torch.load(a / "state.pt", weights_only=False)
    sb = torch.load(b / "state.pt", weights_only=False)
    assert sa["progress"]["step"] == 2 and len(sa["progress"]["hist"]) == 2
    assert sa["progress"]["hist"] == sb["progress"]["hist"]  # random states resumed
    for key, val in sa["net"].items():
        assert torch.equal(val, sb["net"][key]), key
    assert json.loads((a / "train_log.json").read_text())["steps"] == 2
    # a finished run rerun unchanged does not train further
    training.run(data, None, _args(a, 2), {"train"}, 0.0)
    assert torch.load(a / "state.pt", weights_only=False)["progress"]["step"] == 2


def test_weights_parameter_reaches_the_cache_key_and_run_info(tmp_path):
    from lidar_iris_eval.extract import descriptor_code_hash

    if not network.WEIGHTS_FILE.is_file():
        pytest.skip("no ESM weights shipped")
    copy = tmp_path / "copy.npz"
    shutil.copy(network.WEIGHTS_FILE, copy)
    shipped = get_descriptor("esm", "single-scan", weights="esm_weights.npz")
    same = get_descriptor("esm", "single-scan", weights=str(copy))
    assert shipped.weights_path == network.WEIGHTS_FILE
    assert descriptor_code_hash(shipped) == descriptor_code_hash(same)  # same bytes
    with np.load(copy) as z:
        w = {k: z[k] for k in z.files}
    w["q.b"] = w["q.b"] + 1.0
    np.savez(copy, **w)  # the file changed under the same name
    changed = get_descriptor("esm", "single-scan", weights=str(copy))
    assert descriptor_code_hash(changed) != descriptor_code_hash(shipped)
    info = changed.run_info()
    assert info["weights"] == "copy.npz" and info["weights_sha256"] == changed.cache_token()
    with pytest.raises(LirisError, match="esm.weights"):
        get_descriptor("esm", "single-scan", weights=str(tmp_path / "none.npz")).cache_token()


def test_auc_command_on_hand_made_segments(tmp_path, capsys):
    """Two objects seen twice >= 30 frames apart: a network that separates them by
    shape (a long and a round object) ranks both positives before the negatives."""
    from lidar_iris_eval.descriptors.esm import evaluate

    if not network.WEIGHTS_FILE.is_file():
        pytest.skip("no ESM weights shipped")
    data = _toy_set(np.random.default_rng(1))
    path = tmp_path / "segs.npz"
    data.save(path)
    out = evaluate.auc_report(path, ["esm_weights.npz"], gap=WINDOW)
    m = out["weights"]["esm_weights.npz"]
    # 4 true pairs; every other cross-frame pair (4 x 4 - 4 = 12) is a negative
    assert m["positives"] == 4 and m["negatives"] == 12 and m["queries"] == 8
    assert 0.0 <= m["auc"] <= 1.0
    with pytest.raises(SystemExit) as err:
        evaluate.main(["auc", str(tmp_path / "missing.npz")])
    assert err.value.code == 2
    assert "missing.npz" in capsys.readouterr().err
