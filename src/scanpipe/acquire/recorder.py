"""The recorder: run a scan on the rig and write everything raw into one recording.

Two procedures (:class:`RecordOptions.mode`):

- ``step`` (the paper's step-and-scan): from the start, move by the chosen step count
  (:func:`scanpipe.planning.choose_steps`), wait for the move to end and the settle time, then
  for ``profiles_per_position`` complete profiles that began after the settle — placed by their
  frame counters, so a scan sent late (a lagging link) that began before the settle is not
  counted; without counters the first profile received is not counted — and a margin
  (:meth:`~scanpipe.acquire.scanner_client.ScannerClient.wait_for_fresh_profiles`), and repeat
  while the next position is within the sweep;
- ``continuous``: one move to the end of the sweep at a constant pulse rate (the motor step per
  head turn: ``steps × scan_hz`` pulses per second) while the controller reports its position
  periodically and the scanner streams.

The sweep starts at home (the controller's power-on position) and ends at the travel limit the
host obeys: the smaller of the rig's ``motor.pulse_limit`` and the controller's own (``TRAVEL?``;
the ``motor_limit`` event names which applied). A platform on a slip ring (both unlimited)
sweeps ``motor.pulse_limit`` pulses from wherever it stands. A limited platform that stands
away from home is refused (or brought home first with ``home_first``), and at the end of every
scan, also after a stop or an error, the platform is brought back to where the scan started
while the motor still answers: so no series of scans winds the cables.

Cameras record throughout. Threads: one reads the scanner, one the motor link, one per camera,
one flushes the file every ``fsync_interval_s`` (so a SIGKILL loses at most about that much);
the calling thread runs the procedure. SIGINT / SIGTERM stop the motor, bring the platform back
to the start and finish the file properly (a second signal stops the way back). A scanner that
drops the link stops the motor at once; the recorder tries to reconnect and carries on, or ends
the recording cleanly. Every such incident is an event on
``/events`` and in the summary.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, Literal

from pydantic import Field

from scanpipe import __version__
from scanpipe.acquire.cameras import CameraThread, FrameSource, is_device_index, open_capture
from scanpipe.acquire.display import RecorderStatus
from scanpipe.acquire.motor_client import MotorClient, MotorState, TravelLimit
from scanpipe.acquire.scanner_client import ScannerClient
from scanpipe.acquire.sink import RecordingSink, SinkTap
from scanpipe.errors import DeviceError, ScanpipeError
from scanpipe.params import Params
from scanpipe.planning import DEFAULT_MOTOR_STEP_DEG, choose_steps, move_time_s
from scanpipe.protocol import ldoem
from scanpipe.recording.writer import RECORDING_END_EVENT, SCAN_END_EVENT
from scanpipe.rig import Rig

CameraOpener = Callable[[Any], FrameSource]
#: During the continuous turn, a link up but silent for this many head turns (and at least
#: STALL_MIN_S of host time, so a loaded host is not taken for a stall) counts as lost.
STALL_TURNS = 5
STALL_MIN_S = 1.0


class RecordOptions(Params):
    """How to record: the procedure, the step, safety and file settings."""

    mode: Literal["step", "continuous"] = "step"
    motor_step_deg: float = Field(DEFAULT_MOTOR_STEP_DEG, gt=0, le=360)
    profiles_per_position: int = Field(1, ge=1, le=100)
    #: ldoem: ask for the echo amplitudes too (format mask 0x3DFF instead of 0x39FF).
    with_echo: bool = True
    cameras: bool = True
    jpeg_quality: int = Field(90, ge=1, le=100)
    fsync_interval_s: float = Field(1.0, gt=0, le=1.0)
    split_size_mb: float | None = Field(None, gt=0)
    split_duration_s: float | None = Field(None, gt=0)
    reply_timeout_s: float = Field(3.0, gt=0)
    reconnect_attempts: int = Field(2, ge=0, le=100)
    reconnect_delay_s: float = Field(0.5, ge=0)
    #: The virtual rig's clock speed-up: waits that stand for device time (settle, time-outs,
    #: camera periods) shrink by this factor. 1 on a real rig.
    speedup: float = Field(1.0, gt=0, le=10_000)
    #: ZERO the controller at the start: the recorded counts (``/motor/state``) count from the
    #: scan start. The controller keeps its absolute position, which the limit holds on.
    zero_at_start: bool = True
    #: Bring the platform back to the scan's start at the end (also after a stop or an error).
    return_to_start: bool = True
    #: A platform standing away from home is brought home before the scan (else: refused).
    home_first: bool = False
    install_signal_handlers: bool = True


class RecordingStopped(Exception):
    """Internal: the procedure ends early (signal, lost scanner, device error)."""


class Recorder:
    """One recording session; :meth:`run` does it all and returns the summary.

    ``camera_opener(camera_config)`` opens a camera's frame source (OpenCV by default; the
    virtual rig passes its virtual cameras). ``writer_factory`` opens one recording file.
    """

    def __init__(
        self,
        rig: Rig,
        out: Path,
        options: RecordOptions | None = None,
        camera_opener: CameraOpener | None = None,
        writer_factory: Callable[[Path, Rig, Mapping[str, Any]], Any] | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        taps: Sequence[SinkTap] = (),
    ) -> None:
        self.rig = rig
        self.taps = list(taps)
        self.out = out
        self.options = options or RecordOptions()
        self.camera_opener = camera_opener or open_capture
        self.writer_factory = writer_factory or _writer_factory(self.options.fsync_interval_s)
        self.clock_ns = clock_ns
        self.stop_event = threading.Event()
        self.stop_reason = ""
        self.status = "running"
        self.phase = "starting"
        self.positions_done = 0
        self.positions_total: int | None = None
        self.sink: RecordingSink | None = None
        self.scanner: ScannerClient | None = None
        self.motor: MotorClient | None = None
        self.cameras: list[CameraThread] = []
        self._started = time.monotonic()
        self._position_times: list[float] = []
        self._scanner_lost = threading.Event()
        self._rate_window: list[tuple[float, int]] = []
        self._continuous_end: tuple[float, int] | None = None  # (deadline, target) when turning
        self._done = threading.Event()  # the file is being closed: the flusher ends
        self._abort_return = threading.Event()  # a second signal while the platform returns
        self.travel_limit: TravelLimit | None = None
        self._start_count: int | None = None  # the controller's count at the scan start
        # Continuous turn: recent (time, count) motor reports, and since when the stream is
        # expected to deliver (the turn's start, a reconnect): for a stall and a resume.
        self._turn_counts: deque[tuple[int, int]] = deque(maxlen=4096)
        self._stream_since_ns = 0
        self._end_count: int | None = None  # … and at the end of the sweep
        self._returned: bool | None = None
        choice = choose_steps(self.options.motor_step_deg, rig.motor.pulse_step_deg,
                              rig.motor.pulse_limit)
        self.step_count = choice.chosen_steps

    # -- the whole session ----------------------------------------------------------------

    def session_metadata(self) -> dict[str, Any]:
        """The ``scanpipe.session`` metadata: mode, step, start time, host, versions."""
        import platform

        return {
            "mode": self.options.mode,
            "step_count": self.step_count,
            "motor_step_deg": self.step_count * self.rig.motor.pulse_step_deg,
            "profiles_per_position": self.options.profiles_per_position,
            "start_time_ns": self.clock_ns(),
            "host": socket.gethostname(),
            "python": platform.python_version(),
            "scanpipe": __version__,
            "speedup": self.options.speedup,
        }

    def run(self) -> dict[str, Any]:
        """Record until the procedure ends or is stopped; always finish the file properly."""
        opts = self.options
        self.sink = RecordingSink(
            self.out, self.rig, self.session_metadata(), self.writer_factory,
            split_bytes=int(opts.split_size_mb * 1e6) if opts.split_size_mb else None,
            split_s=opts.split_duration_s, clock_ns=self.clock_ns, taps=self.taps)
        flusher = threading.Thread(target=self._flush_loop, name="recording-flush", daemon=True)
        flusher.start()
        try:
            with self._signals():
                try:
                    self._connect()
                    if opts.mode == "step":
                        self._step_and_scan()
                    else:
                        self._continuous()
                    if self.status == "running":
                        self.status = "complete"
                except RecordingStopped:
                    pass
                except DeviceError as err:
                    self._fail("device_error", str(err))
                finally:
                    self._shut_down()
        finally:
            self.stop_event.set()
            self._done.set()
            flusher.join(timeout=2.0)
            failure = self.sink.take_failure()
            if failure is not None:  # data were lost, whatever the procedure's status was
                self.status, self.stop_reason = "failed", f"cannot write the recording: {failure}"
            summary = self.summary()
            self.sink.event(RECORDING_END_EVENT, f"recording ended: {self.status}",
                            {"status": self.status, "reason": self.stop_reason})
            self.sink.close()
        return summary

    def _fail(self, kind: str, message: str) -> None:
        if self.status == "running":
            self.status = "failed"
            self.stop_reason = message
        assert self.sink is not None
        self.sink.event(kind, message)

    @contextmanager
    def _signals(self) -> Iterator[None]:
        """SIGINT / SIGTERM end the scan gracefully (main thread only)."""
        if (not self.options.install_signal_handlers
                or threading.current_thread() is not threading.main_thread()):
            yield
            return

        def handler(signum: int, frame: FrameType | None) -> None:
            name = signal.Signals(signum).name
            if self.stop_event.is_set():
                # Already finishing the file: stop a return to the start, and the next such
                # signal ends the process at once.
                self._abort_return.set()
                signal.signal(signum, signal.SIG_DFL)
                return
            self.request_stop(f"{name} received", status="interrupted")

        previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, h in previous.items():
                signal.signal(s, h)

    def request_stop(self, reason: str, status: str = "interrupted") -> None:
        """Ask the procedure to stop (from a signal handler or another thread)."""
        if self.status == "running":
            self.status = status
            self.stop_reason = reason
        self.stop_event.set()

    def _check_stop(self) -> None:
        if self.stop_event.is_set():
            raise RecordingStopped

    # -- devices ---------------------------------------------------------------------------

    def _connect(self) -> None:
        assert self.sink is not None
        opts = self.options
        self.phase = "connecting"
        self.motor = MotorClient(self.rig.motor, self.sink, opts.reply_timeout_s,
                                 self.clock_ns, on_error=self._motor_link_error)
        self.motor.connect()
        firmware, _ = self.motor.identify()
        travel = self.motor.query_travel()
        self.sink.event("motor_connected", f"motor controller on {self.rig.motor.serial_url}",
                        {"firmware": firmware, "pulse_limit": travel.controller_limit,
                         "absolute_step_count": travel.absolute})
        self._obey_limit()
        self.motor.query_position()
        self.motor.set_accel(self.rig.motor.accel_hz_per_s)
        self._go_home_or_refuse()
        if opts.zero_at_start:
            travel = self.motor.zero()
            self.sink.event("motor_zeroed", "the start position is count 0 (the controller keeps "
                            f"its absolute position {travel.absolute})",
                            {"absolute_step_count": travel.absolute})
        state = self.motor.query_position()
        self._start_count = state.step_count
        self._end_count = state.step_count + self._sweep_pulses(self.motor.absolute(
            state.step_count))
        mask = ldoem.MASK_RANGES_ECHO if opts.with_echo else ldoem.MASK_RANGES
        self.scanner = ScannerClient(self.rig.scanner, self.sink, self._scanner_dropped,
                                     reply_timeout_s=opts.reply_timeout_s, mask=mask,
                                     clock_ns=self.clock_ns)
        self.scanner.connect()
        self.sink.event("scanner_connected",
                        f"{self.rig.scanner.dialect} scanner at "
                        f"{self.rig.scanner.host}:{self.rig.scanner.port}",
                        {"ident": self.scanner.ident,
                         "device_clock_ms_at_host_ns": self.scanner.device_clock})
        if opts.cameras:
            self._start_cameras()

    def _obey_limit(self) -> None:
        """The travel limit: the smaller of the rig's and the controller's, named in an event."""
        assert self.motor is not None and self.sink is not None
        limit = self.motor.limit()
        self.travel_limit = limit
        data = {"pulse_limit": limit.pulses, "source": limit.source, "rig": limit.rig,
                "controller": limit.controller}
        self.sink.event("motor_limit", f"motor: {limit.describe()}", data)
        if limit.rig != limit.controller:
            def shown(value: int | None) -> str:
                return "unlimited" if value is None else str(value)
            self.sink.event("motor_limit_mismatch",
                            f"the controller's travel limit is {shown(limit.controller)}, the rig "
                            f"file's {shown(limit.rig)}; the smaller one applies: "
                            f"{limit.describe()}",
                            {"controller": limit.controller, "rig": limit.rig})

    def _sweep_pulses(self, start_absolute: int) -> int:
        """How far a scan turns from ``start_absolute``: up to the limit, or pulse_limit when
        nothing limits travel (a slip ring)."""
        assert self.travel_limit is not None
        sweep = self.rig.motor.pulse_limit
        if self.travel_limit.pulses is not None:
            sweep = min(sweep, self.travel_limit.pulses - start_absolute)
        return max(sweep, 0)

    def _go_home_or_refuse(self) -> None:
        """A limited platform scans from home: bring it there (``home_first``) or refuse."""
        assert self.motor is not None and self.sink is not None
        assert self.travel_limit is not None
        travel = self.motor.query_travel()
        if self.travel_limit.pulses is None or travel.absolute == 0:
            return
        away_deg = travel.absolute * self.rig.motor.pulse_step_deg
        if not self.options.home_first:
            raise DeviceError(
                f"motor: the platform stands {travel.absolute} pulses ({away_deg:.3f}°) from home "
                "(its position at the controller's power-on), so a scan would not start at home "
                "and could not cover its sweep; check the cables, then record with --home-first "
                "to bring it home")
        state = self.motor.query_position()
        self.motor.set_rate(self.rig.motor.pulse_rate_hz)
        self._move_to(state.step_count - travel.absolute, self.rig.motor.pulse_rate_hz,
                      phase="going home")
        self.sink.event("motor_homed", f"motor: brought home from {travel.absolute} pulses "
                        f"({away_deg:.3f}°) before the scan", {"from_absolute": travel.absolute})

    def _return_to_start(self) -> None:
        """Bring the platform back to the scan's start (tried whatever ended the scan)."""
        assert self.sink is not None
        motor = self.motor
        if (not self.options.return_to_start or motor is None or not motor.connected
                or self._start_count is None):
            return
        start = self._start_count
        self.phase = "returning to the start"
        try:
            state = motor.query_position()
            if state.moving:
                motor.stop()
                state = motor.query_position()
            if state.step_count != start:
                motor.set_rate(self.rig.motor.pulse_rate_hz)
                self._move_to(start, self.rig.motor.pulse_rate_hz, stop=self._abort_return,
                              watch_scanner=False, phase="returning to the start")
            travel = motor.query_travel()
        except (DeviceError, RecordingStopped) as err:
            self._returned = False
            reason = str(err) or "stopped by a second signal"
            with_stop = ""
            if isinstance(err, RecordingStopped):
                try:
                    motor.stop()
                except DeviceError as stop_err:
                    with_stop = f"; STOP failed: {stop_err}"
            self.sink.event("motor_return_failed",
                            f"motor: the platform did not return to the start ({reason}"
                            f"{with_stop}); the next scan is refused until it stands at home",
                            {"start_step_count": start})
            return
        self._returned = True
        self.sink.event("motor_returned", f"motor: back at the start (count {start}, absolute "
                        f"{travel.absolute})", {"absolute_step_count": travel.absolute})

    def _start_cameras(self) -> None:
        assert self.sink is not None
        for cam in self.rig.cameras:
            try:
                source = self.camera_opener(cam)
            except ScanpipeError as err:
                self.sink.event("camera_error", str(err), {"camera_id": cam.id})
                continue
            live_device = is_device_index(cam.source) and self.camera_opener is open_capture
            thread = CameraThread(cam.id, source, self.sink, self.stop_event,
                                  period_s=1.0 / (cam.fps * self.options.speedup),
                                  pace=not live_device, jpeg_quality=self.options.jpeg_quality,
                                  clock_ns=self.clock_ns)
            thread.start()
            self.cameras.append(thread)

    def _scanner_dropped(self, reason: str, kind: str = "scanner_disconnected") -> None:
        """Called by the scanner's reader thread (or the stall watch): stop the motor first,
        then tell the procedure."""
        assert self.sink is not None
        self._scanner_lost.set()
        self.sink.event(kind, f"scanner: {reason}")
        if self.motor is not None:
            try:
                self.motor.stop()
            except DeviceError as err:
                self.sink.event("motor_error", f"STOP after the scanner dropped: {err}")

    def _motor_link_error(self, reason: str) -> None:
        assert self.sink is not None
        self.sink.event("motor_disconnected", f"motor controller: {reason}")
        self.request_stop(f"motor controller: {reason}", status="failed")

    def _reconnect_scanner(self) -> None:
        """After a drop: try to reconnect; :class:`RecordingStopped` when it stays down."""
        assert self.sink is not None and self.scanner is not None
        opts = self.options
        self.scanner.close(cancel=False)
        for attempt in range(1, opts.reconnect_attempts + 1):
            if self.stop_event.wait(opts.reconnect_delay_s):
                raise RecordingStopped
            try:
                self.scanner.connect()
            except DeviceError as err:
                self.sink.event("scanner_reconnect_failed", f"attempt {attempt}: {err}")
                continue
            self._scanner_lost.clear()
            self.sink.event("scanner_reconnected", f"scanner reconnected (attempt {attempt})")
            return
        self.status = "scanner_disconnected"
        self.stop_reason = (f"the scanner dropped the link and {opts.reconnect_attempts} "
                            "reconnect attempt(s) failed")
        raise RecordingStopped

    def _shut_down(self) -> None:
        """Stop the motor, the scanner stream and the cameras; every step is tried."""
        assert self.sink is not None
        self.phase = "stopping"
        if self.motor is not None and self.motor.connected:
            state = self.motor.state
            if self.status != "complete" or (state is not None and state.moving):
                try:
                    self.motor.stop()
                    self.sink.event("motor_stopped", "motor stopped")
                except DeviceError as err:
                    self.sink.event("motor_error", f"STOP failed: {err}")
        if self.scanner is not None:
            self.scanner.close(cancel=True)
        # A follower (run --follow) makes the model now, with every profile recorded, not
        # after the cameras' shut-down and the way back (which come with the recording's end).
        if self._start_count is not None:  # the scan had started
            self.sink.event(SCAN_END_EVENT, f"scan ended ({self.status})",
                            {"status": self.status})
            with contextlib.suppress(OSError, ScanpipeError):  # a failing disk: reported later
                self.sink.flush()
        self.stop_event.set()
        for thread in self.cameras:
            thread.join(timeout=2.0)
        # With the stream and the cameras stopped, no profile or frame is taken on the way back.
        self._return_to_start()
        if self.motor is not None:
            if self.motor.rejected_reports:
                self.sink.event("motor_reports_rejected",
                                f"motor: {self.motor.rejected_reports} position report(s) "
                                "rejected as implausible (a count or target that line noise "
                                "changed): not recorded as motor states",
                                {"count": self.motor.rejected_reports})
            self.motor.close()
        self.phase = "done"

    def _flush_loop(self) -> None:
        """Flush and fsync the file at least every ``fsync_interval_s`` (even when idle)."""
        interval = self.options.fsync_interval_s
        while not self._done.wait(interval / 2):  # on while the platform returns, too
            if self.sink is not None:
                try:
                    self.sink.flush()
                except (OSError, ScanpipeError) as err:
                    self.request_stop(f"cannot write the recording: {err}", status="failed")
            if not self.stop_event.is_set():
                for camera in self.cameras:
                    camera.watchdog()
            self._note_rate()

    # -- procedures ------------------------------------------------------------------------

    def _device_s(self, seconds: float) -> float:
        """Host time for ``seconds`` of device time."""
        return seconds / self.options.speedup

    def _wait_for_stream(self, when: str) -> None:
        """Wait (phase "waiting for the scanner") until a profile arrives, within three head
        turns and a reply's time; else DeviceError "scanner: no profiles {when}"."""
        assert self.scanner is not None
        self.phase = "waiting for the scanner"
        if not self.scanner.wait_for_profiles(self.clock_ns(), 1,
                                              self._device_s(3.0 / self.rig.scanner.scan_hz)
                                              + self.options.reply_timeout_s, self.stop_event):
            self._check_stop()
            raise DeviceError(f"scanner: no profiles {when}")

    def _targets(self, start: int) -> list[int]:
        assert self._end_count is not None
        return list(range(start, self._end_count + 1, self.step_count))

    def _stream_stalled(self) -> float | None:
        """Seconds without a profile while the link is up, when more than
        :data:`STALL_TURNS` head turns (at least :data:`STALL_MIN_S`): a stalled link (TCP
        open, nothing arriving). None otherwise."""
        if self.scanner is None or not self.scanner.connected:
            return None
        since = max(self.scanner.stats.last_profile_ns, self._stream_since_ns)
        silent_s = (self.clock_ns() - since) / 1e9
        limit_s = max(self._device_s(STALL_TURNS / self.rig.scanner.scan_hz), STALL_MIN_S)
        return silent_s if since > 0 and silent_s > limit_s else None

    def _scanner_stalled(self, silent_s: float) -> None:
        """A stalled link is a lost one: stop the motor, close the link (reconnect follows)."""
        assert self.scanner is not None
        self._scanner_dropped(f"no profile for {silent_s:.1f} s while the platform turned "
                              "(the link stalled): closing it to reconnect",
                              kind="scanner_stalled")
        self.scanner.close(cancel=False)

    def _count_at(self, time_ns: int) -> int | None:
        """The platform's count at a host time during the turn (from the motor reports); before
        the turn's first report, the start count (the platform stood there, or had just left
        it: going back there scans again at most what it turned), None without one."""
        reports = [(t, c) for t, c in self._turn_counts if t <= time_ns]
        later = [(t, c) for t, c in self._turn_counts if t > time_ns]
        if not reports:
            return self._start_count
        (t0, c0) = reports[-1]
        if not later:
            return c0
        t1, c1 = later[0]
        return round(c0 + (c1 - c0) * (time_ns - t0) / max(t1 - t0, 1))

    def _resume_turn(self, rate_hz: float) -> None:
        """After the scanner was lost during the continuous turn: with the link closed (no
        profile taken on the way), bring the platform back to where it stood when the last
        profile arrived, reconnect, wait for the stream, and carry on: the turn resumes where
        its profiles stopped, as after a pause, instead of leaving the sector turned blind
        without profiles (a hole in the scan)."""
        assert self.scanner is not None and self.motor is not None and self.sink is not None
        self.scanner.close(cancel=False)
        last_ns = self.scanner.stats.last_profile_ns
        back_to = self._count_at(last_ns) if last_ns else None
        state = self.motor.state or self.motor.query_position()
        if back_to is not None and self._start_count is not None:
            back_to = max(back_to, self._start_count)
        if back_to is not None and back_to < state.step_count:
            self.motor.set_rate(self.rig.motor.pulse_rate_hz)
            self._move_to(back_to, self.rig.motor.pulse_rate_hz, watch_scanner=False,
                          phase=f"back to {back_to}, where the profiles stopped")
            self.motor.set_rate(rate_hz)
        self._reconnect_scanner()
        self._stream_since_ns = self.clock_ns()
        self._wait_for_stream("after reconnecting")
        turned_blind = state.step_count - (back_to if back_to is not None else state.step_count)
        self.sink.event("scan_resumed",
                        f"scan resumed at count {back_to if back_to is not None else '?'} "
                        f"(the last profile before the loss; {turned_blind} pulses turned "
                        "without profiles are scanned again)",
                        {"count": back_to, "from_count": state.step_count})

    def _move_to(self, target: int, rate_hz: float, stop: threading.Event | None = None,
                 watch_scanner: bool = True, phase: str | None = None,
                 watch_stall: bool = False) -> None:
        """Move to the count ``target`` and wait for the controller to report it reached,
        stopped. ``stop`` (default: the recording's stop) ends the wait with
        :class:`RecordingStopped`; ``watch_scanner``: a lost scanner ends it too; ``phase``
        names the move in the live status (default "moving to TARGET"); ``watch_stall``: a
        stream silent for longer than :meth:`_stream_stalled` allows is a lost scanner too
        (the continuous turn, where the motor would otherwise turn on without profiles)."""
        stop = self.stop_event if stop is None else stop
        assert self.motor is not None and self.sink is not None
        state = self.motor.state or self.motor.query_position()
        pulses = target - state.step_count
        if pulses == 0 and not state.moving:
            return
        expected = move_time_s(abs(pulses), rate_hz, self.rig.motor.accel_hz_per_s)
        self.phase = phase or f"moving to {target}"
        try:
            self.motor.move(pulses)
        except DeviceError as err:
            self.sink.event("motor_error", str(err), {"target": target})
            raise
        timeout = self._device_s(expected * 1.5 + 1.0) + self.options.reply_timeout_s
        # A lost scanner stops the motor on purpose: stop waiting then, too.
        lost = self._scanner_lost if watch_scanner else threading.Event()
        stalled: list[float] = []

        def done(state: MotorState) -> bool:
            if watch_stall:  # (under the motor client's lock: no I/O here)
                if not self._turn_counts or self._turn_counts[-1][0] != state.log_time_ns:
                    self._turn_counts.append((state.log_time_ns, state.step_count))
                silent_s = self._stream_stalled()
                if silent_s is not None:
                    stalled.append(silent_s)
                    return True
            return (not state.moving and state.step_count == target) or lost.is_set()

        reached = self.motor.wait_for_state(done, timeout, stop)
        if stop.is_set():
            raise RecordingStopped
        if stalled and not lost.is_set():
            self._scanner_stalled(stalled[0])
        if lost.is_set():
            return  # the procedure reconnects and comes back to this target
        if reached is None:
            # The report of the arrival may have been lost on the link (noise): ask.
            for _ in range(3):
                with contextlib.suppress(DeviceError):
                    asked = self.motor.query_position()
                    if not asked.moving and asked.step_count == target:
                        return
                    break
            last = self.motor.state
            self.sink.event("motor_timeout",
                            f"motor: target {target} not reached within {timeout:.1f} s "
                            f"(last count {last.step_count if last else '?'})",
                            {"target": target})
            raise DeviceError(f"motor: target {target} not reached within {timeout:.1f} s")

    def _step_and_scan(self) -> None:
        assert self.motor is not None and self.scanner is not None and self.sink is not None
        opts, scanner = self.options, self.rig.scanner
        assert self._start_count is not None
        targets = self._targets(self._start_count)
        self.positions_total = len(targets)
        scan_period_s = self._device_s(1.0 / scanner.scan_hz)
        sector_fraction = min(1.0, (scanner.end_angle_deg - scanner.start_angle_deg) / 360.0)
        profile_timeout = (opts.profiles_per_position + 3) * scan_period_s + opts.reply_timeout_s
        self.motor.set_rate(self.rig.motor.pulse_rate_hz)
        index = 0
        while index < len(targets):
            self._check_stop()
            if self._scanner_lost.is_set():
                self._reconnect_scanner()
            position_started = time.monotonic()
            self._move_to(targets[index], self.rig.motor.pulse_rate_hz)
            if self._scanner_lost.is_set():
                continue
            self.phase = f"settling at {targets[index]}"
            if self.stop_event.wait(self._device_s(self.rig.motor.settle_s)):
                raise RecordingStopped
            settled_ns = self.clock_ns()
            self.phase = f"scanning at {targets[index]}"
            # Profiles that began after the settle: one sent late may have begun before it.
            if not self.scanner.wait_for_fresh_profiles(
                    settled_ns, opts.profiles_per_position, round(scan_period_s * 1e9),
                    round(scan_period_s * sector_fraction * 1e9), profile_timeout,
                    self.stop_event):
                self._check_stop()
                if self._scanner_lost.is_set() or not self.scanner.connected:
                    self._scanner_lost.set()
                    continue  # reconnect, then retake this position
                self.sink.event("scanner_timeout",
                                f"scanner: no complete profile within {profile_timeout:.1f} s "
                                f"at position {targets[index]}", {"target": targets[index]})
                raise DeviceError(f"scanner: no profiles for {profile_timeout:.1f} s")
            self.positions_done = index + 1
            self._position_times.append(time.monotonic() - position_started)
            index += 1

    def continuous_rate_hz(self) -> float:
        """Pulse rate of a continuous scan: the step per head turn, ``steps × scan_hz``."""
        return self.step_count * self.rig.scanner.scan_hz

    def _continuous(self) -> None:
        assert self.motor is not None and self.scanner is not None and self.sink is not None
        rate = self.continuous_rate_hz()
        assert self._start_count is not None
        start = self._start_count
        end = self._targets(start)[-1]
        self.positions_total = (end - start) // self.step_count + 1
        self.motor.set_rate(rate)
        # Wait for the stream to run before turning, so the scan starts at the start position.
        self._wait_for_stream("before the continuous turn")
        self._stream_since_ns = self.clock_ns()
        while True:
            self._check_stop()
            if self._scanner_lost.is_set():
                self._resume_turn(rate)
            self.phase = f"turning at {rate:g} pulses/s"
            state = self.motor.state or self.motor.query_position()
            remaining = end - state.step_count
            self._continuous_end = (time.monotonic() + self._device_s(remaining / rate), end)
            self._move_to(end, rate, watch_stall=True)
            if not self._scanner_lost.is_set():
                break
        self.positions_done = self.positions_total
        # One more whole profile at the end position.
        self.scanner.wait_for_profiles(self.clock_ns(), 1,
                                       self._device_s(2.0 / self.rig.scanner.scan_hz) + 1.0,
                                       self.stop_event)

    # -- reporting -------------------------------------------------------------------------

    def _note_rate(self) -> None:
        if self.sink is None:
            return
        now = time.monotonic()
        self._rate_window.append((now, self.sink.stats.total_bytes))
        self._rate_window = [(t, b) for t, b in self._rate_window if now - t <= 5.0]

    def time_left_s(self) -> float | None:
        """A time-left estimate from the positions done so far (step) or the turn (continuous)."""
        if self.options.mode == "continuous":
            if self._continuous_end is None:
                return None
            return max(0.0, self._continuous_end[0] - time.monotonic())
        if not self._position_times or self.positions_total is None:
            return None
        mean = sum(self._position_times[-20:]) / len(self._position_times[-20:])
        return mean * (self.positions_total - self.positions_done)

    def live_status(self) -> RecorderStatus:
        """A snapshot for the live display."""
        stats = self.sink.stats if self.sink else None
        state = self.motor.state if self.motor else None
        step_count = state.step_count if state else 0
        rate = 0.0
        if len(self._rate_window) >= 2:
            (t0, b0), (t1, b1) = self._rate_window[0], self._rate_window[-1]
            rate = (b1 - b0) / (t1 - t0) if t1 > t0 else 0.0
        last = stats.event_log[-1]["message"] if stats and stats.event_log else ""
        return RecorderStatus(
            mode=self.options.mode,
            phase=self.phase,
            elapsed_s=time.monotonic() - self._started,
            profiles=self.scanner.stats.profiles if self.scanner else 0,
            positions_done=self.positions_done,
            positions_total=self.positions_total,
            step_count=step_count,
            pulse_limit=self._end_count if self._end_count is not None
            else self.rig.motor.pulse_limit,
            beta_deg=step_count * self.rig.motor.pulse_step_deg + self.rig.motor.beta_offset_deg,
            frames=dict(stats.images) if stats else {},
            dropped_frames=sum(c.stats.dropped for c in self.cameras),
            data_rate_bps=rate,
            total_bytes=stats.total_bytes if stats else 0,
            time_left_s=self.time_left_s(),
            events=sum(stats.events.values()) if stats else 0,
            last_event=last,
            start_count=self._start_count,
            samples_per_profile=self.rig.scanner.samples_per_profile,
        )

    def _applied_limit(self) -> int:
        """The travel limit obeyed (the sweep when nothing limits travel)."""
        if self.travel_limit is not None and self.travel_limit.pulses is not None:
            return self.travel_limit.pulses
        return self.rig.motor.pulse_limit

    def summary(self) -> dict[str, Any]:
        """The final summary (also the return value of :meth:`run`)."""
        assert self.sink is not None
        stats = self.sink.stats
        state = self.motor.state if self.motor else None
        step_count = state.step_count if state else 0
        return {
            "files": [str(p) for p in self.sink.paths],
            "status": self.status,
            "reason": self.stop_reason,
            "mode": self.options.mode,
            "dialect": self.rig.scanner.dialect,
            "step_count": self.step_count,
            "duration_s": time.monotonic() - self._started,
            "profiles": self.scanner.stats.profiles if self.scanner else 0,
            "positions": self.positions_done,
            "positions_planned": self.positions_total,
            "final_step_count": step_count,
            "final_beta_deg": step_count * self.rig.motor.pulse_step_deg,
            "pulse_limit": self._applied_limit(),
            "limit_source": self.travel_limit.source if self.travel_limit else None,
            "returned_to_start": self._returned,
            "absolute_step_count": (self.motor.travel.absolute
                                    if self.motor and self.motor.travel else None),
            "motor_states": stats.motor_states,
            "frames": dict(stats.images),
            "dropped_frames": {c.camera_id: c.stats.dropped for c in self.cameras},
            "stream_bytes": dict(stats.stream_bytes),
            "events": dict(stats.events),
            "event_log": [
                {k: v for k, v in e.items() if k != "data"} for e in stats.event_log
            ],
            "rig": self.rig.name,
        }


def _writer_factory(fsync_interval_s: float) -> Callable[[Path, Rig, Mapping[str, Any]], Any]:
    """Open recording parts with the recording package's crash-safe writer."""
    from scanpipe.recording.writer import RecordingWriter

    def open_part(path: Path, rig: Rig, session: Mapping[str, Any]) -> Any:
        return RecordingWriter(path, rig, session, fsync_interval_s=fsync_interval_s)

    return open_part

