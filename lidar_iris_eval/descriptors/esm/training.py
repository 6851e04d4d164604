"""Training ESM's network (needs torch: the ``train`` extra). Driven by scripts/train_esm.py.

* **Batches**: ``batch`` distinct objects drawn uniformly among the objects that
  have true pairs, one random true pair (anchor, positive) of each. (Drawing
  pairs uniformly would favour objects seen in many scans: the number of pairs
  grows with the square of the views.)
* **Augmentation** (SegMap/ESM): a random yaw in [-180, 180) degrees, 0-10 %
  of the points removed at random, and with probability 1/2 a partial
  occlusion that removes the points beyond a random vertical plane (0-50 % of
  the segment); then the run-time resampling to 256 points and normalisation.
* **Loss** (Wohlhart and Lepetit 2015, as ESM): with squared L2 distances
  ``d+`` (anchor-positive) and ``d-`` (anchor-negative),
  ``max(0, 1 - d- / (d+ + m)) + d+`` with ``m = 0.01``, averaged.
* **Hard negatives within the class**: each anchor's negative is the closest
  positive of another pair in the batch showing a different object of the same
  coarse class (any class when the batch has none).
* **Schedule**: Adam, learning rate ``lr`` until 70 % of the time budget, then
  ``lr / 5``. Every ``eval_every`` minutes (and at the end) the network is
  scored on a separate *selection* world (segment-retrieval ROC AUC) and the
  best checkpoint is kept; the reported validation world is never used for a
  choice.
* **Quality branch**: afterwards, on the frozen embeddings of the training
  segments that have a true partner in the sample
  (:func:`~lidar_iris_eval.descriptors.esm.metrics.quality_examples`: a segment
  never seen again says nothing about distinctiveness), FC(2) + softmax with
  cross-entropy; label 1 when a true partner is among the segment's 25 nearest
  neighbours (frames >= the minimum frame gap apart).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from lidar_iris_eval.descriptors.esm import network
from lidar_iris_eval.descriptors.esm.dataset import (
    COARSE_NAMES,
    SegmentSet,
    negative_candidates,
    true_pairs,
)
from lidar_iris_eval.descriptors.esm.metrics import (
    quality_examples,
    retrieval_metrics,
    segment_retrieval,
)
from lidar_iris_eval.descriptors.esm.segmentation import normalise, resample
from lidar_iris_eval.descriptors.esm.torch_net import ESMNet

MARGIN = 0.01


def augment(points: np.ndarray, rng: np.random.Generator, n: int = 256,
            norm_scale: float = 0.0, align_yaw: bool = False) -> np.ndarray:
    """One augmented, resampled, normalised copy of a raw segment (see module docstring)."""
    pts = points - points.mean(axis=0)
    yaw = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    pts = pts @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    keep = rng.random(len(pts)) >= rng.uniform(0.0, 0.1)
    if rng.random() < 0.5:
        ang = rng.uniform(-np.pi, np.pi)
        proj = pts[:, 0] * np.cos(ang) + pts[:, 1] * np.sin(ang)
        cut = np.quantile(proj, 1.0 - rng.uniform(0.0, 0.5))
        keep &= proj <= cut
    if keep.sum() >= 20:
        pts = pts[keep]
    return normalise(resample(pts, n, rng), norm_scale, align_yaw)[0]


def embed_eval(net: ESMNet, data: SegmentSet, rows: np.ndarray, seed: int = 0) -> np.ndarray:
    """Embeddings (eval mode, no augmentation, run-time resampling) of segments ``rows``."""
    net.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(rows), 128):
            batch = np.stack([normalise(resample(data.segment(s), net.arch.n_points,
                                                 np.random.default_rng([seed, int(s)])),
                                        net.arch.norm_scale, net.arch.align_yaw)[0]
                              for s in rows[i:i + 128]])
            idx = network.neighbour_index(batch, net.arch)
            out.append(net(torch.from_numpy(batch), idx).numpy())
    return np.concatenate(out) if out else np.zeros((0, net.arch.fc[-1]), np.float32)


def wl_loss(ea: torch.Tensor, ep: torch.Tensor, coarse: np.ndarray, objects: np.ndarray,
            allowed: np.ndarray | None = None):
    """Ratio triplet loss plus pairwise term with within-class hardest negatives
    (``allowed``: the negative mask, by default :func:`negative_candidates`')."""
    d_pos = ((ea - ep) ** 2).sum(1)
    d_all = ((ea[:, None, :] - ep[None, :, :]) ** 2).sum(2)
    if allowed is None:
        allowed = negative_candidates(coarse, objects)
    allowed = torch.from_numpy(allowed)
    d_neg = torch.where(allowed, d_all, torch.full_like(d_all, float("inf"))).min(1).values
    trip = torch.clamp(1.0 - d_neg / (d_pos + MARGIN), min=0.0)
    return (trip + d_pos).mean(), trip.detach(), d_pos.detach()


class PairSampler:
    """Batches of true pairs with distinct objects, objects drawn uniformly (module docstring)."""

    def __init__(self, pairs: np.ndarray, data: SegmentSet):
        key = data.world_id[pairs[:, 0]] * (int(data.object_id.max()) + 1) \
            + data.object_id[pairs[:, 0]]
        order = np.argsort(key, kind="stable")
        self.pairs = pairs[order]
        _, self.starts, self.counts = np.unique(key[order], return_index=True,
                                                return_counts=True)

    @property
    def objects(self) -> int:
        return len(self.starts)

    def __call__(self, batch: int, rng: np.random.Generator) -> np.ndarray:
        obj = rng.choice(self.objects, min(batch, self.objects), replace=False)
        pick = self.starts[obj] + (rng.random(len(obj)) * self.counts[obj]).astype(np.int64)
        ab = self.pairs[pick]
        flip = rng.random(len(ab)) < 0.5
        ab[flip] = ab[flip][:, ::-1]
        return ab


def _score(net: ESMNet, data: SegmentSet, pairs: np.ndarray, rows: np.ndarray,
           gap: int = 10) -> dict:
    """Retrieval metrics of the current network on segments ``rows`` of ``data``."""
    emb = embed_eval(net, data, rows)
    remap = -np.ones(len(data), np.int64)
    remap[rows] = np.arange(len(rows))
    keep = (remap[pairs[:, 0]] >= 0) & (remap[pairs[:, 1]] >= 0)
    return retrieval_metrics(emb, data.frame[rows], remap[pairs[keep]],
                             world=data.world_id[rows], min_frame_gap=gap)


def held_out_rows(data: SegmentSet, n: int, seed: int = 0) -> np.ndarray:
    """At most ``n`` segment rows of ``data`` (a seeded uniform subset, sorted)."""
    rows = np.arange(len(data))
    if len(rows) > n:
        rows = np.sort(np.random.default_rng(seed).choice(len(data), n, replace=False))
    return rows


def _held_out(w: dict, arch, valid: SegmentSet, rng: np.random.Generator,
              n: int = 3000, ignore_same_object: bool = False, gap: int = 10,
              pair_radius: float = 2.0) -> dict:
    """Figures of the exported NumPy network on (at most ``n`` of) held-out segments
    (:func:`metrics.segment_retrieval`; ``rng`` is unused, the subset is seeded 0)."""
    return segment_retrieval(w, arch, valid, gap, n, 0, ignore_same_object, pair_radius)


def _save(obj, path: Path) -> None:
    """``torch.save`` through the atomic writer (a kill never leaves half a checkpoint)."""
    from lidar_iris_eval.atomic import atomic_write

    atomic_write(path, lambda fh: torch.save(obj, fh), what="checkpoint")


def _train(net: ESMNet, train: SegmentSet, sampler: PairSampler, args, work: Path,
           select_set, gap: int, log: dict) -> None:
    """The resumable training loop (``state.pt``; module docstring of scripts/train_esm.py).

    Progress is counted in training minutes and steps summed over runs; the
    state (network, optimiser, step, minutes, NumPy and torch random states,
    selection checks, loss history) is written atomically every
    ``checkpoint_every`` minutes, every ``checkpoint_steps`` steps (when set)
    and at the end, so rerunning continues where the last checkpoint stopped.
    """
    lr = getattr(args, "lr", 1e-3)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    rng = np.random.default_rng(args.seed)
    state_path, best_path = work / "state.pt", work / "best.pt"
    prog = {"step": 0, "minutes": 0.0, "hist": [], "checks": [], "best": -1.0,
            "dropped": False, "last_eval": 0.0, "final": False}
    if state_path.exists():
        saved = torch.load(state_path, weights_only=False)
        if saved.get("arch", repr(net.arch)) != repr(net.arch):
            from lidar_iris_eval.errors import LirisError

            raise LirisError(state_path, "was trained with another network or segment "
                                         "normalisation (--init, --norm-scale, --align-yaw); "
                                         "rerun with the same options or another --work")
        net.load_state_dict(saved["net"])
        opt.load_state_dict(saved["opt"])
        prog = saved["progress"]
        rng.bit_generator.state = saved["numpy_rng"]
        torch.set_rng_state(saved["torch_rng"])
        print(f"resumed at step {prog['step']}, {prog['minutes']:.1f} training minutes",
              flush=True)
    if prog["step"] < args.steps and prog["minutes"] < args.minutes:
        prog["final"] = False  # a larger budget continues a finished run
    eval_every = getattr(args, "eval_every", 8.0)
    ckpt_every = getattr(args, "checkpoint_every", 3.0)
    ckpt_steps = int(getattr(args, "checkpoint_steps", 0) or 0)
    radius = float(getattr(args, "pair_radius", 2.0))
    neg_distance = float(getattr(args, "neg_distance", 0.0) or 0.0)
    sel = select_set() if select_set is not None else None
    if sel is not None:
        sel_pairs = true_pairs(sel, radius, min_frame_gap=gap)
        sel_rows = held_out_rows(sel, 1500, seed=1)
    t0, base = time.time(), prog["minutes"]
    last_save = t0

    def minutes() -> float:
        return base + (time.time() - t0) / 60

    def save() -> None:
        prog["minutes"] = minutes()
        _save({"net": net.state_dict(), "opt": opt.state_dict(), "progress": prog,
               "arch": repr(net.arch),
               "numpy_rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state()},
              state_path)

    def check() -> None:
        if sel is None:
            return
        m = _score(net, sel, sel_pairs, sel_rows, gap)
        prog["checks"].append({"step": prog["step"], "auc": round(m["auc"], 4),
                               "acc25": round(m["accuracy_at_k"][25], 4),
                               "minutes": round(minutes(), 1)})
        print(f"select step {prog['step']}: auc {m['auc']:.4f} "
              f"@25 {m['accuracy_at_k'][25]:.4f}", flush=True)
        if m["auc"] > prog["best"]:
            prog["best"] = m["auc"]
            _save(net.state_dict(), best_path)

    if prog["dropped"]:
        for g in opt.param_groups:
            g["lr"] = lr / 5
    if not prog["checks"] and sel is not None:
        check()  # the starting point (the --init weights) is a candidate too
    while not prog["final"] and prog["step"] < args.steps and minutes() < args.minutes:
        if not prog["dropped"] and minutes() > 0.7 * args.minutes:
            for g in opt.param_groups:
                g["lr"] = lr / 5
            prog["dropped"] = True
            print(f"step {prog['step']}: learning rate {lr / 5:g}", flush=True)
        if minutes() - prog["last_eval"] >= eval_every:
            check()
            prog["last_eval"] = minutes()
        net.train()
        ab = sampler(args.batch, rng)
        pts = np.stack([augment(train.segment(s), rng, norm_scale=net.arch.norm_scale,
                                align_yaw=net.arch.align_yaw) for s in ab.ravel()])
        idx = network.neighbour_index(pts, net.arch)
        emb = net(torch.from_numpy(pts), idx).reshape(len(ab), 2, -1)
        allowed = None
        if neg_distance > 0:  # centroid tracks: nothing this close to the anchor is a negative
            allowed = negative_candidates(train.coarse[ab[:, 0]], train.object_id[ab[:, 0]],
                                          train.world[ab[:, 0]], train.world[ab[:, 1]],
                                          train.world_id[ab[:, 0]], neg_distance)
        loss, trip, _ = wl_loss(emb[:, 0], emb[:, 1], train.coarse[ab[:, 0]],
                                train.object_id[ab[:, 0]], allowed)
        opt.zero_grad()
        loss.backward()
        opt.step()
        prog["hist"].append((loss.item(), (trip > 0).float().mean().item()))
        prog["step"] += 1
        if prog["step"] % 20 == 0:
            recent = np.mean(prog["hist"][-20:], axis=0)
            print(f"step {prog['step']} loss {recent[0]:.4f} active {recent[1]:.2f} "
                  f"{minutes():.1f} min", flush=True)
        if time.time() - last_save >= ckpt_every * 60 or (
                ckpt_steps and prog["step"] % ckpt_steps == 0):
            save()
            last_save = time.time()
    if not prog["final"]:
        check()
        prog["final"] = True
    save()
    log["steps"] = prog["step"]
    log["training_minutes"] = round(prog["minutes"], 1)
    log["final_loss"] = float(np.mean(prog["hist"][-50:], axis=0)[0]) if prog["hist"] else None
    log["selection_checks"] = prog["checks"]
    if sel is not None and best_path.exists():
        net.load_state_dict(torch.load(best_path))
        log["selected_step"] = max(prog["checks"], key=lambda c: c["auc"])["step"]


def validation_name(weights: Path) -> Path:
    """The validation json beside a weights file (``*_weights.npz``: ``*_validation.json``)."""
    weights = Path(weights)
    return weights.with_name(weights.stem.replace("weights", "validation") + ".json")


def run(train: SegmentSet, valid_set, args, stages: set, start: float,
        select_set=None, extra_valid: dict | None = None) -> None:
    """Train, fit the quality branch and export.

    ``valid_set()`` gives the held-out segments the figures are reported on,
    ``select_set()`` (optional) the segments checkpoints are chosen on and
    ``extra_valid`` (name -> callable) further held-out sets reported beside them.
    ``args.init`` (optional) starts from exported weights; ``args.compare``
    (optional) weights scored beside the new ones on the selection and
    validation sets at export, with the choice rule's verdict.
    """
    out = Path(args.out) if getattr(args, "out", None) else network.WEIGHTS_FILE
    if "export" in stages and out.exists() and not getattr(args, "overwrite", False):
        from lidar_iris_eval.errors import LirisError

        raise LirisError(out, "exists (a finished model); give --overwrite to replace it, "
                              "or another --out")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    work = Path(args.work)
    gap = int(getattr(args, "min_frame_gap", 10))
    radius = float(getattr(args, "pair_radius", 2.0))
    pairs = true_pairs(train, radius, min_frame_gap=gap)
    sampler = PairSampler(pairs, train)
    init = getattr(args, "init", None)
    if init is not None:
        w0, arch0 = network.load_weights(init)
        net = ESMNet(arch0)
        net.load_numpy(w0)
        norm = arch0.norm_scale
    else:
        norm = float(args.norm_scale)
        if norm < 0:  # the median RMS radius of the training segments, rounded to 0.1 m
            rms = [normalise(train.segment(s))[1] for s in range(0, len(train), 5)]
            norm = round(float(np.median(rms)), 1)
        net = ESMNet(network.Arch(norm_scale=norm,
                                  align_yaw=bool(getattr(args, "align_yaw", False))))
    ckpt = work / "net.pt"
    log = {"train_segments": len(train), "train_pairs": int(len(pairs)),
           "train_objects_with_pairs": sampler.objects, "norm_scale": norm,
           "min_frame_gap": gap, "init": None if init is None else Path(init).name,
           "classes": {COARSE_NAMES[c]: int((train.coarse == c).sum())
                       for c in np.unique(train.coarse)}}
    if "train" in stages:
        _train(net, train, sampler, args, work, select_set, gap, log)
        _save(net.state_dict(), ckpt)
        (work / "train_log.json").write_text(json.dumps(log, indent=2))
    elif init is not None and not ckpt.exists():
        log["quality_refit_only"] = True  # --stages quality,export on --init's network
    else:
        net.load_state_dict(torch.load(ckpt))
        if (work / "train_log.json").exists():
            log.update(json.loads((work / "train_log.json").read_text()))
    if "quality" in stages:
        for p in net.parameters():
            p.requires_grad_(False)
        net.quality.weight.requires_grad_(True)
        net.quality.bias.requires_grad_(True)
        rows = np.sort(rng.choice(len(train), min(len(train), 4000), replace=False))
        emb = embed_eval(net, train, rows)
        remap = -np.ones(len(train), np.int64)
        remap[rows] = np.arange(len(rows))
        sub = remap[pairs]
        sub = sub[(sub >= 0).all(axis=1)]
        used, y = quality_examples(emb, train.frame[rows], train.world_id[rows], sub, gap=gap)
        opt = torch.optim.Adam([net.quality.weight, net.quality.bias], lr=1e-2)
        x_t, y_t = torch.from_numpy(emb[used]), torch.from_numpy(y)
        for _ in range(args.quality_steps):
            loss = torch.nn.functional.cross_entropy(net.quality_logits(x_t), y_t)
            opt.zero_grad()
            loss.backward()
            opt.step()
        log["quality_examples"] = int(len(used))
        log["quality_positive_rate"] = float(y.mean())
        log["quality_loss"] = float(loss.item())
        _save(net.state_dict(), ckpt)
    if "export" in stages:
        net.eval()
        weights = net.export()
        tmp = out.with_name(out.name + ".tmp.npz")
        np.savez(tmp, **weights)
        tmp.replace(out)
        w, arch = network.load_weights(out)
        compare = getattr(args, "compare", None)
        if compare is not None:
            w_old, arch_old = network.load_weights(compare)
        sets = {"validation": valid_set, **(extra_valid or {})}
        if select_set is not None:
            sets["selection"] = select_set
        for name, make in sets.items():
            valid = make()
            metrics = _held_out(w, arch, valid, np.random.default_rng(0), gap=gap,
                                pair_radius=radius)
            entry = {k: v for k, v in metrics.items() if k != "roc"}
            entry["segments"] = len(valid)
            entry["objects_with_pairs"] = PairSampler(
                true_pairs(valid, radius, min_frame_gap=gap), valid).objects
            loose = _held_out(w, arch, valid, np.random.default_rng(0),
                              ignore_same_object=True, gap=gap, pair_radius=radius)
            entry["same_object_ignored"] = {k: v for k, v in loose.items() if k != "roc"}
            if compare is not None:
                old = _held_out(w_old, arch_old, valid, np.random.default_rng(0), gap=gap,
                                pair_radius=radius)
                entry["compared"] = {k: v for k, v in old.items() if k != "roc"}
                entry["compared_roc"] = old["roc"]
            if name == "validation":
                log["validation"] = entry
                log["validation_roc"] = metrics["roc"]
            else:
                log.setdefault("validation_extra", {})[name] = entry
        if compare is not None:
            log["compared_weights"] = {"file": Path(compare).name,
                                       "sha256": network.sha256_of(compare)}
            if "selection" in log.get("validation_extra", {}):
                sel = log["validation_extra"]["selection"]
                log["choice"] = {
                    "rule": "use the new weights only if their segment-retrieval ROC AUC on "
                            "the selection world beats the compared weights'",
                    "auc_new": sel["auc"], "auc_compared": sel["compared"]["auc"],
                    "use_new": bool(sel["auc"] > sel["compared"]["auc"])}
        log["sha256"] = network.sha256_of(out)
        log["minutes"] = round((time.time() - start) / 60, 1)
        (work / "validation.json").write_text(json.dumps(log, indent=2))
        validation_name(out).write_text(json.dumps(log, indent=2) + "\n")
        print(json.dumps({k: v for k, v in log.items()
                          if k not in ("validation_roc",)}, indent=2, default=str)[:4000])
