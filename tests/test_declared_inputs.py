"""Issue 41 item 7: extraction reads only the inputs the chosen methods declare.

A points-only method on a labelled sequence never opens a label file (its
descriptors equal those of the same scans without labels); a method that
declares ``labels`` reads each label file once; both together read each scan's
files once.
"""

from __future__ import annotations

import shutil
from collections import Counter

import numpy as np
import pytest
from test_scan_inputs import ClassCentroids, labelled_sequence

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.extract import extract, extract_many
from lidar_iris_eval.io import open_sequence, scans


@pytest.fixture
def opened(monkeypatch):
    """Count label files read (by stem)."""
    reads: Counter = Counter()
    real = scans.read_labels

    def counting(path):
        reads[path.stem] += 1
        return real(path)

    monkeypatch.setattr(scans, "read_labels", counting)
    return reads


def test_points_method_reads_no_label_file(tmp_path, opened):
    root = labelled_sequence(tmp_path / "s", n=6)
    bare = shutil.copytree(root, tmp_path / "bare")
    shutil.rmtree(bare / "labels")
    m2dp = get_descriptor("m2dp")
    db = extract(open_sequence(root), m2dp)
    assert sum(opened.values()) == 0
    assert np.array_equal(db.descriptors, extract(open_sequence(bare), m2dp).descriptors)


def test_labels_method_reads_each_label_file_once_also_beside_a_points_method(tmp_path, opened):
    root = labelled_sequence(tmp_path / "s", n=6)
    seq = open_sequence(root)
    extract(seq, ClassCentroids())
    assert sorted(opened.values()) == [1] * 6
    opened.clear()
    both = extract_many(seq, [get_descriptor("m2dp"), ClassCentroids()])
    assert sorted(opened.values()) == [1] * 6
    alone = extract(seq, get_descriptor("m2dp"))
    assert np.array_equal(both[0].descriptors, alone.descriptors)


def test_a_broken_label_file_does_not_stop_a_points_method(tmp_path):
    """Labels are not an input of M2DP: a label file of the wrong length is no error for it
    (it still is for a method that reads labels)."""
    from lidar_iris_eval.errors import LirisError

    root = labelled_sequence(tmp_path / "s", n=4)
    np.zeros(3, "<u4").tofile(root / "labels" / "000002.label")
    extract(open_sequence(root), get_descriptor("m2dp"))
    with pytest.raises(LirisError, match=r"000002\.label: 3 labels"):
        extract(open_sequence(root), ClassCentroids())
