"""The recorder's driver for Hokuyo SCIP 2.0 scanners (URG over serial, UST over TCP).

Start: ``VV`` (who is there; answered as SCIP 1.1 does — the echo and a one-character status
``E`` — the driver sends ``SCIP2.0``, as urg_library does, and asks ``VV`` again in 2.0),
``PP`` (its geometry: the reply is recorded, so the decoder reads ARES/AFRT from the
recording), ``BM`` (laser on), then ``MD`` (``ME`` when the model sends intensities) over the
rig's sector with scan count ``00``: the device streams until ``QT``. Step-and-scan and
continuous recording both use the stream; the client counts profiles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from scanpipe.errors import DeviceError
from scanpipe.protocol import scip
from scanpipe.rig import ScannerConfig
from scanpipe.scanner_models import model_of

if TYPE_CHECKING:
    from scanpipe.acquire.driver_types import ScannerClient


#: SCIP 1.1 answers a SCIP 2.0 command with a one-character status (``E``: not a command).
SCIP11_STATUSES = ("E",)


@dataclass(frozen=True)
class ScipReply:
    """A non-scan reply: its command, status code and the whole message."""

    command: str
    status: str
    message: bytes


class ScipDriver:
    """SCIP 2.0 commands for the recorder (see the module docstring)."""

    def __init__(self, scanner: ScannerConfig) -> None:
        from scanpipe.sim.scip_device import scan_steps, spec_for

        self.scanner = scanner
        self.spec = spec_for(scanner)
        self.reader = scip.ScipReader()
        model = model_of(scanner.model, scanner.dialect)
        self.command = b"ME" if model is not None and model.intensity else b"MD"
        self.steps = scan_steps(scanner, self.spec.geometry)

    def _ask(self, client: ScannerClient, line: bytes, ok: tuple[str, ...] = ("00",)) -> str:
        what = line[:2].decode()

        def accept(reply: object) -> bool:
            return isinstance(reply, ScipReply) and reply.command == what

        reply = client.request(line + b"\n", f"SCIP {what}", accept)
        assert isinstance(reply, ScipReply)
        if reply.status not in ok:
            raise DeviceError(f"scanner: {what} refused with status {reply.status} "
                              f"({scip.status_meaning(reply.status)})")
        return reply.status

    def start(self, client: ScannerClient) -> None:
        """Identify (switching a SCIP 1.1 device to 2.0), read the geometry, laser on, stream
        the rig's sector."""
        try:
            status = self._ask(client, b"VV", ok=("00", *SCIP11_STATUSES))
        except DeviceError as err:
            if "no reply" not in str(err):
                raise
            # A device in SCIP 1.1 might leave a SCIP 2.0 command unanswered: the switch is
            # tried before giving up (no answer to it either: one line naming both).
            self._switch_to_scip2(client, "it did not answer VV", unanswered=str(err))
            status = ""
        else:
            if len(status) == 1:
                self._switch_to_scip2(client, f"it answered VV with the one-character "
                                              f"status {status!r}")
        if len(status) != 2:
            self._ask(client, b"VV")
        self._ask(client, b"PP")
        self._ask(client, b"BM", ok=("00", "02"))
        start, end, cluster = self.steps
        self._ask(client, b"%s%04d%04d%02d%01d%02d" % (self.command, start, end, cluster, 0, 0))

    def _switch_to_scip2(self, client: ScannerClient, why: str, unanswered: str = "") -> None:
        """``SCIP2.0``, as urg_library sends when ``QT`` is answered ``E`` (SCIP 1.1): the
        device answered as SCIP 1.1 does (``why``), or not at all (``unanswered``: that
        time-out). A refusal, or no answer either, is one line."""
        def accept(reply: object) -> bool:
            return isinstance(reply, ScipReply) and reply.command == "SC"

        try:
            reply = client.request(scip.SCIP20_SWITCH + b"\n",
                                   "SCIP2.0 (the switch from SCIP 1.1)", accept)
        except DeviceError as err:
            if not unanswered:
                raise
            raise DeviceError(
                f"{unanswered}, nor to SCIP2.0 (the switch from SCIP 1.1): is it a Hokuyo on "
                "this port, at this baud rate, and powered?") from err
        assert isinstance(reply, ScipReply)
        if reply.status != "0":
            raise DeviceError(
                f"scanner: the Hokuyo speaks SCIP 1.1 ({why}) and refused the switch to SCIP "
                f"2.0 ('SCIP2.0' answered {reply.status!r}); scanpipe records SCIP 2.0 only: "
                "update the sensor's firmware to one with SCIP 2.0 (Hokuyo), or record it with "
                "another tool")

    def stop(self, client: ScannerClient) -> None:
        """``QT``: stop streaming and switch the laser off."""
        client.send(b"QT\n")

    def feed(self, data: bytes) -> tuple[int, list[object]]:
        """Scans completed by ``data``, and the other replies in it."""
        scans = 0
        replies: list[object] = []
        for frame in self.reader.feed(data):
            if frame.parsed is not None:
                scans += int(frame.checksum_ok)
                continue
            lines = frame.payload.split(b"\n")
            replies.append(ScipReply(lines[0][:2].decode("ascii", "replace"),
                                     lines[1][:2].decode("ascii", "replace"), frame.payload))
        return scans, replies
