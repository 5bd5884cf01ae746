"""The scanner dialects by name, a stream decoder for any of them, and auto-detection.

>>> from scanpipe.protocol.registry import DIALECTS, StreamDecoder
>>> sorted(DIALECTS)
['cola_a', 'cola_b', 'ldoem', 'ldrobot', 'ldrobot_ld14', 'paper', 'scip']
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Literal, Protocol

from scanpipe.errors import ProtocolError
from scanpipe.protocol import ldoem, ldrobot, paper, scip, sick_cola
from scanpipe.protocol.framing import (
    NOT_PARSED,
    FrameCounters,
    FrameReader,
    LengthMismatch,
    ParseMany,
    RawFrame,
    UnsupportedVariant,
)
from scanpipe.protocol.profile import Profile, check_plausible

ChecksumMode = Literal["strict", "lenient"]
#: How many bytes auto-detection looks at: a first look, then a longer one if that finds nothing.
DETECT_BYTES = (1 << 16, 1 << 20)


class FrameSource(Protocol):
    """What a dialect's frame reader offers (:class:`~scanpipe.protocol.framing.FrameReader`
    for the shared ``marker, length, payload, XOR`` framing; a dialect with its own framing —
    text lines, fixed packets, STX…ETX — supplies a reader with the same three members through
    ``Dialect.reader_factory``): ``feed`` and ``finish`` return :class:`RawFrame` lists (with
    ``parsed`` set to the frame's profiles, or ``NOT_PARSED``), ``counters`` counts as the
    framing module does, resyncing one byte past a false start."""

    counters: FrameCounters

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[RawFrame]: ...
    def finish(self) -> list[RawFrame]: ...


def reader_warnings(reader: object) -> list[str]:
    """What a frame reader found doubtful about the stream it read (one line each; e.g. SCIP
    scans decoded before any PP reply gave the device's geometry). A reader reports them with
    a ``stream_warnings()`` method; readers without one have nothing to say."""
    report = getattr(reader, "stream_warnings", None)
    return [str(w) for w in report()] if callable(report) else []


#: ``reader_factory(dialect, max_payload_bytes, confirm)``: a fresh reader for a dialect with
#: its own framing.
ReaderFactory = Callable[["Dialect", int, bool], FrameSource]


@dataclass(frozen=True)
class Dialect:
    """One wire format: its name, start marker, encoder, payload decoder and frame limits.

    ``decode_payload(payload, checksum_ok)`` returns the profiles of a frame, None for a valid
    frame that carries no profile, or raises :class:`ProtocolError` (then a frame with a good
    checksum is a false start). ``check_frame(profiles)`` vets a decoded frame with a good
    checksum (``ImplausibleFrame``) and returns its counter (see ``framing.FrameCheck``).
    """

    name: str
    marker: bytes
    min_payload_bytes: int
    max_payload_bytes: int
    encode_profile: Callable[[Profile], bytes]
    decode_payload: Callable[[bytes, bool], list[Profile] | None]
    check_frame: Callable[[list[Profile] | None], int | None]
    description: str
    #: None: the shared framing (:class:`FrameReader` on ``marker``); else the dialect's own.
    reader_factory: ReaderFactory | None = None
    #: The device clock of its profiles: one tick in ns and where it wraps (16-bit ms default).
    device_tick_ns: int = 1_000_000
    device_wrap_ticks: int = 1 << 16
    #: None: count frames with a lenient decoder; else the dialect's own count of its frames
    #: in ``data`` for ``auto`` (a weak marker needs more than one good frame).
    detect_score: Callable[[bytes], int] | None = None
    #: Optional: ``decode_payload(p, True)`` of many payloads at once (see
    #: ``framing.FrameReader``'s ``parse_many``), for the shared framing.
    decode_payloads: ParseMany | None = None

    def frame_reader(self, max_payload_bytes: int | None = None,
                     confirm: bool = True) -> FrameSource:
        """A fresh frame reader for this dialect's framing (``confirm``: framing module)."""
        cap = self.max_payload_bytes if max_payload_bytes is None else max_payload_bytes
        if self.reader_factory is not None:
            return self.reader_factory(self, cap, confirm)
        return FrameReader(self.marker, self.min_payload_bytes, cap, self.decode_payload,
                           self.check_frame, confirm, parse_many=self.decode_payloads)

    def stream_decoder(self, checksum: ChecksumMode = "strict",
                       max_payload_bytes: int | None = None,
                       confirm: bool = True) -> StreamDecoder:
        """A fresh stream decoder (the decoder factory)."""
        return StreamDecoder(self, checksum, max_payload_bytes, confirm)

    def detect(self, data: bytes) -> bool:
        """Whether ``data`` holds at least one frame of this dialect (checksum aside)."""
        return _detect_score(self, data) > 0


def _no_payload(payload: bytes, checksum_ok: bool) -> list[Profile] | None:
    raise ProtocolError("ldrobot packets have no length-framed payload; use its own decoder")


DIALECTS: Mapping[str, Dialect] = {
    "paper": Dialect(
        name="paper",
        marker=paper.MARKER,
        min_payload_bytes=paper.HEADER_BYTES,
        max_payload_bytes=paper.MAX_PAYLOAD_BYTES,
        encode_profile=paper.encode_profile,
        decode_payload=paper.decode_payload,
        check_frame=paper.check_frame,
        description="the frame printed in the paper (02 02 02 02, SICK CoLa-B framing)",
    ),
    "ldoem": Dialect(
        name="ldoem",
        marker=ldoem.MARKER,
        min_payload_bytes=ldoem.MIN_PAYLOAD_BYTES,
        max_payload_bytes=ldoem.MAX_PAYLOAD_BYTES,
        encode_profile=ldoem.encode_profile,
        decode_payload=ldoem.decode_payload,
        check_frame=ldoem.check_frame,
        description="the SICK LD-OEM 1000 TCP protocol (02 'USP' framing, GET_PROFILE replies)",
    ),
    "cola_b": Dialect(
        name="cola_b",
        marker=sick_cola.MARKER,
        min_payload_bytes=4,
        max_payload_bytes=sick_cola.MAX_PAYLOAD_BYTES,
        encode_profile=sick_cola.encode_profile,
        decode_payload=sick_cola.decode_payload,
        check_frame=sick_cola.check_frame,
        description="SICK CoLa-B sSN LMDscandata (LMS1xx/5xx, TiM, LMS4000: 02 02 02 02 "
                    "framing)",
        device_tick_ns=sick_cola.TICK_NS,
        device_wrap_ticks=sick_cola.WRAP_TICKS,
        decode_payloads=sick_cola.decode_payloads,
    ),
    "cola_a": Dialect(
        name="cola_a",
        marker=b"\x02",
        min_payload_bytes=4,
        max_payload_bytes=sick_cola.MAX_PAYLOAD_BYTES * 3,
        encode_profile=sick_cola.encode_profile_ascii,
        decode_payload=sick_cola.decode_ascii,
        check_frame=sick_cola.check_frame,
        description="SICK CoLa-A sSN LMDscandata (ASCII hex tokens between STX and ETX)",
        reader_factory=sick_cola.ascii_reader,
        device_tick_ns=sick_cola.TICK_NS,
        device_wrap_ticks=sick_cola.WRAP_TICKS,
    ),
    "ldrobot": Dialect(
        name="ldrobot",
        marker=ldrobot.MARKER,
        min_payload_bytes=ldrobot.PACKET_BYTES,
        max_payload_bytes=ldrobot.PACKET_BYTES,
        encode_profile=ldrobot.encode_profile,
        decode_payload=_no_payload,
        check_frame=check_plausible,
        description="LDRobot LD06/LD19/STL-27L serial packets (54 2C, 47 bytes, CRC-8); a "
                    "profile is one head turn",
        reader_factory=lambda dialect, max_payload_bytes, confirm: ldrobot.RevolutionReader(),
        detect_score=ldrobot.detect_score,
        device_wrap_ticks=ldrobot.TIME_WRAP_MS,
    ),
    # The LD14/LD14P send the same packets: never detected from the bytes (they cannot tell
    # it), chosen by the rig's model (scanner_models: ld14, ld14p) or by name.
    "ldrobot_ld14": Dialect(
        name="ldrobot_ld14",
        marker=ldrobot.MARKER,
        min_payload_bytes=ldrobot.PACKET_BYTES,
        max_payload_bytes=ldrobot.PACKET_BYTES,
        encode_profile=ldrobot.encode_profile_sl,
        decode_payload=_no_payload,
        check_frame=check_plausible,
        description="LDRobot LD14/LD14P serial packets (the LD06's) with the SDK's "
                    "distance-dependent angle correction; a profile is one head turn",
        reader_factory=lambda dialect, max_payload_bytes, confirm: ldrobot.RevolutionReader(
            sl_correction=True),
        detect_score=lambda data: 0,
        device_wrap_ticks=ldrobot.TIME_WRAP_MS,
    ),
    "scip": Dialect(
        name="scip",
        marker=b"",
        min_payload_bytes=0,
        max_payload_bytes=scip.MAX_MESSAGE_BYTES,
        encode_profile=scip.encode_profile,
        decode_payload=scip.decode_payload,
        check_frame=scip.check_frame,
        description="Hokuyo SCIP 2.0 (URG/UST: MD/ME/MS streams, GD/GE/GS scans)",
        reader_factory=scip.reader_factory,
        device_tick_ns=1_000_000,
        device_wrap_ticks=scip.TIMESTAMP_WRAP_MS,
    ),
}


def get_dialect(name: str) -> Dialect:
    """The dialect called ``name``; :class:`ProtocolError` naming the known ones otherwise."""
    if name not in DIALECTS:
        raise ProtocolError(f"dialect {name!r}: unknown; allowed: {', '.join(DIALECTS)}, auto")
    return DIALECTS[name]


@dataclass(frozen=True)
class DecodedFrame:
    """The profiles of one frame, where it lay in the stream, and its checksum bytes."""

    profiles: list[Profile]
    start_offset: int
    end_offset: int
    checksum_ok: bool
    received_checksum: int
    computed_checksum: int


class StreamDecoder:
    """Bytes in (chunks of any size), profiles out, with counters.

    ``checksum="strict"`` drops frames whose checksum fails (they are counted);
    ``"lenient"`` returns their profiles with ``checksum_ok=False``. Frames whose checksum
    passes are checked further (``confirm``, on by default: see :mod:`scanpipe.protocol.framing`);
    a frame is then handed out once the 7 bytes after it have arrived, or at :meth:`finish`.
    """

    def __init__(self, dialect: Dialect | str, checksum: ChecksumMode = "strict",
                 max_payload_bytes: int | None = None, confirm: bool = True) -> None:
        if checksum not in ("strict", "lenient"):
            raise ProtocolError(f"checksum mode {checksum!r}: allowed strict, lenient")
        self.dialect = get_dialect(dialect) if isinstance(dialect, str) else dialect
        self.checksum: ChecksumMode = checksum
        self._reader = self.dialect.frame_reader(max_payload_bytes, confirm)

    @property
    def reader(self) -> FrameSource:
        """The dialect's frame reader (what it learnt from the stream, e.g. SCIP geometry)."""
        return self._reader

    @property
    def warnings(self) -> list[str]:
        """What the dialect's reader found doubtful about the stream so far (see
        :func:`reader_warnings`)."""
        return reader_warnings(self._reader)

    @property
    def counters(self) -> FrameCounters:
        """Frames decoded, checksum failures, resyncs, bytes skipped, malformed, other frames,
        length mismatches, implausible frames."""
        return self._reader.counters

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[Profile]:
        """Add bytes; return the profiles of every frame they complete."""
        return [p for frame in self.feed_frames(chunk) for p in frame.profiles]

    def finish(self) -> list[Profile]:
        """End of stream: profiles of frames still pending (normally none)."""
        return [p for frame in self.finish_frames() for p in frame.profiles]

    def feed_frames(self, chunk: bytes | bytearray | memoryview) -> list[DecodedFrame]:
        """Like :meth:`feed`, grouped by frame, with each frame's end offset in the stream."""
        return self._decode(self._reader.feed(chunk))

    def finish_frames(self) -> list[DecodedFrame]:
        """Like :meth:`finish`, grouped by frame."""
        return self._decode(self._reader.finish())

    def _decode(self, raw_frames: list[RawFrame]) -> list[DecodedFrame]:
        counters = self.counters
        decoded = []
        for raw in raw_frames:
            if not raw.checksum_ok and self.checksum == "strict":
                counters.bytes_skipped += raw.end_offset - raw.start_offset
                continue
            if raw.parsed is NOT_PARSED:
                try:
                    profiles = self.dialect.decode_payload(raw.payload, raw.checksum_ok)
                except LengthMismatch:
                    counters.length_mismatches += 1
                    counters.bytes_skipped += raw.end_offset - raw.start_offset
                    continue
                except UnsupportedVariant:
                    raise
                except ProtocolError:
                    counters.malformed_frames += 1
                    counters.bytes_skipped += raw.end_offset - raw.start_offset
                    continue
            else:
                profiles = raw.parsed
            if profiles is None:
                counters.other_frames += 1
                continue
            counters.frames_decoded += 1
            decoded.append(DecodedFrame(profiles, raw.start_offset, raw.end_offset,
                                        raw.checksum_ok, raw.received_checksum,
                                        raw.computed_checksum))
        return decoded


def decode_bytes(data: bytes, dialect: Dialect | str, checksum: ChecksumMode = "strict",
                 max_payload_bytes: int | None = None) -> tuple[list[Profile], FrameCounters]:
    """Decode a whole byte stream at once: its profiles and the counters."""
    decoder = StreamDecoder(dialect, checksum, max_payload_bytes)
    profiles = decoder.feed(data) + decoder.finish()
    return profiles, decoder.counters


@dataclass(frozen=True)
class RecoveryScore:
    """How a decode of a damaged stream compares with the profiles actually sent.

    ``recovered`` of ``expected`` intact profiles came out with a good checksum (``lost`` did
    not); ``false_good`` profiles came out with a good checksum but match no sent profile
    (a false frame passed as good: must be 0); ``marked_damaged`` came out with
    ``checksum_ok=False`` (lenient mode). ``counters`` are the decoder's.
    """

    expected: int
    recovered: int
    lost: int
    false_good: int
    marked_damaged: int
    counters: FrameCounters

    def as_dict(self) -> dict[str, object]:
        """Plain data for reports and ``--json``."""
        return asdict(self)


def _profile_key(p: Profile) -> tuple[object, ...]:
    echo = None if p.echo is None else p.echo.tobytes()
    return (p.frame, p.sector, p.start_angle_deg.hex(), p.step_deg.hex(), p.ranges_m.tobytes(),
            echo, p.device_time_ms, p.device_end_time_ms)


def score_recovery(expected: Sequence[Profile], decoded: Sequence[Profile],
                   counters: FrameCounters) -> RecoveryScore:
    """Compare ``decoded`` with the ``expected`` intact profiles (as the same dialect decodes
    them from their intact frames; each expected profile is matched at most once)."""
    wanted: dict[tuple[object, ...], int] = {}
    for p in expected:
        key = _profile_key(p)
        wanted[key] = wanted.get(key, 0) + 1
    recovered = false_good = damaged = 0
    for p in decoded:
        if not p.checksum_ok:
            damaged += 1
            continue
        key = _profile_key(p)
        if wanted.get(key, 0) > 0:
            wanted[key] -= 1
            recovered += 1
        else:
            false_good += 1
    return RecoveryScore(len(expected), recovered, len(expected) - recovered, false_good,
                         damaged, counters)


def _detect_score(dialect: Dialect, data: bytes, limit: int = DETECT_BYTES[-1]) -> int:
    if dialect.detect_score is not None:
        return dialect.detect_score(data[:limit])
    decoder = StreamDecoder(dialect, "lenient")
    decoder.feed(data[:limit])
    decoder.finish()
    c = decoder.counters
    return c.frames_decoded + c.other_frames


def detect_dialect(data: bytes) -> str:
    """The dialect whose frames the first bytes of ``data`` hold; :class:`ProtocolError` if none.

    Frames are counted with a lenient checksum so that a stream of damaged frames (like the
    paper's printed sample) still tells its dialect.
    """
    # a variant the bytes cannot tell apart (DETECTED_AS: the LD14's are the LD06's) is not
    # tried: the rig names it (rig_variant)
    detectable = {name: d for name, d in DIALECTS.items() if name not in DETECTED_AS}
    for limit in DETECT_BYTES:
        scores = {name: _detect_score(d, data, limit) for name, d in detectable.items()}
        best = max(scores, key=lambda name: scores[name])
        if scores[best] > 0:
            return best
        if len(data) <= limit:
            break
    raise ProtocolError(f"cannot detect the dialect: no frame of {', '.join(detectable)} "
                        f"(tried) in the first {min(len(data), DETECT_BYTES[-1])} bytes; "
                        f"{describe_bytes(data)}")


#: File signatures a user may hand over instead of a raw scanner stream, and what to do then.
CONTAINERS: tuple[tuple[bytes, str], ...] = (
    (b"\xd4\xc3\xb2\xa1", "a pcap network capture: scanpipe import-capture or frames read it"),
    (b"\xa1\xb2\xc3\xd4", "a pcap network capture: scanpipe import-capture or frames read it"),
    (b"\x4d\x3c\xb2\xa1", "a pcap network capture: scanpipe import-capture or frames read it"),
    (b"\xa1\xb2\x3c\x4d", "a pcap network capture: scanpipe import-capture or frames read it"),
    (b"\x0a\x0d\x0d\x0a", "a pcapng network capture: scanpipe import-capture or frames read "
                           "it"),
    (b"\x89MCAP", "an MCAP file (a scanpipe recording is read by scanpipe decode)"),
    (b"#ROSBAG", "a ROS 1 bag"),
    (b"SQLite format 3\x00", "an SQLite database (a ROS 2 bag?)"),
    (b"\x1f\x8b", "gzip-compressed: decompress it first"),
    (b"\x28\xb5\x2f\xfd", "zstd-compressed: decompress it first"),
    (b"PK\x03\x04", "a zip archive: extract it first"),
)


def describe_bytes(data: bytes) -> str:
    """What the start of ``data`` is, for an error message: its first bytes in hex and the
    container it looks like, if any."""
    if not data:
        return "the input is empty"
    head = data[:16].hex(" ") + (" …" if len(data) > 16 else "")
    for magic, what in CONTAINERS:
        if data.startswith(magic):
            return f"it begins {head}: {what}"
    return f"it begins {head} (not a pcap/pcapng, MCAP or ROS bag container)"


#: Dialects whose bytes are another's, told apart only by the rig's scanner model (never
#: detected): each → the dialect its bytes are detected as (an LD14's stream reads as an LD06's).
DETECTED_AS: dict[str, str] = {"ldrobot_ld14": "ldrobot"}


def rig_variant(detected: str, rig_dialect: str) -> str:
    """The dialect to decode with when the bytes name ``detected`` and the rig's scanner
    speaks ``rig_dialect``: the rig's when it is a variant of the detected one."""
    return rig_dialect if DETECTED_AS.get(rig_dialect) == detected else detected


def resolve_dialect(name: str, data: bytes) -> Dialect:
    """``name`` as a dialect, detecting it from ``data`` for ``auto``."""
    return get_dialect(detect_dialect(data) if name == "auto" else name)
