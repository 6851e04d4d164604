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
    # optional extra "mapclosures"; without it -d mapclosures is one error line
    "mapclosures": "lidar_iris_eval.descriptors.mapclosures:MapClosures",
}


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
    names = []
    for name, target in _REGISTRY.items():
        module_name = target.split(":")[0]
        if importlib.util.find_spec(module_name) is not None:
            names.append(name)
    return names


def registered_names() -> list[str]:
    """Every registered name, in registry order (the order figures list methods in)."""
    return list(_REGISTRY)


def registered_class(name: str) -> type[Descriptor] | None:
    """The class registered under ``name``, or None when unknown or not importable."""
    if name not in _REGISTRY:
        return None
    module_name, class_name = _REGISTRY[name].split(":")
    try:
        return getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError):
        return None


def method_module(name: str, part: str) -> str | None:
    """``<method package>.<part>`` (e.g. ``reference_loop``) when that module exists.

    A method's folder holds its own reference loop and presets, found from
    its registry line alone.
    """
    if name not in _REGISTRY:
        return None
    package = _REGISTRY[name].split(":")[0]
    target = f"{package}.{part}"
    try:
        return target if importlib.util.find_spec(target) is not None else None
    except ModuleNotFoundError:
        return None


def method_folder(name: str):
    """The folder of the package registered under ``name`` (None if it is a module)."""
    from pathlib import Path

    if name not in _REGISTRY:
        return None
    spec = importlib.util.find_spec(_REGISTRY[name].split(":")[0])
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def descriptor_class(name: str) -> type[Descriptor]:
    """The class registered under ``name``; an unknown name is a LirisError."""
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
