"""``liris bench``: KITTI-scale speed and memory of every descriptor (see lidar_iris_eval.bench)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from lidar_iris_eval.bench import (
    DEFAULT_DESCRIPTORS,
    DEFAULT_PRESETS,
    BenchSettings,
    run_benchmark,
    simulated_sequence,
    summary_rows,
)
from lidar_iris_eval.bench.drivers import find_drivers
from lidar_iris_eval.bench.extraction import (
    bin_files,
    cpp_heading,
    cpp_rows,
    measure_extraction,
    read_bin,
)
from lidar_iris_eval.cli.options import deprecated_alias
from lidar_iris_eval.cli.output import (
    check_output_file,
    echo_table,
    format_table,
    write_output_file,
)
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET
from lidar_iris_eval.runs.writer import json_ready
from lidar_iris_eval.simulate.presets import PRESETS

DEFAULT_FRAMES = 4541
#: azimuth steps of a full-resolution simulated HDL-64E scan (~120k points, like KITTI)
FULL_AZIMUTH_STEPS = 2048


def build_bench_descriptors(text: str, preset: str | None):
    """``--descriptor`` and ``--preset`` to descriptors; Scan Context defaults to ``exhaustive``."""
    from lidar_iris_eval.cli.descriptor_options import parse_descriptor_specs
    from lidar_iris_eval.descriptors import get_descriptor

    return [
        get_descriptor(name, preset=own or DEFAULT_PRESETS.get(name))
        for name, own in parse_descriptor_specs(text, preset)
    ]


@click.command("bench")
@click.option("--frames", type=int, default=None,
              help=f"A COUNT: frames of the simulated sequence [default: {DEFAULT_FRAMES}].")
@click.option("--descriptor", "-d", "descriptor_text", default=DEFAULT_DESCRIPTORS,
              show_default=True, help="NAME[,NAME...]; NAME:PRESET picks one descriptor's preset.")
@click.option("--preset", default=None,
              help="Descriptor preset for all descriptors (default: each one's first; "
                   "scan-context: exhaustive).")
@click.option("--world", "sim_preset", default="kitti-scale", show_default=True,
              type=click.Choice(sorted(PRESETS)),
              help="Simulated world (a liris simulate --world preset) of the sequence.")
@deprecated_alias("--sim-preset", "--world", "sim_preset")
@click.option("--azimuth-steps", type=int, default=None,
              help="Simulated azimuth steps per revolution (default: the sim preset's).")
@click.option("--sequence", type=click.Path(path_type=Path), default=None,
              help="Benchmark an existing sequence instead of simulating one.")
@click.option("--work-dir", type=click.Path(path_type=Path), default=None,
              help="Simulated sequence and descriptor cache [default: <liris cache dir>/bench]; "
                   "reruns reuse both.")
@click.option("--json-out", "json_path", default=None,
              help="Write the report as JSON to FILE ('-' for stdout).")
@deprecated_alias("--json", "--json-out", "json_path")
@click.option("--exclude", type=int, default=30, show_default=True,
              help="Protocol 1 exclusion window E (frames).")
@click.option("--radius", type=float, default=4.0, show_default=True,
              help="Ground-truth radius (metres) for the protocols' metrics.")
@click.option("--protocol", "protocol_list", type=click.Choice(["1", "2"]), multiple=True,
              help="Time only these protocols (repeatable) [default: both].")
@click.option("--skip-protocol1", is_flag=True, help="Do not time protocol 1.")
@click.option("--skip-protocol2", is_flag=True, help="Do not time protocol 2.")
@click.option("--loop-pairs", type=int, default=1000, show_default=True,
              help="Random pairs for the per-pair loop baseline and the equality check (0: skip).")
@click.option("--kernel-queries", type=int, default=128, show_default=True,
              help="Queries timed against the whole database for pairs/s.")
@click.option("--workers", type=int, default=1, show_default=True,
              help="Extraction processes (per-scan times are clean only with 1).")
@click.option("--block-pairs", type=int, default=DEFAULT_PAIR_BUDGET, show_default=True,
              help="Distances per block of the matching driver.")
@click.option("--in-process", is_flag=True,
              help="Run the protocols in this process (faster to start; peak memory then "
                   "includes everything before).")
@click.option("--cpp-scans", type=int, default=4, show_default=True,
              help="Full-resolution scans timed on one core, per descriptor's reference "
                   "preset (0: skip).")
@click.option("--cpp", "cpp_dir", type=click.Path(path_type=Path), default=None,
              help="Folder of reference drivers you built (DIR/lidar-iris, DIR/esf, ...; "
                   "contract: docs/performance.md), timed in this run on the same scans for "
                   "C++ ratios. Without it no ratio is printed, only published figures.")
@click.option("--scans", "scans_dir", type=click.Path(path_type=Path, file_okay=False),
              default=None,
              help="Folder of KITTI .bin scans for the C++ comparison [default: simulated "
                   "full-resolution HDL-64E scans].")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars or status lines.")
def command(frames, descriptor_text, preset, sim_preset, azimuth_steps, sequence, work_dir,
            json_path, exclude, radius, protocol_list, skip_protocol1, skip_protocol2, loop_pairs,
            kernel_queries, workers, block_pairs, in_process, cpp_scans, cpp_dir, scans_dir,
            quiet):
    """Time extraction, the batched kernels and protocols 1/2 of each descriptor.

    By default a 4541-frame sequence (KITTI 00's length) is simulated once into
    the work folder. Progress goes to stderr, a table to stdout at the end.
    """
    from lidar_iris_eval.cache import default_cache_dir
    from lidar_iris_eval.io import open_sequence

    for p, skip in ((1, skip_protocol1), (2, skip_protocol2)):
        if skip and str(p) in protocol_list:
            raise LirisError(f"--protocol {p} --skip-protocol{p}",
                             "contradictory: ask for the protocol or skip it, not both")
    protocols = tuple(p for p, skip in ((1, skip_protocol1), (2, skip_protocol2))
                      if not skip and (not protocol_list or str(p) in protocol_list))
    settings = BenchSettings(exclude=exclude, radius=radius, protocols=protocols,
                             loop_pairs=loop_pairs, kernel_queries=kernel_queries,
                             workers=workers, isolate=not in_process, pair_budget=block_pairs)
    descriptors = build_bench_descriptors(descriptor_text, preset)
    if json_path is not None and json_path != "-":
        check_output_file(json_path, "--json-out")  # before the benchmark, not after it
    work_dir = work_dir if work_dir is not None else default_cache_dir() / "bench"
    drivers = find_drivers(cpp_dir) if cpp_dir is not None else None  # before any work
    if drivers is not None and not cpp_scans:
        raise LirisError("--cpp", "needs scans to time (--cpp-scans > 0)")

    def log(message: str) -> None:
        if not quiet:
            click.echo(message, err=True)

    sim = None
    if sequence is not None:
        if frames is not None or azimuth_steps is not None:
            raise LirisError("--frames/--azimuth-steps", "only apply to a simulated sequence, "
                             "not with --sequence")
    else:
        if frames is not None and frames < 2:
            raise LirisError(f"--frames {frames}", "must be at least 2")
        log(f"simulated sequence ({sim_preset}) in {work_dir}")
        sequence, sim_s = simulated_sequence(work_dir, sim_preset, frames or DEFAULT_FRAMES,
                                             azimuth_steps, progress=not quiet)
        sim = {"preset": sim_preset, "simulate_s": sim_s, "reused": sim_s == 0.0}
    if cpp_scans < 0:
        raise LirisError(f"--cpp-scans {cpp_scans}", "must be >= 0")
    if scans_dir is not None and not scans_dir.is_dir():
        raise LirisError(str(scans_dir), "no such folder (--scans)")
    seq = open_sequence(sequence)
    report = run_benchmark(seq, descriptors, work_dir, settings, progress=not quiet, log=log)
    report["argv"] = [Path(sys.argv[0]).name, *sys.argv[1:]]
    report["sequence"]["simulated"] = sim
    cpp = None
    if cpp_scans:
        cpp = compare_with_cpp(descriptors, cpp_scans, scans_dir, work_dir, log, quiet,
                               drivers)
        report["cpp_comparison"] = cpp
    rows = summary_rows(report)
    report = json_ready(report)
    if json_path == "-":
        click.echo(json.dumps(report, indent=2))
        click.echo(format_table(rows), err=True)
        if cpp is not None:
            click.echo(cpp_heading(cpp), err=True)
            click.echo(format_table(cpp_rows(cpp)), err=True)
        return
    echo_table(rows)  # first: a failing --json write must not lose the table too
    if cpp is not None:
        click.echo("\n" + cpp_heading(cpp))
        echo_table(cpp_rows(cpp))
    for bar in report["bars"]:
        verdict = "met" if bar["met"] else "MISSED"
        click.echo(f"bar: {bar['bar']}: {bar['value']:.4g} (limit {bar['limit']:g}) {verdict}")
    load = report["load_average"]
    click.echo(f"load average: start {load['start']}, end {load['end']}")
    if json_path is not None:
        write_output_file(json_path, json.dumps(report, indent=2) + "\n")


def compare_with_cpp(descriptors, count: int, scans_dir: Path | None, work_dir: Path, log,
                     quiet: bool, drivers: dict | None = None) -> dict:
    """Time each descriptor's ``reference`` preset on full-resolution scans.

    With ``drivers`` (``--cpp``) the user's reference builds are timed in the
    same run on the same files; otherwise only published figures are attached.
    """
    from lidar_iris_eval.descriptors import get_descriptor

    if scans_dir is not None:
        files = bin_files(scans_dir, count)
        if not files:
            raise LirisError(str(scans_dir), "no .bin scans (--scans)")
        source = str(scans_dir)
    else:
        log(f"{count} full-resolution scans (HDL-64E, {FULL_AZIMUTH_STEPS} azimuth steps)")
        path, _ = simulated_sequence(work_dir, "kitti-scale", count, FULL_AZIMUTH_STEPS,
                                     progress=not quiet)
        files = bin_files(Path(path) / "velodyne", count)
        source = "simulated kitti-scale, full resolution"
    scans = [read_bin(f) for f in files]
    names = list(dict.fromkeys(d.name for d in descriptors))
    refs = [get_descriptor(name, preset="reference") for name in names]
    timed = {n: p for n, p in (drivers or {}).items() if n in names}
    log(f"extraction and single-pair time on one core: {', '.join(names)}"
        + (f"; C++ drivers: {', '.join(timed)}" if timed else ""))
    result = measure_extraction(refs, scans, drivers=timed,
                                scan_paths=[str(f.resolve()) for f in files])
    result["scan_source"] = source
    return result
