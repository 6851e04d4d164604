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
    preset_name, values = descriptor_preset_values(name, preset, sensor)
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
    "register_descriptor",
]
