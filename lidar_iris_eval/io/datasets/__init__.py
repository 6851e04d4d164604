"""The dataset registry: one small reader module per dataset, detected from the folder.

Each :class:`DatasetSpec` says what layout its reader expects, which frame the
dataset's poses are in, what liris converts, and which ``--sensor`` preset
fits its LiDAR; it sits at the end of its reader module (``SPECS``), beside
the reader and the detection cue it names, and :data:`DATASETS` lists the
modules' specs in the order of :data:`READERS`. :func:`find_dataset` picks
the spec for a path: the one named by ``dataset=`` (``--dataset``), else the
one specific dataset whose layout matches, else the generic readers (GOSMatch
objects, KITTI layout, ROS bag, folder of scans) in that order. Two specific
matches, or none at all, are one error line naming what was looked for.

Reader modules import only NumPy, SciPy and liris' own io; optional
dependencies (rosbags) are imported when a scan is read.
"""

from __future__ import annotations

from pathlib import Path

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.datasets import (
    apollo,
    boreas,
    generic,
    helipr,
    kitti360,
    mulran,
    nclt,
    newer_college,
    nuscenes,
    oxford,
    wildplaces,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec

#: the reader modules, in the order of the registry: specific datasets, then the generic
#: formats (detected only when no specific dataset matches, in this order)
READERS = (kitti360, mulran, nclt, oxford, helipr, wildplaces, newer_college, nuscenes, boreas,
           apollo, generic)

DATASETS: dict[str, DatasetSpec] = {s.name: s for reader in READERS for s in reader.SPECS}


def _plugin_spec(plugin) -> DatasetSpec:
    """An external reader's spec, named by its entry; one LirisError if it is broken."""
    import dataclasses

    spec = plugin.load()
    if not isinstance(spec, DatasetSpec):
        raise LirisError(plugin.label, "is not a lidar_iris_eval.io.datasets.DatasetSpec")
    return dataclasses.replace(spec, name=plugin.name)


def all_datasets(strict: bool = True) -> dict[str, DatasetSpec]:
    """:data:`DATASETS` and the external readers (entry points ``liris.datasets``,
    ``LIRIS_DATASETS``; :mod:`lidar_iris_eval.plugins`), specific readers first and
    the generic ones last, so an external layout is detected before a folder of scans.

    ``strict=False`` (``liris datasets``) leaves out, with a warning, a reader
    that cannot be loaded; otherwise it is one error naming it.
    """
    from lidar_iris_eval.errors import warn
    from lidar_iris_eval.plugins import plugins

    external = {}
    try:
        found = plugins("datasets", reserved=set(DATASETS))
    except LirisError as err:
        if strict:
            raise
        warn(err.source, err.problem)
        found = []
    for plugin in found:
        try:
            external[plugin.name] = _plugin_spec(plugin)
        except LirisError as err:
            if strict:
                raise
            warn(err.source, f"{err.problem}; not listed")
    if not external:
        return dict(DATASETS)
    specific = {n: s for n, s in DATASETS.items() if not s.generic}
    generic = {n: s for n, s in DATASETS.items() if s.generic}
    return {**specific, **{n: s for n, s in external.items() if not s.generic},
            **{n: s for n, s in external.items() if s.generic}, **generic}


def dataset_names() -> list[str]:
    """Every registered name, specific datasets first."""
    return list(all_datasets())


def get_dataset(name: str) -> DatasetSpec:
    """The spec registered as ``name`` (one error listing the names otherwise)."""
    datasets = all_datasets()
    spec = datasets.get(str(name).lower(), datasets.get(str(name)))
    if spec is None:
        raise LirisError(f"--dataset {name}",
                         f"unknown dataset; choose from {', '.join(datasets)} (liris datasets)")
    return spec


def find_dataset(path: Path, dataset: str | None = None) -> DatasetSpec:
    """The spec to open ``path`` with: forced by ``dataset``, else detected."""
    path = Path(path)
    if dataset is not None:
        return get_dataset(dataset)
    datasets = all_datasets()
    specific = [s for s in datasets.values() if not s.generic and s.detect(path)]
    if len(specific) > 1:
        names = " and ".join(f"{s.name} ({s.looks_for})" for s in specific)
        raise LirisError(path, f"ambiguous dataset layout: {names} both match; "
                               "choose one with --dataset NAME")
    if specific:
        return specific[0]
    for spec in datasets.values():
        if spec.generic and spec.detect(path):
            return spec
    cues = "; ".join(f"{s.name}: {s.looks_for}" for s in datasets.values())
    raise LirisError(path, f"not a known dataset layout or folder of scans; looked for {cues} "
                           "(see liris datasets, or force one with --dataset NAME)")


__all__ = ["DATASETS", "READERS", "DatasetSpec", "all_datasets", "dataset_names", "find_dataset",
           "get_dataset"]
