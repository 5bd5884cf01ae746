"""A scanner that streams from the moment its link is up and ignores what it is sent (the
``paper`` dialect; LDRobot units, whose device derives from it). Its own module so that the
dialects' device modules can build on it without importing :mod:`scanpipe.sim.devices`."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanpipe.rig import ScannerConfig
from scanpipe.sim.wire import profile_frame


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
        return profile_frame(config.dialect, k, ranges_m, config, start_s, echo=echo)
