"""``liris simulate --workers``: the files do not depend on the worker count or the order
frames are cast in (each frame's noise comes from its own (seed, part, session, frame)
stream). Every file of every run is compared byte for byte."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import assert_one_line_error, run_cli

from lidar_iris_eval.executor import ProcessExecutor, SerialExecutor
from lidar_iris_eval.simulate import pipeline, resolve_config, run_simulation
from lidar_iris_eval.simulate.sessions import run_sessions

#: small worlds of the three paths that cast frames: spinning scans (with moving cars,
#: whose primitives change every frame), two sessions with another sensor, push-broom
CASES = {
    "spinning": ("tiny-mixed", dict(frames=12, azimuth_steps=96, moving_cars=True), 1),
    "sessions": ("tiny-mixed", dict(frames=8, azimuth_steps=96), 2),
    "pushbroom": ("forest", dict(frames=20, azimuth_steps=64, pushbroom=3.0), 1),
}


def tree_bytes(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by its relative name."""
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def simulate(out: Path, case: str, workers: int) -> dict[str, bytes]:
    preset, overrides, sessions = CASES[case]
    cfg = resolve_config(preset, overrides)
    if sessions > 1:
        run_sessions(out, cfg, sessions, ("vlp16",), preset=preset, workers=workers)
    else:
        run_simulation(out, cfg, preset=preset, workers=workers)
    return tree_bytes(out)


def frame_files(files: dict[str, bytes]) -> list[str]:
    return [name for name in files if "velodyne/" in name]


@pytest.mark.parametrize("case", sorted(CASES))
def test_two_workers_write_the_same_bytes_as_one(tmp_path, case):
    serial = simulate(tmp_path / "w1", case, 1)
    pooled = simulate(tmp_path / "w2", case, 2)
    assert sorted(pooled) == sorted(serial)
    expected_frames = {"spinning": 12, "sessions": 2 * 8, "pushbroom": 3}[case]
    assert len(frame_files(serial)) == expected_frames
    assert all(len(serial[name]) > 0 for name in frame_files(serial))
    differing = [name for name in serial if pooled[name] != serial[name]]
    assert differing == []


class ReversedExecutor(SerialExecutor):
    """Runs the tasks last to first: a frame that drew from a generator shared with the
    frames before it would change."""

    def imap(self, fn, tasks, shared=()):
        for index in reversed(range(len(tasks))):
            yield index, fn(*shared, *tasks[index])


@pytest.mark.parametrize("case", ["spinning", "pushbroom"])
def test_frames_cast_last_to_first_write_the_same_bytes(tmp_path, monkeypatch, case):
    serial = simulate(tmp_path / "forward", case, 1)
    monkeypatch.setattr(pipeline, "local_executor", lambda workers: ReversedExecutor())
    backward = simulate(tmp_path / "backward", case, 1)
    assert [name for name in serial if backward.get(name) != serial[name]] == []


def test_two_workers_use_a_process_pool(monkeypatch, tmp_path):
    """--workers 2 really goes through the pool (else the equality above proves nothing)."""
    seen = []
    original = ProcessExecutor.imap

    def spy(self, fn, tasks, shared=()):
        seen.append((self.workers, len(tasks)))
        yield from original(self, fn, tasks, shared)

    monkeypatch.setattr(ProcessExecutor, "imap", spy)
    simulate(tmp_path / "w2", "spinning", 2)
    assert seen == [(2, 12)]


def test_cli_workers_gives_the_library_bytes(tmp_path, capsys):
    code, out, err = run_cli(["simulate", tmp_path / "cli", "--world", "tiny-mixed",
                              "--frames", "12", "--azimuth-steps", "96", "--moving-cars",
                              "--workers", "2", "-q"], capsys)
    assert code == 0, err
    assert "wrote 12 scans" in out
    assert tree_bytes(tmp_path / "cli") == simulate(tmp_path / "lib", "spinning", 1)


def test_cli_refuses_zero_workers(tmp_path, capsys):
    code, _, err = run_cli(["simulate", tmp_path / "x", "--workers", "0"], capsys)
    assert_one_line_error(code, err, "--workers")
    assert not (tmp_path / "x").exists()
