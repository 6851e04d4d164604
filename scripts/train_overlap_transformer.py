"""Train OverlapTransformer on simulated worlds (maintainers; needs the ``train`` extra).

    pip install -e ".[train]"        # exactly torch==2.13.0, the CPU build
    OMP_NUM_THREADS=1 nice -n 10 python scripts/train_overlap_transformer.py \
        --work /tmp/ot-train --worlds 4 --frames 400 --minutes 120

Steps (each resumable: finished worlds, depth images and overlap matrices are
kept in ``--work``, and training resumes from ``--work/checkpoint.pth.tar``):

1. simulate ``--worlds`` worlds (``small-mixed`` route, seeds 5001, 5002, ...);
2. their depth images with the method's own projection (``paper``: PNG depth);
3. OverlapNet-style overlap matrices (``liris gt --gt overlap``'s computation):
   positives at overlap >= 0.3, negatives below, as the authors train;
4. triplets: a query, ``--positives`` positives and ``--negatives`` negatives;
   loss ``mean(max(0, margin + max_pos d^2 - d^2_neg))`` (the authors' margin 0.5,
   the hardest positive), Adam;
5. ``--out`` (default ``--work/overlap_transformer_sim.npz``): the weights under
   the authors' names, readable by ``--param overlap-transformer.weights=PATH``.

The checkpoint is a plain ``torch.save`` of ``{"epoch", "step", "state_dict",
"optimizer"}``, which the method also reads directly (no torch at run time).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def prepare_world(work: Path, seed: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 64, 900) depth images and the (N, N) overlap matrix of one simulated world."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.evaluation.overlap import cached_overlap_matrix
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    done = work / f"world{seed}.npz"
    if done.is_file():
        with np.load(done) as z:
            return z["images"], z["overlap"]
    seq_dir = work / f"world{seed}"
    if not (seq_dir / "poses.txt").is_file():
        simulate_sequence(seq_dir, "small-mixed", overwrite=True, frames=frames, seed=seed)
    seq = open_sequence(seq_dir)
    desc = get_descriptor("overlap-transformer", preset="paper")
    images = np.stack([desc.range_image(seq[k]) for k in range(len(seq))])
    overlap, _ = cached_overlap_matrix(seq, work / "cache", progress=False)
    np.savez(done, images=images.astype(np.float32), overlap=overlap)
    return images, overlap


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--worlds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=5001)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--minutes", type=float, default=120.0)
    ap.add_argument("--steps", type=int, default=100000)
    ap.add_argument("--positives", type=int, default=2)
    ap.add_argument("--negatives", type=int, default=4)
    ap.add_argument("--margin", type=float, default=0.5)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--threshold", type=float, default=0.3)
    ap.add_argument("--init", choices=("random-init", "torch"), default="random-init",
                    help="start from the shipped random weights or torch's default init")
    args = ap.parse_args(argv)

    import torch

    from lidar_iris_eval.descriptors.overlap_transformer import network, torch_net

    torch.set_num_threads(args.threads)
    args.work.mkdir(parents=True, exist_ok=True)
    out = args.out or args.work / "overlap_transformer_sim.npz"
    worlds = [prepare_world(args.work, args.first_seed + k, args.frames)
              for k in range(args.worlds)]
    # (world, query) with at least one positive and one negative among the other frames
    queries = []
    for w, (_, ov) in enumerate(worlds):
        for i in range(len(ov)):
            pos = (ov[i] >= args.threshold) & (np.arange(len(ov)) != i)
            if pos.any() and (~pos).sum() > 1:
                queries.append((w, i))
    print(f"{len(queries)} training queries in {len(worlds)} worlds", flush=True)

    net = torch_net.OverlapTransformerNet()
    if args.init == "random-init":
        torch_net.load_numpy(net, network.random_weights(0))  # the shipped start
    else:
        torch.manual_seed(args.first_seed)
        net = torch_net.OverlapTransformerNet()
    opt = torch.optim.Adam(net.parameters(), args.lr)
    ckpt = args.work / "checkpoint.pth.tar"
    step = 0
    if ckpt.is_file():
        state = torch.load(ckpt, weights_only=True)
        net.load_state_dict(state["state_dict"])
        opt.load_state_dict(state["optimizer"])
        step = int(state["step"])
        print(f"resumed at step {step}", flush=True)
    rng = np.random.default_rng([args.first_seed, step])
    start, losses = time.monotonic(), []
    net.train()
    while step < args.steps and time.monotonic() - start < args.minutes * 60:
        w, i = queries[rng.integers(len(queries))]
        images, ov = worlds[w]
        others = np.arange(len(ov)) != i
        pos = np.flatnonzero((ov[i] >= args.threshold) & others)
        neg = np.flatnonzero((ov[i] < args.threshold) & others)
        pick = np.concatenate([[i], rng.choice(pos, args.positives),
                               rng.choice(neg, args.negatives, replace=False)])
        batch = torch.from_numpy(images[pick][:, None])
        d = net(batch)
        dq = ((d[1:] - d[:1]) ** 2).sum(1)
        hardest = dq[:args.positives].max()
        loss = torch.clamp(args.margin + hardest - dq[args.positives:], min=0).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        losses.append(float(loss.detach()))
        if step % 25 == 0:
            print(f"step {step} loss(25) {np.mean(losses[-25:]):.4f} "
                  f"{time.monotonic() - start:.0f} s", flush=True)
            torch.save({"epoch": 0, "step": step, "state_dict": net.state_dict(),
                        "optimizer": opt.state_dict()}, ckpt)
    torch.save({"epoch": 0, "step": step, "state_dict": net.state_dict(),
                "optimizer": opt.state_dict()}, ckpt)
    np.savez(out, **torch_net.numpy_weights(net))
    print(f"wrote {out} after {step} steps", flush=True)


if __name__ == "__main__":
    main()
