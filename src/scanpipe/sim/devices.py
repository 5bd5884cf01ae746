"""The scanners' own behaviour on their link, one adapter per dialect, for the emulator.

:class:`~scanpipe.sim.emulators.ScannerEmulator` serves any scanner over its real transport
(a TCP socket, or a pseudo-terminal for a serial device) and asks the dialect's
:class:`EmulatedDevice` what to do: ``receive`` takes the host's bytes and returns the replies
(and may start or stop the stream: the device's own start/stop commands), ``config`` is the
configuration in force, ``encode`` turns one measured profile into the bytes the device sends.
A new family adds a class here and its entry in :data:`DEVICES` (keyed by dialect name).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from scanpipe.rig import ScannerConfig
from scanpipe.sim.ldoem_device import LdoemDevice
from scanpipe.sim.scip_device import ScipDevice
from scanpipe.sim.wire import device_clock_ms, profile_frame


class EmulatedDevice(Protocol):
    """One scanner's link behaviour (see the module docstring)."""

    #: Whether profiles are being sent (a device that streams from power-on starts True).
    streaming: bool

    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        """Bytes from the host at simulation time ``now_s``; the replies to send."""
        ...

    def config(self) -> ScannerConfig:
        """The scanner settings in force (rate, step, sector may have been set by the host)."""
        ...

    def encode(self, k: int, ranges_m: NDArray[np.float32], echo: NDArray[np.uint16] | None,
               config: ScannerConfig, start_s: float) -> bytes:
        """The bytes carrying profile ``k`` (measured from ``start_s``), as the device sends
        them; ``sent_one`` bookkeeping (a counted stream) happens here too."""
        ...


class StreamingDevice:
    """A device that streams from the moment the link is up and ignores what it is sent
    (the ``paper`` dialect; LDRobot units behave so too)."""

    def __init__(self, scanner: ScannerConfig) -> None:
        self.scanner = scanner
        self.streaming = True

    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        """Nothing to answer."""
        return []

    def config(self) -> ScannerConfig:
        """The rig's settings."""
        return self.scanner

    def encode(self, k: int, ranges_m: NDArray[np.float32], echo: NDArray[np.uint16] | None,
               config: ScannerConfig, start_s: float) -> bytes:
        """The dialect's frame for the profile."""
        return profile_frame(config.dialect, k, ranges_m, config, start_s)


class LdoemEmulated:
    """The LD-OEM 1000: requests answered by :class:`LdoemDevice`; streams after GET_PROFILE."""

    def __init__(self, scanner: ScannerConfig) -> None:
        from scanpipe.protocol import ldoem

        self.scanner = scanner
        self.device = LdoemDevice(scanner)
        self.reader = ldoem.FrameReader(accept_unknown=True)
        self.streaming = False
        self.requests: list[str] = []

    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        """Answer every complete request frame."""
        replies: list[bytes] = []
        for frame in self.reader.feed(data):
            replies += self.device.handle(frame.payload, device_clock_ms(now_s))
            self.requests.append(frame.payload[:2].hex())
        self.streaming = self.device.stream is not None
        return replies

    def config(self) -> ScannerConfig:
        """The sector, step and head speed set by the host."""
        d = self.device
        return self.scanner.model_copy(update={
            "scan_hz": float(d.scan_hz), "beam_step_deg": d.step_ticks / 16.0,
            "start_angle_deg": d.start_ticks / 16.0, "end_angle_deg": d.end_ticks / 16.0})

    def encode(self, k: int, ranges_m: NDArray[np.float32], echo: NDArray[np.uint16] | None,
               config: ScannerConfig, start_s: float) -> bytes:
        """A GET_PROFILE reply in the requested format; ends a counted stream."""
        stream = self.device.stream
        mask = stream.mask if stream is not None else None
        frame = profile_frame("ldoem", k, ranges_m, config, start_s, mask,
                              self.device.clock_ms_offset)
        if stream is not None:
            stream.sent += 1
            if stream.count and stream.sent >= stream.count:
                self.device.stream = None
                self.streaming = False
        return frame


#: The emulated device of each dialect (a new family adds its entry).
DEVICES: dict[str, Callable[[ScannerConfig], EmulatedDevice]] = {
    "ldoem": LdoemEmulated,
    "paper": StreamingDevice,
    "scip": ScipDevice,
}


def emulated_device(scanner: ScannerConfig) -> EmulatedDevice:
    """A fresh emulated device for the scanner's dialect."""
    from scanpipe.errors import SimulationError

    if scanner.dialect not in DEVICES:
        raise SimulationError(f"dialect {scanner.dialect!r}: no emulated device; emulated: "
                              f"{', '.join(DEVICES)}")
    return DEVICES[scanner.dialect](scanner)
