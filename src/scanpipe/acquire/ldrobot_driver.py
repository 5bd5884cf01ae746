"""The recorder driver of the LDRobot LD06 / LD19 / STL-27L (dialect ``ldrobot``) and LD14 /
LD14P (``ldrobot_ld14``: the same packets, angles corrected).

These scanners stream from power-on and take no command on their serial line, so starting
and stopping send nothing: the client opens the port (``scanner.transport = serial``,
``serial_url``, ``baudrate``), records every byte and closes it; the head keeps spinning.
:meth:`LdrobotDriver.feed` counts the revolutions (profiles) the bytes complete, for
step-and-scan waits and continuous mode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from scanpipe.protocol.ldrobot import RevolutionDecoder
from scanpipe.rig import ScannerConfig

if TYPE_CHECKING:
    from scanpipe.acquire.driver_types import ScannerClient


class LdrobotDriver:
    """No commands; revolutions counted in the received bytes."""

    def __init__(self, scanner: ScannerConfig) -> None:
        self.scanner = scanner
        self._decoder = RevolutionDecoder(
            sl_correction=scanner.dialect == "ldrobot_ld14")

    def start(self, client: ScannerClient) -> None:
        """Nothing to send: the device is already streaming."""
        client.ident = f"LDRobot {self.scanner.model or 'scanner'} (no identification on the link)"

    def stop(self, client: ScannerClient) -> None:
        """Nothing to send: there is no stop command (closing the port ends the recording)."""

    def feed(self, data: bytes) -> tuple[int, list[object]]:
        """Revolutions completed by ``data``; never a reply."""
        return len(self._decoder.feed(data)), []
