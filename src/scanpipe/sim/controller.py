"""The motor controller's firmware, as a pure state machine (the motor link: docs/motor-link.md).

:class:`MotorController` answers command lines at a given simulation time and produces the
periodic position reports of a move. The pty emulator (:mod:`scanpipe.sim.emulators`) and
direct mode (:mod:`scanpipe.sim.direct`) both drive it, so both put the same bytes on the link.

The travel limit holds on the ABSOLUTE position: pulses from where the platform stood at power-on
(the creation of the controller). ``ZERO`` only moves the user origin that ``POS`` counts from;
no sequence of ``ZERO`` and ``MOVE`` takes the platform past the limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from scanpipe.rig import MotorConfig
from scanpipe.sim.motion import Move, PlatformState

#: The highest pulse rate the firmware accepts (RATE) and the highest ramp (ACCEL).
MAX_RATE_HZ = 100_000.0
MAX_ACCEL_HZ_PER_S = 1_000_000.0
#: Version 2: the limit holds on the absolute position (version 1 checked the count since ZERO)
#: and ``TRAVEL?`` reports it.
FIRMWARE_ID = "scanpipe-motor 2"
#: How ``ID?`` and ``TRAVEL?`` write the limit of a controller that has none (a slip ring).
UNLIMITED = "unlimited"


@dataclass(frozen=True)
class ControllerReport:
    """A line the controller sends on its own (a position report) at ``time_s``."""

    time_s: float
    line: str


class MotorController:
    """Counts pulses, refuses moves whose absolute target leaves ``0 … limit``, reports positions.

    ``pulse_limit`` is the firmware's own travel limit: ``"rig"`` takes the motor's
    (:attr:`MotorConfig.travel_limit`: none when ``unlimited_travel``), an int sets another
    one (a controller that disagrees with the rig file), ``None`` makes a controller without
    limit (a platform on a slip ring).
    """

    def __init__(self, motor: MotorConfig, platform: PlatformState,
                 report_interval_s: float = 0.02, clock_origin_us: int = 0,
                 pulse_limit: int | Literal["rig"] | None = "rig") -> None:
        self.motor = motor
        self.pulse_limit = motor.travel_limit if pulse_limit == "rig" else pulse_limit
        self.platform = platform
        self.report_interval_s = report_interval_s
        self.clock_origin_us = clock_origin_us
        self.rate_hz = motor.pulse_rate_hz
        self.accel_hz_per_s = motor.accel_hz_per_s
        self._move: Move | None = None
        self._target = 0
        self._next_report_s = math.inf
        self._final_pending = False

    # -- state -----------------------------------------------------------------------------
    def device_time_us(self, time_s: float) -> int:
        """The controller's microsecond clock."""
        return self.clock_origin_us + round(time_s * 1e6)

    def absolute_at(self, time_s: float) -> int:
        """Pulses from the power-on position at ``time_s`` (what the limit is checked on)."""
        return self.platform.timeline().count_at(time_s)

    def limit_text(self) -> str:
        """The limit as ``ID?`` and ``TRAVEL?`` write it."""
        return UNLIMITED if self.pulse_limit is None else str(self.pulse_limit)

    def travel_line(self, time_s: float) -> str:
        """``TRAVEL <absolute> <origin> <limit|unlimited>``: origin is the absolute position of
        count 0 (the last ZERO), so count = absolute − origin."""
        absolute = self.absolute_at(time_s)
        origin = absolute - self.platform.count_at(time_s)
        return f"TRAVEL {absolute} {origin} {self.limit_text()}"

    def position_line(self, time_s: float) -> str:
        """``POS <count> <target> <moving 0|1> <time_us>``."""
        count = self.platform.count_at(time_s)
        moving = self.platform.moving_at(time_s)
        target = self._target if moving else count
        return f"POS {count} {target} {int(moving)} {self.device_time_us(time_s)}"

    def moving(self, time_s: float) -> bool:
        """Whether a move is under way at ``time_s``."""
        return self.platform.moving_at(time_s)

    # -- commands --------------------------------------------------------------------------
    def handle(self, line: str, time_s: float) -> list[str]:
        """The reply lines (without line ends) to one command line received at ``time_s``.

        Call :meth:`reports_until` first so that reports due before ``time_s`` come first.
        """
        words = line.strip().split()
        if not words:
            return []
        name, args = words[0].upper(), words[1:]
        busy = self.moving(time_s)
        if name in ("POS?", "POS"):
            return [self.position_line(time_s), "OK"]
        if name == "ID?" or name == "ID":
            return [f"ID {FIRMWARE_ID} {self.limit_text()}", "OK"]
        if name in ("TRAVEL?", "TRAVEL"):
            return [self.travel_line(time_s), "OK"]
        if name == "STOP":
            count = self.platform.stop(time_s)
            was_moving = self._final_pending
            self._final_pending = False
            self._next_report_s = math.inf
            self._target = count
            lines = [self.position_line(time_s)] if was_moving else []
            return [*lines, f"OK {count}"]
        if name in ("MOVE", "RATE", "ACCEL", "ZERO") and busy:
            return [f"ERR BUSY moving to {self._target}; send STOP first"]
        if name == "ZERO":
            self.platform.zero(time_s)
            self._target = 0
            return ["OK 0"]
        if name in ("RATE", "ACCEL"):
            return self._set_rate(name, args)
        if name == "MOVE":
            return self._move_command(args, time_s)
        return [f"ERR UNKNOWN command {words[0]!r}"]

    def _set_rate(self, name: str, args: list[str]) -> list[str]:
        upper = MAX_RATE_HZ if name == "RATE" else MAX_ACCEL_HZ_PER_S
        try:
            value = float(args[0])
        except (IndexError, ValueError):
            return [f"ERR SYNTAX {name} needs a number"]
        if not 0 < value <= upper or not math.isfinite(value):
            return [f"ERR RANGE {name} {value:g} outside 0 < value <= {upper:g}"]
        if name == "RATE":
            self.rate_hz = value
        else:
            self.accel_hz_per_s = value
        return [f"OK {value:g}"]

    def _move_command(self, args: list[str], time_s: float) -> list[str]:
        try:
            pulses = int(args[0])
        except (IndexError, ValueError):
            return ["ERR SYNTAX MOVE needs a signed pulse count, e.g. MOVE +3"]
        count = self.platform.count_at(time_s)
        target = count + pulses
        absolute = self.absolute_at(time_s)
        if self.pulse_limit is not None and not 0 <= absolute + pulses <= self.pulse_limit:
            return [f"ERR LIMIT absolute {absolute}{pulses:+d} = {absolute + pulses} outside "
                    f"0..{self.pulse_limit}"]
        self._target = target
        if pulses == 0:
            return [f"OK {target}"]
        self._move = self.platform.start_move(time_s, pulses, self.rate_hz, self.accel_hz_per_s)
        self._next_report_s = time_s + self.report_interval_s
        self._final_pending = True
        # a report as the move starts: the host then knows the count held until this instant
        return [f"OK {target}", self.position_line(time_s)]

    # -- reports ---------------------------------------------------------------------------
    def reports_until(self, time_s: float) -> list[ControllerReport]:
        """Position reports due up to ``time_s``: every ``report_interval_s`` while moving,
        and one final report (moving = 0) when a move ends."""
        reports: list[ControllerReport] = []
        if self._move is None or not self._final_pending:
            return reports
        end_s = self._move.end_s
        while self._next_report_s < end_s and self._next_report_s <= time_s:
            at = self._next_report_s
            reports.append(ControllerReport(at, self.position_line(at)))
            self._next_report_s += self.report_interval_s
        if end_s <= time_s:
            reports.append(ControllerReport(end_s, self.position_line(end_s)))
            self._final_pending = False
            self._next_report_s = math.inf
        return reports

    def next_report_s(self) -> float:
        """When the next report falls due (inf when idle)."""
        if self._move is None or not self._final_pending:
            return math.inf
        return min(self._next_report_s, self._move.end_s)
