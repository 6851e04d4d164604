"""Click options shared by several subcommands, so each convention is spelled once."""

from __future__ import annotations

import functools

import click
from click.core import ParameterSource

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.settings import EXCLUDE_PRESETS, resolve_exclude

#: where the resolved convention preset is kept for the command body (click ctx.meta)
CONVENTION_KEY = "liris.convention"
#: the ``convention`` block of a run replayed with ``--config`` (set by cli/workflow.py)
REPLAYED_KEY = "liris.replayed_convention"


def parse_exclude(value: str) -> tuple[int, str]:
    """``"paper"``, ``"reference"`` or an integer to ``(E, name)`` (:func:`resolve_exclude`)."""
    if value not in EXCLUDE_PRESETS:
        if isinstance(value, str) and value.strip().lower().endswith("s"):
            raise LirisError(f"--exclude {value}",
                             "a window in seconds applies to liris eval (by scan times), not here")
        try:
            int(value)
        except ValueError:
            raise LirisError(
                f"--exclude {value}",
                "expected a number of frames, 'paper' (30), 'reference' (300) "
                "or seconds such as 30s",
            ) from None
    return resolve_exclude(value)


def parse_exclude_window(value: str) -> tuple[int | None, float | None, str]:
    """Like :func:`parse_exclude`, also accepting seconds (``"30s"``): ``(E, seconds, name)``."""
    text = str(value).strip()
    if text.lower().endswith("s") and text not in EXCLUDE_PRESETS:
        try:
            seconds = float(text[:-1])
        except ValueError:
            raise LirisError(f"--exclude {value}", "expected seconds such as 30s") from None
        if not seconds > 0:
            raise LirisError(f"--exclude {value}", "exclusion window must be positive")
        return None, seconds, "custom"
    frames, name = parse_exclude(text)
    return frames, None, name


def _given(ctx: click.Context, name: str) -> bool:
    """True when the user set ``name`` (command line, environment or a replayed config)."""
    source = ctx.get_parameter_source(name)
    return source not in (None, ParameterSource.DEFAULT)


def resolve_convention(ctx: click.Context, name: str | None, kwargs: dict):
    """The :class:`~lidar_iris_eval.evaluation.conventions.Convention` of a command call.

    A preset's values fill every ground-truth option the user did not set;
    options set explicitly win (the result is then named ``<preset>+custom``).
    Without a preset, the options themselves form the convention ("liris"
    with the given values). ``kwargs`` is updated in place with the values
    used; a window in seconds leaves ``exclude`` as the string ``"<T>s"``.

    A run replayed with ``--config`` (and no ``--convention``) starts from its
    recorded rules, ``Settings.from_dict(config["convention"])``, and only the
    options given on the command line change them.
    """
    from lidar_iris_eval.evaluation.conventions import get_convention, same_rules, with_overrides
    from lidar_iris_eval.evaluation.settings import Settings

    replayed = ctx.meta.get(REPLAYED_KEY)
    if replayed is not None and name is None:
        return _replayed_convention(ctx, Settings.from_dict(replayed), kwargs)
    # a query/database run (liris eval --query --database) may use the cross-session presets
    cross = bool(ctx.params.get("query_path")) and bool(ctx.params.get("database_path"))
    base = get_convention(name or "liris", cross_session=cross)
    values = {}
    if _given(ctx, "radius") or name is None:
        values["radius"] = kwargs["radius"]
    if _given(ctx, "exclude") or name is None:
        frames, seconds, _ = parse_exclude_window(kwargs["exclude"])
        values["exclude"] = frames
        values["exclude_seconds"] = seconds
    for key in ("distance", "pose_frame", "recall_denominator"):
        if key in kwargs and (_given(ctx, key) or name is None):
            values[key] = kwargs[key]
    conv = with_overrides(base, **values)
    if name is None:  # no preset asked: "liris" when the options are its defaults
        conv = base if same_rules(conv, base) else with_overrides(
            conv, name="custom", source="command-line options")
    _effective_values(conv, kwargs, keep_exclude=_given(ctx, "exclude") or name is None)
    return conv


def _replayed_convention(ctx: click.Context, recorded, kwargs: dict):
    """``--config``: the recorded Settings, with the ground-truth options given here."""
    from lidar_iris_eval.evaluation.conventions import with_overrides

    values = {key: kwargs[key] for key in ("radius", "distance", "pose_frame",
                                           "recall_denominator")
              if key in kwargs and _given(ctx, key)}
    if _given(ctx, "exclude"):
        values["exclude"], values["exclude_seconds"], _ = parse_exclude_window(kwargs["exclude"])
    if values and recorded.name.endswith("custom"):  # already custom: keep its name
        values["name"] = recorded.name
    conv = with_overrides(recorded, **values)
    _effective_values(conv, kwargs, keep_exclude=False)
    return conv


def _effective_values(conv, kwargs: dict, keep_exclude: bool) -> None:
    """Write the convention's values back into the command's keyword arguments."""
    kwargs["radius"] = conv.radius
    kwargs["distance"] = conv.distance
    kwargs["pose_frame"] = conv.pose_frame
    if "recall_denominator" in kwargs:
        kwargs["recall_denominator"] = conv.recall_denominator
    if conv.exclude_seconds is not None:
        kwargs["exclude"] = f"{conv.exclude_seconds:g}s"
    elif not keep_exclude or kwargs["exclude"] is None:
        kwargs["exclude"] = str(conv.exclude)


def _preset_names(names) -> str:
    """Preset names comma-separated; a numbered family (``bevplace-00`` ...) as ``first..last``."""
    import re

    out, families = [], {}
    for name in names:
        m = re.fullmatch(r"(.+-)(\d+)", name)
        if m:
            if m[1] not in families:
                families[m[1]] = []
                out.append(m[1])
            families[m[1]].append(m[2])
        else:
            out.append(name)
    shown = []
    for item in out:
        nums = families.get(item)
        if nums is None:
            shown.append(item)
        elif len(nums) == 1:
            shown.append(item + nums[0])
        else:
            shown.append(f"{item}{nums[0]}..{nums[-1]}")
    return ", ".join(shown)


def convention_help() -> str:
    """``--convention`` help, listing the presets of the conventions table."""
    from lidar_iris_eval.evaluation.conventions import CROSS_SESSION_PRESETS, PRESETS

    return (f"A peer's ground-truth convention: {_preset_names(PRESETS)}; with --query/--database "
            f"also {_preset_names(CROSS_SESSION_PRESETS)} (docs/conventions.md); options given "
            "explicitly win.")


class _ConventionOption(click.Option):
    """``--convention``, whose help is read from the presets table when shown."""

    def get_help_record(self, ctx):
        self.help = convention_help()
        return super().get_help_record(ctx)


def ground_truth_options(func):
    """``--radius``, ``--exclude``, ``--distance``, ``--pose-frame`` and ``--convention``.

    The command receives the effective values (a ``--convention`` preset fills
    the options not given); the resolved convention object is in
    ``click.get_current_context().meta[CONVENTION_KEY]``.
    """

    @click.option("--radius", type=float, default=4.0, show_default=True,
                  help="A pair is positive when closer than this (metres).")
    @click.option("--exclude", "exclude", default="paper", show_default=True,
                  help="Exclusion window E in frames, 'paper' (30) / 'reference' (300), or "
                       "seconds by scan time such as 30s (liris eval).")
    @click.option("--distance", type=click.Choice(["3d", "planar"]), default="3d",
                  show_default=True, help="3-D distance, or planar in the ground plane.")
    @click.option("--pose-frame", type=click.Choice(["camera", "lidar"]), default="camera",
                  show_default=True,
                  help="Measure distances between camera poses (KITTI, the paper) or LiDAR poses.")
    @click.option("--convention", "convention_name", default=None, metavar="NAME",
                  cls=_ConventionOption)
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        ctx = click.get_current_context()
        name = kwargs.pop("convention_name")
        ctx.meta[CONVENTION_KEY] = resolve_convention(ctx, name, kwargs)
        return func(*args, **kwargs)

    return wrapper


def current_convention():
    """The convention resolved by :func:`ground_truth_options` for the running command."""
    return click.get_current_context().meta.get(CONVENTION_KEY)


def deprecated_alias(old: str, new: str, dest: str, **option_kwargs):
    """Keep an old option spelling working for one release, with a warning.

    Adds a hidden option ``old`` whose value, when given, is passed to the
    command as ``dest`` (the parameter of the new spelling ``new``). Apply it
    next to the new option's decorator.
    """
    hidden = f"deprecated_{dest}"

    def decorator(func):
        @click.option(old, hidden, default=None, hidden=True, expose_value=True,
                      **option_kwargs)
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            value = kwargs.pop(hidden)
            if value is not None:
                from lidar_iris_eval.errors import warn

                warn(old, f"deprecated; use {new} (the old spelling goes in the next release)")
                kwargs[dest] = value
            return func(*args, **kwargs)

        return wrapper

    return decorator
