"""import-bag on LaserScans as real drivers fill them: intensities normalised to 0…1 (kept
as fractions of the echo's range, not rounded to 0 or 1), and LDRobot's ROS driver, whose
angle_increment follows the measured motor speed scan by scan (resampled onto one grid; two
settings in one bag refused)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
from test_bag_import import (
    ANGLE_MIN,
    BOX_HI,
    BOX_LO,
    DEFAULT_R_PL,
    INC,
    OMEGA,
    PROFILES,
    SAMPLES,
    SCAN_TIME,
    _header,
    assembled,
    box_range,
    rz,
    turntable_messages,
    write_bag,
)

from scanpipe.bagio import G

RNG = np.random.default_rng(5)


def with_intensities(values: np.ndarray) -> Any:
    def messages(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = []
        for topic, msgtype, t, msg in turntable_messages(ts, "joint"):
            if msgtype.endswith("LaserScan"):
                msg.intensities = values.astype(np.float32)
            out.append((topic, msgtype, t, msg))
        return out
    return messages


def test_intensities_as_fractions_become_the_echo_range(tmp_path: Path, cli: Any) -> None:
    fractions = RNG.uniform(0.0, 1.0, SAMPLES)
    bag = write_bag(tmp_path, "ros1", with_intensities(fractions))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    assert "0…1" in result.err
    assert cli("decode", out, "--out", tmp_path / "dec", "-q").code == 0
    echo = pq.read_table(tmp_path / "dec" / "profiles.parquet").column("echo").to_pylist()[0]
    np.testing.assert_allclose(echo, fractions.astype(np.float32) * 65535.0, atol=1.0)


def test_raw_intensities_are_kept_as_they_are(tmp_path: Path, cli: Any) -> None:
    raw = RNG.integers(0, 4000, SAMPLES).astype(np.float64)
    bag = write_bag(tmp_path, "ros1", with_intensities(raw))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0 and "0…1" not in result.err, result.err
    assert cli("decode", out, "--out", tmp_path / "dec", "-q").code == 0
    echo = pq.read_table(tmp_path / "dec" / "profiles.parquet").column("echo").to_pylist()[0]
    np.testing.assert_array_equal(echo, raw)


def ldrobot_driver_messages(spread: float) -> Any:
    """A turntable scan as LDRobot's ldlidar ROS drivers publish it: angle_increment = the
    head's measured speed ÷ the sample rate, angle_min = the first sample's angle, as many
    samples as fit the span; ranges true at each sample's own angle (the box room)."""
    def messages(ts: Any) -> list[tuple[str, str, float, Any]]:
        scan_type = ts.types["sensor_msgs/msg/LaserScan"]
        out = []
        for k, (topic, msgtype, t, msg) in enumerate(turntable_messages(ts, "joint")):
            if msgtype.endswith("LaserScan"):
                speed = 3600.0 * (1.0 + spread * math.sin(k))
                inc = math.radians(speed / 7200.0)  # 0.5° at 3600°/s
                angle_min = ANGLE_MIN + math.radians(RNG.uniform(-0.3, 0.3))
                n = math.ceil((SAMPLES - 1) * INC / inc)
                theta = angle_min + np.arange(n) * inc
                beams = np.stack([np.cos(theta), np.sin(theta), np.zeros(n)], -1)
                dt = SCAN_TIME * inc / (2 * math.pi)  # the head turns once per SCAN_TIME
                rot = np.stack([rz(OMEGA * (t + i * dt)) for i in range(n)])
                ranges = box_range(np.zeros((n, 3)),
                                   np.einsum("sij,jk,sk->si", rot, DEFAULT_R_PL, beams))
                msg = scan_type(
                    header=_header(ts, t, "laser"), angle_min=angle_min,
                    angle_max=angle_min + (n - 1) * inc, angle_increment=inc,
                    time_increment=dt, scan_time=SCAN_TIME, range_min=0.05,
                    range_max=30.0, ranges=ranges.astype(np.float32),
                    intensities=np.arange(n, dtype=np.float32))
            out.append((topic, msgtype, t, msg))
        return out
    return messages


def test_ldrobot_driver_speed_dependent_step_is_resampled_onto_one_grid(
        tmp_path: Path, cli: Any) -> None:
    # Refused before (LD06/LD19 bags could not be used at all); every scan now lands on one
    # grid, and each assembled point still lies on the room's walls.
    bag = write_bag(tmp_path, "ros1", ldrobot_driver_messages(0.01))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 0, result.err
    assert "every scan resampled onto one grid of 541 beams of 0.499" in result.err
    result = cli("run", out, "--workdir", tmp_path / "w", "--to", "assemble", "-q")
    assert result.code == 0, result.err
    points = assembled(tmp_path / "w")
    ros = np.stack([points[c].astype(np.float64) for c in ("x", "y", "z")], -1) @ G
    valid = np.isfinite(ros).all(axis=1)
    assert valid.sum() >= PROFILES * SAMPLES * 0.98
    # distance to the nearest wall: linear between neighbours on a wall, nearer at corners
    to_wall = np.minimum(np.abs(ros[valid] - BOX_LO), np.abs(BOX_HI - ros[valid])).min(axis=1)
    assert float(np.median(to_wall)) < 1e-4 and float(np.quantile(to_wall, 0.99)) < 5e-3


def test_resampling_keeps_depth_jumps_and_leaves_no_sample_made_up() -> None:
    from scanpipe.bagio import on_one_beam_grid
    from scanpipe.recording import schemas

    def profile(start: float, step: float, ranges: list[float]) -> Any:
        return (0, schemas.Profile(device_time_ns=0, device_end_time_ns=0, frame=0,
                                   start_angle_deg=start, step_deg=step, ranges_m=ranges,
                                   intensities=list(range(len(ranges)))))
    # a wall at 2 m, a jump to 5 m between samples 3 and 4; the second scan's step is 2 % off
    a = profile(0.0, 1.0, [2.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0])
    b = profile(0.0, 1.02, [2.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0])
    c = profile(0.0, 0.98, [2.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0])
    warning = on_one_beam_grid([a, b, c])
    assert "7 beams of 1°" in warning
    for _, p in (a, b, c):
        assert p.start_angle_deg == 0.0 and p.step_deg == 1.0
        assert set(np.round(p.ranges_m[:7], 6)) <= {2.0, 5.0, float("nan")} or \
            np.isnan(p.ranges_m).any()
        finite = np.asarray(p.ranges_m)[np.isfinite(p.ranges_m)]
        assert set(finite.tolist()) <= {2.0, 5.0}  # never a range between the two surfaces
    np.testing.assert_array_equal(a[1].ranges_m, [2.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0])
    # c's samples end at 5.88°: beam 6 is 0.12° past its last sample (kept: 5 m); a scan that
    # ends a step short leaves that beam unmeasured
    assert c[1].ranges_m[6] == 5.0
    short = profile(0.0, 1.0, [2.0, 2.0, 2.0, 2.0, 5.0])
    on_one_beam_grid([a, short, profile(0.0, 1.0, [2.0] * 7)])
    assert np.isnan(short[1].ranges_m[6]) and short[1].ranges_m[4] == 5.0
    assert list(short[1].intensities[:5]) == [0, 1, 2, 3, 4]


def test_a_scan_with_a_wider_step_keeps_every_beam_between_its_samples() -> None:
    # The review's case: a scan 4 % coarser than the median lost a comb of beams (NaN where a
    # grid beam fell mid-way between two good samples, more than half the median step away).
    from scanpipe.bagio import on_one_beam_grid
    from scanpipe.recording import schemas

    scans = [(0, schemas.Profile(device_time_ns=0, device_end_time_ns=0, frame=k,
                                 start_angle_deg=0.0, step_deg=step, ranges_m=[2.0] * 200))
             for k, step in enumerate((1.0, 1.0, 1.04))]
    on_one_beam_grid(scans)
    coarse = np.asarray(scans[2][1].ranges_m)
    inside = np.arange(200) <= 199 * 1.04  # every grid beam within the scan's samples
    assert np.isfinite(coarse[inside]).all(), np.flatnonzero(~np.isfinite(coarse[inside]))


def test_a_later_non_finite_angle_increment_is_one_line(tmp_path: Path, cli: Any) -> None:
    def messages(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = ldrobot_driver_messages(0.01)(ts)
        scans = [m for m in out if m[1].endswith("LaserScan")]
        scans[3][3].angle_increment = float("nan")
        return out
    bag = write_bag(tmp_path, "ros1", messages)
    result = cli("import-bag", bag, "--out", tmp_path / "rec.mcap")
    assert result.code == 1 and result.err.count("\n") == 1, result.err
    assert "angle_increment nan°: only scans with a positive angle_increment" in result.err


def test_two_beam_steps_in_one_bag_are_refused(tmp_path: Path, cli: Any) -> None:
    bag = write_bag(tmp_path, "ros1", ldrobot_driver_messages(0.2))
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1 and result.err.count("\n") == 1, result.err
    assert "angle_increment changes during the bag" in result.err and "5%" in result.err
    assert not out.exists()
