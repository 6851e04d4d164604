"""Options and helpers several verbs share: descriptors, presets, parameters, the sequence.

Verbs (``*_cmd.py``) import from here, never from each other.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import click
import yaml

from lidar_iris_eval.cache import DescriptorCache, default_cache_dir
from lidar_iris_eval.cli.options import workers_option
from lidar_iris_eval.cli.sequence_options import pose_file_options, sequence_options
from lidar_iris_eval.descriptors import Descriptor, available_descriptors, get_descriptor
from lidar_iris_eval.errors import LirisError, register_flags
from lidar_iris_eval.extract import DEFAULT_CHUNK_SIZE, DescriptorDB, extract_many
from lidar_iris_eval.io.sequence import full_scan_hashing
from lidar_iris_eval.localmaps.odometry import ODOMETRY_SOURCES, check_odometry
from lidar_iris_eval.sensors import SENSORS

#: library keywords -> the flags that set them, for errors raised below the CLI
register_flags({"descriptor": "--descriptor", "workers": "--workers"})


def parse_descriptor_specs(text: str, preset: str | None) -> list[tuple[str, str | None]]:
    """``"a,b:reference"`` to ``[("a", preset), ("b", "reference")]``; duplicates are errors."""
    specs = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        name, _, own = item.partition(":")
        specs.append((name.strip(), own.strip() or preset))
    if not specs:
        raise LirisError(f"--descriptor {text}", "give at least one descriptor name")
    names = [n for n, _ in specs]
    if len(set(names)) != len(names):
        raise LirisError(f"--descriptor {text}", "a descriptor is listed twice")
    return specs


def parse_param_overrides(items: tuple[str, ...], names: list[str]) -> dict[str, dict]:
    """``("esf.seed=3", ...)`` to ``{"esf": {"seed": 3}}``; values are read as YAML."""
    overrides: dict[str, dict] = {name: {} for name in names}
    for item in items:
        target, sep, text = item.partition("=")
        name, dot, key = target.strip().rpartition(".")
        if not sep or not dot or not key:
            raise LirisError(f"--param {item}", "expected DESCRIPTOR.KEY=VALUE, e.g. esf.seed=3")
        if name not in overrides:
            raise LirisError(f"--param {item}", f"{name!r} is not among --descriptor {names}")
        try:
            overrides[name][key] = yaml.safe_load(text)
        except yaml.YAMLError:
            raise LirisError(f"--param {item}", "value is not valid YAML") from None
    return overrides


def build_descriptors(text: str, preset: str | None, sensor: str | None = None,
                      params: tuple[str, ...] = (), odometry: str = "gt") -> list[Descriptor]:
    """Descriptors from ``--descriptor``, ``--preset``, ``--sensor``, ``--param`` and
    ``--odometry``.

    Everything is validated (names, presets, parameter keys) before any work.
    ``odometry`` sets the ``odometry`` parameter of every method that has one
    (the pose source of its local maps); ``--param NAME.odometry=`` is refused,
    so ``--odometry`` is the one option that sets it.
    """
    if sensor == "auto":  # resolved per sequence (resolve_sensor) before this point
        raise LirisError("--sensor auto", "works with one sequence; name the sensor preset")
    specs = parse_descriptor_specs(text, preset)
    overrides = parse_param_overrides(params, [name for name, _ in specs])
    for name, values in overrides.items():
        if "odometry" in values:
            raise LirisError(f"--param {name}.odometry", "the pose source of local maps is "
                                                         "set by --odometry gt|kiss-icp")
    check_odometry(odometry)
    return [with_odometry(get_descriptor(name, preset=p, sensor=sensor, **overrides[name]),
                          odometry) for name, p in specs]


def with_odometry(descriptor: Descriptor, odometry: str) -> Descriptor:
    """``descriptor`` with its ``odometry`` parameter set (a method without one: as is)."""
    params = getattr(descriptor, "params", None)
    if not dataclasses.is_dataclass(params) or "odometry" not in {
            f.name for f in dataclasses.fields(params)}:
        return descriptor
    if params.odometry == odometry:
        return descriptor
    return type(descriptor)(dataclasses.replace(params, odometry=odometry), descriptor.preset)


def odometry_option(func):
    """``--odometry gt|kiss-icp`` for ``liris extract`` (``liris eval`` also takes FILE)."""
    return click.option(
        "--odometry", "odometry", type=click.Choice(ODOMETRY_SOURCES), default="gt",
        show_default=True, help=ODOMETRY_HELP)(func)


ODOMETRY_HELP = ("Pose source of the local maps of methods that read them (esm): gt, the "
                 "sequence's poses (an oracle), or kiss-icp, estimated from the scans alone "
                 "(the 'odometry' extra). Methods without local maps ignore it.")


def verify_scans_option(func):
    """``--verify-scans``: run the command with every scan hashed in full for cache keys."""

    @click.option("--verify-scans", is_flag=True,
                  help="Key the cache by a hash of every byte of every scan (slow; catches any "
                       "edit). Default: each file's name, size, modification time and ends.")
    @functools.wraps(func)
    def wrapper(*args, verify_scans: bool = False, **kwargs):
        with full_scan_hashing(verify_scans):
            return func(*args, **kwargs)

    return wrapper


def descriptor_options(func):
    """``--descriptor``, ``--preset``, ``--cache-dir``, ``--workers``, ``--quiet``."""
    options = [
        pose_file_options,
        sequence_options,
        click.option("--descriptor", "-d", "descriptor_text", required=True,
                     help=f"NAME[,NAME...] of {', '.join(available_descriptors())}; "
                          "NAME:PRESET picks a preset for one descriptor."),
        click.option("--preset", default=None,
                     help="Descriptor preset for all descriptors (default: each one's first)."),
        click.option("--param", "params", multiple=True, metavar="NAME.KEY=VALUE",
                     help="Override one descriptor parameter, e.g. esf.seed=3 (repeatable)."),
        click.option("--sensor", type=click.Choice([*SENSORS, "auto"]), default="hdl64",
                     show_default=True,
                     help="Sensor preset (e.g. LiDAR Iris height range; lidar_iris_eval/"
                          "sensors.py); auto guesses it from the first scans."),
        click.option("--cache-dir", type=click.Path(path_type=Path), default=None,
                     help="Descriptor cache folder [default: $LIRIS_CACHE_DIR or ./.liris-cache]."),
        workers_option("extraction and registration (--refine)"),
        click.option("--quiet", "-q", is_flag=True, help="No progress bars."),
        verify_scans_option,
    ]
    for option in reversed(options):
        func = option(func)
    return func


def open_input(sequence: Path, reader_options: dict):
    """Open SEQUENCE with the reader options gathered by ``descriptor_options``."""
    from lidar_iris_eval.io import open_sequence

    return open_sequence(sequence, **reader_options)


def run_extraction(seq, descriptors: list[Descriptor], cache_dir: Path | None, workers: int,
                   quiet: bool, chunk_size: int = DEFAULT_CHUNK_SIZE) -> list[DescriptorDB]:
    """Extract (or load) every descriptor; the cache folder is created on first write."""
    cache = DescriptorCache(cache_dir if cache_dir is not None else default_cache_dir())
    return extract_many(seq, descriptors, cache=cache, workers=workers, progress=not quiet,
                        chunk_size=chunk_size)  # each scan read once for all descriptors
