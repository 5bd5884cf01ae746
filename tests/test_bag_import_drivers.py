"""import-bag on LaserScans as real drivers fill them: intensities normalised to 0…1 (kept
as fractions of the echo's range, not rounded to 0 or 1), and LDRobot's ROS driver, whose
angle_increment follows the measured motor speed scan by scan (refused with its reason)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
from test_bag_import import SAMPLES, _header, turntable_messages, write_bag

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


def test_ldrobot_driver_speed_dependent_step_is_refused_with_its_reason(
        tmp_path: Path, cli: Any) -> None:
    def messages(ts: Any) -> list[tuple[str, str, float, Any]]:
        out = []
        for k, (topic, msgtype, t, msg) in enumerate(turntable_messages(ts, "joint")):
            if msgtype.endswith("LaserScan"):
                # ldlidar_stl_ros2: angle_increment = spin speed / point rate, per scan.
                speed = 3600.0 * (1.0 + 0.01 * math.sin(k))
                msg.angle_increment = math.radians(speed / 4500.0)
                msg.header = _header(ts, t, "laser")
            out.append((topic, msgtype, t, msg))
        return out
    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "rec.mcap"
    result = cli("import-bag", bag, "--out", out)
    assert result.code == 1 and result.err.count("\n") == 1, result.err
    assert "angle_increment changes during the bag" in result.err
    assert "motor speed" in result.err and "import-capture" in result.err
    assert not out.exists()
