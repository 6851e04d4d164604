"""What ``liris bench`` measures and the bars it judges (issues 8 and 18)."""

from __future__ import annotations

from dataclasses import dataclass

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET

#: descriptors benchmarked by default; Scan Context tries every shift (no pruning)
DEFAULT_DESCRIPTORS = "lidar-iris,scan-context:exhaustive,m2dp,esf"
#: preset used for a descriptor named without one (and without --preset)
DEFAULT_PRESETS = {"scan-context": "exhaustive"}
#: issue 8's bars, valid for a 4541-frame sequence on a 2-core machine
BAR_FRAMES = 4541
BAR_LIDAR_IRIS_PROTOCOL_S = 180.0
BAR_LIDAR_IRIS_PEAK_GIB = 4.0
BAR_SCAN_CONTEXT_PROTOCOL2_S = 120.0
BAR_LIDAR_IRIS_SPEEDUP = 100.0
BAR_LIDAR_IRIS_LOOP_PAIRS = 1000


@dataclass(frozen=True)
class BenchSettings:
    """What to measure and how much of it.

    Attributes
    ----------
    exclude, radius : protocol settings (E frames, positive radius in metres).
    protocols : which protocols to time (1, 2 or both).
    loop_pairs : random pairs for the per-pair loop and the equality check.
    loop_pool : the pairs are drawn among this many random frames, so the
        loop's per-frame preparation (e.g. unpacking LiDAR Iris bits) stays
        small; ``loop_pool**2`` must comfortably exceed ``loop_pairs``.
    kernel_queries, kernel_repeats : block of queries timed against the whole
        database, and how often (the median is kept).
    workers : extraction processes (per-scan times are clean only with 1).
    isolate : run each protocol in a fresh spawned process (honest peak
        memory); False runs them in this process (for quick checks only).
    pair_budget : distances per block of the matching driver.
    seed : random pair selection.
    """

    exclude: int = 30
    radius: float = 4.0
    protocols: tuple[int, ...] = (1, 2)
    loop_pairs: int = 1000
    loop_pool: int = 200
    kernel_queries: int = 128
    kernel_repeats: int = 3
    workers: int = 1
    isolate: bool = True
    pair_budget: int = DEFAULT_PAIR_BUDGET
    seed: int = 0

    def __post_init__(self) -> None:
        checks = [
            ("--exclude", self.exclude >= 1, "must be at least 1"),
            ("--radius", self.radius > 0, "must be positive"),
            ("--loop-pairs", self.loop_pairs >= 0, "must be >= 0"),
            ("--loop-pool", self.loop_pool >= 2, "must be at least 2"),
            ("--kernel-queries", self.kernel_queries >= 1, "must be at least 1"),
            ("--kernel-repeats", self.kernel_repeats >= 1, "must be at least 1"),
            ("--workers", self.workers >= 1, "must be at least 1"),
            ("--block-pairs", self.pair_budget >= 1, "must be at least 1"),
        ]
        for source, ok, problem in checks:
            if not ok:
                raise LirisError(source, problem)
        if not set(self.protocols) <= {1, 2}:
            raise LirisError("protocols", "choose from 1 and 2")
