"""Issue 39 item 5: each dataset's spec sits in its reader module, not in a table of the package.

The registry (``lidar_iris_eval.io.datasets``) only collects the reader
modules' ``SPECS``; ``liris datasets`` lists them exactly as the table did.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
from pathlib import Path

from lidar_iris_eval.io import datasets as registry
from lidar_iris_eval.io.datasets import DATASETS, DatasetSpec

#: the registry's order before the move (specific datasets, then the generic formats)
NAMES = ["kitti360", "mulran", "nclt", "nclt-hits", "oxford", "oxford-raw", "helipr",
         "wild-places", "wild-places-v3", "newer-college", "nuscenes", "boreas", "apollo",
         "objects", "kitti", "rosbag", "folder"]
#: sha256 of `liris datasets` (and `--json`) printed by the table in io/datasets/__init__.py
#: at 2de532e, before the specs moved; a change of a spec's text changes it on purpose
LISTING_SHA256 = "07130d7ddd8313534940aa579ad5cb66da2a600ccc3b72325897dd78c490a8ae"
JSON_SHA256 = "b557fcb3659b8469f0ae95811697f81baa69e2b37abd99ab5b0cde164e36b5b0"


def test_each_spec_sits_in_its_reader_module():
    assert list(DATASETS) == NAMES
    for name, spec in DATASETS.items():
        module_name = f"lidar_iris_eval.io.datasets.{spec.opener.split(':')[0]}"
        module = importlib.import_module(module_name)
        assert spec in module.SPECS, name
        assert spec.detect.__module__ == module_name, name  # its cue beside it
        assert callable(getattr(module, spec.opener.split(":")[1])), name
    source = inspect.getsource(registry)
    assert "DatasetSpec(" not in source  # the package holds no table any more
    assert registry.DatasetSpec is DatasetSpec  # external readers still import it from here


def test_every_reader_module_is_listed():
    folder = Path(registry.__file__).parent
    with_specs = sorted(p.stem for p in folder.glob("*.py")
                        if "\nSPECS" in p.read_text(encoding="utf-8"))
    assert sorted(m.__name__.rsplit(".", 1)[1] for m in registry.READERS) == with_specs


def test_listing_is_unchanged_by_the_move(capsys):
    from conftest import run_cli

    for args, digest in ((["datasets"], LISTING_SHA256), (["datasets", "--json"], JSON_SHA256)):
        code, out, err = run_cli(args, capsys)
        assert code == 0, err
        assert hashlib.sha256(out.encode()).hexdigest() == digest, args
