"""The LD-OEM 1000's request handling, as a pure state machine (no sockets, no clock).

The TCP emulator (:mod:`scanpipe.sim.emulators`) and direct mode both use it, so both answer the
acquisition client's start-up requests with the same bytes. Replies follow
:mod:`scanpipe.protocol.ldoem`; a refused request is answered with the request's code, the reply
bit, and a body of u16 0xFFFF followed by an ASCII reason (scanpipe's convention, which the
acquisition client reads).

Request bodies this emulator understands beyond the public facts (documented in
docs/simulation.md): SET_CONFIG = u16 angular step, u16 start angle, u16 end angle (all in 1/16°);
GET_CONFIG replies u16 scan_hz and the same three values; GET_SYNC_CLOCK replies the u16
millisecond clock; SET_TIME_ABS takes a u16 millisecond value, SET_TIME_REL a signed u16 shift.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from scanpipe.device_limits import LDOEM_HEAD_HZ, LDOEM_MAX_MEAN_PULSE_HZ, LDOEM_MAX_PULSE_HZ
from scanpipe.errors import ProtocolError
from scanpipe.protocol import ldoem
from scanpipe.rig import ScannerConfig

IDENT = "LD-OEM1000 scanpipe-sim 1"
#: The encoder ticks of one turn and the smallest step the device takes (0.125° = 2 ticks).
TICKS_PER_TURN = 5760
STEP_QUANTUM_TICKS = 2
MAX_POINTS_PER_SECTOR = 2881


def refusal(service: int, sub: int, reason: str) -> bytes:
    """The reply frame refusing a request, with its reason."""
    return ldoem.reply(service, sub, b"\xff\xff" + reason.encode("ascii", "replace"))


def _u16(*values: int) -> bytes:
    return b"".join(int(v).to_bytes(2, "big") for v in values)


@dataclass
class StreamRequest:
    """A GET_PROFILE in force: how many profiles (0 = until cancelled) in which format."""

    count: int
    mask: int
    sent: int = 0


@dataclass
class LdoemDevice:
    """What the scanner answers and how it is configured (head speed, sector, stream)."""

    scanner: ScannerConfig
    scan_hz: int = 0
    step_ticks: int = 0
    start_ticks: int = 0
    end_ticks: int = 0
    stream: StreamRequest | None = None
    clock_ms_offset: int = 0
    log: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.scan_hz = int(self.scanner.scan_hz)
        self.step_ticks = round(self.scanner.beam_step_deg * 16)
        self.start_ticks = round(self.scanner.start_angle_deg * 16)
        self.end_ticks = round(self.scanner.end_angle_deg * 16)

    def _limit_problem(self, scan_hz: int, step_ticks: int, start: int, end: int) -> str:
        if not LDOEM_HEAD_HZ[0] <= scan_hz <= LDOEM_HEAD_HZ[1]:
            return f"scan_hz {scan_hz} outside {LDOEM_HEAD_HZ[0]}..{LDOEM_HEAD_HZ[1]} Hz"
        if step_ticks <= 0 or step_ticks % STEP_QUANTUM_TICKS:
            return f"beam step {step_ticks}/16 deg is not a multiple of 0.125 deg"
        if not 0 <= start < end <= TICKS_PER_TURN:
            return f"sector {start}..{end}/16 deg is not within one turn"
        if (end - start) // step_ticks > MAX_POINTS_PER_SECTOR:
            return f"sector of {(end - start) // step_ticks} points exceeds {MAX_POINTS_PER_SECTOR}"
        pulse_hz = scan_hz * TICKS_PER_TURN / step_ticks
        if pulse_hz > LDOEM_MAX_PULSE_HZ + 1e-9:
            return f"pulse frequency {pulse_hz:g} Hz exceeds {LDOEM_MAX_PULSE_HZ:g} Hz"
        if pulse_hz * (end - start) / TICKS_PER_TURN > LDOEM_MAX_MEAN_PULSE_HZ + 1e-9:
            return f"mean pulse frequency exceeds {LDOEM_MAX_MEAN_PULSE_HZ:g} Hz"
        return ""

    def handle(self, payload: bytes, clock_ms: int) -> list[bytes]:
        """Reply frames to one request payload. ``clock_ms`` is the device's millisecond clock.

        A GET_PROFILE is answered by the profiles themselves (see :attr:`stream`).
        """
        try:
            message = ldoem.parse_payload(payload)
        except ProtocolError as err:
            self.log.append(f"unknown request: {err}")
            service, sub = (payload[0] & 0x7F, payload[1]) if len(payload) >= 2 else (0, 0)
            return [refusal(service, sub, "unknown request")]
        if message.is_reply:
            return []
        service, sub = message.service, message.sub
        self.log.append(f"request {service:02x} {sub:02x}")
        try:
            return self._dispatch(message, clock_ms)
        except ProtocolError as err:
            return [refusal(service, sub, str(err))]

    def _dispatch(self, message: ldoem.Message, clock_ms: int) -> list[bytes]:
        service, sub = message.service, message.sub
        if (service, sub) == (ldoem.SERVICE_STATUS, ldoem.GET_IDENT):
            return [ldoem.reply(service, sub, IDENT.encode("ascii"))]
        if (service, sub) == (ldoem.SERVICE_STATUS, ldoem.GET_STATUS):
            mode = ldoem.SENSOR_MEASURE if self.stream else ldoem.SENSOR_ROTATE
            return [ldoem.status_reply(mode, ldoem.MOTOR_OK)]
        if (service, sub) == (ldoem.SERVICE_WORKING, ldoem.WORKING_ROTATE):
            hz = message.u16(0)
            problem = self._limit_problem(hz, self.step_ticks, self.start_ticks, self.end_ticks)
            if problem:
                return [refusal(service, sub, problem)]
            self.scan_hz = hz
            return [ldoem.reply(service, sub)]
        if (service, sub) == (ldoem.SERVICE_CONFIG, ldoem.SET_CONFIG):
            step, start, end = message.u16(0), message.u16(1), message.u16(2)
            problem = self._limit_problem(self.scan_hz, step, start, end)
            if problem:
                return [refusal(service, sub, problem)]
            self.step_ticks, self.start_ticks, self.end_ticks = step, start, end
            return [ldoem.reply(service, sub)]
        if (service, sub) == (ldoem.SERVICE_CONFIG, ldoem.GET_CONFIG):
            return [ldoem.reply(service, sub, _u16(self.scan_hz, self.step_ticks,
                                                   self.start_ticks, self.end_ticks))]
        if (service, sub) == (ldoem.SERVICE_CONFIG, ldoem.GET_SYNC_CLOCK):
            return [ldoem.reply(service, sub, _u16((clock_ms + self.clock_ms_offset) & 0xFFFF))]
        if (service, sub) == (ldoem.SERVICE_CONFIG, ldoem.SET_TIME_ABS):
            self.clock_ms_offset = message.u16(0) - clock_ms
            return [ldoem.reply(service, sub)]
        if (service, sub) == (ldoem.SERVICE_CONFIG, ldoem.SET_TIME_REL):
            delta = message.u16(0)
            self.clock_ms_offset += delta - 0x10000 if delta & 0x8000 else delta
            return [ldoem.reply(service, sub)]
        if (service, sub) == (ldoem.SERVICE_MEASURE, ldoem.GET_PROFILE):
            count, mask = ldoem.parse_get_profile_request(message)
            ldoem.check_mask(mask)
            self.stream = StreamRequest(count, mask)
            return []
        if (service, sub) == (ldoem.SERVICE_MEASURE, ldoem.CANCEL_PROFILE):
            self.stream = None
            return [ldoem.reply(service, sub)]
        if service == ldoem.SERVICE_WORKING:
            if sub != ldoem.WORKING_MEASURE:
                self.stream = None
            return [ldoem.reply(service, sub)]
        return [ldoem.reply(service, sub)]  # accepted and ignored (SET_FUNCTION, …)
