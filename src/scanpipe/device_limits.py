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


