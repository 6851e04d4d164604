"""``liris simulate``: write a synthetic sequence with known loops in KITTI layout."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.cli.options import deprecated_alias, workers_option
from lidar_iris_eval.simulate.presets import PRESETS, resolve_config
from lidar_iris_eval.simulate.sensors import SENSORS
from lidar_iris_eval.simulate.trajectories import ROUTES


@click.command("simulate")
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("--world", "preset", type=click.Choice(sorted(PRESETS)), default="tiny-mixed",
              show_default=True, help="Built-in sequence; the options below override it.")
@deprecated_alias("--preset", "--world", "preset", type=click.Choice(sorted(PRESETS)))
@click.option("--frames", type=int, help="A COUNT: number of scans to simulate (default: the "
              "preset's; with --trajectory, every pose of the file). gt/extract/eval take a "
              "START:STOP range instead.")
@click.option("--sensor", type=click.Choice(sorted(SENSORS)), help="LiDAR model.")
@click.option("--route", type=click.Choice(ROUTES),
              help="Revisit pattern: same direction, reverse direction, or both.")
@click.option("--azimuth-steps", type=int,
              help="Rays per beam and turn (default: the preset's; sensor full resolution "
              "is 2048 for hdl64, 1800 for vlp16; see lidar_iris_eval/sensors.py).")
@click.option("--seed", type=int, help="Random seed; the same seed gives identical files.")
@click.option("--moving-cars/--no-moving-cars", default=None,
              help="Add traffic that differs between passes.")
@click.option("--trajectory", type=click.Path(path_type=Path, dir_okay=False),
              help="Follow this KITTI pose file (camera frame) and build the world around it.")
@click.option("--calib", type=click.Path(path_type=Path, dir_okay=False),
              help="calib.txt whose Tr goes with --trajectory (default: a KITTI-like Tr).")
@click.option("--sessions", type=int, default=1, show_default=True,
              help="Drive the same world this many times into OUT_DIR/session0.. (other "
              "parked and moving cars, drive, noise; poses in session 0's frame).")
@click.option("--session-sensor", "session_sensors", multiple=True,
              type=click.Choice(sorted(SENSORS)),
              help="Sensor of session 1, 2, ... (repeat; the last one repeats; default: the "
              "preset's).")
@click.option("--season", type=click.Choice(["leaf-on", "leaf-off"]),
              help="Natural worlds (forest, park): leaf-on or leaf-off crowns and undergrowth "
              "(default: the preset's, leaf-on).")
@click.option("--session-season", "session_seasons", multiple=True,
              type=click.Choice(["leaf-on", "leaf-off"]),
              help="Season of session 1, 2, ... of a natural world (repeat; the last one "
              "repeats; default: session 0's).")
@click.option("--platform", type=click.Choice(["ugv", "handheld"]),
              help="Natural worlds: a ground robot (the preset's) or a walking operator "
              "(1.5 m, 0.3 m a frame, smooth roll and pitch sway of 3 deg).")
@click.option("--pushbroom", type=float, metavar="METRES",
              help="Push-broom mode: every frame is the swathe of an LMS151-like 2-D line "
              "scanner (270 deg, tilted) over this many metres travelled (the ESM paper: 22).")
@click.option("--overwrite", is_flag=True, help="Replace the contents of a non-empty OUT_DIR.")
@workers_option("casting and writing the scans (the files are byte-identical for any count)")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
def command(out_dir, preset, frames, sensor, route, azimuth_steps, seed, moving_cars, trajectory,
            calib, sessions, session_sensors, season, session_seasons, platform, pushbroom,
            overwrite, workers, quiet):
    """Simulate a LiDAR sequence with exact ground truth into OUT_DIR.

    Writes velodyne/*.bin, labels/*.label (SemanticKITTI), poses.txt (camera
    frame), times.txt, calib.txt and manifest.json.
    """
    from lidar_iris_eval.simulate.pipeline import run_simulation

    overrides = dict(
        frames=frames, sensor=sensor, route=route, azimuth_steps=azimuth_steps, seed=seed,
        moving_cars=moving_cars,
        trajectory=None if trajectory is None else str(trajectory),
        calib=None if calib is None else str(calib), season=season, pushbroom=pushbroom,
        platform=platform,
    )
    cfg = resolve_config(preset, overrides)
    if sessions != 1 or session_sensors or session_seasons:
        from lidar_iris_eval.simulate.sessions import run_sessions

        report = run_sessions(out_dir, cfg, sessions, tuple(session_sensors), overwrite,
                              not quiet, preset, seasons=tuple(session_seasons),
                              workers=workers)
        click.echo(report.summary())
        return
    report = run_simulation(out_dir, cfg, overwrite=overwrite, progress=not quiet, preset=preset,
                            workers=workers)
    click.echo(report.summary())
