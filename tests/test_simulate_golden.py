"""Every simulation preset's output stays byte-identical (golden digests of short runs).

The digests were taken before multi-session simulation was added; the version
string in ``manifest.json`` is left out so a release does not change them.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from lidar_iris_eval.simulate import simulate_sequence

GOLDEN = {
    "tiny-mixed": (24, "057ecd9e91f4797d9c6ea92a5607a776ac1485387f75b18ff2555b43417da1de"),
    "tiny-same": (12, "bbec1f3ef9aa4486b30f1013d5cabe72facfd57a14a354ce3db5bb67d2a265fd"),
    "tiny-reverse": (12, "34358c8b2fdf7c2023b2f8e7e72d425b4d02ba4521c0350361eaa129a441b5b2"),
    "small-mixed": (8, "90bdc2551a5d44d300a78e806862ded56a7055fb1e4ff44e0bc75ca23a89ca97"),
    "kitti-scale": (4, "21ed65d0fb8c179d3b78e1f8afd8665ff26ed198abc6ce846188815e6eb8e1af"),
}


def tree_digest(folder: Path) -> str:
    """sha256 over the relative names and bytes of every file (manifest without version)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = path.read_bytes()
        if path.name == "manifest.json":
            manifest = json.loads(data)
            manifest.pop("version", None)
            data = json.dumps(manifest, sort_keys=True).encode()
        digest.update(str(path.relative_to(folder)).encode())
        digest.update(data)
    return digest.hexdigest()


@pytest.mark.parametrize("preset", sorted(GOLDEN))
def test_preset_output_is_unchanged(tmp_path, preset):
    frames, expected = GOLDEN[preset]
    out = simulate_sequence(tmp_path / "seq", preset, frames=frames)
    assert tree_digest(out) == expected
