"""Cross-season place recognition (issue 37 item 5): a leaf-on database, leaf-off queries.

    python scripts/cross_season.py [--out results/cross_season] [--world forest]
        [--frames N] [--azimuth-steps N] [--methods lidar-iris,scan-context,...]
        [--workers N] [--cache-dir DIR] [--overwrite]

One ``liris simulate OUT/sessions --world W --sessions 3 --session-season
leaf-on --session-season leaf-off`` drives the same natural world three times
(``docs/cross-session.md``: every pose in session 0's frame, so no alignment):
session 0 is the leaf-on database, session 1 a second leaf-on drive and
session 2 a leaf-off drive (no broadleaf foliage, less undergrowth; the same
trunks, conifers, logs, rocks and terrain). Each later session is then the
query set of one ``liris eval --query OUT/sessions/session<k> --database
OUT/sessions/session0 -d ...`` per group of methods, into
``OUT/<season>-run-<g>``.

Why the leaf-on control: a later drive differs from the database in more than
the season (its own lateral offsets, speed, tilt and range noise), so the
leaf-off recall alone mixes the two causes. The leaf-on session shares every
change except the season; the gap between its row and the leaf-off row is
what the season costs each method.

The table (Markdown on stdout; ``OUT/cross_season.csv`` and
``OUT/cross_season.json`` hold the same rows) gives Recall@N for N = 1, 5,
10, 25 per method and query season, as liris' ranking defines it (share of
queries with a positive whose first positive is at rank <= N; positives
within 4 m, no exclusion window across sessions). A two-stage method
(GOSMatch, ESM) ranks only its K verified candidates: Recall@N beyond K is
undefined once a query's positives are not among them, and is ``null`` /
"n/a", never 0. Outputs are checked before any work and replaced only with
``--overwrite`` (only what liris wrote), as ``scripts/table1.py`` does.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table1 import liris, method_groups  # noqa: E402 - the sibling script's runner

from lidar_iris_eval.atomic import atomic_write  # noqa: E402
from lidar_iris_eval.cli import run_guarded  # noqa: E402
from lidar_iris_eval.ownership import check_new_files  # noqa: E402
from lidar_iris_eval.runs.writer import check_run_dir  # noqa: E402
from lidar_iris_eval.simulate.writer import check_out_dir  # noqa: E402

PROG = "cross_season"
#: every method liris runs without optional extras (OverlapTransformer ships random weights)
METHODS = ("lidar-iris", "scan-context", "m2dp", "esf", "gosmatch", "esm", "esm:segmatch")
#: the query sessions: session k of the simulation and its season (session 0 is leaf-on)
QUERIES = (("leaf-on", 1), ("leaf-off", 2))
RECALL_N = (1, 5, 10, 25)
COLUMNS = ("world", "sensor", "frames", "query_season", "method", "preset", "n_queries",
           "n_database", *(f"recall_at_{n}" for n in RECALL_N), "recall_at_1pct", "mrr", "run")


def simulation_args(world: str, frames: int | None, azimuth_steps: int | None) -> list[str]:
    """The ``liris simulate`` options of the three sessions (without OUT_DIR)."""
    args = ["--world", world, "--sessions", "3", "--session-season", "leaf-on",
            "--session-season", "leaf-off"]
    if frames is not None:
        args += ["--frames", str(frames)]
    if azimuth_steps is not None:
        args += ["--azimuth-steps", str(azimuth_steps)]
    return args


def reusable(sessions: Path, world: str, frames: int | None,
             azimuth_steps: int | None) -> dict | None:
    """Session 0's configuration when ``sessions`` already holds this simulation, else None.

    Compared: the preset, the three sessions' seasons, and the frame count and
    azimuth grid where the caller set them.
    """
    try:
        meta = json.loads((sessions / "sessions.json").read_text())
        config = json.loads((sessions / "session0" / "manifest.json").read_text())["config"]
        seasons = [s.get("season") for s in meta["sessions"]]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if (meta.get("preset") != world or seasons != ["leaf-on", "leaf-on", "leaf-off"]
            or (frames is not None and config.get("frames") != frames)
            or (azimuth_steps is not None and config.get("azimuth_steps") != azimuth_steps)):
        return None
    return config


def run_name(season: str, k: int) -> str:
    return f"{season}-run-{k}"


def check_outputs(out: Path, world: str, groups: list[list[str]], frames: int | None,
                  azimuth_steps: int | None, overwrite: bool) -> None:
    """Refuse, before any work, an output that may not be replaced (as the CLI would).

    The tables through :func:`~lidar_iris_eval.ownership.check_new_files`, the
    run folders through :func:`~lidar_iris_eval.runs.writer.check_run_dir`,
    a sessions folder of another configuration through
    :func:`~lidar_iris_eval.simulate.writer.check_out_dir` (only one ``liris
    simulate --sessions`` wrote is replaced).
    """
    check_new_files([out / "cross_season.csv", out / "cross_season.json"], overwrite, "--out")
    if reusable(out / "sessions", world, frames, azimuth_steps) is None:
        check_out_dir(out / "sessions", overwrite, sessions=True)
    for season, _ in QUERIES:
        for k in range(len(groups)):
            check_run_dir(out / run_name(season, k), overwrite)


def rows_of(run: Path, group: list[str], season: str, world: str, config: dict) -> list[dict]:
    """One row per method of ``group`` from the cross-session run's metrics.json."""
    metrics = json.loads((run / "metrics.json").read_text())
    results = {r["descriptor"]: r for r in metrics["results"]
               if r["protocol"] == "cross-session"}
    rows = []
    for method in group:
        r = results[method.split(":")[0]]
        recall = r["recall_at_n"]
        rows.append({
            "world": world, "sensor": config["sensor"], "frames": config["frames"],
            "query_season": season, "method": method, "preset": r["preset"],
            "n_queries": int(r["n_ranking_queries"]), "n_database": int(r["n_database"]),
            **{f"recall_at_{n}": None if recall[n - 1] is None else round(recall[n - 1], 4)
               for n in RECALL_N},
            "recall_at_1pct": None if r["recall_at_1pct"] is None
            else round(r["recall_at_1pct"], 4),
            "mrr": None if r["mrr"] is None else round(r["mrr"], 4),
            "run": str(run),
        })
    return rows


def cross_season(out: Path, world: str = "forest", methods=METHODS, frames: int | None = None,
                 azimuth_steps: int | None = None, cache_dir: Path | None = None,
                 workers: int = 1, overwrite: bool = False) -> list[dict]:
    """Simulate the three sessions, evaluate both query seasons, write and return the rows.

    ``frames`` / ``azimuth_steps``: None keeps the world preset's. ``overwrite``
    replaces earlier outputs (only those liris wrote, see :func:`check_outputs`).
    """
    out = Path(out)
    cache_dir = Path(cache_dir) if cache_dir else out / "cache"
    groups = method_groups(list(methods))
    check_outputs(out, world, groups, frames, azimuth_steps, overwrite)
    sessions = out / "sessions"
    config = reusable(sessions, world, frames, azimuth_steps)
    if config is None:
        liris("simulate", str(sessions), *simulation_args(world, frames, azimuth_steps), "-q",
              *(["--overwrite"] * overwrite), prog=PROG)
        config = json.loads((sessions / "session0" / "manifest.json").read_text())["config"]
    rows = []
    for season, k in QUERIES:
        for g, group in enumerate(groups):
            run = out / run_name(season, g)
            liris("eval", "--query", str(sessions / f"session{k}"), "--database",
                  str(sessions / "session0"), "-d", ",".join(group), "--out", str(run), "-q",
                  "--cache-dir", str(cache_dir), "--workers", str(workers),
                  *(["--overwrite"] * overwrite), prog=PROG)
            rows += rows_of(run, group, season, world, config)
    write_tables(out, rows)
    return rows


def write_tables(out: Path, rows: list[dict]) -> None:
    """OUT/cross_season.csv and OUT/cross_season.json, each written atomically."""
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=COLUMNS)
    w.writeheader()
    w.writerows([{k: ("" if v is None else v) for k, v in r.items()} for r in rows])
    atomic_write(out / "cross_season.csv", text.getvalue(), what="table")
    atomic_write(out / "cross_season.json", json.dumps(rows, indent=1) + "\n", what="table")


def markdown(rows: list[dict]) -> str:
    """Methods as rows; per query season Recall@1 / @5 / @10 / @25 ("n/a" when undefined)."""
    seasons = list(dict.fromkeys(r["query_season"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["query_season"], r["method"]): r for r in rows}
    head = ["method"] + [f"{s} queries: R@{' / R@'.join(map(str, RECALL_N))}" for s in seasons]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in methods:
        cells = [m]
        for s in seasons:
            r = cell.get((s, m))
            cells.append("n/a" if r is None else " / ".join(
                "n/a" if r[f"recall_at_{n}"] is None else f"{r[f'recall_at_{n}']:.3f}"
                for n in RECALL_N))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("results/cross_season"))
    p.add_argument("--world", default="forest", choices=("forest", "park"),
                   help="a natural world (only those have seasons)")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--frames", type=int, default=None, help="scans per session (the preset's)")
    p.add_argument("--azimuth-steps", type=int, default=None,
                   help="rays per beam and turn (default: the preset's)")
    p.add_argument("--cache-dir", type=Path, default=None, help="default: OUT/cache")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--overwrite", action="store_true",
                   help="replace earlier tables, runs and sessions (only those liris wrote)")
    a = p.parse_args(argv)
    rows = run_guarded(lambda: cross_season(a.out, a.world, a.methods.split(","), a.frames,
                                            a.azimuth_steps, a.cache_dir, a.workers,
                                            a.overwrite))
    print(markdown(rows))


if __name__ == "__main__":
    main()
