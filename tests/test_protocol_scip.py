"""Hokuyo SCIP 2.0: encoding, check characters, messages, resync, damage, fuzz, geometry."""

from __future__ import annotations

import contextlib
import itertools
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from benchmarks.harness import damage_stream
from scanpipe.errors import ProtocolError, ScanpipeError
from scanpipe.protocol import scip
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import (
    StreamDecoder,
    decode_bytes,
    detect_dialect,
    score_recovery,
)


def profile(i: int, n: int = 121, echo: bool = False, start_deg: float = -135.0,
            step_deg: float = 0.25) -> Profile:
    ranges = (0.02 + ((np.arange(n) * 37 + i * 101) % 9000) / 1000).astype(np.float32)
    ranges[(np.arange(n) + i) % 17 == 0] = np.nan
    return Profile(frame=(i * 25) & 0xFFFF, sector=0, start_angle_deg=start_deg,
                   step_deg=step_deg, ranges_m=ranges,
                   echo=(np.arange(n, dtype=np.uint16) * 7 + i) if echo else None,
                   device_time_ms=i * 25)


def encoded(count: int, n: int = 121, echo: bool = False) -> list[bytes]:
    return [scip.encode_profile(profile(i, n, echo)) for i in range(count)]


def times_of(data: bytes, splits: list[int] | None = None,
             checksum: str = "strict") -> tuple[list[int | None], dict[str, int]]:
    decoder = StreamDecoder("scip", "strict" if checksum == "strict" else "lenient")
    cuts = sorted({0, len(data), *(s % (len(data) + 1) for s in splits or [])})
    out = []
    for a, b in itertools.pairwise(cuts):
        out += decoder.feed(data[a:b])
    out += decoder.finish()
    return [p.device_time_ms for p in out], decoder.counters.as_dict()


def test_spec_examples_of_the_encodings_and_check_characters() -> None:
    # The SCIP 2.0 specification's own examples: 1234 → "CB" (2 chars), 5432 → "1Dh" (3).
    assert scip.encode_values(np.array([1234]), 2) == b"CB"
    assert scip.encode_values(np.array([5432]), 3) == b"1Dh"
    assert scip.decode_values(b"1Dh", 3).tolist() == [5432]
    assert scip.status_line("00") == b"00P\n" and scip.status_line("99") == b"99b\n"
    # A PP line's check character covers "NAME:value", not the ';'.
    assert scip.parameter_lines({"DMIN": "20"}) == b"DMIN:20;4\n"
    with pytest.raises(ProtocolError, match="does not fit 2 SCIP characters"):
        scip.encode_values(np.array([4096]), 2)


def test_hand_built_md_message_decodes() -> None:
    data = scip.encode_values(np.array([5432, 0, 1234]), 3)
    stamp = scip.encode_values(np.array([1000]), 4)
    message = (b"MD0540054201000\n99b\n" + stamp + bytes([scip.check_char(stamp)]) + b"\n"
               + data + bytes([scip.check_char(data)]) + b"\n\n")
    (p,), counters = decode_bytes(message, "scip")
    assert p.start_angle_deg == 0.0 and p.step_deg == 0.25 and p.device_time_ms == 1000
    assert np.allclose(p.ranges_m, [5.432, np.nan, 1.234], equal_nan=True)
    assert p.device_wrap_ticks == 1 << 24 and counters.frames_decoded == 1


@settings(max_examples=60, deadline=None)
@given(command=st.sampled_from([b"MD", b"ME", b"MS", b"GD", b"GE", b"GS"]),
       start=st.integers(0, 1000), cluster=st.integers(1, 10), n=st.integers(1, 300),
       time_ms=st.integers(0, (1 << 24) - 1), seed=st.integers(0, 1000))
def test_every_data_command_round_trips(command: bytes, start: int, cluster: int, n: int,
                                        time_ms: int, seed: int) -> None:
    assume(n * cluster <= 1080)
    rng = np.random.default_rng(seed)
    top = 4.095 if command[1:] == b"S" else 60.0
    ranges = np.round(rng.uniform(0.02, top, n), 3).astype(np.float32)
    ranges[rng.random(n) < 0.1] = np.nan
    echo = rng.integers(0, 65536, n).astype(np.uint16)
    end = start + n * cluster - 1
    message = scip.encode_scan(command, start, end, cluster, time_ms, ranges, echo,
                               status="99" if command[:1] == b"M" else "00")
    (p,), counters = decode_bytes(message, "scip")
    assert counters.frames_decoded == 1 and p.checksum_ok
    assert p.device_time_ms == time_ms and len(p.ranges_m) == n
    assert p.start_angle_deg == (start - 540) * 0.25 and p.step_deg == cluster * 0.25
    assert np.allclose(p.ranges_m, ranges, equal_nan=True, atol=5e-4)
    if command[1:] == b"E":
        assert p.echo is not None and np.array_equal(p.echo, echo)
    else:
        assert p.echo is None


def test_profiles_round_trip_through_encode_profile_with_echo_and_urg_geometry() -> None:
    for p in (profile(3, echo=True), profile(4, n=682, start_deg=-119.53125,
                                              step_deg=360 / 1024)):
        (q,), _ = decode_bytes(scip.encode_profile(p), "scip")
        assert q.start_angle_deg == p.start_angle_deg and q.step_deg == p.step_deg
        assert np.allclose(q.ranges_m, p.ranges_m, equal_nan=True, atol=5e-4)
        assert (q.echo is None) == (p.echo is None)


def test_pp_reply_sets_the_geometry_else_ust_is_assumed() -> None:
    scan = scip.encode_scan(b"MD", 44, 725, 1, 5, np.full(682, 1.0))
    (p,), _ = decode_bytes(scan, "scip")
    assert p.start_angle_deg == (44 - 540) * 0.25  # no PP: UST/UTM geometry
    pp = scip.parameter_reply(b"PP", scip.pp_fields(scip.URG04_GEOMETRY, "URG-04LX", 20, 5600,
                                                    44, 725))
    (p,), counters = decode_bytes(pp + scan, "scip")
    assert p.start_angle_deg == pytest.approx(-119.53125) and counters.other_frames == 1
    # The end time follows the scan speed (600 rpm) over the 682 steps.
    assert p.device_end_time_ms == 5 + round(682 / 1024 * 100)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(splits=st.lists(st.integers(0, 20_000), max_size=30))
def test_any_split_decodes_identically(splits: list[int]) -> None:
    data = b"garbage\n" + b"".join(encoded(8)) + b"MD00"
    whole = times_of(data)
    assert whole[0] == [i * 25 for i in range(8)]
    assert times_of(data, splits) == whole


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(garbage=st.lists(st.binary(max_size=40), min_size=6, max_size=6),
       echo_like=st.lists(st.booleans(), min_size=6, max_size=6),
       splits=st.lists(st.integers(0, 20_000), max_size=10))
def test_garbage_between_messages_never_loses_an_intact_one(
        garbage: list[bytes], echo_like: list[bool], splits: list[int]) -> None:
    frames = encoded(5)
    parts = []
    for i in range(6):
        junk = garbage[i] + (b"MD0000108001000\n99b\n" if echo_like[i] else b"")
        parts.append(junk)
        if i < 5:
            parts.append(frames[i])
    got, _ = times_of(b"".join(parts), splits)
    assert got == [i * 25 for i in range(5)]


def test_truncated_message_is_resynced_and_the_next_kept() -> None:
    a, b, c = encoded(3)
    got, counters = times_of(a + b[: len(b) // 2] + c)
    assert got == [0, 50] and counters["resyncs"] >= 1
    assert counters["bytes_skipped"] == len(b) // 2
    got, counters = times_of(a + b[:-1])
    assert got == [0] and counters["bytes_skipped"] == len(b) - 1


def test_checksum_error_strict_drops_lenient_keeps_marked() -> None:
    a, b, c = encoded(3)
    i = b.index(b"\n", 30) - 5  # a data character
    damaged = b[:i] + bytes([b[i] ^ 0x01]) + b[i + 1:]
    strict, counters = times_of(a + damaged + c)
    assert strict == [0, 50] and counters["checksum_failures"] == 1
    lenient = decode_bytes(a + damaged + c, "scip", "lenient")[0]
    assert [p.checksum_ok for p in lenient] == [True, False, True]


def test_consumed_plus_skipped_is_everything() -> None:
    frames = encoded(4)
    data = b"xx" + frames[0] + frames[1][:10] + frames[2] + b"\n\n" + frames[3] + b"tail"
    got, counters = times_of(data)
    assert got == [0, 50, 75]
    consumed = len(frames[0]) + len(frames[2]) + len(frames[3])
    assert counters["bytes_skipped"] + consumed == len(data)


def damage(stream: bytes, rng: np.random.Generator, events: int) -> bytes:
    """Cuts, bit flips and insertions at random places (the benchmarks' damage)."""
    return damage_stream(stream, rng, events, max_cut=400, max_insert=60)


@pytest.mark.parametrize("seed", range(6))
def test_every_intact_message_is_recovered_from_a_damaged_stream(seed: int) -> None:
    rng = np.random.default_rng(seed)
    messages = encoded(60, n=271, echo=seed % 2 == 1)
    command = b"ME" if seed % 2 else b"MD"
    ack = command + b"0000027001000\n00P\n\n"  # the device's answer to the MD/ME command
    stream = ack + damage(b"".join(messages), rng, 25)
    intact = [m for m in messages if m in stream]
    expected = [p for m in intact for p in decode_bytes(m, "scip")[0]]
    decoded, counters = decode_bytes(stream, "scip")
    # Every intact message comes out ...
    assert score_recovery(expected, decoded, counters).lost == 0
    # ... and nothing comes out that was not sent (damage the protocol cannot see, like a
    # flipped remaining-scan count, may leave a message that still decodes to what was sent).
    sent = [p for m in messages for p in decode_bytes(m, "scip")[0]]
    assert score_recovery(sent, decoded, counters).false_good == 0
    assert len(expected) >= 30


def test_multi_echo_is_refused_clearly() -> None:
    with pytest.raises(ProtocolError, match=r"multi-echo data \(ND\): not supported"):
        decode_bytes(b"ND0000108001000\n99b\n0000P\n\n", "scip")


def test_replies_and_status_codes() -> None:
    reader = scip.ScipReader()
    frames = reader.feed(b"BM\n02R\n\nQT\n00P\n\n")
    assert [f.parsed for f in frames] == [None, None] and reader.last_status == ("QT", "00")
    assert scip.status_meaning("02").endswith("laser already on)")
    assert "command-specific" in scip.status_meaning("7Z")


def test_detection_finds_scip_and_not_the_others() -> None:
    data = b"".join(encoded(3))
    assert detect_dialect(b"noise" + data) == "scip"
    assert scip.ScipReader().feed(data)[0].checksum_ok


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=3000), seed=st.integers(0, 100),
       checksum=st.sampled_from(["strict", "lenient"]))
def test_fuzz_raises_nothing_but_scanpipe_errors(data: bytes, seed: int, checksum: str) -> None:
    # Make line structure, echoes and terminators likely.
    data = (data.replace(b"\x00", b"\n").replace(b"\x01", b"MD0000001001000\n")
            .replace(b"\x02", b"99b\n").replace(b"\x03", b"\n\n"))
    rng = np.random.default_rng(seed)
    mixed = damage(b"".join(encoded(2, n=30)) + data, rng, 3)
    with contextlib.suppress(ScanpipeError):
        decoder = StreamDecoder("scip", "strict" if checksum == "strict" else "lenient")
        decoder.feed(mixed[: len(mixed) // 2])
        decoder.feed(mixed[len(mixed) // 2:])
        decoder.finish()
        detect_dialect(mixed)


FIXTURES = Path(__file__).parent / "fixtures" / "scip"


def test_a_real_utm30lx_scan_decodes() -> None:
    """Bytes a UTM-30LX sent (tests/fixtures/README.md): every check character passes."""
    data = (FIXTURES / "utm30lx_md_scan.txt").read_bytes()
    (p,), counters = decode_bytes(data, "scip")
    assert counters.checksum_failures == 0 and counters.bytes_skipped == 0
    # MD 0000…1080, cluster 4: 271 values from −135° in 1° steps, timestamp "03Fn".
    assert len(p.ranges_m) == 271 and p.start_angle_deg == -135.0 and p.step_deg == 1.0
    assert p.device_time_ms == (3 << 12) + (22 << 6) + 62
    assert p.ranges_m[:3].tolist() == pytest.approx([0.213, 0.229, 0.229])
    assert np.isfinite(p.ranges_m).all() and np.nanmax(p.ranges_m) < 30.0


def test_real_urg04lx_vv_and_pp_replies_parse_and_set_the_geometry() -> None:
    reader = scip.ScipReader()
    frames = reader.feed((FIXTURES / "urg04lx_pp_vv.txt").read_bytes())
    assert [f.parsed for f in frames] == [None, None] and reader.counters.resyncs == 0
    assert reader.geometry == scip.Geometry(1024, 384, 600) and reader.geometry_from_device
    assert reader.range_limits_mm == (20, 5600)


def test_values_outside_the_devices_dmin_dmax_are_no_return() -> None:
    """The real URG-04LX PP reply says DMIN 20, DMAX 5600 mm. Values outside are the
    device's codes (no echo, interference, …: UST/UTM send e.g. 65533), which urg_library and
    urg_node take as out of range; they were decoded as ranges (a phantom wall at 65.5 m)."""
    values = np.array([5, 19, 20, 21, 1234, 5600, 5601, 65533], np.int64)
    scan = (b"MD0384039101000\n" + scip.status_line("99") + scip.timestamp_line(1000)
            + scip.data_block(scip.encode_values(values, 3)) + b"\n")
    pp = (FIXTURES / "urg04lx_pp_vv.txt").read_bytes()
    (p,), counters = decode_bytes(pp + scan, "scip")
    assert counters.checksum_failures == 0
    expected = [np.nan, np.nan, 0.020, 0.021, 1.234, 5.6, np.nan, np.nan]
    assert np.allclose(p.ranges_m, expected, equal_nan=True)
    # without a PP reply only the 20 mm error-code floor applies (no DMAX is known)
    (q,), _ = decode_bytes(scan, "scip")
    assert np.isnan(q.ranges_m[:2]).all() and q.ranges_m[-1] == pytest.approx(65.533)


def test_the_reader_reports_its_own_warning_through_the_decoder() -> None:
    """Readers report what they doubt through ``StreamDecoder.warnings`` (no attribute of one
    reader read by name): SCIP scans without a PP reply say so; other readers say nothing."""
    from scanpipe.protocol.registry import StreamDecoder, reader_warnings
    from scanpipe.protocol.scip import ScipReader

    assert reader_warnings(ScipReader()) == []  # nothing decoded yet
    for name in ("cola_b", "cola_a", "ldoem", "paper", "ldrobot"):
        assert StreamDecoder(name).warnings == []


def _scip11_g_reply(start: int, end: int, cluster: int, mm: int = 1000) -> bytes:
    """A SCIP 1.1 ``G`` reply as Hokuyo's SCIP 1.1 specification lays it out: the echo
    ``G`` + start, end (3 digits each) + cluster (2), a one-character status (``0``: ok), the
    ranges in 2 characters of 6 bits in lines of 64 characters *without* check characters, and
    an empty line. (No public capture of a SCIP 1.1 device was found; urg_library detects one
    by its one-character answer ``E`` to ``QT`` and switches it with ``SCIP2.0``.)"""
    count = -(-(end - start + 1) // cluster)
    data = bytes([(mm >> 6) + 0x30, (mm & 0x3F) + 0x30]) * count
    lines = b"".join(data[i:i + 64] + b"\n" for i in range(0, len(data), 64))
    return b"G%03d%03d%02d\n0\n" % (start, end, cluster) + lines + b"\n"


def test_scip_1_1_is_refused_naming_the_version() -> None:
    """A URG-04LX with old firmware (or not switched) answers SCIP 1.1: one-character status,
    no check characters. It was skipped byte by byte as noise (0 profiles, "cannot detect the
    dialect"); now the decoder says which protocol it saw and what to do."""
    data = _scip11_g_reply(44, 725, 1) * 3
    with pytest.raises(ProtocolError, match=r"SCIP 1\.1 .*not supported.*SCIP2\.0"):
        decode_bytes(data, "scip")
    with pytest.raises(ProtocolError, match=r"SCIP 1\.1"):
        detect_dialect(data)
    # SCIP 2.0 messages (status of two characters and a check) are not taken for it
    assert decode_bytes(b"".join(encoded(3)), "scip")[1].frames_decoded == 3
