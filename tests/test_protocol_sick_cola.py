"""SICK CoLa-B / CoLa-A ``LMDscandata``: hand-built telegrams, every field, round trips,
resync, any split, fuzzing, and a real scanner's capture."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scanpipe.captureio import load_scanner_capture
from scanpipe.errors import ProtocolError, ScanpipeError
from scanpipe.protocol import sick_cola
from scanpipe.protocol.framing import xor_checksum
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import decode_bytes, detect_dialect, score_recovery

FIXTURE = Path(__file__).parent / "fixtures" / "sick" / "tim5xx_lmdscandata.pcapng"


def colab(payload: bytes) -> bytes:
    """A CoLa-B frame built by hand, independent of the encoder."""
    return (b"\x02\x02\x02\x02" + struct.pack(">I", len(payload)) + payload
            + bytes([xor_checksum(payload)]))


def hand_payload(dist: list[int], rssi: list[int] | None = None, blocks: bytes = b"\x00" * 10,
                 scale: float = 1.0, offset: float = 0.0, counter: int = 321,
                 t_us: int = 4_000_000_000) -> bytes:
    """An LMDscandata payload laid out field by field from the device facts."""
    head = b"sSN LMDscandata " + struct.pack(
        ">HHI2sHHII2s2shII", 1, 1, 0x0112A0B3, b"\x00\x00", counter + 5, counter, t_us,
        t_us + 3000, b"\x00\x00", b"\x00\x00", 0, 2500, 5000)
    enc = struct.pack(">H", 1) + struct.pack(">IH", 123456, 7)
    channels = [(b"DIST1", scale, offset, dist)] + ([(b"RSSI1", 1.0, 0.0, rssi)] if rssi else [])
    ch16 = struct.pack(">H", len(channels))
    for name, sc, off, values in channels:
        ch16 += struct.pack(">5sffiHH", name, sc, off, -450000, 5000, len(values))
        ch16 += struct.pack(f">{len(values)}H", *values)
    return head + enc + ch16 + struct.pack(">H", 0) + blocks


def test_hand_built_telegram_every_field() -> None:
    payload = hand_payload([1000, 0, 2500], [10, 0, 65535])
    (p,), counters = decode_bytes(colab(payload), "cola_b")
    assert counters.frames_decoded == 1 and counters.bytes_skipped == 0
    assert p.frame == 321 and p.start_angle_deg == -45.0 and p.step_deg == 0.5
    assert np.array_equal(p.ranges_m, [1.0, np.nan, 2.5], equal_nan=True)
    assert p.echo is not None and p.echo.tolist() == [10, 0, 65535]
    assert p.device_time_ms == 4_000_000_000 and p.device_tick_ns == 1000
    assert p.device_wrap_ticks == 1 << 32
    # last sample: 2 steps of 0.5° at 25 Hz = 1/9000 s after the first, wrapped at 2³² µs
    assert p.device_end_time_ms == (4_000_000_000 + round(1e6 / 9000)) % (1 << 32)
    t = sick_cola.parse_telegram(payload)
    assert (t.version, t.device_number, t.serial_number) == (1, 1, 0x0112A0B3)
    assert (t.telegram_counter, t.scan_counter) == (326, 321)
    assert t.time_of_transmission_us == 4_000_003_000
    assert (t.scan_frequency_centihz, t.measurement_frequency) == (2500, 5000)
    assert t.encoders == ((123456, 7),) and t.channels8 == ()
    assert t.position is None and t.name is None and t.event is None


def test_scale_and_offset_as_sick_driver() -> None:
    (p,), _ = decode_bytes(colab(hand_payload([1000, 2000], scale=2.0, offset=0.25)), "cola_b")
    assert p.ranges_m.tolist() == pytest.approx([2.25, 4.25])


def test_optional_blocks_round_trip() -> None:
    blocks = (struct.pack(">H6fBB", 1, 1.0, 2.0, 3.0, 0.0, 0.5, 90.0, 1, 0)
              + b"\x00\x01" + bytes([5]) + b"LMS11"
              + b"\x00\x01" + bytes([3]) + b"lab"
              + struct.pack(">HHBBBBBI", 1, 2026, 11, 23, 15, 20, 7, 123456)
              + struct.pack(">H4sIIi", 1, b"FDIN", 99, 5000, -450000))
    payload = hand_payload([1, 2, 3], blocks=blocks)
    t = sick_cola.parse_telegram(payload)
    assert t.position == (1.0, 2.0, 3.0, 0.0, 0.5, 90.0, 1, 0)
    assert (t.name, t.comment) == ("LMS11", "lab")
    assert t.time == (2026, 11, 23, 15, 20, 7, 123456)
    assert t.event == (b"FDIN", 99, 5000, -450000)
    assert sick_cola.encode_telegram(t) == payload
    again = sick_cola.parse_ascii(sick_cola.encode_ascii(t)[1:-1])
    assert (again.position, again.name, again.comment, again.time, again.event) == (
        t.position, t.name, t.comment, t.time, t.event)


def test_telegram_without_trailing_flags_and_with_bad_length() -> None:
    short = hand_payload([5, 6], blocks=b"")  # firmware that omits the block flags
    (p,), _ = decode_bytes(colab(short), "cola_b")
    assert p.ranges_m.tolist() == pytest.approx([0.005, 0.006])
    _, counters = decode_bytes(colab(short + b"\x00"), "cola_b")  # one byte too many
    assert counters.frames_decoded == 0 and counters.length_mismatches == 1


def test_other_cola_telegrams_are_not_profiles() -> None:
    stream = sick_cola.command("sEA", "LMDscandata", b"\x01") + colab(hand_payload([7]))
    profiles, counters = decode_bytes(stream, "cola_b")
    assert len(profiles) == 1 and counters.other_frames == 1


def ascii_example() -> bytes:
    """A CoLa-A telegram in the manuals' style: hex tokens, −45° as FFF92230, 1.0 as 3F800000."""
    return (b"\x02sSN LMDscandata 1 1 112A0B3 0 0 1A 1B 3B9ACA00 3B9AD5B8 0 0 0 0 0 9C4 1388 0 "
            b"1 DIST1 3F800000 00000000 FFF92230 1388 3 3E8 0 9C4 0 0 0 0 0 0\x03")


def test_cola_a_hand_built() -> None:
    (p,), counters = decode_bytes(ascii_example(), "cola_a")
    assert counters.frames_decoded == 1
    assert p.frame == 0x1B and p.start_angle_deg == -45.0 and p.step_deg == 0.5
    assert np.array_equal(p.ranges_m, [1.0, np.nan, 2.5], equal_nan=True)
    assert p.device_time_ms == 1_000_000_000
    assert detect_dialect(b"junk" + ascii_example() * 2) == "cola_a"


@settings(max_examples=60, deadline=None)
@given(numbers=st.lists(st.integers(0, 0xFFFFFFFF), min_size=1, max_size=200),
       widths=st.lists(st.integers(0, 7), min_size=1, max_size=200), lower=st.booleans())
def test_bulk_hex_tokens_match_int(numbers: list[int], widths: list[int], lower: bool) -> None:
    """The vectorised tokeniser reads every 1–8 digit token (zero-padded, either case) as
    ``int(token, 16)``; longer tokens and non-hex ones are flagged, never misread."""
    texts = [format(n, "X").zfill(min(8, len(format(n, "X")) + w)) for n, w in
             zip(numbers, widths * len(numbers), strict=False)]
    if lower:
        texts = [t.lower() for t in texts]
    body = " ".join(texts).encode() + b" 123456789 12G4 \x01"
    padded = sick_cola._PAD + b"\x02" + body + b"\x03"
    tok = sick_cola._tokenise(padded, len(sick_cola._PAD), len(padded))
    n = len(texts)
    assert tok.values[:n].tolist() == [int(t, 16) for t in texts]
    assert tok.bad == [n, n + 1, n + 2]  # 9 digits, a G, a control byte
    assert tok.numbers(0, n) and not tok.numbers(0, n + 1)


def _with_data(tokens: bytes) -> bytes:
    """``ascii_example`` with its three DIST1 values replaced by ``tokens``."""
    return ascii_example().replace(b" 3E8 0 9C4 ", b" " + tokens + b" ")


def test_cola_a_data_tokens_vectorised_edge_cases() -> None:
    # zero-padded, lower-case, double spaces: the same values
    (p,), counters = decode_bytes(_with_data(b"000003E8  0 9c4"), "cola_a")
    assert counters.frames_decoded == 1
    assert np.array_equal(p.ranges_m, [1.0, np.nan, 2.5], equal_nan=True)
    # a value above 16 bits, a non-hex digit, a 9-digit token: refused, counted, not misread
    for bad in (b"103E8 0 9C4", b"3G8 0 9C4", b"0000003E8 0 9C4"):
        profiles, counters = decode_bytes(_with_data(bad) + ascii_example(), "cola_a")
        assert len(profiles) == 1 and counters.malformed_frames == 1, bad
    # a token too many: a length mismatch (one too few reads as a telegram that omits its
    # last block flag, which the format allows)
    profiles, counters = decode_bytes(_with_data(b"3E8 0 9C4 7") + ascii_example(), "cola_a")
    assert len(profiles) == 1 and counters.length_mismatches == 1


def test_cola_a_counters_across_batches_and_false_starts() -> None:
    """Garbage, false starts and a frame split over feeds count the same as one whole feed."""
    from scanpipe.protocol.registry import StreamDecoder

    frames = [sick_cola.encode_profile_ascii(profile(301, k, k % 2 == 0)) for k in range(40)]
    data = b"zz\x02\x02" + frames[0] + b"\x03junk\x02half" + b"".join(frames[1:])
    whole, counters = decode_bytes(data, "cola_a")
    assert len(whole) == 40 and counters.resyncs == 3 and counters.bytes_skipped == 2 + 2 + 5 + 5
    decoder = StreamDecoder("cola_a")
    out = []
    for i in range(0, len(data), 997):
        out += decoder.feed(data[i:i + 997])
    out += decoder.finish()
    assert len(out) == 40 and all(a.same_as(b) for a, b in zip(out, whole, strict=True))
    assert decoder.counters == counters


def profile(n: int, k: int, echo: bool) -> Profile:
    rng = np.random.default_rng([n, k])
    raw = rng.integers(0, 20000, n)
    ranges = np.where(raw == 0, np.nan, raw / 1000.0).astype(np.float32)
    return Profile(frame=k, sector=0, start_angle_deg=-45.0, step_deg=0.25, ranges_m=ranges,
                   echo=rng.integers(0, 65535, n).astype(np.uint16) if echo else None,
                   device_time_ms=(k * 40_000) % (1 << 32),
                   device_end_time_ms=(k * 40_000 + 30_000) % (1 << 32),
                   device_tick_ns=1000, device_wrap_ticks=1 << 32)


@pytest.mark.parametrize("dialect", ["cola_b", "cola_a"])
@pytest.mark.parametrize("echo", [False, True])
def test_round_trip(dialect: str, echo: bool) -> None:
    sent = [profile(1081, k, echo) for k in range(3)]
    encode = sick_cola.encode_profile if dialect == "cola_b" else sick_cola.encode_profile_ascii
    decoded, counters = decode_bytes(b"".join(encode(p) for p in sent), dialect)
    assert counters.frames_decoded == 3
    for a, b in zip(sent, decoded, strict=True):
        assert np.allclose(a.ranges_m, b.ranges_m, atol=0.0006, equal_nan=True)
        assert b.start_angle_deg == -45.0 and b.step_deg == 0.25 and b.frame == a.frame
        assert (b.echo is None) == (not echo)
        if echo:
            assert a.echo is not None and b.echo is not None
            assert np.array_equal(a.echo, b.echo)
        assert b.device_time_ms == a.device_time_ms


def _stream(dialect: str, n: int = 4) -> tuple[bytes, list[Profile]]:
    encode = sick_cola.encode_profile if dialect == "cola_b" else sick_cola.encode_profile_ascii
    data = b"".join(encode(profile(41, k, k % 2 == 0)) for k in range(n))
    return data, decode_bytes(data, dialect)[0]


@settings(max_examples=40, deadline=None)
@given(dialect=st.sampled_from(["cola_b", "cola_a"]),
       cuts=st.lists(st.integers(0, 2000), max_size=8))
def test_any_split_decodes_the_same(dialect: str, cuts: list[int]) -> None:
    from scanpipe.protocol.registry import StreamDecoder

    data, whole = _stream(dialect)
    decoder = StreamDecoder(dialect)
    out: list[Profile] = []
    last = 0
    for cut in sorted(c % (len(data) + 1) for c in cuts):
        out += decoder.feed(data[last:cut])
        last = cut
    out += decoder.feed(data[last:]) + decoder.finish()
    assert len(out) == len(whole) and all(a.same_as(b) for a, b in zip(out, whole, strict=True))


@pytest.mark.parametrize("dialect", ["cola_b", "cola_a"])
def test_resync_after_false_starts_recovers_every_intact_frame(dialect: str) -> None:
    data, expected = _stream(dialect, 6)
    encode = sick_cola.encode_profile if dialect == "cola_b" else sick_cola.encode_profile_ascii
    frame = encode(profile(41, 99, False))
    # a frame cut short, a marker claiming a huge length, and a lone start byte in front
    damaged = (frame[: len(frame) // 2] + b"\x02\x02\x02\x02\x00\x00\xff\xff" + b"\x02" + data[
        : len(data) // 2] + frame[:30] + data[len(data) // 2:])
    decoded, counters = decode_bytes(damaged, dialect)
    score = score_recovery(expected[:3] + expected[3:], decoded, counters)
    assert score.false_good == 0
    intact_second_half = [p for p in expected if p.frame >= 3]
    assert all(any(p.same_as(q) for q in decoded) for p in intact_second_half)
    assert counters.resyncs >= 1


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=600), flips=st.lists(st.integers(0, 10_000), max_size=6),
       dialect=st.sampled_from(["cola_b", "cola_a"]))
def test_fuzz_raises_only_scanpipe_errors(data: bytes, flips: list[int], dialect: str) -> None:
    base, _ = _stream(dialect, 2)
    mutated = bytearray(base)
    for f in flips:
        mutated[f % len(mutated)] ^= 0xFF
    for blob in (data, bytes(mutated), base[:7] + data):
        try:
            decode_bytes(blob, dialect)
            sick_cola.parse_telegram(blob[8:]) if dialect == "cola_b" else sick_cola.parse_ascii(
                blob)
        except ScanpipeError:
            pass


def _reference_scans(stream: bytes) -> list[tuple[int, float, float, list[float]]]:
    """Slow reference, per sample, at the driver's offsets (sick_lmd_scandata_parser.cpp)."""
    scans = []
    pos = 0
    while True:
        pos = stream.find(b"\x02\x02\x02\x02", pos)
        if pos < 0 or pos + 8 > len(stream):
            return scans
        (length,) = struct.unpack(">I", stream[pos + 4:pos + 8])
        frame = stream[pos:pos + 8 + length]  # offsets below count from the frame's byte 0
        pos += 9 + length
        if frame[8:24] != b"sSN LMDscandata ":
            continue
        (scan_counter,) = struct.unpack(">H", frame[36:38])
        (n_enc,) = struct.unpack(">H", frame[60:62])
        off = 62 + 6 * n_enc + 2  # the first 16-bit channel
        name = frame[off:off + 5]
        scale, offset = struct.unpack(">ff", frame[off + 5:off + 13])
        (start,) = struct.unpack(">i", frame[off + 13:off + 17])
        step, count = struct.unpack(">HH", frame[off + 17:off + 21])
        assert name == b"DIST1"
        ranges = []
        for i in range(count):
            (raw,) = struct.unpack(">H", frame[off + 21 + 2 * i:off + 23 + 2 * i])
            ranges.append(raw * scale * 0.001 + offset)
        scans.append((scan_counter, start / 10000.0, step / 10000.0, ranges))


def test_real_sick_capture_decodes_like_the_driver() -> None:
    capture = load_scanner_capture(FIXTURE)
    assert capture.dialect == "cola_b" and capture.scanner[-1] == 2112
    stream = b"".join(chunk for _, chunk in capture.received.chunks)
    profiles, counters = decode_bytes(stream, detect_dialect(stream))
    reference = _reference_scans(stream)
    assert len(profiles) == len(reference) == 16
    assert counters.checksum_failures == 0 and counters.malformed_frames == 0
    for p, (counter, start, step, ranges) in zip(profiles, reference, strict=True):
        assert p.frame == counter and p.start_angle_deg == start == -45.0
        assert step == pytest.approx(1 / 3, abs=1e-4) and p.step_deg == step
        assert len(p.ranges_m) == 811
        expected = np.array(ranges, np.float64)
        got = p.ranges_m.astype(np.float64)
        assert np.array_equal(np.isnan(got), expected == 0.0)
        assert np.allclose(got[expected > 0], expected[expected > 0], atol=1e-6)
    frames = np.array([p.frame for p in profiles])
    assert np.all(np.diff(frames) == 1)
    times = np.array([p.device_time_ms for p in profiles], np.int64)
    assert np.diff(times) == pytest.approx(1e6 / 15, rel=0.01)  # 15 Hz in µs


def test_cola_a_commands_round_trip_and_read_the_manuals_decimal_form() -> None:
    args = sick_cola.scan_config_args(25.0, 0.5, -45.0, 225.0)
    frame = sick_cola.command_ascii("sMN", "mLMPsetscancfg", args)
    assert frame == b"\x02sMN mLMPsetscancfg 9C4 1 1388 FFF92230 225510\x03"
    assert sick_cola.parse_command_ascii(frame[1:-1]) == ("sMN", "mLMPsetscancfg", args)
    # the manuals write signed decimal: the same bytes
    manual = b"sMN mLMPsetscancfg +2500 +1 +5000 -450000 +2250000"
    assert sick_cola.parse_command_ascii(manual)[2] == args
    assert sick_cola.parse_command_ascii(b"sFA A") == ("sFA", "", b"\x00\x0a")
    assert sick_cola.command_ascii("sFA", "", b"\x00\x02") == b"\x02sFA 2\x03"
    assert sick_cola.parse_command_ascii(b"sWA LMDscandatacfg") == ("sWA", "LMDscandatacfg", b"")
    for bad, message in ((b"sEN LMDscandata 1 2", "2 arguments, expected 1"),
                         (b"sEN LMDscandata 100", "outside its 8-bit field"),
                         (b"sMN SetAccessMode 3 XYZ", "not a number"),
                         (b"hello", "not a CoLa-A telegram")):
        with pytest.raises(ScanpipeError, match=message):
            sick_cola.parse_command_ascii(bad)


LMS111_FIXTURE = FIXTURE.parent / "lms111_pcapng_excerpt.json"


def _json_capture_stream(path: Path) -> bytes:
    """The TCP payloads of a pcap_json_converter capture (both directions, in order)."""
    import json

    entries = json.loads(path.read_text())
    return b"".join(bytes.fromhex(e["_source"]["layers"]["tcp"]["tcp.payload"].replace(":", ""))
                    for e in entries)


def test_real_lms111_capture_decodes_like_the_driver() -> None:
    """A real LMS111 (firmware V1.80) talking to SICK's driver: every scan decodes to the
    driver's ranges sample for sample; the driver's start-up telegrams are the bytes our
    recorder sends; the telegram's time block (flag 1, 11 bytes) fits the layout exactly."""
    stream = _json_capture_stream(LMS111_FIXTURE)
    profiles, counters = decode_bytes(stream, "cola_b")
    reference = _reference_scans(stream)
    assert len(profiles) == len(reference) == 9 and counters.malformed_frames == 0
    assert counters.length_mismatches == 0 and counters.checksum_failures == 0
    for p, (counter, start, step, ranges) in zip(profiles, reference, strict=True):
        assert p.frame == counter and p.start_angle_deg == start == -45.0
        assert p.step_deg == step == 0.5 and len(p.ranges_m) == 541
        expected = np.array(ranges, np.float64)
        got = p.ranges_m.astype(np.float64)
        assert np.array_equal(np.isnan(got), expected == 0.0)
        assert np.allclose(got[expected > 0], expected[expected > 0], atol=1e-6)
    assert np.all(np.diff([p.frame for p in profiles]) == 1)
    times = np.array([p.device_time_ms for p in profiles], np.int64)
    assert np.diff(times) == pytest.approx(20_000, rel=0.02)  # 50 Hz in µs (the device jitters)
    first = stream.find(b"sSN LMDscandata ")
    length = int.from_bytes(stream[first - 4:first], "big")
    t = sick_cola.parse_telegram(stream[first:first + length])
    assert t.scan_frequency_centihz == 5000 and t.trailing_flags == 5 and t.time is not None
    # what scanpipe's driver sends is what SICK's driver sent this device
    assert sick_cola.command("sMN", "SetAccessMode", bytes([3]) + sick_cola.CLIENT_PASSWORD
                             .to_bytes(4, "big")) in stream
    assert sick_cola.command("sEN", "LMDscandata", b"\x01") in stream
    # the same scans as CoLa-A decode to the same ranges
    telegrams = []
    at = stream.find(b"sSN LMDscandata ")
    while at >= 0:
        size = int.from_bytes(stream[at - 4:at], "big")
        telegrams.append(sick_cola.parse_telegram(stream[at:at + size]))
        at = stream.find(b"sSN LMDscandata ", at + size)
    again, _ = decode_bytes(b"".join(sick_cola.encode_ascii(t) for t in telegrams), "cola_a")
    assert len(again) == 9 and all(a.same_as(b) for a, b in zip(again, profiles, strict=True))


LMS111_DRIVER_OUTPUT = FIXTURE.parent / "lms111_sick_scan_xd_ranges.json"
# sick_scan_xd's ScanAngleShift for sick_lms_1xx: its LaserScan has 0 rad straight ahead, where
# the device's own angle (the telegram's, ours) is 90°.
LMS1XX_ROS_ANGLE_SHIFT_RAD = -np.pi / 2
# float32 rounding of the driver's angle_min (half an ulp at 2.36 rad: 1.2e-7) plus 540 times
# that of angle_increment (half an ulp at 0.0087 rad: 4.7e-10) when a reader sums them.
F32_ANGLE_TOL_RAD = 1.2e-7 + 540 * 4.7e-10


def test_real_lms111_capture_decodes_to_sick_scan_xd_own_output() -> None:
    """The LMS111 telegrams decode to exactly what SICK's own parser (sick_scan_xd, built and
    run by tools/sick_driver_reference/regenerate.sh) put in its LaserScan: every range within
    one float32 ulp, every angle within float32 rounding of angle_min + i · angle_increment."""
    import json

    driver = json.loads(LMS111_DRIVER_OUTPUT.read_text())
    profiles, _ = decode_bytes(_json_capture_stream(LMS111_FIXTURE), "cola_b")
    assert len(driver["scans"]) == len(profiles) == 9
    for p, scan in zip(profiles, driver["scans"], strict=True):
        assert p.frame == scan["scan_counter"] and scan["num_echos"] == 1
        assert scan["scan_time_s"] == pytest.approx(0.02)  # 50 Hz, as the telegram says
        expected = np.array(scan["ranges_m"], np.float32)
        assert len(p.ranges_m) == len(expected) == 541
        # the driver publishes raw 0 as 0.0 m; we mark it NaN ("no echo"); this capture has none
        assert np.all(expected > 0) and not np.any(np.isnan(p.ranges_m))
        assert np.all(np.abs(p.ranges_m - expected) <= np.spacing(expected))
        i = np.arange(len(expected))
        driver_rad = (np.float64(np.float32(scan["angle_min_rad"]))
                      + i * np.float64(np.float32(scan["angle_increment_rad"])))
        ours_rad = np.deg2rad(p.start_angle_deg + i * p.step_deg) + LMS1XX_ROS_ANGLE_SHIFT_RAD
        assert np.max(np.abs(ours_rad - driver_rad)) <= F32_ANGLE_TOL_RAD
        assert driver_rad[-1] == pytest.approx(scan["angle_max_rad"], abs=F32_ANGLE_TOL_RAD)


TIM55X_COLA_A = Path(__file__).parent / "fixtures" / "sick" / "tim55x_cola_a_lmdscandata.txt"


def _tim55x_telegrams() -> list[bytes]:
    lines = TIM55X_COLA_A.read_text().splitlines()
    return [line.encode("ascii") for line in lines if not line.startswith("#")]


@pytest.mark.parametrize("copies", [1, 12])  # 12: the bulk (one layout at once) path too
def test_real_tim55x_cola_a_with_the_default_device_name(copies: int) -> None:
    """A real TiM55x's CoLa-A telegrams end ``… 0 1 B not defined 0 0 0``: the device name
    block holds the factory name "not defined", 11 (B) characters with a space. Read as one
    token per string, every telegram was dropped as malformed (no profile from a TiM in
    CoLa-A mode). The reference reads the tokens by the manual's field order."""
    telegrams = _tim55x_telegrams()
    assert len(telegrams) == 2
    stream = b"".join(b"\x02" + t + b"\x03" for t in telegrams) * copies
    assert detect_dialect(stream) == "cola_a"
    profiles, counters = decode_bytes(stream, "cola_a")
    assert counters.frames_decoded == 2 * copies and counters.malformed_frames == 0
    assert counters.bytes_skipped == 0
    for body, p in zip(telegrams * copies, profiles, strict=True):
        tokens = body.split(b" ")
        at = tokens.index(b"DIST1")
        scale = struct.unpack(">f", bytes.fromhex(tokens[at + 1].decode()))[0]
        start = struct.unpack(">i", bytes.fromhex(tokens[at + 3].decode()))[0]
        step, count = int(tokens[at + 4], 16), int(tokens[at + 5], 16)
        raw = [int(v, 16) for v in tokens[at + 6:at + 6 + count]]
        assert (scale, start, step, count) == (1.0, -450000, 10000, 271)  # −45° … 225° at 1°
        assert p.frame == int(tokens[8], 16) and p.device_time_ms == int(tokens[9], 16)
        assert p.start_angle_deg == -45.0 and p.step_deg == 1.0
        expected = np.array([v * scale / 1000 if v else np.nan for v in raw], np.float32)
        assert np.array_equal(p.ranges_m, expected, equal_nan=True)
        rssi = tokens.index(b"RSSI1")
        assert p.echo is not None
        assert p.echo.tolist() == [int(v, 16) for v in tokens[rssi + 6:rssi + 6 + count]]
    t = sick_cola.parse_ascii(telegrams[1])
    assert t.name == "not defined" and t.comment is None and t.time is None
    assert t.command == b"sSN LMDscandata " and sick_cola.parse_ascii(
        telegrams[0]).command == b"sRA LMDscandata "
    # and back: the encoder writes such a name as the device does
    assert sick_cola.encode_ascii(t)[1:-1] == telegrams[1]


@pytest.mark.parametrize("copies", [1, 12])  # 12: the bulk (one layout at once) path too
def test_cola_a_empty_string_is_read(copies: int) -> None:
    """A name block present with length 0 (``1 0``: a device whose name was cleared; the
    encoder writes an empty name so) holds no token: read as "", the telegram kept (a string
    read by its characters took the next field's token as the string's end and dropped every
    such telegram as a length mismatch)."""
    t = dataclasses.replace(sick_cola.parse_ascii(_tim55x_telegrams()[1]), name="")
    framed = sick_cola.encode_ascii(t)
    assert b" 1 0 0 0 0" in framed  # name present, length 0; comment, time, event absent
    again = sick_cola.parse_ascii(framed[1:-1])
    assert again.name == "" and again.comment is None and again.time is None
    assert again.scan_counter == t.scan_counter
    profiles, counters = decode_bytes(framed * copies, "cola_a")
    assert counters.frames_decoded == copies and counters.malformed_frames == 0
    assert counters.length_mismatches == 0 and counters.bytes_skipped == 0
    assert len(profiles) == copies


@pytest.mark.parametrize("dialect", ["cola_b", "cola_a"])
@pytest.mark.parametrize("copies", [1, 12])  # 12: the bulk path too
def test_multi_layer_telegrams_are_refused(dialect: str, copies: int) -> None:
    """A multi-layer SICK scanner (MRS1000: 4 layers, MRS6000: 24) sends one LMDscandata per
    layer with the layer's elevation in the field after the outputs (SICK's driver:
    ``elevAngleX200`` at payload byte 42, 1/200° on the MRS6000, 1/100° on the MRS1000; F5 B2 =
    −2638 is layer 24). Their beams lie on cones, not in the scan plane; decoded as profiles
    of one plane the layers were interleaved into one cloud without a word."""
    base = profile(301, 0, True)
    flat = sick_cola.profile_telegram(base)
    layers = [dataclasses.replace(flat, layer_angle=a, scan_counter=k)
              for k, a in enumerate((0, -250, 250, 500) * copies)]
    encode = ((lambda t: colab(sick_cola.encode_telegram(t))) if dialect == "cola_b"
              else sick_cola.encode_ascii)
    stream = b"".join(encode(t) for t in layers)
    with pytest.raises(ProtocolError, match=r"multi-layer .*layer angle.*not supported"):
        decode_bytes(stream, dialect)
    # single-layer telegrams (layer angle 0, every LMS1xx/5xx/TiM capture) still decode
    single = b"".join(encode(dataclasses.replace(flat, scan_counter=k)) for k in range(8))
    assert decode_bytes(single, dialect)[1].frames_decoded == 8
