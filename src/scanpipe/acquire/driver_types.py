"""What a scanner driver and the scanner client see of each other (typing only).

Below the drivers (``scanner_drivers``, ``scip_driver``, ``ldrobot_driver``) and the client
(``scanner_client``), so a driver module can name the client without importing the driver table
that imports it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol


class ScannerClient(Protocol):
    """What a driver uses of :class:`scanpipe.acquire.scanner_client.ScannerClient`."""

    #: The device's identification, shown in the recording's events.
    ident: str

    def send(self, frame: bytes) -> None:
        """Write bytes to the scanner (recorded as TX)."""
        ...

    def request(self, data: bytes, what: str, accept: Callable[[object], bool],
                timeout_s: float | None = None) -> object:
        """Send and wait for the first reply ``accept`` takes."""
        ...


class ScannerDriver(Protocol):
    """A scanner family's commands (see the module docstring)."""

    def start(self, client: ScannerClient) -> None:
        """Configure and start streaming."""
        ...

    def stop(self, client: ScannerClient) -> None:
        """Stop streaming."""
        ...

    def feed(self, data: bytes) -> tuple[int, list[object]]:
        """Profiles completed by ``data`` and the replies in it."""
        ...
