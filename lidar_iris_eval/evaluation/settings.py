"""The conventions of one evaluation, frozen in one object.

Every number a result depends on besides the descriptors and the scans lives
here, with its name: the radius of a positive, the exclusion window E (with
the named values the literature uses), the distance, the pose frame, the
recall denominator of protocol 1, the retrieval depth of two-stage methods
and the memory budget of the block driver (which changes speed, not results).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.evaluation.protocol1 import RECALL_DENOMINATORS
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET

#: named exclusion windows (PROTOCOLS.md): the paper's text vs the authors' code
EXCLUDE_PRESETS: dict[str, int] = {"paper": 30, "reference": 300}
DISTANCES = ("3d", "planar")
POSE_FRAMES = ("camera", "lidar")


def resolve_exclude(value: int | str) -> tuple[int, str]:
    """``"paper"``, ``"reference"``, an int or a numeric string to ``(E, name)``.

    The name is the preset's, or ``"custom"`` for a value no preset has.
    """
    if isinstance(value, str) and value in EXCLUDE_PRESETS:
        return EXCLUDE_PRESETS[value], value
    try:
        frames = int(value)
        if isinstance(value, float) and value != frames:
            raise ValueError
    except (TypeError, ValueError):
        raise LirisError(
            option("exclude", value),
            "expected a number of frames, 'paper' (30) or 'reference' (300)",
        ) from None
    if frames < 1:
        raise LirisError(option("exclude", value), "exclusion window must be at least 1 frame")
    named = {v: k for k, v in EXCLUDE_PRESETS.items()}.get(frames, "custom")
    return frames, named


@dataclass(frozen=True)
class Settings:
    """Evaluation conventions (validated on construction).

    Attributes
    ----------
    radius : a pair is positive when its frames are closer than this (metres).
    exclude : E in frames, or ``"paper"`` (30) / ``"reference"`` (300);
        stored as the number, with its name in ``exclude_name``.
    distance : ``"3d"`` or ``"planar"`` (ground plane of the pose frame).
    pose_frame : ``"camera"`` (KITTI camera poses, the paper's counts) or
        ``"lidar"``; ``camera`` falls back to ``lidar`` for sequences without
        camera poses (the run records which was used).
    recall_denominator : protocol 1 recall, ``"revisits"`` or ``"accepted"``.
    candidates : K for retrieval: ``None`` = exhaustive protocol 1 for global
        descriptors, the method's default for two-stage ones.
    pair_budget : distances per block (memory bound; results do not change).
    """

    radius: float = 4.0
    exclude: int | str = "paper"
    distance: str = "3d"
    pose_frame: str = "camera"
    recall_denominator: str = "revisits"
    candidates: int | None = None
    pair_budget: int = DEFAULT_PAIR_BUDGET
    exclude_name: str = field(init=False, default="")

    def __post_init__(self) -> None:
        frames, name = resolve_exclude(self.exclude)
        object.__setattr__(self, "exclude", frames)
        object.__setattr__(self, "exclude_name", name)
        if not self.radius > 0:
            raise LirisError(option("radius", self.radius), "radius must be positive")
        if self.distance not in DISTANCES:
            raise LirisError(option("distance", self.distance), f"choose from {DISTANCES}")
        if self.pose_frame not in POSE_FRAMES:
            raise LirisError(option("pose_frame", self.pose_frame),
                             f"choose from {POSE_FRAMES}")
        if self.recall_denominator not in RECALL_DENOMINATORS:
            raise LirisError(option("recall_denominator", self.recall_denominator),
                             f"choose from {RECALL_DENOMINATORS}")
        if self.candidates is not None and self.candidates < 1:
            raise LirisError(option("candidates", self.candidates), "must be at least 1")
        if self.pair_budget < 1:
            raise LirisError(option("pair_budget", self.pair_budget), "must be at least 1")

    def as_dict(self) -> dict:
        """Plain dict of every setting (for config.yaml / metrics.json)."""
        return asdict(self)
