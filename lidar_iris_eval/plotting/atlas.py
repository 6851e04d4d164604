"""The failure atlas (``liris plot RUN --failures N``, issue 38 item 4).

For each method of a run, from its ``protocol1/<d>/matches.csv``:

* the N most confident false positives: matched queries whose best match is
  not true (``is_true = 0``), lowest descriptor distance first (the first a
  threshold would accept);
* the N revisit queries it missed worst: revisit queries not found at the
  method's max-F1 threshold (top-1 wrong, or true but rejected), highest
  descriptor distance first (the farthest from being accepted).

Each case is one panel row: the bird's-eye views of both scans overlaid at
the method's relative pose (when it estimated one; yaw-only methods are
rotated by their yaw) and at the ground-truth relative pose, the method's
own representation of both scans where it is cheap (LiDAR Iris image, Scan
Context matrix; other methods show the views only), and the pair on the
trajectory. The title names the frame ids, descriptor distance, metres
apart and the pose error. For a missed revisit the pair is the query and its
nearest true database frame (or its own match when that is true but was
rejected); the method's view then shows the frame it matched instead when
that is another one (said in the panel).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.errors import warn
from lidar_iris_eval.plotting import style

#: points drawn per scan in a bird's-eye view (a random subset, fixed seed)
BEV_POINTS = 6000
#: half-width of a bird's-eye view (metres)
BEV_RANGE = 40.0


@dataclass(frozen=True)
class FailureCase:
    """One panel: ``kind`` ``"fp"`` or ``"missed"``, the pair shown and what it scored."""

    kind: str
    query: int
    match: int  # the method's best match (-1: none)
    partner: int  # the frame shown with the query: the match (fp) or the true frame (missed)
    distance: float
    match_dist_m: float
    rre_deg: float
    rte_m: float
    pose: np.ndarray | None  # (4, 4) method's estimate for (query, match), NaN when unknown


def false_positives(matches, n: int):
    """The ``n`` lowest-distance false positives of a ``matches.csv`` table (a DataFrame)."""
    fp = matches[(matches["match"] >= 0) & (matches["is_true"] == 0)]
    return fp.sort_values(["distance", "query"], kind="stable").head(n)


def missed_revisits(matches, n: int, threshold: float | None):
    """The ``n`` revisit queries farthest from being found at ``threshold`` (max-F1)."""
    tau = np.inf if threshold is None or not np.isfinite(threshold) else threshold
    revisit = matches["is_revisit"] == 1
    found = (matches["is_true"] == 1) & (matches["distance"] <= tau)
    missed = matches[revisit & ~found]
    return missed.sort_values(["distance", "query"], ascending=[False, True],
                              kind="stable").head(n)


def failure_cases(run, descriptor: str, n: int) -> list[FailureCase]:
    """The panels of ``descriptor`` in ``run``: false positives first, then misses."""
    table = run.matches(descriptor)
    row = run.row(1, descriptor)
    gt = run.ground_truth()
    coords = _gt_coords(run, gt)
    cases = []
    for kind, part in (("fp", false_positives(table, n)),
                       ("missed", missed_revisits(table, n, row.get("f1_threshold")))):
        for _, r in part.iterrows():
            q, j = int(r["query"]), int(r["match"])
            true_match = int(r["is_true"]) == 1
            partner = j if kind == "fp" or true_match else \
                _nearest_partner(gt, coords, q, fallback=j)
            pose = _pose(r)
            cases.append(FailureCase(kind, q, j, partner, float(r["distance"]),
                                     float(r.get("match_dist_m", np.nan)),
                                     float(r.get("rre_deg", np.nan)),
                                     float(r.get("rte_m", np.nan)), pose))
    return cases


def _gt_coords(run, gt):
    from lidar_iris_eval.evaluation.ground_truth import gt_coordinates

    return gt_coordinates(run.positions(), gt.frame, gt.distance)


def _nearest_partner(gt, coords, q: int, fallback: int) -> int:
    """The nearest database frame of query ``q`` within the radius (its true partner)."""
    limit = int(gt.query_limits()[q])
    if limit < 0:
        return fallback
    d = np.linalg.norm(coords[: limit + 1] - coords[q], axis=1)
    j = int(np.argmin(d))
    return j if d[j] < gt.radius or fallback < 0 else fallback


def _pose(r) -> np.ndarray | None:
    keys = [f"T{a}{b}" for a in range(3) for b in range(4)]
    if all(k in r.index for k in keys):
        values = np.array([r[k] for k in keys], dtype=np.float64).reshape(3, 4)
        pose = np.eye(4)
        pose[:3] = values
        if np.isfinite(pose[:3, :3]).all():
            if not np.isfinite(pose[:3, 3]).all():
                pose[:3, 3] = 0.0  # yaw-only: rotation about the query, no translation
            return pose
    yaw = r.get("yaw_deg", np.nan)
    if yaw is not None and np.isfinite(yaw):
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        pose = np.eye(4)
        pose[:2, :2] = [[c, -s], [s, c]]
        return pose
    return None


def representation(descriptor, scan: np.ndarray):
    """The method's own image of one scan, or None where there is no cheap one."""
    name = getattr(descriptor, "name", "")
    try:
        if name == "lidar-iris":
            from lidar_iris_eval.descriptors import lidar_iris

            return "LiDAR Iris image", lidar_iris.iris_image(scan, descriptor.params)
        if name == "scan-context":
            return "Scan Context", np.asarray(descriptor.compute(scan)["sc"])
    except Exception as err:  # a figure, not a result: say so and go on
        warn(name, f"representation skipped in the failure atlas: {err}")
    return None


def _bev(ax, query_pts, other_pts, transform, title: str, gid: str) -> None:
    ax.set_gid(gid)
    if transform is None:
        ax.text(0.5, 0.5, "no pose estimate", ha="center", va="center", transform=ax.transAxes,
                fontsize=7, color="0.4")
    else:
        moved = other_pts[:, :3] @ transform[:3, :3].T + transform[:3, 3]
        centre = np.asarray(transform[:2, 3], dtype=np.float64)
        if np.abs(centre).max() > BEV_RANGE:  # say so rather than show an empty overlay
            ax.text(0.5, 0.04, f"other scan's origin {np.linalg.norm(centre):.0f} m away, "
                    "outside the view", ha="center", va="bottom", transform=ax.transAxes,
                    fontsize=5.5, color="#d55e00")
        ax.scatter(moved[:, 0], moved[:, 1], s=0.2, c="#d55e00", linewidths=0, alpha=0.6,
                   rasterized=True)
    ax.scatter(query_pts[:, 0], query_pts[:, 1], s=0.2, c="#0072b2", linewidths=0, alpha=0.6,
               rasterized=True)
    ax.set_xlim(-BEV_RANGE, BEV_RANGE)
    ax.set_ylim(-BEV_RANGE, BEV_RANGE)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=7, pad=2)
    ax.tick_params(labelsize=5)


def _subset(points: np.ndarray, seed: int) -> np.ndarray:
    points = np.asarray(points)
    if len(points) <= BEV_POINTS:
        return points
    keep = np.random.default_rng(seed).choice(len(points), BEV_POINTS, replace=False)
    return points[keep]


def atlas_figure(run, descriptor_name: str, cases: list[FailureCase], sequence, descriptor):
    """One figure for one method: a row per case (see the module docstring)."""
    from lidar_iris_eval.evaluation.poses import relative_ground_truth

    rep = descriptor is not None and representation(descriptor, sequence[0]) is not None
    columns = 5 if rep else 3
    from lidar_iris_eval.evaluation.ground_truth import ground_plane_axes

    axes_2d = list(ground_plane_axes(run.ground_truth().frame))
    positions = np.asarray(run.positions())[:, axes_2d]
    with style.context():
        fig = style.new_figure(2.1 * columns, 2.35 * max(1, len(cases)) + 0.3)
        if not cases:
            fig.text(0.5, 0.5, f"{descriptor_name}: no false positives and no missed revisits",
                     ha="center")
            return fig
        rows = fig.subfigures(len(cases), 1, squeeze=False)[:, 0]
        lidar = sequence.poses
        for k, case in enumerate(cases):
            sub = rows[k]
            row = sub.subplots(1, columns, width_ratios=[1, 1, *([0.8, 0.8] if rep else []), 1])
            q, j = case.query, case.partner
            qp, jp = _subset(sequence[q], q), _subset(sequence[j], j)
            shown = case.match if case.match >= 0 else j
            method_pts = jp if shown == j else _subset(sequence[shown], shown)
            gt_rel = relative_ground_truth(lidar, np.array([q]), np.array([j]))[0]
            label = "false positive" if case.kind == "fp" else "missed revisit"
            ids = (_scan_id(sequence, q), _scan_id(sequence, j))
            method_title = "at the method's pose" if shown == j else \
                f"method's match {_scan_id(sequence, shown)}, its pose"
            _bev(row[0], qp, method_pts, case.pose, method_title,
                 f"failure:{case.kind}:{q}:{case.match}:method")
            _bev(row[1], qp, jp, gt_rel, "at the ground-truth pose",
                 f"failure:{case.kind}:{q}:{case.match}:gt")
            col = 2
            if rep:
                for frame in (q, j):
                    found = representation(descriptor, sequence[frame])
                    ax = row[col]
                    if found is not None:
                        name, image = found
                        image = np.asarray(image, dtype=np.float64)
                        positive = image[np.isfinite(image) & (image > 0)]
                        top = float(np.percentile(positive, 99)) if len(positive) else None
                        ax.imshow(image, aspect="auto", cmap="viridis", interpolation="nearest",
                                  vmin=0.0, vmax=top or None)
                        ax.set_title(f"{name} {_scan_id(sequence, frame)}", fontsize=6, pad=2)
                    ax.set_xticks([])
                    ax.set_yticks([])
                    col += 1
            ax = row[col]
            ax.plot(positions[:, 0], positions[:, 1], color="0.75", linewidth=0.6)
            ax.plot(positions[[q, j], 0], positions[[q, j], 1], color="#d55e00", linewidth=0.8)
            ax.scatter(positions[q, 0], positions[q, 1], s=10, c="#0072b2", zorder=3)
            ax.scatter(positions[j, 0], positions[j, 1], s=10, c="#d55e00", zorder=3)
            if shown != j:  # a miss whose best match was another (wrong) frame
                ax.scatter(positions[shown, 0], positions[shown, 1], s=14, marker="x",
                           c="0.2", zorder=3, label="method's match")
                ax.legend(fontsize=5, loc="lower right", frameon=False)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title("on the trajectory", fontsize=7, pad=2)
            apart = case.match_dist_m if j == case.match else \
                float(np.linalg.norm(np.asarray(run.positions())[q]
                                     - np.asarray(run.positions())[j]))
            err = ""
            if np.isfinite(case.rre_deg):
                err = "; pose error" + ("" if shown == j else " of its match")
                err += f" {case.rre_deg:.1f} deg"
                if np.isfinite(case.rte_m):
                    err += f" / {case.rte_m:.2f} m"
            number = sum(c.kind == case.kind for c in cases[:k]) + 1
            sub.suptitle(f"{label} {number}: query {ids[0]} - {ids[1]}; descriptor distance "
                         f"{case.distance:.4g}; {apart:.1f} m apart{err}", fontsize=7.5,
                         x=0.01, ha="left")
        absent = [label for kind, label in (("fp", "no false positive"),
                                            ("missed", "no missed revisit query"))
                  if not any(c.kind == kind for c in cases)]
        fig.suptitle(f"Failure atlas: {style.method_label(descriptor_name)} (blue: query, "
                     "orange: other scan)" + (f"; {', '.join(absent)}" if absent else ""),
                     fontsize=9)
    return fig


def _scan_id(sequence, index: int) -> str:
    from pathlib import Path

    paths = getattr(sequence, "scan_paths", None)
    if paths:
        return Path(paths[index]).stem
    return str(index)


def build_failures(run, n: int, open_sequence) -> dict:
    """``{"failures_<d>": Figure}`` for every protocol 1 method of ``run`` (empty without
    scans). ``open_sequence(run)`` opens the run's sequence or returns None."""
    if not run.descriptors(1):
        warn(run.path, "no protocol 1 results; failure atlas skipped")
        return {}
    sequence = open_sequence(run)
    if sequence is None:
        return {}
    from lidar_iris_eval.descriptors import get_descriptor

    figures = {}
    for name in style.in_method_order(run.descriptors(1)):
        preset, params = run.descriptor_params(name)
        try:
            with warnings.catch_warnings():  # parameter notes were printed by the run itself
                warnings.simplefilter("ignore")
                desc = get_descriptor(name, preset=preset, **params)
        except Exception:  # an external or unknown method: views only
            desc = None
        cases = failure_cases(run, name, n)
        figures[f"failures_{name}"] = atlas_figure(run, name, cases, sequence, desc)
    return figures
