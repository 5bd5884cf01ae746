"""One clock for every emulator: simulation seconds that run ``speedup`` times faster than
real time, and the host-clock time (ns since the epoch) that a simulation instant falls on."""

from __future__ import annotations

import threading
import time


class SimClock:
    """Simulation time since :meth:`start` (or construction), at ``speedup`` × real time."""

    def __init__(self, speedup: float = 1.0) -> None:
        if not speedup > 0:
            from scanpipe.errors import SimulationError

            raise SimulationError(f"speed-up {speedup!r}: must be greater than 0")
        self.speedup = speedup
        self._t0 = time.monotonic()
        self._wall0_ns = time.time_ns()

    def now_s(self) -> float:
        """Simulation seconds since the start."""
        return (time.monotonic() - self._t0) * self.speedup

    def wall_ns(self, sim_s: float) -> int:
        """The host-clock time (ns since the epoch) of simulation instant ``sim_s``."""
        return self._wall0_ns + round(sim_s / self.speedup * 1e9)

    def sleep_until(self, sim_s: float, stop: threading.Event | None = None) -> bool:
        """Sleep until simulation time ``sim_s``; False if ``stop`` was set meanwhile."""
        while True:
            remaining = (sim_s - self.now_s()) / self.speedup
            if remaining <= 0:
                return not (stop is not None and stop.is_set())
            if stop is not None:
                if stop.wait(min(remaining, 0.05)):
                    return False
            else:
                time.sleep(min(remaining, 0.05))
