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

    profile = Profile(
        frame=index & 0xFFFF, sector=0, start_angle_deg=scanner.start_angle_deg,
        step_deg=scanner.beam_step_deg, ranges_m=ranges_m, echo=echo,
        device_time_ms=(device_clock_ms(start_s) + clock_offset_ms) & 0xFFFF,
        device_end_time_ms=(device_clock_ms(start_s + sector_duration_s(scanner))
                            + clock_offset_ms) & 0xFFFF)
    if dialect == "ldoem" and mask is not None and mask != ldoem.MASK_RANGES:
        return ldoem.encode_profile_reply([profile], mask=mask)
    return DIALECTS[dialect].encode_profile(profile)
