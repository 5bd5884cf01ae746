"""The ``ldrobot`` dialect: LDRobot LD06 / LD19 / STL-27L serial packets, and revolutions.

These scanners spin and send from power-on, with no command (facts: LDRobot's LD06/LD19
development manuals and their public SDK, ``ldrobotSensorTeam/ldlidar_sdk``). Every packet is
47 bytes, little-endian::

    0x54 0x2C | speed u16 (°/s) | start angle u16 (0.01°) | 12 × (distance u16 mm, intensity u8)
              | end angle u16 (0.01°) | timestamp u16 (ms, wraps at 30 000) | CRC-8

The CRC is the vendor's table-driven CRC-8 (polynomial 0x4D, initial value 0, no reflection)
over the first 46 bytes. A sample's angle is interpolated between the packet's start and end
angles (across 360° when the end angle has wrapped); a distance of 0 is no return.

Locating packets. ``0x54 0x2C`` is a weak marker (two bytes, and 0x54 is a common distance
byte), so a candidate counts only when its CRC holds *and* its fields are plausible (angles
below 360°, a speed of 1…30 turns/s, a packet span that fits the speed at 2 300…21 600
samples/s). Candidates are located and checked for a whole buffer at once (numpy over
packets). Where two good candidates overlap, the one that the stream continues from (a good
packet exactly 47 bytes later, or the stream's end) wins, then the one that continues a good
packet (exactly 47 bytes before), then the earlier: a false packet inside real data is not
followed by a real one, a real one is. Neighbours link only if the head's motion joins them
(the later one starts where the earlier one's speed × the elapsed time puts it; speeds within
10 %). A good candidate with no linked neighbour (both damaged) is kept only if it continues the
last packet kept, or the next linked packet continues it, across at most 0.1 s. A bad
candidate is a false start: decoding resumes one byte past it;
one that lies exactly where a packet should be (47 bytes after a good one) is counted as a
checksum failure, the rest as resyncs.

Revolutions. A profile is one head turn: the samples whose unwrapped angle falls in
``[k·360°, (k+1)·360°)``. It is resampled onto a fixed grid of ``N`` beams from 0° (``N``
chosen once per stream from the first revolution's sample step, so every profile of a stream
shares one grid, as the assemble stage needs): a grid angle between two samples of the same
surface gets the linear interpolation of their ranges (second order error on a smooth
surface), across a depth jump or a no-return the nearer sample's value, in a hole left by a
lost packet NaN. The echo is the nearer sample's intensity. A revolution's device times (its
first and last grid beam) are interpolated from per-sample times: the packet timestamp is taken
as its first sample's time and the samples follow at the packet's angular step ÷ speed. They
are handed out modulo 30 000 ms (the device's wrap), and the decode stage unwraps them against
the host receive times (``Profile.device_wrap_ticks`` = 30 000;
:func:`scanpipe.clock.unwrap_device_ticks`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ProtocolError
from scanpipe.protocol.framing import FrameCounters, RawFrame
from scanpipe.protocol.profile import Profile, ranges_between

MARKER = b"\x54\x2c"
HEADER = 0x54
VER_LEN = 0x2C
PACKET_BYTES = 47
POINTS_PER_PACKET = 12
#: The device's millisecond timestamp restarts at this value.
TIME_WRAP_MS = 30_000
#: Angles on the wire are u16 in 1/100 degree.
ANGLE_SCALE_PER_DEG = 100.0
TURN_CDEG = 36_000
#: Plausible head speeds (°/s): 1…30 turns per second.
MIN_SPEED_DPS = 360
MAX_SPEED_DPS = 10_800
#: Sample rates of the family (LD14 2 300 … STL-27L 21 600 per second), with a margin: the
#: span of a packet's 11 steps divided by the speed lies between these (seconds).
MIN_PACKET_SPAN_S = 11 / 21_600 * 0.6
MAX_PACKET_SPAN_S = 11 / 2_300 * 1.4
#: Grids per revolution are bounded (36 … 16 384 beams).
MIN_GRID_BEAMS = 36
MAX_GRID_BEAMS = 16_384
#: A packet with no good neighbour must continue the last packet kept within this time (s):
#: beyond it, speed drift makes the predicted angle too loose a test.
MAX_FOLLOW_S = 0.1

_SPAN_STEPS = POINTS_PER_PACKET - 1

#: LD14 / LD14P (triangulation heads; LDRobot's SDK ``ldlidar_sl_ros2``, ``SlTransform``):
#: a sample's true angle is its packet angle less ``atan((SLOPE·d + OFFSET_Y) / (d +
#: OFFSET_X))`` (d in mm; the laser and the receiver sit beside the axis). Samples nearer than
#: the rated 0.1 m are no return: their shift would grow past −3.8° towards −73°, outside
#: what the fit is made for (the LD14's range is 0.1–8 m).
SL_SLOPE = 0.11923
SL_OFFSET_X_MM = 5.9
SL_OFFSET_Y_MM = -18.975571
SL_MIN_DISTANCE_MM = 100


def sl_angle_shift_deg(distance_mm: NDArray[np.integer] | NDArray[np.floating]
                       ) -> NDArray[np.float64]:
    """The LD14/LD14P angle correction (degrees) of samples at ``distance_mm``: the SDK's
    ``SlTransform`` shift, which the decoder subtracts from the packet's angle (positive
    beyond 159 mm: 1.36° at 0.2 m, 5.69° at 1 m, towards 6.80° far away). Exact π here; the
    SDK's 180/3.14159 differs by 1.5 ppm (1e-5° at 7°)."""
    d = np.asarray(distance_mm, np.float64)
    return np.asarray(np.degrees(np.arctan((SL_SLOPE * d + SL_OFFSET_Y_MM)
                                           / (d + SL_OFFSET_X_MM))), np.float64)


#: The range of the shift over the rated distances: a sample's true angle lies between its
#: packet angle − SL_MAX_SHIFT_DEG and its packet angle − SL_MIN_SHIFT_DEG.
SL_MAX_SHIFT_DEG = float(np.degrees(np.arctan(SL_SLOPE)))
SL_MIN_SHIFT_DEG = float(sl_angle_shift_deg(np.array(SL_MIN_DISTANCE_MM)))


def _crc_table() -> NDArray[np.uint8]:
    table = np.zeros(256, np.uint8)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x4D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table[byte] = crc
    return table


#: The vendor's CRC-8 table (polynomial 0x4D); ``CRC_TABLE[1] == 0x4D``.
CRC_TABLE = _crc_table()
_CRC_LIST = CRC_TABLE.tolist()

#: One packet as a numpy record (47 bytes, packed, little-endian).
PACKET_DTYPE = np.dtype([
    ("header", "u1"), ("ver_len", "u1"), ("speed", "<u2"), ("start", "<u2"),
    ("points", [("distance", "<u2"), ("intensity", "u1")], (POINTS_PER_PACKET,)),
    ("end", "<u2"), ("timestamp", "<u2"), ("crc", "u1"),
])
assert PACKET_DTYPE.itemsize == PACKET_BYTES


def crc8(data: bytes | bytearray | memoryview) -> int:
    """The vendor's CRC-8 of ``data`` (table-driven, initial 0)."""
    crc = 0
    table = _CRC_LIST
    for byte in bytes(data):
        crc = table[crc ^ byte]
    return crc


def crc8_rows(rows: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """The CRC-8 of every row of a 2-D uint8 array (one table look-up per column)."""
    crc = np.zeros(rows.shape[0], np.uint8)
    for column in range(rows.shape[1]):
        np.bitwise_xor(crc, rows[:, column], out=crc)
        crc = np.take(CRC_TABLE, crc)
    return crc


@dataclass(frozen=True)
class Packets:
    """Packets as arrays (one entry per packet): where each lay in the stream, its fields, and
    whether its CRC held."""

    offset: NDArray[np.int64]
    speed_dps: NDArray[np.uint16]
    start_cdeg: NDArray[np.uint16]
    end_cdeg: NDArray[np.uint16]
    timestamp_ms: NDArray[np.uint16]
    distance_mm: NDArray[np.uint16]  # (packets, 12)
    intensity: NDArray[np.uint8]  # (packets, 12)
    crc_ok: NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.offset.size)

    @staticmethod
    def empty() -> Packets:
        """No packets."""
        return Packets.from_records(np.zeros(0, PACKET_DTYPE), np.zeros(0, np.int64),
                                    np.zeros(0, bool))

    @staticmethod
    def from_records(records: NDArray[np.void], offsets: NDArray[np.int64],
                     crc_ok: NDArray[np.bool_]) -> Packets:
        """Packets from records of :data:`PACKET_DTYPE`."""
        points = records["points"]
        # Views where the byte order allows (no copy of the samples until they are used).
        return Packets(
            offset=np.asarray(offsets, np.int64),
            speed_dps=records["speed"].astype(np.uint16),
            start_cdeg=records["start"].astype(np.uint16),
            end_cdeg=records["end"].astype(np.uint16),
            timestamp_ms=records["timestamp"].astype(np.uint16),
            distance_mm=points["distance"].astype(np.uint16, copy=False).reshape(
                -1, POINTS_PER_PACKET),
            intensity=points["intensity"].astype(np.uint8, copy=False).reshape(
                -1, POINTS_PER_PACKET),
            crc_ok=np.asarray(crc_ok, bool),
        )

    def take(self, index: NDArray[np.integer] | NDArray[np.bool_]) -> Packets:
        """The packets selected by ``index``."""
        return Packets(self.offset[index], self.speed_dps[index], self.start_cdeg[index],
                       self.end_cdeg[index], self.timestamp_ms[index],
                       self.distance_mm[index], self.intensity[index], self.crc_ok[index])

    @staticmethod
    def concat(parts: Sequence[Packets]) -> Packets:
        """Packets one after the other."""
        if not parts:
            return Packets.empty()
        return Packets(*(np.concatenate([getattr(p, name) for p in parts])
                         for name in ("offset", "speed_dps", "start_cdeg", "end_cdeg",
                                      "timestamp_ms", "distance_mm", "intensity", "crc_ok")))

    def span_cdeg(self) -> NDArray[np.int64]:
        """Angle from the first to the last sample, in 0.01° (across 360°)."""
        return (self.end_cdeg.astype(np.int64) - self.start_cdeg.astype(np.int64)) % TURN_CDEG


def encode_packets(speed_dps: NDArray[np.integer], start_cdeg: NDArray[np.integer],
                   distance_mm: NDArray[np.integer], intensity: NDArray[np.integer],
                   end_cdeg: NDArray[np.integer], timestamp_ms: NDArray[np.integer]) -> bytes:
    """Packets on the wire, one per row of ``distance_mm`` / ``intensity`` (12 columns)."""
    distance = np.atleast_2d(np.asarray(distance_mm))
    n = distance.shape[0]
    if distance.shape[1:] != (POINTS_PER_PACKET,):
        raise ProtocolError(f"ldrobot packets carry {POINTS_PER_PACKET} samples each, not "
                            f"{distance.shape[1:]}")
    values = {"speed": speed_dps, "start": start_cdeg, "end": end_cdeg,
              "timestamp": timestamp_ms, "distance": distance, "intensity": intensity}
    limits = {"intensity": 0xFF}
    for name, value in values.items():
        array = np.asarray(value)
        top = limits.get(name, 0xFFFF)
        if array.size and (array.min() < 0 or array.max() > top):
            raise ProtocolError(f"ldrobot packet field {name}: values must lie in 0…{top}")
    records = np.zeros(n, PACKET_DTYPE)
    records["header"] = HEADER
    records["ver_len"] = VER_LEN
    records["speed"] = speed_dps
    records["start"] = start_cdeg
    records["points"]["distance"] = distance
    records["points"]["intensity"] = np.broadcast_to(np.asarray(intensity), distance.shape)
    records["end"] = end_cdeg
    records["timestamp"] = timestamp_ms
    rows = records.view(np.uint8).reshape(n, PACKET_BYTES)
    rows[:, -1] = crc8_rows(rows[:, :-1])
    return rows.tobytes()


def packet_plausible(packets: Packets) -> NDArray[np.bool_]:
    """Whether each packet's fields are ones the device family sends (module docstring)."""
    speed = packets.speed_dps.astype(np.float64)
    span_s = packets.span_cdeg() / ANGLE_SCALE_PER_DEG / np.maximum(speed, 1.0)
    return np.asarray(
        (packets.start_cdeg < TURN_CDEG) & (packets.end_cdeg < TURN_CDEG)
        & (packets.timestamp_ms < TIME_WRAP_MS)
        & (speed >= MIN_SPEED_DPS) & (speed <= MAX_SPEED_DPS)
        & (span_s >= MIN_PACKET_SPAN_S) & (span_s <= MAX_PACKET_SPAN_S), bool)


def _rows_at(buf: NDArray[np.uint8], starts: NDArray[np.int64]) -> NDArray[np.uint8]:
    """The 47 bytes at each start, as a (n, 47) array (contiguous runs cost one reshape)."""
    n = starts.size
    if n == 0:
        return np.zeros((0, PACKET_BYTES), np.uint8)
    if bool(np.all(np.diff(starts) == PACKET_BYTES)):
        first = int(starts[0])
        return buf[first:first + n * PACKET_BYTES].reshape(n, PACKET_BYTES)
    # Whole 47-byte rows of a sliding window: a row copy each, no per-byte index array.
    windows = np.lib.stride_tricks.sliding_window_view(buf, PACKET_BYTES)
    return np.asarray(windows[starts], np.uint8)


def _rows_to_packets(rows: NDArray[np.uint8], offsets: NDArray[np.int64],
                     crc_ok: NDArray[np.bool_]) -> Packets:
    records = np.ascontiguousarray(rows).view(PACKET_DTYPE).reshape(-1)
    return Packets.from_records(records, offsets, crc_ok)


def parse_packet(data: bytes) -> Packets:
    """One 47-byte packet (CRC checked, not enforced); :class:`ProtocolError` for another
    length or header."""
    if len(data) != PACKET_BYTES or data[:2] != MARKER:
        raise ProtocolError(f"ldrobot packet: {len(data)} bytes beginning {data[:2].hex(' ')}; "
                            f"need {PACKET_BYTES} bytes beginning 54 2c")
    rows = np.frombuffer(data, np.uint8).reshape(1, PACKET_BYTES)
    ok = crc8_rows(rows[:, :-1]) == rows[:, -1]
    return _rows_to_packets(rows, np.zeros(1, np.int64), ok)


class PacketLocator:
    """Finds packets in a byte stream fed in chunks of any size (module docstring).

    Decisions depend only on complete data: a candidate is decided once the three packets'
    worth of bytes after it are in (or at :meth:`finish`), so any split of a stream gives the
    same packets. ``lenient`` also returns damaged packets that lie where a packet should be
    (``crc_ok`` False). ``counters.frames_decoded`` counts packets kept with a good CRC.
    """

    def __init__(self, lenient: bool = False) -> None:
        self.lenient = lenient
        self.counters = FrameCounters()
        self._buffer = np.zeros(0, np.uint8)
        self._base = 0  # stream offset of _buffer[0]
        self._last_end = -1  # stream offset one past the last packet kept (good CRC)
        self._last: Packets | None = None  # the last packet kept (good CRC)

    @property
    def offset(self) -> int:
        """Stream offset of the first byte not yet decided."""
        return self._base

    def feed(self, chunk: bytes | bytearray | memoryview) -> Packets:
        """Add bytes; return the packets they let the locator decide, in stream order."""
        if len(chunk):
            self._buffer = np.concatenate([self._buffer, np.frombuffer(chunk, np.uint8)])
        return self._scan(final=False)

    def finish(self) -> Packets:
        """End of stream: decide everything left."""
        return self._scan(final=True)

    def _scan(self, final: bool) -> Packets:
        buf = self._buffer
        size = buf.size
        counters = self.counters
        # Candidates before ``limit`` are decided now; the three packets after them are in.
        limit = size if final else size - 3 * PACKET_BYTES
        if limit <= 0:
            return Packets.empty()
        marks = np.flatnonzero((buf[:-1] == HEADER) & (buf[1:] == VER_LEN)).astype(np.int64)
        complete = marks + PACKET_BYTES <= size
        # A marker too near the end for a whole packet: a false start once the stream ends.
        incomplete = int(np.count_nonzero(~complete)) if final else 0
        cand = marks[complete]
        rows = _rows_at(buf, cand)
        crc_ok = crc8_rows(rows[:, :-1]) == rows[:, -1] if cand.size else np.zeros(0, bool)
        packets = _rows_to_packets(rows, cand + self._base, crc_ok)
        plausible = packet_plausible(packets)
        kept = self._choose(cand, crc_ok & plausible, packets, size, final, marks)
        decided = cand < limit
        kept_all = kept
        kept = kept[decided[kept]]
        starts_kept = cand[kept]
        keep_mask = np.zeros(cand.size, bool)
        keep_mask[kept] = True
        # Damaged packets where a packet should be: right after a kept one, over none.
        after_kept = _member(starts_kept + PACKET_BYTES, cand)
        if self._last_end >= 0:
            after_kept |= (cand + self._base) == self._last_end
        inside, over = _overlaps(cand, cand[kept_all])
        damaged = decided & ~crc_ok & after_kept & ~inside & ~over
        counters.checksum_failures += int(np.count_nonzero(damaged))
        # Markers inside a kept packet are its data, not false starts.
        counters.resyncs += int(np.count_nonzero(decided & ~keep_mask & ~damaged & ~inside)
                                ) + incomplete
        out_index = kept
        if self.lenient:
            out_index = np.sort(np.concatenate([kept, np.flatnonzero(damaged & plausible)]))
        counters.frames_decoded += int(kept.size)
        consumed = limit
        if kept.size:
            consumed = max(consumed, int(starts_kept[-1]) + PACKET_BYTES)
            self._last_end = self._base + int(starts_kept[-1]) + PACKET_BYTES
            self._last = packets.take(kept[-1:])
        consumed = min(consumed, size)
        counters.bytes_skipped += consumed - int(kept.size) * PACKET_BYTES
        self._buffer = buf[consumed:].copy()
        self._base += consumed
        if out_index.size == cand.size:  # every candidate is a packet: the common case
            return packets
        return packets.take(out_index)

    def _choose(self, cand: NDArray[np.int64], good: NDArray[np.bool_], packets: Packets,
                size: int, final: bool, marks: NDArray[np.int64]) -> NDArray[np.int64]:
        """Indices (into ``cand``) of the good candidates kept, in order."""
        index = np.flatnonzero(good)
        starts = cand[index]
        if starts.size == 0:
            return index
        picked = _Motion.of(packets, index)
        # A neighbour a packet away links a packet only if the head's motion joins them.
        nxt = np.minimum(np.searchsorted(starts, starts + PACKET_BYTES), starts.size - 1)
        succ = (starts[nxt] == starts + PACKET_BYTES) & _continuous(picked, np.arange(
            starts.size), nxt)
        if final:
            succ |= starts + PACKET_BYTES == size
        prv = np.maximum(np.searchsorted(starts, starts - PACKET_BYTES), 0)
        pred = (starts[prv] == starts - PACKET_BYTES) & _continuous(picked, prv, np.arange(
            starts.size))
        if self._last_end >= 0 and self._last is not None:
            after_last = starts + self._base == self._last_end
            if after_last.any():
                last = _Motion.of(self._last, np.zeros(1, np.int64))
                both = last.then(picked.take(after_last))
                pred[after_last] = _continuous(both, np.zeros(1, np.int64),
                                               np.arange(1, both.start_cdeg.size))
        gaps = np.diff(starts)
        conflict = np.zeros(starts.size, bool)
        conflict[1:] |= gaps < PACKET_BYTES
        conflict[:-1] |= gaps < PACKET_BYTES
        isolated = ~succ & ~pred
        # Before any packet was kept, a marker (even of a damaged packet) exactly a packet
        # away vouches for an isolated one; later, its angle must follow from the last kept.
        marked = _member(marks, starts + PACKET_BYTES) | _member(marks, starts - PACKET_BYTES)
        # The rare cases (overlaps, isolated packets) in Python; the rest is kept as is.
        if not (conflict.any() or isolated.any()):
            return index
        keep = ~conflict & ~isolated
        last_kept: int | None = None
        last_end = self._last_end - self._base
        for k in range(starts.size):
            if keep[k]:
                last_kept, last_end = k, int(starts[k]) + PACKET_BYTES
                continue
            if int(starts[k]) < last_end:
                # Overlaps the packet kept last: take it instead only if it is better linked.
                if last_kept is not None and _rank(succ, pred, k) > _rank(succ, pred, last_kept):
                    keep[last_kept] = False
                    keep[k] = True
                    last_kept, last_end = k, int(starts[k]) + PACKET_BYTES
                continue
            later = _next_kept_overlapping(starts, keep, k)
            if later is not None and _rank(succ, pred, later) >= _rank(succ, pred, k):
                continue
            first_ever = bool(marked[k]) and last_kept is None and self._last is None
            if (isolated[k] and not first_ever
                    and not self._follows(packets, index[k], last_kept, index)
                    and not _leads_to(packets, index, keep, k)):
                continue
            keep[k] = True
            if later is not None:
                keep[later] = False
            last_kept, last_end = k, int(starts[k]) + PACKET_BYTES
        return np.asarray(index[keep], np.int64)

    def _follows(self, packets: Packets, at: int, last_kept: int | None,
                 index: NDArray[np.int64]) -> bool:
        """Whether packet ``at`` continues the last packet kept: the same head motion
        (:func:`_continuous`) across at most :data:`MAX_FOLLOW_S` of lost packets."""
        if last_kept is not None:
            previous = _Motion.of(packets, index[last_kept:last_kept + 1])
        elif self._last is not None:
            previous = _Motion.of(self._last, np.zeros(1, np.int64))
        else:
            return False
        both = previous.then(_Motion.of(packets, np.array([at])))
        return bool(_continuous(both, np.zeros(1, np.int64), np.ones(1, np.int64),
                                MAX_FOLLOW_S)[0])


@dataclass(frozen=True)
class _Motion:
    """The fields of packets that tell the head's motion (speed, start angle, timestamp)."""

    speed_dps: NDArray[np.uint16]
    start_cdeg: NDArray[np.uint16]
    timestamp_ms: NDArray[np.uint16]

    @staticmethod
    def of(packets: Packets, index: NDArray[np.int64]) -> _Motion:
        return _Motion(packets.speed_dps[index], packets.start_cdeg[index],
                       packets.timestamp_ms[index])

    def take(self, index: NDArray[np.bool_] | NDArray[np.int64]) -> _Motion:
        return _Motion(self.speed_dps[index], self.start_cdeg[index], self.timestamp_ms[index])

    def then(self, other: _Motion) -> _Motion:
        return _Motion(*(np.concatenate([getattr(self, f), getattr(other, f)])
                         for f in ("speed_dps", "start_cdeg", "timestamp_ms")))


def _continuous(packets: _Motion, a: NDArray[np.int64], b: NDArray[np.int64],
                max_gap_s: float = 0.05) -> NDArray[np.bool_]:
    """Whether packet ``b`` starts where the head reached ``Δt`` after packet ``a`` started
    (``Δt`` from the timestamps: 1 ms resolution, hence the speed × 1.5 ms margin)."""
    speed = packets.speed_dps[a].astype(np.float64)
    d_angle = ((packets.start_cdeg[b].astype(np.int64) - packets.start_cdeg[a].astype(np.int64))
               % TURN_CDEG) / ANGLE_SCALE_PER_DEG
    d_time_s = ((packets.timestamp_ms[b].astype(np.int64) - packets.timestamp_ms[a].astype(
        np.int64)) % TIME_WRAP_MS) / 1000.0
    miss = np.abs((d_angle - speed * d_time_s + 180.0) % 360.0 - 180.0)
    same_speed = np.abs(packets.speed_dps[b].astype(np.float64) - speed) <= 0.1 * speed
    return np.asarray((miss <= 2.0 + speed * 0.0015) & same_speed & (d_time_s <= max_gap_s),
                      bool)


def _member(sorted_values: NDArray[np.int64], queries: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Whether each query is in ``sorted_values`` (ascending): ``np.isin`` by binary search."""
    if sorted_values.size == 0:
        return np.zeros(queries.shape, bool)
    at = np.minimum(np.searchsorted(sorted_values, queries), sorted_values.size - 1)
    return np.asarray(sorted_values[at] == queries, bool)


def _leads_to(packets: Packets, index: NDArray[np.int64], keep: NDArray[np.bool_],
              k: int) -> bool:
    """Whether the next linked packet after candidate ``k`` continues it (the same head
    motion within :data:`MAX_FOLLOW_S`): an isolated packet at the start of a run."""
    later = np.flatnonzero(keep[k + 1:])
    if later.size == 0:
        return False
    pair = _Motion.of(packets, index[np.array([k, k + 1 + int(later[0])])])
    return bool(_continuous(pair, np.zeros(1, np.int64), np.ones(1, np.int64),
                            MAX_FOLLOW_S)[0])


def _rank(succ: NDArray[np.bool_], pred: NDArray[np.bool_], k: int) -> int:
    return 2 * int(succ[k]) + int(pred[k])


def _next_kept_overlapping(starts: NDArray[np.int64], keep: NDArray[np.bool_],
                           k: int) -> int | None:
    """The first kept candidate after ``k`` that overlaps it."""
    j = k + 1
    while j < starts.size and starts[j] < starts[k] + PACKET_BYTES:
        if keep[j]:
            return j
        j += 1
    return None


def _overlaps(cand: NDArray[np.int64], kept_starts: NDArray[np.int64]
              ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Whether each candidate begins inside a kept packet, and whether it runs over the start
    of the next kept packet (a kept packet itself is neither)."""
    if kept_starts.size == 0 or cand.size == 0:
        return np.zeros(cand.size, bool), np.zeros(cand.size, bool)
    at = np.searchsorted(kept_starts, cand, side="right") - 1
    before = kept_starts[np.maximum(at, 0)]
    inside = (at >= 0) & (cand > before) & (cand < before + PACKET_BYTES)
    nxt = np.minimum(at + 1, kept_starts.size - 1)
    over_next = (kept_starts[nxt] > cand) & (kept_starts[nxt] < cand + PACKET_BYTES)
    return np.asarray(inside, bool), np.asarray(over_next & ~inside, bool)


def locate_packets(data: bytes | bytearray | memoryview,
                   lenient: bool = False) -> tuple[Packets, FrameCounters]:
    """All packets of a whole byte stream and the locator's counters."""
    locator = PacketLocator(lenient)
    parts = [locator.feed(data), locator.finish()]
    return Packets.concat(parts), locator.counters


# -- revolutions ---------------------------------------------------------------------------

_PENDING_FIELDS = ("start_deg", "step_deg", "time_ms", "deg_per_ms", "end_offset", "ok",
                   "range_m", "intensity", "shift_deg")

#: Millimetres to metres, 0 → NaN (no return), one gather per packet set.
_MM_TABLE = np.arange(1 << 16, dtype=np.float32) / np.float32(1000.0)
_MM_TABLE[0] = np.nan
_POINT_INDEX32 = np.arange(POINTS_PER_PACKET, dtype=np.float32)
_POINT_INDEX64 = np.arange(POINTS_PER_PACKET, dtype=np.float64)


@dataclass(frozen=True)
class _Pending:
    """Packets waiting to be placed in a revolution (stream order, unwrapped angles):
    per packet its first sample's angle and device time, the sample step, the head speed,
    where the packet ended in the stream, its CRC verdict, and its 12 ranges and intensities."""

    start_deg: NDArray[np.float64]
    step_deg: NDArray[np.float64]
    time_ms: NDArray[np.float64]
    deg_per_ms: NDArray[np.float64]
    end_offset: NDArray[np.int64]
    ok: NDArray[np.bool_]
    range_m: NDArray[np.float32]  # (packets, 12)
    intensity: NDArray[np.uint8]  # (packets, 12)
    # (packets, 12): each sample's angle correction (subtracted), LD14/LD14P; (packets, 0)
    # for the heads that need none, so their decoding pays nothing for it.
    shift_deg: NDArray[np.float32]

    @staticmethod
    def empty(corrected: bool = False) -> _Pending:
        none = np.zeros(0)
        return _Pending(none, none, none, none, np.zeros(0, np.int64), np.zeros(0, bool),
                        np.zeros((0, POINTS_PER_PACKET), np.float32),
                        np.zeros((0, POINTS_PER_PACKET), np.uint8),
                        np.zeros((0, POINTS_PER_PACKET if corrected else 0), np.float32))

    @property
    def corrected(self) -> bool:
        """Whether the samples' angles carry a per-sample correction."""
        return bool(self.shift_deg.shape[1])

    def angle_bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per packet, the lowest and highest angle of its samples (corrected)."""
        span = _SPAN_STEPS * self.step_deg
        if not self.corrected:
            return self.start_deg, self.start_deg + span
        angles = (self.start_deg[:, None] + self.step_deg[:, None] * _POINT_INDEX64
                  - self.shift_deg)
        return angles.min(axis=1), angles.max(axis=1)

    def __len__(self) -> int:
        return int(self.start_deg.size)

    def append(self, other: _Pending) -> _Pending:
        if not len(self):
            return other
        return _Pending(*(np.concatenate([getattr(self, f), getattr(other, f)])
                          for f in _PENDING_FIELDS))

    def tail(self, first: int) -> _Pending:
        return _Pending(*(getattr(self, f)[first:] for f in _PENDING_FIELDS))

    def sample_angles(self, base_deg: float) -> tuple[NDArray[np.float32],
                                                      NDArray[np.int64] | None]:
        """Every sample's unwrapped angle less ``base_deg``, in angle order, and the order
        (flat sample indices) when it is not the stream's: where packets overlap (jitter puts
        a packet's first sample before the previous one's last, or a packet repeats samples)."""
        start = (self.start_deg - base_deg).astype(np.float32)
        step = self.step_deg.astype(np.float32)
        if self.corrected:  # the correction reorders samples wherever the distance changes
            angles = (start[:, None] + step[:, None] * _POINT_INDEX32
                      - self.shift_deg).reshape(-1)
            unordered = bool(np.any(angles[1:] < angles[:-1]))
        else:
            angles = (start[:, None] + step[:, None] * _POINT_INDEX32).reshape(-1)
            last = start + step * np.float32(_SPAN_STEPS)
            unordered = bool(np.any(start[1:] < last[:-1]))
        if unordered:
            order = np.argsort(angles, kind="stable").astype(np.int64)
            return angles[order], order
        return angles, None

    def sample_times(self, index: NDArray[np.int64]) -> NDArray[np.float64]:
        """Device times (unwrapped ms) of the samples at flat ``index``."""
        packet, within = np.divmod(index, POINTS_PER_PACKET)
        return np.asarray(self.time_ms[packet] + within * self.step_deg[packet]
                          / self.deg_per_ms[packet], np.float64)


@dataclass(frozen=True)
class Revolution:
    """One head turn on the grid, and where its packets lay in the stream (the end: that of
    the packet that completed it)."""

    profile: Profile
    end_offset: int
    start_offset: int


class RevolutionAssembler:
    """Packets in (stream order), revolutions out (module docstring). Fixes the grid of ``N``
    beams at the first revolution, unless ``grid_beams`` is given. ``sl_correction``: the
    LD14/LD14P's distance-dependent angle correction (:func:`sl_angle_shift_deg`) is applied
    to every sample before the turn is resampled."""

    def __init__(self, grid_beams: int | None = None, sl_correction: bool = False) -> None:
        if grid_beams is not None and not MIN_GRID_BEAMS <= grid_beams <= MAX_GRID_BEAMS:
            raise ProtocolError(f"grid of {grid_beams} beams: allowed "
                                f"{MIN_GRID_BEAMS}…{MAX_GRID_BEAMS}")
        self.grid_beams = grid_beams
        self.sl_correction = sl_correction
        self._last_shift = 0.0  # the shift of the last sample with a return (SDK: carried)
        self._pending = _Pending.empty(sl_correction)
        self._next_rev = 0
        self._unwrap_deg: float | None = None  # unwrapped start angle of the last packet
        self._last_start_cdeg = 0
        self._last_time_ms: float = 0.0  # unwrapped device ms of the last packet
        self._last_stamp = 0
        self._steps: list[float] = []  # sample steps seen before the grid was fixed
        self._spans: list[float] = []  # the same from single packets (fallback)

    def feed(self, packets: Packets) -> list[Revolution]:
        """Add packets; return every revolution they complete."""
        if len(packets):
            self._pending = self._pending.append(self._unwrap(packets))
        return self._emit(final=False)

    def finish(self) -> list[Revolution]:
        """End of stream: the revolution in progress, if any."""
        return self._emit(final=True)

    def _unwrap(self, packets: Packets) -> _Pending:
        start = packets.start_cdeg.astype(np.int64)
        stamp = packets.timestamp_ms.astype(np.int64)
        speed = np.maximum(packets.speed_dps.astype(np.float64), 1.0)
        prev_start = np.concatenate([[self._last_start_cdeg], start[:-1]])
        prev_stamp = np.concatenate([[self._last_stamp], stamp[:-1]])
        d_angle = ((start - prev_start) % TURN_CDEG) / ANGLE_SCALE_PER_DEG
        d_time = ((stamp - prev_stamp) % TIME_WRAP_MS).astype(np.float64)
        # Whole turns the head made beyond the angle step (a gap in the stream).
        turns = np.maximum(np.rint((speed * d_time / 1000.0 - d_angle) / 360.0), 0.0)
        step = d_angle + 360.0 * turns
        if self._unwrap_deg is None:
            step[0] = start[0] / ANGLE_SCALE_PER_DEG
            d_time[0] = float(stamp[0])
            base_deg, base_ms = 0.0, 0.0
        else:
            base_deg, base_ms = self._unwrap_deg, self._last_time_ms
        unwrapped = base_deg + np.cumsum(step)
        times = base_ms + np.cumsum(d_time)
        self._unwrap_deg = float(unwrapped[-1])
        self._last_time_ms = float(times[-1])
        self._last_start_cdeg = int(start[-1])
        self._last_stamp = int(stamp[-1])
        sample_step = packets.span_cdeg() / ANGLE_SCALE_PER_DEG / _SPAN_STEPS
        if self.grid_beams is None and len(self._steps) < 4096:
            # Back-to-back packets: their start angles 12 steps apart measure the step to
            # 1/1200°, ten times finer than one packet's span does.
            adjacent = np.diff(packets.offset) == PACKET_BYTES
            pair_step = np.diff(unwrapped) / POINTS_PER_PACKET
            fits = adjacent & (np.abs(pair_step - sample_step[:-1]) < 0.2 * sample_step[:-1])
            self._steps.extend(pair_step[fits].tolist())
            self._spans.extend(sample_step[:64].tolist())
        range_m = _MM_TABLE[packets.distance_mm]
        shift = np.zeros((len(packets), 0), np.float32)
        if self.sl_correction:
            range_m, shift = self._sl_shift(packets.distance_mm, range_m)
        return _Pending(
            start_deg=unwrapped, step_deg=sample_step, time_ms=times,
            deg_per_ms=speed / 1000.0, end_offset=packets.offset + PACKET_BYTES,
            ok=packets.crc_ok.copy(), range_m=range_m,
            intensity=packets.intensity, shift_deg=shift)

    def _sl_shift(self, distance_mm: NDArray[np.uint16], range_m: NDArray[np.float32]
                  ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """The LD14 samples' ranges (nearer than 0.1 m: no return) and angle corrections. A
        no-return sample takes the shift of the last sample with a return before it (as the
        SDK does), so it stays in its place among its neighbours."""
        valid = distance_mm >= SL_MIN_DISTANCE_MM
        range_m = np.where(valid, range_m, np.float32(np.nan)).astype(np.float32)
        flat_valid = valid.reshape(-1)
        shift = sl_angle_shift_deg(distance_mm.reshape(-1))
        last = np.maximum.accumulate(np.where(flat_valid, np.arange(flat_valid.size), -1))
        filled = np.where(last >= 0, shift[np.maximum(last, 0)], self._last_shift)
        if filled.size:
            self._last_shift = float(filled[-1])
        return range_m, filled.astype(np.float32).reshape(distance_mm.shape)

    def _grid(self) -> int:
        if self.grid_beams is None:
            steps = np.asarray(self._steps or self._spans, np.float64)
            steps = steps[steps > 0]
            if steps.size == 0:
                raise ProtocolError("ldrobot: no packet with a positive angular span; cannot "
                                    "choose the revolution grid")
            beams = round(360.0 / float(np.median(steps)))
            self.grid_beams = int(np.clip(beams, MIN_GRID_BEAMS, MAX_GRID_BEAMS))
        return self.grid_beams

    def _emit(self, final: bool) -> list[Revolution]:
        pending = self._pending
        if not len(pending):
            return []
        last_angle = float(pending.start_deg[-1] + _SPAN_STEPS * pending.step_deg[-1])
        # A turn is complete once the newest sample is within half a sample step of its end:
        # the next sample belongs to the next turn (and, at the end, the last turn is done).
        # A turn is resampled from its own samples (and the one before it) only, so when it is
        # handed out does not change it. With the LD14 correction a later sample may still
        # land up to SL_MAX_SHIFT_DEG below its packet angle.
        reach = last_angle + 0.5 * float(pending.step_deg[-1]) - (
            SL_MAX_SHIFT_DEG if pending.corrected and not final else 0.0)
        last_complete = int(np.floor(reach / 360.0)) - (0 if final else 1)
        if last_complete < self._next_rev:
            return []
        beams = self._grid()
        half_deg = 180.0 / beams
        # At the end of the stream, a turn cut short ends at its last beam measured.
        cut_short = final and last_angle + 3 * half_deg < (last_complete + 1) * 360.0
        low_deg, high_deg = pending.angle_bounds()
        first_rev = np.floor(low_deg / 360.0).astype(np.int64)
        last_rev = np.floor(high_deg / 360.0).astype(np.int64)
        if pending.corrected:  # corrected samples may reorder packets across a turn's end
            first_rev = np.minimum.accumulate(first_rev[::-1])[::-1]
            last_rev = np.maximum.accumulate(last_rev)
        # A revolution is its grid's beams: it is present when a sample lies within half a
        # grid step of one of them (a turn skipped whole leaves at most a sample just below
        # the next turn's 0°, which is that turn's: no revolution of holes is handed out).
        # With the LD14 correction, the packet's (encoder) angles: the next turn's first
        # samples land up to 6.8° below its 0°, in the skipped turn, and made it present.
        enc_low, enc_high = pending.start_deg, pending.start_deg + _SPAN_STEPS * pending.step_deg
        present = np.concatenate([np.floor((enc_low + half_deg) / 360.0),
                                  np.floor((enc_high + half_deg) / 360.0)
                                  ]).astype(np.int64)
        present = present[(present >= self._next_rev) & (present <= last_complete)]
        revs = np.unique(present)
        out = _resample(pending, revs, beams, first_rev, last_rev,
                        cut_short and revs.size > 0 and int(revs[-1]) == last_complete)
        # Keep the packets of later revolutions and the one before them (interpolation).
        first_kept = max(int(np.searchsorted(last_rev, last_complete + 1)) - 1, 0)
        self._pending = (pending.tail(first_kept) if not final
                         else _Pending.empty(pending.corrected))
        self._next_rev = last_complete + 1
        return out


def _resample(p: _Pending, revs: NDArray[np.int64], beams: int,
              first_rev: NDArray[np.int64], last_rev: NDArray[np.int64],
              cut_last: bool = False) -> list[Revolution]:
    """The revolutions ``revs`` on a grid of ``beams`` from 0° (module docstring), from the
    pending packets. ``cut_last``: the last one was cut short by the end of the stream and
    ends at its last beam within half a grid step of a sample (its end time is then that
    beam's, measured, not a guess past its last sample ahead of when it was received)."""
    if revs.size == 0:
        return []
    step = 360.0 / beams
    base = float(revs[0]) * 360.0
    # Angles relative to the first revolution: float32 keeps 1e-4° over a few turns, and halves
    # the memory traffic of the per-beam arithmetic below.
    local, order = p.sample_angles(base)
    within = np.arange(beams, dtype=np.float64) * step
    grid = ((revs - revs[0])[:, None] * 360.0 + within).astype(np.float32).ravel()
    last_index = local.size - 1
    # Each turn's beams look no further than the turn's own last sample.
    turn_end = np.searchsorted(local, ((revs - revs[0] + 1) * 360.0).astype(np.float32),
                               side="left") - 1
    cap = np.repeat(np.clip(turn_end, 0, last_index), beams)
    right = np.minimum(_first_at_or_after(local, grid, revs, beams, step), cap)
    left = np.maximum(right - 1, 0)
    a0 = local[left]
    gap = np.maximum(local[right] - a0, np.float32(1e-6))
    w = (grid - a0) / gap  # 0…1 between the samples
    nearer = left + (w > np.float32(0.5))
    flat_range = p.range_m.reshape(-1)
    flat_intensity = p.intensity.reshape(-1)
    if order is not None:  # samples in angle order, not stream order
        flat_range, flat_intensity = flat_range[order], flat_intensity[order]
    ranges = ranges_between(flat_range[left], flat_range[right], w)
    # A beam farther than half a grid step from every sample was not measured: in a hole
    # (a lost packet) or beyond the first or last sample.
    half = 0.5 * step
    hole = np.flatnonzero(gap > np.float32(2.0 * step))
    if hole.size:
        w_hole, gap_hole = w[hole], gap[hole]
        near_d = np.minimum(w_hole, 1 - w_hole) * gap_hole
        ranges[hole[near_d > half]] = np.nan
    before = int(np.searchsorted(grid, local[0], side="left"))  # beams before the first sample
    ranges[:before] = flat_range[0]
    ranges[:int(np.searchsorted(grid, local[0] - half, side="left"))] = np.nan
    beyond = np.flatnonzero(grid > local[right])  # past the last sample of their turn
    if beyond.size:
        last = right[beyond]
        far = grid[beyond] - local[last] > np.float32(half)
        ranges[beyond] = np.where(far, np.float32(np.nan), flat_range[last])
        nearer[beyond] = last
    echo = flat_intensity[nearer].astype(np.uint16)
    ranges = ranges.reshape(revs.size, beams)
    echo = echo.reshape(revs.size, beams)
    # Device times of each revolution's first and last beam: interpolated between the samples,
    # extrapolated at the head's speed beyond them.
    first_beam = np.arange(revs.size) * beams
    length = np.full(revs.size, beams, np.int64)
    if cut_last:
        last_sample = float(local[-1]) - float(revs[-1] - revs[0]) * 360.0
        length[-1] = int(np.clip(np.floor((last_sample + half) / step) + 1, 1, beams))
    ends = np.stack([first_beam, first_beam + length - 1])
    stream_index = (lambda i: i) if order is None else (lambda i: order[i])
    times = _beam_times(p, local, grid[ends].astype(np.float64), left[ends], right[ends],
                        nearer[ends], stream_index)
    # A revolution is damaged if any of its packets is.
    span = int(revs[-1] - revs[0]) + 1
    bad = np.zeros(span, np.int64)
    for which in (first_rev, last_rev):
        sel = (which >= revs[0]) & (which <= revs[-1]) & ~p.ok
        bad += np.bincount(which[sel] - revs[0], minlength=span)
    # Stream offsets: a revolution's first packet, and the end of the first packet that
    # reaches its last beam (within half a grid step). The revolution's receive time is that
    # packet's, and the device clock is fitted to it against the last beam's time, taking the
    # smallest latency as zero: the packet after it would make every latency a packet late (a
    # turn late from a device that sends a turn at once), an earlier one (a turn whose tail
    # was lost) would make one negative and shift every time.
    first_packet = np.searchsorted(last_rev, revs, side="left")
    reached = np.floor((p.start_deg + _SPAN_STEPS * p.step_deg + 1.5 * step) / 360.0
                       ).astype(np.int64)
    end_packet = np.searchsorted(np.maximum.accumulate(reached), revs + 1, side="left")
    start_offsets = p.end_offset[np.minimum(first_packet, len(p) - 1)] - PACKET_BYTES
    end_offsets = p.end_offset[np.minimum(end_packet, len(p) - 1)]
    out = []
    for row, rev in enumerate(revs.tolist()):
        profile = Profile(
            frame=rev & 0xFFFF, sector=0, start_angle_deg=0.0, step_deg=step,
            ranges_m=ranges[row, :length[row]], echo=echo[row, :length[row]],
            device_time_ms=int(np.rint(times[0, row])) % TIME_WRAP_MS,
            device_end_time_ms=int(np.rint(times[1, row])) % TIME_WRAP_MS,
            checksum_ok=bool(bad[rev - revs[0]] == 0), device_wrap_ticks=TIME_WRAP_MS)
        out.append(Revolution(profile, int(end_offsets[row]), int(start_offsets[row])))
    return out


def _consecutive(revs: NDArray[np.int64]) -> bool:
    return int(revs[-1] - revs[0]) + 1 == revs.size


def _first_at_or_after(a: NDArray[np.float32], grid: NDArray[np.float32],
                       revs: NDArray[np.int64], beams: int, step: float) -> NDArray[np.int64]:
    """For each grid angle, the index of the first sample at or after it (``a.size`` if none):
    ``np.searchsorted(a, grid)``, but by counting samples per grid cell (one pass, no binary
    search) when the revolutions are consecutive, as they are but for gaps in the stream."""
    if not _consecutive(revs):
        return np.asarray(np.searchsorted(a, grid, side="left"), np.int64)
    cells = revs.size * beams
    step32 = np.float32(step)
    # One plus the cell of each sample (the grid beam at or below it): 0 before the grid,
    # ``cells + 1`` after it.
    cell = (np.maximum(a, -step32) / step32 + np.float32(1)).astype(np.int64)
    np.minimum(cell, cells + 1, out=cell)
    below = np.cumsum(np.bincount(cell, minlength=cells + 2))
    return np.asarray(below[:cells], np.int64)


def _beam_times(p: _Pending, a: NDArray[np.float32], grid: NDArray[np.float64],
                left: NDArray[np.int64], right: NDArray[np.int64], nearer: NDArray[np.int64],
                stream_index: Callable[[NDArray[np.int64]], NDArray[np.int64]]
                ) -> NDArray[np.float64]:
    """Device times (ms) at grid angles (relative, like ``a``), from the samples around them
    (indices into ``a``; ``stream_index`` turns them into the stream's sample indices)."""
    a0, a1 = a[left].astype(np.float64), a[right].astype(np.float64)
    between = (a0 <= grid) & (grid <= a1) & (a1 > a0)
    w = np.divide(grid - a0, a1 - a0, out=np.zeros_like(grid), where=a1 > a0)
    t0, t1 = p.sample_times(stream_index(left)), p.sample_times(stream_index(right))
    near = stream_index(nearer)
    packet = near // POINTS_PER_PACKET
    extrapolated = (p.sample_times(near) + (grid - a[nearer].astype(np.float64))
                    / p.deg_per_ms[packet])
    return np.asarray(np.where(between, t0 + w * (t1 - t0), extrapolated), np.float64)


class RevolutionDecoder:
    """Bytes in (chunks of any size), revolutions out: :class:`PacketLocator` then
    :class:`RevolutionAssembler`. ``lenient`` keeps damaged packets where a packet should be
    (their revolution gets ``checksum_ok`` False); ``sl_correction``: an LD14/LD14P
    (:class:`RevolutionAssembler`)."""

    def __init__(self, lenient: bool = False, grid_beams: int | None = None,
                 sl_correction: bool = False) -> None:
        self.locator = PacketLocator(lenient)
        self.assembler = RevolutionAssembler(grid_beams, sl_correction)

    @property
    def counters(self) -> FrameCounters:
        """The locator's counters (a frame is a packet)."""
        return self.locator.counters

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[Revolution]:
        """Add bytes; return the revolutions they complete."""
        return self.assembler.feed(self.locator.feed(chunk))

    def finish(self) -> list[Revolution]:
        """End of stream: the rest."""
        return self.assembler.feed(self.locator.finish()) + self.assembler.finish()


def decode_revolutions(data: bytes | bytearray | memoryview, lenient: bool = False,
                       grid_beams: int | None = None, sl_correction: bool = False
                       ) -> tuple[list[Profile], FrameCounters]:
    """Every revolution of a whole byte stream, and the counters (``sl_correction``: an
    LD14/LD14P's stream)."""
    decoder = RevolutionDecoder(lenient, grid_beams, sl_correction)
    revolutions = decoder.feed(data) + decoder.finish()
    return [r.profile for r in revolutions], decoder.counters


def encode_profile(profile: Profile, speed_dps: int = 3600) -> bytes:
    """A profile as packets: its samples at ``start + i·step`` in packets of 12 (the last one
    repeating samples when 12 does not divide them); times from ``device_time_ms`` at the head
    speed ``speed_dps``."""
    if not MIN_SPEED_DPS <= speed_dps <= MAX_SPEED_DPS:
        raise ProtocolError(f"head speed {speed_dps} °/s: allowed "
                            f"{MIN_SPEED_DPS}…{MAX_SPEED_DPS}")
    ranges = np.asarray(profile.ranges_m, np.float64)
    n = ranges.size
    if n == 0:
        raise ProtocolError("ldrobot: a profile without samples has no packet")
    packets = -(-n // POINTS_PER_PACKET)
    total = max(n, POINTS_PER_PACKET)
    mm = np.zeros(total, np.int64)
    finite = np.isfinite(ranges) & (ranges > 0)
    mm[:n][finite] = np.clip(np.rint(ranges[finite] * 1000.0), 1, 0xFFFF)
    echo = np.zeros(total, np.int64)
    if profile.echo is not None:
        echo[:n] = np.clip(np.asarray(profile.echo, np.int64), 0, 0xFF)
    angle = profile.start_angle_deg + np.arange(total) * profile.step_deg
    cdeg = np.rint(angle * ANGLE_SCALE_PER_DEG).astype(np.int64) % TURN_CDEG
    # Whole packets of 12; when 12 does not divide the samples, the last packet repeats some
    # (it ends on the last sample) rather than spilling past the profile's end.
    rows = np.minimum(np.arange(packets) * POINTS_PER_PACKET, total - POINTS_PER_PACKET)
    t0 = profile.device_time_ms or 0
    stamp = np.rint(t0 + (angle[rows] - angle[0]) / (speed_dps / 1000.0)).astype(np.int64)
    take = rows[:, None] + np.arange(POINTS_PER_PACKET)
    return encode_packets(np.full(packets, speed_dps), cdeg[rows], mm[take], echo[take],
                          cdeg[rows + POINTS_PER_PACKET - 1], stamp % TIME_WRAP_MS)


def sl_packet_angles_deg(packet_deg: NDArray[np.float64],
                        range_at: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                        iterations: int = 4) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The inverse of the LD14 correction, for encoders and emulators: an LD14 reports a
    sample at packet angle ``a`` whose beam truly points at ``a − shift(d)``, ``d`` the range
    along that beam. For the packet angles ``packet_deg`` (what the packets will carry) and
    ``range_at(beam angles) → ranges (m, NaN = none)``: the beams' true angles and their
    ranges, by fixed-point iteration. It converges on a surface; at a depth edge a packet
    angle may have no consistent beam (the shift of the range found there points elsewhere):
    such a sample is no return (NaN), like a triangulation head's shadowed spot, rather than
    a range at a wrong angle."""
    packet = np.asarray(packet_deg, np.float64)

    def shift_of(ranges: NDArray[np.float64]) -> NDArray[np.float64]:
        mm = np.nan_to_num(np.asarray(ranges, np.float64) * 1000.0, nan=0.0)
        return np.asarray(np.where(mm >= SL_MIN_DISTANCE_MM, sl_angle_shift_deg(mm), 0.0),
                          np.float64)

    beam = packet.copy()
    shift = shift_of(np.asarray(range_at(beam), np.float64))
    used = shift
    ranges = np.full(packet.shape, np.nan)
    for _ in range(iterations):
        beam = packet - shift
        ranges = np.asarray(range_at(beam), np.float64)
        shift, used = shift_of(ranges), shift
    return beam, np.where(np.abs(shift - used) <= 0.01, ranges, np.nan)


def encode_profile_sl(profile: Profile, speed_dps: int = 3600) -> bytes:
    """A profile (true angles) as an LD14/LD14P sends it: each packet sample at angle ``a``
    holds the profile's range at ``a − shift``, interpolated linearly around the turn
    (:func:`sl_packet_angles_deg`); decoding with the correction gives the profile back."""
    ranges = np.asarray(profile.ranges_m, np.float64)
    n = ranges.size
    if n == 0:
        raise ProtocolError("ldrobot: a profile without samples has no packet")
    angles = np.asarray(profile.start_angle_deg + np.arange(n) * profile.step_deg, np.float64)

    def range_at(beam_deg: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(np.interp(beam_deg, angles, ranges, period=360.0), np.float64)

    _, sent = sl_packet_angles_deg(angles, range_at)
    sent[~np.isfinite(ranges)] = np.nan
    return encode_profile(replace(profile, ranges_m=sent.astype(np.float32)), speed_dps)


def detect_score(data: bytes | bytearray | memoryview) -> int:
    """How many packets of ``data`` belong to runs of at least three back-to-back good packets
    (0: not this dialect). A lone ``54 2C`` with a lucky CRC scores nothing."""
    packets, _ = locate_packets(data)
    if len(packets) < 3:
        return 0
    step = np.diff(packets.offset)
    chained = np.zeros(len(packets), bool)
    link = step == PACKET_BYTES
    chained[1:-1] = link[:-1] & link[1:]
    if not chained.any():
        return 0
    # Every packet of a run of three, not just its middle.
    run = chained.copy()
    run[:-1] |= chained[1:]
    run[1:] |= chained[:-1]
    return int(np.count_nonzero(run))


class RevolutionReader:
    """Revolutions as frames for the stream decoder (:class:`scanpipe.protocol.registry`):
    ``feed``/``finish`` return :class:`~scanpipe.protocol.framing.RawFrame` s whose ``parsed``
    is the revolution's profile. ``counters`` are the packet locator's (checksum failures,
    resyncs, bytes skipped), except ``frames_decoded``, which the caller counts (revolutions,
    as a frame reader's callers do); :attr:`packets` counts packets. Damaged packets are never
    used (their samples leave a hole in the revolution), so a revolution's checksum holds."""

    def __init__(self, lenient: bool = False, sl_correction: bool = False) -> None:
        self._decoder = RevolutionDecoder(lenient, sl_correction=sl_correction)
        self.counters = FrameCounters()

    @property
    def packets(self) -> int:
        """Packets kept so far."""
        return self._decoder.counters.frames_decoded

    def _frames(self, revolutions: list[Revolution]) -> list[RawFrame]:
        mine, theirs = self.counters, self._decoder.counters
        for name in ("checksum_failures", "resyncs", "bytes_skipped", "malformed_frames",
                     "other_frames", "length_mismatches", "implausible_frames"):
            setattr(mine, name, getattr(theirs, name))
        return [RawFrame(payload=b"", checksum_ok=r.profile.checksum_ok, received_checksum=0,
                         computed_checksum=0, start_offset=r.start_offset,
                         end_offset=r.end_offset, parsed=[r.profile]) for r in revolutions]

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[RawFrame]:
        """Add bytes; the revolutions they complete."""
        return self._frames(self._decoder.feed(chunk))

    def finish(self) -> list[RawFrame]:
        """End of stream: the rest."""
        return self._frames(self._decoder.finish())
