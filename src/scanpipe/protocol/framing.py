"""``marker, u32 big-endian length, payload, XOR of the payload`` framing, with resync.

Both scanner dialects frame this way and differ only in the 4-byte start marker (the paper's
``02 02 02 02``, the LD-OEM's ``02 'U' 'S' 'P'``). :class:`FrameReader` takes bytes in chunks
of any size and hands back whole frames. Its decisions depend only on complete data, so any
split of a stream gives the same frames:

- bytes before a start marker are skipped;
- a length below the dialect's minimum or above the cap is a false start: resync, i.e. move one
  byte past the marker and search again (never allocate from an unchecked length);
- a frame whose checksum fails and within whose span another start marker begins is a false
  start too (resync), so garbage that claims a length never swallows an intact frame after it;
- a frame whose checksum fails with no marker inside is a damaged frame: a checksum failure,
  returned with ``checksum_ok=False`` (the caller decides whether to keep it);
- at the end of the stream (:meth:`FrameReader.finish`) an incomplete frame is a false start.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from scanpipe.errors import ProtocolError

HEADER_BYTES = 8  # marker + u32 length
_LENGTH = struct.Struct(">I")
TRAILER_BYTES = 1  # XOR checksum
#: ``RawFrame.parsed`` of a frame the reader did not parse (no callback, or a bad checksum).
NOT_PARSED: Any = object()
#: Default cap on a payload length field; larger lengths are false starts.
DEFAULT_MAX_PAYLOAD_BYTES = 1 << 18


def xor_checksum(data: bytes | bytearray | memoryview) -> int:
    """The XOR of all bytes (0 for no bytes)."""
    view = np.frombuffer(data, dtype=np.uint8)
    if view.size == 0:
        return 0
    return int(np.bitwise_xor.reduce(view))


def encode_frame(marker: bytes, payload: bytes) -> bytes:
    """One frame: ``marker``, the payload length (u32 big-endian), the payload, its XOR."""
    if len(payload) > 0xFFFFFFFF:
        raise ProtocolError(f"payload of {len(payload)} bytes does not fit a u32 length")
    return (marker + len(payload).to_bytes(4, "big") + payload
            + bytes([xor_checksum(payload)]))


@dataclass
class FrameCounters:
    """What a reader saw: frames, checksum failures, resyncs, skipped bytes, odd frames."""

    frames_decoded: int = 0
    checksum_failures: int = 0
    resyncs: int = 0
    bytes_skipped: int = 0
    malformed_frames: int = 0
    other_frames: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain data for reports and ``--json``."""
        return asdict(self)


@dataclass(frozen=True)
class RawFrame:
    """One frame cut from a stream: payload, checksum verdict, and where it ended."""

    payload: bytes
    checksum_ok: bool
    received_checksum: int
    computed_checksum: int
    start_offset: int
    end_offset: int  # stream offset one past the frame's last byte
    parsed: Any = None  # what the reader's parse callback returned, or NOT_PARSED


class FrameReader:
    """Cuts frames out of a byte stream fed in chunks of any size (see the module docstring).

    ``parse(payload, checksum_ok)`` tells a frame of the dialect from a frame-shaped accident:
    a frame with a good checksum for which it raises :class:`ProtocolError` is counted as
    malformed and treated as a false start; what it returns is kept in ``RawFrame.parsed``.
    ``counters.frames_decoded`` is left to the caller (it knows which frames it could use);
    the reader counts checksum failures, resyncs, malformed frames and skipped bytes.
    """

    def __init__(self, marker: bytes, min_payload_bytes: int = 0,
                 max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
                 parse: Callable[[bytes, bool], Any] | None = None) -> None:
        if len(marker) != 4:
            raise ProtocolError(f"start marker {marker!r}: must be 4 bytes")
        if not 0 <= min_payload_bytes <= max_payload_bytes:
            raise ProtocolError(f"payload bounds {min_payload_bytes}…{max_payload_bytes}: "
                                "need 0 ≤ min ≤ max")
        self.marker = marker
        self.min_payload_bytes = min_payload_bytes
        self.max_payload_bytes = max_payload_bytes
        self.parse = parse
        self.counters = FrameCounters()
        self._buffer = bytearray()
        self._base = 0  # stream offset of _buffer[0]

    @property
    def offset(self) -> int:
        """Stream offset of the first byte not yet consumed."""
        return self._base

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[RawFrame]:
        """Add bytes; return every frame they complete."""
        self._buffer += chunk
        return self._scan(final=False)

    def finish(self) -> list[RawFrame]:
        """End of stream: resolve an incomplete frame as a false start, skip the tail."""
        frames = self._scan(final=True)
        self.counters.bytes_skipped += len(self._buffer)
        self._base += len(self._buffer)
        self._buffer.clear()
        return frames

    def _scan(self, final: bool) -> list[RawFrame]:
        buf, marker = self._buffer, self.marker
        frames: list[RawFrame] = []
        pos, size = 0, len(buf)
        while True:
            start = buf.find(marker, pos)
            if start < 0:
                # Keep a possible partial marker at the tail; the rest is garbage.
                keep = 0 if final else min(len(marker) - 1, size - pos)
                self.counters.bytes_skipped += size - keep - pos
                pos = size - keep
                break
            self.counters.bytes_skipped += start - pos
            pos = start
            if size - start < HEADER_BYTES:
                if final:
                    self._false_start()
                    pos = start + 1
                    continue
                break
            (length,) = _LENGTH.unpack_from(buf, start + 4)
            if not self.min_payload_bytes <= length <= self.max_payload_bytes:
                self._false_start()
                pos = start + 1
                continue
            end = start + HEADER_BYTES + length + TRAILER_BYTES
            if end > size:
                if final:
                    self._false_start()
                    pos = start + 1
                    continue
                break
            payload = bytes(buf[start + HEADER_BYTES:end - 1])
            computed = xor_checksum(payload)
            received = buf[end - 1]
            if computed != received:
                # A marker starting inside the span means an intact frame may begin there.
                search_end = end + len(marker) - 1
                if search_end > size and not final:
                    break
                if buf.find(marker, start + 1, search_end) >= 0:
                    self._false_start()
                    pos = start + 1
                    continue
            parsed: Any = NOT_PARSED
            if computed == received and self.parse is not None:
                try:
                    parsed = self.parse(payload, True)
                except ProtocolError:
                    self.counters.malformed_frames += 1
                    self._false_start()
                    pos = start + 1
                    continue
            if computed != received:
                self.counters.checksum_failures += 1
            frames.append(RawFrame(
                payload=payload,
                checksum_ok=computed == received,
                received_checksum=received,
                computed_checksum=computed,
                start_offset=self._base + start,
                end_offset=self._base + end,
                parsed=parsed,
            ))
            pos = end
        del buf[:pos]
        self._base += pos
        return frames

    def _false_start(self) -> None:
        self.counters.resyncs += 1
        self.counters.bytes_skipped += 1
