"""The LDRobot LD06 / LD19 / STL-27L serial link: read, record, count revolutions.

These scanners stream from power-on and take no command, so there is nothing to send: opening
the port starts the recording of their stream and closing it ends it (the device keeps
spinning). Every byte read goes to the recording first (``/scanner/stream``, RX, stamped with
the host clock when read); the client decodes the stream only to count complete revolutions
(profiles), for :meth:`LdrobotClient.wait_for_profiles`. Before opening, the rig's settings are
checked against the model's limits (:func:`scanpipe.device_limits.ldrobot_limit_checks`).

The port is opened with :func:`serial.serial_for_url`: a device (``/dev/ttyUSB0``), a
pseudo-terminal (the virtual device) or any URL pyserial knows. Same interface as
:class:`scanpipe.acquire.scanner_client.ScannerClient`, so the recorder drives either.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import Any

from scanpipe.acquire.scanner_client import ScannerStats, StreamSink
from scanpipe.device_limits import LDROBOT_LIMITS, RangeSettings, ldrobot_limit_checks
from scanpipe.errors import DeviceError
from scanpipe.protocol.ldrobot import RevolutionDecoder

RX = 0
#: Serial read timeout: how often the reader thread looks at its stop flag.
POLL_S = 0.05


class LdrobotClient:
    """The serial link of an LDRobot scanner (module docstring).

    ``on_disconnect(reason)`` is called once from the reader thread when the port fails
    (unplugged) or stays silent for ``silence_s`` (not after :meth:`close`).
    """

    def __init__(self, scanner: RangeSettings, model: str, url: str, sink: StreamSink,
                 on_disconnect: Callable[[str], None] | None = None,
                 clock_ns: Callable[[], int] = time.time_ns, baud: int | None = None,
                 silence_s: float = 2.0) -> None:
        if model not in LDROBOT_LIMITS:
            raise DeviceError(f"scanner model {model!r}: not an LDRobot model; allowed: "
                              f"{', '.join(LDROBOT_LIMITS)}")
        self.scanner = scanner
        self.model = model
        self.url = url
        self.baud = LDROBOT_LIMITS[model].baud if baud is None else baud
        self.sink = sink
        self.on_disconnect = on_disconnect
        self.clock_ns = clock_ns
        self.silence_s = silence_s
        self.stats = ScannerStats()
        self.ident = f"LDRobot {model} (no identification on the link)"
        self.device_clock: tuple[int, int] | None = None  # (device ms, host ns): none asked
        self._port: Any = None
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._profiles_changed = threading.Condition()
        self._profile_times: list[int] = []
        self._connected = False

    @property
    def dialect(self) -> str:
        """The wire dialect."""
        return "ldrobot"

    @property
    def connected(self) -> bool:
        """Whether the port is open and bytes arrive."""
        return self._connected

    def connect(self) -> None:
        """Check the settings against the model, open the port and start reading."""
        import serial

        problems = [f"scanner.{c.name} = {c.value:g} is outside the {self.model} limit "
                    f"({c.limit})" for c in ldrobot_limit_checks(self.scanner, self.model)
                    if not c.ok]
        if problems:
            raise DeviceError("; ".join(problems) + " — fix the rig file before recording")
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.baud, timeout=POLL_S)
        except (serial.SerialException, OSError, ValueError) as err:
            raise DeviceError(f"{self.model} scanner at {self.url!r}: cannot open ({err}); "
                              "check the scanner's serial port in the rig file") from err
        self._closing.clear()
        self._connected = True
        self.stats.connects += 1
        self._reader = threading.Thread(target=self._read_loop, name="ldrobot-reader",
                                        daemon=True)
        self._reader.start()

    def close(self, cancel: bool = True) -> None:
        """Stop reading and close the port (there is no stop command: the head keeps
        spinning; ``cancel`` is accepted for the recorder's sake)."""
        self._closing.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        if self._port is not None:
            with contextlib.suppress(OSError):
                self._port.close()
            self._port = None
        self._connected = False

    def _read_loop(self) -> None:
        import serial

        decoder = RevolutionDecoder()
        reason = ""
        last_data = time.monotonic()
        while not self._closing.is_set():
            try:
                data = self._port.read(1 << 14)
            except (serial.SerialException, OSError) as err:
                reason = f"serial port error ({err})"
                break
            now = self.clock_ns()
            if not data:
                if time.monotonic() - last_data > self.silence_s:
                    reason = f"no byte from the scanner for {self.silence_s:g} s"
                    break
                continue
            last_data = time.monotonic()
            self.sink.write_stream("scanner", bytes(data), RX, now)
            self.stats.rx_bytes += len(data)
            complete = len(decoder.feed(data))
            if complete:
                self._profiles_arrived(complete, now)
        if not self._closing.is_set():
            self._connected = False
            with self._profiles_changed:
                self._profiles_changed.notify_all()
            if self.on_disconnect is not None:
                self.on_disconnect(reason)

    def _profiles_arrived(self, count: int, now_ns: int) -> None:
        with self._profiles_changed:
            self.stats.profiles += count
            self.stats.last_profile_ns = now_ns
            self._profile_times.extend([now_ns] * count)
            del self._profile_times[:-256]
            self._profiles_changed.notify_all()

    def wait_for_profiles(self, after_ns: int, count: int, timeout_s: float,
                          stop: threading.Event | None = None) -> bool:
        """Wait until ``count`` revolutions have been received after ``after_ns`` (host
        clock). False on time-out, on a dropped link or when ``stop`` is set."""
        deadline = time.monotonic() + timeout_s
        with self._profiles_changed:
            while True:
                if sum(1 for t in self._profile_times if t > after_ns) >= count:
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._connected or (stop is not None and stop.is_set()):
                    return False
                self._profiles_changed.wait(min(remaining, POLL_S))
