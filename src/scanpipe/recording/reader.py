"""The tolerant recording reader: everything readable, and a warning for everything that is not.

:func:`read_recording` reads a whole recording into a :class:`Recording` in one linear pass
(it never needs the summary section), so a file whose writer was killed is read up to its last
complete chunk. Damage never raises a third-party exception: a damaged chunk or record is
skipped with a warning; the read stops with a warning where the record structure is lost (a cut
record, a length beyond the end of the file, an unknown opcode). Only a file that is missing or
not an MCAP file at all raises :class:`RecordingError`.

It parses MCAP records itself (they are few and simple: the spec's little-endian layout) rather
than through ``mcap.reader``, because that reader stops at the first damaged byte and raises a
dozen exception types.
"""

from __future__ import annotations

import json
import mmap
import struct
import zlib
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from google.protobuf.message import DecodeError
from numpy.typing import NDArray

from scanpipe.errors import RecordingError
from scanpipe.recording import schemas
from scanpipe.recording.writer import (
    CHANNELS_METADATA,
    EVENTS,
    MOTOR_STATE,
    MOTOR_STREAM,
    PROFILE,
    RIG_KEY,
    RIG_METADATA,
    SCANNER_STREAM,
    SESSION_METADATA,
)
from scanpipe.rig import Rig

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x04, 0x05, 0x06
OP_METADATA, OP_DATA_END = 0x0C, 0x0F
KNOWN_OPCODES = frozenset(range(0x01, 0x10))
#: A chunk may not claim to inflate beyond this (never allocate from an unchecked length).
MAX_CHUNK_BYTES = 1 << 30
_STREAM_LINKS = {SCANNER_STREAM: "scanner", MOTOR_STREAM: "motor"}
#: Everything a damaged record can make the parsing below raise.
_DAMAGE = (struct.error, ValueError, KeyError, IndexError, OverflowError, UnicodeDecodeError,
           zstandard.ZstdError, DecodeError, MemoryError)


@dataclass
class StreamData:
    """One direction of a device link: the bytes in seq order and when each chunk arrived."""

    data: bytes
    chunk_end: NDArray[np.int64]  # stream offset one past each chunk's last byte
    log_time_ns: NDArray[np.int64]  # each chunk's log time
    missing_chunks: int = 0  # seq numbers never seen (lost with a damaged chunk)

    def time_at(self, end_offsets: NDArray[np.int64]) -> NDArray[np.int64]:
        """Log time of the chunk holding the byte before each offset (when a frame was whole)."""
        if self.chunk_end.size == 0:
            return np.zeros(len(end_offsets), np.int64)
        index = np.searchsorted(self.chunk_end, np.asarray(end_offsets, np.int64), side="left")
        return self.log_time_ns[np.minimum(index, self.chunk_end.size - 1)]


@dataclass
class MotorStates:
    """The ``/motor/state`` reports, as columns in log-time order."""

    log_time_ns: NDArray[np.int64]
    step_count: NDArray[np.int64]
    target_step_count: NDArray[np.int64]
    moving: NDArray[np.bool_]
    device_time_us: NDArray[np.int64]


@dataclass(frozen=True)
class Image:
    """One camera frame: the encoded bytes and when it was captured."""

    camera_id: str
    log_time_ns: int
    sequence: int
    format: str
    frame_id: str
    data: bytes


@dataclass(frozen=True)
class RecordedEvent:
    """One ``/events`` message."""

    log_time_ns: int
    kind: str
    message: str
    data: dict[str, Any]


@dataclass
class Recording:
    """Everything :func:`read_recording` could read from one file."""

    path: Path
    profile: str
    library: str
    metadata: dict[str, dict[str, str]]
    streams: dict[tuple[str, int], StreamData]
    motor: MotorStates
    images: list[Image]
    events: list[RecordedEvent]
    message_counts: dict[str, int]
    warnings: list[str]
    complete: bool  # the writer finished (data end record seen)
    bytes_read: int
    file_size: int
    chunks_read: int = 0
    chunks_damaged: int = 0

    @property
    def rig_toml(self) -> str | None:
        """The rig TOML stored with the recording, if any."""
        return self.metadata.get(RIG_METADATA, {}).get(RIG_KEY)

    @property
    def session(self) -> dict[str, str]:
        """The ``scanpipe.session`` metadata (mode, start time, host, versions)."""
        return dict(self.metadata.get(SESSION_METADATA, {}))

    def rig(self) -> Rig:
        """The rig the recording was made with; :class:`RecordingError` if absent or invalid."""
        from scanpipe.errors import RigError
        from scanpipe.rig import rig_from_toml

        text = self.rig_toml
        if text is None:
            raise RecordingError(f"{self.path}: no {RIG_METADATA!r} metadata (no rig stored)")
        try:
            return rig_from_toml(text, f"{self.path}:{RIG_METADATA}")
        except RigError as err:
            raise RecordingError(f"{self.path}: stored rig is invalid: {err}") from None

    def stream(self, link: str, direction: int = schemas.RX) -> StreamData:
        """The bytes of one link and direction (empty when the recording has none)."""
        empty = StreamData(b"", np.zeros(0, np.int64), np.zeros(0, np.int64))
        return self.streams.get((link, direction), empty)


@dataclass
class _Collector:
    """What the pass over the records gathers before it is turned into a Recording."""

    channels: dict[int, str] = field(default_factory=dict)
    fallback_channels: dict[int, str] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    stream_parts: dict[tuple[str, int], list[tuple[int, int, bytes]]] = field(
        default_factory=lambda: defaultdict(list))
    motor_rows: list[tuple[int, int, int, bool, int]] = field(default_factory=list)
    images: list[Image] = field(default_factory=list)
    events: list[RecordedEvent] = field(default_factory=list)
    counts: Counter[str] = field(default_factory=Counter)
    undecodable: Counter[str] = field(default_factory=Counter)
    unknown_channels: Counter[int] = field(default_factory=Counter)
    warnings: list[str] = field(default_factory=list)
    profile: str = ""
    library: str = ""
    chunks_read: int = 0
    chunks_damaged: int = 0
    complete: bool = False


class _Buffer:
    """Little-endian field reads with bounds checks (struct.error on overrun)."""

    def __init__(self, data: bytes | memoryview, pos: int = 0) -> None:
        self.data, self.pos = data, pos

    def u16(self) -> int:
        (value,) = struct.unpack_from("<H", self.data, self.pos)
        self.pos += 2
        return int(value)

    def u32(self) -> int:
        (value,) = struct.unpack_from("<I", self.data, self.pos)
        self.pos += 4
        return int(value)

    def u64(self) -> int:
        (value,) = struct.unpack_from("<Q", self.data, self.pos)
        self.pos += 8
        return int(value)

    def raw(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise ValueError(f"field of {n} bytes runs past the record end")
        value = bytes(self.data[self.pos:self.pos + n])
        self.pos += n
        return value

    def string(self) -> str:
        return self.raw(self.u32()).decode("utf-8")

    def string_map(self) -> dict[str, str]:
        end = self.u32() + self.pos
        result = {}
        while self.pos < end:
            key = self.string()
            result[key] = self.string()
        if self.pos != end:
            raise ValueError("map length does not match its entries")
        return result


def read_recording(path: Path | str) -> Recording:
    """Read a recording in one linear pass; see the module docstring for damage handling."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            size = path.stat().st_size
            if size < len(MAGIC):
                raise RecordingError(f"{path}: {size} bytes, not an MCAP recording")
            with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
                if data[:len(MAGIC)] != MAGIC:
                    raise RecordingError(f"{path}: not an MCAP file (bad magic bytes)")
                collector = _Collector()
                bytes_read = _read_records(data, size, collector)
    except FileNotFoundError:
        raise RecordingError(f"{path}: not found") from None
    except IsADirectoryError:
        raise RecordingError(f"{path}: is a directory, expected an MCAP recording") from None
    except (OSError, ValueError) as err:  # mmap of special files raises ValueError
        raise RecordingError(f"{path}: cannot be read ({err})") from None
    return _assemble(path, collector, bytes_read, size)


def _read_records(data: mmap.mmap, size: int, c: _Collector) -> int:
    """The outer record loop. Returns the offset where reading stopped."""
    pos = len(MAGIC)
    while pos < size:
        problem = None
        if pos + 9 > size:
            problem = "the file ends inside a record header"
        else:
            opcode = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            if opcode not in KNOWN_OPCODES:
                problem = f"unknown record opcode {opcode:#04x}"
            elif length > size - pos - 9:
                problem = f"a record of {length} bytes runs past the end of the file"
        if problem is None and opcode in (OP_DATA_END, OP_FOOTER):
            c.complete = True
            return int(pos + 9 + length)
        if problem is None:
            body = data[pos + 9:pos + 9 + length]  # a copy: no view may outlive the mmap
            try:
                if opcode == OP_CHUNK:
                    _read_chunk(body, pos, c)
                else:
                    _read_record(opcode, body, c)
                pos += 9 + length
                continue
            except _DAMAGE as err:
                problem = (f"record {opcode:#04x} at byte {pos} is damaged "
                           f"({type(err).__name__}: {err})")
        # The record structure is lost here: a cut file, or damage. Resume at the next
        # well-formed chunk if there is one; otherwise the file was cut.
        resume = _next_chunk(data, pos + 1, size)
        if resume is None:
            c.warnings.append(_stop_message(c, pos, size, problem))
            return pos
        c.warnings.append(f"{problem}; bytes {pos}…{resume} skipped, reading resumed at the "
                          "next chunk")
        pos = resume
    c.warnings.append(_stop_message(c, pos, size, "the file ends without a data end record"))
    return pos


#: A chunk record's fixed fields: start time, end time, uncompressed size, CRC.
_CHUNK_FIXED_BYTES = 8 + 8 + 8 + 4


def _next_chunk(data: mmap.mmap, start: int, size: int) -> int | None:
    """Offset of the next record at or after ``start`` that is shaped like a whole chunk: its
    length field equals the sum of its parts and its compression is zstd or none."""
    pos = data.find(bytes([OP_CHUNK]), start)
    while pos >= 0:
        fields = pos + 9 + _CHUNK_FIXED_BYTES
        if fields + 4 <= size:
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            (name_length,) = struct.unpack_from("<I", data, fields)
            if (name_length in (0, 4) and fields + 4 + name_length + 8 <= size
                    and data[fields + 4:fields + 4 + name_length] in (b"", b"zstd")):
                (records,) = struct.unpack_from("<Q", data, fields + 4 + name_length)
                expected = _CHUNK_FIXED_BYTES + 4 + name_length + 8 + records
                if length == expected and pos + 9 + length <= size:
                    return int(pos)
        pos = data.find(bytes([OP_CHUNK]), pos + 1)
    return None


def _stop_message(c: _Collector, pos: int, size: int, why: str) -> str:
    return (f"recording incomplete (writer killed?): {why}; read {pos} of {size} bytes, "
            f"{c.chunks_read} complete chunks, stopped at byte {pos}")


def _read_chunk(body: bytes, offset: int, c: _Collector) -> None:
    buf = _Buffer(body)
    start_ns, end_ns, uncompressed_size, crc = buf.u64(), buf.u64(), buf.u64(), buf.u32()
    compression = buf.string()
    compressed = buf.raw(buf.u64())
    try:
        if uncompressed_size > min(MAX_CHUNK_BYTES, 1000 * len(compressed) + (1 << 20)):
            raise ValueError(f"claims {uncompressed_size} bytes from {len(compressed)}")
        if compression == "zstd":
            records = zstandard.ZstdDecompressor().decompress(
                compressed, max_output_size=uncompressed_size)
        elif compression == "":
            records = compressed
        else:
            raise ValueError(f"unsupported compression {compression!r}")
        if len(records) != uncompressed_size or (crc and zlib.crc32(records) != crc):
            raise ValueError("size or CRC of the decompressed records does not match")
    except _DAMAGE as err:
        c.chunks_damaged += 1
        c.warnings.append(f"chunk at byte {offset} (log time {start_ns}…{end_ns} ns) is damaged "
                          f"and was skipped ({type(err).__name__}: {err})")
        return
    c.chunks_read += 1
    pos = 0
    while pos + 9 <= len(records):
        opcode = records[pos]
        (length,) = struct.unpack_from("<Q", records, pos + 1)
        if length > len(records) - pos - 9:
            break
        _read_record(opcode, memoryview(records)[pos + 9:pos + 9 + length], c)
        pos += 9 + length
    if pos != len(records):
        c.warnings.append(f"chunk at byte {offset}: its records end {len(records) - pos} bytes "
                          "early; the rest was skipped")


def _read_record(opcode: int, body: bytes | memoryview, c: _Collector) -> None:
    buf = _Buffer(body)
    if opcode == OP_MESSAGE:
        channel, sequence, log_time = buf.u16(), buf.u32(), buf.u64()
        buf.pos += 8  # publish time
        _read_message(channel, sequence, log_time, bytes(body[buf.pos:]), c)
    elif opcode == OP_CHANNEL:
        channel = buf.u16()
        buf.u16()  # schema id: the topic says which scanpipe message it carries
        c.channels[channel] = buf.string()
    elif opcode == OP_METADATA:
        name = buf.string()
        values = buf.string_map()
        c.metadata[name] = values
        if name == CHANNELS_METADATA:
            c.fallback_channels = {int(k): v for k, v in values.items()}
    elif opcode == OP_HEADER:
        c.profile, c.library = buf.string(), buf.string()
        if c.profile != PROFILE:
            c.warnings.append(f"MCAP profile {c.profile!r}: not written by scanpipe "
                              f"(expected {PROFILE!r}); reading what is recognisable")


def _read_message(channel: int, sequence: int, log_time: int, data: bytes, c: _Collector) -> None:
    topic = c.channels.get(channel) or c.fallback_channels.get(channel)
    if topic is None:
        c.unknown_channels[channel] += 1
        return
    c.counts[topic] += 1
    try:
        if topic in _STREAM_LINKS:
            chunk = schemas.ByteChunk.FromString(data)
            c.stream_parts[(_STREAM_LINKS[topic], int(chunk.direction))].append(
                (int(chunk.seq), log_time, chunk.data))
        elif topic == MOTOR_STATE:
            state = schemas.MotorState.FromString(data)
            c.motor_rows.append((log_time, state.step_count, state.target_step_count,
                                 state.moving, state.device_time_us))
        elif topic == EVENTS:
            event = schemas.Event.FromString(data)
            details = json.loads(event.data_json) if event.data_json else {}
            c.events.append(RecordedEvent(log_time, event.kind, event.message,
                                          details if isinstance(details, dict) else {}))
        elif topic.startswith("/camera/") and topic.endswith("/image"):
            image = schemas.CompressedImage.FromString(data)
            camera_id = topic[len("/camera/"):-len("/image")]
            c.images.append(Image(camera_id, log_time, sequence, image.format, image.frame_id,
                                  image.data))
    except _DAMAGE:
        c.undecodable[topic] += 1


def _assemble(path: Path, c: _Collector, bytes_read: int, size: int) -> Recording:
    warnings = list(c.warnings)
    for topic, n in sorted(c.undecodable.items()):
        warnings.append(f"{n} messages on {topic} could not be decoded and were skipped")
    if c.unknown_channels:
        warnings.append(f"{sum(c.unknown_channels.values())} messages on unknown channels "
                        f"{sorted(c.unknown_channels)} were skipped")
    streams = {}
    for key, parts in c.stream_parts.items():
        parts.sort(key=lambda part: part[0])
        seqs = np.fromiter((p[0] for p in parts), np.int64, len(parts))
        unique = np.unique(seqs)
        missing = int(unique[-1] - unique[0] + 1 - unique.size) if unique.size else 0
        if unique.size != seqs.size:
            warnings.append(f"{key[0]} stream: {seqs.size - unique.size} repeated chunks kept")
        if missing:
            warnings.append(f"{key[0]} stream ({'RX' if key[1] == 0 else 'TX'}): {missing} "
                            "chunks missing (lost with damaged chunks); frames across the gap "
                            "are resynchronised")
        lengths = np.fromiter((len(p[2]) for p in parts), np.int64, len(parts))
        streams[key] = StreamData(
            data=b"".join(p[2] for p in parts),
            chunk_end=np.cumsum(lengths),
            log_time_ns=np.fromiter((p[1] for p in parts), np.int64, len(parts)),
            missing_chunks=missing,
        )
    rows = sorted(c.motor_rows, key=lambda r: r[0])
    motor = MotorStates(
        log_time_ns=np.array([r[0] for r in rows], np.int64),
        step_count=np.array([r[1] for r in rows], np.int64),
        target_step_count=np.array([r[2] for r in rows], np.int64),
        moving=np.array([r[3] for r in rows], np.bool_),
        device_time_us=np.array([r[4] for r in rows], np.uint64).astype(np.int64),
    )
    return Recording(
        path=path, profile=c.profile, library=c.library, metadata=c.metadata, streams=streams,
        motor=motor, images=sorted(c.images, key=lambda i: (i.camera_id, i.log_time_ns)),
        events=sorted(c.events, key=lambda e: e.log_time_ns), message_counts=dict(c.counts),
        warnings=warnings, complete=c.complete, bytes_read=bytes_read, file_size=size,
        chunks_read=c.chunks_read, chunks_damaged=c.chunks_damaged,
    )
