"""SICK CoLa bulk decoding: telegrams of one layout read together must give exactly what the
field-by-field path gives (profiles, offsets, checksum verdicts and every counter) on mixed
layouts, other telegrams, refused values and damaged streams, split anywhere."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmarks.harness import damage_stream
from scanpipe.protocol import sick_cola
from scanpipe.protocol.framing import NOT_PARSED, FrameCounters, FrameReader
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import DIALECTS

LMS111 = Path(__file__).parent / "fixtures" / "sick" / "lms111_pcapng_excerpt.json"


def _lms111_telegrams() -> list[sick_cola.ScanTelegram]:
    """The real LMS111's scan telegrams (time block, 541 samples, RSSI1)."""
    entries = json.loads(LMS111.read_text())
    stream = b"".join(bytes.fromhex(e["_source"]["layers"]["tcp"]["tcp.payload"]
                                    .replace(":", "")) for e in entries)
    out, at = [], stream.find(b"sSN LMDscandata ")
    while at >= 0:
        size = int.from_bytes(stream[at - 4:at], "big")
        out.append(sick_cola.parse_telegram(stream[at:at + size]))
        at = stream.find(b"sSN LMDscandata ", at + size)
    return out


def _profile(k: int, n: int, echo: bool) -> Profile:
    rng = np.random.default_rng([k, n])
    raw = rng.integers(0, 20000, n)
    return Profile(frame=k, sector=0, start_angle_deg=-45.0, step_deg=0.25,
                   ranges_m=np.where(raw == 0, np.nan, raw / 1000.0).astype(np.float32),
                   echo=rng.integers(0, 65535, n).astype(np.uint16) if echo else None,
                   device_time_ms=k * 40_000, device_end_time_ms=k * 40_000 + 30_000,
                   device_tick_ns=1000, device_wrap_ticks=1 << 32)


def _variants(k: int, base: sick_cola.ScanTelegram) -> list[sick_cola.ScanTelegram]:
    """Telegrams of other layouts and values: 8-bit RSSI, blocks, sRA, a refused scale, an
    angle no SICK device sends, a DIST channel of another width."""
    dist = base.channels16[0]
    rssi8 = sick_cola.Channel("RSSI1", 1.0, 0.0, dist.start_angle, dist.step,
                              (np.asarray(dist.data) % 256).astype(np.uint8))
    return [
        replace(base, channels16=(dist,), channels8=(rssi8,), scan_counter=k),
        replace(base, name="LMS", comment="lab", time=(2026, 11, 23, 1, 2, 3, 4),
                event=(b"FDIN", 1, 2, -3), scan_counter=k),
        replace(base, command=b"sRA LMDscandata ", scan_counter=k),
        replace(base, channels16=(replace(dist, scale=0.0),), scan_counter=k),
        replace(base, channels16=(replace(dist, start_angle=-5_000_000),), scan_counter=k),
        replace(base, channels16=(replace(dist, scale=2.0, offset=0.5),), scan_counter=k),
        replace(base, trailing_flags=0, scan_counter=k),
        replace(base, channels16=base.channels16[::-1], scan_counter=k),  # RSSI1 first
        replace(base, channels16=(replace(dist, name="DIST2"), *base.channels16[1:]),
                scan_counter=k),  # no DIST1: refused
    ]


def _stream(seed: int, binary: bool) -> bytes:
    """Runs of one layout (synthetic and the real LMS111's) broken by other layouts, other
    telegrams and refused ones."""
    rng = np.random.default_rng(seed)
    real = _lms111_telegrams()
    encode = ((lambda t: sick_cola.encode_frame(sick_cola.MARKER, sick_cola.encode_telegram(t)))
              if binary else sick_cola.encode_ascii)
    other = (sick_cola.command("sEA", "LMDscandata", b"\x01") if binary
             else sick_cola.command_ascii("sEA", "LMDscandata", b"\x01"))
    parts: list[bytes] = []
    for k in range(60):
        kind = rng.random()
        if kind < 0.5:
            t = sick_cola.profile_telegram(_profile(k, 181, echo=k % 7 != 0))
        elif kind < 0.8:
            t = replace(real[k % len(real)], scan_counter=k)
        elif kind < 0.95:
            base = sick_cola.profile_telegram(_profile(k, 97, echo=True))
            variants = _variants(k, base)
            t = variants[int(rng.integers(len(variants)))]
        else:
            parts.append(other)
            continue
        parts.append(encode(t))
    return b"".join(parts)


def _damage(data: bytes, seed: int, events: int) -> bytes:
    """Bit flips, cuts, insertions and false starts (a marker / STX and a plausible length)."""
    false_start = b"\x02\x02\x02\x02\x00\x00\x01\x00" if seed % 2 else b"\x02sSN "
    return damage_stream(data, np.random.default_rng(seed), events, max_cut=3000,
                         max_insert=40, false_starts=(false_start,))


def _run(reader: Any, data: bytes, cuts: list[int]) -> tuple[list[tuple[Any, ...]],
                                                               FrameCounters]:
    frames = []
    last = 0
    for cut in [*sorted(cuts), len(data)]:
        frames += reader.feed(data[last:cut])
        last = cut
    frames += reader.finish()
    return [(f.start_offset, f.end_offset, f.checksum_ok, f.payload, f.parsed)
            for f in frames], reader.counters


def _same(fast: list[tuple[Any, ...]], slow: list[tuple[Any, ...]]) -> None:
    assert len(fast) == len(slow)
    for a, b in zip(fast, slow, strict=True):
        assert a[:4] == b[:4]
        pa, pb = a[4], b[4]
        if pa is NOT_PARSED or pa is None:
            assert pb is pa
            continue
        assert len(pa) == len(pb) == 1 and pa[0].same_as(pb[0])
        assert (pa[0].device_tick_ns, pa[0].device_wrap_ticks) == (
            pb[0].device_tick_ns, pb[0].device_wrap_ticks)
        assert pa[0].ranges_m.dtype == pb[0].ranges_m.dtype
        assert (pa[0].echo is None or pa[0].echo.dtype == pb[0].echo.dtype)


def _readers(binary: bool) -> tuple[Any, Any]:
    if binary:
        fast = DIALECTS["cola_b"].frame_reader()
        assert isinstance(fast, FrameReader) and fast.parse_many is not None
        slow = replace(DIALECTS["cola_b"], decode_payloads=None).frame_reader()
        return fast, slow
    return sick_cola.AsciiFrameReader(), sick_cola.AsciiFrameReader(bulk=False)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), binary=st.booleans(), events=st.integers(0, 12),
       cuts=st.lists(st.integers(0, 1 << 20), max_size=6))
def test_bulk_equals_field_by_field(seed: int, binary: bool, events: int,
                                    cuts: list[int]) -> None:
    data = _damage(_stream(seed, binary), seed + 1, events)
    cuts = [c % (len(data) + 1) for c in cuts]
    fast, slow = _readers(binary)
    got, got_counters = _run(fast, data, cuts)
    want, want_counters = _run(slow, data, cuts)
    _same(got, want)
    assert got_counters == want_counters


@pytest.mark.parametrize("binary", [True, False])
def test_the_bulk_path_reads_whole_runs(binary: bool) -> None:
    """A stream of one layout (the real LMS111's) is read in bulk, not frame by frame: the
    test above would pass vacuously otherwise."""
    telegrams = [replace(t, scan_counter=k) for k, t in
                 enumerate(_lms111_telegrams() * 4)]
    if binary:
        payloads = [sick_cola.encode_telegram(t) for t in telegrams]
        parsed = sick_cola.decode_payloads(payloads)
        assert all(p is not NOT_PARSED for p in parsed)
        for payload, p in zip(payloads, parsed, strict=True):
            assert p[0].same_as(sick_cola.decode_payload(payload)[0])  # type: ignore[index]
        return
    data = b"".join(sick_cola.encode_ascii(t) for t in telegrams)
    padded = sick_cola._PAD + data
    tok = sick_cola._tokenise(padded, len(sick_cola._PAD), len(padded))
    spans, at = [], len(sick_cola._PAD)
    while at < len(padded):
        end = padded.index(b"\x03", at)
        spans.append((at, end))
        at = end + 1
    edges = np.array(spans, np.int64)
    edges[:, 0] += 1
    parsed = sick_cola._parse_token_frames(padded, tok, spans, np.searchsorted(tok.starts,
                                                                                edges))
    assert all(p is not NOT_PARSED for p in parsed)
    for (start, end), p in zip(spans, parsed, strict=True):
        assert p[0].same_as(sick_cola.decode_ascii(padded[start + 1:end])[0])


def test_a_telegram_the_bulk_path_refuses_is_counted_as_before() -> None:
    """In a run of one layout, a telegram with an unusable scale or a 16-bit value in an 8-bit
    channel is left to the field-by-field path, which counts it as malformed."""
    base = sick_cola.profile_telegram(_profile(0, 50, echo=True))
    good = [replace(base, scan_counter=k) for k in range(12)]
    bad_scale = replace(base, channels16=(replace(base.channels16[0], scale=-1.0),
                                          base.channels16[1]), scan_counter=12)
    ascii_frames = [sick_cola.encode_ascii(t) for t in good[:6]]
    ascii_frames.append(sick_cola.encode_ascii(bad_scale))
    ascii_frames += [sick_cola.encode_ascii(t) for t in good[6:]]
    data = b"".join(ascii_frames)
    for reader in sick_cola.AsciiFrameReader(), sick_cola.AsciiFrameReader(bulk=False):
        frames, counters = _run(reader, data, [])
        assert len(frames) == 12 and counters.malformed_frames == 1
    binary = b"".join(sick_cola.encode_frame(sick_cola.MARKER, sick_cola.encode_telegram(t))
                      for t in [*good[:6], bad_scale, *good[6:]])
    fast, slow = _readers(True)
    got, got_counters = _run(fast, binary, [])
    want, want_counters = _run(slow, binary, [])
    _same(got, want)
    assert got_counters == want_counters and got_counters.malformed_frames == 1
    assert len(got) == 12
    # 8-bit RSSI value above 255 in CoLa-A (two hex digits too many)
    eight = replace(base, channels16=base.channels16[:1], channels8=(
        sick_cola.Channel("RSSI1", 1.0, 0.0, 0, 2500, np.full(50, 7, np.uint8)),))
    text = [sick_cola.encode_ascii(replace(eight, scan_counter=k)) for k in range(8)]
    text[4] = text[4].replace(b" 7 7 ", b" 7 1FF ", 1)
    frames, counters = _run(sick_cola.AsciiFrameReader(), b"".join(text), [])
    assert len(frames) == 7 and counters.malformed_frames == 1


def test_frame_reader_bulk_needs_its_lookahead_like_the_frame_path() -> None:
    """Frames are held for the 7 bytes after them in bulk too, so a split stream gives the
    same frames."""
    data = b"".join(sick_cola.encode_profile(_profile(k, 40, True)) for k in range(10))
    fast, slow = _readers(True)
    got, got_counters = _run(fast, data, list(range(0, len(data), 997)))
    want, want_counters = _run(slow, data, list(range(0, len(data), 997)))
    _same(got, want)
    assert got_counters == want_counters and len(got) == 10


def _binary(t: sick_cola.ScanTelegram) -> bytes:
    return sick_cola.encode_frame(sick_cola.MARKER, sick_cola.encode_telegram(t))


@pytest.mark.parametrize("binary", [True, False])
def test_same_layout_other_channel_names_are_read_by_name(binary: bool) -> None:
    """Telegrams whose channels are those of the run's layout in another order, or under
    another name, are read by name (or refused), not at the template's positions."""
    base = sick_cola.profile_telegram(_profile(0, 64, echo=True))
    run = [replace(base, scan_counter=k) for k in range(10)]
    run[4] = replace(run[4], channels16=base.channels16[::-1])
    run[7] = replace(run[7], channels16=(replace(base.channels16[0], name="DIST2"),
                                         base.channels16[1]))
    data = b"".join(_binary(t) if binary else sick_cola.encode_ascii(t) for t in run)
    fast, slow = _readers(binary)
    got, got_counters = _run(fast, data, [])
    want, want_counters = _run(slow, data, [])
    _same(got, want)
    assert got_counters == want_counters and got_counters.malformed_frames == 1
    swapped = got[4][4][0]
    assert np.array_equal(swapped.ranges_m, got[0][4][0].ranges_m, equal_nan=True)


def test_a_frame_that_swallowed_a_whole_frame_is_a_false_start_in_bulk_too() -> None:
    """A frame with a good checksum whose data holds a whole other frame (a cut frame's
    claimed length landing on a frame boundary) is refused and the inner frame kept, inside a
    run of back-to-back frames as frame by frame."""
    base = sick_cola.profile_telegram(_profile(0, 64, echo=False))
    inner = _binary(replace(base, scan_counter=50))
    padded = inner + b"\x00" * (len(inner) % 2)
    carrier = replace(base, scan_counter=3, channels16=(replace(
        base.channels16[0], data=np.frombuffer(padded, ">u2").astype(np.uint16)),))
    frames = [_binary(replace(base, scan_counter=k)) for k in range(3)]
    frames.append(_binary(carrier))
    frames += [_binary(replace(base, scan_counter=k)) for k in range(4, 9)]
    data = b"".join(frames)
    fast, slow = _readers(True)
    got, got_counters = _run(fast, data, [])
    want, want_counters = _run(slow, data, [])
    _same(got, want)
    assert got_counters == want_counters
    counters_seen = [f[4][0].frame for f in got]
    assert 50 in counters_seen and 3 not in counters_seen


def test_a_long_channel_name_against_a_short_token_at_the_end_of_the_data() -> None:
    """The template's channel names are compared only with tokens of their length (a longer
    name must not be read past the end of the data)."""
    base = sick_cola.profile_telegram(_profile(0, 8, echo=False))
    extra = sick_cola.Channel("X" * 40, 1.0, 0.0, 0, 2500, np.zeros(0, np.uint16))
    run = [replace(base, scan_counter=k, channels16=(*base.channels16, extra), trailing_flags=0)
           for k in range(6)]
    run[-1] = replace(run[-1], channels16=(*base.channels16, replace(extra, name="Y")))
    data = b"".join(sick_cola.encode_ascii(t) for t in run)
    fast, slow = _readers(False)
    got, got_counters = _run(fast, data, [])
    want, want_counters = _run(slow, data, [])
    _same(got, want)
    assert got_counters == want_counters and len(got) == 6


@settings(max_examples=80, deadline=None)
@given(binary=st.booleans(), edits=st.lists(st.tuples(st.integers(0, 1 << 20),
                                                      st.integers(0, 255)), max_size=30))
def test_fuzzing_runs_of_one_layout(binary: bool, edits: list[tuple[int, int]]) -> None:
    """Random bytes written into a run the bulk path reads: the same frames and counters as
    field by field, and nothing escapes but scanpipe's own errors (the fuzz tests elsewhere
    use streams too short for the bulk path)."""
    base = sick_cola.profile_telegram(_profile(1, 30, echo=True))
    telegrams = [replace(base, scan_counter=k) for k in range(8)]
    data = bytearray(b"".join(_binary(t) if binary else sick_cola.encode_ascii(t)
                              for t in telegrams))
    for at, value in edits:
        data[at % len(data)] = value
    fast, slow = _readers(binary)
    got, got_counters = _run(fast, bytes(data), [])
    want, want_counters = _run(slow, bytes(data), [])
    _same(got, want)
    assert got_counters == want_counters
