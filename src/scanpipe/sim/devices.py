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
from scanpipe.sim.streaming_device import StreamingDevice
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
                              self.device.clock_ms_offset, echo)
        if stream is not None:
            stream.sent += 1
            if stream.count and stream.sent >= stream.count:
                self.device.stream = None
                self.streaming = False
        return frame


def _ldrobot(scanner: ScannerConfig) -> EmulatedDevice:
    from scanpipe.sim.ldrobot_device import LdrobotEmulated

    return LdrobotEmulated(scanner)


class SickColaDevice:
    """A SICK scanner speaking CoLa-B (LMS1xx on TCP 2112, TiM5xx) or CoLa-A (LMS1xx on TCP
    2111: the same telegrams as ASCII tokens between STX and ETX), after the rig's dialect:
    log-in (``sMN SetAccessMode``), scan configuration within its model's modes (``sMN
    mLMPsetscancfg``, answered with status 0, or 1/2/4 for a bad frequency, resolution or
    sector as the manuals list), ``sMN Run``, and streaming with ``sEN LMDscandata 1`` / ``0``
    (answered ``sEA LMDscandata 1/0``). Anything else is answered ``sFA`` with error 2
    (unknown method)."""

    def __init__(self, scanner: ScannerConfig) -> None:
        from scanpipe.protocol import framing, sick_cola

        self.scanner = scanner
        self.current = scanner
        self.ascii = scanner.dialect == "cola_a"
        self.reader: framing.FrameReader | sick_cola.AsciiFrameReader = (
            sick_cola.AsciiFrameReader(1 << 16, parse=False) if self.ascii
            else framing.FrameReader(sick_cola.MARKER, 0, 1 << 16, confirm=False))
        self.streaming = False
        self.logged_in = False
        self.requests: list[str] = []

    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        """Answer every complete command."""
        from scanpipe.errors import ProtocolError
        from scanpipe.protocol import sick_cola

        parse = sick_cola.parse_command_ascii if self.ascii else sick_cola.parse_command
        replies = []
        for frame in self.reader.feed(data):
            if not frame.checksum_ok:
                continue
            try:
                kind, name, args = parse(frame.payload)
            except ProtocolError:
                replies.append(self._reply("sFA", "", (2).to_bytes(2, "big")))
                continue
            self.requests.append(f"{kind} {name}")
            replies.append(self._answer(kind, name, args))
        return replies

    def _reply(self, kind: str, name: str, args: bytes) -> bytes:
        """A telegram in the device's flavour (``args`` as CoLa-B bytes)."""
        from scanpipe.protocol import sick_cola

        if self.ascii:
            return sick_cola.command_ascii(kind, name, args)
        if kind == "sFA":
            return sick_cola.failure(int.from_bytes(args, "big"))
        return sick_cola.command(kind, name, args)

    def _answer(self, kind: str, name: str, args: bytes) -> bytes:
        from scanpipe.protocol import sick_cola
        from scanpipe.scanner_models import SCANNER_MODELS

        if (kind, name) == ("sEN", "LMDscandata") and args[:1] in (b"\x00", b"\x01"):
            self.streaming = args[:1] == b"\x01"
            return self._reply("sEA", "LMDscandata", args[:1])
        if (kind, name) == ("sMN", "SetAccessMode") and len(args) == 5:
            level, password = args[0], int.from_bytes(args[1:5], "big")
            self.logged_in = (level, password) == (sick_cola.ACCESS_LEVEL_CLIENT,
                                                   sick_cola.CLIENT_PASSWORD)
            return self._reply("sAN", "SetAccessMode", bytes([int(self.logged_in)]))
        if (kind, name) == ("sMN", "mLMPsetscancfg") and len(args) == sick_cola.SCANCFG.size:
            freq, _sectors, res, start, end = sick_cola.SCANCFG.unpack(args)
            hz, step = freq / 100.0, res / sick_cola.ANGLE_UNITS_PER_DEG
            model = SCANNER_MODELS.get(self.scanner.model)
            modes = model.modes if model else ((self.scanner.scan_hz,
                                                self.scanner.beam_step_deg),)
            fov = model.fov_deg if model else (self.scanner.start_angle_deg,
                                               self.scanner.end_angle_deg)
            status = 0
            if not self.logged_in:
                return self._reply("sFA", "", (10).to_bytes(2, "big"))  # access denied
            if not any(abs(hz - h) < 1e-3 for h, _ in modes):
                status = 1
            elif not any(abs(hz - h) < 1e-3 and abs(step - s) < 1e-3 for h, s in modes):
                status = 2
            elif not fov[0] - 1e-6 <= start / 1e4 < end / 1e4 <= fov[1] + 1e-6:
                status = 4
            if status == 0:
                self.current = self.scanner.model_copy(update={
                    "scan_hz": hz, "beam_step_deg": step, "start_angle_deg": start / 1e4,
                    "end_angle_deg": end / 1e4 + step})
            return self._reply("sAN", "mLMPsetscancfg", bytes([status]) + args)
        if (kind, name) == ("sMN", "Run"):
            return self._reply("sAN", "Run", b"\x01")
        if (kind, name) == ("sRN", "DeviceIdent"):
            ident = f"{self.scanner.model or 'SICK'} scanpipe-sim".encode("ascii")
            if self.ascii:  # strings as length + one token each
                ident = ident.replace(b" ", b"_")
                return (b"\x02sRA DeviceIdent " + format(len(ident), "X").encode() + b" "
                        + ident + b" 2 V1\x03")
            return sick_cola.command("sRA", "DeviceIdent",
                                     len(ident).to_bytes(2, "big") + ident + b"\x00\x01V1")
        return self._reply("sFA", "", (2).to_bytes(2, "big"))

    def config(self) -> ScannerConfig:
        """The configuration set by ``mLMPsetscancfg`` (the rig's until then)."""
        return self.current

    def encode(self, k: int, ranges_m: NDArray[np.float32], echo: NDArray[np.uint16] | None,
               config: ScannerConfig, start_s: float) -> bytes:
        """An ``sSN LMDscandata`` telegram (DIST1, RSSI1 when the model sends intensities)."""
        return profile_frame(config.dialect, k, ranges_m, config, start_s, echo=echo)


#: The emulated device of each dialect (a new family adds its entry).
DEVICES: dict[str, Callable[[ScannerConfig], EmulatedDevice]] = {
    "ldoem": LdoemEmulated,
    "paper": StreamingDevice,
    "ldrobot": _ldrobot,
    "ldrobot_ld14": _ldrobot,
    "cola_b": SickColaDevice,
    "cola_a": SickColaDevice,
    "scip": ScipDevice,
}


def emulated_device(scanner: ScannerConfig) -> EmulatedDevice:
    """A fresh emulated device for the scanner's dialect."""
    from scanpipe.errors import SimulationError

    if scanner.dialect not in DEVICES:
        raise SimulationError(f"dialect {scanner.dialect!r}: no emulated device; emulated: "
                              f"{', '.join(DEVICES)}")
    return DEVICES[scanner.dialect](scanner)
