"""The motor controller's serial link (the line protocol of docs/motor-link.md).

Opened with :func:`serial.serial_for_url`, so a device (``/dev/ttyUSB0``), a pseudo-terminal
(the emulator's) or ``loop://`` all work. Every byte read or written goes to the recording
(``/motor/stream``) before it is interpreted; every position report becomes a ``/motor/state``
message. Commands wait for the controller's OK / ERR reply.

The client never asks for a move whose ABSOLUTE target (pulses from the controller's power-on
position, learnt with ``TRAVEL?``) would leave ``0 … limit``, where the limit is the smaller of
the rig's (``motor.pulse_limit``, none with ``motor.unlimited_travel``) and the controller's own.
The controller refuses such a move too, but a driver that relies on the far end for safety is
one firmware bug away from winding a cable round the axis. ``ZERO`` moves only the origin of the
reported count; it never resets the absolute position the limit is checked on.
"""

from __future__ import annotations

import contextlib
import queue
import re
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
#: The reply heads of the controller: a line whose first word is none of them is searched for
#: one (line noise before a reply on the serial link).
_HEADS = re.compile(r"(?<![A-Za-z])(OK|ERR|ID|TRAVEL|POS)(?= |$)")
#: Commands that may be sent again when their reply was lost (the same effect twice).
_IDEMPOTENT = ("ID?", "TRAVEL?", "POS?", "ZERO", "RATE", "ACCEL", "STOP")
#: Reports believed as they come after a MOVE, ZERO or STOP (or at the start).
_ANCHOR_REPORTS = 2
#: Consecutive implausible position reports after which the newest is believed (re-anchor).
_REANCHOR_AFTER = 3
#: A line longer than this without a newline is noise: only its tail is kept.
_MAX_LINE = 4096


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
class Travel:
    """``TRAVEL?``: the absolute position (pulses from power-on), the absolute position of
    count 0 (``origin``: count = absolute − origin) and the controller's limit (None: none)."""

    absolute: int
    origin: int
    controller_limit: int | None


@dataclass(frozen=True)
class TravelLimit:
    """The travel limit the host obeys: the smaller of the rig's and the controller's.

    ``pulses`` is None when neither sets one; ``source`` names which applied: ``"rig"``,
    ``"controller"``, ``"rig and controller"`` (equal) or ``"none"``.
    """

    pulses: int | None
    source: str
    rig: int | None
    controller: int | None

    def describe(self) -> str:
        """One phrase: the limit and where it comes from."""
        if self.pulses is None:
            return "no travel limit (motor.unlimited_travel and an unlimited controller)"
        where = {"rig": "motor.pulse_limit of the rig file",
                 "controller": "the controller's own limit",
                 "rig and controller": "the rig file and the controller agree"}[self.source]
        return f"travel limit {self.pulses} pulses from home ({where})"


def applied_limit(rig_limit: int | None, controller_limit: int | None) -> TravelLimit:
    """The smaller of two travel limits (None: that side has none) and which one it is."""
    if rig_limit is None and controller_limit is None:
        return TravelLimit(None, "none", None, None)
    if controller_limit is None or (rig_limit is not None and rig_limit < controller_limit):
        return TravelLimit(rig_limit, "rig", rig_limit, controller_limit)
    source = "rig and controller" if rig_limit == controller_limit else "controller"
    return TravelLimit(controller_limit, source, rig_limit, controller_limit)


def parse_travel(fields: list[str]) -> Travel:
    """``TRAVEL <absolute> <origin> <limit|unlimited>`` fields after ``TRAVEL``."""
    absolute, origin, limit = fields[:3]
    return Travel(int(absolute), int(origin), None if limit == "unlimited" else int(limit))


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
        self._travel_line: list[str] | None = None
        self._travel: Travel | None = None
        # Plausibility of position reports (the link has no checksum: line noise can change a
        # digit): the rate the controller may turn at, and whether a command may have moved the
        # count or the target since the last report.
        self._rate_hz = float(motor.pulse_rate_hz)
        self._anchor_reports = _ANCHOR_REPORTS
        self._implausible_run = 0
        self._velocity: float | None = None  # pulses per second between the last two reports
        self._zeroed = False  # ZERO sent: the next report restarts the count
        self.rejected_reports = 0

    # -- connection ------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the serial URL and start reading."""
        from scanpipe.extras import require

        serial = require("serial", "the motor controller's serial link (record, simulate)")
        url = self.motor.serial_url
        try:
            self._port = serial.serial_for_url(url, baudrate=self.motor.baudrate, timeout=POLL_S)
        except (serial.SerialException, OSError, ValueError) as err:
            raise DeviceError(f"motor controller at {url!r}: cannot open ({err}); check "
                              "motor.serial_url in the rig file") from err
        self._closing.clear()
        self._travel = None  # the controller may have been zeroed or powered off meanwhile
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
        """Send one command line and wait for its OK / ERR. A command whose effect does not
        change when it is repeated (queries, ZERO, RATE, ACCEL, STOP) is sent once more when
        its reply was lost (line noise)."""
        tries = 2 if line.split(" ", 1)[0] in _IDEMPOTENT else 1
        with self._command_lock:
            for attempt in range(tries):
                while not self._replies.empty():  # drop stale replies of timed-out commands
                    self._replies.get_nowait()
                self._zeroed = self._zeroed or line == "ZERO"
                if line.startswith(("MOVE", "ZERO", "STOP")):
                    # The count or the target may jump now, and reports in flight still show
                    # the old ones: the next few are believed as they come.
                    self._anchor_reports = _ANCHOR_REPORTS
                self._write((line + "\n").encode("ascii"))
                try:
                    return self._replies.get(
                        timeout=self.reply_timeout_s if timeout_s is None else timeout_s)
                except queue.Empty:
                    if attempt + 1 == tries:
                        raise DeviceError(f"motor controller: no reply to {line!r} within "
                                          f"{self.reply_timeout_s:g} s") from None
        raise AssertionError("unreachable")

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

    def query_travel(self) -> Travel:
        """``TRAVEL?``: the absolute position, the origin of the count and the controller's limit.

        A controller that does not answer it (firmware 1 reset its only count on ZERO) cannot
        be trusted with the travel limit: :class:`DeviceError`.
        """
        self._travel_line = None
        reply = self.command("TRAVEL?")
        fields = self._travel_line
        if not reply.ok or fields is None:
            raise DeviceError(
                f"motor controller: no answer to TRAVEL? ({reply.text or 'no TRAVEL line'}); it "
                "does not report its absolute position since power-on, so the travel limit "
                "cannot be kept across ZERO: update its firmware (docs/motor-link.md)")
        try:
            travel = parse_travel(fields)
        except (ValueError, IndexError):
            raise DeviceError(f"motor controller: cannot read the TRAVEL line "
                              f"{' '.join(fields)!r}") from None
        self._travel = travel
        return travel

    @property
    def travel(self) -> Travel | None:
        """The last ``TRAVEL?`` answer on this connection (None before the first)."""
        return self._travel

    def limit(self) -> TravelLimit:
        """The travel limit obeyed: the smaller of the rig's and the controller's."""
        travel = self._travel or self.query_travel()
        return applied_limit(self.motor.travel_limit, travel.controller_limit)

    def absolute(self, count: int) -> int:
        """The absolute position (pulses from power-on) of a reported count."""
        travel = self._travel or self.query_travel()
        return count + travel.origin

    def check_move(self, pulses: int, from_count: int) -> None:
        """Raise :class:`DeviceError` if a move of ``pulses`` from the reported count
        ``from_count`` would take the absolute position out of ``0 … limit``; sends nothing."""
        limit = self.limit()
        if limit.pulses is None:
            return
        start = self.absolute(from_count)
        target = start + pulses
        if not 0 <= target <= limit.pulses:
            raise DeviceError(f"motor: a move of {pulses:+d} pulses from absolute {start} would "
                              f"reach {target}, outside 0…{limit.pulses} ({limit.describe()}); "
                              "not sent")

    def move(self, pulses: int) -> None:
        """Start a relative move of ``pulses`` (signed); returns once the controller accepts it.

        Checked against the travel limit on this side first, on the absolute position of the
        last reported count.
        """
        state = self._state or self.query_position()
        self.check_move(pulses, state.step_count)
        try:
            self._checked(f"MOVE {pulses:+d}")
        except DeviceError as err:
            if "no reply" not in str(err):
                raise
            # The reply was lost (line noise), or the command: a relative move must not be
            # sent twice, so ask where the controller is heading.
            now = self.query_position()
            if now.target_step_count != state.step_count + pulses:
                self.check_move(pulses, now.step_count)
                self._checked(f"MOVE {state.step_count + pulses - now.step_count:+d}")

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
        self._rate_hz = max(float(rate_hz), 1.0)

    def stop(self) -> None:
        """Stop any move at once (STOP); the controller keeps the count it reached."""
        self.command("STOP")

    def zero(self) -> Travel:
        """Make the current position count 0 (the origin of reported counts; the absolute
        position and the limit are unchanged); returns the controller's travel after it."""
        self._checked("ZERO")
        self._travel = None
        self.query_position()  # the last report counts from the old origin
        return self.query_travel()

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
            if b"\n" not in self._line and len(self._line) > _MAX_LINE:
                del self._line[:-_MAX_LINE]
            while b"\n" in self._line:
                raw, _, rest = self._line.partition(b"\n")
                self._line = bytearray(rest)
                self._handle(raw.decode("ascii", "replace").strip(), now)

    def _plausible(self, state: MotorState) -> bool:
        """Whether a position report can be believed: since the last one, with no MOVE, ZERO
        or STOP sent, the target is the same and the count moved towards it by no more than
        the pulse rate allows (×1.25 + 2 pulses) in the controller's elapsed time (the first
        :data:`_ANCHOR_REPORTS` after such a command are held to the rate alone, the first after
        ZERO is believed). The link
        has no checksum: a digit changed by line noise would otherwise place profiles at a
        wrong platform angle without a word. Rejected reports are counted (``rejected
        reports``); after :data:`_REANCHOR_AFTER` in a row the newest is believed."""
        previous = self._state
        if previous is None or self._zeroed:
            self._zeroed = False
            self._anchor_reports = max(self._anchor_reports - 1, 0)
            self._implausible_run = 0
            self._velocity = None
            return True
        anchoring = self._anchor_reports > 0
        self._anchor_reports = max(self._anchor_reports - 1, 0)
        elapsed_s = (state.device_time_us - previous.device_time_us) / 1e6
        if elapsed_s <= 0:  # the controller's clock cannot tell: the host's receive times
            elapsed_s = max((state.log_time_ns - previous.log_time_ns) / 1e9, 0.0)
        step = state.step_count - previous.step_count
        towards = previous.target_step_count - previous.step_count
        # A STOP ends a move where the platform stands: at rest, its target set to the count
        # it reached on the way (after the reports in flight have spent the anchor ones).
        stopped_on_the_way = (not state.moving and state.target_step_count == state.step_count
                              and previous.moving)
        ok = abs(step) <= self._rate_hz * elapsed_s * 1.25 + 2 and (anchoring or (
            (state.target_step_count == previous.target_step_count or stopped_on_the_way)
            and step * towards >= 0 and abs(step) <= abs(towards)))
        if ok and not anchoring and self._velocity is not None:
            # On from the last speed: the ramp can change it by at most accel · t (twice the
            # rig's acceleration allowed) plus 2 pulses of rounding.
            lo, hi = sorted((previous.step_count, previous.target_step_count))
            expected = min(max(previous.step_count + self._velocity * elapsed_s, lo), hi)
            accel = 2.0 * float(self.motor.accel_hz_per_s)
            ok = abs(state.step_count - expected) <= accel * elapsed_s ** 2 + 2 + \
                0.01 * abs(step)
        if ok:
            self._implausible_run = 0
            self._velocity = step / elapsed_s if elapsed_s > 0 else None
            return True
        self.rejected_reports += 1
        self._implausible_run += 1
        if self._implausible_run >= _REANCHOR_AFTER:
            self._implausible_run = 0
            self._velocity = None
            return True
        return False

    def _handle(self, line: str, now_ns: int) -> None:
        if not line:
            return
        head = line.split(maxsplit=1)[0]
        if head not in ("OK", "ERR", "ID", "TRAVEL", "POS"):
            found = list(_HEADS.finditer(line))  # noise before the reply: read from its head
            if not found:
                return
            line = line[found[-1].start():]
        head, *fields = line.split()
        if head == "OK":
            self._replies.put(Reply(True, " ".join(fields)))
        elif head == "ERR":
            self._replies.put(Reply(False, " ".join(fields) or "error"))
        elif head == "ID":
            self.ident = " ".join(fields)
        elif head == "TRAVEL":
            self._travel_line = fields
        elif head == "POS":
            try:
                count, target, moving, time_us = parse_position(fields)
            except (ValueError, IndexError):
                return
            state = MotorState(count, target, moving, time_us, now_ns)
            if not self._plausible(state):
                return
            self.sink.write_motor_state(now_ns, count, target, moving, time_us)
            with self._state_changed:
                self._state = state
                self.reports += 1
                self._state_changed.notify_all()
