"""The researcher's-workflow options of ``liris eval`` (issue 17), kept out of eval_cmd.

:func:`workflow_options` adds

* ``--config RUN/config.yaml``: rerun a recorded run; its values become the
  command's defaults, so any option given on the command line wins;
* ``--external NAME=PATH`` (repeatable) and ``--external-metric``: descriptors
  computed elsewhere, evaluated like the built-in ones;
* ``--format``: print the summary table as an aligned table, Markdown,
  LaTeX or CSV (the same function as ``liris show``).

The command body reads them back with :func:`external_options`,
:func:`table_format` and :func:`config_extra`.
"""

from __future__ import annotations

import functools

import click
from click.core import ParameterSource

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.runs.table import FORMATS

_META = "liris.workflow"


def _load_config(ctx: click.Context, param: click.Parameter, value):
    """Eager ``--config``: the recorded run's options become this call's defaults."""
    if value is None or ctx.resilient_parsing:
        return value
    from lidar_iris_eval.cli.options import REPLAYED_KEY
    from lidar_iris_eval.runs.replay import config_defaults, read_config, replayed_convention

    config = read_config(value)
    defaults = config_defaults(config)
    ctx.meta[REPLAYED_KEY] = replayed_convention(config)  # rebuilt by Settings.from_dict
    for p in ctx.command.params:  # a SEQUENCE... argument takes a list
        if p.name in defaults and p.nargs == -1 and isinstance(defaults[p.name], str):
            defaults[p.name] = [defaults[p.name]]
    ctx.default_map = {**(ctx.default_map or {}), **defaults}
    ctx.meta.setdefault(_META, {})["config"] = str(value)
    return value


def workflow_options(func):
    """``--config``, ``--external``, ``--external-metric`` and ``--format`` (see module doc).

    Apply it above ``descriptor_options``: ``--descriptor`` then becomes
    optional, since ``--external`` alone is a complete request.
    """
    for param in getattr(func, "__click_params__", []):
        if param.name in ("descriptor_text", "protocols", "sequence"):
            param.required = False  # may come from --config or --external; checked below

    @click.option("--config", "config_path", type=click.Path(dir_okay=True), default=None,
                  is_eager=True, expose_value=False, callback=_load_config,
                  help="Rerun a recorded run: RUN/config.yaml (or RUN). Options given here win.")
    @click.option("--external", "externals", multiple=True, metavar="NAME=PATH",
                  help="Evaluate descriptors computed elsewhere: an .npy (N, D) of vectors or "
                       "an (N, N) distance matrix, one row per scan; repeatable.")
    @click.option("--external-metric", type=click.Choice(["l2", "cosine", "l1"]), default=None,
                  help="Distance between external vectors [default: l2; an (N, N) file is read "
                       "as a distance matrix unless a metric is given].")
    @click.option("--format", "fmt", type=click.Choice(FORMATS), default="table",
                  show_default=True, help="Summary table as text, Markdown, LaTeX or CSV.")
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        ctx = click.get_current_context()
        meta = ctx.meta.setdefault(_META, {})
        meta["externals"] = list(kwargs.pop("externals") or ())
        meta["external_metric"] = kwargs.pop("external_metric")
        meta["format"] = kwargs.pop("fmt")
        planned = kwargs.get("plan") is not None  # a plan file names its own runs
        # a query/database run names its own sessions and has its own protocol
        sessions = kwargs.get("query_path") is not None or kwargs.get("database_path") is not None
        paired = kwargs.get("pairs_text") is not None  # --pairs: the list is the protocol
        paired = paired or bool(kwargs.get("loop_paths"))  # --loops: protocol 1 of the file
        loops_from_poses = bool(kwargs.get("loop_paths"))  # --poses alone (checked later)
        if not kwargs.get("sequence") and not planned and not sessions and not loops_from_poses:
            raise LirisError("liris eval", "give a SEQUENCE (or --config RUN/config.yaml)")
        if not kwargs.get("protocols") and not planned and not sessions and not paired:
            raise LirisError("liris eval", "give --protocol 1 and/or --protocol 2")
        # a descriptor list given here replaces the recorded one, with its parameters
        if ctx.get_parameter_source("descriptor_text") == ParameterSource.COMMANDLINE:
            if ctx.get_parameter_source("params") == ParameterSource.DEFAULT_MAP:
                kwargs["params"] = ()
            if ctx.get_parameter_source("externals") == ParameterSource.DEFAULT_MAP:
                meta["externals"] = []
        if ctx.get_parameter_source("externals") == ParameterSource.COMMANDLINE and \
                ctx.get_parameter_source("descriptor_text") == ParameterSource.DEFAULT_MAP:
            kwargs["descriptor_text"] = None
            kwargs["params"] = ()
        several = planned or len(kwargs.get("sequence") or ()) > 1
        if meta["externals"] and several:
            raise LirisError("--external", "one descriptor file fits one sequence; evaluate "
                                           "each sequence with its own --external")
        if (not kwargs.get("descriptor_text") and not meta["externals"] and not planned
                and not kwargs.get("loop_paths")):
            raise LirisError("--descriptor", "give at least one descriptor (or --external)")
        return func(*args, **kwargs)

    return wrapper


def _meta() -> dict:
    return click.get_current_context().meta.get(_META, {})


def external_options() -> tuple[tuple[str, ...], str | None]:
    """The running command's ``--external NAME=PATH`` specs and ``--external-metric``."""
    meta = _meta()
    return tuple(meta.get("externals", [])), meta.get("external_metric")


def load_externals(specs, metric: str | None, seq) -> list:
    """External descriptors from ``NAME=PATH`` specs, checked against ``seq``'s scan count."""
    from lidar_iris_eval.descriptors.external import load_external, parse_external_spec

    out = []
    for spec in specs:
        name, path = parse_external_spec(spec)
        out.append(load_external(name, path, len(seq), metric))
    return out


def table_format() -> str:
    return _meta().get("format", "table")


def config_extra(convention=None) -> dict:
    """Extra ``config.yaml`` keys: the command line, provenance and the convention preset."""
    from lidar_iris_eval.runs.replay import provenance

    extra = {"command": provenance()}
    if _meta().get("config"):
        extra["command"]["replayed_from"] = _meta()["config"]
    if convention is not None:  # the preset the command line resolved (its rules: `convention`)
        extra["command"]["convention"] = convention.name
    return extra  # the conventions block is the run's Settings.to_dict() (Evaluation.config)


def extract_all(seq, descriptors, cache, workers: int, quiet: bool, executor=None):
    """One DescriptorDB per descriptor: extracted (or cached) ones and external files."""
    from lidar_iris_eval.descriptors.external import ExternalDescriptor
    from lidar_iris_eval.extract import external_database, extract_many

    own = [d for d in descriptors if not isinstance(d, ExternalDescriptor)]
    extracted = iter(extract_many(seq, own, cache=cache, workers=workers, progress=not quiet,
                                  executor=executor))  # each scan read once for all of them
    return [external_database(d, seq.name, seq.fingerprint())
            if isinstance(d, ExternalDescriptor) else next(extracted) for d in descriptors]


def export_npy(dbs, folder) -> dict[str, str]:
    """Write each plain ``(N, D)`` numeric descriptor array as ``folder/<name>.npy``.

    These are the files ``liris eval --external NAME=PATH`` reads back, so a
    method's own descriptors can be checked against its built-in evaluation.
    Multi-part (structured) or variable-size descriptors have no such form
    and are reported as skipped. Existing files are never replaced.
    """
    from pathlib import Path

    import numpy as np

    from lidar_iris_eval.atomic import atomic_write
    from lidar_iris_eval.errors import os_error, warn

    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise os_error(err, folder, "cannot create the --export-npy folder") from None
    written = {}
    for db in dbs:
        array = db.descriptors
        if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiu" or array.ndim != 2:
            warn(db.descriptor, "not a plain (N, D) numeric array (a structured or variable-size "
                                "descriptor); not exported")
            continue
        target = folder / f"{db.descriptor}.npy"
        if target.exists():
            raise LirisError(target, "exists; remove it or choose another --export-npy folder")
        atomic_write(target, lambda handle, a=array: np.save(handle, a, allow_pickle=False),
                     what="exported descriptors")
        written[db.descriptor] = str(target)
    return written
