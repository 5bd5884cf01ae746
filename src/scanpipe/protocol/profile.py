"""One decoded scanner profile sector, the unit every dialect decodes to and encodes from."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ProtocolError
from scanpipe.protocol.framing import ImplausibleFrame

#: Distances on the wire are u16 in 1/256 m; 0 means "no return".
RANGE_SCALE_PER_M = 256.0
#: Angles on the wire are u16 in 1/16 degree.
ANGLE_SCALE_PER_DEG = 16.0
#: Device timestamps are 16-bit milliseconds: they wrap every 65.536 s.
DEVICE_TIME_WRAP_MS = 1 << 16
#: Encoder ticks (1/16°) per turn: directions wrap here.
TICKS_PER_TURN = 5760
#: A 2-D scanner sees one turn: no start angle, step or sector span exceeds it.
FULL_TURN_DEG = 360.0
#: The echo (intensity) of a sample is a u16: this is its full scale.
ECHO_FULL_SCALE = 65535.0
#: Two neighbouring samples lie on one surface when their ranges differ by less than this share
#: of the nearer, plus the absolute part below (a wall seen at 80° incidence changes by ~8 % per
#: 0.8° step).
CONTINUITY_SHARE = 0.10
CONTINUITY_M = 0.03


@dataclass(frozen=True, eq=False)
class Profile:
    """One profile sector as sent by the scanner.

    ``ranges_m`` is float32 with NaN for "no return"; ``echo`` is uint16 or None when the
    dialect or format mask carries none. ``device_time_ms`` / ``device_end_time_ms`` are the raw
    16-bit millisecond timestamps of the sector's start and end as on the wire (None when absent).
    ``checksum_ok`` is False only for frames returned by the lenient checksum mode.

    Dialects whose device clock is not a 16-bit millisecond counter keep their raw clock
    values in ``device_time_ms`` / ``device_end_time_ms`` too and say what one count is:
    ``device_tick_ns`` (1 000 000 = 1 ms; 1000 for the µs counters of SICK CoLa) and
    ``device_wrap_ticks`` (where the counter wraps: 2¹⁶ for the LD-OEM, 2³² for SICK, 30 000
    for LDRobot). The decode stage unwraps against host time with them.
    """

    frame: int
    sector: int
    start_angle_deg: float
    step_deg: float
    ranges_m: NDArray[np.float32]
    echo: NDArray[np.uint16] | None = None
    device_time_ms: int | None = None
    device_end_time_ms: int | None = None
    checksum_ok: bool = True
    device_tick_ns: int = 1_000_000
    device_wrap_ticks: int = DEVICE_TIME_WRAP_MS

    def same_as(self, other: Profile) -> bool:
        """Field-by-field equality, NaN equal to NaN (dataclass ``==`` cannot compare arrays)."""
        return (
            self.frame == other.frame
            and self.sector == other.sector
            and _same_float(self.start_angle_deg, other.start_angle_deg)
            and _same_float(self.step_deg, other.step_deg)
            and np.array_equal(self.ranges_m, other.ranges_m, equal_nan=True)
            and ((self.echo is None and other.echo is None) or (
                self.echo is not None and other.echo is not None
                and np.array_equal(self.echo, other.echo)))
            and self.device_time_ms == other.device_time_ms
            and self.device_end_time_ms == other.device_end_time_ms
            and self.checksum_ok == other.checksum_ok
        )


def _same_float(a: float, b: float) -> bool:
    return a == b or (a != a and b != b)


def ranges_to_wire(ranges_m: NDArray[np.floating]) -> NDArray[np.uint16]:
    """Ranges in metres to u16 in 1/256 m: NaN (and ≤ 0) → 0 = no return, clipped to 255.996 m."""
    scaled = np.rint(np.asarray(ranges_m, dtype=np.float64) * RANGE_SCALE_PER_M)
    scaled = np.where(np.isfinite(scaled) & (scaled > 0), scaled, 0.0)
    wire = np.clip(scaled, 0, 65535).astype(np.uint16)
    # A positive range that rounds to 0 is still a return: keep it distinguishable from "none".
    wire[(wire == 0) & (scaled > 0)] = 1
    return wire


def _range_table() -> NDArray[np.float32]:
    table = np.arange(1 << 16, dtype=np.float32) / np.float32(RANGE_SCALE_PER_M)
    table[0] = np.nan
    return table


#: Every u16 wire distance in metres (one gather decodes a profile).
_RANGE_TABLE = _range_table()


def ranges_from_wire(wire: NDArray[np.unsignedinteger]) -> NDArray[np.float32]:
    """u16 distances in 1/256 m to float32 metres, 0 → NaN (no return)."""
    return _RANGE_TABLE[np.asarray(wire, dtype=np.uint16)]


def angle_to_wire(angle_deg: float) -> int:
    """An angle in degrees to its u16 wire value in 1/16° (0…4095.9375°)."""
    value = round(angle_deg * ANGLE_SCALE_PER_DEG)
    if not 0 <= value <= 0xFFFF:
        raise ProtocolError(f"angle {angle_deg!r}°: outside 0…4095.9375° (u16 in 1/16°)")
    return value


def are_fractions(values: NDArray[np.floating]) -> bool:
    """Whether intensities were normalised to 0…1 by their writer (all finite ones within it,
    some not whole): they are to be scaled to the echo's full scale, not rounded to 0 or 1."""
    finite = values[np.isfinite(values)]
    return bool(finite.size and finite.min() >= 0.0 and finite.max() <= 1.0
                and np.any(finite != np.round(finite)))


def ranges_between(left_m: NDArray[np.float32], right_m: NDArray[np.float32],
                   fraction: NDArray[np.float32]) -> NDArray[np.float32]:
    """The range at ``fraction`` (0…1) of the way from one sample to its neighbour, for a beam
    resampled onto another angle grid: linear on one surface (second order error on a smooth
    one), the nearer sample's across a depth jump or a no-return (NaN compares False)."""
    change = right_m - left_m
    smooth = np.abs(change) <= np.float32(CONTINUITY_SHARE) * left_m + np.float32(CONTINUITY_M)
    return np.where(smooth, left_m + fraction * change,
                    np.where(fraction > np.float32(0.5), right_m, left_m))


def check_plausible(profiles: Sequence[Profile] | None,
                    max_points: int | None = None,
                    min_start_deg: float = 0.0) -> int | None:
    """The frame counter of a frame's profiles (None for a frame without profiles), or
    :class:`~scanpipe.protocol.framing.ImplausibleFrame` when the angles cannot come from a
    360° scanner: a start angle or step outside 0…360°, a zero step with several samples, or
    samples spanning more than a turn; or when a sector holds more than ``max_points``.
    ``min_start_deg`` lowers the start bound for devices whose zero is inside their field of
    view (SICK: −45°…225°, Hokuyo: −135°…135°); samples must then still end by 360°."""
    if not profiles:
        return None
    for p in profiles:
        n = len(p.ranges_m)
        start, step = p.start_angle_deg, p.step_deg
        problem = ""
        if start == start and not min_start_deg <= start <= FULL_TURN_DEG:
            problem = f"start angle {start}°"
        elif step == step and not 0.0 <= step <= FULL_TURN_DEG:
            problem = f"step {step}°"
        elif step == step and n >= 2 and (step == 0.0 or (n - 1) * step > FULL_TURN_DEG):
            problem = f"{n} samples at {step}° (span over 360°)"
        elif max_points is not None and n > max_points:
            problem = f"{n} samples (at most {max_points})"
        if problem:
            raise ImplausibleFrame(f"frame {p.frame} sector {p.sector}: {problem}")
    return profiles[0].frame


def unwrap_counter(values: NDArray[np.integer], period: int) -> NDArray[np.int64]:
    """Unwrap a counter that wraps at ``period`` (a u16 frame number, a 16-bit ms clock).

    Each backwards jump of more than half the period counts one wrap; smaller backwards steps
    (reordering, jitter) are kept as they are. Like :func:`numpy.unwrap`, in integers.
    """
    t = np.asarray(values, dtype=np.int64)
    if t.size == 0:
        return t
    step = np.diff(t)
    half = period // 2
    wraps = np.concatenate([[0], np.cumsum((step < -half).astype(np.int64)
                                           - (step > half).astype(np.int64))])
    return np.asarray(t + wraps * period, dtype=np.int64)


def unwrap_ms16(times_ms: NDArray[np.integer]) -> NDArray[np.int64]:
    """Unwrap 16-bit millisecond timestamps (they wrap every 65.536 s) into int64 milliseconds."""
    return unwrap_counter(times_ms, DEVICE_TIME_WRAP_MS)
