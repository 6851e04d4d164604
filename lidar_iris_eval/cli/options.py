"""Click options shared by several subcommands, so each convention is spelled once."""

from __future__ import annotations

import functools

import click
from click.core import ParameterSource

from lidar_iris_eval.evaluation.settings import EXCLUDE_PRESETS, OPTION_RULES, Settings  # noqa: F401 (re-exported)
from lidar_iris_eval.evaluation.settings import parse_exclude as settings_parse_exclude

#: where the resolved convention preset is kept for the command body (click ctx.meta)
CONVENTION_KEY = "liris.convention"
#: the ``convention`` block of a run replayed with ``--config`` (set by cli/workflow.py)
REPLAYED_KEY = "liris.replayed_convention"


def parse_exclude(value: str) -> tuple[int, str]:
    """``"paper"``, ``"reference"`` or frames to ``(E, name)``; seconds are refused here
    (commands without scan times). The parse is :func:`settings.parse_exclude`."""
    frames, _, name = settings_parse_exclude(value, seconds=False)
    return frames, name


def _given(ctx: click.Context, name: str) -> bool:
    """True when the user set ``name`` (command line, environment or a replayed config)."""
    source = ctx.get_parameter_source(name)
    return source not in (None, ParameterSource.DEFAULT)


def resolve_convention(ctx: click.Context, name: str | None, kwargs: dict):
    """The :class:`~lidar_iris_eval.evaluation.settings.Settings` of a command call.

    The options the user set (command line, environment or a replayed config)
    go to :meth:`Settings.from_options`, the one parse and merge of the
    conventions: a preset's values fill every option not set, options set
    explicitly win (``<preset>+custom``); without a preset the options form
    the convention. A run replayed with ``--config`` (and no ``--convention``)
    starts from its recorded rules, ``Settings.from_dict(config["convention"])``.
    ``kwargs`` is updated in place with the values used; a window in seconds
    leaves ``exclude`` as the string ``"<T>s"``.
    """
    from lidar_iris_eval.evaluation.conventions import get_convention

    replayed = ctx.meta.get(REPLAYED_KEY) if name is None else None
    if replayed is not None:
        base = Settings.from_dict(replayed)
    elif name is not None:  # a query/database run may use the cross-session presets
        cross = bool(ctx.params.get("query_path")) and bool(ctx.params.get("database_path"))
        base = get_convention(name, cross_session=cross)
    else:
        base = None
    given = {key: kwargs[key] for key in OPTION_RULES if key in kwargs and _given(ctx, key)}
    conv = Settings.from_options(base, **given)
    # the user's spelling of E stays ("paper", "30s") unless a preset or a replay set it
    keep = replayed is None and ("exclude" in given or name is None)
    _effective_values(conv, kwargs, keep_exclude=keep)
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


#: ``--workers``'s default in every verb that has it (``liris eval`` and ``extract``,
#: ``liris simulate``): one process, so a run is serial unless asked otherwise
DEFAULT_WORKERS = 1


def workers_option(what: str):
    """The ``--workers`` option, declared once for every verb that runs a process pool.

    ``what`` says what the processes do in that verb (its help text). The
    check (at least 1, clamped to the usable CPUs with a warning) is attached
    to every option named ``workers`` in :mod:`lidar_iris_eval.cli`.
    """
    return click.option("--workers", type=int, default=DEFAULT_WORKERS, show_default=True,
                        help=f"Processes for {what}.")
