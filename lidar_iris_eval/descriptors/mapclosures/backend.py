"""The optional ``map-closures`` package (PRBonn, MIT), imported only when used.

MapClosures pins ``numpy<2.3``, so it is an optional extra of liris
(``pip install -e ".[mapclosures]"``, docs/mapclosures.md); the base install
never pulls it. Every entry point of this method calls :func:`require` first,
so a missing package is one error line naming the extra, not an ImportError.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

from lidar_iris_eval.errors import LirisError

#: the exact release the method is written against (its API and C++ constants)
PINNED_VERSION = "2.2.0"
EXTRA_HINT = ("needs the optional extra 'mapclosures' (pip install -e \".[mapclosures]\"; "
              "it pins numpy<2.3, see docs/mapclosures.md)")


def available() -> bool:
    """True when the ``map_closures`` package can be imported."""
    return importlib.util.find_spec("map_closures") is not None


def installed_version() -> str | None:
    """The installed ``map-closures`` version, or None."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("map-closures")
    except PackageNotFoundError:
        return None


def require(source: str = "mapclosures") -> None:
    """A LirisError naming the extra when ``map_closures`` is missing."""
    if not available():
        raise LirisError(source, EXTRA_HINT)


def module() -> ModuleType:
    """The ``map_closures`` package (after :func:`require`)."""
    require()
    return importlib.import_module("map_closures")


def closer(config: dict):
    """A fresh ``map_closures.MapClosures`` with ``config`` (``MapClosuresConfig`` fields)."""
    require()
    api = importlib.import_module("map_closures.map_closures")
    cfg = importlib.import_module("map_closures.config")
    return api.MapClosures(cfg.MapClosuresConfig(**config))


def pybind() -> ModuleType:
    """The C++ bindings: ``_MapClosures``, ``_VoxelMap``, ``_Vector3dVector``."""
    require()
    return importlib.import_module("map_closures.pybind.map_closures_pybind")
