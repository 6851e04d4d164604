"""OverlapTransformer: projection, NumPy vs PyTorch, torch-free checkpoint reader, CLI."""

from __future__ import annotations

import json
import math
import pickle
import struct
import zipfile

import numpy as np
import pytest
from conftest import KITTI, assert_one_line_error, run_cli

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.learned import weights_digest
from lidar_iris_eval.descriptors.overlap_transformer import checkpoint, network, projection
from lidar_iris_eval.descriptors.overlap_transformer.descriptor import SHIPPED_DIR, SIM_WEIGHTS
from lidar_iris_eval.errors import LirisError

SAMPLES = KITTI / "samples" / "00" / "velodyne"


def _kitti_scans() -> list[np.ndarray]:
    files = sorted(SAMPLES.glob("*.bin")) if SAMPLES.is_dir() else []
    return [np.fromfile(f, np.float32).reshape(-1, 4)[:, :3] for f in files]


# ------------------------------------------------------------------ projection


def _at(yaw_deg: float, pitch_deg: float, r: float) -> list[float]:
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    return [r * math.cos(p) * math.cos(y), r * math.cos(p) * math.sin(y), r * math.sin(p)]


def test_projection_puts_known_points_at_known_pixels():
    # 900 columns of 0.4 degrees, column 450 straight ahead, columns running clockwise
    # (y to the left is azimuth +90, so it lands 225 columns before forward);
    # 64 rows of 28/64 degrees from +3 (row 0) down to -25 (row 63).
    pts = np.array([
        _at(0.2, 2.9, 10.0),      # ahead, top row
        _at(90.2, 0.2, 12.0),     # left: column 450 - 225 - 1 (0.2 deg left of 90)
        _at(-90.2, -24.9, 7.3),   # right, bottom row
        _at(179.9, -11.0, 20.6),  # behind on the left: column 0
        _at(0.2, 2.9, 30.0),      # same pixel as the first, farther: the nearer wins
        _at(45.0, -5.0, 85.0),    # beyond 80 m: dropped
        _at(-45.2, 10.0, 4.5),    # above the field of view: clamped into row 0
    ], dtype=np.float32)
    img = projection.range_image(pts, depth_format="float")
    row_of = lambda pitch: int((3.0 - pitch) / (28.0 / 64))  # noqa: E731
    expected = {(row_of(2.9), 449): 10.0, (row_of(0.2), 224): 12.0, (63, 675): 7.3,
                (row_of(-11.0), 0): 20.6, (0, 450 + 112): 4.5}
    assert (row_of(2.9), row_of(0.2), row_of(-11.0)) == (0, 6, 32)
    for (r, c), depth in expected.items():
        assert img[r, c] == pytest.approx(depth, abs=1e-4), (r, c)
    assert (img >= 0).sum() == len(expected)
    assert np.all(img[img < 0] == -1.0)
    png = projection.range_image(pts, depth_format="png")
    assert png[0, 449] == 10.0 and png[row_of(0.2), 224] == 12.0 and png[63, 675] == 7.0
    assert png[row_of(-11.0), 0] == 21.0 and png[0, 562] == 4.0  # 4.5 rounds to even
    assert (png == 0).sum() == 64 * 900 - len(expected)


# ------------------------------------------------------------------ network vs torch


def _torch_net(weights):
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.overlap_transformer import torch_net

    torch.set_num_threads(1)
    net = torch_net.OverlapTransformerNet().eval()
    torch_net.load_numpy(net, weights)
    return torch, net


def test_numpy_forward_equals_torch_on_random_weights():
    w = network.random_weights(seed=5)
    torch, net = _torch_net(w)
    rng = np.random.default_rng(1)
    imgs = rng.uniform(-1, 60, (2, 1, 64, 900)).astype(np.float32)
    scans = _kitti_scans()
    if scans:
        imgs = np.concatenate([imgs] + [projection.range_image(s)[None, None] for s in scans])
    ours = network.forward(w, imgs)
    with torch.no_grad():
        theirs = net(torch.from_numpy(imgs)).numpy()
    assert np.max(np.abs(ours - theirs)) <= 1e-5
    assert np.allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-5)
    # identical top-1 rankings (every descriptor against the others)
    d_ours = ((ours[:, None] - ours[None]) ** 2).sum(-1) + np.diag(np.full(len(ours), np.inf))
    d_theirs = ((theirs[:, None] - theirs[None]) ** 2).sum(-1) + np.diag(
        np.full(len(ours), np.inf))
    assert (d_ours.argmin(1) == d_theirs.argmin(1)).all()


@pytest.mark.parametrize("weights", [SIM_WEIGHTS, "random-init"])
def test_descriptor_is_yaw_invariant(weights):
    """Column shifts are exact by construction; other turns move points between pixels."""
    desc = get_descriptor("overlap-transformer", preset="paper", weights=weights)
    scans = _kitti_scans()
    if not scans:
        rng = np.random.default_rng(3)
        scans = [rng.normal(0, 15, (20000, 3)).astype(np.float32) * [1, 1, 0.1]
                 for _ in range(2)]
    img = desc.range_image(scans[0])
    a = desc.compute_images(img[None])[0]
    rolled = desc.compute_images(np.roll(img, 311, axis=1)[None])[0]
    assert np.max(np.abs(a - rolled)) < 1e-5
    other = desc.compute(scans[1 if len(scans) > 1 else 0] * np.float32(0.7))
    far = desc.distance(a, other)[0]
    for yaw in (37.0, 180.0):
        t = math.radians(yaw)
        rot = np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0],
                        [0, 0, 1]], dtype=np.float32)
        turned = desc.compute(scans[0] @ rot.T)
        assert desc.distance(a, turned)[0] < 0.25 * far, yaw


# ------------------------------------------------------------------ checkpoint reader


def _op_str(text: str) -> bytes:
    raw = text.encode()
    return b"X" + struct.pack("<I", len(raw)) + raw


def _op_int(value: int) -> bytes:
    return b"J" + struct.pack("<i", value)


def _tuple(items: list[bytes]) -> bytes:
    return b"(" + b"".join(items) + b"t"


def hand_checkpoint(path, tensors: dict[str, np.ndarray], root: str = "archive",
                    extra_pickle: bytes = b"") -> None:
    """A torch.save-style zip written opcode by opcode, without torch."""
    body = b"\x80\x02}(" + _op_str("state_dict") + b"}("
    blobs = {}
    for n, (name, arr) in enumerate(tensors.items()):
        arr = np.ascontiguousarray(arr, dtype=np.float32)
        blobs[str(n)] = arr.tobytes()
        strides = [int(s // 4) for s in arr.strides]
        pid = _tuple([_op_str("storage"), b"ctorch\nFloatStorage\n", _op_str(str(n)),
                      _op_str("cpu"), _op_int(arr.size)]) + b"Q"
        call = (b"ctorch._utils\n_rebuild_tensor_v2\n"
                + _tuple([pid, _op_int(0), _tuple([_op_int(s) for s in arr.shape]),
                          _tuple([_op_int(s) for s in strides]), b"\x89",
                          b"ccollections\nOrderedDict\n)R"]) + b"R")
        body += _op_str(name) + call
    body += b"u" + extra_pickle + b"u."
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{root}/data.pkl", body)
        z.writestr(f"{root}/byteorder", "little")
        for key, raw in blobs.items():
            z.writestr(f"{root}/data/{key}", raw)


def test_hand_built_checkpoint_round_trips_without_torch(tmp_path):
    rng = np.random.default_rng(0)
    tensors = {"a.weight": rng.normal(size=(3, 4)).astype(np.float32),
               "module.b": rng.normal(size=(5,)).astype(np.float32),
               "c": rng.normal(size=(2, 3, 1, 1)).astype(np.float32)}
    path = tmp_path / "hand.pth.tar"
    hand_checkpoint(path, tensors)
    sd = checkpoint.state_dict(checkpoint.read_checkpoint(path))
    assert set(sd) == {"a.weight", "b", "c"}
    for key, arr in tensors.items():
        assert np.array_equal(sd[key.removeprefix("module.")], arr)


def test_hand_built_model_checkpoint_gives_the_same_descriptors(tmp_path):
    """A whole model written without torch reads back to the very same network."""
    weights = network.random_weights(seed=2)
    path = tmp_path / "model.pth.tar"
    hand_checkpoint(path, {f"module.{k}": v for k, v in weights.items()})
    from_file = get_descriptor("overlap-transformer", weights=str(path))
    generated = get_descriptor("overlap-transformer", weights="random-init", seed=2)
    img = np.random.default_rng(4).uniform(0, 50, (2, 64, 900)).astype(np.float32)
    assert np.array_equal(from_file.compute_images(img), generated.compute_images(img))
    assert from_file.cache_token() != generated.cache_token()  # file bytes vs arrays
    assert from_file.run_info()["weights"] == "model.pth.tar"


def test_torch_saved_checkpoint_round_trips(tmp_path):
    torch = pytest.importorskip("torch")
    from lidar_iris_eval.descriptors.overlap_transformer import torch_net

    torch.manual_seed(0)
    net = torch_net.OverlapTransformerNet()
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    net(torch.rand(1, 1, 64, 900)).sum().backward()
    opt.step()
    path = tmp_path / "pretrained_overlap_transformer.pth.tar"
    saved = {"epoch": 1, "state_dict": net.state_dict(), "optimizer": opt.state_dict(),
             "view": torch.arange(12.0).reshape(3, 4).t(), "half": torch.ones(2).bfloat16()}
    legacy = tmp_path / "legacy.pth.tar"  # the pre-1.6 format, still written on request
    torch.save(saved, legacy, _use_new_zipfile_serialization=False)
    torch.save(saved, path)
    for file in (path, legacy):
        obj = checkpoint.read_checkpoint(file)
        sd = checkpoint.state_dict(obj)
        for key, value in net.state_dict().items():
            assert np.array_equal(sd[key], value.numpy()), (file.name, key)
        assert obj["epoch"] == 1 and set(obj["optimizer"]["state"][0]) >= {"exp_avg", "step"}
        assert np.array_equal(obj["view"], np.arange(12.0).reshape(3, 4).T)
        assert np.array_equal(obj["half"], [1.0, 1.0])
    # through the method: same descriptors as the torch model
    desc = get_descriptor("overlap-transformer", preset="paper", weights=str(path))
    img = np.random.default_rng(2).uniform(0, 40, (1, 64, 900)).astype(np.float32)
    with torch.no_grad():
        ref = net.eval()(torch.from_numpy(img[:, None])).numpy()
    assert np.max(np.abs(desc.compute_images(img) - ref)) <= 1e-5
    assert desc.cache_token() != get_descriptor("overlap-transformer").cache_token()


class _Boom:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


def test_malicious_checkpoints_are_refused(tmp_path):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pth"
    payload = pickle.dumps(_Boom(marker), protocol=2)[2:-1]  # the object without PROTO/STOP
    hand_checkpoint(evil, {"a": np.zeros(2, np.float32)}, extra_pickle=_op_str("x") + payload)
    with pytest.raises(checkpoint.CheckpointError, match="posix.system|os.system|nt.system"):
        checkpoint.read_checkpoint(evil)
    bare = tmp_path / "evil-legacy.pth"  # a bare pickle is read as the legacy format
    bare.write_bytes(pickle.dumps(_Boom(marker), protocol=2))
    with pytest.raises(checkpoint.CheckpointError, match="refused"):
        checkpoint.read_checkpoint(bare)
    assert not marker.exists()
    try:
        import torch
    except ImportError:
        return
    evil2 = tmp_path / "evil2.pth.tar"
    torch.save({"state_dict": {"a": torch.zeros(2)}, "hook": _Boom(marker)}, evil2)
    with pytest.raises(checkpoint.CheckpointError, match="refused"):
        checkpoint.read_checkpoint(evil2)
    assert not marker.exists()


@pytest.mark.parametrize("kind", ["truncated", "not-zip", "legacy", "missing", "wrong-model",
                                  "frozen-sha"])
def test_bad_weights_are_one_error_line(tmp_path, capsys, kind):
    path = tmp_path / "w.pth.tar"
    if kind == "frozen-sha":  # liris' format, the frozen projection's digest not its seed's
        path = tmp_path / "w.npz"
        with np.load(SHIPPED_DIR / SIM_WEIGHTS) as z:
            arrays = {k: z[k] for k in z.files}
        arrays[network.FROZEN_SHA256] = np.array("0" * 64)
        np.savez(path, **arrays)
    elif kind == "truncated":
        hand_checkpoint(path, {"a": np.zeros(1000, np.float32)})
        path.write_bytes(path.read_bytes()[:-300])
    elif kind == "not-zip":
        path.write_text("hello")
    elif kind == "legacy":
        path.write_bytes(pickle.dumps({"a": 1}, protocol=2))
    elif kind == "wrong-model":
        hand_checkpoint(path, {"conv1.weight": np.zeros((16, 5, 5, 1), np.float32)})
    desc = get_descriptor("overlap-transformer", weights=str(path))
    with pytest.raises(LirisError, match="overlap-transformer.weights="):
        desc.cache_token()
    code, _, err = run_cli(["extract", tmp_path / "nowhere", "-d", "overlap-transformer",
                            "--param", f"overlap-transformer.weights={path}"], capsys)
    assert code == 2 and "Traceback" not in err
    if kind != "missing":  # (a missing sequence folder may be named first)
        seq = tmp_path / "seq"
        from lidar_iris_eval.simulate.pipeline import simulate_sequence

        simulate_sequence(seq, "tiny-mixed", frames=3, azimuth_steps=256)
        code, _, err = run_cli(["extract", seq, "-d", "overlap-transformer", "--param",
                                f"overlap-transformer.weights={path}", "--cache-dir",
                                tmp_path / "c", "-q"], capsys)
        assert_one_line_error(code, err, "overlap-transformer.weights=", str(path))


# ------------------------------------------------------------------ through liris eval


def test_eval_runs_both_protocols(tmp_path, capsys):
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    # the first tiny-mixed frames hold no revisit: a short exclusion window makes
    # neighbouring frames the loops (the run, not the score, is what this checks)
    seq = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=40, azimuth_steps=512)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "-d", "overlap-transformer", "--protocol", "1",
                            "--protocol", "2", "--exclude", "5", "--cache-dir", tmp_path / "cache",
                            "--param", "overlap-transformer.weights=random-init",
                            "--out", out, "-q"], capsys)
    assert code == 0, err
    rows = [r for r in json.loads((out / "metrics.json").read_text())["results"]
            if r["descriptor"] == "overlap-transformer"]
    assert {r["protocol"] for r in rows} == {1, 2}
    assert all(r["weights"] == "random-init" and r["weights_trained"] is False for r in rows)
    assert all(0.0 < r["f1_max"] <= 1.0 for r in rows)


@pytest.mark.parametrize("metric", ["l2sq", "l2", "cosine"])
def test_distances_agree_and_the_method_pickles(metric):
    desc = get_descriptor("overlap-transformer", metric=metric)
    rng = np.random.default_rng(9)
    d = rng.normal(size=(5, 256))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    clone = pickle.loads(pickle.dumps(desc))  # worker processes (bench, dask) get a copy
    full, _ = clone.pairwise(d, d)
    for i in range(5):
        assert np.array_equal(desc.distances(d[i], d)[0], full[i])
        assert desc.distance(d[i], d[3])[0] == full[i, 3]
    cos = d @ d.T
    expected = {"l2sq": 2 - 2 * cos, "l2": np.sqrt(np.maximum(2 - 2 * cos, 0)), "cosine": 1 - cos}
    assert np.allclose(full, expected[metric], atol=1e-7)  # sqrt of a rounding 0 ~ 3e-8


# ------------------------------------------------------------------ liris' trained weights

#: SHA-256 of the shipped ot_sim_weights.npz (a retrained file changes it: update the
#: model card's figures with it)
SIM_SHA256 = "c9494b8ba40ba48b20903ed06d375eb7b46cad538bbd9c62f0757e4a7d4fab25"
#: SHA-256 of network.frozen_projection(1) (16.8 M float32, regenerated at load)
FROZEN_SEED1_SHA256 = "80734f3b25f43f059a1799dabd92feed0ddc599b1f380024991d22cd2d7a8cc9"


def test_shipped_weights_are_the_default_and_pinned():
    import hashlib

    path = SHIPPED_DIR / SIM_WEIGHTS
    assert hashlib.sha256(path.read_bytes()).hexdigest() == SIM_SHA256
    for preset in ("paper", "reference", "float"):
        desc = get_descriptor("overlap-transformer", preset=preset)
        assert desc.params.weights == SIM_WEIGHTS, preset
    desc = get_descriptor("overlap-transformer")  # the dataclass default too
    info = desc.run_info()
    assert info["weights"] == SIM_WEIGHTS and info["weights_trained"] is True
    assert info["weights_sha256"] == SIM_SHA256[:16]  # the file's bytes: the cache key
    with np.load(path) as z:
        assert int(z[network.FROZEN_SEED]) == 1
        assert str(z[network.FROZEN_SHA256]) == FROZEN_SEED1_SHA256
        assert network.FROZEN_NAME not in z.files
        stored = sum(z[k].size for k in z.files if k in network.shapes())
    assert stored == 1_678_480  # every weight but the frozen 65,536 x 256 projection
    assert path.stat().st_size < 8_000_000


@pytest.mark.parametrize("method", ["overlap-transformer", "bevplace"])
def test_a_file_named_like_the_shipped_weights_in_the_working_directory_does_not_shadow_it(
        method, tmp_path, monkeypatch):
    shipped = get_descriptor(method)
    name = shipped.params.weights
    expected = shipped.shipped_dir / name
    monkeypatch.chdir(tmp_path)
    (tmp_path / name).write_bytes(b"not weights")  # would be refused if it were read
    desc = get_descriptor(method)
    import hashlib
    assert desc.cache_token() == hashlib.sha256(expected.read_bytes()).hexdigest()[:16]
    # a path (not a bare name) is the user's file: read, and refused in one line
    with pytest.raises(LirisError, match="weights"):
        get_descriptor(method, weights=str(tmp_path / name)).cache_token()


def test_random_init_is_still_reachable_by_name():
    desc = get_descriptor("overlap-transformer", preset="paper", weights="random-init")
    info = desc.run_info()
    assert info["weights"] == "random-init" and info["weights_trained"] is False
    expected = weights_digest(network.random_weights(0), network.shapes())
    assert info["weights_sha256"] == expected[:16]
    assert info["weights_sha256"] != get_descriptor("overlap-transformer").cache_token()


def test_frozen_projection_is_regenerated_exactly():
    matrix = network.frozen_projection(1)
    assert matrix.shape == (65536, 256) and matrix.dtype == np.float32
    assert network.array_sha256(matrix) == FROZEN_SEED1_SHA256
    assert np.array_equal(matrix, network.frozen_projection(1))
    assert not np.array_equal(matrix[:4], network.frozen_projection(2)[:4])
    assert abs(float(matrix.std()) - 1 / 32) < 1e-4  # the authors' randn / sqrt(1024) scale
    loaded = get_descriptor("overlap-transformer").weights()
    assert np.array_equal(loaded[network.FROZEN_NAME], matrix)
    # a file holding both, or a seed without its digest, is refused
    small = {network.FROZEN_SEED: np.array(1), network.FROZEN_SHA256: np.array("0" * 64)}
    with pytest.raises(ValueError, match="SHA-256"):
        network.expand_frozen(small)
    with pytest.raises(ValueError, match="both"):
        network.expand_frozen({**small, network.FROZEN_NAME: matrix})
    with pytest.raises(ValueError, match="no "):
        network.expand_frozen({network.FROZEN_SEED: np.array(1)})
    plain = {"a": np.zeros(2)}
    assert network.expand_frozen(plain) is plain  # the authors' files pass unchanged


#: descriptors of the first real KITTI 00 sample scan with the shipped weights (``paper``)
KITTI_GOLDEN = {"first8": [-0.002152, -0.145795, -0.001377, 0.009298, 0.008782, -0.07822,
                           0.046752, 0.021891],
                "cos01": 0.989439}


def test_shipped_weights_golden_descriptors_on_kitti():
    scans = _kitti_scans()
    if not scans:
        pytest.skip("no KITTI samples in ../shared")
    desc = get_descriptor("overlap-transformer", preset="paper")
    got = np.stack([desc.compute(s) for s in scans[:2]])
    assert np.allclose(got[0, :8], KITTI_GOLDEN["first8"], atol=2e-5)
    assert abs(float(got[0] @ got[1]) - KITTI_GOLDEN["cos01"]) < 2e-5
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


def test_shipped_weights_numpy_equals_torch():
    w = get_descriptor("overlap-transformer").weights()
    torch, net = _torch_net(w)
    imgs = np.random.default_rng(6).uniform(0, 60, (2, 1, 64, 900)).astype(np.float32)
    scans = _kitti_scans()
    if scans:
        imgs = np.concatenate([imgs] + [projection.range_image(s)[None, None] for s in scans])
    with torch.no_grad():
        theirs = net(torch.from_numpy(imgs)).numpy()
    assert np.max(np.abs(network.forward(w, imgs) - theirs)) <= 1e-5


def _train_script():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "train_overlap_transformer.py"
    spec = importlib.util.spec_from_file_location("train_overlap_transformer", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_training_resumes_where_it_stopped(tmp_path):
    """Two steps, a stop, two more steps == four steps at once (same weights, same log)."""
    pytest.importorskip("torch")
    script = _train_script()
    rng = np.random.default_rng(0)
    overlap = np.where(np.abs(np.subtract.outer(np.arange(6), np.arange(6))) <= 1, 0.9, 0.0)
    images = rng.integers(0, 40, (6, 64, 900)).astype(np.float32)
    for run in ("once", "twice"):
        (tmp_path / run).mkdir()
        np.savez(tmp_path / run / "world7001-s4.npz", images=images, overlap=overlap)
    common = ["--seeds", "7001", "--positives", "1", "--negatives", "2", "--warmup", "2",
              "--save-every", "1", "--snapshot-every", "1000"]
    script.main(["--work", str(tmp_path / "once"), "--steps", "4", *common])
    script.main(["--work", str(tmp_path / "twice"), "--steps", "2", *common])
    script.main(["--work", str(tmp_path / "twice"), "--steps", "4", *common])
    once, twice = (np.load(tmp_path / r / "ot_sim_weights.npz") for r in ("once", "twice"))
    assert set(once.files) == set(twice.files)
    for name in once.files:
        if name != "liris.info":
            assert np.array_equal(once[name], twice[name]), name
    assert json.loads(str(twice["liris.info"]))["step"] == 4
    logs = [(tmp_path / r / "losses.tsv").read_text().splitlines() for r in ("once", "twice")]
    assert [line.split("\t")[:2] for line in logs[0]] == [line.split("\t")[:2] for line in logs[1]]
    # the written file loads into the method and equals the trained torch model's forward
    desc = get_descriptor("overlap-transformer", weights=str(tmp_path / "once" /
                                                             "ot_sim_weights.npz"))
    assert desc.run_info()["weights_trained"] is True
    assert desc.compute_images(images[:1]).shape == (1, 256)
