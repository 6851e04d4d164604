"""ESM's segment-retrieval metrics on hand-made embeddings, and true pairs from object ids."""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.descriptors.esm.dataset import SegmentSet, true_pairs
from lidar_iris_eval.descriptors.esm.metrics import quality_examples, retrieval_metrics, roc_auc


def test_auc_by_hand():
    assert roc_auc(np.array([0.0, 1.0]), np.array([2.0, 3.0])) == 1.0
    assert roc_auc(np.array([2.0, 3.0]), np.array([0.0, 1.0])) == 0.0
    # one tie out of four comparisons counts half: (3 + 0.5) / 4
    assert roc_auc(np.array([0.0, 2.0]), np.array([2.0, 3.0])) == 0.875


def test_accuracy_at_k_by_hand():
    # segments 0..3 in frames 0, 0, 20, 20; 0<->2 are a true pair; 1 and 3 unrelated
    emb = np.array([[0.0, 0.0], [5.0, 0.0], [0.1, 0.0], [0.2, 0.0]])
    frame = np.array([0, 0, 20, 20])
    m = retrieval_metrics(emb, frame, np.array([[0, 2]]), min_frame_gap=10, ks=(1, 2))
    # query 0: allowed 2 (d=0.01) and 3 (0.04) -> partner first; query 2: allowed 0 (0.01), 1
    assert m["queries"] == 2 and m["accuracy_at_k"] == {1: 1.0, 2: 1.0}
    # pairs across frames: (0,2) positive; (0,3), (1,2), (1,3) negatives, all farther
    assert m["positives"] == 1 and m["negatives"] == 3 and m["auc"] == 1.0
    # swap the places of 2 and 3: query 0 now finds 3 (0.1 away) before its partner 2
    # (0.2 away), a miss at k=1; query 2's nearest allowed is still 0, a hit
    far = retrieval_metrics(emb[[0, 1, 3, 2]], frame, np.array([[0, 2]]), ks=(1,))
    assert far["accuracy_at_k"][1] == 0.5 and np.isclose(far["auc"], 2 / 3)  # (0,3) is closer


def test_true_pairs_need_same_object_place_and_frame_gap():
    world = np.array([[0, 0, 0], [0.5, 0, 0], [0.4, 0, 0], [9, 0, 0], [0.2, 0, 0]], float)
    data = SegmentSet(
        points=np.zeros((5, 3), np.float32), offsets=np.arange(6),
        object_id=np.array([7, 7, 7, 7, 8]), coarse=np.ones(5, np.int8),
        frame=np.array([0, 30, 3, 60, 40]), world=world, purity=np.ones(5),
        world_id=np.zeros(5, np.int64),
    )
    # 0-1: same object, 0.5 m, 30 frames -> pair; 0-2: only 3 frames apart; 0-3: 9 m apart;
    # 1-2: 27 frames, 0.1 m -> pair; 4 is another object
    assert true_pairs(data).tolist() == [[0, 1], [1, 2]]


def test_same_object_non_pairs_can_be_ignored():
    # 0<->2 true pair; 3 is the same object as 0 but another piece (not a pair), nearer to
    # 0 than its partner; 1 is an unrelated object
    emb = np.array([[0.0, 0.0], [5.0, 0.0], [0.2, 0.0], [0.1, 0.0]])
    frame = np.array([0, 0, 20, 20])
    pairs = np.array([[0, 2]])
    strict = retrieval_metrics(emb, frame, pairs, ks=(1,))
    # strict: (0,3) is a negative nearer than the positive -> AUC 2/3; query 0 misses at k=1
    assert np.isclose(strict["auc"], 2 / 3) and strict["accuracy_at_k"][1] == 0.5
    key = np.array([7, 8, 7, 7])
    loose = retrieval_metrics(emb, frame, pairs, ks=(1,), ignore=key)
    # (0,3) no longer counts ((2,3) share a frame): the negatives left, (1,2) and (1,3), are
    # both farther than the positive, and both queries hit at k=1
    assert loose["negatives"] == 2 and loose["auc"] == 1.0
    assert loose["accuracy_at_k"][1] == 1.0


def test_quality_examples_leave_out_segments_never_seen_again():
    # six segments on a line of embeddings; true pairs (0, 3) and (1, 4); 2 and 5 have none
    emb = np.array([[0.0, 0], [5, 0], [12, 0], [0.1, 0], [7.5, 0], [20, 0]])
    frame = np.array([0, 0, 0, 40, 40, 40])
    world = np.zeros(6, np.int64)
    pairs = np.array([[0, 3], [1, 4]])
    rows, labels = quality_examples(emb, frame, world, pairs, k=1, gap=30)
    assert rows.tolist() == [0, 1, 3, 4]  # 2 and 5 can never be labelled 1: not examples
    # nearest at >= 30 frames: 0 -> 3 (true), 1 -> 4 (2.5 against 3.0 to 3: true),
    # 3 -> 0 (true), 4 -> 1 (2.5; 2 is 4.5 and 0 is 7.5 away; 3 and 5 share its frame)
    assert labels.tolist() == [1, 1, 1, 1]
    rows, labels = quality_examples(emb, frame, world, np.array([[0, 4], [1, 3]]), k=1, gap=30)
    assert rows.tolist() == [0, 1, 3, 4] and labels.tolist() == [0, 0, 0, 0]
    # another world's segment is never a candidate, whatever its distance
    rows, labels = quality_examples(emb, frame, np.array([0, 0, 0, 1, 0, 0]), pairs, k=1, gap=30)
    assert rows.tolist() == [0, 1, 3, 4] and labels.tolist() == [0, 1, 0, 1]
