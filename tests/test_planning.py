"""The paper's step arithmetic (eq. 1–4) and the scan plan."""

from __future__ import annotations

import json
import math

import pytest

from scanpipe.errors import PlanError
from scanpipe.planning import choose_steps, frame_bytes, move_time_s, plan_scan
from scanpipe.rig import MotorConfig, Rig, ScannerConfig, default_rig

STEP = 0.036


def test_paper_example_six_degrees() -> None:
    choice = choose_steps(6.0, STEP, 5000)
    assert choice.pulse_step_deg == pytest.approx(0.036)
    assert choice.steps_per_turn == 10_000
    assert choice.requested_steps == pytest.approx(166.667)
    assert choice.possible_steps == (164, 165, 166, 167, 168)
    assert choice.possible_angles_deg == pytest.approx((5.904, 5.940, 5.976, 6.012, 6.048))
    assert choice.chosen_steps == 167  # 6.012° is 0.012° away, 5.976° is 0.024° away


def test_exact_multiple_is_not_floored_below() -> None:
    # 0.108 / 0.036 is 2.9999999999999996 in floating point: it means 3 steps.
    choice = choose_steps(0.108, STEP, 5000)
    assert choice.requested_steps == 3.0
    assert choice.chosen_steps == 3
    assert choice.possible_steps == (1, 2, 3, 4, 5)


def test_smallest_step_keeps_five_valid_offers() -> None:
    choice = choose_steps(0.036, STEP, 5000)
    assert choice.possible_steps == (1, 2, 3, 4, 5)
    assert choice.chosen_steps == 1
    tiny = choose_steps(0.001, STEP, 5000)
    assert tiny.chosen_steps == 1 and min(tiny.possible_steps) == 1


def test_limit_keeps_offers_within_pulse_limit() -> None:
    choice = choose_steps(180.0, STEP, 5000)
    assert choice.possible_steps == (4996, 4997, 4998, 4999, 5000)
    assert choice.chosen_steps == 5000


@pytest.mark.parametrize("angle", [0.0, -1.0, 180.01, math.nan, math.inf])
def test_bad_angles_are_refused(angle: float) -> None:
    with pytest.raises(PlanError):
        choose_steps(angle, STEP, 5000)


def test_paper_lab_scan_is_1667_by_1440() -> None:
    plan = plan_scan(default_rig(), 0.108)
    assert plan.profiles == 1667
    assert plan.samples_per_profile == 1440
    assert plan.points == 1667 * 1440
    assert plan.raw_bytes == 1667 * frame_bytes("ldoem", 1440)
    assert 4.5e6 < plan.raw_bytes < 5.0e6  # "~4.8 MB of frames" (issue 3)
    assert plan.travel_deg == pytest.approx(1666 * 0.108)
    assert all(c.ok for c in plan.device_limits)


def test_scan_time_at_seven_hz() -> None:
    rig = Rig(scanner=ScannerConfig(scan_hz=7))
    assert plan_scan(rig, 0.108).scan_time_s == pytest.approx(1667 / 7)


def test_device_limits_flag_too_fast_head() -> None:
    rig = Rig(scanner=ScannerConfig(scan_hz=8))  # 8 · 360 / 0.25 = 11520 Hz mean > 10800
    checks = {c.name: c.ok for c in plan_scan(rig, 6).device_limits}
    assert checks == {"scan_hz": True, "beam_step_deg": True, "pulse_hz": True,
                      "mean_pulse_hz": False}


def test_other_gearbox() -> None:
    rig = Rig(motor=MotorConfig(gear_ratio=10, pulse_limit=2500))
    plan = plan_scan(rig, 0.72)
    assert plan.steps.pulse_step_deg == pytest.approx(0.072)
    assert plan.motor_step_count == 10


def test_move_time_trapezoid_and_triangle() -> None:
    # 1000 pulses at 1000 Hz with 5000 Hz/s: 1 s cruising + 0.2 s of ramps.
    assert move_time_s(1000, 1000.0, 5000.0) == pytest.approx(1.2)
    assert move_time_s(0, 1000.0, 5000.0) == 0.0
    assert move_time_s(10, 1000.0, 5000.0) == pytest.approx(2 * math.sqrt(10 / 5000))


def test_cli_plan_json_gives_the_paper_angles(cli) -> None:  # type: ignore[no-untyped-def]
    result = cli("plan", "--motor-step", "6", "--json")
    assert result.code == 0
    data = json.loads(result.out)
    assert data["pulse_step_deg"] == pytest.approx(0.036)
    assert data["steps_per_turn"] == 10_000
    assert data["requested_steps"] == pytest.approx(166.667)
    assert data["possible_angles_deg"] == pytest.approx([5.904, 5.940, 5.976, 6.012, 6.048])


def test_cli_plan_text_marks_closest(cli) -> None:  # type: ignore[no-untyped-def]
    result = cli("plan", "--motor-step", "6")
    assert result.code == 0
    assert "6.012°  ← closest" in result.out
    assert "profiles            30" in result.out


@pytest.mark.parametrize(
    ("angle", "needle"),
    [("0", "greater than 0"), ("-3", "greater than 0"), ("181", "pulse limit"),
     ("abc", "valid number"), ("nan", "greater than 0")],
)
def test_cli_plan_bad_angle_is_one_line_exit_2(cli, angle: str, needle: str) -> None:  # type: ignore[no-untyped-def]
    result = cli("plan", f"--motor-step={angle}")
    assert result.code == 2
    assert needle in result.err
    assert result.err.count("\n") == 1 and "Traceback" not in result.err
    assert result.out == ""
