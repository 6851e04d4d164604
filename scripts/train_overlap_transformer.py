"""Train OverlapTransformer on simulated worlds (maintainers; needs the ``train`` extra).

    pip install -e ".[train]"        # exactly torch==2.13.0, the CPU build
    OMP_NUM_THREADS=1 nice -n 15 python scripts/train_overlap_transformer.py \\
        --work /tmp/ot-train --seeds 7001 7002 7003 7004 --steps 700 --minutes 180

With the defaults, this is how liris' shipped ``ot_sim_weights.npz`` was made: 700 steps,
62 minutes on one thread of the shared 2-core machine (MODEL_CARD.md has the run's figures
and the held-out selection; the step-700 file, the last, was the best). ``--minutes`` is
the training wall budget summed over restarts (keep it <= 180: 3 h on 2 cores).
Steps, each resumable: finished worlds are kept in ``--work``
(``world<seed>-s<stride>.npz``), training resumes from ``--work/checkpoint.pth.tar``
and appends to ``--work/losses.tsv``; a killed run restarted with the same
arguments continues where its last checkpoint (every ``--save-every`` steps) left.

1. simulate ``--worlds`` worlds: ``small-mixed``'s route and style with seeds
   ``--first-seed``, ``+1``, ... (7001-7004 by default; ``small-mixed`` itself is
   seed 21 and the held-out selection world 7101, see MODEL_CARD.md);
2. keep every ``--stride``-th frame (4: about 3.7 m apart) and compute its depth
   image with the method's own projection (``paper``: PNG depth);
3. the OverlapNet overlap of every pair of kept frames (``liris gt --gt overlap``'s
   computation, :func:`lidar_iris_eval.evaluation.overlap.overlap_matrix`); a pair is
   positive at overlap >= 0.3, negative below, as the authors train. The stride is
   what keeps this affordable (about 17 ms a pair on one core: 100 frames, 3 minutes);
4. one step = one query, ``--positives`` positives and ``--negatives`` negatives drawn
   at random; the authors' loss: for each negative ``max(0, margin + max_pos d^2 -
   d^2_neg)``, summed over the negatives (their ``triplet_loss``, ``lazy=False``,
   margin 0.5, squared L2 of unit vectors), Adam with ``--lr`` after a linear warm-up
   of ``--warmup`` steps;
5. unlike the authors, NetVLAD's 65,536 x 256 projection (``net_vlad.hidden1_weights``,
   16.8 M of the 18.5 M weights) is frozen at :func:`network.frozen_projection`
   (``--frozen-seed``); everything else is trained. The written ``.npz`` holds the
   other 1.7 M weights under the authors' names plus the seed and the SHA-256 of the
   frozen matrix, which the method regenerates and checks at load;
6. ``--out`` (default ``--work/ot_sim_weights.npz``) and, every ``--snapshot-every``
   steps, ``--work/snapshots/step<N>.npz`` (for selection on a held-out world).

The checkpoint is a plain ``torch.save`` of ``{"epoch", "step", "state_dict",
"optimizer"}`` (the authors' keys), which the method also reads directly.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def prepare_world(work: Path, seed: int, frames: int, stride: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 64, 900) depth images and the (N, N) overlap matrix of one simulated world."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.evaluation.overlap import lidar_poses_of, overlap_matrix, points_of
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    done = work / f"world{seed}-s{stride}.npz"
    if done.is_file():
        with np.load(done) as z:
            return z["images"], z["overlap"]
    seq_dir = work / f"world{seed}"
    if not (seq_dir / "poses.txt").is_file():
        simulate_sequence(seq_dir, "small-mixed", overwrite=True, frames=frames, seed=seed)
    seq = open_sequence(seq_dir)
    keep = np.arange(0, len(seq), stride)
    desc = get_descriptor("overlap-transformer", preset="paper")
    start = time.monotonic()
    images = np.stack([desc.range_image(seq[int(k)]) for k in keep]).astype(np.float32)
    poses = lidar_poses_of(seq)[keep]
    overlap = overlap_matrix(lambda k: points_of(seq, int(keep[k])), poses)
    tmp = work / f".world{seed}-s{stride}.tmp.npz"
    np.savez(tmp, images=images, overlap=overlap, frames=keep)
    tmp.replace(done)
    print(f"world {seed}: {len(keep)} frames, overlap in {time.monotonic() - start:.0f} s, "
          f"{int((np.triu(overlap, 1) >= 0.3).sum())} positive pairs", flush=True)
    return images, overlap


def export_weights(net, path: Path, frozen_seed: int, info: dict) -> None:
    """The shipped format: every trained tensor, the frozen matrix as its seed + SHA-256."""
    from lidar_iris_eval.descriptors.overlap_transformer import network, torch_net

    w = torch_net.numpy_weights(net)
    frozen = w.pop(network.FROZEN_NAME)
    expected = network.frozen_projection(frozen_seed)
    if not np.array_equal(frozen, expected):
        raise RuntimeError("the frozen projection changed during training")
    w[network.FROZEN_SEED] = np.array(frozen_seed, np.int64)
    w[network.FROZEN_SHA256] = np.array(network.array_sha256(expected))
    w["liris.info"] = np.array(json.dumps(info, sort_keys=True))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez(tmp, **w)
    tmp.replace(path)


def kmeans_init(net, images: np.ndarray, alpha: float, seed: int, iterations: int = 10) -> None:
    """NetVLAD's centres from k-means of the initial network's tokens (the NetVLAD paper's
    initialisation): ``cluster_weights2`` = unit centres ``c_k``, soft assignment
    ``softmax(2 alpha x.c_k - alpha |c_k|^2)``. With torch's random centres the 900
    unit ReLU tokens of every scan sit far from all centres alike, the residuals are
    dominated by the centres and descriptors of different scans have cosine 0.999+
    (measured), which the triplet loss did not leave in 20-50 steps."""
    import torch
    import torch.nn.functional as F

    with torch.no_grad():
        x = torch.from_numpy(np.asarray(images, np.float32)[:, None])
        for n in range(1, 12):
            x = torch.relu(getattr(net, f"conv{n}")(x))
        first = torch.relu(net.convLast1(x))[:, :, 0, :].transpose(1, 2)
        mixed = net.transformer_encoder(first.transpose(0, 1)).transpose(0, 1)
        both = torch.cat([first, mixed], dim=2).transpose(1, 2)[:, :, None, :]
        tokens = F.normalize(torch.relu(net.convLast2(both)), dim=1)[:, :, 0, :]
        tokens = tokens.transpose(1, 2).reshape(-1, tokens.shape[1]).numpy()
    k = net.net_vlad.cluster_weights.shape[1]
    rng = np.random.default_rng(seed)
    centres = tokens[rng.choice(len(tokens), k, replace=False)].copy()
    for _ in range(iterations):  # spherical k-means
        nearest = (tokens @ centres.T).argmax(1)
        for c in range(k):
            if (nearest == c).any():
                centres[c] = tokens[nearest == c].mean(0)
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    with torch.no_grad():
        vlad = net.net_vlad
        vlad.cluster_weights.copy_(torch.from_numpy(2 * alpha * centres.T))
        vlad.cluster_biases.copy_(torch.from_numpy(-alpha * (centres ** 2).sum(1)))
        vlad.cluster_weights2.copy_(torch.from_numpy(centres.T[None]))


def triplet_loss(d, positives: int, margin: float, scaled: bool):
    """``sum_neg max(0, margin + max_pos |q-p|^2 - |q-n|^2)``; row 0 the query.

    ``scaled``: both squared distances divided by the query's mean squared distance
    to its negatives (held constant in the gradient), so the margin is relative and
    shrinking every descriptor towards one point no longer lowers the loss."""
    import torch

    dq = ((d[1:] - d[:1]) ** 2).sum(1)
    if scaled:
        dq = dq / (dq[positives:].mean().detach() + 1e-12)
    hardest = dq[:positives].max()
    return torch.clamp(margin + hardest - dq[positives:], min=0).sum()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--worlds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=7001)
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="world seeds (default: --worlds seeds from --first-seed)")
    ap.add_argument("--frames", type=int, default=400, help="simulated frames per world")
    ap.add_argument("--stride", type=int, default=4, help="keep every N-th frame")
    ap.add_argument("--prepare-only", action="store_true",
                    help="simulate and compute overlaps, then stop (run several in parallel)")
    ap.add_argument("--minutes", type=float, default=62.0,
                    help="training wall budget, summed over restarts")
    ap.add_argument("--steps", type=int, default=100000)
    ap.add_argument("--positives", type=int, default=2)
    ap.add_argument("--negatives", type=int, default=6)
    ap.add_argument("--margin", type=float, default=0.5)
    ap.add_argument("--loss", choices=("authors", "scaled"), default="authors",
                    help="the authors' triplet loss on squared distances, or the same "
                         "on distances relative to the query's mean negative distance")
    ap.add_argument("--lr", type=float, default=1e-5)
    ap.add_argument("--warmup", type=int, default=50, help="linear lr warm-up steps")
    ap.add_argument("--frozen-seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--threshold", type=float, default=0.3)
    ap.add_argument("--save-every", type=int, default=25)
    ap.add_argument("--snapshot-every", type=int, default=50)
    ap.add_argument("--init-seed", type=int, default=0, help="torch.manual_seed of the init")
    ap.add_argument("--init", choices=("kmeans", "torch"), default="kmeans",
                    help="NetVLAD centres from k-means of tokens, or torch's random init")
    ap.add_argument("--alpha", type=float, default=30.0, help="k-means init sharpness")
    ap.add_argument("--init-every", type=int, default=5, help="k-means on every N-th image")
    args = ap.parse_args(argv)

    args.work.mkdir(parents=True, exist_ok=True)
    seeds = args.seeds or [args.first_seed + k for k in range(args.worlds)]
    worlds = [prepare_world(args.work, seed, args.frames, args.stride) for seed in seeds]
    if args.prepare_only:
        return

    import torch

    from lidar_iris_eval.descriptors.overlap_transformer import network, torch_net

    torch.set_num_threads(args.threads)
    out = args.out or args.work / "ot_sim_weights.npz"
    # (world, query) with at least one positive and enough negatives among the other frames
    queries = []
    for w, (_, ov) in enumerate(worlds):
        for i in range(len(ov)):
            others = np.arange(len(ov)) != i
            pos = (ov[i] >= args.threshold) & others
            if pos.any() and ((ov[i] < args.threshold) & others).sum() >= args.negatives:
                queries.append((w, i))
    print(f"{len(queries)} training queries in {len(worlds)} worlds", flush=True)

    torch.manual_seed(args.init_seed)  # torch's default initialisation (the authors')
    net = torch_net.OverlapTransformerNet()
    frozen = net.net_vlad.hidden1_weights
    with torch.no_grad():
        frozen.copy_(torch.from_numpy(network.frozen_projection(args.frozen_seed)))
    frozen.requires_grad_(False)
    ckpt = args.work / "checkpoint.pth.tar"
    if args.init == "kmeans" and not ckpt.is_file():
        sample = np.concatenate([images[::args.init_every] for images, _ in worlds])
        kmeans_init(net, sample, args.alpha, args.init_seed)
    trainable = [p for p in net.parameters() if p.requires_grad]
    print(f"{sum(p.numel() for p in trainable):,} trained weights, "
          f"{frozen.numel():,} frozen", flush=True)
    opt = torch.optim.Adam(trainable, args.lr)
    log = args.work / "losses.tsv"
    step, spent = 0, 0.0
    if ckpt.is_file():
        state = torch.load(ckpt, weights_only=True)
        net.load_state_dict(state["state_dict"])
        opt.load_state_dict(state["optimizer"])
        step, spent = int(state["step"]), float(state.get("seconds", 0.0))
        print(f"resumed at step {step} ({spent / 60:.1f} min trained)", flush=True)
    if not log.is_file():
        log.write_text("step\tloss\tseconds\n")

    def save() -> None:
        tmp = ckpt.with_name(".checkpoint.tmp")
        torch.save({"epoch": 0, "step": step, "seconds": spent, "state_dict": net.state_dict(),
                    "optimizer": opt.state_dict()}, tmp)
        tmp.replace(ckpt)

    def info() -> dict:
        return {"step": step, "minutes": round(spent / 60, 1), "seeds": seeds,
                "frames": args.frames, "stride": args.stride,
                "positives": args.positives, "negatives": args.negatives,
                "margin": args.margin, "loss": args.loss, "lr": args.lr, "warmup": args.warmup,
                "frozen_seed": args.frozen_seed, "init_seed": args.init_seed,
                "init": args.init, "alpha": args.alpha,
                "torch": torch.__version__}

    start = time.monotonic() - spent
    net.train()
    pending: list[tuple[int, float]] = []
    while step < args.steps and time.monotonic() - start < args.minutes * 60:
        # the draws of step k depend on k only, so a resumed run draws what an unbroken one would
        rng = np.random.default_rng([args.first_seed, step])
        w, i = queries[rng.integers(len(queries))]
        images, ov = worlds[w]
        others = np.arange(len(ov)) != i
        pos = np.flatnonzero((ov[i] >= args.threshold) & others)
        neg = np.flatnonzero((ov[i] < args.threshold) & others)
        pick = np.concatenate([[i], rng.choice(pos, args.positives),
                               rng.choice(neg, args.negatives, replace=False)])
        for group in opt.param_groups:
            group["lr"] = args.lr * min(1.0, (step + 1) / max(args.warmup, 1))
        loss = triplet_loss(net(torch.from_numpy(images[pick][:, None])), args.positives,
                            args.margin, args.loss == "scaled")
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        spent = time.monotonic() - start
        pending.append((step, float(loss.detach())))
        if step % args.save_every == 0:
            save()
            with log.open("a") as f:
                f.writelines(f"{s}\t{v:.5f}\t{spent:.0f}\n" for s, v in pending)
            print(f"step {step} loss({len(pending)}) {np.mean([v for _, v in pending]):.4f} "
                  f"{spent / 60:.1f} min", flush=True)
            pending = []
        if step % args.snapshot_every == 0:
            export_weights(net, args.work / "snapshots" / f"step{step}.npz",
                           args.frozen_seed, info())
    save()
    with log.open("a") as f:
        f.writelines(f"{s}\t{v:.5f}\t{spent:.0f}\n" for s, v in pending)
    export_weights(net, out, args.frozen_seed, info())
    print(f"wrote {out} after {step} steps, {spent / 60:.1f} min", flush=True)


if __name__ == "__main__":
    main()
