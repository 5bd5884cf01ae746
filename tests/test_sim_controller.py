"""The motor controller firmware (docs/motor-link.md) and the ldoem device, without I/O."""

from __future__ import annotations

import itertools
from typing import Literal

import pytest

from scanpipe.protocol import ldoem
from scanpipe.rig import MotorConfig, ScannerConfig
from scanpipe.sim.controller import MotorController
from scanpipe.sim.ldoem_device import LdoemDevice
from scanpipe.sim.motion import PlatformState


def _controller(limit: int = 5000, controller_limit: int | Literal["rig"] | None = "rig"
                ) -> tuple[MotorController, PlatformState]:
    motor = MotorConfig(pulse_limit=limit)
    platform = PlatformState(motor.pulse_step_deg)
    return MotorController(motor, platform, report_interval_s=0.02,
                           pulse_limit=controller_limit), platform


def test_move_past_the_limit_is_refused_and_nothing_moves() -> None:
    controller, platform = _controller(limit=100)
    assert controller.handle("MOVE +60", 0.0) == ["OK 60", "POS 0 60 1 0"]
    controller.reports_until(5.0)
    assert controller.handle("MOVE +41", 5.0) == ["ERR LIMIT absolute 60+41 = 101 outside 0..100"]
    assert controller.handle("MOVE -61", 5.0)[0].startswith("ERR LIMIT")
    assert not platform.moving_at(5.5) and platform.count_at(9.0) == 60
    assert controller.reports_until(9.0) == []
    assert controller.handle("MOVE +40", 9.0)[0] == "OK 100"  # exactly to the limit is fine


def test_move_reports_positions_then_a_final_report() -> None:
    controller, _ = _controller()
    controller.handle("MOVE +100", 1.0)
    reports = controller.reports_until(10.0)
    counts = [int(r.line.split()[1]) for r in reports]
    assert counts == sorted(counts) and counts[-1] == 100
    assert all(r.line.split()[3] == "1" for r in reports[:-1])
    assert reports[-1].line.split()[2:4] == ["100", "0"]
    spacing = [b.time_s - a.time_s for a, b in itertools.pairwise(reports[:-1])]
    assert all(s == pytest.approx(0.02) for s in spacing)
    assert controller.next_report_s() == float("inf")


def test_busy_stop_zero_and_queries() -> None:
    controller, platform = _controller()
    controller.handle("RATE 200", 0.0)
    assert controller.handle("MOVE +1000", 0.0)[0] == "OK 1000"
    assert controller.handle("MOVE +1", 1.0)[0].startswith("ERR BUSY")
    assert controller.handle("ZERO", 1.0)[0].startswith("ERR BUSY")
    pos = controller.handle("POS?", 1.0)
    assert pos[0].startswith("POS ") and pos[1] == "OK"
    stopped = controller.handle("STOP", 2.0)
    count = int(stopped[-1].split()[1])
    assert stopped[0].split()[3] == "0" and 0 < count < 1000
    assert platform.count_at(5.0) == count
    assert controller.handle("ZERO", 5.0) == ["OK 0"]
    assert controller.handle("POS?", 5.0)[0].split()[1:4] == ["0", "0", "0"]


@pytest.mark.parametrize(("line", "reply"), [
    ("MOVE", "ERR SYNTAX"), ("MOVE x", "ERR SYNTAX"), ("RATE -5", "ERR RANGE"),
    ("ACCEL abc", "ERR SYNTAX"), ("JUMP 3", "ERR UNKNOWN"), ("ID?", "ID scanpipe-motor 2 5000"),
    ("TRAVEL?", "TRAVEL 0 0 5000"),
    ("rate 500", "OK 500"),
])
def test_command_replies(line: str, reply: str) -> None:
    controller, _ = _controller()
    assert controller.handle(line, 0.0)[0].startswith(reply)


def _finish(controller: MotorController, time_s: float) -> float:
    """Let the move under way end; the time after it."""
    controller.reports_until(time_s + 100.0)
    return time_s + 100.0


def test_zero_does_not_reset_the_travel_the_limit_holds_on() -> None:
    # The issue: MOVE +5000, ZERO, MOVE +5000, ZERO, MOVE +5000 turned the platform 540°.
    controller, platform = _controller()
    t = 0.0
    assert controller.handle("MOVE +5000", t)[0] == "OK 5000"
    t = _finish(controller, t)
    assert controller.handle("ZERO", t) == ["OK 0"]
    assert controller.handle("TRAVEL?", t) == ["TRAVEL 5000 5000 5000", "OK"]
    assert controller.handle("POS?", t)[0].split()[1] == "0"  # POS counts from the new origin
    assert controller.handle("MOVE +5000", t) == [
        "ERR LIMIT absolute 5000+5000 = 10000 outside 0..5000"]
    assert controller.handle("MOVE +1", t)[0].startswith("ERR LIMIT")
    assert platform.timeline().count_at(t + 50) == 5000  # nothing moved
    # Back below the new origin is fine (negative counts), down to home and no further.
    assert controller.handle("MOVE -5000", t)[0] == "OK -5000"
    t = _finish(controller, t)
    assert controller.handle("MOVE -1", t)[0] == "ERR LIMIT absolute 0-1 = -1 outside 0..5000"
    assert controller.handle("TRAVEL?", t)[0] == "TRAVEL 0 5000 5000"


def test_an_unlimited_controller_turns_any_amount() -> None:
    controller, platform = _controller(controller_limit=None)
    assert controller.handle("ID?", 0.0)[0] == "ID scanpipe-motor 2 unlimited"
    t = 0.0
    for _ in range(3):
        assert controller.handle("MOVE +5000", t)[0].startswith("OK")
        t = _finish(controller, t)
        controller.handle("ZERO", t)
    assert controller.handle("TRAVEL?", t)[0] == "TRAVEL 15000 15000 unlimited"
    assert platform.beta_deg_at(t)[()] == pytest.approx(540.0)


def test_a_controller_limit_other_than_the_rigs() -> None:
    controller, _ = _controller(limit=5000, controller_limit=400)
    assert controller.handle("ID?", 0.0)[0] == "ID scanpipe-motor 2 400"
    assert controller.handle("MOVE +401", 0.0)[0].startswith("ERR LIMIT absolute 0+401")


def _payload(frame: bytes) -> bytes:
    return frame[8:-1]


def test_ldoem_device_answers_and_refuses_like_the_device() -> None:
    device = LdoemDevice(ScannerConfig(beam_step_deg=0.25, scan_hz=5))
    ident = ldoem.parse_payload(_payload(device.handle(_payload(ldoem.get_ident_request()),
                                                      0)[0]))
    assert ident.is_reply and ident.body.startswith(b"LD-OEM1000")
    refused = ldoem.parse_payload(_payload(device.handle(_payload(ldoem.rotate_request(25)),
                                                         0)[0]))
    assert refused.body.startswith(b"\xff\xff") and b"5..20" in refused.body
    # 8 Hz at 0.25° is 11 520 Hz: above the 10 800 Hz mean pulse limit over 360°
    assert device.handle(_payload(ldoem.rotate_request(8)), 0)[0][10:12] == b"\xff\xff"
    assert device.handle(_payload(ldoem.rotate_request(6)), 0) == [
        ldoem.reply(ldoem.SERVICE_WORKING, ldoem.WORKING_ROTATE)]
    assert device.scan_hz == 6
    assert device.handle(_payload(ldoem.get_profile_request(3, ldoem.MASK_RANGES_ECHO)), 0) == []
    assert device.stream is not None and device.stream.count == 3
    assert device.handle(_payload(ldoem.cancel_profile_request()), 0) == [
        ldoem.reply(ldoem.SERVICE_MEASURE, ldoem.CANCEL_PROFILE)]
    assert device.stream is None
    bad_step = ldoem.request(
        ldoem.SERVICE_CONFIG, ldoem.SET_CONFIG, (3).to_bytes(2, "big") + (0).to_bytes(2, "big")
        + (5760).to_bytes(2, "big"))
    assert b"multiple of 0.125" in device.handle(_payload(bad_step), 0)[0]


def test_ldoem_device_clock_can_be_set_and_shifted() -> None:
    device = LdoemDevice(ScannerConfig())

    def clock(now_ms: int) -> int:
        reply = device.handle(_payload(ldoem.get_sync_clock_request()), now_ms)[0]
        return ldoem.parse_payload(_payload(reply)).u16(0)

    assert clock(1000) == 1000
    device.handle(_payload(ldoem.set_time_abs_request(40000)), 1000)
    assert clock(1500) == 40500
    device.handle(_payload(ldoem.set_time_rel_request(-500)), 1500)
    assert clock(1500) == 40000
