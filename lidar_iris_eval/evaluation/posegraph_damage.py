"""What a pose graph's false loops cost (issue 35, item 4; docs/loops.md).

A g2o pose graph (its vertices' poses as the initial estimate, its odometry
edges, its loop edges scored true/false by :mod:`.external_loops`) is optimised
with GTSAM's Levenberg-Marquardt three ways:

* ``none``: the odometry edges only;
* ``true``: odometry + the loops the ground truth calls true;
* ``all``: odometry + every loop edge of the file (true, false, and those the
  convention does not score);

and, for each false loop on its own, odometry + the true loops + that loop.
Each optimised trajectory is compared with the sequence's LiDAR poses at the
vertices' scans: **APE RMSE** = the root mean square of the position errors
after the rigid (SE(3), no scale) least-squares alignment of Umeyama (1991),
as ``evo_ape --align`` computes it. A false loop's **added error** is
``APE(true + that loop) - APE(true)``.

The first vertex (or the file's first ``FIX``) is held by a tight prior (the
gauge). Each edge's information matrix is g2o's, in g2o's error order
``(x, y, z, qx, qy, qz)``, turned into GTSAM's tangent order ``(rx, ry, rz,
x, y, z)``; the quaternion's vector part is half the rotation angle, so its
information is divided by 4 for the angle. An optional robust kernel
(``huber`` / ``cauchy``, with ``kernel_k`` in whitened units) is applied to
the loop edges only, the way back ends guard against false loops.

GTSAM is the optional extra ``posegraph`` (``pip install 'lidar_iris_eval[posegraph]'``),
imported only when this runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidar_iris_eval.errors import LirisError

KERNELS = ("none", "huber", "cauchy")
#: the default kernel width (whitened residual units)
KERNEL_K = 1.345
#: at most this many false loops are optimised one by one
MAX_SINGLE_FALSE = 200
APE_RULE = ("APE RMSE (m) of the optimised vertex positions against the sequence's LiDAR "
            "positions at the vertices' scans, after SE(3) Umeyama alignment (no scale); "
            "Levenberg-Marquardt; first vertex (or FIX) held by a prior")


def _gtsam():
    try:
        import gtsam
    except ImportError:
        raise LirisError("pose-graph damage", "needs gtsam: pip install "
                                              "'lidar_iris_eval[posegraph]'") from None
    return gtsam


def umeyama_se3(estimate: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R, t`` minimising ``sum |reference - (R @ estimate + t)|^2`` (rotation, no scale)."""
    mu_e, mu_r = estimate.mean(axis=0), reference.mean(axis=0)
    cov = (reference - mu_r).T @ (estimate - mu_e) / len(estimate)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    return R, mu_r - R @ mu_e


def ape_rmse(estimate: np.ndarray, reference: np.ndarray) -> float:
    """APE RMSE (m) of ``(M, 3)`` positions after SE(3) alignment onto ``reference``."""
    R, t = umeyama_se3(estimate, reference)
    err = reference - (estimate @ R.T + t)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _gtsam_information(info: np.ndarray) -> np.ndarray:
    """A g2o 6x6 information (x y z qx qy qz) in GTSAM's Pose3 tangent order (r, t)."""
    order = [3, 4, 5, 0, 1, 2]
    out = np.asarray(info, dtype=np.float64)[np.ix_(order, order)].copy()
    scale = np.array([0.5, 0.5, 0.5, 1.0, 1.0, 1.0])  # d(q_vec) = d(angle) / 2
    return out * np.outer(scale, scale)


@dataclass(frozen=True)
class Damage:
    """APE RMSE of the three optimisations and of each false loop added alone."""

    ape_none: float
    ape_true: float
    ape_all: float
    #: per false loop (file order): its index among the file's loops and APE(true + it)
    false_loops: np.ndarray
    ape_true_plus: np.ndarray
    n_vertices: int
    n_odometry: int
    n_true: int
    n_false: int
    n_all: int
    kernel: str = "none"
    kernel_k: float = KERNEL_K
    extra: dict = field(default_factory=dict)

    @property
    def added(self) -> np.ndarray:
        return self.ape_true_plus - self.ape_true

    def summary(self) -> dict:
        """The keys added to the run's row (``posegraph_*``)."""
        return {"posegraph_ape_none_m": self.ape_none, "posegraph_ape_true_m": self.ape_true,
                "posegraph_ape_all_m": self.ape_all,
                "posegraph_worst_false_added_m": (float(self.added.max())
                                                  if len(self.added) else None),
                "posegraph_vertices": self.n_vertices, "posegraph_kernel": self.kernel,
                "posegraph_rule": APE_RULE}

    def table(self) -> dict[str, list]:
        """One row per optimisation: ``none``, ``true``, ``all``, then ``true+<loop>``."""
        rows = {"graph": ["none", "true", "all"],
                "loop": [-1, -1, -1],
                "n_loops": [0, self.n_true, self.n_all],
                "ape_rmse_m": [self.ape_none, self.ape_true, self.ape_all],
                "added_m": [np.nan, 0.0, self.ape_all - self.ape_true]}
        for k, ape in zip(self.false_loops, self.ape_true_plus, strict=True):
            rows["graph"].append(f"true+{int(k)}")
            rows["loop"].append(int(k))
            rows["n_loops"].append(self.n_true + 1)
            rows["ape_rmse_m"].append(float(ape))
            rows["added_m"].append(float(ape - self.ape_true))
        return rows


def posegraph_damage(graph, loop_edges: np.ndarray, status: np.ndarray,
                     vertex_scans: dict[int, int], reference: np.ndarray, *,
                     kernel: str = "none", kernel_k: float = KERNEL_K,
                     max_iterations: int = 100) -> Damage:
    """Optimise ``graph`` (:class:`~lidar_iris_eval.io.loops.G2OGraph`) three ways plus one
    per false loop (module docstring).

    ``loop_edges[k]`` is the index in ``graph.edges`` of the file's ``k``-th loop (-1:
    the loop is no edge, e.g. it has no pose), ``status[k]`` its status (``"true"``,
    ``"false"``, other); ``vertex_scans`` maps each vertex id to its scan;
    ``reference`` ``(N, 3)`` are the sequence's positions the APE is measured against.
    """
    if kernel not in KERNELS:
        raise LirisError(f"--posegraph-kernel {kernel}", f"choose from {', '.join(KERNELS)}")
    if not graph.vertices:
        raise LirisError("pose-graph damage", "the graph has no vertices (no initial "
                                              "estimate to optimise)")
    gtsam = _gtsam()
    loop_edges = np.asarray(loop_edges, dtype=np.int64)
    in_graph = loop_edges >= 0
    loop_set = {int(e) for e in loop_edges[in_graph]}
    odometry = [e for e in range(len(graph.edges)) if e not in loop_set]
    ids = sorted(graph.vertices)
    anchor = graph.fixed[0] if graph.fixed else ids[0]
    initial = gtsam.Values()
    for vid in ids:
        initial.insert(vid, gtsam.Pose3(graph.vertices[vid]))

    def factor(e: int, robust: bool):
        a, b, T, info = graph.edges[e]
        model = gtsam.noiseModel.Gaussian.Information(_gtsam_information(info))
        if robust and kernel != "none":
            estimator = (gtsam.noiseModel.mEstimator.Huber.Create(kernel_k) if kernel == "huber"
                         else gtsam.noiseModel.mEstimator.Cauchy.Create(kernel_k))
            model = gtsam.noiseModel.Robust.Create(estimator, model)
        return gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(T), model)

    base = gtsam.NonlinearFactorGraph()
    base.add(gtsam.PriorFactorPose3(anchor, gtsam.Pose3(graph.vertices[anchor]),
                                    gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for e in odometry:
        base.add(factor(e, robust=False))
    loop_factors = {int(e): factor(int(e), robust=True) for e in loop_edges[in_graph]
                    if np.isfinite(graph.edges[int(e)][2]).all()}
    order = [v for v in ids if v in vertex_scans]
    ref = reference[[vertex_scans[v] for v in order]]
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)

    def ape(edges: list[int]) -> float:
        g = gtsam.NonlinearFactorGraph(base)
        for e in edges:
            if e in loop_factors:
                g.add(loop_factors[e])
        try:
            result = gtsam.LevenbergMarquardtOptimizer(g, initial, params).optimize()
        except RuntimeError as err:  # e.g. an indeterminant system: vertices not joined
            raise LirisError("pose-graph damage", f"optimisation failed: "
                                                  f"{str(err).splitlines()[0]}") from None
        est = np.array([result.atPose3(v).translation() for v in order])
        return ape_rmse(est, ref)

    if len(order) < 3:
        raise LirisError("pose-graph damage", "fewer than 3 vertices are placed on scans")
    status = np.asarray(status)
    true_edges = [int(e) for e in loop_edges[(status == "true") & in_graph]]
    false_idx = np.flatnonzero((status == "false") & in_graph)[:MAX_SINGLE_FALSE]
    ape_true = ape(true_edges)
    plus = np.array([ape(true_edges + [int(loop_edges[k])]) for k in false_idx])
    return Damage(ape([]), ape_true, ape(sorted(loop_set)),
                  false_idx.astype(np.int64), plus, len(order), len(odometry),
                  len(true_edges), int(np.count_nonzero((status == "false") & in_graph)),
                  len(loop_set), kernel, kernel_k)
