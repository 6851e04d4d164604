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
