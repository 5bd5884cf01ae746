"""What the scanners can do: their limits, checked on plain settings.

Below the rig model (the rig validator and the planner both take from here, so neither imports
the other for it). A check reads the settings through :class:`ScanSettings` — the scanner
section of a rig has those attributes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol


class ScanSettings(Protocol):
    """The scanner settings a limit check reads (``scanpipe.rig.ScannerConfig`` has them)."""

    @property
    def scan_hz(self) -> float: ...
    @property
    def beam_step_deg(self) -> float: ...
    @property
    def start_angle_deg(self) -> float: ...
    @property
    def end_angle_deg(self) -> float: ...


#: LD-OEM 1000 limits (from public driver sources; see shared/paper/NOTES.md).
LDOEM_HEAD_HZ = (5, 20)
LDOEM_STEP_QUANTUM_DEG = 0.125
LDOEM_MAX_PULSE_HZ = 14_400.0
LDOEM_MAX_MEAN_PULSE_HZ = 10_800.0


@dataclass(frozen=True)
class LimitCheck:
    """One device limit: what it is, the value the rig asks for, the bound, and whether it holds."""

    name: str
    value: float
    limit: str
    ok: bool


def ldoem_limit_checks(scanner: ScanSettings) -> tuple[LimitCheck, ...]:
    """The LD-OEM 1000's limits for the scanner settings of a rig."""
    hz, step = scanner.scan_hz, scanner.beam_step_deg
    pulse_hz = hz * 360.0 / step
    active = (scanner.end_angle_deg - scanner.start_angle_deg) / 360.0
    quanta = step / LDOEM_STEP_QUANTUM_DEG
    return (
        LimitCheck("scan_hz", hz, "5–20 Hz in whole Hz",
                   LDOEM_HEAD_HZ[0] <= hz <= LDOEM_HEAD_HZ[1] and float(hz).is_integer()),
        LimitCheck("beam_step_deg", step, "a multiple of 0.125°",
                   abs(quanta - round(quanta)) < 1e-9 and round(quanta) >= 1),
        LimitCheck("pulse_hz", pulse_hz, "scan_hz · 360 / step ≤ 14400 Hz",
                   pulse_hz <= LDOEM_MAX_PULSE_HZ + 1e-9),
        LimitCheck("mean_pulse_hz", pulse_hz * active, "pulse_hz · active share ≤ 10800 Hz",
                   pulse_hz * active <= LDOEM_MAX_MEAN_PULSE_HZ + 1e-9),
    )


def device_limit_problems(scanner: ScanSettings) -> list[str]:
    """LD-OEM limit violations of scanner settings, one line each (empty when fine)."""
    problems = []
    for check in ldoem_limit_checks(scanner):
        if not check.ok:
            key = "scan_hz" if check.name.endswith("pulse_hz") else check.name
            problems.append(
                f"scanner.{key}: {check.name} = {check.value:g} is outside the LD-OEM limit "
                f"({check.limit})"
            )
    return problems




@dataclass(frozen=True)
class LdrobotLimits:
    """One LDRobot model (LDRobot datasheets): serial link, sample rate, head speed range and
    range window, its nominal head speed, and whether its samples need the triangulation
    heads' angle correction (LD14/LD14P: ``protocol.ldrobot.sl_angle_shift_deg``). The head
    speed is set by the host (PWM) within ``head_hz``; the sample rate is fixed, so the beam
    step follows from the speed."""

    model: str
    baud: int
    sample_hz: float
    head_hz: tuple[float, float]
    min_range_m: float
    max_range_m: float
    nominal_hz: float = 10.0
    angle_correction: bool = False

    def beam_step_deg(self, scan_hz: float) -> float:
        """The angle between two samples at ``scan_hz`` head turns per second."""
        return 360.0 * scan_hz / self.sample_hz


#: LD06 and LD19: 4 500 samples/s, 5–13 Hz, 0.02–12 m, 230 400 baud; STL-27L: 21 600
#: samples/s, 6–12 Hz (uncertain: the datasheets quote 10 Hz typical), 0.03–25 m, 921 600 baud.
#: LD14: 2 300 samples/s, 115 200 baud (LDRobot's SDK ldlidar_sl_ros2: LD_14 measure rate and
#: launch file); LD14P: 4 000 samples/s, 230 400 baud (the SDK's LD_14P_4000HZ, which its
#: node uses for an LD14P; older LD14P firmware sampled 2 300/s); both 0.1–8 m, 6 Hz default,
#: 2–8 Hz (the LD14P datasheet; the LD14's speed range is assumed the same).
LDROBOT_LIMITS: dict[str, LdrobotLimits] = {
    "ld06": LdrobotLimits("ld06", 230_400, 4_500.0, (5.0, 13.0), 0.02, 12.0),
    "ld19": LdrobotLimits("ld19", 230_400, 4_500.0, (5.0, 13.0), 0.02, 12.0),
    "stl27l": LdrobotLimits("stl27l", 921_600, 21_600.0, (6.0, 12.0), 0.03, 25.0),
    "ld14": LdrobotLimits("ld14", 115_200, 2_300.0, (2.0, 8.0), 0.1, 8.0, 6.0, True),
    "ld14p": LdrobotLimits("ld14p", 230_400, 4_000.0, (2.0, 8.0), 0.1, 8.0, 6.0, True),
}


class RangeSettings(ScanSettings, Protocol):
    """Scanner settings with the range window (``scanpipe.rig.ScannerConfig`` has them)."""

    @property
    def min_range_m(self) -> float: ...
    @property
    def max_range_m(self) -> float: ...


def ldrobot_limit_checks(scanner: RangeSettings, model: str) -> tuple[LimitCheck, ...]:
    """An LDRobot model's limits for the scanner settings of a rig (``model``: a key of
    :data:`LDROBOT_LIMITS`). The beam step must be what the sample rate gives at ``scan_hz``
    (within 2 %: the head's speed wobbles and the decoder's grid follows the measured step)."""
    limits = LDROBOT_LIMITS[model]
    hz, step = scanner.scan_hz, scanner.beam_step_deg
    expected = limits.beam_step_deg(hz)
    low, high = limits.head_hz
    return (
        LimitCheck("scan_hz", hz, f"{low:g}–{high:g} Hz", low <= hz <= high),
        LimitCheck("beam_step_deg", step,
                   f"360 · scan_hz / {limits.sample_hz:g} samples/s = {expected:.4g}° (±2 %)",
                   abs(step - expected) <= 0.02 * expected),
        LimitCheck("min_range_m", scanner.min_range_m, f"≥ {limits.min_range_m:g} m",
                   scanner.min_range_m >= limits.min_range_m - 1e-9),
        LimitCheck("max_range_m", scanner.max_range_m, f"≤ {limits.max_range_m:g} m",
                   scanner.max_range_m <= limits.max_range_m + 1e-9),
    )
