#!/usr/bin/env python
"""Train ESM's segment network on simulated worlds (maintainer command).

Needs the ``train`` extra (``pip install -e .[train]``: torch 2.13.0, CPU build).
Inference never needs torch: the result is a small ``.npz`` read by NumPy.

Steps (each cached in ``--work``; rerun to continue):

1. ``data``: simulate the training and validation worlds in memory and segment
   every scan (seeds disjoint from every preset and README sequence);
2. ``train``: the embedding network with the Wohlhart-Lepetit ratio triplet loss
   on squared L2 plus the pairwise term, hard negatives within the coarse class;
3. ``quality``: the quality branch on the frozen network;
4. ``export``: weights to ``lidar_iris_eval/descriptors/esm/esm_weights.npz`` and
   the validation figures to ``esm_validation.json`` (for the model card).

``--source scans`` (default) segments single scans; ``--source local-maps``
segments the **local maps** the ``local-maps`` preset builds at run time (the
last W = 30 scans, gt poses, input filter ``all``; true pairs: the same piece of
the same object in local maps >= W frames apart) and exports
``esm_localmap_weights.npz`` plus ``esm_localmap_validation.json``.

``--source segments`` trains on segment files of **any sequence liris reads**,
written by ``scripts/esm_segments.py`` (the ``local-maps`` preset's local maps
and front end on the sequence's poses): ``--train-segments`` (one or more
files, e.g. KITTI 05 and 06), ``--valid-segments`` (the held-out figures, e.g.
KITTI 00) and optionally ``--select-segments`` (checkpoint choice; without it
the last step is exported). Positives: views of one segment in local maps
>= W = 30 frames apart whose world centroids lie within ``--match`` m (1 m);
negatives mined hard in each batch: for each anchor the nearest (squared L2
embedding) positive of the other pairs, among those whose world centroid lies
at least ``--neg-distance`` m (5 m) from the anchor's (a nearer one may be the
same thing segmented differently). docs/esm.md "Training on real sequences".

Resumable: each world's segments are cached in ``--work`` and training writes
``state.pt`` (network, optimiser, step, training minutes, random states)
atomically every ``--checkpoint-every`` minutes and every ``--checkpoint-steps``
steps; rerunning the same command continues where it stopped, until
``--steps`` / ``--minutes`` of training in total. The export never replaces an
existing weights file unless ``--overwrite`` is given.

Example (the command that made the shipped local-map weights, model card)::

    OMP_NUM_THREADS=1 nice -n 10 python scripts/train_esm.py --source local-maps \
        --work /tmp/esm-lm --threads 1 --data-jobs 2 --batch 32 --steps 100000 \
        --minutes 45 --eval-every 6 --init lidar_iris_eval/descriptors/esm/esm_weights.npz \
        --overwrite
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from lidar_iris_eval.descriptors.esm.dataset import (
    SegmentSet,
    relabel_worlds,
    simulate_local_map_segments,
    simulate_segments,
    true_pairs,
)

#: training worlds: (seed, sensor, azimuth steps, frames, every k-th frame segmented,
#: shape variety). Large blocks (the ``kitti-scale`` preset's 55-100 m) leave room for
#: buildings and yards within 50 m of the road; a long drive sampled every 4th frame sees
#: many distinct objects; ``shape_variety`` (a world parameter no sequence uses) gives cars
#: five body types and trees multi-lobed or conifer crowns. Presets use seeds 11-13, 21, 31;
#: README sequences use those presets, the KITTI-00 trajectory (seed 0) or the matching
#: tuning world (seed 1001): all disjoint from these.
TRAIN_WORLDS = [
    *[(3001 + i, "hdl64", 1024, 800, 4, True) for i in range(6)],
    *[(3007 + i, "hdl64", 2048, 800, 4, True) for i in range(3)],
    *[(3010 + i, "hdl64", 720, 800, 4, True) for i in range(3)],
    *[(3013 + i, "vlp32", 1800, 800, 4, True) for i in range(2)],
    *[(3015 + i, "os1-64", 1024, 800, 4, True) for i in range(2)],
]
#: the held-out world the figures are reported on (same recipe)
VALID_WORLDS = [(4001, "hdl64", 1024, 800, 4, True)]
#: checkpoints are chosen on this world (same recipe), never on the validation world
SELECT_WORLDS = [(4002, "hdl64", 1024, 800, 4, True)]
#: a second held-out world with the simulator's default shapes (what sequences contain)
PLAIN_WORLDS = [(4003, "hdl64", 1024, 800, 4, False)]
WORLDS = {"train": TRAIN_WORLDS, "valid": VALID_WORLDS, "select": SELECT_WORLDS,
          "plain": PLAIN_WORLDS}

#: local-map worlds (``--source local-maps``): (seed, sensor, azimuth steps, frames, every
#: k-th frame's local map segmented, shape variety, blocks, block size). Every scan is
#: simulated (a local map holds 30); maps 10 frames apart overlap by two thirds, so every
#: 10th is enough. Half the worlds use ``small-mixed``'s street blocks (30-38 m, one block:
#: 800 frames circle it several times, many revisits), the rest larger grids; most use
#: 720 azimuth steps as ``small-mixed``. Seeds 5001-5016 / 6001-6002 are used by no preset
#: (11-13, 21, 31), README sequence (0, 1001) or the single-scan training (3001-3016,
#: 4001-4003), so both networks are compared on worlds neither has seen.
_SMALL, _GRID = ((1, 1), (30.0, 38.0)), ((3, 2), (30.0, 38.0))
_LARGE = ((3, 2), (55.0, 100.0))
LM_TRAIN_WORLDS = [
    *[(5001 + i, "hdl64", 720, 800, 10, False, *_SMALL) for i in range(3)],
    *[(5004 + i, "hdl64", 720, 800, 10, True, *_SMALL) for i in range(3)],
    *[(5007 + i, "hdl64", 720, 800, 10, i % 2 == 0, *_GRID) for i in range(3)],
    *[(5010 + i, "hdl64", 1024, 800, 10, True, *_LARGE) for i in range(3)],
    (5013, "hdl64", 2048, 800, 10, True, *_GRID),
    (5014, "vlp32", 1800, 800, 10, True, *_SMALL),
    (5015, "os1-64", 1024, 800, 10, True, *_GRID),
    (5016, "hdl64", 720, 800, 10, False, *_LARGE),
]
#: the reported validation world and the checkpoint-selection world: ``small-mixed``'s
#: recipe (HDL-64E, 720 steps, one 30-38 m block, default shapes), other seeds, 800 frames
LM_VALID_WORLDS = [(6001, "hdl64", 720, 800, 10, False, *_SMALL)]
LM_SELECT_WORLDS = [(6002, "hdl64", 720, 800, 10, False, *_SMALL)]
#: a held-out world of larger blocks with buildings (same recipe otherwise)
LM_PLAIN_WORLDS = [(6003, "hdl64", 720, 800, 10, False, *_GRID)]
LM_WORLDS = {"train": LM_TRAIN_WORLDS, "valid": LM_VALID_WORLDS, "select": LM_SELECT_WORLDS,
             "plain": LM_PLAIN_WORLDS}
#: the local-map preset's window (W = E = 30, the ``paper`` exclusion window) and filter
LM_WINDOW, LM_FILTER = 30, "all"


def world_config(seed: int, sensor: str, az: int, frames: int) -> dict:
    return dict(frames=frames, seed=seed, sensor=sensor, azimuth_steps=az, route="mixed",
                blocks=(3, 2), block_size=(55.0, 100.0), n_moving_cars=2)


def _one_world(job: tuple) -> SegmentSet:
    k, (seed, sensor, az, frames, every, variety) = job
    return simulate_segments(world_config(seed, sensor, az, frames), world_index=k, every=every,
                             progress=False, shape_variety=variety)


def _one_local_map_world(job: tuple) -> Path:
    k, (seed, sensor, az, frames, every, variety, blocks, block_size), folder = job
    path = folder / f"world_{seed}.npz"
    if not path.exists():  # one file per world: an interrupted data stage resumes
        cfg = dict(world_config(seed, sensor, az, frames), blocks=blocks, block_size=block_size)
        simulate_local_map_segments(cfg, world_index=k, every=every, window=LM_WINDOW,
                                    input_filter=LM_FILTER, progress=False,
                                    shape_variety=variety).save(path)
    return path


def stage_local_map_data(work: Path, which: str, jobs: int = 1) -> SegmentSet:
    """The local-map segments of ``LM_WORLDS[which]`` (simulated once, then read)."""
    path = work / f"lm_{which}_segments.npz"
    if path.exists():
        return SegmentSet.load(path)
    folder = work / f"lm_{which}"
    folder.mkdir(parents=True, exist_ok=True)
    todo = [(k, w, folder) for k, w in enumerate(LM_WORLDS[which])]
    if jobs > 1 and len(todo) > 1:
        from multiprocessing import get_context

        with get_context("spawn").Pool(jobs) as pool:
            files = pool.map(_one_local_map_world, todo, chunksize=1)
    else:
        files = [_one_local_map_world(job) for job in todo]
    data = SegmentSet.concat([SegmentSet.load(f) for f in files])
    data.save(path)
    print(f"{path.name}: {len(data)} segments, "
          f"{len(true_pairs(data, min_frame_gap=LM_WINDOW))} true pairs", flush=True)
    return data


def stage_data(work: Path, which: str, jobs: int = 1, source: str = "scans") -> SegmentSet:
    """The training or validation segments (simulated once, then read from ``work``).

    ``jobs`` worlds are simulated at once (one process each); the result does not
    depend on it.
    """
    if source == "local-maps":
        return stage_local_map_data(work, which, jobs)
    worlds = WORLDS[which]
    path = work / f"{which}_segments.npz"
    if path.exists():
        return SegmentSet.load(path)
    todo = list(enumerate(worlds))
    if jobs > 1 and len(todo) > 1:
        from multiprocessing import get_context

        with get_context("spawn").Pool(jobs) as pool:
            parts = pool.map(_one_world, todo, chunksize=1)
    else:
        parts = [_one_world(job) for job in todo]
    data = SegmentSet.concat(parts)
    data.save(path)
    print(f"{path.name}: {len(data)} segments, {len(true_pairs(data))} true pairs", flush=True)
    return data


def load_segments(files: list[Path], flag: str) -> SegmentSet:
    """The segment files ``files`` as one set, file ``k`` becoming world ``k``."""
    from lidar_iris_eval.errors import LirisError

    parts = []
    for f in files:
        try:
            parts.append(SegmentSet.load(f))
        except (OSError, KeyError, ValueError) as err:
            raise LirisError(f"{flag} {f}", f"cannot read a segments file ({err})") from None
    return relabel_worlds(parts)


def train_on_segments(args) -> None:
    """``--source segments``: train on files of scripts/esm_segments.py (module docstring)."""
    from lidar_iris_eval.errors import LirisError

    if not args.train_segments or not args.valid_segments:
        raise LirisError("--source segments", "give --train-segments and --valid-segments")
    if args.out is None:
        raise LirisError("--source segments", "give --out (the new weights file)")
    args.pair_radius = 1.0 if args.match is None else args.match
    args.neg_distance = 5.0 if args.neg_distance is None else args.neg_distance
    args.work.mkdir(parents=True, exist_ok=True)
    stages = set(args.stages.split(",")) - {"data"}
    start = time.time()
    train = load_segments(args.train_segments, "--train-segments")
    pairs = true_pairs(train, args.pair_radius, min_frame_gap=args.min_frame_gap)
    if len(pairs) == 0:
        raise LirisError("--train-segments", f"no positives (views >= {args.min_frame_gap} "
                                             f"frames apart within {args.pair_radius} m)")
    print(f"train: {len(train)} segments, {len(pairs)} true pairs", flush=True)
    from lidar_iris_eval.descriptors.esm import training

    valid = load_segments(args.valid_segments, "--valid-segments")
    select = (load_segments(args.select_segments, "--select-segments")
              if args.select_segments else None)
    training.run(train, lambda: valid, args, stages, start,
                 select_set=(lambda: select) if select is not None else None)
    print(json.dumps({"minutes": round((time.time() - start) / 60, 1)}))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("esm-train"))
    ap.add_argument("--source", choices=["scans", "local-maps", "segments"], default="scans",
                    help="segments of single scans or of run-time local maps of simulated "
                         "worlds, or segment files of any sequence (scripts/esm_segments.py)")
    ap.add_argument("--train-segments", type=Path, nargs="+", default=[],
                    help="--source segments: the training segment files")
    ap.add_argument("--valid-segments", type=Path, nargs="+", default=[],
                    help="--source segments: held-out segment files the figures are reported on")
    ap.add_argument("--select-segments", type=Path, nargs="+", default=[],
                    help="--source segments: held-out files checkpoints are chosen on")
    ap.add_argument("--match", type=float, default=None,
                    help="positives' world-centroid distance (m) [1.0 for --source segments, "
                         "2.0 otherwise]")
    ap.add_argument("--neg-distance", type=float, default=None,
                    help="no negative whose world centroid is this close to the anchor's (m) "
                         "[5.0 for --source segments, off otherwise: classes are known]")
    ap.add_argument("--min-frame-gap", type=int, default=LM_WINDOW,
                    help="--source segments: positives' frames at least this far apart: the "
                         "segment files' W (esm_segments.py --exclude) [30]")
    ap.add_argument("--checkpoint-steps", type=int, default=0,
                    help="also write state.pt every N steps (0: only by --checkpoint-every)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace an existing --out weights file (a finished model)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data-jobs", type=int, default=1, help="worlds simulated at once")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--quality-steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=48, help="anchor-positive pairs per step")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--lr", type=float, default=1e-3,
                    help="Adam's learning rate; divided by 5 at 70 %% of --minutes")
    ap.add_argument("--eval-every", type=float, default=8.0,
                    help="minutes between checkpoint scores on the selection world")
    ap.add_argument("--checkpoint-every", type=float, default=3.0,
                    help="minutes between resumable checkpoints (state.pt)")
    ap.add_argument("--norm-scale", type=float, default=-1.0,
                    help="segment normalisation: 0 per-segment RMS radius, >0 this constant, "
                         "<0 (default) the training segments' median RMS radius")
    ap.add_argument("--align-yaw", action="store_true",
                    help="turn each segment to its horizontal principal axis before the network")
    ap.add_argument("--init", type=Path, default=None,
                    help="start from these weights (.npz; their architecture, norm scale and "
                         "alignment) instead of a random network")
    ap.add_argument("--compare", type=Path, default=None,
                    help="weights scored beside the new ones at export (default: the shipped "
                         "esm_weights.npz for --source local-maps)")
    ap.add_argument("--minutes", type=float, default=30.0,
                    help="stop after this many minutes of training (summed over resumed runs)")
    ap.add_argument("--stages", default="data,train,quality,export")
    ap.add_argument("--out", type=Path, default=None, help="weights file (default: in package)")
    args = ap.parse_args(argv)
    if args.source == "segments":
        return train_on_segments(args)
    args.pair_radius = 2.0 if args.match is None else args.match
    args.neg_distance = args.neg_distance or 0.0
    if args.min_frame_gap != LM_WINDOW:
        ap.error("--min-frame-gap is for --source segments")
    args.work.mkdir(parents=True, exist_ok=True)
    local = args.source == "local-maps"
    args.min_frame_gap = LM_WINDOW if local else 10
    if local and args.out is None:
        from lidar_iris_eval.descriptors.esm import network

        args.out = network.LOCALMAP_WEIGHTS_FILE
    if local and args.compare is None:
        from lidar_iris_eval.descriptors.esm import network

        args.compare = network.WEIGHTS_FILE
    stages = set(args.stages.split(","))
    start = time.time()
    train = stage_data(args.work, "train", args.data_jobs, args.source)
    if "data" in stages:
        for which in ("valid", "select", "plain"):
            stage_data(args.work, which, args.data_jobs, args.source)
    if stages == {"data"}:
        return
    from lidar_iris_eval.descriptors.esm import training

    def data(which: str):
        return lambda: stage_data(args.work, which, 1, args.source)

    training.run(train, data("valid"), args, stages, start, select_set=data("select"),
                 extra_valid={"default_shapes" if not local else "grid_world": data("plain")})
    print(json.dumps({"minutes": round((time.time() - start) / 60, 1)}))


if __name__ == "__main__":
    from lidar_iris_eval.cli import run_guarded

    run_guarded(main)
