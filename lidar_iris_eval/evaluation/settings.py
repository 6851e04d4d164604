"""The conventions of one evaluation, frozen in one object (:class:`Settings`).

Every number a result depends on besides the descriptors and the scans lives
here, with its name: the radius of a positive and its inclusivity, the
exclusion window E in frames or seconds (with the named values the literature
uses) and its window rule, the distance, the pose frame, the recall
denominator of protocol 1, LoGG3D-Net's "not a revisit" band, whether the
last frame is a query, the retrieval depth of two-stage methods and the
memory budget of the block driver (which changes speed, not results).

The object is validated once, on construction; peers' presets
(:mod:`~lidar_iris_eval.evaluation.conventions`) are instances of it, and
:meth:`Settings.to_dict` / :meth:`Settings.from_dict` are the ``convention``
block of ``config.yaml`` (and the source of the ``conventions`` block of
``metrics.json``), from which the run reader rebuilds the run's own ground
truth. ``Convention`` is the same class under the name the presets use.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET

#: named exclusion windows (PROTOCOLS.md): the paper's text vs the authors' code
EXCLUDE_PRESETS: dict[str, int] = {"paper": 30, "reference": 300}
DISTANCES = ("3d", "planar")
POSE_FRAMES = ("camera", "lidar")
RECALL_DENOMINATORS = ("revisits", "accepted")
WINDOW_RULES = ("liris", "logg3d")
#: the ground-truth rules (what to_dict writes besides the preset name and source)
RULES = ("radius", "exclude", "exclude_seconds", "window_rule", "distance", "pose_frame",
         "recall_denominator", "not_revisit_radius", "inclusive_radius", "last_frame_query",
         "database_frames", "query_start")


def resolve_exclude(value: int | str) -> tuple[int, str]:
    """``"paper"``, ``"reference"``, an int or a numeric string to ``(E, name)``.

    The name is the preset's, or ``"custom"`` for a value no preset has.
    """
    if isinstance(value, str) and value in EXCLUDE_PRESETS:
        return EXCLUDE_PRESETS[value], value
    try:
        if isinstance(value, bool):
            raise ValueError
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


def parse_exclude(value: int | str, seconds: bool = True
                  ) -> tuple[int | None, float | None, str]:
    """The one parse of a user's E: ``(frames, seconds, name)``.

    ``value`` is a number of frames, a preset name (``"paper"``, ``"reference"``)
    or, when ``seconds`` allows it, a window in seconds such as ``"30s"``
    (``frames`` is then None and ``name`` ``"custom"``). The message of a bad
    value names the option as the user wrote it (``--exclude`` on the command line).
    """
    text = value.strip() if isinstance(value, str) else value
    if isinstance(text, str) and text.lower().endswith("s") and text not in EXCLUDE_PRESETS:
        if not seconds:
            raise LirisError(option("exclude", value), "a window in seconds applies to liris "
                                                       "eval (by scan times), not here")
        window = _seconds(text)
        if not window > 0:
            raise LirisError(option("exclude", value), "exclusion window must be positive")
        return None, window, "custom"
    if isinstance(text, str) and text not in EXCLUDE_PRESETS:
        try:
            int(text)
        except ValueError:
            raise LirisError(option("exclude", value), "expected a number of frames, 'paper' "
                             "(30), 'reference' (300)" + (" or seconds such as 30s"
                                                          if seconds else "")) from None
    frames, name = resolve_exclude(text)
    return frames, None, name


def _seconds(value: Any) -> float | None:
    """``"30s"`` -> 30.0; anything else -> None."""
    if isinstance(value, str) and value.strip().lower().endswith("s") \
            and value.strip() not in EXCLUDE_PRESETS:
        try:
            return float(value.strip()[:-1])
        except ValueError:
            raise LirisError(option("exclude", value), "expected seconds such as 30s") from None
    return None


@dataclass(frozen=True)
class Settings:
    """Evaluation conventions, validated once on construction.

    Attributes
    ----------
    radius : a database frame is a true match closer than this (metres).
    exclude : E in frames, or ``"paper"`` (30) / ``"reference"`` (300), or a
        window in seconds such as ``"30s"``; stored as the number of frames
        (None for a window in seconds), with its name in ``exclude_name``.
    distance : ``"3d"`` or ``"planar"`` (ground plane of the pose frame).
    pose_frame : ``"camera"`` (KITTI camera poses, the paper's counts) or
        ``"lidar"``; ``camera`` falls back to ``lidar`` for sequences without
        camera poses (the run records which was used).
    recall_denominator : protocol 1 recall, ``"revisits"`` or ``"accepted"``.
    candidates : K for retrieval: ``None`` = exhaustive protocol 1 for global
        descriptors, the method's default for two-stage ones.
    pair_budget : distances per block (memory bound; results do not change).
    exclude_seconds : the window in seconds, or None for a window in frames.
    window_rule : ``"liris"`` (database ``t_j <= t_i - T``) or ``"logg3d"``
        (also the first scan after ``t_i - T``, and queries only once ``T``
        has passed since the first scan).
    not_revisit_radius : metres, or None. Accepted matches between
        ``radius`` and this are neither true nor false positives.
    inclusive_radius : a protocol 1 match exactly at ``radius`` is true
        (LoGG3D's ``<=``); protocol 2 positives stay strict.
    last_frame_query : False when the last frame is never a query.
    database_frames : None, or N: the database is frames ``[0, N)`` for every
        query (BEVPlace's split of one sequence); the window is then unused.
    query_start : with ``database_frames``, the first query frame (queries
        are frames ``>= query_start``; default ``database_frames``).
    name : preset name; None names it ``liris`` when every rule is liris'
        default, else ``custom``.
    source : where the values come from.
    """

    radius: float = 4.0
    exclude: int | str | None = "paper"
    distance: str = "3d"
    pose_frame: str = "camera"
    recall_denominator: str = "revisits"
    candidates: int | None = None
    pair_budget: int = DEFAULT_PAIR_BUDGET
    exclude_seconds: float | None = None
    window_rule: str = "liris"
    not_revisit_radius: float | None = None
    inclusive_radius: bool = False
    last_frame_query: bool = True
    database_frames: int | None = None
    query_start: int | None = None
    name: str | None = None
    source: str = ""
    exclude_name: str = field(init=False, default="")

    def __post_init__(self) -> None:
        seconds = self.exclude_seconds
        if seconds is None:
            seconds = _seconds(self.exclude)
        if seconds is not None:
            if not float(seconds) > 0:
                raise LirisError(option("exclude", f"{seconds}s"),
                                 "exclusion window must be positive")
            object.__setattr__(self, "exclude_seconds", float(seconds))
            object.__setattr__(self, "exclude", None)
            object.__setattr__(self, "exclude_name", "seconds")
        else:
            frames, name = resolve_exclude(self.exclude)
            object.__setattr__(self, "exclude", frames)
            object.__setattr__(self, "exclude_name", name)
        try:
            radius_ok = 0 < float(self.radius) < float("inf")
        except (TypeError, ValueError):
            radius_ok = False
        if not radius_ok:
            raise LirisError(option("radius", self.radius), "radius must be positive")
        for key, allowed in (("distance", DISTANCES), ("pose_frame", POSE_FRAMES),
                             ("recall_denominator", RECALL_DENOMINATORS),
                             ("window_rule", WINDOW_RULES)):
            if getattr(self, key) not in allowed:
                raise LirisError(option(key, getattr(self, key)),
                                 f"choose from {', '.join(allowed)}")
        if self.candidates is not None and self.candidates < 1:
            raise LirisError(option("candidates", self.candidates), "must be at least 1")
        if self.pair_budget < 1:
            raise LirisError(option("pair_budget", self.pair_budget), "must be at least 1")
        if self.not_revisit_radius is not None and not self.not_revisit_radius >= self.radius:
            raise LirisError(option("not_revisit_radius", self.not_revisit_radius),
                             "must be at least the radius")
        if self.database_frames is not None:
            start = self.database_frames if self.query_start is None else self.query_start
            if self.database_frames < 1 or start < self.database_frames:
                raise LirisError(option("database_frames", self.database_frames),
                                 "needs at least 1 database frame and queries after them")
            object.__setattr__(self, "query_start", int(start))
        elif self.query_start is not None:
            raise LirisError(option("query_start", self.query_start),
                             "only used together with database_frames")
        if self.name is None:
            default = all(getattr(self, k) == getattr(_LIRIS_RULES, k) for k in RULES) \
                if _LIRIS_RULES is not None else True
            object.__setattr__(self, "name", "liris" if default else "custom")

    @property
    def standard(self) -> bool:
        """True when the ordinary protocol 1 (frame window, strict radius) applies."""
        return (self.exclude_seconds is None and self.not_revisit_radius is None
                and not self.inclusive_radius and self.last_frame_query
                and self.database_frames is None)

    def replace(self, **values) -> Settings:
        """A validated copy with ``values`` replaced (see :func:`with_overrides` for names)."""
        return dataclasses.replace(self, **values)

    def as_dict(self) -> dict:
        """Plain dict of every field (for tests and debugging)."""
        return dataclasses.asdict(self)

    def to_dict(self) -> dict:
        """The ``convention`` block of ``config.yaml``: preset name, every rule, source."""
        return {"preset": self.name, **{k: getattr(self, k) for k in RULES},
                "source": self.source}

    @classmethod
    def from_dict(cls, block: dict, **extra) -> Settings:
        """Rebuild from :meth:`to_dict` output (unknown keys are ignored); ``extra``
        sets the fields that block does not hold (``candidates``, ``pair_budget``)."""
        values = {k: block[k] for k in RULES if k in block}
        if values.get("exclude_seconds") is not None:
            values["exclude"] = None
        elif values.get("exclude") is None:
            values.pop("exclude", None)
        name = block.get("preset", block.get("name"))
        return cls(**values, name=name, source=block.get("source") or "", **extra)

    @classmethod
    def from_options(cls, convention: Settings | None = None, **given) -> Settings:
        """The conventions of one command call, parsed once.

        Parameters
        ----------
        convention : the rules to start from: a peer's preset
            (:func:`~lidar_iris_eval.evaluation.conventions.get_convention`), the
            recorded rules of a run replayed with ``--config``
            (:meth:`Settings.from_dict`), or None when no preset is asked, so the
            options alone form the convention.
        **given : the options the user set explicitly, as written (``exclude`` may be
            ``"paper"``, ``"12"`` or ``"30s"``); None values are ignored.

        Returns
        -------
        Settings
            ``convention`` with the given rules replaced, renamed ``<name>+custom``
            when a rule changes (a name already ending in ``custom`` is kept).
            Without a convention: the ``liris`` preset when the options are its
            rules, else ``custom`` from the command-line options. The only place
            the command line's conventions are parsed and merged, so a preset
            added to the table, a replayed run and the Python API agree.
        """
        unknown = set(given) - set(OPTION_RULES)
        if unknown:
            raise TypeError(f"Settings.from_options: unknown options {sorted(unknown)}")
        values = {k: v for k, v in given.items() if v is not None}
        if "exclude" in values:
            values["exclude"], values["exclude_seconds"], _ = parse_exclude(values["exclude"])
        if convention is None:
            conv = with_overrides(LIRIS, **values)
            return LIRIS if same_rules(conv, LIRIS) else with_overrides(
                conv, name="custom", source="command-line options")
        if not values:  # nothing given: the rules themselves
            return convention
        if convention.name.endswith("custom"):
            values["name"] = convention.name
        return with_overrides(convention, **values)


_LIRIS_RULES: Settings | None = None
#: the ``liris`` preset (the conventions table lists it first): the defaults of every rule
_LIRIS_RULES = Settings(
    name="liris", radius=4.0, exclude=30, distance="3d", pose_frame="camera",
    recall_denominator="revisits",
    source="LiDAR Iris paper (IROS 2020) text: 4 m, E = 30; recall over revisit queries "
           "as in the authors' draw.py")
LIRIS = _LIRIS_RULES


def with_overrides(conv: Settings, **values) -> Settings:
    """A copy of ``conv`` with the given fields replaced (None values are ignored).

    Setting ``exclude`` clears ``exclude_seconds`` and vice versa, since a
    window is either in frames or in seconds. A changed rule renames the
    copy ``<name>+custom`` unless ``name`` is given.
    """
    given = {k: v for k, v in values.items() if v is not None}
    if "exclude" in given:
        given.setdefault("exclude_seconds", None)
    if given.get("exclude_seconds") is not None:
        given["exclude"] = None
    changed = any(getattr(conv, k) != v for k, v in given.items()
                  if k not in ("name", "source"))
    if changed and "name" not in given:
        given["name"] = f"{conv.name}+custom"
    return conv.replace(**given)


def same_rules(a: Settings, b: Settings) -> bool:
    """True when two conventions differ at most in name and source."""
    return all(getattr(a, k) == getattr(b, k) for k in RULES)


#: the rules a command line sets (``--radius``, ``--exclude``, ``--distance``, ...)
OPTION_RULES = ("radius", "exclude", "distance", "pose_frame", "recall_denominator")



#: the name the conventions module and its presets use for the same object
Convention = Settings
