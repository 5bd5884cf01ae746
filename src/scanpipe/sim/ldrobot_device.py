"""The simulated LDRobot LD06 / LD19 / STL-27L / LD14 / LD14P: a head that spins and sends
from power-on (the LD14/LD14P's beams lie the SDK's distance-dependent shift below the angles
their packets report; :func:`scanpipe.protocol.ldrobot.sl_packet_angles_deg`).

The real devices take no command on their serial line (the LD06's speed is set by a PWM pin;
some firmwares of the family accept none at all, and none is needed to start them), so the
emulator models that: packets stream from the moment the port exists, whether anybody reads
or not. What it models (deterministic for a seed, any packet computable on its own):

- the sample clock: sample ``k`` is measured at ``k / sample_hz`` (4 500/s LD06 and LD19,
  21 600/s STL-27L), 12 to a packet;
- the head: ``scan_hz`` turns per second with a slow speed wobble (±0.5 % at 0.37 Hz, a
  PWM-driven motor), so samples are not on a fixed angular grid and a turn holds a varying
  number of them; a packet reports its head speed (°/s), the encoder angles of its first and
  last sample (0.01°, with 0.02° of encoder jitter) and its first sample's time (ms, wrapping
  at 30 000 like the devices);
- the beams: the true beam of a sample lies on the straight line between the packet's true
  start and end angles (what the vendor's interpolation assumes); its range is ray cast at
  the platform angle of its instant, with Gaussian noise, a base dropout rate plus fading at
  grazing incidence (a dropout is distance 0 with a low intensity, a "low-confidence" sample),
  and the device's range window; distances are whole millimetres;
- intensity: high for a square-on return, falling with incidence and range.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import tty
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanpipe.device_limits import LDROBOT_LIMITS, LdrobotLimits
from scanpipe.errors import SimulationError
from scanpipe.protocol import ldrobot
from scanpipe.rig import ScannerConfig
from scanpipe.sim.clock import SimClock
from scanpipe.sim.motion import PlatformState
from scanpipe.sim.scanner import MeasurementModel, true_ranges
from scanpipe.sim.scene import Scene
from scanpipe.sim.streaming_device import StreamingDevice

F64 = NDArray[np.float64]

#: The device clock reads this many ms when the simulation starts (then wraps at 30 000).
CLOCK_ORIGIN_MS = 12_345
#: The head's speed wobble: relative amplitude and frequency (Hz).
WOBBLE = 0.005
WOBBLE_HZ = 0.37
#: Encoder jitter on the reported start and end angles (degrees, 1 σ).
ENCODER_JITTER_DEG = 0.02
#: How often the emulator thread looks at the clock at most (real seconds).
POLL_S = 0.02


@dataclass(frozen=True)
class LdrobotModel:
    """What one model of the family is: its limits (:data:`LDROBOT_LIMITS`), the head speed
    it runs at, and its range noise (a modelling choice: the datasheets quote accuracy bands,
    not a σ)."""

    limits: LdrobotLimits
    scan_hz: float
    noise_sigma_m: float

    @property
    def name(self) -> str:
        """The model's key."""
        return self.limits.model

    @property
    def sample_hz(self) -> float:
        """Samples per second (fixed by the model)."""
        return self.limits.sample_hz

    @property
    def baud(self) -> int:
        """The serial link's baud rate."""
        return self.limits.baud

    @property
    def min_range_m(self) -> float:
        """The nearest range it measures."""
        return self.limits.min_range_m

    @property
    def max_range_m(self) -> float:
        """The farthest range it measures."""
        return self.limits.max_range_m

    @property
    def samples_per_turn(self) -> float:
        """Samples in one head turn at the nominal speed."""
        return self.sample_hz / self.scan_hz

    @property
    def beam_step_deg(self) -> float:
        """The angle between two samples at the nominal speed."""
        return self.limits.beam_step_deg(self.scan_hz)


#: The family at its nominal speed (10 Hz; LD14/LD14P 6 Hz), with a range noise σ of 10 mm
#: (LD14/LD14P 15 mm, as their scanner models).
LDROBOT_MODELS: dict[str, LdrobotModel] = {
    name: LdrobotModel(limits, limits.nominal_hz, 0.015 if limits.angle_correction else 0.010)
    for name, limits in LDROBOT_LIMITS.items()}


def ldrobot_model(name: str) -> LdrobotModel:
    """The model called ``name``; :class:`SimulationError` naming the known ones otherwise."""
    if name not in LDROBOT_MODELS:
        raise SimulationError(f"LDRobot model {name!r}: unknown; allowed: "
                              f"{', '.join(LDROBOT_MODELS)}")
    return LDROBOT_MODELS[name]


@dataclass(frozen=True)
class HeadPackets:
    """Packets ``first … first + n − 1`` on the wire, and their truth."""

    first: int
    data: bytes
    sample_time_s: F64  # (n, 12): simulation time of every sample
    beam_deg: F64  # (n, 12): true beam angle (device angle, before the scanner's α offset)
    beta_deg: F64  # (n, 12): true platform angle at each sample
    ranges_true_m: F64  # (n, 12): noise-free, NaN = no hit or outside the range window


class LdrobotHead:
    """The spinning head of one device over a scene on a platform (module docstring)."""

    def __init__(self, model: LdrobotModel, scene: Scene, scanner_true: ScannerConfig,
                 platform: PlatformState, measurement: MeasurementModel,
                 phase_deg: float = 0.0) -> None:
        self.model = model
        self.scene = scene
        self.scanner = scanner_true
        self.platform = platform
        self.measurement = measurement
        self.phase_deg = phase_deg
        self._omega_dps = 360.0 * model.scan_hz
        rng = np.random.default_rng([measurement.seed, 0x1D06])
        self._wobble_phase = float(rng.uniform(0, 2 * np.pi))

    @property
    def packet_s(self) -> float:
        """Time from one packet's first sample to the next packet's."""
        return ldrobot.POINTS_PER_PACKET / self.model.sample_hz

    def packet_due(self, index: int) -> float:
        """Simulation time at which packet ``index`` is complete (its last sample taken)."""
        return (index * ldrobot.POINTS_PER_PACKET + ldrobot.POINTS_PER_PACKET - 1
                ) / self.model.sample_hz

    def head_deg(self, time_s: F64) -> F64:
        """The head's true (unwrapped) angle at ``time_s``: the integral of its speed."""
        w = 2 * np.pi * WOBBLE_HZ
        t = np.asarray(time_s, np.float64)
        wobble = -WOBBLE / w * (np.cos(w * t + self._wobble_phase) - np.cos(self._wobble_phase))
        return np.asarray(self.phase_deg + self._omega_dps * (t + wobble), np.float64)

    def speed_dps(self, time_s: F64) -> F64:
        """The head's speed at ``time_s`` (°/s)."""
        w = 2 * np.pi * WOBBLE_HZ
        t = np.asarray(time_s, np.float64)
        return np.asarray(self._omega_dps * (1 + WOBBLE * np.sin(w * t + self._wobble_phase)),
                          np.float64)

    def packets(self, first: int, count: int) -> HeadPackets:
        """Packets ``first … first + count − 1``: bytes and truth."""
        if count <= 0:
            raise SimulationError(f"LDRobot head: {count} packets asked for")
        n, per = count, ldrobot.POINTS_PER_PACKET
        index = np.arange(first, first + n, dtype=np.int64)
        times = (index[:, None] * per + np.arange(per)) / self.model.sample_hz  # (n, 12)
        start_true = self.head_deg(times[:, 0])
        end_true = self.head_deg(times[:, -1])
        beams = start_true[:, None] + (end_true - start_true)[:, None] * (
            np.arange(per) / (per - 1))
        beta = self.platform.beta_deg_at(times.ravel()).reshape(n, per)
        if self.model.limits.angle_correction:
            # LD14/LD14P: the sample reported at the interpolated angle is the beam that
            # points there less the distance-dependent shift (the decoder adds it back).
            def range_at(beam_deg: F64) -> F64:
                return cast_beams(self.scene, self.scanner, beam_deg, beta.ravel())[0]

            beams = ldrobot.sl_packet_angles_deg(beams.ravel(), range_at)[0].reshape(n, per)
        truth, cos_inc = cast_beams(self.scene, self.scanner, beams.ravel(), beta.ravel())
        truth = truth.reshape(n, per)
        cos_inc = cos_inc.reshape(n, per)
        u = self._uniforms(first, n)
        distance_mm, intensity = self._measure(truth, cos_inc, u)
        jitter = _normal(u[:, 48:50], u[:, 50:52]).T * ENCODER_JITTER_DEG
        start_cdeg = np.rint((start_true + jitter[0]) * 100).astype(np.int64) % ldrobot.TURN_CDEG
        end_cdeg = np.rint((end_true + jitter[1]) * 100).astype(np.int64) % ldrobot.TURN_CDEG
        speed = np.clip(np.rint(self.speed_dps(times[:, 0])), 0, 0xFFFF).astype(np.int64)
        stamp = (CLOCK_ORIGIN_MS + np.floor(times[:, 0] * 1000.0).astype(np.int64)
                 ) % ldrobot.TIME_WRAP_MS
        data = ldrobot.encode_packets(speed, start_cdeg, distance_mm, intensity, end_cdeg, stamp)
        return HeadPackets(first, data, times, beams, beta, truth)

    def _uniforms(self, first: int, count: int) -> F64:
        """The random numbers of packets ``first …``: :data:`_DRAWS` uniforms each, the same
        for a packet however the packets are batched (a counter-based generator)."""
        bits = np.random.Philox(key=[self.measurement.seed, 0x1D06])
        bits.advance(first * _DRAWS // 4)  # Philox counts blocks of four draws
        return np.random.Generator(bits).random((count, _DRAWS))

    def _measure(self, truth: F64, cos_inc: F64,
                 u: F64) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        m, model = self.measurement, self.model
        value = truth + _normal(u[:, 0:12], u[:, 12:24]) * model.noise_sigma_m
        grazing = np.cos(np.radians(m.grazing_start_deg))
        p_graze = np.clip((grazing - cos_inc) / max(grazing, 1e-9), 0.0, 1.0)
        dropped = u[:, 24:36] < m.dropout_rate + (1 - m.dropout_rate) * p_graze
        lost = (dropped | ~np.isfinite(value) | (value < model.min_range_m)
                | (value > model.max_range_m))
        distance = np.where(lost, 0, np.clip(np.rint(value * 1000.0), 1, 0xFFFF))
        with np.errstate(invalid="ignore"):
            strength = 40 + 200 * np.nan_to_num(cos_inc) * np.clip(
                1 - np.nan_to_num(truth) / (2 * model.max_range_m), 0, 1)
        low = np.floor(u[:, 36:48] * 16)  # a dropout's intensity: 0…15
        jitter = (u[:, 36:48] - 0.5) * 8
        intensity = np.where(lost, low, np.clip(np.rint(strength + jitter), 16, 255))
        return distance.astype(np.int64), intensity.astype(np.int64)


#: Uniform draws per packet: 24 for the 12 range noises, 12 dropout draws, 12 for the
#: intensities, 4 for the two encoder jitters (a multiple of 4: Philox's block).
_DRAWS = 52


def _normal(u1: F64, u2: F64) -> F64:
    """Standard normal numbers from two uniforms each (Box–Muller)."""
    return np.asarray(np.sqrt(-2.0 * np.log1p(-u1)) * np.cos(2 * np.pi * u2), np.float64)


def cast_beams(scene: Scene, scanner_true: ScannerConfig, beam_deg: F64,
               beta_deg: F64) -> tuple[F64, F64]:
    """True ranges (NaN = no hit or outside the scanner's window) and |cos incidence| of beams
    at device angles ``beam_deg`` (the scanner's α offset added), each at its own platform
    angle ``beta_deg`` (flat arrays of one length): :func:`~scanpipe.sim.scanner.true_ranges`
    for one row of free beam angles."""
    truth = true_ranges(scene, scanner_true, np.asarray(beta_deg, np.float64)[None, :],
                        beam_deg=np.asarray(beam_deg, np.float64))
    return truth.ranges_m[0], truth.cos_incidence[0].astype(np.float64)


class LdrobotEmulator:
    """The device on a pseudo-terminal (open :attr:`port_path` like its USB serial port).

    A background thread writes every packet whose last sample has been taken (on the shared
    :class:`~scanpipe.sim.clock.SimClock`) from :meth:`start` to :meth:`stop`, whether anybody
    reads or not: like the real device, which never waits for the host. Bytes the terminal
    cannot take (nobody reading, its buffer full) are lost, as on a UART (``bytes_lost``).
    """

    def __init__(self, head: LdrobotHead, clock: SimClock) -> None:
        self.head = head
        self.clock = clock
        self.port_path = ""
        self.packets_sent = 0
        self.bytes_lost = 0
        self._master = -1
        self._slave = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Open the pseudo-terminal and start streaming."""
        try:
            self._master, self._slave = os.openpty()
        except OSError as err:
            raise SimulationError(f"LDRobot emulator: cannot open a pseudo-terminal: {err}"
                                  ) from err
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port_path = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._loop, name="ldrobot-emulator",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop streaming and close the pseudo-terminal (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def _loop(self) -> None:
        head, per_s = self.head, 1.0 / self.head.packet_s
        while not self._stop.is_set():
            now = self.clock.now_s()
            due = int(np.floor((now - head.packet_due(0)) * per_s)) + 1  # packets complete
            if due > self.packets_sent:
                # At most a second of packets per write: a stalled thread catches up in steps.
                count = min(due - self.packets_sent, int(per_s) + 1)
                self._write(head.packets(self.packets_sent, count).data)
                self.packets_sent += count
                continue
            self._stop.wait(min(POLL_S, max(head.packet_s * 4 / self.clock.speedup, 0.001)))

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                written = os.write(self._master, view)
            except BlockingIOError:
                written = 0
            except OSError as err:
                if err.errno in (errno.EIO, errno.EAGAIN):
                    written = 0
                else:
                    raise
            if written == 0:
                self.bytes_lost += len(view)  # nobody reads fast enough: lost, as on a UART
                return
            view = view[written:]


class LdrobotEmulated(StreamingDevice):
    """The LDRobot device for :class:`~scanpipe.sim.emulators.ScannerEmulator` (the shared
    emulator over a pty, ``transport = serial``): it streams from the moment the port exists
    and ignores what it is sent (there is no command). Each measured profile (the rig's grid,
    one head turn) goes out as packets of 12 samples the moment the turn is measured; when 12
    does not divide the turn, its last packet ends on its last sample and repeats a few of the
    previous packet's (a real head's packet would hold the next turn's first samples, which the
    shared emulator measures only a turn later: repeating keeps the turn's latency at one
    packet, as on the device). Each packet
    carries the head speed (with the ±0.5 % wobble), the encoder angles of its first and last
    sample (with 0.02° of jitter), its first sample's time on the device clock (ms, wrapping at
    30 000) and per sample the distance (mm, 0 = no return) and an intensity (the echo model
    scaled to 16…255; a no-return gets 0…15, a low-confidence sample)."""

    def __init__(self, scanner: ScannerConfig) -> None:
        super().__init__(scanner)  # no command to answer; the head speed is set by PWM
        rng = np.random.default_rng(0x1D06)
        self._wobble_phase = float(rng.uniform(0, 2 * np.pi))
        self._packets = 0

    @staticmethod
    def packet_ends(samples: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Per packet of a turn of ``samples`` (as :meth:`encode` lays them out): the index of
        its last sample and the byte offset one past it. The emulator sends each packet once
        its last sample is taken, as the device does."""
        per = ldrobot.POINTS_PER_PACKET
        count = -(-samples // per) if samples >= per else 0
        rows = np.minimum(np.arange(count, dtype=np.int64) * per, samples - per)
        return rows + per - 1, (np.arange(count, dtype=np.int64) + 1) * ldrobot.PACKET_BYTES

    def encode(self, k: int, ranges_m: NDArray[np.float32], echo: NDArray[np.uint16] | None,
               config: ScannerConfig, start_s: float) -> bytes:
        """The packets completed by profile ``k`` (its samples after the carried ones)."""
        n = len(ranges_m)
        step = config.beam_step_deg
        angle = config.start_angle_deg + np.arange(n) * step
        time_s = start_s + (angle - config.start_angle_deg) / (360.0 * config.scan_hz)
        ranges = np.asarray(ranges_m, np.float64)
        lost = ~np.isfinite(ranges) | (ranges <= 0)
        mm = np.where(lost, 0.0, np.clip(np.rint(np.nan_to_num(ranges) * 1000.0), 1, 0xFFFF))
        low = (np.arange(n) * 7 + k) % 16
        # the u16 echo model (40 000 head-on at 1 m, white) to the u8 intensity: 250 there
        strong = (np.zeros(n) if echo is None else np.asarray(echo, np.float64)) / 160.0
        intensity = np.where(lost, low, np.clip(np.rint(strong), 16, 255)).astype(np.float64)
        per = ldrobot.POINTS_PER_PACKET
        if n < per:
            return b""
        packets = -(-n // per)
        rows = np.minimum(np.arange(packets) * per, n - per)[:, None] + np.arange(per)
        a, t = angle[rows], time_s[rows]
        mm, intensity = mm[rows], intensity[rows]
        self._packets += packets
        u = np.random.default_rng([0x1D06, k]).random((packets, 4))
        jitter = _normal(u[:, 0:2], u[:, 2:4]).T * ENCODER_JITTER_DEG
        w = 2 * np.pi * WOBBLE_HZ
        speed = 360.0 * config.scan_hz * (1 + WOBBLE * np.sin(w * t[:, 0] + self._wobble_phase))
        start = np.rint((a[:, 0] + jitter[0]) * 100).astype(np.int64) % ldrobot.TURN_CDEG
        end = np.rint((a[:, -1] + jitter[1]) * 100).astype(np.int64) % ldrobot.TURN_CDEG
        stamp = (CLOCK_ORIGIN_MS + np.floor(t[:, 0] * 1000.0).astype(np.int64)
                 ) % ldrobot.TIME_WRAP_MS
        return ldrobot.encode_packets(
            np.clip(np.rint(speed), 0, 0xFFFF).astype(np.int64), start, mm.astype(np.int64),
            intensity.astype(np.int64), end, stamp)
