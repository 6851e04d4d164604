"""One ``liris eval`` call as a frozen value (:class:`EvalRequest`) and the mode it asks for.

``liris eval`` has six modes: one sequence, several sequences (or a plan of
them), a query/database pair of sessions, a plan of such pairs, a pair list
(``--pairs``) and other systems' loops (``--loops``). The command body
parses its options into one :class:`EvalRequest` and hands it to the mode
:func:`lidar_iris_eval.cli.eval_cmd.mode_of` names; each mode is a small
function taking the request, which refuses the options it does not use and reads only the
fields it needs. The request is built once, before any work, so no mode
re-reads click's context or the command line.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.loop_poses import LoopPoseSettings
from lidar_iris_eval.evaluation.settings import Settings


@dataclass(frozen=True)
class EvalRequest:
    """Everything one ``liris eval`` call asked for, validated by click and the conventions.

    Frozen so that no mode can change what another one (or the printout)
    reads; the mappings it holds (``reader_options``, ``loop_extra``,
    ``command_extra``) are the parsed options and are not modified by the
    modes (:meth:`config_extra` hands out a copy of the provenance).

    ``convention`` is the resolved convention (``--convention`` and the
    ground-truth options, :meth:`Settings.from_options`); ``settings`` is
    the same with the retrieval depth (``--candidates``) and the block
    budget (``--block-pairs``) of this call.
    """

    convention: Settings
    settings: Settings
    sequences: tuple[Path, ...] = ()
    protocols: tuple[str, ...] = ()
    descriptor_text: str | None = None
    preset: str | None = None
    params: tuple[str, ...] = ()
    sensor: str | None = None
    reader_options: dict[str, Any] = field(default_factory=dict)
    cache_dir: Path | None = None
    workers: int = 1
    scheduler: str = "processes"
    quiet: bool = False
    out: Path | None = None
    overwrite: bool = False
    as_json: bool = False
    fmt: str = "table"
    plan: Path | None = None
    query: Path | None = None
    database: Path | None = None
    align: Path | None = None
    pairs_text: str | None = None
    loop_paths: tuple[Path, ...] = ()
    loops_format: str | None = None
    loops_index_base: int = 0
    loops_gap: int = 1
    loop_extra: dict[str, Any] = field(default_factory=dict)
    convention_band: bool = False
    ranking: bool = False
    export_path: Path | None = None
    loop_settings: LoopPoseSettings = field(default_factory=LoopPoseSettings)
    odometry: str = "gt"
    odometry_path: Path | None = None
    seeds: tuple[int, ...] | None = None
    externals: tuple[str, ...] = ()
    external_metric: str | None = None
    command_extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # checked here, not in a mode: every mode runs workers
        if self.workers < 1:
            raise LirisError(f"--workers {self.workers}", "must be at least 1")

    @property
    def within(self) -> bool:
        """True unless a query/database option is given (a cross-session run)."""
        return self.query is None and self.database is None and self.align is None

    def cache(self):
        """The descriptor cache of ``--cache-dir`` (or the default folder)."""
        from lidar_iris_eval.cache import DescriptorCache, default_cache_dir

        return DescriptorCache(self.cache_dir if self.cache_dir is not None
                               else default_cache_dir())

    def config_extra(self) -> dict[str, Any]:
        """The ``config.yaml`` provenance keys (command line, replay, preset), a fresh copy
        per run written, as :func:`~lidar_iris_eval.cli.workflow.config_extra` made them."""
        return copy.deepcopy(self.command_extra)

    def refuse_convention_band(self) -> None:
        """``--convention-band`` needs one within-sequence run of descriptors."""
        if self.convention_band:
            raise LirisError("--convention-band", "applies to one within-sequence run of "
                             "descriptors (no --query/--database, --plan, --loops, --pairs, "
                             "--seeds)")

    def refuse_estimated_odometry(self) -> None:
        """Refuse an estimated odometry where local maps are not built (cross-session runs)."""
        if self.odometry != "gt":
            raise LirisError(f"--odometry {self.odometry}", "applies to within-sequence runs "
                             "(a SEQUENCE or a plan of sequences)")


__all__ = ["EvalRequest"]
