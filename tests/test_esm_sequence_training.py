"""ESM training on a plain sequence (issue 34 item 3): a tiny simulated sequence written in
KITTI layout, stripped of every simulator tag (labels, object ids, manifest), opened as any
scan folder with poses; segments from the ``local-maps`` front end, positives by world
centroids, a few training steps end to end, the checkpoint and the resume.

The training half needs torch (the ``train`` extra; CI's ``.venv-torch``); it is skipped
without it."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors.esm.dataset import SegmentSet, true_pairs

ROOT = Path(__file__).resolve().parents[1]
WINDOW = 30
INIT = ROOT / "lidar_iris_eval/descriptors/esm/esm_localmap_weights.npz"


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def plain_sequence(tmp_path_factory):
    """100 frames of ``tiny-mixed`` at 360 azimuth steps, as a bare KITTI folder."""
    from lidar_iris_eval.simulate import simulate_sequence

    seq = simulate_sequence(tmp_path_factory.mktemp("plain") / "seq", preset="tiny-mixed",
                            frames=100, azimuth_steps=360, moving_cars=False)
    for extra in ("labels", "object_ids"):
        shutil.rmtree(seq / extra, ignore_errors=True)
    (seq / "manifest.json").unlink(missing_ok=True)
    assert sorted(p.name for p in seq.iterdir()) == ["calib.txt", "poses.txt", "times.txt",
                                                      "velodyne"]
    return seq


@pytest.fixture(scope="module")
def segments(plain_sequence, tmp_path_factory):
    out = tmp_path_factory.mktemp("segs") / "seq.npz"
    _script("esm_segments").main([str(plain_sequence), "-o", str(out), "--exclude",
                                  str(WINDOW)])
    return out


def test_segments_of_a_plain_sequence_and_their_positives(segments):
    d = SegmentSet.load(segments)
    assert len(d) > 50 and set(np.unique(d.frame) % 10) == {0}
    sizes = np.diff(d.offsets)
    assert sizes.min() >= 1 and sizes.max() <= 1024
    assert np.all(d.object_id > 0) and np.all(d.coarse == 0)
    pairs = true_pairs(d, 1.0, min_frame_gap=WINDOW)
    # brute force, independent of the tracks: every two views within 1 m, >= W frames apart
    dist = np.linalg.norm(d.world[:, None] - d.world[None, :], axis=2)
    gap = np.abs(d.frame[:, None] - d.frame[None, :])
    expect = {(int(a), int(b)) for a, b in zip(*np.nonzero((dist <= 1.0) & (gap >= WINDOW)),
                                               strict=True) if a < b}
    assert expect and {(int(a), int(b)) for a, b in pairs} == expect


def test_segments_script_bad_input_is_one_error_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as err:
        _script("esm_segments").main([str(tmp_path / "none"), "-o", str(tmp_path / "x.npz")])
    assert err.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("liris: error:")


def test_segments_script_refuses_to_replace_its_output(segments, plain_sequence, capsys):
    """An existing --out is replaced only with --overwrite, checked before any work."""
    before = segments.read_bytes()
    with pytest.raises(SystemExit) as err:
        _script("esm_segments").main([str(plain_sequence), "-o", str(segments)])
    assert err.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "--overwrite" in lines[0] and str(segments) in lines[0]
    assert segments.read_bytes() == before


def _train(segments, work, out, steps, *extra):
    train_esm = _script("train_esm")
    train_esm.main(["--source", "segments", "--train-segments", str(segments),
                    "--valid-segments", str(segments), "--work", str(work), "--out", str(out),
                    "--threads", "1", "--batch", "8", "--steps", str(steps),
                    "--quality-steps", "3", "--checkpoint-steps", "2", "--seed", "5",
                    "--init", str(INIT),
                    *extra])


def test_training_on_a_plain_sequence_checkpoints_and_resumes(segments, tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.esm import network
    from lidar_iris_eval.descriptors.esm.torch_net import ESMNet
    from lidar_iris_eval.errors import LirisError

    work, out = tmp_path / "work", tmp_path / "w.npz"
    _train(segments, work, out, 4)
    state = torch.load(work / "state.pt", weights_only=False)
    hist = np.array([h[0] for h in state["progress"]["hist"]])
    assert state["progress"]["step"] == 4 and len(hist) == 4
    assert np.all(np.isfinite(hist)) and np.all(hist >= 0)
    # the checkpoint round-trips: the state's network exports the weights file's layers
    # (all but the quality branch, fitted after training)
    _, arch = network.load_weights(out)
    net = ESMNet(arch)
    net.load_state_dict(state["net"])
    exported = net.export()
    with np.load(out) as z, np.load(INIT) as z0:
        body = [k for k in z.files if k != "arch" and not k.startswith("q.")]
        assert body and all(np.allclose(exported[k], z[k]) for k in body)
        # and the four steps moved the network away from its starting weights
        assert any(not np.allclose(z[k], z0[k]) for k in body)
    # a finished model is never replaced silently
    capsys.readouterr()
    with pytest.raises(LirisError, match="--overwrite"):
        _train(segments, work, out, 6)
    # a resume with another starting network is refused, not mixed in
    with np.load(INIT) as z:
        other = {k: z[k] for k in z.files}
    arch = json.loads(str(other["arch"]))
    other["arch"] = np.array(json.dumps({**arch, "norm_scale": arch["norm_scale"] + 0.3}))
    np.savez(tmp_path / "init2.npz", **other)
    with pytest.raises(LirisError, match="same options"):
        _train(segments, work, tmp_path / "other.npz", 6, "--init", str(tmp_path / "init2.npz"))
    # a larger budget with the same work folder continues from the saved step
    _train(segments, work, out, 6, "--overwrite")
    assert "resumed at step 4" in capsys.readouterr().out
    again = torch.load(work / "state.pt", weights_only=False)
    assert again["progress"]["step"] == 6
    assert [h[0] for h in again["progress"]["hist"][:4]] == hist.tolist()
    assert np.isfinite(again["progress"]["hist"][-1][0])


def test_state_is_written_every_n_steps(segments, tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.esm import training

    saved = []
    real = training._save

    def spy(obj, path):
        if path.name == "state.pt":
            saved.append(obj["progress"]["step"])
        real(obj, path)

    monkeypatch.setattr(training, "_save", spy)
    _train(segments, tmp_path / "work", tmp_path / "w.npz", 5, "--stages", "train")
    # steps 2 and 4 (--checkpoint-steps 2), then the final state at step 5
    assert saved == [2, 4, 5]
