"""ROS 1 / ROS 2 bags written with rosbags' own writer, read back by liris.

The reference is the same sequence in KITTI layout: a bag holding its clouds
plus odometry at 50 Hz (five times the scan rate) must give the same points,
the same LiDAR poses and the same ground truth.
"""

from __future__ import annotations

import json
import pickle
import sys
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation, Slerp

from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.rosbag import decode_pointcloud2, open_rosbag

needs_rosbags = pytest.mark.skipif(find_spec("rosbags") is None, reason="rosbags not installed")

T0_NS = 1_600_000_000_000_000_000
SCAN_PERIOD_NS = 100_000_000  # 10 Hz
ODOM_PERIOD_NS = 20_000_000  # 50 Hz
CLOUD_LATENCY_NS = 30_000_000  # recording time lags the header stamp
TR = np.array([[0.0, -1.0, 0.0, 0.02], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27],
               [0.0, 0.0, 0.0, 1.0]])
# x, y, z, (4 pad bytes), intensity, ring, (2 pad), time: 32-byte points like PCL's
LAYOUT = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("ring", 20, 4),
          ("time", 24, 7)]
FORMATS = ["rosbag1", "mcap", "sqlite3"]


# ---------------------------------------------------------------- data
def loop_poses(n: int, laps: float = 1.3, radius: float = 8.0) -> np.ndarray:
    """LiDAR poses driving ``laps`` times round a circle, facing along it."""
    theta = 2 * np.pi * laps * np.arange(n) / n
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", (theta + np.pi / 2)[:, None]).as_matrix()
    poses[:, 0, 3] = radius * np.cos(theta)
    poses[:, 1, 3] = radius * np.sin(theta)
    poses[:, 2, 3] = 0.05 * np.sin(3 * theta)
    return poses


def make_clouds(n: int, points: int = 150, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.normal(scale=15, size=(points, 4)).astype(np.float32) for _ in range(n)]


def write_kitti_layout(folder: Path, clouds: list[np.ndarray], lidar_poses: np.ndarray) -> Path:
    (folder / "velodyne").mkdir(parents=True)
    for i, cloud in enumerate(clouds):
        cloud.tofile(folder / "velodyne" / f"{i:06d}.bin")
    camera = TR @ lidar_poses @ np.linalg.inv(TR)
    np.savetxt(folder / "poses.txt", camera[:, :3, :4].reshape(-1, 12), fmt="%.17g")
    (folder / "calib.txt").write_text("Tr: " + " ".join(f"{v:.17g}" for v in TR[:3].ravel()))
    np.savetxt(folder / "times.txt", np.arange(len(clouds)) * 0.1)
    return folder


def upsample(poses: np.ndarray, factor: int) -> np.ndarray:
    """Poses at ``factor`` times the rate: linear translation, scipy slerp rotation."""
    key_times = np.arange(len(poses), dtype=float)
    fine = np.arange((len(poses) - 1) * factor + 1) / factor
    out = np.tile(np.eye(4), (len(fine), 1, 1))
    out[:, :3, :3] = Slerp(key_times, Rotation.from_matrix(poses[:, :3, :3]))(fine).as_matrix()
    for axis in range(3):
        out[:, axis, 3] = np.interp(fine, key_times, poses[:, axis, 3])
    return out


# ---------------------------------------------------------------- bag writing
class BagWriter:
    """Writes PointCloud2 / Odometry / PoseStamped messages with rosbags."""

    def __init__(self, path: Path, fmt: str):
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = fmt == "rosbag1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            self.writer = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.conns = {}

    def close(self):
        self.writer.close()

    def _conn(self, topic, msgtype):
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        return self.conns[topic]

    def _write(self, topic, msg, log_ns):
        typ = msg.__msgtype__
        data = self.ts.serialize_ros1(msg, typ) if self.ros1 else self.ts.serialize_cdr(msg, typ)
        self.writer.write(self._conn(topic, typ), log_ns, data)

    def header(self, stamp_ns, frame):
        types = self.ts.types
        stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                     nanosec=stamp_ns % 10**9)
        if self.ros1:
            return types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def cloud(self, topic, cloud, stamp_ns, log_ns):
        self._write(topic, make_cloud_msg(self.ts, self.header(stamp_ns, "velodyne"), cloud),
                    log_ns)

    def pose(self, topic, pose, stamp_ns, log_ns, kind="odometry"):
        t = self.ts.types
        vec = t["geometry_msgs/msg/Vector3"]
        qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
        geometry = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](*pose[:3, 3]),
            orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )
        header = self.header(stamp_ns, "odom")
        if kind == "pose":
            msg = t["geometry_msgs/msg/PoseStamped"](header=header, pose=geometry)
        else:
            twist = t["geometry_msgs/msg/Twist"](linear=vec(0, 0, 0), angular=vec(0, 0, 0))
            msg = t["nav_msgs/msg/Odometry"](
                header=header, child_frame_id="velodyne",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=geometry,
                                                               covariance=np.zeros(36)),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                                 covariance=np.zeros(36)),
            )
        self._write(topic, msg, log_ns)


def make_cloud_msg(ts, header, cloud: np.ndarray, big_endian=False, row_pad=0, height=1):
    """A PointCloud2 with LAYOUT fields; rings and times are set from the index."""
    order = ">" if big_endian else "<"
    dtype = np.dtype({
        "names": [n for n, _, _ in LAYOUT],
        "formats": [order + ("u2" if d == 4 else "f4") for _, _, d in LAYOUT],
        "offsets": [o for _, o, _ in LAYOUT], "itemsize": 32,
    })
    rec = np.zeros(len(cloud), dtype)
    for k, name in enumerate(("x", "y", "z", "intensity")):
        rec[name] = cloud[:, k]
    rec["ring"] = np.arange(len(cloud)) % 16
    rec["time"] = np.arange(len(cloud)) * 1e-5
    width = len(cloud) // height
    rows = rec.view(np.uint8).reshape(height, width * 32)
    data = np.concatenate([rows, np.full((height, row_pad), 0xAB, np.uint8)], axis=1).ravel()
    field = ts.types["sensor_msgs/msg/PointField"]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=header, height=height, width=width,
        fields=[field(name=n, offset=o, datatype=d, count=1) for n, o, d in LAYOUT],
        is_bigendian=big_endian, point_step=32, row_step=width * 32 + row_pad,
        data=data, is_dense=True,
    )


def write_bag(path: Path, fmt: str, clouds, odom_poses=None, odom_stamps_ns=None,
              cloud_stamps_ns=None, extra=None) -> Path:
    writer = BagWriter(path, fmt)
    if cloud_stamps_ns is None:
        cloud_stamps_ns = T0_NS + np.arange(len(clouds)) * SCAN_PERIOD_NS
    events = [(int(s) + CLOUD_LATENCY_NS, "cloud", i, int(s))
              for i, s in enumerate(cloud_stamps_ns)]
    if odom_poses is not None:
        events += [(int(s) + 5_000_000, "odom", j, int(s)) for j, s in enumerate(odom_stamps_ns)]
    for log_ns, kind, idx, stamp in sorted(events):
        if kind == "cloud":
            writer.cloud("/velodyne_points", clouds[idx], stamp, log_ns)
        else:
            writer.pose("/odom", odom_poses[idx], stamp, log_ns)
    if extra:
        extra(writer)
    writer.close()
    return path


def simulated_or_synthetic(folder: Path) -> tuple[Path, list[np.ndarray], np.ndarray]:
    """A VLP-16 sequence from the simulator (100 frames with revisits) in KITTI layout,
    or, without the simulator, 120 random clouds on 1.3 laps of a circle."""
    try:
        from lidar_iris_eval.simulate import simulate_sequence
    except ImportError:
        simulate_sequence = None
    if simulate_sequence is None:
        clouds = make_clouds(120)
        lidar = loop_poses(120)
        return write_kitti_layout(folder, clouds, lidar), clouds, lidar
    kitti = simulate_sequence(folder, preset="tiny-mixed", sensor="vlp16", frames=100)
    scans = sorted((kitti / "velodyne").glob("*.bin"))
    clouds = [np.fromfile(p, dtype=np.float32).reshape(-1, 4) for p in scans]
    assert np.allclose(np.loadtxt(kitti / "times.txt"), np.arange(len(clouds)) * 0.1)
    return kitti, clouds, open_sequence(kitti).poses


@pytest.fixture(scope="module")
def loop_sequence(tmp_path_factory):
    """A sequence with revisits in KITTI layout, plus its LiDAR poses as 50 Hz odometry."""
    root = tmp_path_factory.mktemp("loop")
    kitti, clouds, lidar = simulated_or_synthetic(root / "kitti")
    odom = upsample(lidar, SCAN_PERIOD_NS // ODOM_PERIOD_NS)
    odom_ns = T0_NS + np.arange(len(odom)) * ODOM_PERIOD_NS
    return root, kitti, clouds, lidar, odom, odom_ns


def bag_name(fmt):
    return {"rosbag1": "rec.bag", "mcap": "rec_mcap", "sqlite3": "rec_db3"}[fmt]


# ---------------------------------------------------------------- equality with KITTI
@needs_rosbags
@pytest.mark.parametrize("fmt", FORMATS)
def test_bag_equals_kitti_layout(loop_sequence, fmt):
    root, kitti, clouds, lidar, odom, odom_ns = loop_sequence
    bag = root / bag_name(fmt)
    if not bag.exists():
        write_bag(bag, fmt, clouds, odom, odom_ns)
    seq_bag, seq_kitti = open_sequence(bag), open_sequence(kitti)
    assert len(seq_bag) == len(seq_kitti) == len(clouds)
    for i in (0, 1, 57, len(clouds) - 1):  # some; every scan is read in the eval test
        scan = seq_bag.scan(i)
        np.testing.assert_array_equal(scan.points, seq_kitti[i])
        np.testing.assert_array_equal(scan.intensity, clouds[i][:, 3])
    np.testing.assert_allclose(seq_bag.poses, seq_kitti.poses, rtol=0, atol=1e-6)
    np.testing.assert_allclose(seq_bag.positions("lidar"), lidar[:, :3, 3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(seq_bag.times - 1.6e9, np.arange(len(clouds)) * 0.1, atol=1e-6)
    fields = seq_bag.scan_fields(3)
    np.testing.assert_array_equal(fields["ring"], np.arange(len(clouds[3])) % 16)
    assert fields["time"].dtype == np.float32

    runner = CliRunner()
    from lidar_iris_eval.cli import cli

    results = []
    for path in (bag, kitti):
        out = runner.invoke(cli, ["gt", str(path), "--pose-frame", "lidar", "--json"])
        assert out.exit_code == 0, out.output
        results.append(json.loads(out.output))
    for key in ("frames", "revisit_queries", "positive_ordered_pairs"):
        assert results[0][key] == results[1][key], key
    assert results[0]["revisit_queries"] > 0


@needs_rosbags
def test_eval_protocol1_on_bag_equals_kitti_layout(loop_sequence, tmp_path):
    if find_spec("lidar_iris_eval.cli.eval_cmd") is None:
        pytest.skip("liris eval not available yet")
    import csv

    from lidar_iris_eval.cli import cli

    root, kitti, clouds, lidar, odom, odom_ns = loop_sequence
    bag = root / bag_name("rosbag1")
    if not bag.exists():
        write_bag(bag, "rosbag1", clouds, odom, odom_ns)
    tables, metrics = [], []
    for name, path in (("bag", bag), ("kitti", kitti)):
        out = tmp_path / name
        result = CliRunner().invoke(cli, ["eval", str(path), "--protocol", "1", "-d",
                                          "scan-context", "--pose-frame", "lidar", "--out",
                                          str(out), "-q", "--json"])
        assert result.exit_code == 0, result.output
        metrics.append(json.loads(result.output)["results"][0])
        with open(out / "protocol1" / "scan-context" / "matches.csv") as handle:
            tables.append(list(csv.DictReader(handle)))
    assert metrics[0]["n_revisits"] == metrics[1]["n_revisits"] > 0
    assert len(tables[0]) == len(tables[1]) > 0
    for row_bag, row_kitti in zip(*tables, strict=True):
        assert (row_bag["query"], row_bag["match"]) == (row_kitti["query"], row_kitti["match"])
        assert abs(float(row_bag["distance"]) - float(row_kitti["distance"])) <= 1e-6
        assert row_bag["is_revisit"] == row_kitti["is_revisit"]


@needs_rosbags
def test_bag_is_lazy_fingerprinted_and_picklable(loop_sequence):
    root, kitti, clouds, lidar, odom, odom_ns = loop_sequence
    bag = root / bag_name("rosbag1")
    if not bag.exists():
        write_bag(bag, "rosbag1", clouds, odom, odom_ns)
    seq = open_rosbag(bag)
    assert seq._reader is None  # nothing open until a scan is read
    first = seq[5]
    clone = pickle.loads(pickle.dumps(seq))
    np.testing.assert_array_equal(clone[5], first)
    assert clone.fingerprint() == seq.fingerprint()
    assert open_rosbag(bag, every=2).fingerprint() != seq.fingerprint()
    seq.close()


# ---------------------------------------------------------------- time matching
def straight_poses(times_s: np.ndarray) -> np.ndarray:
    """Constant velocity and yaw rate: linear + slerp interpolation reproduce it exactly."""
    poses = np.tile(np.eye(4), (len(times_s), 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(times_s * 0.4, [0, 0, 1])).as_matrix()
    poses[:, :3, 3] = np.outer(times_s, [3.0, 1.0, 0.0])
    return poses


@needs_rosbags
@pytest.mark.parametrize("fmt", ["rosbag1", "mcap"])
def test_odometry_interpolated_at_scan_stamps(tmp_path, fmt):
    n = 30
    clouds = make_clouds(n, points=20, seed=1)
    scan_s = np.arange(n) * 0.1
    # 50 Hz odometry, 7 ms off the scan clock, starting 1.207 s in: 12 scans have no pose
    odom_s = 1.207 + np.arange(100) * 0.02
    odom_ns = T0_NS + np.round(odom_s * 1e9).astype(np.int64)
    bag = write_bag(tmp_path / bag_name(fmt), fmt, clouds, straight_poses(odom_s), odom_ns)
    with pytest.warns(LirisWarning, match="dropped 12 of 30 scans"):
        seq = open_rosbag(bag)
    np.testing.assert_array_equal(seq.frame_ids, np.arange(12, n))
    # scan 12 (1.2 s) is 7 ms before the first pose: it takes that pose, no extrapolation
    np.testing.assert_allclose(seq.poses[0], straight_poses(odom_s[:1])[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(seq.poses[1:], straight_poses(scan_s[13:]), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(seq[0], clouds[12][:, :3])
    # recording times are 30 ms (clouds) and 5 ms (odometry) late: 25 ms shift,
    # so scan 11 (recorded at 1.13 s) is now within 0.1 s of the first pose
    with pytest.warns(LirisWarning, match="dropped 11 of 30 scans"):
        seq_bag_time = open_rosbag(bag, stamps="bag")
    np.testing.assert_allclose(seq_bag_time.times - 1.6e9, scan_s[11:] + 0.03, atol=1e-6)
    np.testing.assert_allclose(seq_bag_time.poses[1:], straight_poses(scan_s[12:] + 0.025),
                               rtol=0, atol=1e-9)


@needs_rosbags
def test_keyframes_and_tum_pose_file(tmp_path):
    n = 20
    clouds = make_clouds(n, points=10, seed=2)
    bag = write_bag(tmp_path / "nopose.bag", "rosbag1", clouds)
    scan_s = np.arange(n) * 0.1
    poses = straight_poses(scan_s)  # 0.316 m between scans
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    tum = tmp_path / "traj.tum"
    np.savetxt(tum, np.column_stack([1.6e9 + scan_s, poses[:, :3, 3], quat]), fmt="%.9f")
    seq = open_rosbag(bag, poses=tum)
    np.testing.assert_allclose(seq.poses, poses, rtol=0, atol=1e-5)
    seq = open_rosbag(bag, poses=tum, every=4)
    np.testing.assert_array_equal(seq.frame_ids, [0, 4, 8, 12, 16])
    np.testing.assert_array_equal(seq[2], clouds[8][:, :3])
    seq = open_rosbag(bag, poses=tum, min_distance=1.0)  # every 4th scan: 1.26 m
    np.testing.assert_array_equal(seq.frame_ids, [0, 4, 8, 12, 16])
    seq = open_rosbag(bag, poses=tum, min_distance=0.5)  # every 2nd: 0.63 m
    np.testing.assert_array_equal(seq.frame_ids, np.arange(0, 20, 2))


# ---------------------------------------------------------------- errors
@needs_rosbags
def test_clear_errors(tmp_path):
    clouds = make_clouds(3, points=10)
    stamps = T0_NS + np.arange(3) * SCAN_PERIOD_NS
    odom = straight_poses(np.arange(3) * 0.1)

    def second_cloud_topic(writer):
        writer.cloud("/os_cloud", clouds[0], T0_NS, T0_NS)

    bag = write_bag(tmp_path / "a.bag", "rosbag1", clouds, odom, stamps)
    with pytest.raises(LirisError, match=r"--topic /lidar.*no such topic.*/odom.*/velodyne_points"):
        open_rosbag(bag, topic="/lidar")
    with pytest.raises(LirisError, match=r"--topic /odom.*unsupported message type"):
        open_rosbag(bag, topic="/odom")
    with pytest.raises(LirisError, match="--pose-topic /velodyne_points.*unsupported"):
        open_rosbag(bag, pose_topic="/velodyne_points")
    nopose = write_bag(tmp_path / "b.bag", "rosbag1", clouds)
    with pytest.raises(LirisError, match=r"b\.bag.*no nav_msgs/msg/Odometry.*--poses"):
        open_rosbag(nopose)
    two = write_bag(tmp_path / "c.bag", "rosbag1", clouds, odom, stamps, extra=second_cloud_topic)
    with pytest.raises(LirisError, match=r"several .*PointCloud2 topics.*--topic"):
        open_rosbag(two)
    assert len(open_rosbag(two, topic="/velodyne_points")) == 3
    with pytest.raises(LirisError, match="times: not used for a ROS bag"):
        open_rosbag(bag, times="x.txt")
    with pytest.raises(LirisError, match="cannot read ROS bag"):
        (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\nnot really")
        open_rosbag(tmp_path / "junk.bag")


def test_missing_rosbags_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import now fails
    (tmp_path / "x.bag").write_bytes(b"")
    with pytest.raises(LirisError, match=r'pip install "lidar_iris_eval\[rosbag\]"'):
        open_sequence(tmp_path / "x.bag")


# ---------------------------------------------------------------- PointCloud2 decoding
@needs_rosbags
@pytest.mark.parametrize("big_endian, row_pad, height", [(False, 0, 1), (True, 0, 4),
                                                         (False, 12, 4), (True, 5, 2)])
def test_decode_pointcloud2_layouts(big_endian, row_pad, height):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    cloud = make_clouds(1, points=40, seed=5)[0]
    header = ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="l")
    msg = make_cloud_msg(ts, header, cloud, big_endian=big_endian, row_pad=row_pad, height=height)
    # round trip through CDR so the message is what a reader would see
    msg = ts.deserialize_cdr(ts.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    out = decode_pointcloud2(msg)
    for k, name in enumerate(("x", "y", "z", "intensity")):
        np.testing.assert_array_equal(out[name], cloud[:, k])
    np.testing.assert_array_equal(out["ring"], np.arange(40) % 16)
    np.testing.assert_array_equal(out["time"], (np.arange(40) * 1e-5).astype(np.float32))
    msg.data = msg.data[:-40]
    with pytest.raises(LirisError, match="truncated PointCloud2"):
        decode_pointcloud2(msg)
