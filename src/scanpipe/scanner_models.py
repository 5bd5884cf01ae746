"""The scanner models scanpipe knows: what each device is, how it is reached, and its limits.

One row per device in :data:`SCANNER_MODELS` (a :class:`ScannerModel`): its wire dialect, its
transport (TCP port, or a serial line and its baud rate), its field of view in the device's own
angles, the (scan rate, beam step) modes it offers, its range limits, its range noise σ (the
simulator's default) and whether it sends echo intensities. ``scanpipe rig init --scanner NAME``
writes a rig for a model, ``scanpipe plan`` and the rig validator check its limits
(:func:`limit_checks`, :func:`limit_problems`), ``scanpipe simulate --scanner NAME`` simulates it.

A rig's ``scanner.model`` names its row; an older rig without the key is an LD-OEM 1000 when its
dialect is ``ldoem`` and an unnamed scanner (no limits known) otherwise.

Base floor: imports only :mod:`scanpipe.device_limits`, so :mod:`scanpipe.rig` can use it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

from scanpipe.device_limits import (
    LDROBOT_LIMITS,
    LimitCheck,
    ScanSettings,
    device_limit_problems,
    ldoem_limit_checks,
    ldrobot_limit_checks,
)

#: Every dialect name a rig may give (the protocol registry holds one entry per name; a test
#: keeps the two equal). A new family adds its name here and its entry in protocol/registry.py.
DIALECT_NAMES: tuple[str, ...] = ("ldoem", "paper", "cola_b", "cola_a", "ldrobot",
                                  "ldrobot_ld14", "scip")
Transport = Literal["tcp", "serial"]


class ModelSettings(ScanSettings, Protocol):
    """The scanner settings a model's limit check reads (``ScannerConfig`` has them)."""

    @property
    def min_range_m(self) -> float: ...
    @property
    def max_range_m(self) -> float: ...


@dataclass(frozen=True)
class ScannerModel:
    """One scanner model (see the module docstring).

    ``fov_deg`` is (first sample, last sample) in the device's angles at the finest step; a rig
    writes ``end_angle_deg`` one beam step past the last sample (sectors are half-open).
    ``modes`` are the (scan_hz, beam_step_deg) pairs the device offers. ``limit_checks``
    replaces the table check for devices whose limits are not a list of modes (the LD-OEM).
    ``other_dialects`` are further dialects the device speaks, each with its TCP port (the
    LMS1xx: CoLa-A on 2111 beside CoLa-B on 2112); a rig selects one with its ``dialect``.
    """

    name: str
    description: str
    dialect: str
    transport: Transport
    fov_deg: tuple[float, float]
    modes: tuple[tuple[float, float], ...]
    range_m: tuple[float, float]
    noise_sigma_m: float
    intensity: bool
    port: int = 2112
    baudrate: int = 0
    limit_checks: Callable[[ModelSettings], tuple[LimitCheck, ...]] | None = None
    other_dialects: Mapping[str, int] | None = None

    @property
    def dialects(self) -> tuple[str, ...]:
        """Every dialect the device speaks, its default first."""
        return (self.dialect, *(self.other_dialects or {}))

    @property
    def scan_hz(self) -> float:
        """The default scan rate (the first mode's)."""
        return self.modes[0][0]

    @property
    def beam_step_deg(self) -> float:
        """The default beam step (the first mode's)."""
        return self.modes[0][1]

    def rig_values(self, dialect: str = "") -> dict[str, object]:
        """The ``[scanner]`` keys of a rig for this model in its default mode (and
        ``dialect``, one of :attr:`dialects`, with its port; the default one if empty)."""
        dialect = dialect or self.dialect
        step = self.beam_step_deg
        start, last = self.fov_deg
        samples = round((last - start) / step) + (0 if self.dialect == "ldoem" else 1)
        values: dict[str, object] = {
            "model": self.name, "dialect": dialect, "transport": self.transport,
            "beam_step_deg": step, "scan_hz": self.scan_hz,
            "start_angle_deg": start, "end_angle_deg": start + samples * step,
            "min_range_m": self.range_m[0], "max_range_m": self.range_m[1],
        }
        if self.transport == "tcp":
            values["port"] = (self.other_dialects or {}).get(dialect, self.port)
        else:
            values["baudrate"] = self.baudrate
        return values


def table_limit_checks(model: ScannerModel, scanner: ModelSettings) -> tuple[LimitCheck, ...]:
    """A model's limits from its table row: a mode it offers, the field of view, the range."""
    hz, step = scanner.scan_hz, scanner.beam_step_deg
    modes = ", ".join(f"{h:g} Hz at {s:g}°" for h, s in model.modes)
    # The scan rate is judged alone, the beam step at that rate: only the wrong one is named.
    steps_at_hz = [s for h, s in model.modes if abs(hz - h) < 1e-6]
    hz_ok = bool(steps_at_hz)
    step_ok = any(abs(step - s) < 1e-6 for s in steps_at_hz)
    step_limit = (f"at {hz:g} Hz: one of {', '.join(f'{s:g}°' for s in steps_at_hz)}"
                  if hz_ok else f"one of {modes}")
    first, last = model.fov_deg
    return (
        LimitCheck("scan_hz", hz, f"one of {modes}", hz_ok),
        LimitCheck("beam_step_deg", step, step_limit, step_ok or not hz_ok),
        LimitCheck("start_angle_deg", scanner.start_angle_deg, f"≥ {first:g}°",
                   scanner.start_angle_deg >= first - 1e-9),
        LimitCheck("end_angle_deg", scanner.end_angle_deg, f"≤ {last:g}° + one beam step",
                   scanner.end_angle_deg <= last + step + 1e-9),
        LimitCheck("min_range_m", scanner.min_range_m, f"≥ {model.range_m[0]:g} m",
                   scanner.min_range_m >= model.range_m[0] - 1e-9),
        LimitCheck("max_range_m", scanner.max_range_m, f"≤ {model.range_m[1]:g} m",
                   scanner.max_range_m <= model.range_m[1] + 1e-9),
    )


def _ldrobot_checks(model: str) -> Callable[[ModelSettings], tuple[LimitCheck, ...]]:
    """The limit check of one LDRobot model (any head speed in its range, the beam step the
    sample rate gives at it)."""
    def check(scanner: ModelSettings) -> tuple[LimitCheck, ...]:
        return ldrobot_limit_checks(scanner, model)
    return check


SCANNER_MODELS: Mapping[str, ScannerModel] = {
    "ldoem1000": ScannerModel(
        name="ldoem1000", description="SICK LD-OEM 1000 (the paper's scanner, 360°)",
        dialect="ldoem", transport="tcp", fov_deg=(0.0, 360.0),
        modes=((5.0, 0.25),), range_m=(0.5, 250.0), noise_sigma_m=0.010, intensity=True,
        port=49152, limit_checks=ldoem_limit_checks),
    "lms111": ScannerModel(
        name="lms111", description="SICK LMS111 (270°, 20 m, CoLa-B on TCP 2112)",
        dialect="cola_b", transport="tcp", fov_deg=(-45.0, 225.0),
        modes=((25.0, 0.5), (25.0, 0.25), (50.0, 0.5)), range_m=(0.5, 20.0),
        noise_sigma_m=0.012, intensity=True, port=2112, other_dialects={"cola_a": 2111}),
    "tim571": ScannerModel(
        name="tim571", description="SICK TiM571 (270°, 25 m, CoLa-B on TCP 2112)",
        dialect="cola_b", transport="tcp", fov_deg=(-45.0, 225.0),
        modes=((15.0, 1.0 / 3.0),), range_m=(0.05, 25.0),
        noise_sigma_m=0.020, intensity=True, port=2112),
    # The LD14/LD14P speak the LD06's packets but need the SDK's angle correction: their own
    # dialect (never detected from the bytes), so a recording of one names it.
    **{name: ScannerModel(
        name=name, description=f"LDRobot {label} (360°, {lim.max_range_m:g} m, "
                               f"{lim.sample_hz:g} samples/s, serial {lim.baud} baud)",
        dialect="ldrobot_ld14" if lim.angle_correction else "ldrobot", transport="serial",
        # the last whole step within the turn (360° need not be a whole number of steps)
        fov_deg=(0.0, (math.floor(360.0 / lim.beam_step_deg(lim.nominal_hz) + 1e-9) - 1)
                 * lim.beam_step_deg(lim.nominal_hz)),
        modes=((lim.nominal_hz, lim.beam_step_deg(lim.nominal_hz)),),
        range_m=(lim.min_range_m, lim.max_range_m),
        # LD14/LD14P: ±1 % in 1–6 m (datasheet), a 1.5 cm σ in a room (a modelling choice)
        noise_sigma_m=0.015 if lim.angle_correction else 0.010, intensity=True,
        baudrate=lim.baud, limit_checks=_ldrobot_checks(name))
       for name, label, lim in (("ld06", "LD06", LDROBOT_LIMITS["ld06"]),
                                ("ld19", "LD19", LDROBOT_LIMITS["ld19"]),
                                ("stl27l", "STL-27L", LDROBOT_LIMITS["stl27l"]),
                                ("ld14", "LD14", LDROBOT_LIMITS["ld14"]),
                                ("ld14p", "LD14P", LDROBOT_LIMITS["ld14p"]))},
    "ust10lx": ScannerModel(
        name="ust10lx", description="Hokuyo UST-10LX (270°, 10 m, SCIP 2.0 on TCP 10940)",
        dialect="scip", transport="tcp", fov_deg=(-135.0, 135.0),
        modes=((40.0, 0.25), (40.0, 0.5), (40.0, 1.0)), range_m=(0.06, 10.0), noise_sigma_m=0.040,
        intensity=True, port=10940),
    "urg04lx": ScannerModel(
        name="urg04lx", description="Hokuyo URG-04LX (240°, 5.6 m, SCIP 2.0 on serial/USB)",
        dialect="scip", transport="serial", fov_deg=(-119.53125, 119.8828125),
        modes=((10.0, 360.0 / 1024.0), (10.0, 720.0 / 1024.0)), range_m=(0.02, 5.6),
        noise_sigma_m=0.030,
        intensity=False, baudrate=115200),
}


def get_model(name: str) -> ScannerModel:
    """The model called ``name``; ``KeyError`` with the known names otherwise (callers turn it
    into their own error)."""
    if name not in SCANNER_MODELS:
        raise KeyError(f"scanner model {name!r}: unknown; allowed: {', '.join(SCANNER_MODELS)}")
    return SCANNER_MODELS[name]


def model_of(model: str, dialect: str) -> ScannerModel | None:
    """The model of a rig's scanner: its ``model`` key, else the LD-OEM for dialect ldoem."""
    if model:
        return SCANNER_MODELS.get(model)
    return SCANNER_MODELS["ldoem1000"] if dialect == "ldoem" else None


def model_label(model: str, dialect: str) -> str:
    """A short name for messages: "LD-OEM", "LMS111", … ("" for an unnamed scanner)."""
    found = model_of(model, dialect)
    if found is None:
        return ""
    return "LD-OEM" if found.name == "ldoem1000" else found.description.split(" (")[0].split()[-1]


class NamedSettings(ModelSettings, Protocol):
    """Settings that also name their model and dialect (``ScannerConfig``)."""

    @property
    def model(self) -> str: ...
    @property
    def dialect(self) -> str: ...


def limit_checks(scanner: NamedSettings) -> tuple[LimitCheck, ...]:
    """The device limits of a rig's scanner settings (none for an unnamed scanner)."""
    found = model_of(scanner.model, scanner.dialect)
    if found is None:
        return ()
    if found.limit_checks is not None:
        return found.limit_checks(scanner)
    return table_limit_checks(found, scanner)


def limit_problems(scanner: NamedSettings) -> list[str]:
    """Device limit violations of scanner settings, one line each (empty when fine)."""
    found = model_of(scanner.model, scanner.dialect)
    if found is not None and found.limit_checks is ldoem_limit_checks:
        return device_limit_problems(scanner)  # the LD-OEM's own wording
    label = model_label(scanner.model, scanner.dialect)
    problems = []
    for check in limit_checks(scanner):
        if not check.ok:
            key = "scan_hz" if check.name.endswith("pulse_hz") else check.name
            problems.append(f"scanner.{key}: {check.name} = {check.value:g} is outside the "
                            f"{label} limit ({check.limit})")
    return problems
