"""descriptors.base.reads_local_maps: the one test of "this method reads local maps".

The extraction pipeline, ``Descriptor.run_info`` and ``liris eval --odometry FILE``
all ask it; here its answer is checked against what each method declares.
"""

from __future__ import annotations

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.base import reads_local_maps


def test_esm_reads_local_maps_only_in_its_local_map_mode():
    assert reads_local_maps(get_descriptor("esm", source="local-map"))
    assert not reads_local_maps(get_descriptor("esm", source="scan"))


def test_a_scan_method_reads_none():
    assert not reads_local_maps(get_descriptor("m2dp"))


def test_an_object_that_declares_no_inputs_reads_none():
    class Plain:
        name = "plain"

    assert not reads_local_maps(Plain())
