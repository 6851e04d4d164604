"""Methods and dataset readers from outside the repository.

A package adds a method or a dataset reader to liris without forking it by
declaring an entry point (``importlib.metadata``; the same mechanism pytest
and nerfstudio use to find their plugins)::

    # pyproject.toml of the package "liris-mine"
    [project.entry-points."liris.methods"]
    mine = "liris_mine.method:Mine"            # a Descriptor subclass

    [project.entry-points."liris.datasets"]
    mine-data = "liris_mine.reader:SPEC"       # a lidar_iris_eval.io.datasets.DatasetSpec

Once the package is installed (``pip install -e .``), ``liris eval SEQ -d mine``
runs the method and SEQ is detected (or forced with ``--dataset mine-data``)
with the reader. For a quick trial without a package, the environment
variables ``LIRIS_METHODS`` and ``LIRIS_DATASETS`` hold comma-separated
``name=module:attr`` entries (``LIRIS_METHODS=mine=my_module:Mine``); their
modules are imported from ``sys.path`` and then the working directory. An
environment entry replaces an entry point of the same name; neither replaces a
built-in name.

Nothing is imported until a plugin is used; a plugin that cannot be loaded
is one error naming it (:meth:`Plugin.load`).
"""

from __future__ import annotations

import importlib
import os
import sys
from dataclasses import dataclass
from typing import Any

from lidar_iris_eval.errors import LirisError

#: kind -> (entry-point group, environment variable)
GROUPS = {"methods": ("liris.methods", "LIRIS_METHODS"),
          "datasets": ("liris.datasets", "LIRIS_DATASETS")}


@dataclass(frozen=True)
class Plugin:
    """One external method or reader: ``name`` -> ``target`` (``"module:attr"``)."""

    kind: str  # "methods" or "datasets"
    name: str
    target: str
    origin: str  # "entry point liris.methods of liris-mine 0.1" or "LIRIS_METHODS"

    @property
    def label(self) -> str:
        """How messages name the plugin."""
        what = "method" if self.kind == "methods" else "dataset"
        return f"{what} plugin {self.name} ({self.target}, {self.origin})"

    @property
    def from_environment(self) -> bool:
        return not self.origin.startswith("entry point")

    def load(self) -> Any:
        """Import the module and return the attribute; one LirisError naming the plugin."""
        module_name, _, attr = self.target.partition(":")
        added = self.from_environment and os.getcwd() not in sys.path
        if added:  # a quick trial: my_module.py in the working directory
            sys.path.append(os.getcwd())
        try:
            value = importlib.import_module(module_name)
            for part in attr.split("."):
                value = getattr(value, part)
        except Exception as err:  # any failure of someone else's module: name it, exit 2
            detail = " ".join(str(err).split()) or "no message"
            raise LirisError(self.label, f"cannot be loaded: {type(err).__name__}: "
                                         f"{detail}") from None
        finally:
            if added and os.getcwd() in sys.path:
                sys.path.remove(os.getcwd())
        return value


def _parse_environment(kind: str) -> list[Plugin]:
    variable = GROUPS[kind][1]
    text = os.environ.get(variable, "").strip()
    out = []
    for entry in (e.strip() for e in text.split(",")):
        if not entry:
            continue
        name, sep, target = (s.strip() for s in entry.partition("="))
        module_name, colon, attr = target.partition(":")
        if not sep or not name or not colon or not module_name or not attr:
            raise LirisError(f"{variable}={text}",
                             f"expected comma-separated name=module:attr entries, got "
                             f"{entry!r}")
        out.append(Plugin(kind, name, target, variable))
    return out


def _entry_points(kind: str) -> list[Plugin]:
    from importlib.metadata import entry_points

    group = GROUPS[kind][0]
    out = []
    for ep in entry_points(group=group):
        dist = getattr(ep, "dist", None)
        owner = f" of {dist.metadata['Name']} {dist.version}" if dist is not None else ""
        out.append(Plugin(kind, ep.name, ep.value, f"entry point {group}{owner}"))
    return out


_CACHE: dict[tuple, list[Plugin]] = {}


def plugins(kind: str, reserved: frozenset[str] | set[str] = frozenset()) -> list[Plugin]:
    """The external ``kind`` ("methods" or "datasets"), entry points then environment.

    An environment entry replaces an entry point of the same name; a name in
    ``reserved`` (the built-in names) is never replaced, and one entry point
    claiming it is an error. A malformed environment variable is a LirisError.
    The answer is cached per ``sys.path`` and environment value.
    """
    key = (kind, tuple(sys.path), os.environ.get(GROUPS[kind][1], ""))
    if key not in _CACHE:
        found: dict[str, Plugin] = {}
        for plugin in _entry_points(kind) + _parse_environment(kind):
            found[plugin.name] = plugin
        if len(_CACHE) > 32:
            _CACHE.clear()
        _CACHE[key] = list(found.values())
    taken = [p for p in _CACHE[key] if p.name in reserved]
    if taken:
        raise LirisError(taken[0].label, "uses the name of a built-in; choose another name")
    return list(_CACHE[key])


__all__ = ["GROUPS", "Plugin", "plugins"]
