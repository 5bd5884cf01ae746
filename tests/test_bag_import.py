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


def turntable_messages(ts: Any, angle_source: str, scan_topics: tuple[str, ...] = ("/scan",)
                       ) -> list[tuple[str, str, float, Any]]:
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
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    points = assembled(tmp_path / "w")
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    check_against_truth(points, truth)
    no_return = (points["sample"] == 5) | (points["sample"] == 6)
    assert np.isnan(points["range_m"][no_return]).all()  # inf, below range_min: no return
    assert np.isfinite(points["range_m"][~no_return]).all()


def test_tf_bag_takes_the_mount_and_the_yaw(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "mcap", lambda ts: turntable_messages(ts, "tf"))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--tf", "base:platform")
    assert result.code == 0, result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    _, truth, _ = ros_scan(TF_R_PL, TF_T_PL, YAW0)
    check_against_truth(assembled(tmp_path / "w"), truth)
