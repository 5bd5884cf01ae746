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
from typing import TYPE_CHECKING, Protocol

from scanpipe.acquire.scip_driver import ScipDriver
from scanpipe.rig import ScannerConfig

if TYPE_CHECKING:
    from scanpipe.acquire.scanner_client import ScannerClient


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


#: The driver of each dialect that has one (``ldoem`` and ``paper`` live in the client).
DRIVERS: dict[str, Callable[[ScannerConfig], ScannerDriver]] = {"scip": ScipDriver}
