"""Stream decoding that survives real links: splits, garbage, false starts, truncation, fuzz."""

from __future__ import annotations

import contextlib
import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scanpipe.errors import ProtocolError, ScanpipeError
from scanpipe.protocol import ldoem, paper
from scanpipe.protocol.framing import FrameReader
from scanpipe.protocol.profile import Profile, unwrap_ms16
from scanpipe.protocol.registry import (
    DIALECTS,
    StreamDecoder,
    decode_bytes,
    detect_dialect,
    get_dialect,
)

# The shared framing (marker, length, payload, XOR); CoLa-A has its own (test_protocol_sick_cola).
DIALECT_NAMES = sorted(d for d, v in DIALECTS.items() if v.reader_factory is None)


def profile(i: int, n: int = 12) -> Profile:
    ranges = ((np.arange(n) + 1 + i) % 4000 / 16).astype(np.float32)
    return Profile(frame=i, sector=0, start_angle_deg=0.0, step_deg=0.25, ranges_m=ranges,
                   device_time_ms=(i * 200) & 0xFFFF,
                   device_end_time_ms=(i * 200 + 50) & 0xFFFF)


def encoded(dialect: str, count: int, n: int = 12) -> list[bytes]:
    return [get_dialect(dialect).encode_profile(profile(i, n)) for i in range(count)]


def frames_of(data: bytes, dialect: str, splits: list[int] | None = None,
              checksum: str = "strict") -> tuple[list[int], dict[str, int]]:
    decoder = StreamDecoder(dialect, "strict" if checksum == "strict" else "lenient")
    cuts = sorted({0, len(data), *(s % (len(data) + 1) for s in splits or [])})
    out = []
    for a, b in itertools.pairwise(cuts):
        out += decoder.feed(data[a:b])
    out += decoder.finish()
    return [p.frame for p in out], decoder.counters.as_dict()


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(splits=st.lists(st.integers(0, 10_000), max_size=30))
def test_any_split_decodes_identically(dialect: str, splits: list[int]) -> None:
    data = b"garbage" + b"".join(encoded(dialect, 8)) + b"\x02US"
    whole = frames_of(data, dialect)
    assert whole[0] == list(range(8))
    assert frames_of(data, dialect, splits) == whole


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(garbage=st.lists(st.binary(max_size=40), min_size=6, max_size=6),
       lengths=st.lists(st.integers(0, 2000), min_size=6, max_size=6),
       with_marker=st.lists(st.booleans(), min_size=6, max_size=6),
       splits=st.lists(st.integers(0, 10_000), max_size=10))
def test_garbage_between_frames_never_loses_an_intact_frame(
        dialect: str, garbage: list[bytes], lengths: list[int], with_marker: list[bool],
        splits: list[int]) -> None:
    marker = get_dialect(dialect).marker
    frames = encoded(dialect, 5)
    parts = []
    for i in range(6):
        junk = garbage[i]
        if with_marker[i]:  # a false start claiming a length that may swallow what follows
            junk += marker + lengths[i].to_bytes(4, "big")
        parts.append(junk)
        if i < 5:
            parts.append(frames[i])
    got, counters = frames_of(b"".join(parts), dialect, splits)
    assert got == list(range(5))
    assert counters["frames_decoded"] == 5


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_false_start_with_every_short_length_before_a_frame(dialect: str) -> None:
    """A false start whose span ends inside the next frame's marker must not hide it."""
    marker = get_dialect(dialect).marker
    a, b = encoded(dialect, 2)
    for length in range(0, 64):
        for split in (None, [3], [len(a) + 9]):
            data = a + marker + length.to_bytes(4, "big") + b
            assert frames_of(data, dialect, split)[0] == [0, 1], (length, split)


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_false_start_marker_inside_data_keeps_the_frame(dialect: str) -> None:
    marker = get_dialect(dialect).marker
    wire = np.frombuffer(marker * 4, dtype=">u2")  # ranges whose bytes spell the marker
    per_m = 1000.0 if dialect.startswith("cola") else 256.0  # SICK: mm on the wire
    inner = Profile(frame=3, sector=0, start_angle_deg=0.0, step_deg=1.0,
                    ranges_m=(wire / per_m).astype(np.float32))
    frame = get_dialect(dialect).encode_profile(inner)
    assert frame.count(marker) >= 4
    data = encoded(dialect, 1)[0] + frame + encoded(dialect, 3)[2]
    got, counters = frames_of(data, dialect)
    assert got == [0, 3, 2]
    assert counters["resyncs"] == 0 and counters["bytes_skipped"] == 0


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_truncated_frame_is_resynced_and_the_next_kept(dialect: str) -> None:
    a, b, c = encoded(dialect, 3)
    data = a + b[: len(b) // 2] + c
    got, counters = frames_of(data, dialect)
    assert got == [0, 2]
    assert counters["resyncs"] >= 1
    assert counters["bytes_skipped"] == len(b) // 2
    # A frame cut at the very end of the stream is skipped at finish().
    got, counters = frames_of(a + b[:-1], dialect)
    assert got == [0] and counters["bytes_skipped"] == len(b) - 1


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_absurd_length_is_capped_not_allocated(dialect: str) -> None:
    marker = get_dialect(dialect).marker
    data = marker + b"\xff\xff\xff\xf0" + b"".join(encoded(dialect, 2))
    decoder = StreamDecoder(dialect, max_payload_bytes=4096)
    got = decoder.feed(data) + decoder.finish()
    assert [p.frame for p in got] == [0, 1]
    assert decoder.counters.resyncs == 1 and decoder.counters.bytes_skipped == 8


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_checksum_error_strict_drops_lenient_keeps_marked(dialect: str) -> None:
    a, b, c = encoded(dialect, 3)
    damaged = b[:-1] + bytes([b[-1] ^ 0x55])
    data = a + damaged + c
    strict, counters = frames_of(data, dialect)
    assert strict == [0, 2] and counters["checksum_failures"] == 1
    lenient = decode_bytes(data, dialect, "lenient")[0]
    assert [p.frame for p in lenient] == [0, 1, 2]
    assert [p.checksum_ok for p in lenient] == [True, False, True]


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_consumed_plus_skipped_is_everything(dialect: str) -> None:
    frames = encoded(dialect, 4)
    data = b"xx" + frames[0] + frames[1][:10] + frames[2] + b"\x02\x02" + frames[3] + b"tail"
    got, counters = frames_of(data, dialect)
    consumed = len(frames[0]) + len(frames[2]) + len(frames[3])
    assert got == [0, 2, 3]
    assert counters["bytes_skipped"] + consumed == len(data)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=3000), dialect=st.sampled_from(sorted(DIALECTS)),
       checksum=st.sampled_from(["strict", "lenient"]))
def test_fuzz_arbitrary_bytes_raise_nothing_but_scanpipe_errors(
        data: bytes, dialect: str, checksum: str) -> None:
    marker = get_dialect(dialect).marker
    data = data.replace(b"\x02\x02", marker)  # make markers, hence frame parsing, likely
    with contextlib.suppress(ScanpipeError):
        decoder = StreamDecoder(dialect, "strict" if checksum == "strict" else "lenient",
                                max_payload_bytes=4096)
        decoder.feed(data[: len(data) // 2])
        decoder.feed(data[len(data) // 2:])
        decoder.finish()
        detect_dialect(data)


@settings(max_examples=100, deadline=None)
@given(payload=st.binary(max_size=600))
def test_fuzz_ldoem_payloads_with_good_checksums(payload: bytes) -> None:
    data = ldoem.encode_frame(b"\x83\x01" + payload) + ldoem.encode_frame(payload)
    data += paper.MARKER + len(payload).to_bytes(4, "big") + payload + b"\x00"
    for name in sorted(DIALECTS):
        with contextlib.suppress(ScanpipeError):
            decode_bytes(data, name, "lenient")


def test_detection() -> None:
    assert detect_dialect(b"noise" + b"".join(encoded("ldoem", 2))) == "ldoem"
    assert detect_dialect(b"".join(encoded("paper", 2))) == "paper"
    with pytest.raises(ProtocolError, match="cannot detect"):
        detect_dialect(b"\x00" * 100)
    assert DIALECTS["ldoem"].detect(encoded("ldoem", 1)[0])
    assert not DIALECTS["paper"].detect(encoded("ldoem", 1)[0])


def test_unknown_dialect_and_checksum_mode() -> None:
    with pytest.raises(ProtocolError, match="allowed: paper, ldoem"):
        get_dialect("cola")
    with pytest.raises(ProtocolError, match="strict, lenient"):
        StreamDecoder("paper", "loose")  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match="4 bytes"):
        FrameReader(b"\x02")


def test_unwrap_ms16_across_the_wrap() -> None:
    raw = np.array([65000, 65400, 264, 664, 30000, 60000, 1000, 900], np.int64)
    assert unwrap_ms16(raw).tolist() == [65000, 65400, 65800, 66200, 30000 + 65536,
                                         60000 + 65536, 1000 + 2 * 65536, 900 + 2 * 65536]
