"""Natural worlds (``--world forest`` / ``park``): loops, seasons, geometry, golden output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_simulate_golden import fingerprint

from lidar_iris_eval.simulate import build_scenario, resolve_config, simulate_sequence
from lidar_iris_eval.simulate import labels as L
from lidar_iris_eval.simulate.nature import NATURE_STYLES
from lidar_iris_eval.simulate.raycast import BOX, CYLINDER, ELLIPSOID
from lidar_iris_eval.simulate.sensors import simulate_scan

#: (preset, options) of the golden fingerprints of the natural worlds (and push-broom swathes)
GOLDEN = {"forest": ("forest", dict(frames=6)),
          "forest-leaf-off": ("forest", dict(frames=6, season="leaf-off")),
          "park": ("park", dict(frames=6)),
          "forest-pushbroom": ("forest", dict(frames=20, azimuth_steps=64, pushbroom=3.0))}
#: rewrite with ``python tests/test_simulate_nature.py`` only for an intended change
GOLDEN_FILE = Path(__file__).parent / "data" / "simulate_golden_nature.npz"
#: worlds whose points move with the CPU: the push-broom lines' grazing rays change
#: with an ulp of NumPy's SIMD arithmetic (the golden file was written on an AVX-512
#: machine; an AVX2 one keeps 0.3 % fewer points, 2026-12-07), so only the poses,
#: times, calibration and point counts (within 1 %) are compared
CPU_SENSITIVE = {"forest-pushbroom"}


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_natural_world_output_is_unchanged(tmp_path, name):
    preset, options = GOLDEN[name]
    got = fingerprint(simulate_sequence(tmp_path / "seq", preset, **options))
    with np.load(GOLDEN_FILE) as golden:
        expected = {key: golden[f"{name}/{key}"] for key in got}
    np.testing.assert_allclose(got["text"], expected["text"], rtol=1e-9, atol=1e-12)
    if name in CPU_SENSITIVE:
        np.testing.assert_allclose(got["counts"], expected["counts"], rtol=0.01)
        return
    assert list(got["digests"]) == list(expected["digests"])
    np.testing.assert_array_equal(got["counts"], expected["counts"])
    np.testing.assert_allclose(got["sample"], expected["sample"], rtol=0, atol=1e-4)


@pytest.mark.parametrize("world", ["forest", "park"])
def test_the_route_revisits_itself(tmp_path, capsys, world):
    """The trail loop closes within 200 frames: liris gt finds revisit queries."""
    # a coarse azimuth grid: the loop is in the poses, not the scans
    code, out, err = run_cli(["simulate", tmp_path / world, "--world", world, "--azimuth-steps",
                              "128", "-q"], capsys)
    assert code == 0, err
    code, out, err = run_cli(["gt", tmp_path / world, "--json"], capsys)
    assert code == 0, err
    gt = json.loads(out)
    gt = gt[0] if isinstance(gt, list) else gt
    assert gt["revisit_queries"] > 20
    manifest = json.loads((tmp_path / world / "manifest.json").read_text())
    assert manifest["config"]["world_style"] == world
    assert set(manifest["classes"]) >= {str(L.TRUNK), str(L.VEGETATION), str(L.TERRAIN)}


def _scan_stats(preset: str, frame: int = 20, **overrides):
    cfg = resolve_config(preset, {"frames": 40, **overrides})
    scen = build_scenario(cfg)
    scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(frame),
                         scen.poses[frame], None)
    cls = scan.label & 0xFFFF
    ground = np.isin(cls, (L.ROAD, L.SIDEWALK, L.TERRAIN))
    return scen, scan, cls, ground


def test_forest_scans_differ_from_urban_ones():
    _, _, cls_u, ground_u = _scan_stats("tiny-mixed")
    scen, scan, cls_f, ground_f = _scan_stats("forest")
    # a street scan: buildings and cars, no trunks beyond street trees
    assert np.isin(cls_u, (L.BUILDING, L.CAR)).mean() > 0.02
    # a forest scan: no building, car or road; trunks and crowns are a large share
    assert not np.isin(cls_f, (L.BUILDING, L.CAR, L.ROAD, L.MOVING_CAR)).any()
    assert np.isin(cls_f, (L.TRUNK, L.VEGETATION)).mean() > 0.2
    assert (cls_f == L.TRUNK).mean() > 3 * (cls_u == L.TRUNK).mean()
    # hilly ground: the forest floor's heights (world frame) spread far more than a street's
    pts_w = scan.points[ground_f] @ scen.poses[20][:3, :3].T + scen.poses[20][:3, 3]
    near = np.linalg.norm(scan.points[ground_f, :2], axis=1) < 30
    assert np.ptp(pts_w[near, 2]) > 1.0


def test_the_platform_pitches_and_rolls_on_slopes():
    scen = build_scenario(resolve_config("forest", {}))
    up = scen.poses[:, :3, 2]
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
    assert np.percentile(tilt, 90) > 2.0  # slopes of several per cent
    step = np.linalg.norm(np.diff(scen.poses[:, :3, 3], axis=0), axis=1)
    assert np.median(step) < 0.7  # slow (urban presets: about 1 m a frame)
    # the sensor stays above the trail: no primitive contains it
    for i in range(0, len(scen.poses), 25):
        prims = scen.world.near(scen.poses[i, :2, 3], 3.0)
        rel = scen.poses[i, :3, 3] - prims.center
        inside = np.all(np.abs(rel) < prims.size, axis=1) & (prims.kind != ELLIPSOID)
        inside |= (prims.kind == ELLIPSOID) & (((rel / prims.size) ** 2).sum(1) < 1)
        assert not inside.any()


def _off_normal_deg(scen):
    """Angle between the sensor's up axis and the terrain normal under it, per frame."""
    g = scen.world.ground
    _, gx, gy = g.elevation(scen.poses[:, 0, 3], scen.poses[:, 1, 3])
    n = np.stack([-gx, -gy, np.ones_like(gx)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((n * scen.poses[:, :3, 2]).sum(1), -1, 1)))


def test_handheld_platform_is_lower_slower_and_sways():
    ugv = build_scenario(resolve_config("forest", {"frames": 120}))
    hand = build_scenario(resolve_config("forest", {"frames": 120, "platform": "handheld"}))
    for scen, height in ((ugv, 1.8), (hand, 1.5)):  # hdl32's mount, the walker's 1.5 m
        g = scen.world.ground.surface_height(scen.poses[:, 0, 3], scen.poses[:, 1, 3])
        # the sensor sits ``height`` along the tilted up axis: a little less vertically
        assert np.median(scen.poses[:, 2, 3] - g) == pytest.approx(height, abs=0.05)
    step_u = np.median(np.linalg.norm(np.diff(ugv.poses[:, :3, 3], axis=0), axis=1))
    step_h = np.median(np.linalg.norm(np.diff(hand.poses[:, :3, 3], axis=0), axis=1))
    assert step_h < 0.7 * step_u
    assert np.median(_off_normal_deg(hand)) > 2 * np.median(_off_normal_deg(ugv))
    np.testing.assert_array_equal(ugv.world.ground.height, hand.world.ground.height)


def test_trees_have_trunks_branches_and_crowns():
    world = build_scenario(resolve_config("forest", {"frames": 10})).world
    p, objects = world.prims, world.objects
    trunks = np.nonzero((p.label == L.TRUNK) & (p.kind == CYLINDER))[0]
    branches = (p.label == L.TRUNK) & (p.kind == BOX)  # branches and fallen logs
    crowns = (p.label == L.VEGETATION) & (p.kind == ELLIPSOID)
    tree_ids = np.unique(objects[trunks])
    with_branches = np.isin(tree_ids, objects[branches])
    with_crowns = np.isin(tree_ids, objects[crowns])
    assert len(tree_ids) > 500
    assert with_branches.mean() > 0.5 and with_crowns.mean() > 0.95
    # conifers (one trunk cylinder, stacked whorls) and broadleaf (trunk + leader)
    per_tree = np.bincount(objects[trunks])[tree_ids]
    assert (per_tree == 1).any() and (per_tree == 2).any()
    assert (p.label == L.OTHER_OBJECT).any()  # rocks


def test_leaf_off_is_the_same_forest_without_leaves():
    on = build_scenario(resolve_config("forest", {"frames": 10})).world
    off = build_scenario(resolve_config("forest", {"frames": 10, "season": "leaf-off"})).world
    np.testing.assert_array_equal(on.ground.height, off.ground.height)

    def rows(w, label):
        m = w.prims.label == label
        return {tuple(np.round(np.r_[w.prims.center[k], w.prims.size[k]], 6))
                for k in np.nonzero(m)[0]}

    for label in (L.TRUNK, L.OTHER_OBJECT):  # wood and rocks: identical
        assert rows(on, label) == rows(off, label)
    veg_on, veg_off = rows(on, L.VEGETATION), rows(off, L.VEGETATION)
    assert len(veg_off) < 0.6 * len(veg_on)
    # what stays green is evergreen (unchanged rows) or shrunk undergrowth (lower than 1 m)
    changed = veg_off - veg_on
    assert changed and all(r[5] < 1.0 for r in changed)
    # a leaf-off scan sees more wood and less foliage from the same pose
    def shares(season):
        _, _, cls, _ = _scan_stats("forest", season=season)
        return (cls == L.VEGETATION).mean(), (cls == L.TRUNK).mean()

    (veg_a, trunk_a), (veg_b, trunk_b) = shares("leaf-on"), shares("leaf-off")
    assert veg_b < veg_a and trunk_b > trunk_a


def test_leaf_off_session_of_one_forest(tmp_path, capsys):
    code, out, err = run_cli(["simulate", tmp_path / "s", "--world", "forest", "--frames", "8",
                              "--sessions", "2", "--session-season", "leaf-off", "-q"], capsys)
    assert code == 0, err
    meta = json.loads((tmp_path / "s" / "sessions.json").read_text())
    assert [s["season"] for s in meta["sessions"]] == ["leaf-on", "leaf-off"]
    manifest = json.loads((tmp_path / "s" / "session1" / "manifest.json").read_text())
    assert manifest["config"]["season"] == "leaf-off"


@pytest.mark.parametrize("args, source", [
    (["--world", "tiny-mixed", "--season", "leaf-off"], "--season"),
    (["--world", "tiny-mixed", "--sessions", "2", "--session-season", "leaf-off"],
     "--session-season"),
    (["--world", "forest", "--session-season", "leaf-off"], "--session-season"),
    (["--world", "tiny-mixed", "--platform", "handheld"], "--platform"),
    (["--world", "forest", "--trajectory", "poses.txt"], "--trajectory"),
])
def test_bad_season_options_are_one_error_line(tmp_path, capsys, args, source):
    code, out, err = run_cli(["simulate", tmp_path / "x", *args, "-q"], capsys)
    assert_one_line_error(code, err, source)
    assert not (tmp_path / "x").exists()


def test_every_natural_world_is_a_preset():
    from lidar_iris_eval.simulate import PRESETS

    assert {PRESETS[w]["world_style"] for w in ("forest", "park")} == set(NATURE_STYLES)


if __name__ == "__main__":  # maintainer: rewrite the golden file after an intended change
    import tempfile

    arrays = {}
    for name, (preset, options) in GOLDEN.items():
        with tempfile.TemporaryDirectory() as tmp:
            out = simulate_sequence(Path(tmp) / "seq", preset, **options)
            for key, value in fingerprint(out).items():
                arrays[f"{name}/{key}"] = value
    np.savez_compressed(GOLDEN_FILE, **arrays)
    print(f"wrote {GOLDEN_FILE}")
