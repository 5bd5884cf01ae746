"""Step arithmetic (paper eq. 1–4), time and size estimates for a scan, checked against the
device limits (:mod:`scanpipe.device_limits`).

Everything here is pure arithmetic on the rig; the CLI only formats it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from scanpipe.device_limits import LimitCheck
from scanpipe.errors import PlanError
from scanpipe.rig import Rig
from scanpipe.scanner_models import limit_checks, model_label

#: The motor step of a scan when none is asked for: the paper's lab scan (3 pulses of 0.036°).
DEFAULT_MOTOR_STEP_DEG = 0.108
#: A requested step count within this of an integer counts as that integer (0.108 / 0.036 is
#: 2.9999999999999996 in binary floating point, and means 3 steps).
_STEP_EPSILON = 1e-9
@dataclass(frozen=True)
class StepChoice:
    """The achievable step counts around a requested angle (paper eq. 4 and the five offers)."""

    requested_motor_step_deg: float
    pulse_step_deg: float
    steps_per_turn: int
    requested_steps: float
    possible_steps: tuple[int, ...]
    possible_angles_deg: tuple[float, ...]
    closest_index: int

    @property
    def chosen_steps(self) -> int:
        """The step count whose angle is closest to the request."""
        return self.possible_steps[self.closest_index]


@dataclass(frozen=True)
class ScanPlan:
    """Everything the planner says about one scan with one rig and one motor step."""

    steps: StepChoice
    motor_step_count: int
    motor_step_deg: float
    travel_deg: float
    profiles: int
    samples_per_profile: int
    points: int
    frame_bytes: int
    raw_bytes: int
    scan_time_s: float
    step_and_scan_time_s: float
    device_limits: tuple[LimitCheck, ...] = field(default_factory=tuple)
    #: The scanner model whose limits these are ("LD-OEM" for the paper's rig).
    device_model: str = "LD-OEM"

    def to_json(self) -> dict[str, Any]:
        """Plain data for ``--json``: the step arithmetic at top level, then the scan figures."""
        data: dict[str, Any] = asdict(self.steps)
        data["chosen_steps"] = self.steps.chosen_steps
        rest = asdict(self)
        rest.pop("steps")
        data.update(rest)
        data["device_limits_ok"] = all(c.ok for c in self.device_limits)
        return data


def choose_steps(motor_step_deg: float, pulse_step_deg: float, pulse_limit: int) -> StepChoice:
    """The five achievable motor steps around ``motor_step_deg`` (paper eq. 1–4).

    ``pulse_step_deg`` is the platform angle of one pulse (the paper's minimum step). Takes the
    integer part of ``motor_step / pulse_step`` and offers it with ±1 and ±2 steps. Near the
    ends (1 step, the pulse limit) the window of five shifts inward so that every offer is valid.
    """
    if not math.isfinite(motor_step_deg) or motor_step_deg <= 0:
        raise PlanError(f"motor step {motor_step_deg!r}: must be a number greater than 0 degrees")
    max_angle = pulse_limit * pulse_step_deg
    if motor_step_deg > max_angle + _STEP_EPSILON:
        raise PlanError(
            f"motor step {motor_step_deg!r}: beyond the pulse limit ({pulse_limit} pulses × "
            f"{pulse_step_deg:g}° = {max_angle:g}°); allowed: 0 < motor step ≤ {max_angle:g}"
        )
    requested = motor_step_deg / pulse_step_deg
    base = max(1, math.floor(requested + _STEP_EPSILON))
    width = min(5, pulse_limit)
    low = min(max(1, base - 2), pulse_limit - width + 1)
    steps = tuple(range(low, low + width))
    angles = tuple(round(s * pulse_step_deg, 12) for s in steps)
    closest = min(range(width), key=lambda i: (abs(angles[i] - motor_step_deg), angles[i]))
    return StepChoice(
        requested_motor_step_deg=motor_step_deg,
        pulse_step_deg=pulse_step_deg,
        steps_per_turn=round(360.0 / pulse_step_deg),
        requested_steps=round(requested, 3),
        possible_steps=steps,
        possible_angles_deg=angles,
        closest_index=closest,
    )


#: Bytes per profile of the other dialects: (fixed, per sample without echo). CoLa-B: 9 of
#: framing, ~90 of telegram header and one 16-bit channel header, 2 per sample (RSSI doubles
#: it); CoLa-A: about 5 ASCII characters per sample and ~250 of header.
WIRE_BYTES: dict[str, tuple[int, int]] = {"cola_b": (100, 2), "cola_a": (250, 5),
                                          # LDRobot: 47-byte packets of 12 samples (4 each)
                                          "ldrobot": (0, 4), "ldrobot_ld14": (0, 4),
                                          # SCIP: 3 characters a value, 66 bytes a 64-char line
                                          "scip": (60, 4)}


def frame_bytes(dialect: str, samples: int, with_echo: bool = False) -> int:
    """Bytes on the wire for one profile of ``samples`` points in a dialect's default format.

    ``ldoem``: 9 bytes of framing, 6 of reply header, 6 of profile header (mask 0x39FF),
    14 per sector plus 2 per point (4 with echoes), 4 of sensor status. ``paper``: 9 bytes of
    framing, 21 of header, 2 per point.
    """
    if dialect == "ldoem":
        return 9 + 6 + 6 + 14 + (4 if with_echo else 2) * samples + 4
    if dialect == "paper":
        return 9 + 21 + 2 * samples
    if dialect in WIRE_BYTES:
        fixed, per_sample = WIRE_BYTES[dialect]
        return fixed + (2 * per_sample if with_echo else per_sample) * samples
    raise PlanError(f"dialect {dialect!r}: unknown; allowed: ldoem, paper, "
                    f"{', '.join(WIRE_BYTES)}")


def move_time_s(pulses: int, pulse_rate_hz: float, accel_hz_per_s: float) -> float:
    """Time to send ``pulses`` with a trapezoidal rate profile (linear ramp up and down)."""
    if pulses <= 0:
        return 0.0
    ramp_pulses = pulse_rate_hz**2 / accel_hz_per_s  # pulses spent ramping up and down together
    if pulses >= ramp_pulses:
        return pulses / pulse_rate_hz + pulse_rate_hz / accel_hz_per_s
    return 2.0 * math.sqrt(pulses / accel_hz_per_s)


def plan_scan(rig: Rig, motor_step_deg: float = DEFAULT_MOTOR_STEP_DEG) -> ScanPlan:
    """Plan a step-and-scan over the pulse limit with the step closest to ``motor_step_deg``."""
    motor, scanner = rig.motor, rig.scanner
    choice = choose_steps(motor_step_deg, motor.pulse_step_deg, motor.pulse_limit)
    step_count = choice.chosen_steps
    profiles = motor.pulse_limit // step_count + 1
    samples = scanner.samples_per_profile
    per_frame = frame_bytes(scanner.dialect, samples)
    move_s = move_time_s(step_count, motor.pulse_rate_hz, motor.accel_hz_per_s)
    # After a move: settle, then wait out the profile under way and take one whole profile.
    per_position_s = move_s + motor.settle_s + 2.0 / scanner.scan_hz
    limits = limit_checks(scanner)
    return ScanPlan(
        steps=choice,
        motor_step_count=step_count,
        motor_step_deg=step_count * motor.pulse_step_deg,
        travel_deg=(profiles - 1) * step_count * motor.pulse_step_deg,
        profiles=profiles,
        samples_per_profile=samples,
        points=profiles * samples,
        frame_bytes=per_frame,
        raw_bytes=profiles * per_frame,
        scan_time_s=profiles / scanner.scan_hz,
        step_and_scan_time_s=profiles * per_position_s,
        device_limits=limits,
        device_model=model_label(scanner.model, scanner.dialect),
    )
