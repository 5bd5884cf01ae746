"""An emulated Hokuyo scanner (UST-10LX on TCP, URG-04LX on a serial line): SCIP 2.0 commands.

Answers ``VV``/``PP``/``II`` (version, parameters, state), ``BM``/``QT`` (laser on / off and
stop), ``RS`` (reset), ``MD``/``ME``/``MS`` (stream with start/end step, cluster count, skip
and scan count: ``00`` = until ``QT``) and ``GD``/``GE``/``GS`` (one scan). An unknown command
gets status ``0E``; parameters out of range the command's own error code (SCIP 2.0 numbering).

Start modes (:attr:`ScipDevice.protocol`): ``2.0`` (the default); ``1.1``, a URG-04LX of older
firmware, which answers every SCIP 2.0 command with its echo and the one-character SCIP 1.1
status ``E`` (what urg_library reads from ``QT`` to tell SCIP 1.1) until it receives
``SCIP2.0``, answered ``0``, and speaks SCIP 2.0 from then on; ``1.1-silent``, the same but
leaving SCIP 2.0 commands unanswered; ``1.1-only``, firmware without SCIP 2.0, which answers
``SCIP2.0`` with ``E`` too.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanpipe.protocol import scip
from scanpipe.rig import ScannerConfig
from scanpipe.sim.wire import device_clock_ms


@dataclass(frozen=True)
class HokuyoSpec:
    """What a Hokuyo model reports and accepts."""

    model: str
    geometry: scip.Geometry
    amin: int
    amax: int
    dmin_mm: int
    dmax_mm: int


SPECS: dict[str, HokuyoSpec] = {
    "ust10lx": HokuyoSpec("UST-10LX", scip.UST_GEOMETRY, 0, 1080, 60, 10000),
    "urg04lx": HokuyoSpec("URG-04LX", scip.URG04_GEOMETRY, 44, 725, 20, 5600),
}


def spec_for(scanner: ScannerConfig) -> HokuyoSpec:
    """The Hokuyo model of a rig's scanner (by ``model``, else by its beam step)."""
    if scanner.model in SPECS:
        return SPECS[scanner.model]
    geometry = scip.geometry_for_step(scanner.beam_step_deg)
    return SPECS["urg04lx"] if geometry == scip.URG04_GEOMETRY else SPECS["ust10lx"]


def scan_steps(scanner: ScannerConfig, geometry: scip.Geometry) -> tuple[int, int, int]:
    """(start step, end step, cluster) covering a rig's sector."""
    cluster = max(1, round(scanner.beam_step_deg / geometry.step_deg))
    start = geometry.step_of(scanner.start_angle_deg)
    end = start + scanner.samples_per_profile * cluster - 1
    return start, end, cluster


_STREAM = re.compile(rb"^(M[DSE])(\d{4})(\d{4})(\d{2})(\d)(\d{2})(;[ -~]{0,16})?$")
_SINGLE = re.compile(rb"^(G[DSE])(\d{4})(\d{4})(\d{2})(;[ -~]{0,16})?$")


@dataclass
class _Stream:
    command: bytes
    start: int
    end: int
    cluster: int
    skip: int
    count: int  # 0 = until QT
    single: bool
    sent: int = 0


#: The protocols a device may start in (module docstring).
START_PROTOCOLS = ("2.0", "1.1", "1.1-silent", "1.1-only")


class ScipDevice:
    """The device side of SCIP 2.0 (see the module docstring); ``protocol``: its start mode."""

    def __init__(self, scanner: ScannerConfig, protocol: str = "2.0") -> None:
        if protocol not in START_PROTOCOLS:
            raise ValueError(f"SCIP start protocol {protocol!r}: allowed "
                             f"{', '.join(START_PROTOCOLS)}")
        self.protocol = protocol
        self.scanner = scanner
        self.spec = spec_for(scanner)
        self.streaming = False
        self.laser_on = False
        self.stream: _Stream | None = None
        self.requests: list[str] = []
        self._line = bytearray()

    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        """Answer every complete command line (LF or CR ends one)."""
        replies: list[bytes] = []
        self._line += data.replace(b"\r", b"\n")
        while b"\n" in self._line:
            line, _, rest = bytes(self._line).partition(b"\n")
            self._line = bytearray(rest)
            reply = self._handle(line, now_s) if line else b""
            if reply:  # a single scan's reply is the scan; a silent device answers nothing
                replies.append(reply)
        self.streaming = self.stream is not None
        return replies

    def _handle(self, line: bytes, now_s: float) -> bytes:
        self.requests.append(line[:2].decode("ascii", "replace"))
        if self.protocol != "2.0":
            # SCIP 1.1: echo and a one-character status, no check character.
            if line == scip.SCIP20_SWITCH and self.protocol != "1.1-only":
                self.protocol = "2.0"
                return line + b"\n0\n\n"
            return b"" if self.protocol == "1.1-silent" else line + b"\nE\n\n"
        if line == scip.SCIP20_SWITCH:
            return line + b"\n" + scip.status_line("0E") + b"\n"  # already SCIP 2.0
        command = line[:2]
        spec = self.spec
        if command == b"VV":
            return scip.parameter_reply(line, {
                "VEND": "Hokuyo Automatic Co., Ltd.", "PROD": spec.model,
                "FIRM": "emulated (scanpipe)", "PROT": "SCIP 2.0", "SERI": "H0000000"})
        if command == b"PP":
            return scip.parameter_reply(line, scip.pp_fields(
                spec.geometry, spec.model, spec.dmin_mm, spec.dmax_mm, spec.amin, spec.amax))
        if command == b"II":
            return scip.parameter_reply(line, {
                "MODL": spec.model, "LASR": "ON" if self.laser_on else "OFF",
                "SCSP": str(spec.geometry.scan_rpm), "MESM": "Measuring mode",
                "SBPS": "Ethernet" if self.scanner.transport == "tcp" else "USB",
                "TIME": scip.encode_values(np.array([device_clock_ms(now_s)
                                                     % scip.TIMESTAMP_WRAP_MS]), 4).decode(),
                "STAT": "Sensor works well."})
        if command == b"BM":
            status = "02" if self.laser_on else "00"
            self.laser_on = True
            return line + b"\n" + scip.status_line(status) + b"\n"
        if command in (b"QT", b"RS"):
            self.stream = None
            self.laser_on = False
            return line + b"\n" + scip.status_line("00") + b"\n"
        if command in scip.DATA_COMMANDS:
            return self._start(line)
        return line + b"\n" + scip.status_line("0E") + b"\n"

    def _start(self, line: bytes) -> bytes:
        single = line[:1] == b"G"
        match = (_SINGLE if single else _STREAM).match(line)
        if match is None:
            return line + b"\n" + scip.status_line("0C") + b"\n"
        start, end, cluster = int(match[2]), int(match[3]), max(1, int(match[4]))
        skip = 0 if single else int(match[5])
        count = 1 if single else int(match[6])
        spec = self.spec
        status = ("01" if start < spec.amin or start > spec.amax
                  else "04" if end > spec.amax else "05" if end < start else "00")
        if status != "00":
            return line + b"\n" + scip.status_line(status) + b"\n"
        self.laser_on = True
        self.stream = _Stream(line[:2], start, end, cluster, skip, count, single)
        # A stream's reply carries no data; a single scan's reply is the scan itself.
        return b"" if single else line + b"\n" + scip.status_line("00") + b"\n"

    def config(self) -> ScannerConfig:
        """The sector and step the host asked for (the rig's until it asks)."""
        s = self.stream
        if s is None:
            return self.scanner
        g = self.spec.geometry
        samples = -(-(s.end - s.start + 1) // s.cluster)
        start_deg = g.angle_deg(s.start)
        step = s.cluster * g.step_deg
        scan_hz = g.scan_rpm / 60.0 / (s.skip + 1) if g.scan_rpm else self.scanner.scan_hz
        return self.scanner.model_copy(update={
            "beam_step_deg": step, "start_angle_deg": start_deg,
            "end_angle_deg": start_deg + samples * step, "scan_hz": scan_hz})

    def encode(self, k: int, ranges_m: NDArray[np.float32], echo: NDArray[np.uint16] | None,
               config: ScannerConfig, start_s: float) -> bytes:
        """One scan message; counts down a counted stream."""
        s = self.stream
        if s is None:
            return b""
        s.sent += 1
        remaining = 0 if s.count == 0 else max(s.count - s.sent, 0)
        if s.count and s.sent >= s.count:
            self.stream = None
            self.streaming = False
        return scip.encode_scan(s.command, s.start, s.end, s.cluster, device_clock_ms(start_s),
                                ranges_m, echo, skip=s.skip, remaining=remaining,
                                status="00" if s.single else "99")
