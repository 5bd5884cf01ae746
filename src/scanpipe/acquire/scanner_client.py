"""The scanner's TCP link, for both dialects.

Every byte read from or written to the socket goes to the recording first (``/scanner/stream``,
RX/TX, stamped with the host clock when read or sent); the client decodes the stream only to
count profiles and to read replies to its own requests. The recording stays the raw truth.

- ``paper``: the scanner streams frames as soon as the connection is open; stopping closes it.
- ``ldoem``: before connecting, the rig's settings are checked against the LD-OEM 1000's limits
  (:func:`scanpipe.device_limits.device_limit_problems`). Then the start-up requests (GET_IDENT,
  GET_STATUS, GET_SYNC_CLOCK, SET_CONFIG of the sector, ROTATE at the head speed, GET_PROFILE
  streaming) are
  sent one by one, each waiting for its reply; a refused request is a :class:`DeviceError`.
  Stopping sends CANCEL_PROFILE and waits briefly for its reply.
- any other dialect: its driver (:data:`scanpipe.acquire.scanner_drivers.DRIVERS`) runs the
  device's own start-up and stop commands and counts profiles in the received bytes.

The link is TCP (``scanner.transport = tcp``: host, port) or a serial line (``serial``:
``serial_url`` opened with :func:`serial.serial_for_url` at ``baudrate`` — a device, a pty).
Before connecting, the rig's settings are checked against the scanner model's limits.
"""

from __future__ import annotations

import contextlib
import queue
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from scanpipe.acquire.driver_types import ScannerDriver
from scanpipe.acquire.scanner_drivers import DRIVERS
from scanpipe.acquire.sink import Link
from scanpipe.errors import DeviceError, ProtocolError
from scanpipe.protocol import ldoem
from scanpipe.protocol.framing import RawFrame
from scanpipe.protocol.profile import angle_to_wire
from scanpipe.protocol.registry import DIALECTS, StreamDecoder
from scanpipe.rig import ScannerConfig
from scanpipe.scanner_models import limit_problems

RX, TX = 0, 1
#: Socket read timeout: how often the reader thread looks at its stop flag.
POLL_S = 0.1
#: Frame counters wrap here (u16: LD-OEM, paper, SICK scan counter).
COUNTER_PERIOD = 1 << 16
#: Profiles that place the head's turns for :meth:`ScannerClient.wait_for_fresh_profiles`
#: (a few seconds: a device's rate error stays far below a scan over them).
FRESH_WINDOW = 64


class StreamSink(Protocol):
    """Where raw link bytes go (:class:`scanpipe.acquire.sink.RecordingSink`)."""

    def write_stream(self, link: Link, data: bytes, direction: int, log_time_ns: int) -> None: ...


@dataclass
class ScannerStats:
    """What the client saw on the link."""

    profiles: int = 0
    rx_bytes: int = 0
    tx_bytes: int = 0
    last_profile_ns: int = 0
    connects: int = 0


class _SerialLink:
    """A serial port with the socket calls the client uses; ``recv`` returns b"" only on a
    closed port (a read time-out raises ``TimeoutError``, like a socket's)."""

    def __init__(self, url: str, baudrate: int) -> None:
        import serial

        try:
            self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=POLL_S)
        except (serial.SerialException, OSError, ValueError) as err:
            raise DeviceError(f"scanner at {url}: cannot open the serial port ({err}); check "
                              "scanner.serial_url") from err

    def recv(self, size: int) -> bytes:
        """Bytes read (at least one), or ``TimeoutError`` when none came within the poll."""
        import serial

        try:
            data: bytes = self.port.read(max(1, min(size, self.port.in_waiting)))
        except (serial.SerialException, OSError) as err:
            raise OSError(str(err)) from err
        if not data:
            raise TimeoutError
        return data

    def sendall(self, data: bytes) -> None:
        """Write everything."""
        import serial

        try:
            self.port.write(data)
        except (serial.SerialException, OSError) as err:
            raise OSError(str(err)) from err

    def close(self) -> None:
        """Close the port."""
        self.port.close()


class ScannerClient:
    """A connection to the scanner that streams profiles into the recording.

    ``on_disconnect(reason)`` is called once from the reader thread when the link drops
    unexpectedly (not after :meth:`close`). Use :meth:`wait_for_profiles` to wait for complete
    profiles received after a moment (step-and-scan).
    """

    def __init__(
        self,
        scanner: ScannerConfig,
        sink: StreamSink,
        on_disconnect: Callable[[str], None] | None = None,
        connect_timeout_s: float = 3.0,
        reply_timeout_s: float = 3.0,
        mask: int = ldoem.MASK_RANGES,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.scanner = scanner
        self.sink = sink
        self.on_disconnect = on_disconnect
        self.connect_timeout_s = connect_timeout_s
        self.reply_timeout_s = reply_timeout_s
        self.mask = mask
        self.clock_ns = clock_ns
        self.stats = ScannerStats()
        self.ident = ""
        self.device_clock: tuple[int, int] | None = None  # (device ms, host ns)
        self._sock: socket.socket | _SerialLink | None = None
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._send_lock = threading.Lock()
        self._profiles_changed = threading.Condition()
        self._profile_times: list[int] = []  # recv times of recent profiles (bounded)
        #: Their frame counters (unwrapped; None where the link gives none): one per head turn.
        self._profile_counters: list[int | None] = []
        self._last_counter: int | None = None
        self._replies: queue.Queue[ldoem.Message] = queue.Queue()
        self._want_profile = threading.Event()
        self._connected = False
        self.driver: ScannerDriver | None = None
        self._driver_replies: queue.Queue[object] = queue.Queue()

    @property
    def dialect(self) -> str:
        """The wire dialect of the rig's scanner."""
        return self.scanner.dialect

    @property
    def connected(self) -> bool:
        """Whether the link is up."""
        return self._connected

    # -- connection -----------------------------------------------------------------------

    def connect(self) -> None:
        """Open the link, run the start-up (ldoem, or the dialect's driver) and start
        streaming profiles."""
        problems = limit_problems(self.scanner)
        if problems:
            raise DeviceError("; ".join(problems) + " — fix the rig file before recording")
        self.driver = DRIVERS[self.dialect](self.scanner) if self.dialect in DRIVERS else None
        link: socket.socket | _SerialLink
        if self.scanner.transport == "serial":
            link = _SerialLink(self.scanner.serial_url, self.scanner.baudrate)
        else:
            host, port = self.scanner.host, self.scanner.port
            try:
                link = socket.create_connection((host, port), timeout=self.connect_timeout_s)
            except OSError as err:
                raise DeviceError(f"scanner at {host}:{port}: cannot connect "
                                  f"({err.strerror or err}); check scanner.host and "
                                  "scanner.port") from err
            link.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            link.settimeout(POLL_S)
        self._sock = link
        self._closing.clear()
        self._replies = queue.Queue()
        self._driver_replies = queue.Queue()
        self._connected = True
        self.stats.connects += 1
        self._reader = threading.Thread(target=self._read_loop, args=(link,),
                                         name="scanner-reader", daemon=True)
        self._reader.start()
        try:
            if self.driver is not None:
                self.driver.start(self)
            elif self.dialect == "ldoem":
                self._ldoem_start()
        except DeviceError:
            self.close(cancel=False)
            raise

    def request(self, data: bytes, what: str, accept: Callable[[object], bool],
                timeout_s: float | None = None) -> object:
        """For drivers: send ``data`` and wait for the first reply (as the driver's ``feed``
        returned it) that ``accept`` takes; :class:`DeviceError` naming ``what`` on time-out
        or a dropped link."""
        self.send(data)
        limit = self.reply_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + limit
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._connected:
                cause = "the link dropped" if not self._connected else "no reply"
                raise DeviceError(f"scanner: {cause} to {what} within {limit:g} s")
            try:
                reply = self._driver_replies.get(timeout=min(remaining, POLL_S))
            except queue.Empty:
                continue
            if accept(reply):
                return reply

    def _ldoem_start(self) -> None:
        s = self.scanner
        ident = self._request(ldoem.get_ident_request(), ldoem.SERVICE_STATUS, ldoem.GET_IDENT)
        self.ident = ident.body.decode("ascii", "replace").strip("\x00 ")
        self._request(ldoem.get_status_request(), ldoem.SERVICE_STATUS, ldoem.GET_STATUS)
        sent_ns = self.clock_ns()
        clock = self._request(ldoem.get_sync_clock_request(), ldoem.SERVICE_CONFIG,
                              ldoem.GET_SYNC_CLOCK)
        received_ns = self.clock_ns()
        # The device's 16-bit ms clock against the host clock, for whoever maps device times.
        try:
            self.device_clock = (clock.u16(0), (sent_ns + received_ns) // 2)
        except ProtocolError as err:
            raise DeviceError(f"scanner: unexpected GET_SYNC_CLOCK reply ({err})") from err
        config = b"".join(angle_to_wire(v).to_bytes(2, "big") for v in (
            s.beam_step_deg, s.start_angle_deg, s.end_angle_deg))
        # SET_CONFIG body: u16 step, start, end in 1/16° (docs/simulation.md).
        self._request(ldoem.request(ldoem.SERVICE_CONFIG, ldoem.SET_CONFIG, config),
                      ldoem.SERVICE_CONFIG, ldoem.SET_CONFIG)
        self._request(ldoem.rotate_request(int(s.scan_hz)), ldoem.SERVICE_WORKING,
                      ldoem.WORKING_ROTATE)
        self._request(ldoem.get_profile_request(0, self.mask), ldoem.SERVICE_MEASURE,
                      ldoem.GET_PROFILE, expect_profile=True)

    def close(self, cancel: bool = True) -> None:
        """Stop streaming (CANCEL_PROFILE for ldoem) and close the link."""
        if self._sock is None:
            return
        if cancel and self._connected and self.driver is not None:
            with contextlib.suppress(DeviceError):
                self.driver.stop(self)
        elif cancel and self._connected and self.dialect == "ldoem":
            # Closing anyway if the reply does not come; the raw stream shows what happened.
            with contextlib.suppress(DeviceError):
                self._request(ldoem.cancel_profile_request(), ldoem.SERVICE_MEASURE,
                              ldoem.CANCEL_PROFILE, timeout_s=min(self.reply_timeout_s, 1.0))
        self._closing.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        with contextlib.suppress(OSError):
            self._sock.close()
        self._sock = None
        self._connected = False

    # -- sending and replies -------------------------------------------------------------

    def send(self, frame: bytes) -> None:
        """Write bytes to the scanner, recording them as TX first."""
        sock = self._sock
        if sock is None or not self._connected:
            raise DeviceError("scanner: not connected")
        with self._send_lock:
            self.sink.write_stream("scanner", frame, TX, self.clock_ns())
            try:
                sock.sendall(frame)
            except OSError as err:
                raise DeviceError(f"scanner: send failed ({err.strerror or err})") from err
            self.stats.tx_bytes += len(frame)

    def _request(self, frame: bytes, service: int, sub: int, expect_profile: bool = False,
                 timeout_s: float | None = None) -> ldoem.Message:
        """Send an ldoem request and wait for its reply (a profile reply counts for
        GET_PROFILE streaming, whose first answer is the first profile)."""
        if expect_profile:
            self._want_profile.set()
        self.send(frame)
        deadline = time.monotonic() + (self.reply_timeout_s if timeout_s is None else timeout_s)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._connected:
                what = "the link dropped" if not self._connected else "no reply"
                raise DeviceError(f"scanner: {what} to request {service:02x} {sub:02x} within "
                                  f"{self.reply_timeout_s:g} s")
            try:
                message = self._replies.get(timeout=min(remaining, POLL_S))
            except queue.Empty:
                continue
            if (message.service, message.sub) != (service, sub):
                continue  # a late reply to an earlier request
            if not expect_profile:
                refused = _refusal(message)
                if refused:
                    raise DeviceError(f"scanner refused request {service:02x} {sub:02x}: "
                                      f"{refused}")
            return message

    # -- reading -------------------------------------------------------------------------

    def _read_loop(self, sock: socket.socket | _SerialLink) -> None:
        # Reading, stamping and storing only; counting profiles (a decoder) runs in its own
        # thread, fed in order: the receive times are the clock the chain fits the device's to,
        # and a read that waited for the decoder of the chunk before it was stamped that much
        # late (an STL-27L's 250 KB/s at a 3× speed-up on a loaded host: reads fell 60–110 ms
        # behind for seconds, and the points 2.8 σ off).
        chunks: queue.SimpleQueue[tuple[bytes, int] | None] = queue.SimpleQueue()
        counter = threading.Thread(target=self._count_loop, args=(chunks,),
                                   name="scanner-count", daemon=True)
        counter.start()
        reason = ""
        try:
            while not self._closing.is_set():
                try:
                    data = sock.recv(1 << 16)
                except TimeoutError:
                    continue
                except OSError as err:
                    reason = f"connection error ({err.strerror or err})"
                    break
                now = self.clock_ns()
                if not data:
                    reason = "connection closed by the scanner"
                    break
                self.sink.write_stream("scanner", data, RX, now)
                self.stats.rx_bytes += len(data)
                chunks.put((data, now))
        finally:
            chunks.put(None)
            counter.join()
        if not self._closing.is_set():
            self._connected = False
            with self._profiles_changed:
                self._profiles_changed.notify_all()
            if self.on_disconnect is not None:
                self.on_disconnect(reason)

    def _count_loop(self, chunks: queue.SimpleQueue[tuple[bytes, int] | None]) -> None:
        """Count the profiles the received chunks complete (live: when one arrives, not when
        the next frame confirms it), and pass the driver's replies on."""
        driver = self.driver
        paper_decoder = (StreamDecoder(DIALECTS["paper"], confirm=False)
                         if self.dialect == "paper" and driver is None else None)
        reader = (ldoem.FrameReader(accept_unknown=True)
                  if self.dialect == "ldoem" and driver is None else None)
        while (item := chunks.get()) is not None:
            data, now = item
            counters: list[int] | None = None
            if driver is not None:
                complete, replies = driver.feed(data)
                for reply in replies:
                    self._driver_replies.put(reply)
            elif paper_decoder is not None:
                counters = [f.profiles[0].frame for f in paper_decoder.feed_frames(data)
                            if f.profiles]
                complete = len(counters)
            else:
                assert reader is not None
                counters = self._ldoem_frames(reader.feed(data))
                complete = len(counters)
            if complete:
                self._profiles_arrived(complete, now, counters)

    def _ldoem_frames(self, frames: list[RawFrame]) -> list[int]:
        """The frame counters of the profile replies (the replies to requests queued)."""
        counters = []
        for frame in frames:
            if not frame.checksum_ok:
                continue
            try:
                message = ldoem.parse_payload(frame.payload)
            except ProtocolError:
                continue
            if message.is_profile_reply:
                try:
                    sectors = ldoem.decode_profile_reply(frame.payload).sectors
                except ProtocolError:
                    sectors = []
                counters.append(sectors[0].frame if sectors else -1)  # -1: no counter
                if self._want_profile.is_set():  # the first profile answers GET_PROFILE
                    self._want_profile.clear()
                    self._replies.put(message)
            elif message.is_reply:
                self._replies.put(message)
        return counters

    def _profiles_arrived(self, count: int, now_ns: int,
                          counters: list[int] | None = None) -> None:
        unwrapped: list[int | None] = [None] * count
        if counters is not None and len(counters) == count and min(counters, default=0) >= 0:
            for i, c in enumerate(counters):  # u16 counters, unwrapped as they come
                last = self._last_counter
                step = 0 if last is None else (c - last) % COUNTER_PERIOD
                step = step - COUNTER_PERIOD if step >= COUNTER_PERIOD // 2 else step
                self._last_counter = c if last is None else last + step
                unwrapped[i] = self._last_counter
        with self._profiles_changed:
            self.stats.profiles += count
            self.stats.last_profile_ns = now_ns
            self._profile_times.extend([now_ns] * count)
            self._profile_counters.extend(unwrapped)
            del self._profile_times[:-256]  # more than profiles_per_position can ask for
            del self._profile_counters[:-256]
            self._profiles_changed.notify_all()

    def wait_for_profiles(self, after_ns: int, count: int, timeout_s: float,
                          stop: threading.Event | None = None) -> bool:
        """Wait until ``count`` profiles have been received after ``after_ns`` (host clock).

        False on time-out, on a dropped link or when ``stop`` is set.
        """
        deadline = time.monotonic() + timeout_s
        with self._profiles_changed:
            while True:
                if sum(1 for t in self._profile_times if t > after_ns) >= count:
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._connected or (stop is not None and stop.is_set()):
                    return False
                self._profiles_changed.wait(min(remaining, POLL_S))


    def wait_for_fresh_profiles(self, after_ns: int, count: int, period_ns: int,
                                sector_ns: int, timeout_s: float,
                                stop: threading.Event | None = None) -> bool:
        """Wait until ``count`` profiles that *began* after ``after_ns`` (host clock) have been
        received, and a margin after that: at a stopped position, a scan sent late (a lagging
        host or device) may have begun before the stop although it arrives after it, and the
        times the chain later gives profiles and motor states are fitted, not exact.

        With frame counters that advance once per head turn (ldoem, paper), the recent
        profiles place the head's turns on the host clock: ``base = min_j(r_j − c_j·T)``
        (receive time r, counter c, ``T = period_ns``: the least-delayed profile's placement,
        as the chain's clock fit does), and a profile began at ``base + c·T − sector``
        (``sector = sector_ns``). The margin is half a turn plus the 90th percentile of the
        recent profiles' delays ``r_j − (base + c_j·T)`` (a loaded link waits longer).
        Without counters, the first profile received after ``after_ns`` may have begun before
        it and is not counted (no margin). False on time-out, on a dropped link or when
        ``stop`` is set.
        """
        deadline = time.monotonic() + timeout_s
        with self._profiles_changed:
            while True:
                fresh, hold_ns = self._fresh_count(after_ns, count, period_ns, sector_ns)
                wait_s = max(0.0, (hold_ns - self.clock_ns()) / 1e9)
                if fresh >= count and wait_s == 0.0:
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._connected or (stop is not None and stop.is_set()):
                    return False
                self._profiles_changed.wait(min(remaining, POLL_S, wait_s or POLL_S))

    def _fresh_count(self, after_ns: int, count: int, period_ns: int,
                     sector_ns: int) -> tuple[int, int]:
        """How many recent profiles began after ``after_ns``, and until when to hold still
        once ``count`` of them are in (see :meth:`wait_for_fresh_profiles`; 0: no hold)."""
        times = self._profile_times[-FRESH_WINDOW:]
        counters = self._profile_counters[-FRESH_WINDOW:]
        received = [(t, c) for t, c in zip(times, counters, strict=True) if t > after_ns]
        if not received:
            return 0, 0
        known = [(t, c) for t, c in zip(times, counters, strict=True) if c is not None]
        if len(known) < len(times) or period_ns <= 0:
            return len(received) - 1, 0
        base = min(t - c * period_ns for t, c in known)
        fresh = [t for t, c in received
                 if c is not None and base + c * period_ns - sector_ns >= after_ns]
        if len(fresh) < count:
            return len(fresh), 0
        delays = sorted(t - (base + c * period_ns) for t, c in known)
        margin = period_ns // 2 + delays[int(0.9 * (len(delays) - 1))]
        return len(fresh), fresh[count - 1] + margin


def _refusal(message: ldoem.Message) -> str:
    """Why a reply refuses its request ('' when it does not).

    The emulator and scanpipe's driver agree on a refusal as a reply whose body starts with
    the u16 0xFFFF followed by an ASCII reason.
    """
    if message.body[:2] == b"\xff\xff":
        return message.body[2:].decode("ascii", "replace") or "refused"
    return ""
