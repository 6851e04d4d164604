"""ESM's segmentation report (liris segments) and the local-map front end (issue 34)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.esm.local_segments import local_ground_mask, local_map_clusters
from lidar_iris_eval.descriptors.esm.segmentation import SegmentParams, euclidean_clusters
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.segment_report import neighbour_repeatability


def _grid(x0, x1, y0, y1, step, z=lambda x, y: 0 * x):
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step), indexing="ij")
    x, y = x.ravel(), y.ravel()
    return np.stack([x, y, z(x, y)], 1)


def _box(cx, cy, z0, size, step):
    g = np.arange(0, size, step)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    pts = np.stack([x.ravel() + cx, y.ravel() + cy, z.ravel() + z0], 1)
    surface = (np.isclose(pts[:, 0], cx) | np.isclose(pts[:, 0], cx + g[-1])
               | np.isclose(pts[:, 1], cy) | np.isclose(pts[:, 1], cy + g[-1])
               | np.isclose(pts[:, 2], z0 + g[-1]))
    return pts[surface]


def test_local_ground_follows_a_slope_and_keeps_what_stands_on_it():
    slope = np.tan(np.radians(10.0))
    ground = _grid(-10, 10, -10, 10, 0.1, lambda x, y: slope * x)
    box = _box(3.0, 0.0, slope * 3.0 + 0.5, 1.5, 0.1)  # 0.5 m above the slope
    pts = np.concatenate([ground, box])
    is_ground = local_ground_mask(pts, cell=1.0, clearance=0.3)
    assert is_ground[: len(ground)].mean() > 0.99
    assert not is_ground[len(ground):].any()
    # a car-like box standing on flat ground, its lowest points 0.4 m up: the columns
    # under it take the ground beside them, so only its lowest layer goes
    flat = _grid(-5, 5, -5, 5, 0.1)
    flat = flat[~((np.abs(flat[:, 0] + 0.05) < 1.0) & (np.abs(flat[:, 1] + 0.05) < 1.0))]
    car = _box(-1.0, -1.0, 0.4, 2.0, 0.1)  # no ground seen under it
    is_ground = local_ground_mask(np.concatenate([flat, car]), cell=1.0, clearance=0.3)
    assert is_ground[: len(flat)].all()
    car_ground = is_ground[len(flat):]
    assert 0 < car_ground.mean() < 0.2 and (car[car_ground][:, 2] < 0.6).all()
    # a height rule in one frame (z <= 0.3) keeps half the slope and removes nothing uphill
    assert (ground[:, 2] > 0.3).mean() > 0.3


def test_default_clusters_are_plain_connected_components_in_first_voxel_order():
    rng = np.random.default_rng(0)
    pts = np.concatenate([_box(x, 0, 0, 1.2, 0.1) for x in (0.0, 5.0, 10.0)]
                         + [rng.uniform(20, 30, (50, 3))])
    perm = rng.permutation(len(pts))
    pts = pts[perm]
    members = local_map_clusters(pts, SegmentParams())
    comp = euclidean_clusters(pts, 0.2)
    sizes = np.bincount(comp)
    expected = sorted((np.nonzero(comp == c)[0] for c in np.nonzero(sizes >= 100)[0]),
                      key=lambda m: m[0])
    assert len(members) == 3
    assert all(np.array_equal(a, b) for a, b in zip(members, expected, strict=True))


def test_density_normalisation_makes_the_size_rule_independent_of_the_density():
    dense = _grid(0, 2, 0, 2, 0.1, lambda x, y: 0 * x + 1.0)  # a 2 m x 2 m plate, 400 voxels
    sparse = dense[::3]  # a third of them: points 0.1-0.3 m apart
    plain = SegmentParams(radius=0.2, min_points=100)
    assert len(local_map_clusters(dense, plain)) == 1
    assert len(local_map_clusters(sparse, plain)) == 0  # below 100 voxels
    normalised = SegmentParams(radius=0.3, min_points=25, max_points=3750, cluster_voxel=0.2)
    for cloud in (dense, sparse):
        members = local_map_clusters(cloud, normalised)
        assert len(members) == 1 and len(members[0]) == len(cloud)  # every map voxel kept
    too_big = SegmentParams(radius=0.3, min_points=25, max_points=90, cluster_voxel=0.2)
    assert local_map_clusters(dense, too_big) == []  # 100 coarse voxels > 90


def test_front_end_parameters_are_checked():
    with pytest.raises(LirisError, match="esm.cluster_voxel"):
        get_descriptor("esm", cluster_voxel=0.05)
    with pytest.raises(LirisError, match="esm.ground_cell"):
        get_descriptor("esm", ground_cell=-1.0)


def test_neighbour_repeatability_counts_centroids_within_the_match_distance():
    poses = np.tile(np.eye(4), (3, 1, 1))
    a = np.array([[0.0, 0, 0], [5.0, 0, 0], [10.0, 0, 0]])
    # map 2: one segment in place, one moved 3 m, one 0.5 m aside
    feats = [{"world": a}, {"world": a + [0.5, 0, 0]}, {"world": a + [[0, 0, 0], [3, 0, 0],
                                                                      [0, 0.5, 0]]}]
    # map 1 against map 0: all 0.5 m off; map 2 against map 1: 0.5 m and 0.71 m
    assert neighbour_repeatability(feats, poses, 1, 1.0, 50.0) == (3 + 2, 6)
    assert neighbour_repeatability(feats, poses, 2, 1.0, 50.0) == (2, 3)
    assert neighbour_repeatability(feats, poses, 1, 0.4, 50.0) == (0, 6)
    # only segments inside both crops count (map_radius - 5 m of both poses)
    assert neighbour_repeatability(feats, poses, 1, 1.0, 12.0) == (2 + 1, 3)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from lidar_iris_eval.simulate import simulate_sequence

    return simulate_sequence(tmp_path_factory.mktemp("seg") / "seq", preset="tiny-mixed")


def test_segments_command_prints_json_and_figure(tiny, tmp_path, capsys):
    out, fig = tmp_path / "r.json", tmp_path / "r.png"
    code, text, err = run_cli(["segments", tiny, "--exclude", "30", "--limit", "120",
                               "--json-out", out, "--figure", fig, "--preset", "local-maps",
                               "--preset", "local-maps-sensor-z"], capsys)
    assert code == 0, err
    assert "repeatability at neighbours" in text and "retrieval rank" in text
    reports = json.loads(out.read_text())
    assert [r["preset"] for r in reports] == ["local-maps", "local-maps-sensor-z"]
    for r in reports:
        nb, rv = r["neighbours"], r["revisits"]
        assert r["frames"] == 120 and len(r["segments_per_map"]) == 120
        assert 0 <= nb["repeated"] <= nb["counted"]
        assert rv["repeated"] <= rv["query_segments"]
        ranks = [x for q in rv["per_query"] for x in q["ranks"]]
        assert len(ranks) == rv["repeated"] and all(x >= 1 for x in ranks)
        assert rv["within_knn"] == sum(x <= r["knn"] for x in ranks)
    assert fig.stat().st_size > 10_000


@pytest.mark.parametrize("args, words", [
    (["--preset", "single-scan"], "not a local-map preset"),
    (["--figure", "x.jpg"], ".png, .pdf or .svg"),
    (["--param", "radius"], "KEY=VALUE"),
    (["--param", "cluster_voxel=0.01"], "esm.cluster_voxel"),
])
def test_segments_command_refuses_bad_input(tiny, tmp_path, capsys, args, words):
    code, text, err = run_cli(["segments", tiny, *args], capsys)
    assert code == 2 and text == ""
    assert err.count("liris: error:") == 1 and words in err


def test_segments_command_does_not_replace_an_existing_output(tiny, tmp_path, capsys):
    """--json-out and --figure follow the rule of every single output file: an existing
    file is replaced only with --overwrite (it was replaced silently)."""
    out = tmp_path / "mine.json"
    out.write_text("the user's own file\n")
    code, text, err = run_cli(["segments", tiny, "--limit", "40", "--json-out", out], capsys)
    assert code == 2 and err.count("liris: error:") == 1 and "--overwrite" in err, err
    assert out.read_text() == "the user's own file\n"
