"""ROS 2 bags as a recorder leaves them when it is stopped hard, and files whose name does not
say what they are: written by rosbags' own writers, then cut or stripped the way ``ros2 bag
record`` / ``rosbag record`` leave them (metadata.yaml is written at close, an MCAP's summary
and footer at close, a ROS 1 bag's index at close and its name ends in ``.active`` until then).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_bag_import import (
    DEFAULT_R_PL,
    OMEGA,
    PROFILES,
    SCAN_TIME,
    assembled,
    check_against_truth,
    ros_scan,
    turntable_messages,
    write_bag,
)

from scanpipe.bagio import G


def padded(ts: Any) -> list[tuple[str, str, float, Any]]:
    """The turntable scan with a bulky camera topic beside it, so rosbags' MCAP writer (1 MiB
    chunks) spreads the scan over several chunks, as a real recording with a camera does."""
    messages = turntable_messages(ts, "joint")
    image = ts.types["sensor_msgs/msg/Image"]
    header = next(m for _, _, _, m in messages if hasattr(m, "header")).header
    for k in range(24):
        t = k * PROFILES * SCAN_TIME / 24
        messages.append(("/cam/image_raw", "sensor_msgs/msg/Image", t, image(
            header=header, height=240, width=320, encoding="rgb8", is_bigendian=0,
            step=960, data=np.random.default_rng(k).integers(0, 255, 240 * 960, np.uint8))))
    return sorted(messages, key=lambda m: m[2])


def storage_file(bag: Path) -> Path:
    (file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    return file


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_bag_folder_without_metadata_yaml_is_read_from_its_storage_files(
        tmp_path: Path, cli: Any, kind: str) -> None:
    """``ros2 bag record`` killed: the folder holds the storage file but no metadata.yaml."""
    bag = write_bag(tmp_path, kind, lambda ts: turntable_messages(ts, "joint"))
    (bag / "metadata.yaml").unlink()
    before = sorted(p.name for p in bag.iterdir())
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    assert "no metadata.yaml" in result.err and storage_file(bag).name in result.err
    assert "60 profiles × 541 samples" in result.out
    assert sorted(p.name for p in bag.iterdir()) == before  # the bag is left as it was
    assert cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q").code == 0
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    check_against_truth(assembled(tmp_path / "w"), truth)


def test_folder_without_metadata_or_storage_is_one_line(tmp_path: Path, cli: Any) -> None:
    folder = tmp_path / "empty_bag"
    folder.mkdir()
    (folder / "notes.txt").write_text("x")
    result = cli("import-bag", folder, "--out", tmp_path / "rec.mcap")
    assert result.code == 1
    assert result.err.count("\n") == 1, result.err
    assert "no metadata.yaml and no .db3 or .mcap file" in result.err
    assert not (tmp_path / "rec.mcap").exists()


@pytest.mark.parametrize("keep_metadata", [False, True])
def test_mcap_bag_cut_mid_write_keeps_its_complete_chunks(tmp_path: Path, cli: Any,
                                                          keep_metadata: bool) -> None:
    """An MCAP bag whose recorder was killed: no summary, no footer, a chunk cut in half."""
    bag = write_bag(tmp_path, "mcap", padded)
    if not keep_metadata:
        (bag / "metadata.yaml").unlink()
    file = storage_file(bag)
    whole = file.read_bytes()
    file.write_bytes(whole[:int(len(whole) * 0.6)])
    cut = file.read_bytes()
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert any(w.startswith(f"{file.name}: cut before its end") for w in report["warnings"])
    assert 10 < report["profiles"] < PROFILES
    assert file.read_bytes() == cut  # never repaired in place
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([bag.name, "rec.mcap"])
    assert cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q").code == 0
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    points = assembled(tmp_path / "w")
    kept = int(points["profile"].max()) + 1
    assert kept == report["profiles"]
    rig = np.stack([points[c].astype(np.float64) for c in ("x", "y", "z")], -1)
    valid = np.isfinite(rig).all(axis=1)
    assert valid.sum() >= kept * 530
    error = np.linalg.norm((rig @ G)[valid] - truth[points["profile"], points["sample"]][valid],
                           axis=1)
    assert float(error.max()) < 2e-3


def test_ros1_bag_left_active_by_its_recorder_is_one_line(tmp_path: Path, cli: Any) -> None:
    """``rosbag record`` killed leaves NAME.bag.active without an index."""
    bag = write_bag(tmp_path, "ros1", lambda ts: turntable_messages(ts, "joint"))
    data = bytearray(bag.read_bytes())
    # The bag header's index_pos (the first record's first field) is 0 until the bag is closed.
    at = data.index(b"index_pos=") + len(b"index_pos=")
    data[at:at + 8] = bytes(8)
    active = tmp_path / "scan.bag.active"
    active.write_bytes(bytes(data))
    bag.unlink()
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", active, "--out", out)
    assert result.code == 1
    assert result.err.count("\n") == 1, result.err
    assert f"{active}: a ROS 1 bag without its index" in result.err
    assert "rosbag reindex" in result.err
    assert sorted(p.name for p in tmp_path.iterdir()) == [active.name]


@pytest.mark.parametrize("name", ["scan.db4", "scan.bag.orig", "scan"])
def test_a_bag_under_another_name_is_read_by_its_content(tmp_path: Path, cli: Any,
                                                         name: str) -> None:
    source = storage_file(write_bag(tmp_path, "sqlite3",
                                    lambda ts: turntable_messages(ts, "joint")))
    if name.startswith("scan.bag"):
        source = write_bag(tmp_path, "ros1", lambda ts: turntable_messages(ts, "joint"))
    renamed = tmp_path / "renamed"
    renamed.mkdir()
    shutil.copy(source, renamed / name)
    result = cli("import-bag", renamed / name, "--out", tmp_path / "rec.mcap")
    assert result.code == 0, result.err
    assert "60 profiles × 541 samples" in result.out
    assert [p.name for p in renamed.iterdir()] == [name]


@pytest.mark.parametrize("content", [b"", b"hello world, not a bag" * 10])
def test_a_file_that_is_no_bag_is_one_line(tmp_path: Path, cli: Any, content: bytes) -> None:
    path = tmp_path / "scan.db4"
    path.write_bytes(content)
    result = cli("import-bag", path, "--out", tmp_path / "rec.mcap")
    assert result.code == 1
    assert result.err.count("\n") == 1, result.err
    assert f"{path}: not a readable ROS bag (it starts with neither" in result.err


def _joint_states_shifted(ts: Any, start_s: float, end_s: float,
                          shift_s: float = 0.0) -> list[tuple[str, str, float, Any]]:
    """The turntable scan with its JointStates kept in [start_s, end_s] and their stamps moved
    by ``shift_s`` (a joint publisher on another clock)."""
    from test_bag_import import _header

    out = []
    for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
        if topic == "/joint_states":
            if not start_s <= t <= end_s:
                continue
            msg.header = _header(ts, t + shift_s, "")
        out.append((topic, msgtype, t, msg))
    return out


def test_scans_outside_the_angle_reports_are_dropped_not_held(tmp_path: Path, cli: Any) -> None:
    """The joint publisher starts late and stops early: the scans before and after it have no
    measured platform angle (assemble would hold the nearest one: a cloud smeared along β)."""
    bag = write_bag(tmp_path, "sqlite3", lambda ts: _joint_states_shifted(ts, 0.5, 2.2))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    # scans start every 50 ms and last 50 ms: 0.50 … 2.15 lies within 0.50 … 2.20
    assert report["profiles"] == 34
    assert any("26 scans outside the platform angle reports (0.5 … 2.2 s" in w
               for w in report["warnings"]), report["warnings"]
    assert cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q").code == 0
    points = assembled(tmp_path / "w")
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    rig = np.stack([points[c].astype(np.float64) for c in ("x", "y", "z")], -1)
    valid = np.isfinite(rig).all(axis=1)
    assert valid.sum() >= 34 * 530
    expected = truth[10:44][points["profile"], points["sample"]]
    assert float(np.linalg.norm((rig @ G)[valid] - expected[valid], axis=1).max()) < 2e-3


def test_scans_beyond_the_angle_reports_of_a_platform_at_rest_are_kept(
        tmp_path: Path, cli: Any) -> None:
    """A joint publisher that starts after the laser (the usual order in a real bag) with the
    platform at rest there: the held angle is right, so no scan is dropped and nothing warned."""
    from test_bag_import import _header

    def messages(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = []
        for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
            if topic == "/joint_states":
                if t < 0.5:
                    continue
                msg.header = _header(ts, t, "")
                # at rest for 1.1 s from the first report, then turning to the end
                msg.position = np.array([OMEGA * max(t - 1.6, 0.0), 0.5])
            out.append((topic, msgtype, t, msg))
        return out

    bag = write_bag(tmp_path, "sqlite3", messages)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["profiles"] == 60  # the ten scans before the first report included
    assert not any("outside the platform angle reports" in w for w in report["warnings"])


def test_angles_on_another_clock_than_the_scans_are_refused(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "mcap", lambda ts: _joint_states_shifted(ts, 0.0, 4.0, -1e6))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1
    assert result.err.count("\n") == 1, result.err
    assert "no scan lies within the platform angle reports" in result.err
    assert not out.exists()


def test_two_scanners_on_one_topic_are_refused(tmp_path: Path, cli: Any) -> None:
    """Two lasers publishing on one topic (told apart by header.frame_id only) interleave two
    scans of different geometry: imported as one, every other profile would be misplaced."""
    import copy

    from test_bag_import import _header

    def two_frames(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = []
        for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
            out.append((topic, msgtype, t, msg))
            if msgtype.endswith("LaserScan"):
                rear = copy.deepcopy(msg)
                rear.header = _header(ts, t + 0.001, "laser_rear")
                out.append((topic, msgtype, t + 0.001, rear))
        return out

    bag = write_bag(tmp_path, "sqlite3", two_frames)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1
    assert result.err.count("\n") == 1, result.err
    assert "/scan: scans from 2 frames (laser: 60, laser_rear: 60)" in result.err
    assert not out.exists()


TILT_IDL = """// generated from rosidl_adapter/resource/msg.idl.em
// with input from rig_msgs/msg/Tilt.msg
// generated code does not contain a copyright notice

#include "std_msgs/msg/Header.idl"

module rig_msgs {
  module msg {
    @verbatim (language="comment", text=
      "The platform's tilt")
    struct Tilt {
      std_msgs::msg::Header header;

      @verbatim (language="comment", text=
        "radians")
      double angle;
    };
  };
};
"""
HEADER_IDL = """#include "builtin_interfaces/msg/Time.idl"

module std_msgs {
  module msg {
    struct Header {
      builtin_interfaces::msg::Time stamp;
      string frame_id;
    };
  };
};
"""
TIME_IDL = """module builtin_interfaces {
  module msg {
    struct Time {
      int32 sec;
      uint32 nanosec;
    };
  };
};
"""


def _idl(*parts: tuple[str, str]) -> bytes:
    """A ros2idl schema as rosbag2 writes it: every .idl after a two-line delimiter."""
    return "".join(f"{'=' * 80}\nIDL: {name}\n{text}" for name, text in parts).encode()


@pytest.mark.parametrize("extra", ["ros2idl", "broken_ros2msg"])
def test_a_topic_whose_definition_rosbags_cannot_parse_does_not_sink_the_bag(
        tmp_path: Path, cli: Any, extra: str) -> None:
    """A standalone MCAP as ``ros2 bag record -s mcap`` writes it (ros2msg schemas) with one
    more topic: a type defined in IDL (its schema holds rosidl's ``#include`` lines, which
    rosbags' IDL parser rejects), or a definition rosbags cannot parse at all."""
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore
    from test_bag_import import T0

    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "scan.mcap"
    with path.open("wb") as handle:
        writer = Writer(handle)
        writer.start(profile="ros2", library="rosbag2 (as written by ros2 bag record)")
        channels: dict[str, int] = {}
        for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
            if topic not in channels:
                schema = writer.register_schema(msgtype, "ros2msg",
                                                ts.generate_msgdef(msgtype, 2)[0].encode())
                channels[topic] = writer.register_channel(topic, "cdr", schema)
            stamp = T0 + round(t * 1e9)
            writer.add_message(channels[topic], stamp, bytes(ts.serialize_cdr(msg, msgtype)),
                               stamp)
        if extra == "ros2idl":
            schema = writer.register_schema("rig_msgs/msg/Tilt", "ros2idl", _idl(
                ("rig_msgs/msg/Tilt", TILT_IDL), ("std_msgs/msg/Header", HEADER_IDL),
                ("builtin_interfaces/msg/Time", TIME_IDL)))
        else:
            schema = writer.register_schema("rig_msgs/msg/Tilt", "ros2msg",
                                            b"std_msgs/Header header\nfloat64<> angle\n")
        tilt = writer.register_channel("/tilt", "cdr", schema)
        writer.add_message(tilt, T0, b"\x00\x01\x00\x00" + bytes(24), T0)
        writer.finish()
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", path, "--out", out)
    assert result.code == 0, result.err
    assert "60 profiles × 541 samples" in result.out
    if extra == "broken_ros2msg":
        assert "/tilt (rig_msgs/msg/Tilt): its message definition cannot be parsed" in result.err
    assert cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q").code == 0
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    check_against_truth(assembled(tmp_path / "w"), truth)


def test_a_continuous_joint_reported_wrapped_to_pi_is_unwrapped(
        tmp_path: Path, cli: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A continuous joint whose driver reports its position wrapped into (−π, π]: across the
    wrap the angle between two reports must not swing back through a whole turn."""
    import math

    import test_bag_import

    yaw0 = 0.91 * math.pi  # from 163.8°: the position wraps at 0.27 s, within a scan
    scan = test_bag_import.ros_scan
    monkeypatch.setattr(test_bag_import, "ros_scan",
                        lambda r, t, yaw: scan(r, t, yaw + yaw0))

    def wrapped(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = []
        for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
            if topic == "/joint_states":
                psi = yaw0 + msg.position[0]
                msg.position[0] = (psi + math.pi) % (2 * math.pi) - math.pi
            out.append((topic, msgtype, t, msg))
        return out

    bag = write_bag(tmp_path, "mcap", wrapped)
    out = tmp_path / "rec.mcap"
    assert cli("import-bag", bag, "--out", out).code == 0
    assert cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q").code == 0
    _, truth, _ = scan(DEFAULT_R_PL, np.zeros(3), yaw0)
    check_against_truth(assembled(tmp_path / "w"), truth)


def test_non_finite_joint_positions_are_left_out_with_a_warning(
        tmp_path: Path, cli: Any) -> None:
    """A driver reporting NaN for an unhomed joint now and then: np.unwrap spread one NaN to
    every later angle (the bag was refused as "reaching nan°"); the reports are left out."""
    def with_nans(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = []
        for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
            if topic == "/joint_states" and round(t * 100) % 37 == 5:
                msg.position[0] = float("nan")
            out.append((topic, msgtype, t, msg))
        return out

    bag = write_bag(tmp_path, "mcap", with_nans)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out, "--json")
    assert result.code == 0, result.err
    warnings = json.loads(result.out)["warnings"]
    assert any("turntable on /joint_states: 9 reports with a non-finite position" in w
               for w in warnings), warnings
    assert cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q").code == 0
    _, truth, _ = ros_scan(DEFAULT_R_PL, np.zeros(3), 0.0)
    check_against_truth(assembled(tmp_path / "w"), truth)


def test_a_cut_bag_whose_copy_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    """The complete chunks of a cut MCAP bag are copied into a scratch folder; a scratch disk
    that cannot take them (full, or a file size limit: here a real RLIMIT_FSIZE) is one line
    naming the bag and where, not a traceback, and no recording is left."""
    import os
    import resource
    import signal
    import subprocess
    import sys

    import scanpipe

    bag = write_bag(tmp_path, "mcap", padded)
    file = storage_file(bag)
    whole = file.read_bytes()
    file.write_bytes(whole[:int(len(whole) * 0.6)])
    out = tmp_path / "rec.mcap"
    limit = 4096  # smaller than the copy

    def limited() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past it fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    env = {**os.environ, "PYTHONPATH": str(Path(scanpipe.__file__).parents[1]),
           "PYTHONDONTWRITEBYTECODE": "1", "TMPDIR": str(tmp_path)}
    result = subprocess.run([sys.executable, "-m", "scanpipe.cli.main", "import-bag", str(bag),
                             "--out", str(out)], env=env, capture_output=True, text=True,
                            preexec_fn=limited, timeout=120)
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith(f"scanpipe: error: {file}: its complete chunks cannot be "
                                    "copied"), result.stderr
    assert "TMPDIR" in result.stderr
    assert not out.exists()
