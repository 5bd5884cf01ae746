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

An 8-bit XOR passes one random frame in 256, so a frame whose checksum passes is not trusted on
that alone (``confirm=True``, the default). It must also parse (``parse``: a sample count that
disagrees with the length is :class:`LengthMismatch`), hold values the device can send
(``check``: :class:`ImplausibleFrame`), and must not look like a cut frame that swallowed an
intact one. That last danger exists only when a *viable* marker (a marker followed by an
in-bounds length) begins inside the frame's span; then the frame is rejected when

- the bytes right after it are not a start marker (a cut frame's claimed end lands inside
  the data of what follows), or
- its counter (``check``'s return value: frame number, profile count) steps backwards modulo
  ``counter_period``, or
- a complete frame with a good checksum that parses and passes ``check`` lies inside its span
  (the cut frame's claimed end happens to fall on a frame boundary).

A rejected frame is a false start: decoding resumes one byte past its marker, so the frame it
swallowed is still found. Deciding needs the 7 bytes after a frame (a marker and a length),
so a frame that ends within 7 bytes of the data fed so far is held until more bytes arrive or
the stream ends (at the end, the end of the stream counts as a start marker).
``confirm=False`` hands frames out at once with the checksum as the only test: for
request/reply links where a reply is the last thing sent and nothing follows it.

Bulk: a run of frames that follow each other back to back, with no start marker inside any of
them, needs none of the checks above but the checksum, ``parse`` and ``check``. When the
dialect gives ``parse_many`` (all payloads of such a run parsed at once, vectorised; a payload
it cannot vouch for is ``NOT_PARSED``), the reader checksums the run at once and hands out its
frames up to the first one that is not clean; that frame goes through the frame-by-frame path
above. The frames and counters are the same either way.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ProtocolError

HEADER_BYTES = 8  # marker + u32 length
_LENGTH = struct.Struct(">I")
TRAILER_BYTES = 1  # XOR checksum
# A marker beginning in a frame's last byte ends its length field 7 bytes past the frame.
_LOOKAHEAD_BYTES = HEADER_BYTES - 1
#: ``RawFrame.parsed`` of a frame the reader did not parse (no callback, or a bad checksum).
NOT_PARSED: Any = object()
#: Default cap on a payload length field; larger lengths are false starts.
DEFAULT_MAX_PAYLOAD_BYTES = 1 << 18
#: Runs shorter than this go frame by frame (numpy's set-up cost outweighs the bulk gain).
BULK_MIN_FRAMES = 4
#: The longest run vetted at once (its arrays stay cache-sized: ~10 % faster than 1024). A run
#: that stops early (a damaged frame) halves the next one's limit, a clean one doubles it, so
#: damage costs little wasted work.
BULK_MAX_FRAMES = 128


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


class LengthMismatch(ProtocolError):
    """A frame whose declared counts (samples, points) disagree with its payload length."""


class ImplausibleFrame(ProtocolError):
    """A frame that parses but holds values the device cannot send (angles, sizes)."""


class UnsupportedVariant(ProtocolError):
    """A sound frame of a variant scanpipe does not read (a multi-layer scanner's telegram):
    raised through the readers to the caller, never counted as damage and skipped — decoding
    the rest would be a silent misreading."""


@dataclass
class FrameCounters:
    """What a reader saw: frames, checksum failures, resyncs, skipped bytes, odd frames.

    ``length_mismatches`` counts frames whose declared sample count disagrees with their
    length; ``implausible_frames`` counts frames whose checksum passed but that failed the
    other checks (values out of the device's range, a cut frame that swallowed another: see the
    module docstring). Both are false starts, so each also counts one resync.
    """

    frames_decoded: int = 0
    checksum_failures: int = 0
    resyncs: int = 0
    bytes_skipped: int = 0
    malformed_frames: int = 0
    other_frames: int = 0
    length_mismatches: int = 0
    implausible_frames: int = 0

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


#: ``check(parsed)``: raises :class:`ImplausibleFrame` (or another :class:`ProtocolError`) for a
#: parsed frame the device cannot have sent; returns the frame's counter, or None if it has none.
FrameCheck = Callable[[Any], "int | None"]
#: ``parse_many(payloads, block, starts)``: what ``parse(payload, True)`` returns for each
#: payload, or ``NOT_PARSED`` where it cannot vouch for that (the reader then parses it on its
#: own). ``block`` holds the same bytes (payload ``i`` from ``starts[i]``), read in place: the
#: payloads are not joined again.
ParseMany = Callable[[list[bytes], NDArray[np.uint8], NDArray[np.intp]], list[Any]]


class FrameReader:
    """Cuts frames out of a byte stream fed in chunks of any size (see the module docstring).

    ``parse(payload, checksum_ok)`` tells a frame of the dialect from a frame-shaped accident:
    a frame with a good checksum for which it raises :class:`ProtocolError` is counted
    (:class:`LengthMismatch` as a length mismatch, others as malformed) and treated as a false
    start; what it returns is kept in ``RawFrame.parsed``. ``check(parsed)`` then vets the
    values and gives the frame's counter (see :data:`FrameCheck`). ``confirm`` turns on the
    checks beyond the XOR (module docstring). ``counters.frames_decoded`` is left to the
    caller (it knows which frames it could use). ``parse_many`` (with ``parse``) vets runs of
    back-to-back frames in bulk (module docstring).
    """

    def __init__(self, marker: bytes, min_payload_bytes: int = 0,
                 max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
                 parse: Callable[[bytes, bool], Any] | None = None,
                 check: FrameCheck | None = None, confirm: bool = True,
                 counter_period: int = 1 << 16, parse_many: ParseMany | None = None) -> None:
        if len(marker) != 4:
            raise ProtocolError(f"start marker {marker!r}: must be 4 bytes")
        if not 0 <= min_payload_bytes <= max_payload_bytes:
            raise ProtocolError(f"payload bounds {min_payload_bytes}…{max_payload_bytes}: "
                                "need 0 ≤ min ≤ max")
        if counter_period < 2:
            raise ProtocolError(f"counter period {counter_period}: must be ≥ 2")
        self.marker = marker
        self.min_payload_bytes = min_payload_bytes
        self.max_payload_bytes = max_payload_bytes
        self.parse = parse
        self.check = check
        self.confirm = confirm
        self.counter_period = counter_period
        self.parse_many = parse_many if parse is not None else None
        self._bulk_limit = 64
        self.counters = FrameCounters()
        self._buffer = bytearray()
        self._base = 0  # stream offset of _buffer[0]
        self._last_counter: int | None = None

    @property
    def offset(self) -> int:
        """Stream offset of the first byte not yet consumed."""
        return self._base

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[RawFrame]:
        """Add bytes; return every frame they complete (and confirm)."""
        self._buffer += chunk
        return self._scan(final=False)

    def finish(self) -> list[RawFrame]:
        """End of stream: resolve held and incomplete frames, skip the tail."""
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
            if self.parse_many is not None:
                bulk, pos = self._bulk(buf, start, final)
                if bulk:
                    frames += bulk
                    continue
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
            # The checks below read a marker and a length up to 7 bytes past the frame.
            if self.confirm and not final and end + _LOOKAHEAD_BYTES > size:
                break
            payload = bytes(buf[start + HEADER_BYTES:end - 1])
            computed = xor_checksum(payload)
            received = buf[end - 1]
            parsed: Any = NOT_PARSED
            if computed != received:
                # A marker starting inside the span means an intact frame may begin there.
                search_end = end + len(marker) - 1
                if search_end > size and not final:
                    break
                if buf.find(marker, start + 1, search_end) >= 0:
                    self._false_start()
                    pos = start + 1
                    continue
                self.counters.checksum_failures += 1
            else:
                try:
                    parsed = self._vet(buf, start, end, payload, final)
                except LengthMismatch:
                    self.counters.length_mismatches += 1
                    self._false_start()
                    pos = start + 1
                    continue
                except ImplausibleFrame:
                    self.counters.implausible_frames += 1
                    self._false_start()
                    pos = start + 1
                    continue
                except UnsupportedVariant:
                    raise
                except ProtocolError:
                    self.counters.malformed_frames += 1
                    self._false_start()
                    pos = start + 1
                    continue
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

    def _bulk(self, buf: bytearray, start: int, final: bool) -> tuple[list[RawFrame], int]:
        """The clean frames of the back-to-back run at ``start`` (module docstring) and where
        the run stopped; none when the run is shorter than :data:`BULK_MIN_FRAMES`."""
        assert self.parse_many is not None
        marker, size = self.marker, len(buf)
        low, high = max(self.min_payload_bytes, 1), self.max_payload_bytes
        # a frame the frame-by-frame path would hold for its look-ahead is held here too
        need = _LOOKAHEAD_BYTES if self.confirm and not final else 0
        spans: list[tuple[int, int]] = []
        at = start
        while (len(spans) < self._bulk_limit and at + HEADER_BYTES <= size
               and buf.startswith(marker, at)):
            (length,) = _LENGTH.unpack_from(buf, at + 4)
            end = at + HEADER_BYTES + length + TRAILER_BYTES
            if not low <= length <= high or end + need > size:
                break
            # a marker inside: the frame-by-frame checks decide
            if buf.find(marker, at + 1, end + len(marker) - 1) >= 0:
                break
            spans.append((at, end))
            at = end
        if len(spans) < BULK_MIN_FRAMES:
            return [], start
        payloads = [bytes(buf[a + HEADER_BYTES:b - 1]) for a, b in spans]
        # the run's bytes in place (a view of the buffer: released before it is resized)
        block = np.frombuffer(buf, np.uint8, spans[-1][1] - start, start)
        bounds = np.array(spans, np.intp) - start
        bounds[:, 0] += HEADER_BYTES
        bounds[:, 1] -= TRAILER_BYTES
        # XOR over [payload start, payload end) of each frame: every other reduceat segment
        computed = np.bitwise_xor.reduceat(block, bounds.ravel())[::2].tolist()
        received = [buf[b - 1] for _, b in spans]
        good = next((i for i, (c, r) in enumerate(zip(computed, received, strict=True))
                     if c != r), len(spans))
        parsed_all = (self.parse_many(payloads[:good], block, bounds[:good, 0])
                      if good >= BULK_MIN_FRAMES else [])
        del block
        frames: list[RawFrame] = []
        for (a, b), payload, parsed, checksum in zip(spans, payloads, parsed_all, received,
                                                     strict=False):
            if parsed is NOT_PARSED:
                break
            if self.check is not None:
                try:
                    counter = self.check(parsed)
                except ProtocolError:
                    break  # the frame-by-frame path counts it
                if counter is not None:
                    self._last_counter = counter
            frames.append(RawFrame(payload, True, checksum, checksum, self._base + a,
                                   self._base + b, parsed))
        if len(frames) == len(spans):
            self._bulk_limit = min(2 * self._bulk_limit, BULK_MAX_FRAMES)
        else:
            self._bulk_limit = max(self._bulk_limit // 2, 2 * BULK_MIN_FRAMES)
        return frames, (spans[len(frames) - 1][1] if frames else start)

    def _vet(self, buf: bytearray, start: int, end: int, payload: bytes, final: bool) -> Any:
        """Parse and check a frame whose checksum passed; what ``parse`` returned, or raise."""
        parsed: Any = NOT_PARSED
        counter = None
        if self.parse is not None:
            parsed = self.parse(payload, True)
            if self.check is not None:
                counter = self.check(parsed)
        if self.confirm:
            self._confirm(buf, start, end, counter, final)
        if counter is not None:
            self._last_counter = counter
        return parsed

    def _confirm(self, buf: bytearray, start: int, end: int, counter: int | None,
                 final: bool) -> None:
        """Raise :class:`ImplausibleFrame` if the frame at ``start`` looks like a cut frame that
        swallowed an intact one (module docstring)."""
        marker = self.marker
        inner = self._viable_markers(buf, start + 1, end)
        if not inner:
            return
        after = bytes(buf[end:end + len(marker)])
        # At the end of the stream, the end (or a cut marker) counts as a start marker.
        followed = after == marker or (final and marker.startswith(after))
        if not followed:
            raise ImplausibleFrame(f"frame at byte {self._base + start}: no start marker "
                                   "after it, and a marker inside it")
        last = self._last_counter
        if counter is not None and last is not None:
            back = (last - counter) % self.counter_period
            if 0 < back < self.counter_period // 2:
                raise ImplausibleFrame(f"frame at byte {self._base + start}: counter {counter} "
                                       f"steps back from {last}, and a marker inside it")
        for inner_start in inner:
            if self._valid_frame_within(buf, inner_start, end):
                raise ImplausibleFrame(f"frame at byte {self._base + start}: holds a whole "
                                       f"frame at byte {self._base + inner_start}")

    def _viable_markers(self, buf: bytearray, begin: int, end: int) -> list[int]:
        """Markers beginning in ``[begin, end)`` (they may run past ``end``) followed by an
        in-bounds length, or too near the data's end to tell."""
        marker, found = self.marker, []
        limit = min(end + len(marker) - 1, len(buf))  # the whole stream is here at the end
        at = buf.find(marker, begin, limit)
        while at >= 0:
            if at + HEADER_BYTES > len(buf):
                found.append(at)
            else:
                (length,) = _LENGTH.unpack_from(buf, at + 4)
                if self.min_payload_bytes <= length <= self.max_payload_bytes:
                    found.append(at)
            at = buf.find(marker, at + 1, limit)
        return found

    def _valid_frame_within(self, buf: bytearray, start: int, limit: int) -> bool:
        """Whether a whole frame with a good checksum that parses and passes ``check`` begins
        at ``start`` and ends by ``limit``."""
        if start + HEADER_BYTES > limit:
            return False
        (length,) = _LENGTH.unpack_from(buf, start + 4)
        end = start + HEADER_BYTES + length + TRAILER_BYTES
        if not self.min_payload_bytes <= length <= self.max_payload_bytes or end > limit:
            return False
        payload = bytes(buf[start + HEADER_BYTES:end - 1])
        if xor_checksum(payload) != buf[end - 1]:
            return False
        if self.parse is not None:
            try:
                parsed = self.parse(payload, True)
                if self.check is not None:
                    self.check(parsed)
            except UnsupportedVariant:
                raise
            except ProtocolError:
                return False
        return True

    def _false_start(self) -> None:
        self.counters.resyncs += 1
        self.counters.bytes_skipped += 1
