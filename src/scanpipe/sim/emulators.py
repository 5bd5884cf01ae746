"""Device emulators on real endpoints: the scanner on a loopback TCP port, the motor controller
on a pseudo-terminal, and virtual cameras with the interface of an OpenCV capture.

All share one :class:`~scanpipe.sim.clock.SimClock` and one
:class:`~scanpipe.sim.motion.PlatformState`: a profile is measured at the platform angle of
its instant, however the motor was driven. Each emulator runs in threads; ``stop()`` ends them
and closes every descriptor. :class:`VirtualRig` starts and stops the whole set.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.errors import SimulationError
from scanpipe.rig import CameraConfig, MotorConfig, Rig, ScannerConfig
from scanpipe.sim.camera import CameraModel, render_rgb
from scanpipe.sim.clock import SimClock
from scanpipe.sim.controller import MotorController
from scanpipe.sim.devices import EmulatedDevice, emulated_device
from scanpipe.sim.motion import Move, PlatformState
from scanpipe.sim.options import SimOptions
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.scanner import (
    MeasurementModel,
    echo_amplitude,
    measure,
    packet_beams,
    sample_time_offsets_s,
    sector_duration_s,
    true_ranges,
)
from scanpipe.sim.scene import Scene
from scanpipe.sim.scip_device import ScipDevice
from scanpipe.sim.truth import truth_table, write_truth

#: How often idle emulator threads look at their stop flag (real seconds).
POLL_S = 0.02
#: A device that sends packets as their samples are taken gets them sent in at most this many
#: groups a turn: an STL-27L's 180 packets one by one, or in 32 groups, cost the recorder (a
#: decoder feed per read) more CPU than a loaded host had, and its reads fell behind by 100 ms;
#: in 8 groups a turn's last packet still goes out the moment it is taken, with only its group
#: (~1 KB, not the whole turn's 8.5 KB) to pass through the pty before it.
PACKET_GROUPS = 8


@dataclass(frozen=True)
class SentProfile:
    """The truth of one profile the scanner emulator sent."""

    head_index: int
    start_s: float
    beta_first_deg: float
    beta_last_deg: float
    ranges_true_m: NDArray[np.float64]


#: A device's packets of a scan of n samples: each packet's last sample and the byte offset one
#: past the packet (``LdrobotEmulated.packet_ends``).
PacketEnds = Callable[[int], tuple[NDArray[np.int64], NDArray[np.int64]]]


@dataclass(frozen=True)
class _Prepared:
    """A scan measured ahead of being sent, and the platform moves it was measured with; for
    a device that sends packets as their samples are taken, its bytes and per packet the
    simulation time of its last sample and the byte offset one past it."""

    k: int
    moves: tuple[Move, ...]
    measured: NDArray[np.float32]
    echo: NDArray[np.uint16] | None
    sent: SentProfile
    data: bytes = b""
    packet_due_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    packet_end: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    def bytes_ready(self, now_s: float) -> int:
        """The bytes of the packets whose last sample was taken by ``now_s``."""
        ready = int(np.searchsorted(self.packet_due_s, now_s, side="right"))
        return int(self.packet_end[ready - 1]) if ready else 0

    def next_packet_s(self, sent_bytes: int) -> float:
        """When the first packet not yet sent is complete."""
        waiting = int(np.searchsorted(self.packet_end, sent_bytes, side="right"))
        return float(self.packet_due_s[min(waiting, self.packet_due_s.size - 1)])


class _PtyEndpoint:
    """The device side of a pseudo-terminal, with the socket calls the server loop uses.

    Writes nobody reads are dropped (counted in ``overruns``), as on a real UART; reads while
    no client has the terminal open see nothing."""

    #: While a reader drains the terminal, a write waits this long (real seconds) for room
    #: before bytes are dropped: the terminal holds only ~4 KiB, a few of an LDRobot's turns at
    #: a 10× speed-up, and a thread the host schedules late must not lose a burst.
    DRAIN_WAIT_S = 0.5

    def __init__(self, master: int) -> None:
        self.master = master
        self.overruns = 0
        self._drained = False  # the last write went through: somebody reads

    def fileno(self) -> int:
        """The master descriptor (for select)."""
        return self.master

    def recv(self, size: int) -> bytes:
        """Bytes from the client; ``b"\\x00"``-free empty reads mean "nothing yet", never EOF."""
        try:
            return os.read(self.master, size) or b""
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as err:
            if err.errno == errno.EIO:  # no client has the terminal open right now
                return b""
            raise

    def sendall(self, data: bytes) -> None:
        """Write to the client; what does not fit the terminal's buffer is lost (after up to
        :attr:`DRAIN_WAIT_S` of waiting for room while somebody reads)."""
        view = memoryview(data)
        while view:
            try:
                written = os.write(self.master, view)
            except BlockingIOError:
                if self._drained and select.select([], [self.master], [],
                                                   self.DRAIN_WAIT_S)[1]:
                    continue
                self._drained = False
                self.overruns += 1
                return
            except OSError as err:
                if err.errno in (errno.EIO, errno.EAGAIN):
                    self._drained = False
                    self.overruns += 1
                    return
                raise
            view = view[written:]
        self._drained = True

    def close(self) -> None:
        """Nothing: the emulator closes the terminal itself."""


class ScannerEmulator:
    """The scanner on its real transport: a loopback TCP port (``scanner.transport = tcp``) or
    a pseudo-terminal (``serial``: open :attr:`port_path` with pyserial).

    What the device says and when it streams comes from its dialect's
    :class:`~scanpipe.sim.devices.EmulatedDevice` (the LD-OEM answers requests and streams after
    GET_PROFILE; ``paper`` streams from the moment a client connects). The head turns from the
    start at ``scan_hz``: profile k starts at ``phase + k / scan_hz`` simulation seconds and is
    sent when its sector is complete.
    """

    def __init__(self, scene: Scene, scanner_true: ScannerConfig, platform: PlatformState,
                 clock: SimClock, measurement: MeasurementModel, host: str = "127.0.0.1",
                 port: int = 0, phase_s: float = 0.0, scip_protocol: str = "2.0") -> None:
        self.scene = scene
        #: A Hokuyo's protocol at power-on (``sim.scip_device.START_PROTOCOLS``).
        self.scip_protocol = scip_protocol
        self.scanner = scanner_true
        self.platform = platform
        self.clock = clock
        self.measurement = measurement
        self.phase_s = phase_s
        self._bind = (host, port)
        self._server: socket.socket | None = None
        self._pty: tuple[int, int] | None = None
        self.port_path = ""
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()
        self.sent: list[SentProfile] = []
        #: Scans skipped because the emulator could not measure them in time (a loaded host).
        self.skipped_scans = 0
        self.devices: list[EmulatedDevice] = []

    @property
    def dialect(self) -> str:
        """The wire dialect."""
        return self.scanner.dialect

    @property
    def requests(self) -> list[str]:
        """What the devices were asked, connection after connection (where they log it)."""
        with self._lock:
            devices = list(self.devices)
        return [r for d in devices for r in getattr(d, "requests", [])]

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` the emulator listens on (TCP transport)."""
        if self._server is None:
            raise SimulationError("scanner emulator: not started (or not on TCP)")
        host, port = self._server.getsockname()[:2]
        return str(host), int(port)

    def start(self) -> None:
        """Listen (TCP) or open the pseudo-terminal (serial) and serve in background threads."""
        if self.scanner.transport == "serial":
            try:
                master, slave = os.openpty()
            except OSError as err:
                raise SimulationError(f"scanner emulator: cannot open a pseudo-terminal: {err}"
                                      ) from err
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._pty = (master, slave)
            self.port_path = os.ttyname(slave)
            self._spawn(self._serve, "scanner-pty", _PtyEndpoint(master))
            return
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            server.bind(self._bind)
        except OSError as err:
            server.close()
            raise SimulationError(f"scanner emulator: cannot listen on {self._bind}: {err}"
                                  ) from err
        server.listen(4)
        server.settimeout(POLL_S * 5)
        self._server = server
        self._spawn(self._accept_loop, "scanner-accept")

    def _spawn(self, target: Any, name: str, *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def stop(self) -> None:
        """Stop serving, close every connection and join the threads."""
        self._stop.set()
        self.drop_connections()
        if self._server is not None:
            with contextlib.suppress(OSError):
                self._server.close()
        for thread in self._threads:
            thread.join(timeout=5.0)
        self._threads.clear()
        if self._pty is not None:
            for fd in self._pty:
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._pty = None

    def drop_connections(self) -> None:
        """Close every client connection (a scanner that goes away); keeps listening."""
        with self._lock:
            clients, self._clients = self._clients, []
        for client in clients:
            with contextlib.suppress(OSError):
                client.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                client.close()

    def _accept_loop(self) -> None:
        assert self._server is not None
        while not self._stop.is_set():
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._clients.append(client)
            self._spawn(self._serve, "scanner-client", client)

    # -- one connection --------------------------------------------------------------------
    def _serve(self, client: socket.socket | _PtyEndpoint) -> None:
        device = emulated_device(self.scanner)
        if isinstance(device, ScipDevice):
            device.protocol = self.scip_protocol
        with self._lock:
            self.devices.append(device)
        serial = isinstance(client, _PtyEndpoint)
        next_k = self._next_head_index(self.clock.now_s())
        # A scan is measured (ray cast) ahead of its end by ``lead_s`` of simulation time, the
        # time measuring took last (×2), and sent at its end: a real head sends a scan the
        # moment it is taken, and measuring it only at its end put every receipt that much
        # late (≈ 4 ms of host time for an STL-27L turn), a floor under the latency that the
        # chain's clock fit, which takes the smallest latency as zero, turns into a time
        # error. It is re-measured at its end if the platform's moves changed meanwhile, so
        # the truth stays the truth.
        #
        # A device that sends a scan in packets as its samples are taken (``packet_ends``:
        # LDRobot) gets each packet once its last sample's instant has passed: the scan is
        # measured ahead of its start with the platform's moves so far, which fix every past
        # instant (a move begins now or later), so re-measuring after a change leaves the
        # packets already sent as they were.
        prepared: _Prepared | None = None
        packets = getattr(device, "packet_ends", None)
        sent_bytes = 0
        sent_at_s = -np.inf
        lead_s = 0.0
        try:
            while not self._stop.is_set():
                config = device.config()
                period = 1.0 / config.scan_hz
                due_s = self.phase_s + next_k * period + sector_duration_s(config)
                if packets is None:
                    wake_s = due_s if prepared is not None else due_s - lead_s
                elif prepared is None:
                    wake_s = self.phase_s + next_k * period - lead_s
                else:  # packets in groups, at most PACKET_GROUPS a turn (each wake costs CPU)
                    wake_s = max(prepared.next_packet_s(sent_bytes),
                                 sent_at_s + period / PACKET_GROUPS)
                wait_real = (wake_s - self.clock.now_s()) / self.clock.speedup
                timeout = min(max(wait_real, 0.0), POLL_S) if device.streaming else POLL_S
                readable, _, _ = select.select([client], [], [], timeout)
                if readable:
                    data = client.recv(1 << 16)
                    if not data and not serial:
                        return
                    if data:
                        was_streaming = device.streaming
                        now = self.clock.now_s()
                        for reply in device.receive(data, now):
                            client.sendall(reply)
                        if device.streaming and not was_streaming:
                            next_k = self._next_head_index(now, 1.0 / device.config().scan_hz)
                            prepared = None
                    continue
                if not device.streaming:
                    prepared = None
                    continue
                now_s = self.clock.now_s()
                if now_s >= due_s and sent_bytes == 0:
                    # A real head never falls behind: scans the emulator could not measure in
                    # time are skipped (counted), not sent late with stale device stamps, which
                    # would bend the host-device clock fit.
                    newest = int(np.floor((now_s - self.phase_s - sector_duration_s(config))
                                          / period + 1e-9))
                    if newest > next_k:
                        with self._lock:
                            self.skipped_scans += newest - next_k
                        next_k, prepared = newest, None
                        continue
                if packets is not None:
                    if prepared is None and now_s >= self.phase_s + next_k * period - lead_s:
                        began = time.monotonic()
                        prepared = self._prepare(next_k, config, device, packets)
                        lead_s = min(0.5 * period, 2.0 * (time.monotonic() - began)
                                     * self.clock.speedup)
                    if prepared is None:
                        continue
                    if prepared.moves != self.platform.timeline().moves:
                        prepared = self._prepare(next_k, config, device, packets)
                    sent_now_s = self.clock.now_s()
                    ready = prepared.bytes_ready(sent_now_s)
                    if ready > sent_bytes:
                        client.sendall(prepared.data[sent_bytes:ready])
                        sent_bytes, sent_at_s = ready, sent_now_s
                    if sent_bytes == len(prepared.data):
                        with self._lock:
                            self.sent.append(prepared.sent)
                        next_k, prepared, sent_bytes = next_k + 1, None, 0
                    continue
                if prepared is None and now_s >= due_s - lead_s:
                    began = time.monotonic()
                    prepared = self._prepare(next_k, config)
                    lead_s = min(0.5 * period, 2.0 * (time.monotonic() - began)
                                 * self.clock.speedup)
                if prepared is not None and self.clock.now_s() >= due_s:
                    if prepared.moves != self.platform.timeline().moves:
                        prepared = self._prepare(next_k, config)
                    client.sendall(self._send(prepared, config, device))
                    next_k, prepared = next_k + 1, None
        except OSError:
            return
        finally:
            with contextlib.suppress(OSError):
                client.close()

    def _next_head_index(self, now_s: float, period: float | None = None) -> int:
        period = period if period is not None else 1.0 / self.scanner.scan_hz
        return max(0, int(np.ceil((now_s - self.phase_s) / period - 1e-9)))

    def _prepare(self, k: int, config: ScannerConfig, device: EmulatedDevice | None = None,
                 packets: PacketEnds | None = None) -> _Prepared:
        """Measure scan ``k`` (at the platform angles of its samples' instants); with
        ``packets``, also its bytes and when each packet's last sample is taken."""
        moves = self.platform.timeline().moves
        start_s = self.phase_s + k / config.scan_hz
        offsets = sample_time_offsets_s(config)
        times = start_s + offsets
        beta = self.platform.beta_deg_at(times)[None, :]
        truth = true_ranges(self.scene, config, beta)
        beams = packet_beams(self.scene, config, beta) if config.dialect == "ldrobot_ld14" \
            else truth
        measured = measure(beams, self.measurement, k, config)[0]
        echo = (echo_amplitude(measured[None, :], beams)[0] if self._sends_echo(config)
                else None)
        sent = SentProfile(k, start_s, float(beta[0, 0]), float(beta[0, -1]), truth.ranges_m[0])
        if device is None or packets is None:
            return _Prepared(k, moves, measured, echo, sent)
        last_sample, byte_end = packets(len(measured))
        return _Prepared(k, moves, measured, echo, sent,
                         device.encode(k, measured, echo, config, start_s),
                         start_s + offsets[last_sample], byte_end)

    def _send(self, prepared: _Prepared, config: ScannerConfig, device: EmulatedDevice) -> bytes:
        """The device's bytes for a measured scan, recorded as sent."""
        with self._lock:
            self.sent.append(prepared.sent)
        return device.encode(prepared.k, prepared.measured, prepared.echo, config,
                             prepared.sent.start_s)

    @staticmethod
    def _sends_echo(config: ScannerConfig) -> bool:
        # The LD-OEM sends echoes when the GET_PROFILE mask asks for them (wire.profile_frame).
        from scanpipe.scanner_models import model_of

        if config.dialect == "ldoem":
            return True
        model = model_of(config.model, config.dialect)
        return model is not None and model.intensity

    def truth_table(self) -> pa.Table:
        """Per-profile truth of everything sent so far, in sending order (host-clock times)."""
        with self._lock:
            sent = list(self.sent)
        offsets = sample_time_offsets_s(self.scanner)
        samples = max((len(s.ranges_true_m) for s in sent), default=len(offsets))
        ranges = np.full((len(sent), samples), np.nan)
        for row, s in enumerate(sent):
            ranges[row, :len(s.ranges_true_m)] = s.ranges_true_m
        return truth_table(
            np.array([self.clock.wall_ns(s.start_s) for s in sent], dtype=np.int64),
            np.array([self.clock.wall_ns(s.start_s + offsets[-1]) for s in sent], dtype=np.int64),
            np.array([s.beta_first_deg for s in sent]), np.array([s.beta_last_deg for s in sent]),
            ranges)


class MotorEmulator:
    """The motor controller on a pseudo-terminal (open :attr:`port_path` with pyserial)."""

    def __init__(self, motor: MotorConfig, platform: PlatformState, clock: SimClock,
                 report_interval_s: float = 0.02) -> None:
        self.clock = clock
        self.controller = MotorController(motor, platform, report_interval_s)
        self._master = -1
        self._slave = -1
        self.port_path = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.commands: list[str] = []
        self.overruns = 0

    def start(self) -> None:
        """Open the pseudo-terminal and answer commands in a background thread."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port_path = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._loop, name="motor-emulator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close the pseudo-terminal."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def _send(self, lines: list[str]) -> None:
        data = "".join(line + "\n" for line in lines).encode("ascii")
        try:
            os.write(self._master, data)
        except BlockingIOError:
            self.overruns += 1  # nobody reads: the line is lost, as on a real UART
        except OSError as err:
            if err.errno not in (errno.EIO, errno.EAGAIN):
                raise

    def _reports(self, now_s: float) -> None:
        reports = self.controller.reports_until(now_s)
        if reports:
            self._send([r.line for r in reports])

    def _loop(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            now = self.clock.now_s()
            next_report = self.controller.next_report_s()
            timeout = POLL_S
            if np.isfinite(next_report):
                timeout = min(POLL_S, max(0.0, (next_report - now) / self.clock.speedup))
            try:
                readable, _, _ = select.select([self._master], [], [], timeout)
            except (OSError, ValueError):
                return
            if readable:
                try:
                    buffer += os.read(self._master, 4096)
                except BlockingIOError:
                    pass
                except OSError:
                    continue  # EIO: no client has the terminal open right now
                while b"\n" in buffer or b"\r" in buffer:
                    cut = min(i for i in (buffer.find(b"\n"), buffer.find(b"\r")) if i >= 0)
                    line, buffer = buffer[:cut], buffer[cut + 1:]
                    text = line.decode("ascii", "replace").strip()
                    if not text:
                        continue
                    now = self.clock.now_s()
                    self._reports(now)
                    self.commands.append(text)
                    self._send(self.controller.handle(text, now))
            self._reports(self.clock.now_s())


class VirtualCamera:
    """A camera with the interface of ``cv2.VideoCapture``: ``read``, ``grab``/``retrieve``,
    ``get``, ``set``, ``isOpened``, ``release``. Frames are BGR, rendered at the platform angle
    of the instant of ``grab`` (or ``read``)."""

    is_live = True

    def __init__(self, scene: Scene, cam: CameraConfig, platform: PlatformState,
                 clock: SimClock, model: CameraModel = CameraModel(), seed: int = 0,
                 index: int = 0) -> None:
        self.scene = scene
        self.cam = cam
        self.platform = platform
        self.clock = clock
        self.model = model
        self.seed = seed
        self.index = index
        self.frames = 0
        self._grab_s: float | None = None
        self._open = True
        self.captures: list[tuple[float, float]] = []  # (simulation time, true β)

    def isOpened(self) -> bool:
        """Whether the camera can deliver frames."""
        return self._open

    def grab(self) -> bool:
        """Take the capture instant (now)."""
        if not self._open:
            return False
        self._grab_s = self.clock.now_s()
        return True

    def retrieve(self) -> tuple[bool, NDArray[np.uint8] | None]:
        """Render the frame of the last :meth:`grab` (BGR, like OpenCV)."""
        if not self._open or self._grab_s is None:
            return False, None
        beta = float(self.platform.beta_deg_at(self._grab_s))
        rng = np.random.default_rng([self.seed, 13, self.index, self.frames])
        rgb = render_rgb(self.scene, self.cam, beta, self.model, rng)
        self.captures.append((self._grab_s, beta))
        self.frames += 1
        self._grab_s = None
        return True, np.ascontiguousarray(rgb[..., ::-1])

    def read(self) -> tuple[bool, NDArray[np.uint8] | None]:
        """Grab and retrieve one frame."""
        if not self.grab():
            return False, None
        return self.retrieve()

    def get(self, prop: int) -> float:
        """``CAP_PROP_FPS``, ``CAP_PROP_FRAME_WIDTH``, ``CAP_PROP_FRAME_HEIGHT``,
        ``CAP_PROP_POS_FRAMES``; 0 for anything else (as OpenCV does)."""
        values = {cv2.CAP_PROP_FPS: self.cam.fps, cv2.CAP_PROP_FRAME_WIDTH: self.cam.width,
                  cv2.CAP_PROP_FRAME_HEIGHT: self.cam.height,
                  cv2.CAP_PROP_POS_FRAMES: self.frames, cv2.CAP_PROP_FRAME_COUNT: 0}
        return float(values.get(prop, 0.0))

    def set(self, prop: int, value: float) -> bool:
        """Settings are fixed by the rig: always False (as OpenCV for unsupported ones)."""
        return False

    def release(self) -> None:
        """Close the camera."""
        self._open = False


class VirtualRig:
    """The whole virtual rig: scene, clock, platform, scanner, motor controller and cameras.

    Use as a context manager, or call :meth:`start` and :meth:`stop`. :meth:`client_rig` is
    the nominal rig pointed at the emulators' endpoints (what ``record`` should be given);
    :meth:`write_truth` writes the ground-truth folder of what was sent.
    """

    def __init__(self, options: SimOptions | None = None, speedup: float = 1.0,
                 scene: Scene | None = None) -> None:
        from scanpipe.sim.direct import checked_rigs

        self.options = options if options is not None else SimOptions()
        self.nominal, self.true = checked_rigs(self.options)
        if scene is None:
            from scanpipe.sim.direct import check_scene_in_view

            scene = resolve_scene(self.options.scene, self.options.scene_pose,
                                  self.options.scene_up)
            check_scene_in_view(scene, self.true.scanner, self.options.scene)
        self.scene = scene
        self.clock = SimClock(speedup)
        motor = self.true.motor
        self.platform = PlatformState(motor.pulse_step_deg, motor.beta_offset_deg)
        phase = float(np.random.default_rng([self.options.seed, 7]).uniform(
            0.0, 1.0 / self.true.scanner.scan_hz))
        self.scanner = ScannerEmulator(self.scene, self.true.scanner, self.platform, self.clock,
                                       self.options.measurement(), phase_s=phase,
                                       scip_protocol=self.options.scip_protocol)
        self.motor = MotorEmulator(motor, self.platform, self.clock,
                                   self.options.report_interval_s)
        self.cameras = {
            cam.id: VirtualCamera(self.scene, cam, self.platform, self.clock,
                                  self.options.camera_model(), self.options.seed, index)
            for index, cam in enumerate(self.true.cameras)
        } if self.options.cameras else {}
        self._started = False

    def start(self) -> None:
        """Start the scanner server and the motor controller."""
        self.scene.cast(np.zeros(3), np.array([[0.0, 1.0, 0.0]]))  # build the BVH up front
        self.scanner.start()
        try:
            self.motor.start()
        except OSError as err:
            self.scanner.stop()
            raise SimulationError(f"motor emulator: cannot open a pseudo-terminal: {err}"
                                  ) from err
        self._started = True

    def stop(self) -> None:
        """Stop every emulator (idempotent)."""
        if self._started:
            self.scanner.stop()
            self.motor.stop()
            for camera in self.cameras.values():
                camera.release()
            self._started = False

    def __enter__(self) -> VirtualRig:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def client_rig(self) -> Rig:
        """The nominal rig with the scanner, motor and camera sources at the emulators."""
        if self.nominal.scanner.transport == "serial":
            scanner = self.nominal.scanner.model_copy(
                update={"serial_url": self.scanner.port_path})
        else:
            host, port = self.scanner.address
            scanner = self.nominal.scanner.model_copy(update={"host": host, "port": port})
        motor = self.nominal.motor.model_copy(update={"serial_url": self.motor.port_path})
        cameras = tuple(c.model_copy(update={"source": f"sim:{c.id}"})
                        for c in self.nominal.cameras)
        return self.nominal.model_copy(update={"scanner": scanner, "motor": motor,
                                               "cameras": cameras})

    def camera(self, source: str) -> VirtualCamera:
        """The virtual camera for a ``sim:<id>`` source (or a bare id)."""
        camera_id = source.removeprefix("sim:")
        if camera_id not in self.cameras:
            known = ", ".join(self.cameras) or "none"
            raise SimulationError(f"no virtual camera {camera_id!r} (cameras: {known})")
        return self.cameras[camera_id]

    def write_truth(self, folder: Path, summary: dict[str, Any] | None = None) -> None:
        """The ground-truth folder for what the scanner emulator sent."""
        import json

        from scanpipe.sim.direct import versions

        meta = {"seed": self.options.seed, "options": json.loads(self.options.model_dump_json()),
                "versions": versions(), "speedup": self.clock.speedup,
                "summary": summary or {}, "profiles_sent": len(self.scanner.sent),
                "scans_skipped": self.scanner.skipped_scans,
                "camera_captures": {k: len(c.captures) for k, c in self.cameras.items()}}
        write_truth(folder, self.scene, self.true, self.scanner.truth_table(), meta)
