"""Benchmark LiDAR Iris: extraction, the batched comparison kernel, and KITTI-00-sized runs.

Usage::

    .venv/bin/python scripts/bench_lidar_iris.py                 # everything, 4541 frames
    .venv/bin/python scripts/bench_lidar_iris.py --frames 1000   # smaller database
    .venv/bin/python scripts/bench_lidar_iris.py --no-full       # skip protocol 1/2 runs
    .venv/bin/python scripts/bench_lidar_iris.py --harmonics     # phase-correlation study
    .venv/bin/python scripts/bench_lidar_iris.py --search        # shift searches: cost, misses
    .venv/bin/python scripts/bench_lidar_iris.py --sensors       # searches per sensor preset
    .venv/bin/python scripts/bench_lidar_iris.py --pairs SEQ --sensor os0-128
                                                # every pair < 4 m of a sequence vs the oracle

Figures (medians where repeated):

* extraction per scan (binning, log-Gabor filtering, packing) on one core, for
  a real 121,618-point KITTI scan (or a synthetic 120k-point cloud without
  ../shared);
* pairs/s of the compiled kernel (one thread and all threads) against a
  straightforward per-pair NumPy loop on unpacked bits, on the same pairs in
  the same run, and whether their distances are identical;
* protocol 2 (every unordered pair once, as the distance is symmetric, filling
  the full N x N affinity) and protocol 1 (each query i against all
  j <= i - 30, best match) on N frames, in blocks of queries;
* peak resident memory (ru_maxrss).

The database is built from perturbed copies of the four real scans (random yaw,
translation up to 4 m, random subsampling to 40-100 %): no simulator needed.
The machine is shared, so the load average is printed next to the figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import time
from pathlib import Path

import numpy as np

from lidar_iris_eval.bench import lidar_iris_reference
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors import lidar_iris as li

VELODYNE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "samples" / "00"
VELODYNE = VELODYNE / "velodyne"


def load_scans() -> list[np.ndarray]:
    """The four real KITTI scans, or four synthetic 120k-point clouds without ../shared."""
    files = sorted(VELODYNE.glob("*.bin")) if VELODYNE.is_dir() else []
    if files:
        return [np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files]
    print("../shared scans not found: using synthetic 120k-point clouds")
    rng = np.random.default_rng(0)
    out = []
    for _ in range(4):
        r = 60 * np.sqrt(rng.random(120_000))
        a = rng.random(120_000) * 2 * np.pi
        z = np.where(rng.random(120_000) < 0.6, -1.7, rng.uniform(-1.7, 4, 120_000))
        out.append(np.c_[r * np.cos(a), r * np.sin(a), z].astype(np.float32))
    return out


def perturb(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random yaw, a translation of up to 4 m and random subsampling to 40-100 %."""
    yaw = rng.uniform(0, 2 * np.pi)
    dist, ang = rng.uniform(0, 4), rng.uniform(0, 2 * np.pi)
    keep = points[rng.random(len(points)) < rng.uniform(0.4, 1.0)].astype(np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    x = c * keep[:, 0] - s * keep[:, 1] + dist * np.cos(ang)
    y = s * keep[:, 0] + c * keep[:, 1] + dist * np.sin(ang)
    return np.c_[x, y, keep[:, 2]].astype(np.float32)


def median_ms(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU (process) milliseconds of ``fn()``; CPU time is less
    disturbed by other jobs on a shared machine."""
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def bench_extraction(desc, scans) -> None:
    p = desc.params
    scan = max(scans, key=len)
    image = li.iris_image(scan, p)
    desc.compute(scan)
    print(f"\n== extraction ({len(scan)} points, preset {desc.preset}, 1 core, median of 30)")
    for label, fn in [
        ("iris image (binning)", lambda: li.iris_image(scan, p)),
        ("features + packing + spectra", lambda: li.describe_image(image, p)),
        ("compute() total", lambda: desc.compute(scan)),
    ]:
        wall, cpu = median_ms(fn, 30)
        print(f"{label:30s} {wall:7.2f} ms wall, {cpu:7.2f} ms CPU")


def build_database(desc, scans, frames: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = time.perf_counter()
    db = np.stack([desc.compute(perturb(scans[i % len(scans)], rng)) for i in range(frames)])
    dt = time.perf_counter() - t
    print(f"\nbuilt {frames} descriptors from perturbed real scans in {dt:.1f} s")
    mb = db.nbytes / 2**20
    print(f"({1e3 * dt / frames:.1f} ms per frame incl. perturbation; {mb:.0f} MiB stored)")
    return db


def bench_kernel(desc, db, baseline_pairs: int, threads: int) -> None:
    import numba

    p = desc.params
    rng = np.random.default_rng(1)
    n = len(db)
    qi = rng.integers(0, n, baseline_pairs)
    dj = rng.integers(0, n, baseline_pairs)
    feats = {}
    for i in set(qi.tolist()) | set(dj.tolist()):
        feats[i] = li.binary_features(db[i]["image"], p)
    t, c = time.perf_counter(), time.process_time()
    slow = [
        lidar_iris_reference(db[i], db[j], feats[i], feats[j], p)
        for i, j in zip(qi, dj, strict=True)
    ]
    wall_slow = (time.perf_counter() - t) / baseline_pairs
    cpu_slow = (time.process_time() - c) / baseline_pairs
    fast = [desc.distance(db[i], db[j])[0] for i, j in zip(qi, dj, strict=True)]
    same = np.array_equal(np.array(slow), np.array(fast), equal_nan=True)

    block = db[: min(256, n)]
    desc.pairwise(block[:2], db[:2])  # compile / load the cache
    print(f"\n== comparison kernel ({len(block)} queries x {n} database)")
    print(
        f"straightforward per-pair NumPy loop: {1e6 * wall_slow:9.1f} us/pair wall, "
        f"{1e6 * cpu_slow:9.1f} CPU-us/pair ({baseline_pairs} pairs)"
    )
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)  # e.g. under taskset
    for th in sorted({1, threads}):
        numba.set_num_threads(th)
        t, c = time.perf_counter(), time.process_time()
        desc.pairwise(block, db)
        wall = (time.perf_counter() - t) / (len(block) * n)
        cpu = (time.process_time() - c) / (len(block) * n)
        print(
            f"batched kernel, {th} thread(s): {1e6 * wall:7.2f} us/pair wall "
            f"({1 / wall:,.0f} pairs/s, {wall_slow / wall:,.0f}x the loop), "
            f"{1e6 * cpu:7.2f} CPU-us/pair ({cpu_slow / cpu:,.0f}x the loop)"
        )
    numba.set_num_threads(threads)
    print(f"kernel distances identical to the loop on {baseline_pairs} random pairs: {same}")


def bench_numpy_batched(db, pairs: int = 2000) -> None:
    """The best case for a numba-free kernel: vectorised NumPy masked Hamming of
    one query against many candidates at one common shift (a real kernel also
    needs a per-pair window, i.e. gathers, and the shift estimate)."""
    n = min(pairs, len(db))
    dt = np.ascontiguousarray(db["T"][:n])
    dm = np.ascontiguousarray(db["M"][:n])
    wm = dm.shape[1]

    def one_shift(s: int):
        t, m = np.roll(dt[0], s, axis=1), np.roll(dm[0], s, axis=1)
        mask = m[None] | dm
        keep = ~mask
        diff = np.bitwise_count((t[None, :wm] ^ dt[:, :wm]) & keep).sum((1, 2))
        diff += np.bitwise_count((t[None, wm:] ^ dt[:, wm:]) & keep).sum((1, 2))
        return diff, np.bitwise_count(mask).sum((1, 2))

    one_shift(1)
    _, cpu = median_ms(lambda: one_shift(3), 5)
    per_pair = 1e3 * cpu / n
    print(
        f"vectorised NumPy (no numba), Hamming only at one shift: {per_pair:.2f} CPU-us/pair "
        f"per shift, {5 * per_pair:.1f} for a 5-shift window"
    )


def bench_protocols(desc, db, block: int, exclusion: int) -> None:
    n = len(db)
    print(f"\n== full runs on {n} frames, blocks of {block} queries")
    t, c = time.perf_counter(), time.process_time()
    affinity = np.full((n, n), np.nan, dtype=np.float32)
    for a in range(0, n, block):
        b = min(n, a + block)
        d, _ = desc.pairwise(db[a:b], db[:b])  # each unordered pair once (plus the block square)
        affinity[a:b, :b] = d
        affinity[:b, a:b] = d.T
    t2, c2 = time.perf_counter() - t, time.process_time() - c
    pairs = n * (n - 1)
    print(
        f"protocol 2: {t2:7.1f} s wall, {c2:7.1f} s CPU for the {n}x{n} affinity "
        f"({pairs:,} ordered pairs)"
    )

    t, c = time.perf_counter(), time.process_time()
    best = np.full(n, -1)
    best_d = np.full(n, np.inf)
    for a in range(exclusion, n, block):
        b = min(n, a + block)
        d, _ = desc.pairwise(db[a:b], db[: b - exclusion])
        rows = np.arange(a, b)[:, None]
        d[np.arange(b - exclusion)[None, :] > rows - exclusion] = np.inf
        best[a:b] = np.argmin(d, axis=1)
        best_d[a:b] = d[np.arange(b - a), best[a:b]]
    t1, c1 = time.perf_counter() - t, time.process_time() - c
    print(
        f"protocol 1 (E={exclusion}): {t1:7.1f} s wall, {c1:7.1f} s CPU "
        f"(each query vs all j <= i - {exclusion})"
    )
    consistent = np.allclose(
        best_d[exclusion:],
        np.nanmin(np.where(np.tril(np.ones((n, n), bool), -exclusion), affinity, np.inf), axis=1)[
            exclusion:
        ],
    )
    print(f"protocol 1 best distances equal the protocol 2 affinity's: {consistent}")


def harmonics_study(scans, cases: int = 120) -> None:
    """How often the window around the phase-correlation peak misses the best shift."""
    rng = np.random.default_rng(1)
    pert = [(i % len(scans), perturb(scans[i % len(scans)], rng)) for i in range(cases)]
    print(f"\n== phase-correlation harmonics ({cases} perturbed copies vs their originals)")
    for preset in ("paper", "reference"):
        full = get_descriptor("lidar-iris", preset=preset, shift_window=180)
        base = [full.compute(s) for s in scans]
        cand = [full.compute(pts) for _, pts in pert]
        best = np.array(
            [full.distance(base[b], c)[0] for (b, _), c in zip(pert, cand, strict=True)]
        )
        for k in (0, 64, 48, 32, 24, 16, 12, 8):
            desc = get_descriptor("lidar-iris", preset=preset, shift_harmonics=k)

            def respec(d, p=desc.params):
                out = np.zeros((), li.descriptor_dtype(p))
                out["image"], out["T"], out["M"] = d["image"], d["T"], d["M"]
                out["spec_re"], out["spec_im"] = li.row_spectra(d["image"], p)
                return out

            got = np.array(
                [
                    desc.distance(respec(base[b]), respec(c))[0]
                    for (b, _), c in zip(pert, cand, strict=True)
                ]
            )
            excess = got - best
            misses = int(np.sum(excess > 1e-12))
            print(
                f"{preset:9s} K={k:3d}: window misses the best shift {misses:3d}/{cases}, "
                f"excess distance max {excess.max():.4f} mean {excess.mean():.5f}"
            )


def protocol2_seconds(desc, db, block: int) -> tuple[float, float]:
    """Wall and CPU seconds of the protocol 2 affinity (each unordered pair once)."""
    n = len(db)
    t, c = time.perf_counter(), time.process_time()
    for a in range(0, n, block):
        b = min(n, a + block)
        desc.pairwise(db[a:b], db[:b])
    return time.perf_counter() - t, time.process_time() - c


def search_study(scans, frames: int, block: int, rounds: int = 2, cases: int = 400) -> None:
    """Shift searches side by side: protocol 2 cost as a ratio, and how often each
    reaches the exhaustive-best shift on perturbed real scans (rotated + translated).

    Both searches run alternately on the same database in the same process, so
    the ratio is fair on a shared machine; the minimum of ``rounds`` runs is kept.
    """
    variants = {
        "phase": dict(shift_search="phase"),
        "phase+refine": dict(shift_search="phase+refine"),
    }
    searches = tuple(variants)
    descs = {s: get_descriptor("lidar-iris", **kw) for s, kw in variants.items()}
    db = build_database(descs["phase"], scans, frames)
    for d in descs.values():
        d.pairwise(db[:2], db[:2])  # compile
    best = {s: (np.inf, np.inf) for s in searches}
    for _ in range(rounds):
        for s, d in descs.items():
            wall, cpu = protocol2_seconds(d, db, block)
            best[s] = (min(best[s][0], wall), min(best[s][1], cpu))
    base = best["phase"]
    print(f"\n== protocol 2 on {frames} frames, {rounds} alternating rounds (min), load "
          f"{os.getloadavg()[0]:.1f}")
    for s in searches:
        wall, cpu = best[s]
        print(f"{s:13s} {wall:7.1f} s wall ({wall / base[0]:.2f}x), {cpu:7.1f} s CPU "
              f"({cpu / base[1]:.2f}x)")
    rng = np.random.default_rng(7)
    oracle = get_descriptor("lidar-iris", shift_search="exhaustive")
    pert = [(i % len(scans), perturb(scans[i % len(scans)], rng)) for i in range(cases)]
    base_d = [oracle.compute(s) for s in scans]
    cand = [oracle.compute(pts) for _, pts in pert]
    pairs = [(base_d[b], c) for (b, _), c in zip(pert, cand, strict=True)]
    exact = np.array([oracle.distance(a, c)[0] for a, c in pairs])
    print(f"\n== {cases} rotated + translated (<= 4 m) + subsampled copies of the real scans")
    for s in searches:
        got = np.array([descs[s].distance(a, c)[0] for a, c in pairs])
        excess = got - exact
        print(f"{s:13s} exhaustive-best shift on {np.mean(excess <= 0) * 100:5.1f}% of pairs, "
              f"within 0.01 on {np.mean(excess <= 0.01) * 100:5.1f}%, "
              f"max excess {excess.max():.4f}")


def simulated_views(sensor: str, places: int, views: int, seed: int = 5):
    """Scans of the simulated town with ``sensor``: ``views`` poses per place (up to
    1.4 m off in x and y, any yaw). Returns ``[(place, points), ...]``."""
    from lidar_iris_eval.simulate import build_scenario, resolve_config
    from lidar_iris_eval.simulate.sensors import simulate_scan

    scen = build_scenario(resolve_config("tiny-mixed", dict(sensor=sensor)))
    rng = np.random.default_rng(seed)
    out = []
    for place, frame in enumerate(np.linspace(0, len(scen.poses) - 1, places).astype(int)):
        for _ in range(views):
            pose = scen.poses[frame].copy()
            yaw = rng.uniform(0, 2 * np.pi)
            turn = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                             [0, 0, 1.0]])
            pose[:3, :3] = pose[:3, :3] @ turn
            pose[:2, 3] += rng.uniform(-1.4, 1.4, 2)
            scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(frame), pose, rng)
            out.append((place, scan.points))
    return out


def sensors_study(places: int = 16, views: int = 4) -> None:
    """Per sensor preset: same-place pairs at the exhaustive-best shift, per search."""
    from lidar_iris_eval.sensors import SENSORS

    print(f"\n== simulated same-place pairs ({places} places x {views} views per sensor, "
          "<= 2 m apart, any yaw): share at the exhaustive best / within 0.01")
    for sensor in SENSORS:
        scans = simulated_views(sensor, places, views)
        place = np.array([p for p, _ in scans])
        pairs = (place[:, None] == place[None, :]) & ~np.eye(len(scans), dtype=bool)
        oracle = get_descriptor("lidar-iris", sensor=sensor, shift_search="exhaustive")
        descs = np.stack([oracle.compute(pts) for _, pts in scans])
        best = oracle.pairwise(descs, descs)[0][pairs]
        line = f"{sensor:8s} ({pairs.sum()} pairs, median best {np.median(best):.3f})"
        for search in ("phase", "phase+refine"):
            desc = get_descriptor("lidar-iris", sensor=sensor, shift_search=search)
            excess = desc.pairwise(descs, descs)[0][pairs] - best
            line += (f"  {search}: {np.mean(excess <= 0) * 100:5.1f}% / "
                     f"{np.mean(excess <= 0.01) * 100:5.1f}%")
        print(line, flush=True)


def pairs_study(path: str, sensor: str, peaks: tuple[int, ...] = (2, 3, 4)) -> None:
    """Every pair < 4 m of a sequence against the exhaustive oracle, split into
    recognisable and weak pairs (:mod:`lidar_iris_eval.descriptors.lidar_iris.oracle`),
    per metre band, for ``phase`` and ``phase+refine`` with several band peaks.

    CPU seconds of the pairs' comparisons are printed as ratios against ``phase``
    in the same run (small: only the listed pairs are compared)."""
    from lidar_iris_eval.descriptors.lidar_iris.oracle import search_agreement
    from lidar_iris_eval.io import open_sequence

    seq = open_sequence(path)
    base = get_descriptor("lidar-iris", sensor=sensor)
    descs = np.stack([base.compute(seq[i]) for i in range(len(seq))])
    positions = seq.positions("lidar")
    variants = {"phase": dict(shift_search="phase")}
    variants.update({f"phase+refine, {k} peaks": dict(refine_peaks=k) for k in peaks})
    print(f"\n== {path} ({len(seq)} frames, sensor {sensor}): pairs < 4 m against the oracle; "
          "exact / within 0.01")
    for name, kw in variants.items():
        desc = get_descriptor("lidar-iris", sensor=sensor, **kw)
        res = search_agreement(desc, descs, positions)
        rec = res.recognisable
        line = (f"{name:24s} all {len(rec)}: {res.rate() * 100:5.1f} / "
                f"{res.rate(tolerance=0.01) * 100:5.1f} %  recognisable {rec.sum()}: "
                f"{res.rate(rec) * 100:6.2f} %  weak {(~rec).sum()}: "
                f"{res.rate(~rec) * 100:5.1f} / {res.rate(~rec, 0.01) * 100:5.1f} %")
        print(line, flush=True)
    print(f"recognisable: oracle distance < {res.threshold:.3f} (1st percentile of "
          f"{res.unrelated.size} unrelated pairs > 15 m apart; their median "
          f"{np.median(res.unrelated):.3f}); weak pairs' median best "
          f"{np.median(res.best[~rec]):.3f}")
    for lo in range(4):
        band = (res.metres >= lo) & (res.metres < lo + 1)
        print(f"  {lo}-{lo + 1} m: {band.sum():4d} pairs, {np.mean(rec[band]) * 100:5.1f} % "
              f"recognisable, median best {np.median(res.best[band]):.3f}, default search "
              f"exact {res.rate(band) * 100:5.1f} %")


def routes_study(velodyne: str, preset: str, rounds: int = 5) -> None:
    """Fast kernel vs the baseline route on all pairs of ~200 scans: ratio and equality."""
    import numba

    numba.set_num_threads(1)
    desc = get_descriptor("lidar-iris", preset=preset)
    if velodyne:
        files = sorted(Path(velodyne).glob("*.bin"))[::23][:200]
        db = np.stack([desc.compute(np.fromfile(f, np.float32).reshape(-1, 4)[:, :3])
                       for f in files])
    else:
        db = build_database(desc, load_scans(), 200)
    print(f"load average {os.getloadavg()[0]:.2f}; {len(db)} descriptors, {len(db) ** 2} pairs")
    for search in ("phase+refine", "phase"):
        p = dataclasses.replace(desc.params, shift_search=search)
        for route in ("fast", "baseline"):
            li.compare_blocks(db[:2], db[:2], p, route=route)
        cpu = {"fast": [], "baseline": []}
        out = {}
        for _ in range(rounds):
            for route in ("baseline", "fast"):
                start = time.process_time()
                out[route] = li.compare_blocks(db, db, p, route=route)
                cpu[route].append((time.process_time() - start) / len(db) ** 2)
        same = (np.array_equal(out["fast"][0], out["baseline"][0], equal_nan=True)
                and np.array_equal(out["fast"][1], out["baseline"][1]))
        old, new = (1e6 * float(np.median(cpu[r])) for r in ("baseline", "fast"))
        print(f"{search:13s} baseline {old:6.2f} CPU-us/pair, fast {new:6.2f}, ratio "
              f"{old / new:.2f}, bitwise equal: {same}")
    print(f"load average {os.getloadavg()[0]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4541)
    parser.add_argument("--block", type=int, default=512, help="queries per pairwise call")
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--baseline-pairs", type=int, default=200)
    parser.add_argument("--no-full", action="store_true", help="skip the protocol 1/2 runs")
    parser.add_argument("--harmonics", action="store_true", help="only the harmonics study")
    parser.add_argument("--routes", metavar="VELODYNE", nargs="?", const="",
                        help="only the fast kernel vs the baseline route (the previous kernel), "
                             "interleaved, CPU time, 1 thread; on the .bin scans of VELODYNE "
                             "(every 23rd) or the perturbed real scans")
    parser.add_argument("--search", action="store_true",
                        help="only the shift-search comparison (cost ratio, misses)")
    parser.add_argument("--sensors", action="store_true",
                        help="only the per-sensor-preset search study (simulated)")
    parser.add_argument("--pairs", metavar="SEQUENCE",
                        help="only the study of every pair < 4 m of SEQUENCE against the oracle")
    parser.add_argument("--sensor", default="hdl64", help="sensor preset for --pairs")
    args = parser.parse_args()

    print(f"load average at start: {os.getloadavg()}")
    if args.sensors:
        sensors_study()
        return
    if args.pairs:
        pairs_study(args.pairs, args.sensor)
        return
    scans = load_scans()
    if args.routes is not None:
        routes_study(args.routes, args.preset)
        return
    if args.harmonics:
        harmonics_study(scans)
        return
    if args.search:
        search_study(scans, args.frames, args.block)
        return
    desc = get_descriptor("lidar-iris", preset=args.preset)
    bench_extraction(desc, scans)
    db = build_database(desc, scans, args.frames)
    bench_kernel(desc, db, args.baseline_pairs, args.threads)
    bench_numpy_batched(db)
    if not args.no_full:
        bench_protocols(desc, db, args.block, exclusion=30)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"\npeak resident memory: {peak:.2f} GiB")
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
