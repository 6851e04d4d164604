"""Global descriptors and their registry.

Use :func:`get_descriptor` to build one by name and preset::

    desc = get_descriptor("lidar-iris", preset="paper")
"""

from __future__ import annotations

import importlib
import importlib.util

from lidar_iris_eval.config import descriptor_preset_values, make_params
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError, option, warn

#: registry name -> "module:ClassName"; modules import lazily so that a broken
#: or slow descriptor does not slow down the others.
_REGISTRY: dict[str, str] = {
    "lidar-iris": "lidar_iris_eval.descriptors.lidar_iris:LidarIris",
    "scan-context": "lidar_iris_eval.descriptors.scan_context:ScanContext",
    "m2dp": "lidar_iris_eval.descriptors.m2dp:M2DP",
    "esf": "lidar_iris_eval.descriptors.esf:ESF",
    "gosmatch": "lidar_iris_eval.descriptors.gosmatch:GOSMatch",
    "esm": "lidar_iris_eval.descriptors.esm:ESM",
    "overlap-transformer": "lidar_iris_eval.descriptors.overlap_transformer:OverlapTransformer",
    "bevplace": "lidar_iris_eval.descriptors.bevplace:BEVPlace",
    # optional extra "mapclosures"; without it -d mapclosures is one error line
    "mapclosures": "lidar_iris_eval.descriptors.mapclosures:MapClosures",
}


#: the built-in names, which no plugin may take
_BUILTIN = frozenset(_REGISTRY)


def _plugins(strict: bool = True) -> dict:
    """External methods (entry points ``liris.methods``, ``LIRIS_METHODS``) by name.

    ``strict=False`` (listings, help text) drops what cannot be read instead
    of raising: only using a broken plugin is an error.
    """
    from lidar_iris_eval.plugins import plugins

    try:
        found = plugins("methods", reserved=_BUILTIN)
    except LirisError:
        if strict:
            raise
        return {}
    return {p.name: p for p in found if p.name not in _REGISTRY}


def _targets(strict: bool = False) -> dict[str, str]:
    """Every registered name -> ``"module:ClassName"``: the table, then the plugins."""
    return {**_REGISTRY, **{n: p.target for n, p in _plugins(strict).items()}}


def _findable(module_name: str) -> bool:
    try:
        return importlib.util.find_spec(module_name) is not None
    except Exception:  # a plugin's parent package that fails to import: not listed
        return False


def register_descriptor(name: str, target: str) -> None:
    """Register a descriptor class under ``name``, given as ``"module:ClassName"``.

    This is how a new method (or a test double) plugs into extract, eval and
    bench without touching them; the module is imported on first use.
    """
    if ":" not in target:
        raise ValueError(f"target must be 'module:ClassName', got {target!r}")
    _REGISTRY[name] = target


def available_descriptors() -> list[str]:
    """Names of the registered descriptors whose module is present."""
    return [name for name, target in _targets().items() if _findable(target.split(":")[0])]


def registered_names() -> list[str]:
    """Every registered name, in registry order (the order figures list methods in);
    external methods (entry points, ``LIRIS_METHODS``) after the built-in ones."""
    return list(_targets())


def registered_class(name: str) -> type[Descriptor] | None:
    """The class registered under ``name``, or None when unknown or not importable."""
    targets = _targets()
    if name not in targets:
        return None
    module_name, class_name = targets[name].split(":")
    try:
        return getattr(importlib.import_module(module_name), class_name)
    except Exception:  # a broken plugin: figures fall back to their defaults
        return None


def method_module(name: str, part: str) -> str | None:
    """``<method package>.<part>`` (e.g. ``reference_loop``) when that module exists.

    A method's folder holds its own reference loop and presets, found from
    its registry line alone.
    """
    targets = _targets()
    if name not in targets:
        return None
    package = targets[name].split(":")[0]
    target = f"{package}.{part}"
    try:
        return target if importlib.util.find_spec(target) is not None else None
    except ModuleNotFoundError:
        return None


def method_folder(name: str):
    """The folder of the package registered under ``name``.

    For an external method whose class sits in a plain module
    (``liris_mine.method:Mine``), the folder of that module (its package);
    None for a built-in or ``register_descriptor`` module outside a package.
    """
    from pathlib import Path

    targets = _targets()
    if name not in targets:
        return None
    try:
        spec = importlib.util.find_spec(targets[name].split(":")[0])
    except Exception:
        return None
    if spec is None:
        return None
    if spec.submodule_search_locations:
        return Path(next(iter(spec.submodule_search_locations)))
    if name in _plugins(strict=False) and spec.origin:
        return Path(spec.origin).parent
    return None


def _plugin_class(plugin) -> type[Descriptor]:
    """Load an external method's class; one LirisError naming the plugin if it is broken."""
    cls = plugin.load()
    if not (isinstance(cls, type) and issubclass(cls, Descriptor)):
        raise LirisError(plugin.label, "is not a lidar_iris_eval.descriptors.base.Descriptor "
                                       "subclass")
    if getattr(cls, "name", None) != plugin.name:
        raise LirisError(plugin.label, f"its class is named {getattr(cls, 'name', None)!r}; "
                                       "the entry's name must be the class's `name`")
    return cls


def descriptor_class(name: str) -> type[Descriptor]:
    """The class registered under ``name``; an unknown name or a broken plugin is a
    LirisError."""
    external = _plugins(strict=True)
    if name in external:
        return _plugin_class(external[name])
    if name not in available_descriptors():
        raise LirisError(
            option("descriptor", name),
            f"unknown descriptor; choose from {', '.join(available_descriptors())}",
        )
    module_name, class_name = _REGISTRY[name].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def get_descriptor(
    name: str, preset: str | None = None, sensor: str | None = None, **overrides
) -> Descriptor:
    """Build descriptor ``name`` from a YAML preset, sensor overrides and keyword overrides.

    Unknown parameter names raise :class:`~lidar_iris_eval.errors.LirisError`.
    """
    cls = descriptor_class(name)
    folder = method_folder(name)
    own = folder / "presets.yaml" if folder is not None else None
    preset_name, values = descriptor_preset_values(
        name, preset, sensor, path=own if own is not None and own.is_file() else None)
    values.update(overrides)
    params = make_params(cls.params_type, values, source=f"{name} preset {preset_name}")
    warn_ignored(name, params, overrides)
    return cls(params, preset=preset_name)


def warn_ignored(name: str, params, given) -> None:
    """Warn for each parameter set in ``given`` that ``params`` say their search ignores.

    A params class may define ``ignored() -> {name: reason}`` (e.g. LiDAR Iris'
    ``shift_window`` outside the ``phase`` search), so an option that changes
    nothing is never silent.
    """
    ignored = getattr(params, "ignored", None)
    if ignored is None:
        return
    for key, reason in ignored().items():
        if key in given:
            warn(f"{name}.{key}", f"ignored: {reason}")


__all__ = [
    "Descriptor",
    "available_descriptors",
    "descriptor_class",
    "get_descriptor",
    "method_folder",
    "method_module",
    "register_descriptor",
    "registered_class",
    "registered_names",
]
