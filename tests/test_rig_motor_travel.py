"""``motor.pulse_limit`` is a strict whole number within what a cabled platform turns;
``motor.unlimited_travel = true`` is the explicit way to say the platform turns freely."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from scanpipe.errors import RigError
from scanpipe.rig import MAX_LIMITED_TRAVEL_DEG, load_rig, rig_to_toml


def _write(tmp_path: Path, motor: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(f"[motor]\n{motor}\n")
    return path


@pytest.mark.parametrize(("motor", "message"), [
    ("pulse_limit = 1e17", "motor.pulse_limit = 1e+17: must be a whole number of pulses "
                           "(1 … 2147483647), not a float"),
    ("pulse_limit = true", "motor.pulse_limit = true: must be a whole number of pulses "
                           "(1 … 2147483647), not a boolean"),
    ("pulse_limit = 5000.0", "motor.pulse_limit = 5000.0: must be a whole number"),
    ("pulse_limit = 100000000000000000",
     "motor.pulse_limit = 100000000000000000: more pulses than a controller counts"),
    ("pulse_limit = 20001", "motor.pulse_limit = 20001: 720.036° of travel (20001 × 0.036°) is "
                            "more than 720° (two platform turns)"),
    ("gear_ratio = 100\npulse_limit = 100001", "give at most 100000 pulses, or set "
                                               "motor.unlimited_travel = true"),
    ("pulse_limit = 0", "motor.pulse_limit = 0"),
    ("unlimited_travel = 'yes'", "motor.unlimited_travel = \"yes\""),
    ("unlimited_travel = 1", "motor.unlimited_travel = 1"),
])
def test_bad_pulse_limits_are_refused_in_one_line(
        tmp_path: Path, cli: Callable[..., Any], motor: str, message: str) -> None:
    path = _write(tmp_path, motor)
    with pytest.raises(RigError) as info:
        load_rig(path)
    assert message in str(info.value)
    result = cli("rig", "check", path)
    assert result.code == 2
    assert message in result.err and "Traceback" not in result.err
    assert len(result.err.strip().splitlines()) == 1
    assert path.read_text() == f"[motor]\n{motor}\n"  # the file is left as it was


def test_record_refuses_such_a_rig_before_touching_anything(
        tmp_path: Path, cli: Callable[..., Any]) -> None:
    path = _write(tmp_path, "pulse_limit = true")
    out = tmp_path / "scan.mcap"
    out.write_bytes(b"an earlier recording")
    result = cli("record", "--out", out, "--rig", path, "--force", "--quiet")
    assert result.code == 2 and "motor.pulse_limit = true" in result.err
    assert out.read_bytes() == b"an earlier recording"


def test_the_bound_is_two_platform_turns(tmp_path: Path) -> None:
    assert MAX_LIMITED_TRAVEL_DEG == 720.0
    rig = load_rig(_write(tmp_path, "pulse_limit = 20000"))  # 720° at 0.036°: allowed
    assert rig.motor.travel_limit == 20000


def test_an_unlimited_rig_says_so_and_round_trips(tmp_path: Path) -> None:
    rig = load_rig(_write(tmp_path, "unlimited_travel = true\npulse_limit = 30000"))
    assert rig.motor.unlimited_travel and rig.motor.travel_limit is None
    assert rig.motor.pulse_limit == 30000  # the sweep of one scan (1080°)
    text = rig_to_toml(rig)
    assert "unlimited_travel = true" in text and "slip ring" in text
    again = tmp_path / "again.toml"
    again.write_text(text)
    assert load_rig(again) == rig


def test_the_default_rig_is_limited() -> None:
    rig = load_rig(None)
    assert not rig.motor.unlimited_travel and rig.motor.travel_limit == 5000
