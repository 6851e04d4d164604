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

Example (the command that made the shipped weights)::

    nice -n 10 python scripts/train_esm.py --work /tmp/esm-train --threads 2
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from lidar_iris_eval.descriptors.esm.dataset import SegmentSet, simulate_segments, true_pairs

#: training worlds: (seed, sensor, azimuth steps, frames). Presets use seeds 11-13, 21, 31;
#: README sequences use those presets or the KITTI-00 trajectory (seed 0).
TRAIN_WORLDS = [
    (1001, "hdl64", 1024, 500),
    (1002, "hdl64", 2048, 500),
    (1003, "vlp16", 1800, 500),
    (1004, "hdl64", 720, 500),
]
VALID_WORLDS = [(2001, "hdl64", 1024, 500)]


def world_config(seed: int, sensor: str, az: int, frames: int) -> dict:
    return dict(frames=frames, seed=seed, sensor=sensor, azimuth_steps=az, route="mixed",
                block_size=(30.0, 38.0), n_moving_cars=2)


def stage_data(work: Path, which: str) -> SegmentSet:
    """The training or validation segments (simulated once, then read from ``work``)."""
    worlds = TRAIN_WORLDS if which == "train" else VALID_WORLDS
    path = work / f"{which}_segments.npz"
    if path.exists():
        return SegmentSet.load(path)
    parts = [simulate_segments(world_config(*w), world_index=k) for k, w in enumerate(worlds)]
    data = SegmentSet.concat(parts)
    data.save(path)
    print(f"{path.name}: {len(data)} segments, {len(true_pairs(data))} true pairs", flush=True)
    return data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("esm-train"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--quality-steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=48, help="anchor-positive pairs per step")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--norm-scale", type=float, default=-1.0,
                    help="segment normalisation: 0 per-segment RMS radius, >0 this constant, "
                         "<0 (default) the training segments' median RMS radius")
    ap.add_argument("--minutes", type=float, default=30.0, help="stop training after this")
    ap.add_argument("--stages", default="data,train,quality,export")
    ap.add_argument("--out", type=Path, default=None, help="weights file (default: in package)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    stages = set(args.stages.split(","))
    start = time.time()
    train = stage_data(args.work, "train")
    if "data" in stages:
        stage_data(args.work, "valid")
    if stages == {"data"}:
        return
    from lidar_iris_eval.descriptors.esm import training

    training.run(train, lambda: stage_data(args.work, "valid"), args, stages, start)
    print(json.dumps({"minutes": round((time.time() - start) / 60, 1)}))


if __name__ == "__main__":
    main()
