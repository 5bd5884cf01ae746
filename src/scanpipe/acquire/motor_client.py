"""The motor controller's serial link (the line protocol of docs/motor-link.md).

Opened with :func:`serial.serial_for_url`, so a device (``/dev/ttyUSB0``), a pseudo-terminal
(the emulator's) or ``loop://`` all work. Every byte read or written goes to the recording
(``/motor/stream``) before it is interpreted; every position report becomes a ``/motor/state``
message. Commands wait for the controller's OK / ERR reply.

The client never asks for a move that would leave ``0 … pulse_limit``: the controller refuses
such a move too, but a driver that relies on the far end for safety is one firmware bug away
from winding a cable round the axis.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from scanpipe.acquire.sink import Link
from scanpipe.errors import DeviceError
from scanpipe.rig import MotorConfig

RX, TX = 0, 1
POLL_S = 0.05


class MotorSink(Protocol):
    """Where link bytes and motor states go (:class:`~scanpipe.acquire.sink.RecordingSink`)."""

    def write_stream(self, link: Link, data: bytes, direction: int, log_time_ns: int) -> None: ...

    def write_motor_state(self, log_time_ns: int, step_count: int, target_step_count: int,
                          moving: bool, device_time_us: int) -> None: ...


@dataclass(frozen=True)
class MotorState:
    """One position report: pulse count, target, whether it turns, the controller's clock."""

    step_count: int
    target_step_count: int
    moving: bool
    device_time_us: int
    log_time_ns: int


@dataclass(frozen=True)
class Reply:
    """A controller reply to a command: OK (with optional text) or ERR with its reason."""

    ok: bool
    text: str


def parse_position(fields: list[str]) -> tuple[int, int, bool, int]:
    """``POS <count> <target> <moving 0|1> <time_us>`` fields after ``POS``."""
    count, target, moving, time_us = fields[:4]
    return int(count), int(target), moving == "1", int(time_us)


class MotorClient:
    """A connection to the motor controller.

    Thread-safe: the recorder's main thread sends commands while the reader thread parses
    replies and reports, and a disconnect handler may send STOP from another thread.
    """

    def __init__(
        self,
        motor: MotorConfig,
        sink: MotorSink,
        reply_timeout_s: float = 2.0,
        clock_ns: Callable[[], int] = time.time_ns,
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.motor = motor
        self.sink = sink
        self.reply_timeout_s = reply_timeout_s
        self.clock_ns = clock_ns
        self.on_error = on_error
        self._port: Any = None
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._command_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._replies: queue.Queue[Reply] = queue.Queue()
        self._state_changed = threading.Condition()
        self._state: MotorState | None = None
        self._line = bytearray()
        self.reports = 0
        self.ident = ""

    # -- connection ------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the serial URL and start reading."""
        import serial

        url = self.motor.serial_url
        try:
            self._port = serial.serial_for_url(url, baudrate=self.motor.baudrate, timeout=POLL_S)
        except (serial.SerialException, OSError, ValueError) as err:
            raise DeviceError(f"motor controller at {url!r}: cannot open ({err}); check "
                              "motor.serial_url in the rig file") from err
        self._closing.clear()
        self._reader = threading.Thread(target=self._read_loop, name="motor-reader", daemon=True)
        self._reader.start()

    def close(self) -> None:
        """Stop reading and close the port (does not stop the motor: call :meth:`stop`)."""
        self._closing.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        if self._port is not None:
            with contextlib.suppress(OSError):
                self._port.close()
            self._port = None

    @property
    def connected(self) -> bool:
        """Whether the port is open."""
        return self._port is not None

    # -- state -----------------------------------------------------------------------------

    @property
    def state(self) -> MotorState | None:
        """The last reported state (None before the first report)."""
        return self._state

    def wait_for_state(self, predicate: Callable[[MotorState], bool], timeout_s: float,
                       stop: threading.Event | None = None) -> MotorState | None:
        """Wait for a report that satisfies ``predicate``; None on time-out or ``stop``."""
        deadline = time.monotonic() + timeout_s
        with self._state_changed:
            while True:
                if self._state is not None and predicate(self._state):
                    return self._state
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (stop is not None and stop.is_set()):
                    return None
                self._state_changed.wait(min(remaining, POLL_S))

    # -- commands --------------------------------------------------------------------------

    def command(self, line: str, timeout_s: float | None = None) -> Reply:
        """Send one command line and wait for its OK / ERR."""
        with self._command_lock:
            while not self._replies.empty():  # drop stale replies of timed-out commands
                self._replies.get_nowait()
            self._write((line + "\n").encode("ascii"))
            try:
                return self._replies.get(
                    timeout=self.reply_timeout_s if timeout_s is None else timeout_s)
            except queue.Empty:
                raise DeviceError(f"motor controller: no reply to {line!r} within "
                                  f"{self.reply_timeout_s:g} s") from None

    def _checked(self, line: str) -> Reply:
        reply = self.command(line)
        if not reply.ok:
            raise DeviceError(f"motor controller refused {line!r}: {reply.text}")
        return reply

    def query_position(self) -> MotorState:
        """Ask for a position report and return it."""
        before = self.reports
        self._checked("POS?")
        state = self.wait_for_state(lambda s: self.reports > before, self.reply_timeout_s)
        if state is None:
            raise DeviceError("motor controller: no position report after POS?")
        return state

    def check_move(self, pulses: int, from_count: int) -> None:
        """Raise :class:`DeviceError` if a move would leave ``0 … pulse_limit``; sends nothing."""
        target = from_count + pulses
        limit = self.motor.pulse_limit
        if not 0 <= target <= limit:
            raise DeviceError(f"motor: a move of {pulses:+d} pulses from {from_count} would reach "
                              f"{target}, outside 0…{limit} (motor.pulse_limit); not sent")

    def move(self, pulses: int) -> None:
        """Start a relative move of ``pulses`` (signed); returns once the controller accepts it.

        Checked against the pulse limit on this side first, from the last reported count.
        """
        state = self._state or self.query_position()
        self.check_move(pulses, state.step_count)
        self._checked(f"MOVE {pulses:+d}")

    def identify(self) -> tuple[str, int | None]:
        """``ID?``: the firmware's name and its pulse limit (None if it does not say)."""
        self.ident = ""
        reply = self.command("ID?")
        if not reply.ok:
            return "", None
        *name, limit = self.ident.split() or [""]
        return " ".join(name), int(limit) if limit.isdigit() else None

    def set_accel(self, accel_hz_per_s: float) -> None:
        """Set the ramp of the pulse rate (ACCEL)."""
        self._checked(f"ACCEL {accel_hz_per_s:g}")

    def set_rate(self, rate_hz: float) -> None:
        """Set the cruising pulse rate of the next moves (RATE)."""
        self._checked(f"RATE {rate_hz:g}")

    def stop(self) -> None:
        """Stop any move at once (STOP); the controller keeps the count it reached."""
        self.command("STOP")

    def zero(self) -> None:
        """Make the current position the controller's zero."""
        self._checked("ZERO")

    # -- I/O -------------------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        port = self._port
        if port is None:
            raise DeviceError("motor controller: not connected")
        with self._write_lock:
            self.sink.write_stream("motor", data, TX, self.clock_ns())
            try:
                port.write(data)
                port.flush()
            except Exception as err:  # pyserial raises SerialException or OSError
                raise DeviceError(f"motor controller: write failed ({err})") from err

    def _read_loop(self) -> None:
        port = self._port
        while not self._closing.is_set() and port is not None:
            try:
                data = port.read(max(1, getattr(port, "in_waiting", 0) or 1))
            except Exception as err:  # pyserial: SerialException, OSError
                if not self._closing.is_set() and self.on_error is not None:
                    self.on_error(f"serial read failed ({err})")
                return
            if not data:
                continue
            now = self.clock_ns()
            self.sink.write_stream("motor", bytes(data), RX, now)
            self._line += data
            while b"\n" in self._line:
                raw, _, rest = self._line.partition(b"\n")
                self._line = bytearray(rest)
                self._handle(raw.decode("ascii", "replace").strip(), now)

    def _handle(self, line: str, now_ns: int) -> None:
        if not line:
            return
        head, *fields = line.split()
        if head == "OK":
            self._replies.put(Reply(True, " ".join(fields)))
        elif head == "ERR":
            self._replies.put(Reply(False, " ".join(fields) or "error"))
        elif head == "ID":
            self.ident = " ".join(fields)
        elif head == "POS":
            try:
                count, target, moving, time_us = parse_position(fields)
            except (ValueError, IndexError):
                return
            state = MotorState(count, target, moving, time_us, now_ns)
            self.sink.write_motor_state(now_ns, count, target, moving, time_us)
            with self._state_changed:
                self._state = state
                self.reports += 1
                self._state_changed.notify_all()
