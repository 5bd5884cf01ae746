"""The ``ldoem`` dialect: the SICK LD-OEM 1000's own TCP protocol (facts: shared/paper/NOTES.md).

Frame: ``02 55 53 50`` ("STX U S P"), u32 big-endian payload length, payload, XOR of the
payload. Payload byte 0 is the service code, byte 1 the sub-code; a reply echoes the request's
service code with bit 0x80 set. All fields are big-endian u16.

A GET_PROFILE reply (``83 01``): format mask, number of sectors, then the fields the mask selects:
the profile header (PROFILESENT, PROFILECOUNT, LAYERNUM); per sector SECTORNUM, DIRSTEP (1/16°),
POINTNUM, TSTART (ms), STARTDIR (1/16°), per point DISTANCE (1/256 m), DIRECTION (1/16°), ECHO,
then TEND (ms) and ENDDIR (1/16°); last SENSTAT (4 bytes; the 4th byte holds the sensor mode in
its low nibble and the motor mode in its high nibble).

The request builders and :func:`encode_profile_reply` return whole frames, ready to send;
:func:`parse_payload` reads the payload of any frame (request or reply).
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ProtocolError
from scanpipe.protocol import framing
from scanpipe.protocol.framing import LengthMismatch
from scanpipe.protocol.profile import (
    ANGLE_SCALE_PER_DEG,
    TICKS_PER_TURN,
    Profile,
    angle_to_wire,
    check_plausible,
    ranges_from_wire,
    ranges_to_wire,
)

MARKER = b"\x02USP"
DEFAULT_PORT = 49152
REPLY_BIT = 0x80

# Service codes and their sub-codes.
SERVICE_STATUS = 0x01
GET_IDENT = 0x01
GET_STATUS = 0x02
SERVICE_CONFIG = 0x02
SET_CONFIG = 0x01
GET_CONFIG = 0x02
SET_TIME_ABS = 0x03
SET_TIME_REL = 0x04
GET_SYNC_CLOCK = 0x05
SET_FUNCTION = 0x0A
GET_FUNCTION = 0x0B
SERVICE_MEASURE = 0x03
GET_PROFILE = 0x01
CANCEL_PROFILE = 0x02
SERVICE_WORKING = 0x04
WORKING_RESET = 0x01
WORKING_IDLE = 0x02
WORKING_ROTATE = 0x03
WORKING_MEASURE = 0x04

#: Every (service, sub-code) pair the protocol defines.
KNOWN_CODES = frozenset({
    (SERVICE_STATUS, GET_IDENT), (SERVICE_STATUS, GET_STATUS),
    *((SERVICE_CONFIG, sub) for sub in (SET_CONFIG, GET_CONFIG, SET_TIME_ABS, SET_TIME_REL,
                                         GET_SYNC_CLOCK, SET_FUNCTION, GET_FUNCTION)),
    (SERVICE_MEASURE, GET_PROFILE), (SERVICE_MEASURE, CANCEL_PROFILE),
    *((SERVICE_WORKING, sub) for sub in (WORKING_RESET, WORKING_IDLE, WORKING_ROTATE,
                                          WORKING_MEASURE)),
})

# Profile format mask bits.
PROFILESENT = 0x0001
PROFILECOUNT = 0x0002
LAYERNUM = 0x0004
SECTORNUM = 0x0008
DIRSTEP = 0x0010
POINTNUM = 0x0020
TSTART = 0x0040
STARTDIR = 0x0080
DISTANCE = 0x0100
DIRECTION = 0x0200
ECHO = 0x0400
TEND = 0x0800
ENDDIR = 0x1000
SENSTAT = 0x2000
ALL_MASK_BITS = 0x3FFF
MASK_RANGES = 0x39FF
MASK_RANGES_ECHO = 0x3DFF

# Sensor modes (low nibble of SENSTAT's 4th byte) and motor modes (high nibble).
SENSOR_IDLE = 0x1
SENSOR_ROTATE = 0x2
SENSOR_MEASURE = 0x3
SENSOR_ERROR = 0x4
MOTOR_OK = 0x0
MOTOR_SPIN_TOO_LOW = 0x4
MOTOR_SPIN_TOO_HIGH = 0x9
MOTOR_ERROR = 0xB

#: Device limits: sectors per profile and points per sector.
MAX_SECTORS = 8
MAX_SECTOR_POINTS = 2881
#: Profile-reply payloads: 2 codes + mask + sector count, at least.
MIN_PAYLOAD_BYTES = 2
#: 8 sectors of 2881 points with every field, plus headers: a generous cap.
MAX_PAYLOAD_BYTES = 1 << 18

_HEADER_FIELDS = (PROFILESENT, PROFILECOUNT, LAYERNUM)
_SECTOR_HEAD_FIELDS = (SECTORNUM, DIRSTEP, POINTNUM, TSTART, STARTDIR)
_POINT_FIELDS = (DISTANCE, DIRECTION, ECHO)
_SECTOR_TAIL_FIELDS = (TEND, ENDDIR)


def encode_frame(payload: bytes) -> bytes:
    """One USP frame around ``payload``."""
    return framing.encode_frame(MARKER, payload)


class FrameReader(framing.FrameReader):
    """The USP framing: :class:`scanpipe.protocol.framing.FrameReader` with the ``02 USP`` marker.

    By default it accepts only payloads with a known service code whose profile replies parse
    and pass :func:`check_frame`. ``confirm`` is off by default: this reader serves
    request/reply links, where a reply is often the last thing sent and must not wait for the
    next frame's marker (recordings go through ``StreamDecoder``, which confirms).
    """

    def __init__(self, max_payload_bytes: int = MAX_PAYLOAD_BYTES,
                 accept_unknown: bool = False, confirm: bool = False) -> None:
        super().__init__(MARKER, MIN_PAYLOAD_BYTES, max_payload_bytes,
                         None if accept_unknown else decode_payload,
                         None if accept_unknown else check_frame, confirm)


@dataclass(frozen=True)
class Message:
    """A parsed payload: service code (without the reply bit), sub-code, reply flag, the rest."""

    service: int
    sub: int
    is_reply: bool
    body: bytes

    @property
    def is_profile_reply(self) -> bool:
        """A GET_PROFILE reply (``83 01``), which carries profiles."""
        return self.is_reply and (self.service, self.sub) == (SERVICE_MEASURE, GET_PROFILE)

    def u16(self, index: int) -> int:
        """The ``index``-th big-endian u16 of the body; :class:`ProtocolError` when too short."""
        if len(self.body) < 2 * index + 2:
            raise ProtocolError(f"ldoem message {self.service:02x} {self.sub:02x}: body of "
                                f"{len(self.body)} bytes has no u16 #{index}")
        return int.from_bytes(self.body[2 * index:2 * index + 2], "big")


def parse_payload(payload: bytes) -> Message:
    """Service code, sub-code and body of a request or reply payload."""
    if len(payload) < 2:
        raise ProtocolError(f"ldoem payload of {len(payload)} bytes: needs service and sub-code")
    service, sub = payload[0] & ~REPLY_BIT, payload[1]
    if (service, sub) not in KNOWN_CODES:
        raise ProtocolError(f"ldoem payload: unknown service {payload[0]:#04x} / sub-code "
                            f"{sub:#04x}")
    return Message(service, sub, bool(payload[0] & REPLY_BIT), payload[2:])


def is_valid_payload(payload: bytes) -> bool:
    """A known service code, and, for a profile reply, a layout that parses exactly."""
    try:
        message = parse_payload(payload)
        if message.is_profile_reply:
            decode_profile_reply(payload)
    except ProtocolError:
        return False
    return True


def request(service: int, sub: int, body: bytes = b"") -> bytes:
    """A whole request frame."""
    return encode_frame(bytes([service, sub]) + body)


def reply(service: int, sub: int, body: bytes = b"") -> bytes:
    """A whole reply frame (the request's service code with the reply bit)."""
    return encode_frame(bytes([service | REPLY_BIT, sub]) + body)


def _u16(*values: int) -> bytes:
    return b"".join((v & 0xFFFF).to_bytes(2, "big") for v in values)


def get_ident_request() -> bytes:
    """GET_IDENT (``01 01``)."""
    return request(SERVICE_STATUS, GET_IDENT)


def get_status_request() -> bytes:
    """GET_STATUS (``01 02``)."""
    return request(SERVICE_STATUS, GET_STATUS)


def get_config_request(config_key: int) -> bytes:
    """GET_CONFIG (``02 02``) of one configuration key."""
    return request(SERVICE_CONFIG, GET_CONFIG, _u16(config_key))


def set_config_request(config_key: int, data: bytes) -> bytes:
    """SET_CONFIG (``02 01``): a configuration key and its raw value."""
    return request(SERVICE_CONFIG, SET_CONFIG, _u16(config_key) + data)


def set_time_abs_request(time_ms: int) -> bytes:
    """SET_TIME_ABS (``02 03``): set the 16-bit millisecond clock."""
    return request(SERVICE_CONFIG, SET_TIME_ABS, _u16(time_ms))


def set_time_rel_request(delta_ms: int) -> bytes:
    """SET_TIME_REL (``02 04``): shift the clock by a signed 16-bit number of milliseconds."""
    if not -0x8000 <= delta_ms <= 0x7FFF:
        raise ProtocolError(f"time shift {delta_ms} ms: allowed −32768…32767")
    return request(SERVICE_CONFIG, SET_TIME_REL, _u16(delta_ms))


def get_sync_clock_request() -> bytes:
    """GET_SYNC_CLOCK (``02 05``): read the device clock."""
    return request(SERVICE_CONFIG, GET_SYNC_CLOCK)


def working_mode_request(mode: int, body: bytes = b"") -> bytes:
    """A WORKING request: RESET, IDLE, ROTATE (body: u16 head speed in Hz) or MEASURE."""
    if (SERVICE_WORKING, mode) not in KNOWN_CODES:
        raise ProtocolError(f"working mode {mode:#04x}: allowed 0x01…0x04")
    return request(SERVICE_WORKING, mode, body)


def rotate_request(scan_hz: int) -> bytes:
    """WORKING / ROTATE (``04 03``) at ``scan_hz`` head rotations per second."""
    return working_mode_request(WORKING_ROTATE, _u16(scan_hz))


def get_profile_request(n_profiles: int, mask: int = MASK_RANGES) -> bytes:
    """GET_PROFILE (``03 01``): ``n_profiles`` (0 = stream until cancelled) with format ``mask``."""
    if not 0 <= n_profiles <= 0xFFFF:
        raise ProtocolError(f"n_profiles {n_profiles}: allowed 0…65535 (0 = continuous)")
    check_mask(mask)
    return request(SERVICE_MEASURE, GET_PROFILE, _u16(n_profiles, mask))


def cancel_profile_request() -> bytes:
    """CANCEL_PROFILE (``03 02``): stop a profile stream."""
    return request(SERVICE_MEASURE, CANCEL_PROFILE)


def parse_get_profile_request(message: Message) -> tuple[int, int]:
    """``(n_profiles, mask)`` of a GET_PROFILE request."""
    if message.is_reply or (message.service, message.sub) != (SERVICE_MEASURE, GET_PROFILE):
        raise ProtocolError("not a GET_PROFILE request")
    return message.u16(0), message.u16(1)


def status_reply(sensor_mode: int = SENSOR_MEASURE, motor_mode: int = MOTOR_OK) -> bytes:
    """A GET_STATUS reply: u16 sensor mode, u16 motor mode (scanpipe's emulator layout)."""
    return reply(SERVICE_STATUS, GET_STATUS, _u16(sensor_mode, motor_mode))


def parse_status_reply(message: Message) -> tuple[int, int]:
    """``(sensor_mode, motor_mode)`` of a GET_STATUS reply."""
    if not message.is_reply or (message.service, message.sub) != (SERVICE_STATUS, GET_STATUS):
        raise ProtocolError("not a GET_STATUS reply")
    return message.u16(0), message.u16(1)


def check_mask(mask: int) -> int:
    """``mask`` if it only selects defined fields; :class:`ProtocolError` otherwise."""
    if not 0 <= mask <= 0xFFFF or mask & ~ALL_MASK_BITS:
        raise ProtocolError(f"format mask {mask:#06x}: only bits 0x3FFF are defined")
    return mask


def encode_profile_reply(
    profiles_of_one_scan: Sequence[Profile],
    mask: int = MASK_RANGES,
    profile_count: int | None = None,
    profile_sent: int = 0,
    layer: int = 0,
    sensor_mode: int = SENSOR_MEASURE,
    motor_mode: int = MOTOR_OK,
) -> bytes:
    """One GET_PROFILE reply frame holding the sectors of one scan, in the fields ``mask`` selects.

    ``profile_count`` defaults to the first sector's ``frame``. Missing device times are sent as
    0; a missing echo as 0; NaN ranges as 0 (no return).
    """
    check_mask(mask)
    if not profiles_of_one_scan:
        raise ProtocolError("a profile reply needs at least one sector")
    count = profiles_of_one_scan[0].frame if profile_count is None else profile_count
    parts = [bytes([SERVICE_MEASURE | REPLY_BIT, GET_PROFILE]),
             _u16(mask, len(profiles_of_one_scan))]
    header = {PROFILESENT: profile_sent, PROFILECOUNT: count, LAYERNUM: layer}
    parts.append(_u16(*(header[f] for f in _HEADER_FIELDS if mask & f)))
    for p in profiles_of_one_scan:
        parts.append(_encode_sector(p, mask))
    if mask & SENSTAT:
        parts.append(bytes([0, 0, 0, ((motor_mode & 0xF) << 4) | (sensor_mode & 0xF)]))
    return encode_frame(b"".join(parts))


def _encode_sector(p: Profile, mask: int) -> bytes:
    n = len(p.ranges_m)
    if n > 0xFFFF:
        raise ProtocolError(f"sector of {n} points: at most 65535")
    start, step = angle_to_wire(p.start_angle_deg), angle_to_wire(p.step_deg)
    directions = (start + step * np.arange(n, dtype=np.int64)) % TICKS_PER_TURN
    t_start = p.device_time_ms or 0
    head = {SECTORNUM: p.sector, DIRSTEP: step, POINTNUM: n, TSTART: t_start, STARTDIR: start}
    tail = {TEND: t_start if p.device_end_time_ms is None else p.device_end_time_ms,
            ENDDIR: int(directions[-1]) if n else start}
    columns: list[NDArray[np.integer]] = []
    if mask & DISTANCE:
        columns.append(ranges_to_wire(p.ranges_m))
    if mask & DIRECTION:
        columns.append(directions)
    if mask & ECHO:
        columns.append(np.zeros(n, np.uint16) if p.echo is None else np.asarray(p.echo))
    points = (np.stack(columns, axis=1).astype(">u2").tobytes() if columns else b"")
    return (_u16(*(head[f] for f in _SECTOR_HEAD_FIELDS if mask & f)) + points
            + _u16(*(tail[f] for f in _SECTOR_TAIL_FIELDS if mask & f)))


def encode_profile(profile: Profile) -> bytes:
    """One profile as one GET_PROFILE reply frame with the default mask (0x39FF)."""
    return encode_profile_reply([profile])


@dataclass(frozen=True)
class ProfileReply:
    """A decoded GET_PROFILE reply: its header fields and sectors."""

    mask: int
    profile_sent: int | None
    profile_count: int | None
    layer: int | None
    sectors: list[Profile]
    sensor_mode: int | None
    motor_mode: int | None


_MASK_AND_COUNT = struct.Struct(">HH")


@dataclass(frozen=True)
class _Layout:
    """Which fields a mask selects, in wire order."""

    header: tuple[int, ...]
    sector_head: tuple[int, ...]
    point: tuple[int, ...]
    sector_tail: tuple[int, ...]
    header_struct: struct.Struct
    sector_head_struct: struct.Struct
    sector_tail_struct: struct.Struct


@functools.lru_cache(maxsize=64)
def _layout(mask: int) -> _Layout:
    def pick(fields: tuple[int, ...]) -> tuple[int, ...]:
        return tuple(f for f in fields if mask & f)

    header, head, tail = pick(_HEADER_FIELDS), pick(_SECTOR_HEAD_FIELDS), pick(_SECTOR_TAIL_FIELDS)
    return _Layout(header, head, pick(_POINT_FIELDS), tail, _u16_struct(len(header)),
                   _u16_struct(len(head)), _u16_struct(len(tail)))


def _u16_struct(count: int) -> struct.Struct:
    return struct.Struct(f">{count}H")


class _Cursor:
    """Reads big-endian u16 fields from a payload, with a bounds check on every read."""

    def __init__(self, payload: bytes, pos: int) -> None:
        self.payload, self.pos = payload, pos

    def need(self, n_bytes: int, what: str) -> None:
        if self.pos + n_bytes > len(self.payload):
            raise LengthMismatch(f"ldoem profile reply of {len(self.payload)} bytes ends inside "
                                f"{what} (at byte {self.pos}, needs {n_bytes})")

    def u16s(self, fields: struct.Struct, what: str) -> tuple[int, ...]:
        self.need(fields.size, what)
        values = fields.unpack_from(self.payload, self.pos)
        self.pos += fields.size
        return values

    def block(self, rows: int, cols: int, what: str) -> NDArray[np.uint16]:
        self.need(2 * rows * cols, what)
        data = np.frombuffer(self.payload, dtype=">u2", count=rows * cols, offset=self.pos)
        self.pos += 2 * rows * cols
        return data.reshape(rows, cols).astype(np.uint16)


def decode_profile_reply(payload: bytes, checksum_ok: bool = True) -> ProfileReply:
    """Parse a GET_PROFILE reply payload; :class:`ProtocolError` unless it parses exactly."""
    if len(payload) < 6 or payload[0] != SERVICE_MEASURE | REPLY_BIT or payload[1] != GET_PROFILE:
        raise ProtocolError("ldoem payload is not a GET_PROFILE reply (83 01, mask, sectors)")
    cur = _Cursor(payload, 2)
    mask, n_sectors = cur.u16s(_MASK_AND_COUNT, "mask and sector count")
    check_mask(mask)
    layout = _layout(mask)
    header = dict(zip(layout.header, cur.u16s(layout.header_struct, "profile header"),
                      strict=True))
    frame = header.get(PROFILECOUNT, header.get(PROFILESENT, 0))
    point_fields = layout.point
    tail_bytes = 2 * len(layout.sector_tail)
    senstat_bytes = 4 if mask & SENSTAT else 0
    sectors = []
    for index in range(n_sectors):
        head = dict(zip(layout.sector_head,
                        cur.u16s(layout.sector_head_struct, "sector header"), strict=True))
        if POINTNUM in head:
            n = head[POINTNUM]
        elif not point_fields:
            n = 0
        elif n_sectors == 1:  # no point count: the single sector fills the payload
            rest = len(payload) - cur.pos - tail_bytes - senstat_bytes
            if rest < 0 or rest % (2 * len(point_fields)):
                raise LengthMismatch(f"ldoem profile reply: {rest} bytes of points do not divide "
                                    f"into {len(point_fields)} fields")
            n = rest // (2 * len(point_fields))
        else:
            raise ProtocolError(f"ldoem mask {mask:#06x}: several sectors need POINTNUM")
        points = cur.block(n, len(point_fields), f"the points of sector {index}")
        column = {f: points[:, i] for i, f in enumerate(point_fields)}
        tail = dict(zip(layout.sector_tail,
                        cur.u16s(layout.sector_tail_struct, "sector trailer"), strict=True))
        sectors.append(_sector_profile(frame, index, head, column, tail, n, checksum_ok))
    sensor_mode = motor_mode = None
    if senstat_bytes:
        cur.need(4, "sensor status")
        sensor_mode, motor_mode = payload[cur.pos + 3] & 0xF, payload[cur.pos + 3] >> 4
        cur.pos += 4
    if cur.pos != len(payload):
        raise LengthMismatch(f"ldoem profile reply: {len(payload) - cur.pos} bytes left over "
                            f"after mask {mask:#06x} and {n_sectors} sectors")
    return ProfileReply(mask, header.get(PROFILESENT), header.get(PROFILECOUNT),
                        header.get(LAYERNUM), sectors, sensor_mode, motor_mode)


def _sector_profile(frame: int, index: int, head: dict[int, int],
                    column: dict[int, NDArray[np.uint16]], tail: dict[int, int], n: int,
                    checksum_ok: bool) -> Profile:
    directions = column.get(DIRECTION)
    # Angles in ticks (1/16°): from the sector fields, else from the per-point directions,
    # else from the end direction and the point count.
    step: float | None = head.get(DIRSTEP)
    start: float | None = head.get(STARTDIR)
    end = tail.get(ENDDIR)
    if step is None and directions is not None and n >= 2:
        step = (int(directions[1]) - int(directions[0])) % TICKS_PER_TURN
    if start is None and directions is not None and n >= 1:
        start = int(directions[0])
    if step is None and start is not None and end is not None and n >= 2:
        step = ((end - start) % TICKS_PER_TURN) / (n - 1)
    if start is None and step is not None and end is not None:
        start = (end - step * max(n - 1, 0)) % TICKS_PER_TURN
    nan = float("nan")
    distance = column.get(DISTANCE)
    ranges = (ranges_from_wire(distance) if distance is not None
              else np.full(n, np.nan, dtype=np.float32))
    echo = column.get(ECHO)
    return Profile(
        frame=frame,
        sector=head.get(SECTORNUM, index),
        start_angle_deg=nan if start is None else start / ANGLE_SCALE_PER_DEG,
        step_deg=nan if step is None else step / ANGLE_SCALE_PER_DEG,
        ranges_m=ranges,
        echo=None if echo is None else np.ascontiguousarray(echo),
        device_time_ms=head.get(TSTART),
        device_end_time_ms=tail.get(TEND),
        checksum_ok=checksum_ok,
    )


def decode_payload(payload: bytes, checksum_ok: bool = True) -> list[Profile] | None:
    """The profiles in a frame's payload; None for a valid frame that carries none (another
    reply or a request); :class:`ProtocolError` when it cannot be understood."""
    message = parse_payload(payload)
    if not message.is_profile_reply:
        return None
    return decode_profile_reply(payload, checksum_ok).sectors


def check_frame(profiles: list[Profile] | None) -> int | None:
    """The profile counter of a decoded reply (None for a frame without profiles);
    ``ImplausibleFrame`` for more than 8 sectors, more than 2881 points in a sector, or angles
    no 360° scanner sends (see :func:`scanpipe.protocol.profile.check_plausible`)."""
    if profiles is not None and len(profiles) > MAX_SECTORS:
        raise framing.ImplausibleFrame(f"ldoem profile reply of {len(profiles)} sectors: the "
                                       f"device sends at most {MAX_SECTORS}")
    return check_plausible(profiles, MAX_SECTOR_POINTS)
