"""The ESM paper's Table I analogue: localisations at zero false positives per world and method.

    python scripts/table1.py [--out results/table1] [--frames N] [--azimuth-steps N]
        [--worlds urban-dense,forest,park] [--methods lidar-iris,scan-context,...]
        [--workers N] [--cache-dir DIR] [--figure] [--overwrite]

For every world (default ``urban-dense``, ``forest`` with its HDL-32E,
``park`` with its VLP-16) it runs ``liris simulate OUT/<world>/seq --world W``
(skipped when that folder already holds the same configuration), then
``liris eval`` protocol 1 at E = 30 (the paper's exclusion, the defaults of
liris eval) with every method into run folders ``OUT/<world>/run-<k>`` (one
``-d a,b,c`` run per group of methods; ``esm`` and ``esm:segmatch`` share a
name, so they go to different runs), reads each run's metrics.json and
prints a Markdown table; ``OUT/table1.csv`` and ``OUT/table1.json`` hold the
same rows.

Outputs are never replaced silently (as ``liris`` itself): before any work
starts, an existing ``table1.csv`` / ``table1.json``, run folder or simulated
sequence of another configuration is refused unless ``--overwrite`` is given,
and even then only what liris wrote is replaced (a run folder with its liris
manifest and nothing added, a sequence ``liris simulate`` wrote); a bad output
is one ``liris: error:`` line naming it, exit code 2. The two tables are
written atomically (a reader sees the old file or the new one, never half).

Columns: ``localisations`` = localisations at zero false positives =
R@100P x revisit queries (liris' protocol 1 recall is over revisit queries);
``loc_zero_fp_matches`` recounts them from matches.csv (accepted true matches
before the first false one, best score first; ESM's ``zero_fp_report``) as a
cross-check; ``revisits``; ``f1_max``; ``r100p``.

ESM runs its default (``local-maps``, shipped weights, not retrained);
``esm:segmatch`` is the same pipeline with SegMatch's eigenvalue features.
OverlapTransformer is left out by default (it ships random weights; add it
with ``--methods``). The default sizes are the shortest that revisit:
200 frames of forest and park (a lap is about 140 frames), 300 of
urban-dense (its first revisit is near frame 190). ``--figure`` also writes
``liris plot``'s trajectory figure of every world's first run
(``OUT/<world>/run-0/figures/trajectory.png``: the paper's Fig. 5 style).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from lidar_iris_eval.atomic import atomic_write
from lidar_iris_eval.cli import run_guarded
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.ownership import check_new_files
from lidar_iris_eval.runs.writer import check_run_dir
from lidar_iris_eval.simulate.writer import check_out_dir

WORLDS = ("urban-dense", "forest", "park")
#: the shortest sequences with revisit queries at E = 30 (liris gt on each preset)
DEFAULT_FRAMES = {"urban-dense": 300, "forest": 200, "park": 200}
METHODS = ("lidar-iris", "scan-context", "m2dp", "esf", "gosmatch", "esm", "esm:segmatch")
COLUMNS = ("world", "sensor", "frames", "method", "preset", "revisits", "localisations",
           "loc_zero_fp_matches", "f1_max", "r100p", "run")


def liris(*args: str, prog: str = "table1") -> None:
    """Run the liris CLI of this interpreter; stop on its error.

    ``prog`` names the calling script in its progress lines and failures.

    A bad input (liris' exit code 2) is passed on as its one error line, so
    the script's own failure reads like the CLI's; anything else is shown in
    full with the command that failed.
    """
    cmd = [sys.executable, "-m", "lidar_iris_eval", *args]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode == 2 and done.stderr.strip().startswith("liris: error:"):
        raise LirisError(None, done.stderr.strip().splitlines()[-1]
                         .removeprefix("liris: error:").strip())
    if done.returncode:
        sys.stderr.write(done.stderr)
        raise SystemExit(f"{prog}: failed: liris {' '.join(args)}")
    print(f"{prog}: liris {' '.join(args[:2])} ... {time.perf_counter() - t0:.0f} s",
          file=sys.stderr, flush=True)


def method_groups(methods: list[str]) -> list[list[str]]:
    """Split methods into runs in which no descriptor name repeats (esm, esm:segmatch)."""
    groups: list[list[str]] = []
    for m in methods:
        base = m.split(":")[0]
        for g in groups:
            if base not in {x.split(":")[0] for x in g}:
                g.append(m)
                break
        else:
            groups.append([m])
    return groups


def reusable(seq: Path, frames: int, azimuth_steps: int | None) -> dict | None:
    """The configuration of a simulated sequence at ``seq`` that matches the request, or None."""
    manifest = seq / "manifest.json"
    if not manifest.is_file():
        return None
    try:
        config = json.loads(manifest.read_text())["config"]
        if config["frames"] == frames and (azimuth_steps is None
                                           or config["azimuth_steps"] == azimuth_steps):
            return config
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return None


def simulate(world: str, seq: Path, frames: int, azimuth_steps: int | None,
             overwrite: bool = False) -> dict:
    """Simulate the world once; reuse a folder that already holds the same configuration."""
    config = reusable(seq, frames, azimuth_steps)
    if config is not None:
        return config
    args = ["simulate", str(seq), "--world", world, "--frames", str(frames), "-q"]
    if overwrite:
        args.append("--overwrite")
    if azimuth_steps is not None:
        args += ["--azimuth-steps", str(azimuth_steps)]
    liris(*args)
    return json.loads((seq / "manifest.json").read_text())["config"]


def zero_fp_count(matches_csv: Path) -> int:
    """Accepted true matches before the first false one, best (smallest) distance first."""
    import pandas as pd

    m = pd.read_csv(matches_csv)
    m = m[np.isfinite(m["distance"])].sort_values(["distance", "query"], kind="stable")
    false = np.nonzero(m["is_true"].to_numpy() == 0)[0]
    first = int(false[0]) if len(false) else len(m)
    return int(m["is_true"].iloc[:first].sum())


def evaluate(world: str, seq: Path, sensor: str, groups: list[list[str]], out: Path,
             cache_dir: Path, workers: int, overwrite: bool = False) -> list[dict]:
    """Protocol 1 of every method group on ``seq`` into ``out/run-<k>``; one row per method."""
    rows = []
    for k, group in enumerate(groups):
        run = out / f"run-{k}"
        liris("eval", str(seq), "-d", ",".join(group), "--protocol", "1", "--exclude", "30",
              "--sensor", sensor, "--out", str(run), "-q", *(["--overwrite"] * overwrite),
              "--cache-dir", str(cache_dir), "--workers", str(workers))
        metrics = json.loads((run / "metrics.json").read_text())
        results = {r["descriptor"]: r for r in metrics["results"] if r["protocol"] == 1}
        for method in group:
            name = method.split(":")[0]
            r = results[name]
            if r["recall_denominator"] != "revisits":
                raise SystemExit(f"table1: {run}: recall is not over revisit queries")
            rows.append({
                "world": world, "sensor": sensor, "frames": metrics["sequence"]["n_frames"],
                "method": method, "preset": r["preset"], "revisits": int(r["n_revisits"]),
                "localisations": int(round(r["r100p"] * r["n_revisits"])),
                "loc_zero_fp_matches": zero_fp_count(run / "protocol1" / name / "matches.csv"),
                "f1_max": round(float(r["f1_max"]), 4), "r100p": round(float(r["r100p"]), 4),
                "run": str(run),
            })
    return rows


def world_frames(world: str, frames: int | dict | None) -> int:
    """The length of ``world``: one count for all, a ``{world: count}`` dict, or the default."""
    if isinstance(frames, dict):
        return frames[world]
    return frames if frames is not None else DEFAULT_FRAMES.get(world, 200)


def check_outputs(out: Path, worlds, groups: list[list[str]], frames: int | dict | None,
                  azimuth_steps: int | None, overwrite: bool) -> None:
    """Refuse, before any work, every output the run would replace without ``--overwrite``.

    The same rules as the CLI's, through its own checks: the tables are single
    files (:func:`~lidar_iris_eval.ownership.check_new_files`), run folders
    are replaced only when liris wrote them with nothing added
    (:func:`~lidar_iris_eval.runs.writer.check_run_dir`), and a sequence of
    another configuration only when ``liris simulate`` wrote it
    (:func:`~lidar_iris_eval.simulate.writer.check_out_dir`). Checking up
    front matters because the run takes minutes: a refusal after the first
    world would leave a half-replaced table folder.

    Raises
    ------
    LirisError
        Naming the first output that may not be written.
    """
    out = Path(out)
    check_new_files([out / "table1.csv", out / "table1.json"], overwrite, "--out")
    for world in worlds:
        seq = out / world / "seq"
        if reusable(seq, world_frames(world, frames), azimuth_steps) is None:
            check_out_dir(seq, overwrite)
        for k in range(len(groups)):
            check_run_dir(out / world / f"run-{k}", overwrite)


def write_tables(out: Path, rows: list[dict]) -> None:
    """OUT/table1.csv and OUT/table1.json, each written atomically."""
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=COLUMNS)
    w.writeheader()
    w.writerows(rows)
    atomic_write(out / "table1.csv", text.getvalue(), what="table")
    atomic_write(out / "table1.json", json.dumps(rows, indent=1) + "\n", what="table")


def table1(out: Path, worlds=WORLDS, methods=METHODS, frames: int | dict | None = None,
           azimuth_steps: int | None = None, cache_dir: Path | None = None, workers: int = 1,
           figure: bool = False, overwrite: bool = False) -> list[dict]:
    """Simulate, evaluate and tabulate; writes OUT/table1.csv and OUT/table1.json.

    ``frames``: one count for every world, a ``{world: count}`` dict, or None
    (:data:`DEFAULT_FRAMES`). ``overwrite``: replace earlier outputs (only
    those liris wrote, see :func:`check_outputs`), as ``--overwrite``.
    """
    out = Path(out)
    cache_dir = Path(cache_dir) if cache_dir else out / "cache"
    groups = method_groups(list(methods))
    check_outputs(out, list(worlds), groups, frames, azimuth_steps, overwrite)
    rows = []
    for world in worlds:
        config = simulate(world, out / world / "seq", world_frames(world, frames),
                          azimuth_steps, overwrite)
        rows += evaluate(world, out / world / "seq", config["sensor"], groups, out / world,
                         cache_dir, workers, overwrite)
        if figure:
            liris("plot", str(out / world / "run-0"))
    write_tables(out, rows)
    return rows


def markdown(rows: list[dict]) -> str:
    """Methods as rows, worlds as column groups: localisations at zero FP / F1max / R@100P."""
    worlds = list(dict.fromkeys(r["world"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["world"], r["method"]): r for r in rows}
    head = ["method"]
    for w in worlds:
        r0 = next(r for r in rows if r["world"] == w)
        head.append(f"{w} ({r0['sensor']}, {r0['frames']} fr, {r0['revisits']} revisits): "
                    "loc@0FP / F1max / R@100P")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in methods:
        cells = [m]
        for w in worlds:
            r = cell.get((w, m))
            cells.append("n/a" if r is None else
                         f"{r['localisations']} / {r['f1_max']:.3f} / {r['r100p']:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("results/table1"))
    p.add_argument("--worlds", default=",".join(WORLDS))
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--frames", type=int, default=None,
                   help="scans per world (default: " +
                        ", ".join(f"{w} {n}" for w, n in DEFAULT_FRAMES.items()) + ")")
    p.add_argument("--azimuth-steps", type=int, default=None,
                   help="rays per beam and turn (default: each preset's)")
    p.add_argument("--cache-dir", type=Path, default=None, help="default: OUT/cache")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--figure", action="store_true",
                   help="also liris plot every world's first run (trajectory.png)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace earlier tables, runs and sequences (only those liris wrote)")
    a = p.parse_args(argv)
    rows = run_guarded(lambda: table1(a.out, a.worlds.split(","), a.methods.split(","),
                                      a.frames, a.azimuth_steps, a.cache_dir, a.workers,
                                      a.figure, a.overwrite))
    print(markdown(rows))


if __name__ == "__main__":
    main()
