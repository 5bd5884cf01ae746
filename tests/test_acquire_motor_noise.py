"""Line noise on the motor controller's serial link (a real pty to the controller emulator): a
digit changed in a position report, bytes of noise before a reply. The link has no checksum; the
recording must neither place profiles at a wrong platform angle nor fail for one lost reply."""

from __future__ import annotations

import contextlib
import os
import random
from pathlib import Path
from typing import Any

import pytest
from acquire_helpers import record_against, sim_options

from scanpipe.recording.reader import read_recording
from scanpipe.sim.emulators import MotorEmulator, VirtualRig
from scanpipe.sim.room import box_room


def _noisy_controller(monkeypatch: pytest.MonkeyPatch, kind: str) -> set[tuple[int, int]]:
    """Corrupt the controller's lines: ``flip`` changes one digit of the count in 3 % of the
    position reports (the line still parses), ``noise`` puts printable noise (with or without
    its own line end) before 3 % of the lines and raw bytes between 5 % of the sends. Returns
    the (count, time) of every report the controller really sent."""
    rng = random.Random(5)
    sent: set[tuple[int, int]] = set()
    send = MotorEmulator._send

    def noisy(self: MotorEmulator, lines: list[str]) -> None:
        out = []
        for line in lines:
            fields = line.split()
            if fields and fields[0] == "POS":
                sent.add((int(fields[1]), int(fields[4])))
            if rng.random() < (0.03 if kind == "flip" and fields[0] == "POS" else
                               0.03 if kind == "noise" else 0.0):
                if kind == "flip":
                    digits = list(fields[1])
                    at = rng.randrange(len(digits))
                    if digits[at].isdigit():
                        digits[at] = str((int(digits[at]) + rng.randrange(1, 10)) % 10)
                    fields[1] = "".join(digits)
                    line = " ".join(fields)
                else:
                    line = ("".join(chr(rng.randrange(33, 127))
                                    for _ in range(rng.randrange(1, 20)))
                            + ("\n" if rng.random() < 0.5 else "") + line)
            out.append(line)
        if kind == "noise" and rng.random() < 0.05:
            with contextlib.suppress(OSError):
                os.write(self._master, bytes(rng.randrange(256) for _ in range(12)))
        send(self, out)

    monkeypatch.setattr(MotorEmulator, "_send", noisy)
    return sent


@pytest.mark.parametrize(("kind", "mode"), [("flip", "continuous"), ("flip", "step"),
                                            ("noise", "step")])
def test_line_noise_on_the_motor_link(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                      kind: str, mode: str) -> None:
    sent = _noisy_controller(monkeypatch, kind)
    out = tmp_path / "rec.mcap"
    with VirtualRig(sim_options("ldoem", mode, pulse_limit=4000), speedup=4.0,
                    scene=box_room()) as rig:
        summary: dict[str, Any] = record_against(rig, out)
    assert summary["status"] == "complete", summary
    motor = read_recording(out).motor
    recorded = set(zip(motor.step_count.tolist(), motor.device_time_us.tolist(), strict=True))
    # No changed count became a state, but for a change as small as the ramp and rounding
    # allow (a last digit; the link has no checksum to tell): at most 8 pulses, 0.29°.
    true_at = {t: c for c, t in sent}
    off = [abs(c - true_at[t]) for c, t in recorded - sent]
    assert max(off, default=0) <= 8, sorted(off)
    if kind == "flip":
        assert summary["events"].get("motor_reports_rejected") == 1
