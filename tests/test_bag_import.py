"""ROS bags in: bags written by rosbags' own writers (ROS 1, ROS 2 SQLite and MCAP) holding a
turntable scan of a known box room, computed on the ROS side from ROS conventions only
(LaserScan θ counter-clockwise about the laser's z, z up, the joint turning about +z), imported,
run through the chain and compared with the ROS-side truth point by point."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from numpy.typing import NDArray
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from scanpipe.bagio import G

F64 = NDArray[np.float64]
# An asymmetric box room in the ROS base frame (z up): a mirrored or swapped axis misses it.
BOX_LO = np.array([-2.0, -1.5, -1.0])
BOX_HI = np.array([3.0, 2.5, 1.6])
ANGLE_MIN = math.radians(-135.0)
INC = math.radians(0.5)
SAMPLES = 541
SCAN_TIME = 0.05  # s per head turn
PROFILES = 60
T0 = 1_700_000_000_000_000_000
OMEGA = math.pi / (PROFILES * SCAN_TIME)  # half a platform turn over the scan
YAW0 = 0.3  # the TF yaw at the start (the joint starts at 0)
# The zero mount of an import without TF (bagio's docstring): laser x → platform x,
# laser y → platform −z, laser z → platform y.
DEFAULT_R_PL = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
# The TF test's mount: a cyclic axis change and an offset from the axis.
TF_R_PL = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])
TF_T_PL = np.array([0.15, 0.05, 0.3])


def rz(angle: float) -> F64:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def box_range(origin: F64, direction: F64) -> F64:
    """Distance from ``origin`` (inside the box) along unit rows of ``direction`` to a wall."""
    with np.errstate(divide="ignore", invalid="ignore"):
        to_wall = np.where(direction > 0, (BOX_HI - origin) / direction,
                           np.where(direction < 0, (BOX_LO - origin) / direction, np.inf))
    return np.asarray(to_wall.min(axis=1), np.float64)


def ros_scan(r_pl: F64, t_pl: F64, yaw0: float) -> tuple[list[F64], F64, F64]:
    """Ranges per profile, their ROS base-frame points (P, S, 3), and the sample times."""
    theta = ANGLE_MIN + np.arange(SAMPLES) * INC
    beams = np.stack([np.cos(theta), np.sin(theta), np.zeros(SAMPLES)], -1)  # laser frame
    dt = SCAN_TIME * INC / (2 * math.pi)
    ranges, points = [], np.zeros((PROFILES, SAMPLES, 3))
    times = np.zeros((PROFILES, SAMPLES))
    for p in range(PROFILES):
        t = p * SCAN_TIME + np.arange(SAMPLES) * dt
        psi = yaw0 + OMEGA * t
        rot = np.stack([rz(a) for a in psi])  # per sample: the platform turns during a profile
        origin = rot @ t_pl
        direction = np.einsum("sij,jk,sk->si", rot, r_pl, beams)
        r = box_range(origin, direction)
        ranges.append(r)
        points[p] = origin + r[:, None] * direction
        times[p] = t
    return ranges, points, times


def _header(ts: Any, time_s: float, frame: str) -> Any:
    ns = T0 + round(time_s * 1e9)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    header_type = ts.types["std_msgs/msg/Header"]
    if "seq" in ts.fielddefs["std_msgs/msg/Header"][1][0]:
        return header_type(seq=0, stamp=stamp, frame_id=frame)
    return header_type(stamp=stamp, frame_id=frame)


def _transform(ts: Any, time_s: float, parent: str, child: str, rotation: F64,
               translation: F64) -> Any:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    types = ts.types
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, time_s, parent), child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=translation[0], y=translation[1],
                                                          z=translation[2]),
            rotation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)))


def image_messages(ts: Any) -> list[tuple[str, str, float, Any]]:
    """A JPEG CompressedImage camera with its CameraInfo, and a raw rgb8 Image camera."""
    import cv2

    out: list[tuple[str, str, float, Any]] = []
    types = ts.types
    pixels = np.zeros((48, 64, 3), np.uint8)
    pixels[:, :32] = (0, 0, 255)  # BGR red left half
    ok, jpeg = cv2.imencode(".jpg", pixels)
    assert ok
    k = np.array([50.0, 0, 31.5, 0, 50.0, 23.5, 0, 0, 1])
    info_fields = ts.fielddefs["sensor_msgs/msg/CameraInfo"][1]
    names = [f[0] for f in info_fields]
    lower = "k" in names
    for i in range(4):
        t = i * 0.7
        out.append(("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", t,
                    types["sensor_msgs/msg/CompressedImage"](
                        header=_header(ts, t, "cam"), format="jpeg",
                        data=np.frombuffer(jpeg.tobytes(), np.uint8))))
        out.append(("/raw/image_raw", "sensor_msgs/msg/Image", t, types["sensor_msgs/msg/Image"](
            header=_header(ts, t, "raw"), height=48, width=64, encoding="rgb8",
            is_bigendian=0, step=64 * 3, data=pixels[:, :, ::-1].copy().ravel())))
    values = {n: None for n in names}
    values.update({"header": _header(ts, 0.0, "cam"), "height": 48, "width": 64,
                   "distortion_model": "plumb_bob"})
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
    values.update({("d" if lower else "D"): np.zeros(5), ("k" if lower else "K"): k,
                   ("r" if lower else "R"): np.eye(3).ravel(),
                   ("p" if lower else "P"): np.zeros(12), "binning_x": 0, "binning_y": 0,
                   "roi": roi})
    out.append(("/cam/camera_info", "sensor_msgs/msg/CameraInfo", 0.0,
                types["sensor_msgs/msg/CameraInfo"](**values)))
    return out


def multi_echo(ts: Any, messages: list[tuple[str, str, float, Any]]
               ) -> list[tuple[str, str, float, Any]]:
    """The LaserScans as MultiEchoLaserScans: the true range first, a nearer false echo next."""
    types = ts.types
    echo = types["sensor_msgs/msg/LaserEcho"]
    out = []
    for topic, msgtype, t, msg in messages:
        if msgtype == "sensor_msgs/msg/LaserScan":
            fields = {k: getattr(msg, k) for k in ("header", "angle_min", "angle_max",
                      "angle_increment", "time_increment", "scan_time", "range_min",
                      "range_max")}
            msg = types["sensor_msgs/msg/MultiEchoLaserScan"](
                **fields,
                ranges=[echo(echoes=np.array([r, 0.3 * r], np.float32)) for r in msg.ranges],
                intensities=[echo(echoes=np.array([5.0, 1.0], np.float32))
                             for _ in msg.ranges])
            msgtype = "sensor_msgs/msg/MultiEchoLaserScan"
        out.append((topic, msgtype, t, msg))
    return out


def turntable_messages(ts: Any, angle_source: str, scan_topics: tuple[str, ...] = ("/scan",),
                       images: bool = False) -> list[tuple[str, str, float, Any]]:
    """(topic, type, time, message) of a turntable scan; JointState ``turntable`` or TF."""
    use_tf = angle_source == "tf"
    r_pl, t_pl = (TF_R_PL, TF_T_PL) if use_tf else (DEFAULT_R_PL, np.zeros(3))
    ranges, _, _ = ros_scan(r_pl, t_pl, YAW0 if use_tf else 0.0)
    scan_type = ts.types["sensor_msgs/msg/LaserScan"]
    out: list[tuple[str, str, float, Any]] = []
    for p, r in enumerate(ranges):
        r = r.astype(np.float32)
        r[5] = np.inf  # no return, the ROS way
        r[6] = 0.01  # below range_min: no return
        for topic in scan_topics:
            out.append((topic, "sensor_msgs/msg/LaserScan", p * SCAN_TIME, scan_type(
                header=_header(ts, p * SCAN_TIME, "laser"), angle_min=ANGLE_MIN,
                angle_max=ANGLE_MIN + (SAMPLES - 1) * INC, angle_increment=INC,
                time_increment=SCAN_TIME * INC / (2 * math.pi), scan_time=SCAN_TIME,
                range_min=0.05, range_max=30.0, ranges=r,
                intensities=np.full(SAMPLES, 100.0, np.float32))))
    duration = PROFILES * SCAN_TIME + 0.1
    for k in range(int(duration / 0.01) + 1):
        t = k * 0.01
        psi = OMEGA * t
        if use_tf:
            tf_type = ts.types["tf2_msgs/msg/TFMessage"]
            out.append(("/tf", "tf2_msgs/msg/TFMessage", t, tf_type(transforms=[
                _transform(ts, t, "base", "platform", rz(YAW0 + psi), np.array([0, 0, 0.0]))])))
        else:
            js = ts.types["sensor_msgs/msg/JointState"]
            out.append(("/joint_states", "sensor_msgs/msg/JointState", t, js(
                header=_header(ts, t, ""), name=["turntable", "fixed_wheel"],
                position=np.array([psi, 0.5]), velocity=np.zeros(0), effort=np.zeros(0))))
    if use_tf:  # platform → mount → laser, split in two static transforms
        tf_type = ts.types["tf2_msgs/msg/TFMessage"]
        half = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90° about z
        out.append(("/tf_static", "tf2_msgs/msg/TFMessage", 0.0, tf_type(transforms=[
            _transform(ts, 0.0, "platform", "mount", half, TF_T_PL),
            _transform(ts, 0.0, "mount", "laser", half.T @ TF_R_PL, np.zeros(3))])))
    if images:
        out += image_messages(ts)
    return sorted(out, key=lambda m: m[2])


def write_bag(path: Path, kind: str, messages: Callable[[Any], list[Any]]) -> Path:
    """A bag of ``kind`` (ros1, sqlite3, mcap) written by rosbags' own writers."""
    if kind == "ros1":
        ts = get_typestore(Stores.ROS1_NOETIC)
        bag = path / "scan.bag"
        with Writer1(bag) as writer:
            conns: dict[str, Any] = {}
            for topic, msgtype, t, msg in messages(ts):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(conns[topic], T0 + round(t * 1e9) + 1000,
                             ts.serialize_ros1(msg, msgtype))
        return bag
    ts = get_typestore(Stores.ROS2_HUMBLE)
    bag = path / f"scan_{kind}"
    plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
    with Writer2(bag, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, msgtype, t, msg in messages(ts):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], T0 + round(t * 1e9) + 1000, ts.serialize_cdr(msg, msgtype))
    return bag


def assembled(workdir: Path) -> dict[str, Any]:
    table = pq.read_table(workdir / "assemble" / "points.parquet")
    return {name: table.column(name).to_numpy() for name in table.column_names}


def check_against_truth(points: Any, truth: F64) -> None:
    """Every assembled point where the ROS side put it (rig frame mapped back to ROS)."""
    rig = np.stack([points[c].astype(np.float64) for c in ("x", "y", "z")], -1)
    ros = rig @ G  # G is orthonormal: rig = G · ros
    expected = truth[points["profile"], points["sample"]]
    valid = np.isfinite(ros).all(axis=1)
    assert valid.sum() >= PROFILES * (SAMPLES - 2) * 0.99
    error = np.linalg.norm(ros[valid] - expected[valid], axis=1)
    assert float(np.max(error)) < 2e-3, float(np.max(error))
    assert np.all(ros[valid] >= BOX_LO - 2e-3) and np.all(ros[valid] <= BOX_HI + 2e-3)


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_joint_state_bag_assembles_the_room(tmp_path: Path, cli: Any, kind: str) -> None:
    bag = write_bag(tmp_path, kind, lambda ts: turntable_messages(ts, "joint"))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    assert "60 profiles × 541 samples" in result.out
    info = cli("info", out)
    assert info.code == 0 and "profiles    60 (decoded" in info.out
    assert "/scanner/profiles               60" in info.out
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    points = assembled(tmp_path / "w")
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    check_against_truth(points, truth)
    no_return = (points["sample"] == 5) | (points["sample"] == 6)
    assert np.isnan(points["range_m"][no_return]).all()  # inf, below range_min: no return
    assert np.isfinite(points["range_m"][~no_return]).all()


def test_multi_echo_takes_the_first_echo(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "sqlite3", lambda ts: multi_echo(ts, turntable_messages(ts, "joint")))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    assert "MultiEchoLaserScan: the first echo of each beam is taken" in result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    points = assembled(tmp_path / "w")
    check_against_truth(points, truth)
    assert set(np.unique(points["echo"]).tolist()) == {5}


def test_tf_bag_takes_the_mount_and_the_yaw(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "mcap", lambda ts: turntable_messages(ts, "tf"))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--tf", "base:platform")
    assert result.code == 0, result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    _, truth, _ = ros_scan(TF_R_PL, TF_T_PL, YAW0)
    check_against_truth(assembled(tmp_path / "w"), truth)


FIXTURES = Path(__file__).parent / "fixtures"


@pytest.mark.parametrize("kind", ["ros1", "sqlite3"])
def test_full_run_on_an_imported_bag_with_images(tmp_path: Path, cli: Any, kind: str) -> None:
    from scanpipe.recording.reader import read_recording

    bag = write_bag(tmp_path, kind, lambda ts: turntable_messages(ts, "joint", images=True))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", "/cam/image/compressed",
                 "--image", "/raw/image_raw")
    assert result.code == 0, result.err
    assert "no CameraInfo" in result.err and "/raw/image_raw" in result.err
    recording = read_recording(out)
    rig = recording.rig()
    cam = rig.camera("cam_image_compressed")
    assert (cam.width, cam.height, cam.fx, cam.cx, cam.cy) == (64, 48, 50.0, 31.5, 23.5)
    formats = {(i.camera_id, i.format) for i in recording.images}
    assert formats == {("cam_image_compressed", "jpeg"), ("raw_image_raw", "png")}
    import cv2

    png = next(i.data for i in recording.images if i.format == "png")
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert tuple(decoded[0, 0]) == (0, 0, 255) and tuple(decoded[0, 63]) == (0, 0, 0)
    result = cli("run", out, "--workdir", tmp_path / "w", "-q")
    assert result.code == 0, result.err
    assert (tmp_path / "w" / "export").is_dir()


def test_ambiguous_scan_topics_are_listed(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "sqlite3",
                    lambda ts: turntable_messages(ts, "joint", ("/front/scan", "/rear/scan")))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1
    assert result.err.count("\n") == 1
    assert "2 laser scan topics; choose one with --scan" in result.err
    assert "/front/scan (sensor_msgs/LaserScan, 60)" in result.err
    assert "/rear/scan (sensor_msgs/LaserScan, 60)" in result.err
    assert not out.exists()
    assert cli("import-bag", bag, "--out", out, "--scan", "/rear/scan").code == 0


def test_existing_output_is_not_overwritten_without_force(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "mcap", lambda ts: turntable_messages(ts, "joint"))
    out = tmp_path / "rec.mcap"
    out.write_bytes(b"precious")
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 2
    assert "already exists; pass --force" in result.err
    assert out.read_bytes() == b"precious"
    assert cli("import-bag", bag, "--out", out, "--force").code == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"


@pytest.mark.parametrize("damage", ["cut", "garbage"])
def test_damaged_bag_is_one_line(tmp_path: Path, cli: Any, damage: str) -> None:
    source = (FIXTURES / "psen_scan_v2_laser.bag").read_bytes()
    bag = tmp_path / "bad.bag"
    bag.write_bytes(source[:len(source) // 2] if damage == "cut"
                    else bytes(range(256)) * 20)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1
    assert result.err.startswith(f"scanpipe: error: {bag}: not a readable ROS bag")
    assert result.err.count("\n") == 1
    assert not out.exists() and list(tmp_path.iterdir()) == [bag]


def test_bag_without_laser_scan_names_what_it_holds(tmp_path: Path, cli: Any) -> None:
    bag = FIXTURES / "psen_scan_v2_zones.bag"  # a real ROS 1 bag: one zone configuration
    result = cli("import-bag", bag, "--out", tmp_path / "rec.mcap")
    assert result.code == 1
    assert result.err == (f"scanpipe: error: {bag}: no laser scan (sensor_msgs/LaserScan or "
                          "MultiEchoLaserScan) in the bag; found: /laser_1/zoneconfiguration "
                          "(psen_scan_v2/ZoneSetConfiguration, 1)\n")


def test_no_platform_angle_lists_topics(cli: Any, tmp_path: Path) -> None:
    bag = FIXTURES / "psen_scan_v2_laser.bag"
    result = cli("import-bag", bag, "--out", tmp_path / "rec.mcap")
    assert result.code == 1 and result.err.count("\n") == 1
    assert "no platform angle chosen (no JointState in the bag); pass --joint NAME or --tf" \
        in result.err
    assert "/laser_scanner/scan (sensor_msgs/LaserScan, 522)" in result.err


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_info_and_run_on_a_bag_say_import_bag(tmp_path: Path, cli: Any, kind: str) -> None:
    bag = write_bag(tmp_path, kind, lambda ts: turntable_messages(ts, "joint"))
    target = bag if kind == "ros1" else (bag / f"{bag.name}.mcap" if kind == "mcap" else bag)
    for command in (["info", target], ["run", target, "--workdir", tmp_path / "w"]):
        result = cli(*command)
        if kind == "mcap" and command[0] == "info":
            # info shows any MCAP file (its channels), and says how to make a recording of it
            assert result.code == 0 and "sensor_msgs/msg/LaserScan" in result.out
            assert "scanpipe import-bag" in result.err
            continue
        assert result.code != 0
        errors = [line for line in result.err.splitlines() if "error" in line]
        assert len(errors) == 1, result.err
        assert "ROS" in errors[0] and "scanpipe import-bag" in errors[0], result.err
        assert "not an MCAP file" not in result.err


def test_public_laser_bag_imports(tmp_path: Path, cli: Any) -> None:
    """The Pilz PSENscan driver's recorded LaserScan (tests/fixtures/README.md) with a
    platform angle added: counts, beam angles and ranges as the scanner wrote them."""
    from rosbags.highlevel import AnyReader

    from scanpipe.recording.reader import read_recording

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "laser_with_joint.bag"
    scans: list[Any] = []
    with AnyReader([FIXTURES / "psen_scan_v2_laser.bag"]) as reader, Writer1(bag) as writer:
        (conn,) = [c for c in reader.connections if c.topic == "/laser_scanner/scan"]
        out_conn = writer.add_connection(conn.topic, conn.msgtype, typestore=ts)
        for c, t, raw in reader.messages(connections=[conn]):
            writer.write(out_conn, t, raw)  # the scanner's own bytes
            scans.append((t, reader.deserialize(raw, c.msgtype)))
        joints = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState",
                                       typestore=ts)
        # The angle reports span the scans' stamps (0.2 ms before their log times) and more.
        first, last = scans[0][0] - 10**8, scans[-1][0] + 10**8
        for k in range(50):
            t = first + (last - first) * k // 49
            msg = ts.types["sensor_msgs/msg/JointState"](
                header=ts.types["std_msgs/msg/Header"](
                    seq=k, stamp=ts.types["builtin_interfaces/msg/Time"](
                        sec=t // 10**9, nanosec=t % 10**9), frame_id=""),
                name=["turntable"], position=np.array([k * 0.05]),
                velocity=np.zeros(0), effort=np.zeros(0))
            writer.write(joints, t, ts.serialize_ros1(msg, "sensor_msgs/msg/JointState"))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--json")
    assert result.code == 0, result.err
    assert '"profiles": 522' in result.out and '"samples_per_profile": 500' in result.out
    recording = read_recording(out)
    assert len(recording.profiles) == 522
    msg = scans[0][1]
    p = recording.profiles[0]
    assert p.start_angle_deg == pytest.approx(math.degrees(msg.angle_min) + 90, abs=1e-9)
    assert p.step_deg == pytest.approx(math.degrees(msg.angle_increment), abs=1e-12)
    raw = np.asarray(msg.ranges, np.float32)
    usable = (raw >= msg.range_min) & (raw <= msg.range_max)
    np.testing.assert_array_equal(p.ranges_m[usable], raw[usable])
    assert np.isnan(p.ranges_m[~usable]).all()
    assert recording.motor.step_count[-1] == round(-math.degrees(49 * 0.05) / 1e-4)
    rig = recording.rig()
    assert rig.scanner.beam_step_deg == pytest.approx(0.1, abs=1e-6)
    assert rig.scanner.max_range_m == pytest.approx(40.0)
    result = cli("decode", out, "--out", tmp_path / "d")
    assert result.code == 0, result.err


@pytest.mark.parametrize(("args", "code", "message"), [
    (["--scan", "/nope"], 1, "--scan /nope: no such topic; laser scan topics: /scan "
                             "(sensor_msgs/LaserScan, 60)"),
    (["--scan", "/joint_states"], 1, "--scan /joint_states: is sensor_msgs/msg/JointState, "
                                     "not a LaserScan"),
    (["--joint", "elbow"], 1, "--joint elbow: no JointState reports it"),
    (["--tf", "base"], 2, "--tf 'base': expected PARENT:CHILD"),
    (["--tf", "base:platform", "--joint", "turntable"], 2, "--joint and --tf both"),
    (["--tf", "map:base"], 1, "--tf map:base: no such transform in /tf; transforms found: none"),
    (["--image", "/scan"], 1, "--image /scan: not an image topic; image topics: no topics"),
])
def test_bad_arguments_are_one_line(tmp_path: Path, cli: Any, args: list[str], code: int,
                                    message: str) -> None:
    bag = write_bag(tmp_path, "ros1", lambda ts: turntable_messages(ts, "joint"))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, *args)
    assert result.code == code
    assert message in result.err and result.err.count("\n") == 1, result.err
    assert not out.exists()


def test_fixed_joint_is_not_a_platform(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "ros1", lambda ts: turntable_messages(ts, "joint"))
    result = cli("import-bag", bag, "--out", tmp_path / "rec.mcap", "--joint", "fixed_wheel")
    assert result.code == 0  # named explicitly: taken, even though it stands still
    from scanpipe.recording.reader import read_recording

    steps = read_recording(tmp_path / "rec.mcap").motor.step_count
    assert set(steps.tolist()) == {round(-math.degrees(0.5) / 1e-4)}


def test_rig_option_keeps_its_calibration(tmp_path: Path, cli: Any) -> None:
    from scanpipe.recording.reader import read_recording
    from scanpipe.rig import load_rig

    bag = write_bag(tmp_path, "mcap", lambda ts: turntable_messages(ts, "joint"))
    rig_file = tmp_path / "rig.toml"
    assert cli("rig", "init", rig_file).code == 0
    rig_file.write_text(rig_file.read_text().replace("alpha_offset_deg = 0.0",
                                                     "alpha_offset_deg = 1.5"))
    assert load_rig(rig_file).scanner.alpha_offset_deg == 1.5
    out = tmp_path / "rec.mcap"
    assert cli("import-bag", bag, "--out", out, "--rig", rig_file).code == 0
    rig = read_recording(out).rig()
    assert rig.scanner.alpha_offset_deg == 1.5 and rig.scanner.dialect == "ldoem"
    assert rig.motor.pulse_step_deg == pytest.approx(1e-4)


def test_tf_child_that_moves_off_the_axis_is_refused(tmp_path: Path, cli: Any) -> None:
    def drifting(ts: Any) -> list[tuple[str, str, float, Any]]:
        messages = turntable_messages(ts, "tf")
        for topic, _, t, msg in messages:
            if topic == "/tf":
                msg.transforms[0].transform.translation.x = 0.1 * t  # slides, not a turntable
        return messages

    bag = write_bag(tmp_path, "sqlite3", drifting)
    result = cli("import-bag", bag, "--out", tmp_path / "rec.mcap", "--tf", "base:platform")
    assert result.code == 1 and result.err.count("\n") == 1
    assert "platform does not only turn about base's z" in result.err
