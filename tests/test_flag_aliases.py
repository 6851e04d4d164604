"""Consistent flags: new spellings, and the old ones kept for one release with a warning."""

from __future__ import annotations

from conftest import run_cli


def test_simulate_world_and_its_deprecated_preset_alias(tmp_path, capsys):
    code, _, err = run_cli(["simulate", tmp_path / "a", "--world", "tiny-same", "--frames", "3",
                            "-q"], capsys)
    assert code == 0, err
    assert "deprecated" not in err
    code, _, err = run_cli(["simulate", tmp_path / "b", "--preset", "tiny-same", "--frames", "3",
                            "-q"], capsys)
    assert code == 0, err
    assert "--preset: deprecated; use --world" in err
    for name in ("velodyne/000002.bin", "poses.txt"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_bench_help_shows_the_new_spellings_only(capsys):
    code, out, _ = run_cli(["bench", "--help"], capsys)
    assert code == 0
    assert "--json-out" in out and "--world" in out
    assert "--sim-preset" not in out and "--json " not in out


def test_scan_context_grid_is_named_like_lidar_iris_with_the_old_names_deprecated():
    import warnings

    import pytest

    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.errors import LirisError, LirisWarning

    iris = get_descriptor("lidar-iris")
    sc = get_descriptor("scan-context", rings=10, sectors=30)
    assert (iris.params.rings, iris.params.sectors) == (80, 360)
    assert (sc.params.rings, sc.params.sectors) == (10, 30)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = get_descriptor("scan-context", num_rings=10, num_sectors=30)
    assert old.params == sc.params
    assert any(issubclass(w.category, LirisWarning) and "num_rings is deprecated; use rings"
               in str(w.message) for w in caught)
    with pytest.raises(LirisError, match="same parameter"):
        get_descriptor("scan-context", num_rings=10, rings=10)
