"""The tolerant recording reader: everything readable, and a warning for everything that is not.

:func:`read_recording` reads a whole recording into a :class:`Recording` in one linear pass
(it never needs the summary section), so a file whose writer was killed is read up to its last
complete chunk. Damage never raises a third-party exception: a damaged chunk (its CRC, size or
zstd data wrong) is skipped with a warning; where the record structure is lost (an unknown
opcode, a length beyond the end of the file, a damaged length field) reading resynchronises on
the next record shaped like a whole chunk, so every intact chunk after the damage is read. What
was lost is counted in :class:`RecordingLoss` (``Recording.loss``): chunks, bytes and log time,
exact when the summary section's chunk indexes are intact, a lower bound otherwise. Only a file
that is missing or not an MCAP file at all raises :class:`RecordingError`.

It parses MCAP records itself (they are few and simple: the spec's little-endian layout) rather
than through ``mcap.reader``, because that reader stops at the first damaged byte and raises a
dozen exception types.
"""

from __future__ import annotations

import bisect
import contextlib
import json
import mmap
import os
import struct
import zlib
from collections import Counter, defaultdict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

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
    PART_CONTINUES_EVENT,
    PROFILE,
    RECORDING_END_EVENT,
    RIG_KEY,
    RIG_METADATA,
    SCAN_END_EVENT,
    SCANNER_PROFILES,
    SCANNER_STREAM,
    SESSION_METADATA,
)
from scanpipe.rig import Rig

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL = 0x01, 0x02, 0x03, 0x04
OP_MESSAGE, OP_CHUNK = 0x05, 0x06
OP_ATTACHMENT = 0x09
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_METADATA, OP_DATA_END = 0x07, 0x08, 0x0C, 0x0F
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
class DecodedProfile:
    """One ``/scanner/profiles`` message: a profile another tool already decoded."""

    log_time_ns: int
    device_time_ns: int  # 0 = unknown
    device_end_time_ns: int  # 0 = unknown
    frame: int
    start_angle_deg: float
    step_deg: float
    ranges_m: NDArray[np.float32]
    intensities: NDArray[np.float32]


@dataclass(frozen=True)
class RecordedEvent:
    """One ``/events`` message."""

    log_time_ns: int
    kind: str
    message: str
    data: dict[str, Any]


@dataclass(frozen=True)
class LostRegion:
    """One stretch of the file that could not be read: a damaged chunk or skipped bytes."""

    offset: int  # byte offset in the file
    length: int  # bytes
    reason: str
    start_ns: int | None = None  # log time lost, when known
    end_ns: int | None = None


@dataclass(frozen=True)
class RecordingLoss:
    """What damage or a cut cost a recording: the tolerant reader's loss counters.

    ``chunks`` counts data chunks not read (damaged, skipped while resynchronising, or cut off);
    ``bytes`` the file bytes not read (damaged records, skipped stretches, a cut tail);
    ``time_ns`` the log time those chunks spanned (the union of their time ranges). With an
    intact summary section (``from_summary``) chunks and times come from its chunk indexes and
    are exact. Without one (a killed writer, a damaged summary) ``chunks`` is a lower bound (the
    chunk headers still recognisable in the lost stretches) and ``time_ns`` the log time between
    the intact chunks on either side of each lost stretch (for a cut tail, up to the end time in
    the cut chunk's header when it is readable). ``regions`` lists each lost stretch.
    """

    chunks: int = 0
    bytes: int = 0
    time_ns: int = 0
    from_summary: bool = False
    regions: tuple[LostRegion, ...] = ()

    @property
    def time_s(self) -> float:
        """``time_ns`` in seconds."""
        return self.time_ns / 1e9

    @property
    def any(self) -> bool:
        """Whether anything was lost."""
        return bool(self.chunks or self.bytes)

    def as_dict(self) -> dict[str, Any]:
        """Plain data for JSON (regions as dicts)."""
        return {"chunks": self.chunks, "bytes": self.bytes, "time_s": self.time_s,
                "time_ns": self.time_ns, "exact": self.from_summary,
                "regions": [vars(r).copy() for r in self.regions]}


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
    loss: RecordingLoss = field(default_factory=RecordingLoss)
    profiles: list[DecodedProfile] = field(default_factory=list)

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
        from scanpipe.rig import RECORDED, rig_from_toml

        text = self.rig_toml
        if text is None:
            raise RecordingError(f"{self.path}: no {RIG_METADATA!r} metadata (no rig stored)")
        try:
            return rig_from_toml(text, f"{self.path}:{RIG_METADATA}", context=RECORDED)
        except RigError as err:
            raise RecordingError(f"{self.path}: stored rig is invalid: {err}") from None

    def partial_scan_warnings(self) -> list[str]:
        """Why this file may hold only part of a scan: a part of a split recording
        (``record --split-*``), a scan the recorder ended before its sweep was done
        (Ctrl-C, a lost device, a failure), or a camera lost during it."""
        warnings = []
        # A foreign or damaged file may hold other JSON than an object in an event's data.
        events = [e for e in self.events if isinstance(e.data, dict)]
        part = self.session.get("part")
        following = [e for e in events if e.kind == PART_CONTINUES_EVENT]
        if following:
            warnings.append(
                f"part {part} of a split recording: the scan continues in "
                f"{following[-1].data.get('next_file', 'the next part')}; this file alone "
                "holds only part of it")
        elif part not in (None, "0"):  # part 0 without a next part is the whole scan
            warnings.append(f"part {part} of a split recording (the last one if its "
                            "recorder finished); the scan's other parts are separate files")
        # The scan's end says whether the sweep was done (the way back that follows may still
        # fail); a recording cut before it only has the recording's end.
        ends = [e for e in events if e.kind in (SCAN_END_EVENT, RECORDING_END_EVENT)]
        status = ends[0].data.get("status") if ends else None
        if status not in (None, "complete"):
            reasons = [e.data.get("reason") for e in events
                       if e.kind == RECORDING_END_EVENT and e.data.get("reason")]
            why = f" ({reasons[0]})" if reasons else ""
            warnings.append(f"the scan ended {status}{why} before its sweep was done: the "
                            "recording holds only part of the scan, so the model will be "
                            "partial")
        # A camera lost during the scan: its frames cover only the platform angles before.
        start = events[0].log_time_ns if events else 0
        for event in events:
            if event.kind == "camera_lost":
                warnings.append(f"camera {event.data.get('camera_id', '?')} was lost "
                                f"{(event.log_time_ns - start) / 1e9:.1f} s into the recording "
                                f"({event.message}): its frames stop there, so its texture "
                                "covers only what it saw before")
        return warnings

    def stream(self, link: str, direction: int = schemas.RX) -> StreamData:
        """The bytes of one link and direction (empty when the recording has none)."""
        empty = StreamData(b"", np.zeros(0, np.int64), np.zeros(0, np.int64))
        return self.streams.get((link, direction), empty)


@dataclass(frozen=True)
class McapSchema:
    """One schema record of an MCAP file."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class McapChannel:
    """One channel record of an MCAP file, with what was read of its messages."""

    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]
    messages: int = 0
    first_ns: int | None = None
    last_ns: int | None = None


@dataclass(frozen=True)
class McapAttachment:
    """One attachment record of an MCAP file."""

    log_time_ns: int
    create_time_ns: int
    name: str
    media_type: str
    data: bytes


class MessageSink(Protocol):
    """Called for every message read: channel id, sequence, log and publish time, payload."""

    def __call__(self, channel_id: int, sequence: int, log_time_ns: int, publish_time_ns: int,
                 data: bytes) -> None: ...


@dataclass
class McapCatalogue:
    """What :func:`read_catalogue` read from any MCAP file: header, schemas, channels with
    message counts and log-time ranges, metadata, attachments, and the damage met."""

    path: Path
    profile: str
    library: str
    schemas: dict[int, McapSchema]
    channels: dict[int, McapChannel]
    metadata: dict[str, dict[str, str]]
    attachments: list[McapAttachment]
    unknown_channel_messages: int
    warnings: list[str]
    complete: bool
    bytes_read: int
    file_size: int
    chunks_read: int
    chunks_damaged: int
    loss: RecordingLoss

    @property
    def messages(self) -> int:
        """Messages read on known channels."""
        return sum(c.messages for c in self.channels.values())


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
    profiles: list[DecodedProfile] = field(default_factory=list)
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
    good_chunks: dict[int, tuple[int, int]] = field(default_factory=dict)  # offset → times
    lost: list[LostRegion] = field(default_factory=list)
    # The generic catalogue of any MCAP file (see :func:`read_catalogue`).
    generic: bool = False  # any MCAP: no scanpipe decoding, no profile checks
    schemas: dict[int, McapSchema] = field(default_factory=dict)
    channel_info: dict[int, McapChannel] = field(default_factory=dict)
    attachments: list[McapAttachment] = field(default_factory=list)
    on_message: MessageSink | None = None


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
        return bytes(self.view(n))

    def view(self, n: int) -> memoryview:
        """The next ``n`` bytes, not copied."""
        if n < 0 or self.pos + n > len(self.data):
            raise ValueError(f"field of {n} bytes runs past the record end")
        value = memoryview(self.data)[self.pos:self.pos + n]
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


def read_recording(path: Path | str, handle: IO[bytes] | None = None) -> Recording:
    """Read a recording in one linear pass; see the module docstring for damage handling.

    ``handle``: read this open file (named ``path`` in the result and in messages) instead of
    opening ``path`` (a follower's file, which its writer may have renamed or deleted)."""
    path = Path(path)
    collector = _Collector()
    bytes_read, size, loss = _scan(path, collector, handle)
    return _assemble(path, collector, bytes_read, size, loss)


def read_catalogue(path: Path | str, on_message: MessageSink | None = None) -> McapCatalogue:
    """Read any MCAP file (not only recordings) in the same tolerant linear pass: its schemas,
    channels, message counts and log-time ranges, metadata and attachments.

    ``on_message`` is called for every message read (what ``scanpipe recover`` copies). Damage
    is handled as in :func:`read_recording`; only a missing or non-MCAP file raises.
    """
    path = Path(path)
    collector = _Collector(generic=True, on_message=on_message)
    bytes_read, size, loss = _scan(path, collector)
    return _catalogue(path, collector, bytes_read, size, loss)


def read_recording_and_catalogue(path: Path | str) -> tuple[Recording, McapCatalogue]:
    """A recording and its generic catalogue from one pass (``scanpipe info``)."""
    path = Path(path)
    collector = _Collector()
    bytes_read, size, loss = _scan(path, collector)
    return (_assemble(path, collector, bytes_read, size, loss),
            _catalogue(path, collector, bytes_read, size, loss))


def header_profile(path: Path | str) -> str | None:
    """The MCAP profile in a file's header record, or None when the file does not start with a
    readable header (the full readers then say why)."""
    try:
        with Path(path).open("rb") as handle:
            head = handle.read(len(MAGIC) + 9 + 4 + 4096)
        if head[:len(MAGIC)] != MAGIC or head[len(MAGIC)] != OP_HEADER:
            return None
        buf = _Buffer(head, len(MAGIC) + 9)
        return buf.string()
    except (OSError, *_DAMAGE):
        return None


def _catalogue(path: Path, collector: _Collector, bytes_read: int, size: int,
               loss: RecordingLoss) -> McapCatalogue:
    warnings = list(collector.warnings)
    unknown = sum(collector.unknown_channels.values())
    if unknown:
        warnings.append(f"{unknown} messages on channels without a channel record "
                        f"{sorted(collector.unknown_channels)} were skipped")
    return McapCatalogue(
        path=path, profile=collector.profile, library=collector.library,
        schemas=dict(collector.schemas), channels=dict(collector.channel_info),
        metadata=dict(collector.metadata), attachments=list(collector.attachments),
        unknown_channel_messages=unknown, warnings=warnings, complete=collector.complete,
        bytes_read=bytes_read, file_size=size, chunks_read=collector.chunks_read,
        chunks_damaged=collector.chunks_damaged, loss=loss)


def _scan(path: Path, collector: _Collector, opened: IO[bytes] | None = None
          ) -> tuple[int, int, RecordingLoss]:
    """The linear pass over one file: ``(bytes read, file size, loss)``."""
    try:
        with contextlib.nullcontext(opened) if opened is not None else path.open("rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            if size < len(MAGIC):
                raise RecordingError(f"{path}: {size} bytes, not an MCAP recording")
            with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
                if data[:len(MAGIC)] != MAGIC:
                    raise RecordingError(f"{path}: {_not_mcap(bytes(data[:16]))}")
                bytes_read = _read_records(data, size, collector)
                loss = _loss(data, size, collector)
    except FileNotFoundError:
        raise RecordingError(f"{path}: not found") from None
    except IsADirectoryError:
        if (path / "metadata.yaml").is_file():
            raise RecordingError(f"{path}: is a ROS 2 bag, not a scanpipe recording; convert it "
                                 f"with: scanpipe import-bag {path} --out REC.mcap") from None
        raise RecordingError(f"{path}: is a directory, expected an MCAP recording") from None
    except (OSError, ValueError) as err:  # mmap of special files raises ValueError
        raise RecordingError(f"{path}: cannot be read ({err})") from None
    except RecordingError as err:
        if str(err).startswith("is a ROS"):
            raise RecordingError(f"{path}: {err}") from None
        raise
    return bytes_read, size, loss


def _not_mcap(head: bytes) -> str:
    """Why a file is not a recording: a ROS bag is named as one, with the way in."""
    if head.startswith(b"#ROSBAG V"):
        kind = "a ROS 1 bag"
    elif head.startswith(b"SQLite format 3\0"):
        kind = "an SQLite file (a ROS 2 bag's .db3?)"
    else:
        return "not an MCAP file (bad magic bytes)"
    return (f"is {kind}, not a scanpipe recording; convert it with: scanpipe import-bag "
            "BAG --out REC.mcap")


#: The batch reader hands the pages of the file it has read back to the kernel every this
#: many bytes: a mapped page counts in the process's resident memory until then (a 286 MB
#: recording would otherwise add 286 MB to decode's peak). The file stays in the page cache.
_RELEASE_BYTES = 32 << 20


def _release_pages(data: mmap.mmap, start: int, end: int) -> int:
    """Drop the mapping's resident pages in [start, end) (page-aligned inwards); the offset up
    to which pages are now released."""
    first = start - start % mmap.PAGESIZE
    last = end - end % mmap.PAGESIZE
    if last > first and hasattr(mmap, "MADV_DONTNEED"):
        with contextlib.suppress(OSError, ValueError):
            data.madvise(mmap.MADV_DONTNEED, first, last - first)
        return last
    return start


class _ChunkPrefetch:
    """Decompresses and checks the next chunk in a worker thread while the current one's
    messages are parsed: zstd and crc32 release the GIL, so on two cores they overlap (most of
    a recording's bytes are camera frames, whose inflating and CRC is most of the reading).

    The worker only runs :func:`_decode_chunk` on a copy of the chunk's bytes: the same result,
    or the same exception, as a direct call. The loop takes it only for the chunk at the same
    offset with the same length, after its own checks; anything else is decoded directly.
    """

    #: How many records (message indexes) after a chunk are skipped to find the next one.
    LOOK_AHEAD = 256

    def __init__(self, data: mmap.mmap, size: int) -> None:
        self._data, self._size = data, size
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="mcap-inflate")
        self._pending: tuple[int, bytes, Future[tuple[int, int, bytes]]] | None = None

    def take(self, pos: int, length: int) -> tuple[bytes, Future[tuple[int, int, bytes]]] | None:
        """The body of the chunk record at ``pos`` and its decode, if that was started ahead."""
        pending, self._pending = self._pending, None
        if pending is None or pending[0] != pos or len(pending[1]) != length:
            return None
        return pending[1], pending[2]

    def ahead(self, pos: int) -> None:
        """Start decoding the next chunk record at or after ``pos`` (past message indexes)."""
        data, size = self._data, self._size
        for _ in range(self.LOOK_AHEAD):
            if pos + 9 > size:
                return
            opcode = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            if length > size - pos - 9:
                return
            if opcode == OP_CHUNK:
                body = data[pos + 9:pos + 9 + length]
                self._pending = (pos, body, self._pool.submit(_decode_chunk, body))
                return
            if opcode != OP_MESSAGE_INDEX:
                return
            pos += 9 + length

    def close(self) -> None:
        """Stop the worker (a pending decode is dropped)."""
        self._pending = None
        self._pool.shutdown(wait=True, cancel_futures=True)


def _read_records(data: mmap.mmap, size: int, c: _Collector) -> int:
    """The outer record loop. Returns the offset where reading stopped."""
    prefetch = _ChunkPrefetch(data, size)
    try:
        return _read_records_with(data, size, c, prefetch)
    finally:
        prefetch.close()


def _read_records_with(data: mmap.mmap, size: int, c: _Collector,
                       prefetch: _ChunkPrefetch) -> int:
    pos = len(MAGIC)
    released = 0
    while pos < size:
        if pos - released >= _RELEASE_BYTES:
            released = _release_pages(data, released, pos)
        problem = None
        opcode = length = 0
        if pos + 9 > size:
            problem = "the file ends inside a record header"
        else:
            opcode = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            if opcode not in KNOWN_OPCODES:
                problem = f"unknown record opcode {opcode:#04x}"
            elif length > size - pos - 9:
                problem = f"a record of {length} bytes runs past the end of the file"
        if problem is None:
            shaped = _chunk_end(data, pos, size, check_length=True) is not None
            if opcode == OP_CHUNK and not shaped:
                problem = f"chunk at byte {pos}: its length field does not match its contents"
            elif opcode != OP_CHUNK and shaped:  # a chunk whose opcode byte was hit
                problem = f"record at byte {pos}: opcode {opcode:#04x} on a chunk-shaped record"
            elif opcode in (OP_DATA_END, OP_FOOTER):
                if length == _END_LENGTHS[opcode]:
                    c.complete = True
                    return int(pos + 9 + length)
                problem = f"end record at byte {pos} has a wrong length ({length})"
            elif opcode != OP_CHUNK and not _length_confirmed(data, pos, opcode, length, size):
                problem = (f"record {opcode:#04x} at byte {pos}: its length {length} does not "
                           "match its contents")
        if problem is None:
            started = prefetch.take(pos, length) if opcode == OP_CHUNK else None
            # A copy: no view may outlive the mmap.
            body = started[0] if started else data[pos + 9:pos + 9 + length]
            try:
                if opcode == OP_CHUNK:
                    prefetch.ahead(pos + 9 + length)
                    _read_chunk(body, pos, c, started[1] if started else None)
                else:
                    _read_record(opcode, body, c)
                pos += 9 + length
                continue
            except _DAMAGE as err:
                problem = (f"record {opcode:#04x} at byte {pos} is damaged "
                           f"({type(err).__name__}: {err})")
        # The record structure is lost here: damage in a record header, or a cut file. A chunk
        # whose opcode or length field was hit is still recognised by its inner fields and
        # accepted if its CRC matches; otherwise resume at the next well-formed chunk.
        recovered = _recover_chunk(data, pos, size, c)
        if recovered is not None:
            c.warnings.append(f"{problem}; the chunk there was recovered by its CRC")
            pos = recovered
            continue
        resume = _next_chunk(data, pos + 1, size)
        if resume is None:
            c.lost.append(LostRegion(pos, size - pos, "cut", *_header_times(data, pos, size)))
            c.warnings.append(_stop_message(c, pos, size, problem))
            return pos
        c.lost.append(LostRegion(pos, resume - pos, "skipped"))
        c.warnings.append(f"{problem}; bytes {pos}…{resume} skipped, reading resumed at the "
                          "next chunk")
        pos = resume
    c.warnings.append(_stop_message(c, pos, size, "the file ends without a data end record"))
    return pos


#: A chunk record's fixed fields: start time, end time, uncompressed size, CRC.
_CHUNK_FIXED_BYTES = 8 + 8 + 8 + 4
#: The body length of the data end record (a CRC) and of the footer (two offsets and a CRC).
_END_LENGTHS = {OP_DATA_END: 4, OP_FOOTER: 20}


#: Top-level records whose parsing checks that their fields fill the length exactly.
_SELF_CHECKED = frozenset({OP_HEADER, OP_METADATA})


def _length_confirmed(data: mmap.mmap, pos: int, opcode: int, length: int, size: int) -> bool:
    """Whether a record's length field is confirmed: by its own fields (message index; header
    and metadata are checked when parsed), or else by a record starting where it ends (or a
    chunk shaped by its inner fields there, whose own header may be the damaged one)."""
    if opcode in _SELF_CHECKED:
        return True
    if opcode == OP_MESSAGE_INDEX:
        if length < 6:
            return False
        (records,) = struct.unpack_from("<I", data, pos + 9 + 2)
        return bool(length == 6 + records and records % 16 == 0)
    end = pos + 9 + length
    return _record_starts(data, end, size) or _chunk_end(data, end, size) is not None


def _record_starts(data: mmap.mmap, pos: int, size: int) -> bool:
    """Whether a record can start at ``pos``: a known opcode and a length inside the file (or
    the file ends there, or is cut inside the header: that is found when reading on)."""
    if pos + 9 > size:
        return True
    (length,) = struct.unpack_from("<Q", data, pos + 1)
    return data[pos] in KNOWN_OPCODES and length <= size - pos - 9


def _chunk_end(data: mmap.mmap, pos: int, size: int, check_length: bool = False,
               check_opcode: bool = False) -> int | None:
    """Where the chunk record at ``pos`` ends, if its inner fields are consistent (compression
    zstd or none, the records inside the file); optionally also that its length field equals
    the sum of the parts and its opcode is a chunk's."""
    fields = pos + 9 + _CHUNK_FIXED_BYTES
    if fields + 4 > size:
        return None
    (name_length,) = struct.unpack_from("<I", data, fields)
    if name_length not in (0, 4) or fields + 4 + name_length + 8 > size:
        return None
    if data[fields + 4:fields + 4 + name_length] not in (b"", b"zstd"):
        return None
    (records,) = struct.unpack_from("<Q", data, fields + 4 + name_length)
    expected = _CHUNK_FIXED_BYTES + 4 + name_length + 8 + records
    if pos + 9 + expected > size:
        return None
    if check_opcode and data[pos] != OP_CHUNK:
        return None
    if check_length and struct.unpack_from("<Q", data, pos + 1)[0] != expected:
        return None
    return int(pos + 9 + expected)


def _next_chunk(data: mmap.mmap, start: int, size: int) -> int | None:
    """Offset of the next record at or after ``start`` that is shaped like a whole chunk."""
    pos = data.find(bytes([OP_CHUNK]), start)
    while pos >= 0:
        if _chunk_end(data, pos, size, check_length=True, check_opcode=True) is not None:
            return int(pos)
        pos = data.find(bytes([OP_CHUNK]), pos + 1)
    return None


def _recover_chunk(data: mmap.mmap, pos: int, size: int, c: _Collector) -> int | None:
    """Read the record at ``pos`` as a chunk despite a damaged opcode, record length or
    records length field; the offset after it, or None.

    Two ends are tried: the record length's (the compressed bytes then run to it, whatever the
    records length says) and the inner fields' (a compression field and a records length that
    fit). The zstd frame must fill the compressed bytes exactly, the CRC (required) must match,
    and a record (or the end of the file) must follow.
    """
    if pos + 9 + _CHUNK_FIXED_BYTES + 4 > size:
        return None
    (length,) = struct.unpack_from("<Q", data, pos + 1)
    candidates = [(int(pos + 9 + length), True)] if length <= size - pos - 9 else []
    inner_end = _chunk_end(data, pos, size)
    if inner_end is not None:
        candidates.append((inner_end, False))
    for end, to_end in candidates:
        if end + 9 <= size and data[end] not in KNOWN_OPCODES:  # a cut record may follow
            continue
        try:
            start_ns, end_ns, records = _decode_chunk(data[pos + 9:end], require_crc=True,
                                                      compressed_to_end=to_end)
        except _DAMAGE:
            continue
        _read_chunk_records(records, pos, start_ns, end_ns, c)
        return end
    return None


def _header_times(data: mmap.mmap, pos: int, size: int) -> tuple[int | None, int | None]:
    """The log time range a chunk header at ``pos`` claims, if it is readable."""
    if pos + 9 + 16 > size or data[pos] != OP_CHUNK:
        return None, None
    start_ns, end_ns = struct.unpack_from("<QQ", data, pos + 9)
    return int(start_ns), int(end_ns)


def _stop_message(c: _Collector, pos: int, size: int, why: str) -> str:
    return (f"recording incomplete (writer killed?): {why}; read {pos} of {size} bytes, "
            f"{c.chunks_read} complete chunks, stopped at byte {pos}")


def _inflate(compressed: bytes | memoryview, claimed_size: int, piece: int = 1 << 20) -> bytes:
    """Decompress a zstd frame, reading at most one piece past ``claimed_size``.

    Memory grows with the bytes the frame really holds, never with what a (damaged) header
    claims, and zeros that compress 5000:1 (a blank image) are as good as any other data.
    """
    reader = zstandard.ZstdDecompressor().stream_reader(compressed)
    parts: list[bytes] = []
    total = 0
    while total <= claimed_size:
        part = reader.read(piece)
        if not part:
            break
        parts.append(part)
        total += len(part)
    return b"".join(parts)


def _decode_chunk(body: bytes, require_crc: bool = False,
                  compressed_to_end: bool = False) -> tuple[int, int, bytes]:
    """A chunk record's time range and its records, checked by size and CRC (raises on damage).

    ``compressed_to_end``: the compressed records run to the end of ``body`` (their length field
    is not trusted). ``require_crc``: a CRC must be present, and the zstd frame must end exactly
    at the end of the compressed bytes (zstd ignores trailing bytes)."""
    buf = _Buffer(body)
    start_ns, end_ns, uncompressed_size, crc = buf.u64(), buf.u64(), buf.u64(), buf.u32()
    compression = buf.string()
    records_length = buf.u64()
    compressed = buf.view(len(body) - buf.pos if compressed_to_end else records_length)
    if uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(f"claims {uncompressed_size} bytes (at most {MAX_CHUNK_BYTES})")
    if compression == "zstd":
        records = _inflate(compressed, uncompressed_size)
    elif compression == "":
        records = bytes(compressed)
    else:
        raise ValueError(f"unsupported compression {compression!r}")
    if len(records) != uncompressed_size or (crc and zlib.crc32(records) != crc):
        raise ValueError("size or CRC of the decompressed records does not match")
    if require_crc:  # recovering a chunk with a damaged header: its bytes must fit exactly
        if not crc:
            raise ValueError("no CRC to confirm the chunk")
        if compression == "zstd":
            stream = zstandard.ZstdDecompressor().decompressobj()
            stream.decompress(compressed)  # the frame is known good: its size is bounded
            if stream.unused_data:
                raise ValueError(f"{len(stream.unused_data)} bytes after the zstd frame")
    return start_ns, end_ns, records


def _read_chunk(body: bytes, offset: int, c: _Collector,
                decoded: Future[tuple[int, int, bytes]] | None = None) -> None:
    """One chunk record; ``decoded``: :func:`_decode_chunk` of ``body``, started already."""
    try:
        start_ns, end_ns, records = (decoded.result() if decoded is not None
                                     else _decode_chunk(body))
    except _DAMAGE as err:
        start_ns, end_ns = struct.unpack_from("<QQ", body) if len(body) >= 16 else (0, 0)
        c.chunks_damaged += 1
        c.lost.append(LostRegion(offset, 9 + len(body), "damaged chunk", start_ns, end_ns))
        c.warnings.append(f"chunk at byte {offset} (log time {start_ns}…{end_ns} ns) is damaged "
                          f"and was skipped ({type(err).__name__}: {err})")
        return
    _read_chunk_records(records, offset, start_ns, end_ns, c)


#: A record's opcode and length; a message record's fields before its payload.
_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time
#: A message's log time: after its channel (u16) and sequence (u32).
_LOG_TIME, _LOG_TIME_AT = struct.Struct("<Q"), 6
_LOG_TIME_END = _LOG_TIME_AT + _LOG_TIME.size


def _read_chunk_records(records: bytes, offset: int, start_ns: int, end_ns: int,
                        c: _Collector) -> None:
    c.chunks_read += 1
    first_ns, last_ns = None, None  # the messages' own times: the CRC covers them, not the header
    pos, size = 0, len(records)
    view = memoryview(records)
    head, message_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    # Messages are parsed here, inline: the per-record calls cost more than the bytes.
    while pos + 9 <= size:
        opcode, length = head(records, pos)
        end = pos + 9 + length
        if end > size:
            break
        whole = opcode == OP_MESSAGE and length >= _MESSAGE_HEAD.size
        log_ns = None
        if whole:
            channel, sequence, log_ns, publish_ns = message_head(records, pos + 9)
        elif opcode == OP_MESSAGE and length >= _LOG_TIME_END:  # cut short after its time
            (log_ns,) = _LOG_TIME.unpack_from(records, pos + 9 + _LOG_TIME_AT)
        if log_ns is not None:
            if first_ns is None or log_ns < first_ns:
                first_ns = log_ns
            if last_ns is None or log_ns > last_ns:
                last_ns = log_ns
        if whole:
            assert log_ns is not None
            _message(channel, sequence, log_ns, publish_ns,
                     view[pos + 9 + _MESSAGE_HEAD.size:end], c)
        else:  # another record, or a message too short for its fields: _read_record says so
            _read_record(opcode, view[pos + 9:end], c)
        pos = end
    c.good_chunks[offset] = ((start_ns, end_ns) if first_ns is None or last_ns is None
                             else (int(first_ns), int(last_ns)))
    if pos != len(records):
        c.warnings.append(f"chunk at byte {offset}: its records end {len(records) - pos} bytes "
                          "early; the rest was skipped")


def _message(channel: int, sequence: int, log_time: int, publish_time: int,
             payload: bytes | memoryview, c: _Collector) -> None:
    """One message record (its fields parsed): counted, then decoded or handed on."""
    info = c.channel_info.get(channel)
    if info is not None:
        info.messages += 1
        if info.first_ns is None or log_time < info.first_ns:
            info.first_ns = log_time
        if info.last_ns is None or log_time > info.last_ns:
            info.last_ns = log_time
    if c.generic:
        if info is None:
            c.unknown_channels[channel] += 1
        elif c.on_message is not None:
            c.on_message(channel, sequence, log_time, publish_time, bytes(payload))
        return
    _read_message(channel, sequence, log_time, payload, c)


def _read_record(opcode: int, body: bytes | memoryview, c: _Collector) -> None:
    buf = _Buffer(body)
    if opcode == OP_MESSAGE:
        channel, sequence, log_time, publish_time = buf.u16(), buf.u32(), buf.u64(), buf.u64()
        _message(channel, sequence, log_time, publish_time, memoryview(body)[buf.pos:], c)
    elif opcode == OP_CHANNEL:
        channel, schema_id = buf.u16(), buf.u16()
        topic = buf.string()
        c.channels[channel] = topic
        if channel not in c.channel_info:
            encoding = buf.string()
            c.channel_info[channel] = McapChannel(channel, schema_id, topic, encoding,
                                                  buf.string_map())
    elif opcode == OP_SCHEMA:
        schema_id, name, encoding = buf.u16(), buf.string(), buf.string()
        c.schemas.setdefault(schema_id, McapSchema(schema_id, name, encoding,
                                                   buf.raw(buf.u32())))
    elif opcode == OP_ATTACHMENT:
        log_time, create_time = buf.u64(), buf.u64()
        name, media_type = buf.string(), buf.string()
        payload = buf.raw(buf.u64())
        (crc,) = struct.unpack_from("<I", body, buf.pos)
        if crc and zlib.crc32(bytes(body[:buf.pos])) != crc:
            raise ValueError(f"attachment {name!r}: CRC mismatch")
        c.attachments.append(McapAttachment(log_time, create_time, name, media_type, payload))
    elif opcode == OP_METADATA:
        name = buf.string()
        values = buf.string_map()
        _check_consumed(buf)
        c.metadata[name] = values
        if name == CHANNELS_METADATA:
            c.fallback_channels = {int(k): v for k, v in values.items()}
    elif opcode == OP_HEADER:
        c.profile, c.library = buf.string(), buf.string()
        _check_consumed(buf)
        if c.generic:
            return
        if c.profile in ("ros1", "ros2"):
            raise RecordingError(f"is a ROS {c.profile[-1]} bag (MCAP storage), not a scanpipe "
                                 "recording; convert it with: scanpipe import-bag BAG --out "
                                 "REC.mcap")
        if c.profile != PROFILE:
            c.warnings.append(f"MCAP profile {c.profile!r}: not written by scanpipe "
                              f"(expected {PROFILE!r}); reading what is recognisable")


def _check_consumed(buf: _Buffer) -> None:
    if buf.pos != len(buf.data):
        raise ValueError(f"{len(buf.data) - buf.pos} bytes after the record's fields")


def _read_message(channel: int, sequence: int, log_time: int, data: bytes | memoryview,
                  c: _Collector) -> None:
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
        elif topic == SCANNER_PROFILES:
            p = schemas.Profile.FromString(data)
            c.profiles.append(DecodedProfile(
                log_time, int(p.device_time_ns), int(p.device_end_time_ns), int(p.frame),
                float(p.start_angle_deg), float(p.step_deg),
                np.array(p.ranges_m, np.float32), np.array(p.intensities, np.float32)))
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


def _motor_states(motor_rows: list[tuple[int, int, int, bool, int]]) -> MotorStates:
    """The motor state reports as columns in log-time order."""
    rows = sorted(motor_rows, key=lambda r: r[0])
    return MotorStates(
        log_time_ns=np.array([r[0] for r in rows], np.int64),
        step_count=np.array([r[1] for r in rows], np.int64),
        target_step_count=np.array([r[2] for r in rows], np.int64),
        moving=np.array([r[3] for r in rows], np.bool_),
        device_time_us=np.array([r[4] for r in rows], np.uint64).astype(np.int64),
    )


def _summary_chunks(data: mmap.mmap, size: int) -> list[tuple[int, int, int]] | None:
    """(offset, start_ns, end_ns) of every chunk the summary section indexes, or None when the
    file has no summary or its CRC does not confirm it."""
    footer = size - len(MAGIC) - 29
    if footer <= len(MAGIC) or data[size - len(MAGIC):size] != MAGIC or data[footer] != OP_FOOTER:
        return None
    summary_start, _, crc = struct.unpack_from("<QQI", data, footer + 9)
    if not crc or not len(MAGIC) < summary_start <= footer:
        return None
    if zlib.crc32(data[summary_start:footer + 9 + 16]) != crc:
        return None
    chunks = []
    pos = summary_start
    try:
        while pos + 9 <= footer:
            opcode = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            if opcode == OP_CHUNK_INDEX:
                start_ns, end_ns, offset = struct.unpack_from("<QQQ", data, pos + 9)
                chunks.append((int(offset), int(start_ns), int(end_ns)))
            pos += 9 + length
    except struct.error:
        return None
    return chunks


def _chunk_headers(data: mmap.mmap, start: int, end: int) -> int:
    """How many zstd chunk headers a lost stretch holds (a compression field with a chunk
    opcode where it belongs; chunk indexes in the summary have the field too)."""
    count, pos = 0, data.find(_ZSTD_FIELD, start, end)
    while pos >= 0:
        at = pos - 9 - _CHUNK_FIXED_BYTES
        count += at >= start and data[at] == OP_CHUNK
        pos = data.find(_ZSTD_FIELD, pos + 1, end)
    return count


_ZSTD_FIELD = b"\x04\x00\x00\x00zstd"


def _union_ns(spans: list[tuple[int, int]]) -> int:
    """Total length of the union of [start, end] log time spans."""
    total, reach = 0, None
    for start, end in sorted(s for s in spans if s[1] >= s[0]):
        if reach is None or start > reach:
            total += end - start
            reach = end
        elif end > reach:
            total += end - reach
            reach = end
    return total


def _loss(data: mmap.mmap, size: int, c: _Collector) -> RecordingLoss:
    """Count what was lost (see :class:`RecordingLoss`)."""
    lost_bytes = sum(r.length for r in c.lost)
    indexed = _summary_chunks(data, size)
    if indexed is not None:
        missing = [(s, e) for offset, s, e in indexed if offset not in c.good_chunks]
        return RecordingLoss(len(missing), lost_bytes, _union_ns(missing), True, tuple(c.lost))
    # No usable summary: bound each lost stretch by the intact chunks on either side.
    good = sorted(c.good_chunks.items())
    offsets = [offset for offset, _ in good]
    spans: list[tuple[int, int]] = []
    chunks = 0
    for region in c.lost:
        found = 1 if region.reason == "damaged chunk" else _chunk_headers(
            data, region.offset, region.offset + region.length)
        if not found:
            continue
        chunks += found
        index = bisect.bisect_left(offsets, region.offset)
        before = good[index - 1][1][1] if index > 0 else None
        after = good[index][1][0] if index < len(good) else None
        start = before if before is not None else region.start_ns
        end = after if after is not None else region.end_ns
        if start is not None and end is not None and 0 <= end - start < _MAX_LOST_SPAN_NS:
            spans.append((start, end))
    return RecordingLoss(chunks, lost_bytes, _union_ns(spans), False, tuple(c.lost))


#: A lost stretch claiming more log time than this has damaged times: its time is not counted.
_MAX_LOST_SPAN_NS = 3600 * 10**9


def _assemble(path: Path, c: _Collector, bytes_read: int, size: int,
              loss: RecordingLoss) -> Recording:
    warnings = list(c.warnings)
    if loss.any:
        bound = "" if loss.from_summary else "at least "
        if loss.chunks:
            warnings.append(f"lost {bound}{loss.chunks} chunks, {loss.bytes} bytes and "
                            f"{bound}{loss.time_s:.3f} s of log time to damage or a cut")
        else:
            warnings.append(f"lost {loss.bytes} bytes to damage or a cut, outside any chunk "
                            "found (index or summary records)")
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
    motor = _motor_states(c.motor_rows)
    return Recording(
        path=path, profile=c.profile, library=c.library, metadata=c.metadata, streams=streams,
        motor=motor, images=sorted(c.images, key=lambda i: (i.camera_id, i.log_time_ns)),
        events=sorted(c.events, key=lambda e: e.log_time_ns), message_counts=dict(c.counts),
        warnings=warnings, complete=c.complete, bytes_read=bytes_read, file_size=size,
        chunks_read=c.chunks_read, chunks_damaged=c.chunks_damaged, loss=loss,
        profiles=sorted(c.profiles, key=lambda p: (p.log_time_ns, p.frame)),
    )


class RecordingTail:
    """Reads a recording while its writer is still appending to it (``scanpipe run --follow``).

    Each :meth:`poll` parses the records that have become complete since the last one, with the
    same record functions and in the same order as :func:`read_recording`, so once the data end
    record is read :meth:`recording` is exactly what :func:`read_recording` returns for the
    finished file. The tail never guesses: a record that does not check out (damage, an unknown
    opcode) stops it where it is (:attr:`stuck`), and the caller reads the finished file with
    :func:`read_recording` instead, which handles damage.

    ``handle`` is an open binary file, read through its descriptor, so the tail keeps reading
    the same file when it is renamed into place (``scanpipe simulate`` writes a temporary name).
    """

    def __init__(self, path: Path, handle: IO[bytes]) -> None:
        self.path = Path(path)
        self._fd = handle.fileno()
        self._collector = _Collector()
        self.position = 0  # the offset of the first record not yet parsed
        self.bytes_read = 0  # where the batch reader would stop (after the data end record)
        self.stuck: str | None = None
        self._taken: dict[tuple[str, int], int] = defaultdict(int)

    @property
    def complete(self) -> bool:
        """Whether the data end record has been read (the writer finished)."""
        return self._collector.complete

    @property
    def size(self) -> int:
        """The file's size now, in bytes."""
        return os.fstat(self._fd).st_size

    @property
    def warnings(self) -> list[str]:
        """What the record functions noted so far (a damaged chunk …)."""
        return list(self._collector.warnings)

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """The metadata records read so far (the rig, the session)."""
        return self._collector.metadata

    @property
    def motor_states(self) -> int:
        """Motor state reports read so far."""
        return len(self._collector.motor_rows)

    def event_kinds(self) -> list[str]:
        """The kinds of the events read so far, in the order read."""
        return [e.kind for e in self._collector.events]

    def snapshot(self) -> Recording:
        """What has been read so far, as a :class:`Recording` (its loss not counted: the file is
        not finished)."""
        return _assemble(self.path, self._collector, self.position, self.size, RecordingLoss())

    def motor(self) -> MotorStates:
        """The motor state reports read so far, in log-time order."""
        return _motor_states(self._collector.motor_rows)

    def new_stream_parts(self, link: str, direction: int) -> list[tuple[int, int, bytes]]:
        """``(seq, log time, bytes)`` of one link's chunks read since the last call."""
        parts = self._collector.stream_parts.get((link, direction), [])
        start = self._taken[(link, direction)]
        self._taken[(link, direction)] = len(parts)
        return parts[start:]

    def poll(self) -> bool:
        """Parse every record completed since the last poll; True when any was parsed."""
        if self.complete or self.stuck is not None:
            return False
        size = self.size
        if size <= max(self.position, len(MAGIC)):
            return False
        with mmap.mmap(self._fd, size, access=mmap.ACCESS_READ) as data:
            if self.position == 0:
                if data[:len(MAGIC)] != MAGIC:
                    raise RecordingError(f"{self.path}: {_not_mcap(bytes(data[:16]))}")
                self.position = len(MAGIC)
            start = self.position
            try:
                self._parse(data, size)
            except RecordingError as err:  # a ROS bag's header: the batch reader's message
                raise RecordingError(f"{self.path}: {err}") from None
            return self.position > start

    def _parse(self, data: mmap.mmap, size: int) -> None:
        c, pos = self._collector, self.position
        while pos + 9 <= size:
            opcode = data[pos]
            (length,) = struct.unpack_from("<Q", data, pos + 1)
            if opcode not in KNOWN_OPCODES:
                self.stuck = f"unknown record opcode {opcode:#04x} at byte {pos}"
                break
            end = pos + 9 + length
            if end > size:
                break  # the record is still being written
            if opcode in (OP_DATA_END, OP_FOOTER):
                if length != _END_LENGTHS[opcode]:
                    self.stuck = f"end record at byte {pos} has a wrong length ({length})"
                    break
                c.complete = True
                self.bytes_read = end
                pos = end
                break
            if opcode == OP_CHUNK:
                if _chunk_end(data, pos, size, check_length=True) is None:
                    self.stuck = f"chunk at byte {pos}: its length field does not match"
                    break
            elif not _next_record_complete(data, end, size):
                break  # the next record confirms this one's length: wait for it
            elif _chunk_end(data, pos, size, check_length=True) is not None or \
                    not _length_confirmed(data, pos, opcode, length, size):
                self.stuck = f"record {opcode:#04x} at byte {pos}: its length is not confirmed"
                break
            body = data[pos + 9:end]
            try:
                if opcode == OP_CHUNK:
                    _read_chunk(body, pos, c)
                else:
                    _read_record(opcode, body, c)
            except _DAMAGE as err:
                self.stuck = f"record {opcode:#04x} at byte {pos} is damaged ({err})"
                break
            pos = end
        self.position = pos

    def recording(self) -> Recording:
        """The whole recording, as :func:`read_recording` reads the finished file; only once
        :attr:`complete` and not :attr:`stuck`."""
        if not self.complete or self.stuck is not None:
            raise RecordingError(f"{self.path}: the tail has not read the whole recording "
                                 "(read the finished file instead)")
        size = self.size
        with mmap.mmap(self._fd, size, access=mmap.ACCESS_READ) as data:
            loss = _loss(data, size, self._collector)
        return _assemble(self.path, self._collector, self.bytes_read, size, loss)


def _next_record_complete(data: mmap.mmap, pos: int, size: int) -> bool:
    """Whether the record starting at ``pos`` is wholly in the file (by its length field)."""
    if pos + 9 > size:
        return False
    (length,) = struct.unpack_from("<Q", data, pos + 1)
    return bool(length <= size - pos - 9)


def writer_finished(handle: IO[bytes]) -> bool:
    """Whether an open recording ends as a finished MCAP file does (the closing magic bytes
    after the footer): its writer closed it."""
    try:
        size = os.fstat(handle.fileno()).st_size
        return size >= 2 * len(MAGIC) and os.pread(handle.fileno(), len(MAGIC),
                                                   size - len(MAGIC)) == MAGIC
    except OSError:
        return False
