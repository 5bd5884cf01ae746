"""``import-bag``: what a LaserScan's numbers mean beyond the common case — range_max as a
driver's no-return sentinel (not REP 117's +inf), and a negative time_increment (beams taken
from the last angle to the first) on a platform that turns during each scan."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from test_bag_import import (
    ANGLE_MIN,
    DEFAULT_R_PL,
    INC,
    OMEGA,
    PROFILES,
    SAMPLES,
    SCAN_TIME,
    _header,
    assembled,
    box_range,
    check_against_truth,
    rz,
    turntable_messages,
    write_bag,
)


def test_range_max_is_a_no_return(tmp_path: Path, cli: Any) -> None:
    """LMS1xx's driver (by default) and Gazebo's laser plugin publish range_max for no echo:
    taken as ranges they made a phantom wall on a sphere of radius range_max."""
    def messages(ts: Any) -> list[Any]:
        out = turntable_messages(ts, "joint")
        for _, msgtype, _, msg in out:
            if msgtype == "sensor_msgs/msg/LaserScan":
                msg.ranges[10:20] = msg.range_max
        return out

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    assert f"/scan: {10 * PROFILES} ranges equal to range_max (30 m) taken as no return" \
        in result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    points = assembled(tmp_path / "w")
    sentinel = (points["sample"] >= 10) & (points["sample"] < 20)
    assert np.isnan(points["range_m"][sentinel]).all()
    assert np.nanmax(points["range_m"]) < 10.0


def test_negative_time_increment_places_each_beam_at_its_own_time(tmp_path: Path,
                                                                  cli: Any) -> None:
    """Beams taken last-to-first (ranges[0] at the stamp, ranges[i] at stamp + i·dt, dt < 0):
    spread forward from the stamp they were placed up to 2.25° of platform turn off (12 cm
    at 3 m)."""
    dt = SCAN_TIME * INC / (2 * math.pi)
    theta = ANGLE_MIN + np.arange(SAMPLES) * INC
    beams = np.stack([np.cos(theta), np.sin(theta), np.zeros(SAMPLES)], -1)
    truth = np.zeros((PROFILES, SAMPLES, 3))
    ranges = []
    for p in range(PROFILES):
        t = p * SCAN_TIME + (SAMPLES - 1 - np.arange(SAMPLES)) * dt  # the last beam first
        rot = np.stack([rz(OMEGA * a) for a in t])
        direction = np.einsum("sij,jk,sk->si", rot, DEFAULT_R_PL, beams)
        r = box_range(np.zeros(3), direction)
        ranges.append(r.astype(np.float32))
        truth[p] = r[:, None] * direction

    def messages(ts: Any) -> list[Any]:
        out = [m for m in turntable_messages(ts, "joint")
               if m[1] != "sensor_msgs/msg/LaserScan"]
        scan = ts.types["sensor_msgs/msg/LaserScan"]
        for p, r in enumerate(ranges):
            stamp = p * SCAN_TIME + (SAMPLES - 1) * dt  # ranges[0]'s time
            out.append(("/scan", "sensor_msgs/msg/LaserScan", stamp, scan(
                header=_header(ts, stamp, "laser"), angle_min=ANGLE_MIN,
                angle_max=ANGLE_MIN + (SAMPLES - 1) * INC, angle_increment=INC,
                time_increment=-dt, scan_time=SCAN_TIME, range_min=0.05, range_max=30.0,
                ranges=r, intensities=np.full(SAMPLES, 100.0, np.float32))))
        return sorted(out, key=lambda m: m[2])

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    check_against_truth(assembled(tmp_path / "w"), truth)


def test_point_cloud_only_bag_is_refused_with_the_way_on(tmp_path: Path, cli: Any) -> None:
    """laser_assembler's output: PointCloud2 of assembled scans, no LaserScan."""
    def messages(ts: Any) -> list[Any]:
        cloud = ts.types["sensor_msgs/msg/PointCloud2"]
        field = ts.types["sensor_msgs/msg/PointField"]
        fields = [field(name=n, offset=4 * i, datatype=7, count=1)
                  for i, n in enumerate("xyz")]
        return [("/assembled_cloud", "sensor_msgs/msg/PointCloud2", 0.1 * k, cloud(
            header=_header(ts, 0.1 * k, "base"), height=1, width=2, fields=fields,
            is_bigendian=False, point_step=12, row_step=24,
            data=np.zeros(24, np.uint8), is_dense=True)) for k in range(3)]

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1
    assert "found: /assembled_cloud (sensor_msgs/PointCloud2, 3)" in result.err
    assert "use scanpipe import-points" in result.err and result.err.count("\n") == 1
    assert not out.exists()
