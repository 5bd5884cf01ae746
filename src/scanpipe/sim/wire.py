"""Simulated profiles on the wire: one place that turns measured ranges into dialect frames,
used by the TCP emulator and by direct mode alike (so both send the same bytes)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanpipe.rig import ScannerConfig
from scanpipe.sim.scanner import sector_duration_s

#: The scanner's own millisecond clock reads this when the simulation starts.
SCANNER_CLOCK_ORIGIN_MS = 12_345


def device_clock_ms(time_s: float) -> int:
    """The scanner's millisecond clock (not wrapped) at simulation time ``time_s``."""
    return SCANNER_CLOCK_ORIGIN_MS + int(np.floor(time_s * 1000.0))


def device_clock_ticks(time_s: float, tick_ns: int) -> int:
    """The scanner's own clock (not wrapped) in ticks of ``tick_ns`` at ``time_s``."""
    return int(np.floor((SCANNER_CLOCK_ORIGIN_MS / 1000.0 + time_s) * 1e9 / tick_ns))


def profile_frame(dialect: str, index: int, ranges_m: NDArray[np.float32],
                  scanner: ScannerConfig, start_s: float, mask: int | None = None,
                  clock_offset_ms: int = 0, echo: NDArray[np.uint16] | None = None) -> bytes:
    """The frame carrying profile ``index`` (measured at ``start_s``) in ``dialect``.

    ``mask`` selects the ldoem fields (the GET_PROFILE request's; default 0x39FF);
    ``clock_offset_ms`` is what SET_TIME_ABS moved the device clock by; ``echo`` the
    amplitudes (:func:`scanpipe.sim.scanner.echo_amplitude`), sent when the mask asks for them.
    """
    from scanpipe.protocol import ldoem
    from scanpipe.protocol.profile import Profile
    from scanpipe.protocol.registry import DIALECTS

    d = DIALECTS[dialect]
    if d.device_tick_ns == 1_000_000 and d.device_wrap_ticks == 1 << 16:
        start_ticks = (device_clock_ms(start_s) + clock_offset_ms) & 0xFFFF
        end_ticks = (device_clock_ms(start_s + sector_duration_s(scanner))
                     + clock_offset_ms) & 0xFFFF
    else:  # another clock: the last sample's time, as SICK and the others report it
        last_s = start_s + (len(ranges_m) - 1) * scanner.beam_step_deg / (360.0 * scanner.scan_hz)
        start_ticks = device_clock_ticks(start_s, d.device_tick_ns) % d.device_wrap_ticks
        end_ticks = device_clock_ticks(last_s, d.device_tick_ns) % d.device_wrap_ticks
    profile = Profile(
        frame=index & 0xFFFF, sector=0, start_angle_deg=scanner.start_angle_deg,
        step_deg=scanner.beam_step_deg, ranges_m=ranges_m, echo=echo,
        device_time_ms=start_ticks, device_end_time_ms=end_ticks,
        device_tick_ns=d.device_tick_ns, device_wrap_ticks=d.device_wrap_ticks)
    if dialect == "ldoem" and mask is not None and mask != ldoem.MASK_RANGES:
        return ldoem.encode_profile_reply([profile], mask=mask)
    if dialect in ("ldrobot", "ldrobot_ld14"):
        # The packets carry the head speed and their times follow from it: the rig's rate,
        # not the encoder's 10 Hz default (a 6 Hz LD14 read as 10 Hz lost every other turn).
        from scanpipe.protocol import ldrobot

        # An LD14's ranges come measured at its packets' beams (sim.scanner.packet_beams):
        # the packets carry them as they are.
        return ldrobot.encode_profile(profile, round(360.0 * scanner.scan_hz))
    return DIALECTS[dialect].encode_profile(profile)
