"""Recorder drivers for the scanner families beyond the LD-OEM and the paper's stream.

:class:`~scanpipe.acquire.scanner_client.ScannerClient` owns the link (TCP or serial), the
recording of every byte and the profile bookkeeping; a driver knows the device's commands:

- ``start(client)``: configure within the device's limits and start streaming, with
  ``client.send(bytes)`` and ``client.request(bytes, what, accept)`` (waits for a reply that
  ``feed`` returned and ``accept`` takes); raise :class:`~scanpipe.errors.DeviceError` on a
  refusal;
- ``stop(client)``: stop streaming (best effort, the link is closed after it);
- ``feed(data)``: received bytes in (chunks of any size); the number of profiles they
  complete and the replies to requests they hold.

A new family adds a class and its entry in :data:`DRIVERS` (keyed by dialect name).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from scanpipe.acquire.driver_types import ScannerClient, ScannerDriver
from scanpipe.acquire.scip_driver import ScipDriver
from scanpipe.errors import DeviceError
from scanpipe.rig import ScannerConfig


@dataclass(frozen=True)
class ColaReply:
    """A CoLa-B answer: ``sEA LMDscandata`` + its argument bytes, ``sFA`` + error code …"""

    kind: str
    name: str
    args: bytes


class SickColaDriver:
    """SICK CoLa-B (LMS1xx on TCP 2112, TiM5xx) or CoLa-A (LMS1xx on TCP 2111: the same
    telegrams as ASCII tokens between STX and ETX), after the rig's dialect.

    Start: ``sMN SetAccessMode`` (authorised client), then — for a model with more than one
    mode — ``sMN mLMPsetscancfg`` with the rig's rate, step and sector (status 0 expected)
    and ``sMN Run``; then ``sEN LMDscandata 1``. Stop: ``sEN LMDscandata 0``. A refusal
    (``sFA``, a non-zero status) is a :class:`DeviceError` naming it.
    """

    def __init__(self, scanner: ScannerConfig) -> None:
        from scanpipe.protocol import framing, sick_cola

        self.scanner = scanner
        self.ascii = scanner.dialect == "cola_a"
        self.reader: framing.FrameReader | sick_cola.AsciiFrameReader = (
            sick_cola.AsciiFrameReader(sick_cola.MAX_PAYLOAD_BYTES * 3, parse=False)
            if self.ascii else framing.FrameReader(sick_cola.MARKER, 0,
                                                   sick_cola.MAX_PAYLOAD_BYTES, confirm=False))

    def _ask(self, client: ScannerClient, kind: str, name: str, args: bytes,
             answer_kind: str) -> ColaReply:
        from scanpipe.protocol import sick_cola

        encode = sick_cola.command_ascii if self.ascii else sick_cola.command
        reply = client.request(encode(kind, name, args), f"{kind} {name}",
                               lambda r: isinstance(r, ColaReply) and (
                                   r.name == name or r.kind == "sFA"))
        assert isinstance(reply, ColaReply)
        if reply.kind == "sFA" or reply.kind != answer_kind:
            code = int.from_bytes(reply.args[:2], "big") if reply.kind == "sFA" else -1
            raise DeviceError(f"scanner refused {kind} {name} (sFA error {code}; "
                              "2 = unknown method, 10 = access denied)")
        return reply

    def start(self, client: ScannerClient) -> None:
        """Log in, configure within the model's modes, start the stream."""
        from scanpipe.protocol import sick_cola
        from scanpipe.scanner_models import model_of

        s = self.scanner
        model = model_of(s.model, s.dialect)
        if model is not None and len(model.modes) > 1:
            password = sick_cola.CLIENT_PASSWORD.to_bytes(4, "big")
            login = self._ask(client, "sMN", "SetAccessMode",
                              bytes([sick_cola.ACCESS_LEVEL_CLIENT]) + password, "sAN")
            if login.args[:1] != b"\x01":
                raise DeviceError("scanner refused the log-in (sMN SetAccessMode)")
            last = s.end_angle_deg - s.beam_step_deg
            answer = self._ask(client, "sMN", "mLMPsetscancfg", sick_cola.scan_config_args(
                s.scan_hz, s.beam_step_deg, s.start_angle_deg, last), "sAN")
            status = answer.args[0] if answer.args else -1
            if status != 0:
                meaning = {1: "frequency", 2: "resolution", 3: "frequency and resolution",
                           4: "scan area"}.get(status, "unknown")
                raise DeviceError(f"scanner refused the scan configuration "
                                  f"{s.scan_hz:g} Hz, {s.beam_step_deg:g}°, "
                                  f"{s.start_angle_deg:g}…{last:g}° (status {status}: "
                                  f"{meaning} not possible)")
            self._ask(client, "sMN", "Run", b"", "sAN")
        answer = self._ask(client, "sEN", "LMDscandata", b"\x01", "sEA")
        if answer.args[:1] != b"\x01":
            raise DeviceError("scanner did not confirm sEN LMDscandata 1")

    def stop(self, client: ScannerClient) -> None:
        """``sEN LMDscandata 0``, waiting briefly for its answer."""
        self._ask(client, "sEN", "LMDscandata", b"\x00", "sEA")

    def feed(self, data: bytes) -> tuple[int, list[object]]:
        """Scan telegrams counted, other telegrams returned as replies."""
        from scanpipe.errors import ProtocolError
        from scanpipe.protocol import sick_cola

        profiles, replies = 0, list[object]()
        for frame in self.reader.feed(data):
            if not frame.checksum_ok:
                continue
            if frame.payload[:16] in sick_cola.COMMANDS:  # the same in both flavours
                profiles += 1
                continue
            if frame.payload[:4] == b"sFA " and not self.ascii:
                replies.append(ColaReply("sFA", "", frame.payload[4:]))
                continue
            try:
                if self.ascii:
                    kind, name, args = sick_cola.parse_command_ascii(frame.payload)
                else:
                    kind, name, args = sick_cola.parse_command(frame.payload)
            except ProtocolError:
                continue
            replies.append(ColaReply(kind, name, args))
        return profiles, replies


#: The driver of each dialect that has one (``ldoem`` and ``paper`` live in the client).
DRIVERS: dict[str, Callable[[ScannerConfig], ScannerDriver]] = {
    "cola_b": SickColaDriver, "cola_a": SickColaDriver, "scip": ScipDriver}


def _register() -> None:
    from scanpipe.acquire.ldrobot_driver import LdrobotDriver

    DRIVERS["ldrobot"] = LdrobotDriver
    DRIVERS["ldrobot_ld14"] = LdrobotDriver


_register()
