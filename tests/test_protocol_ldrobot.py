"""The LDRobot LD06/LD19/STL-27L dialect: packets, CRC, locating, revolutions, damage, fuzz."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.harness import damage_frames
from scanpipe.errors import ProtocolError, ScanpipeError
from scanpipe.protocol import ldrobot as ld
from scanpipe.protocol.profile import Profile

FIXTURE = Path(__file__).parent / "fixtures" / "ldrobot" / "packets.hex"


def fixture_packets() -> list[bytes]:
    lines = FIXTURE.read_text().splitlines()
    return [bytes.fromhex(line) for line in lines if line.strip() and not line.startswith("#")]


def slow_crc(data: bytes) -> int:
    """CRC-8, polynomial 0x4D, bit by bit (the obvious reference)."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x4D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def stream(packets: int, rate_hz: float = 4500.0, speed_dps: float = 3600.0,
           jitter: float = 0.0, seed: int = 0, t0_ms: int = 0) -> tuple[bytes, np.ndarray]:
    """A synthetic device stream: sample clock at ``rate_hz``, head at ``speed_dps`` (± jitter
    per packet), ranges 1 + 0.5 sin(angle) m. Returns the bytes and the true sample angles."""
    rng = np.random.default_rng(seed)
    speed = speed_dps * (1 + jitter * rng.standard_normal(packets))
    dt = 1.0 / rate_hz
    span = speed * dt * 11
    starts = np.concatenate([[7.3], 7.3 + np.cumsum(speed[:-1] * dt * 12)])
    angles = starts[:, None] + (span / 11)[:, None] * np.arange(12)
    dist = np.rint((1.0 + 0.5 * np.sin(np.radians(angles))) * 1000).astype(int)
    stamps = (t0_ms + np.rint(np.arange(packets) * 12 * dt * 1000)).astype(int) % 30000
    data = ld.encode_packets(np.rint(speed).astype(int),
                             np.rint(starts * 100).astype(int) % 36000, dist,
                             np.full(dist.shape, 200),
                             np.rint((starts + span) * 100).astype(int) % 36000, stamps)
    return data, angles


# -- golden vectors from material scanpipe did not make -------------------------------------

def test_crc_table_is_the_vendors() -> None:
    # First and last entries of the table in LDRobot's SDK (lipkg.cpp, CrcTable).
    assert ld.CRC_TABLE[:8].tolist() == [0x00, 0x4D, 0x9A, 0xD7, 0x79, 0x34, 0xE3, 0xAE]
    assert ld.CRC_TABLE[-4:].tolist() == [0x7F, 0x32, 0xE5, 0xA8]
    rng = np.random.default_rng(1)
    rows = rng.integers(0, 256, (50, 46), dtype=np.uint8)
    assert ld.crc8_rows(rows).tolist() == [slow_crc(r.tobytes()) for r in rows]
    assert [ld.crc8(r.tobytes()) for r in rows] == ld.crc8_rows(rows).tolist()


def test_the_manuals_example_packet() -> None:
    example = fixture_packets()[0]
    p = ld.parse_packet(example)
    assert p.crc_ok.tolist() == [True]
    assert (int(p.speed_dps[0]), int(p.start_cdeg[0]), int(p.end_cdeg[0]),
            int(p.timestamp_ms[0])) == (2152, 32427, 33470, 6714)
    assert p.distance_mm[0].tolist() == [224, 220, 217, 213, 211, 208, 205, 202, 199, 197,
                                         194, 192]
    assert int(p.intensity[0, 0]) == 228 and int(p.intensity[0, -1]) == 229
    assert ld.packet_plausible(p).tolist() == [True]


def test_a_real_ld20_packet_of_no_returns() -> None:
    captured = fixture_packets()[1]
    p = ld.parse_packet(captured)
    assert p.crc_ok.tolist() == [True]
    assert (int(p.speed_dps[0]), int(p.start_cdeg[0]), int(p.end_cdeg[0]),
            int(p.timestamp_ms[0])) == (2164, 34480, 35074, 2334)
    assert p.distance_mm[0].tolist() == [0] * 12
    assert p.intensity[0].tolist()[:3] == [0xD4] * 3
    # In a stream: located, and its samples are no-returns (NaN), not 0 m.
    data = b"\x00\x54" + captured + captured[:20]
    packets, _ = ld.locate_packets(data)
    assert len(packets) == 1 and packets.offset.tolist() == [2]
    profiles, _ = ld.decode_revolutions(captured, grid_beams=360)
    assert len(profiles) == 1
    assert np.isnan(profiles[0].ranges_m).all()


def test_fixture_packets_byte_flips_break_the_crc() -> None:
    for packet in fixture_packets():
        for i in range(2, 46):
            damaged = bytearray(packet)
            damaged[i] ^= 0x10
            assert ld.parse_packet(bytes(damaged)).crc_ok.tolist() == [False]


# -- packets -------------------------------------------------------------------------------

@settings(max_examples=80, deadline=None)
@given(n=st.integers(1, 20), seed=st.integers(0, 2**32 - 1))
def test_packets_round_trip(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    fields = dict(speed_dps=rng.integers(0, 65536, n), start_cdeg=rng.integers(0, 65536, n),
                  distance_mm=rng.integers(0, 65536, (n, 12)),
                  intensity=rng.integers(0, 256, (n, 12)),
                  end_cdeg=rng.integers(0, 65536, n), timestamp_ms=rng.integers(0, 65536, n))
    data = ld.encode_packets(**fields)
    assert len(data) == n * ld.PACKET_BYTES
    for k in range(n):
        p = ld.parse_packet(data[k * 47:(k + 1) * 47])
        assert p.crc_ok.all()
        assert int(p.speed_dps[0]) == fields["speed_dps"][k]
        assert int(p.start_cdeg[0]) == fields["start_cdeg"][k]
        assert int(p.end_cdeg[0]) == fields["end_cdeg"][k]
        assert int(p.timestamp_ms[0]) == fields["timestamp_ms"][k]
        assert p.distance_mm[0].tolist() == fields["distance_mm"][k].tolist()
        assert p.intensity[0].tolist() == fields["intensity"][k].tolist()


def test_encoder_refuses_values_that_do_not_fit() -> None:
    with pytest.raises(ProtocolError, match="distance"):
        ld.encode_packets([3600], [0], np.full((1, 12), 70000), np.zeros((1, 12)), [100], [0])
    with pytest.raises(ProtocolError, match="12 samples"):
        ld.encode_packets([3600], [0], np.zeros((1, 11)), np.zeros((1, 11)), [100], [0])
    with pytest.raises(ProtocolError, match="54 2c"):
        ld.parse_packet(b"\x55" * 47)


def test_implausible_packets_with_good_crc_are_not_packets() -> None:
    def one(speed: int, start: int, end: int) -> bytes:
        return ld.encode_packets([speed], [start], np.full((1, 12), 1000),
                                 np.full((1, 12), 9), [end], [0])

    for bad in (one(0, 100, 980), one(3600, 36001, 880), one(3600, 100, 36500),
                one(60000, 100, 980), one(3600, 100, 100), one(3600, 100, 20000)):
        packets, counters = ld.locate_packets(bad * 3)
        assert len(packets) == 0
        assert counters.resyncs == 3
    assert len(ld.locate_packets(one(3600, 100, 980) * 3)[0]) == 3


# -- locating in a stream ------------------------------------------------------------------

def located(data: bytes, cuts: list[int]) -> tuple[list[int], dict[str, int]]:
    locator = ld.PacketLocator()
    points = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    out = [locator.feed(data[a:b]) for a, b in itertools.pairwise(points)]
    out.append(locator.finish())
    return ld.Packets.concat(out).offset.tolist(), locator.counters.as_dict()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cuts=st.lists(st.integers(0, 10_000), max_size=30))
def test_any_split_locates_identically(cuts: list[int]) -> None:
    data, _ = stream(40)
    rng = np.random.default_rng(3)
    noisy = (b"\x54\x2c\x54" + data[:470] + bytes(rng.integers(0, 256, 60, np.uint8))
             + b"\x54\x2c" + data[470:1000] + data[1010:] + b"\x54")
    whole = located(noisy, [])
    assert len(whole[0]) == 39  # 40 packets, one cut by the 10 missing bytes
    assert located(noisy, cuts) == whole


def test_consumed_plus_skipped_is_everything() -> None:
    data, _ = stream(30)
    noisy = b"xx\x54\x2c" + data[:200] + data[210:] + b"\x54\x2c\x00"
    _, counters = located(noisy, [100, 500, 900])
    assert counters["frames_decoded"] * 47 + counters["bytes_skipped"] == len(noisy)


def damage(data: bytes, seed: int, rate: float) -> tuple[bytes, list[int]]:
    """Damage whole packets at random (byte flips, truncation, garbage with markers and
    packet-shaped fakes with good CRCs inserted: :func:`benchmarks.harness.damage_frames`);
    return the new stream and the indices of the packets left intact."""
    rng = np.random.default_rng(seed)

    def fake() -> bytes:
        packet = bytearray(rng.integers(0, 256, 47, np.uint8).tobytes())
        packet[:2] = b"\x54\x2c"
        packet[46] = ld.crc8(bytes(packet[:46]))
        return bytes(packet)

    packets = [data[k * 47:(k + 1) * 47] for k in range(len(data) // 47)]
    return damage_frames(packets, rng, rate, fake, markers=b"\x54\x2c")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_intact_packet_is_recovered_from_a_damaged_stream(seed: int) -> None:
    data, _ = stream(5000, jitter=0.003, seed=seed)
    damaged, intact = damage(data, seed, rate=0.3)
    sent = ld.locate_packets(data)[0]
    packets, counters = ld.locate_packets(damaged)
    key = lambda p, i: (int(p.start_cdeg[i]), int(p.timestamp_ms[i]),  # noqa: E731
                        p.distance_mm[i].tobytes())
    want = {key(sent, k) for k in intact}
    got = [key(packets, i) for i in range(len(packets))]
    assert len(want) == len(intact)
    assert want <= set(got)  # 100 % of intact packets
    assert not set(got) - {key(sent, k) for k in range(len(sent))}  # nothing false
    assert counters.checksum_failures > 0 and counters.resyncs > 0


def test_lenient_keeps_damaged_packets_where_packets_should_be() -> None:
    data, _ = stream(20)
    broken = bytearray(data)
    broken[5 * 47 + 10] ^= 0xFF
    strict, counters = ld.locate_packets(bytes(broken))
    lenient, _ = ld.locate_packets(bytes(broken), lenient=True)
    assert len(strict) == 19 and counters.checksum_failures == 1
    assert len(lenient) == 20 and lenient.crc_ok.tolist().count(False) == 1
    profiles, _ = ld.decode_revolutions(bytes(broken), lenient=True)
    assert [p.checksum_ok for p in profiles] == [False]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=3000))
def test_fuzz_arbitrary_bytes_raise_nothing_but_scanpipe_errors(data: bytes) -> None:
    try:
        ld.decode_revolutions(data)
        ld.decode_revolutions(data, lenient=True)
        ld.detect_score(data)
    except ScanpipeError:
        pass


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(bodies=st.lists(st.binary(min_size=45, max_size=45), min_size=1, max_size=40),
       cuts=st.lists(st.integers(0, 2000), max_size=5))
def test_fuzz_packets_with_good_crcs_and_any_fields(bodies: list[bytes], cuts: list[int]) -> None:
    packets = []
    for body in bodies:
        head = b"\x54\x2c" + body
        packets.append(head + bytes([ld.crc8(head)]))
    data = b"".join(packets)
    try:
        decoder = ld.RevolutionDecoder()
        points = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
        for a, b in itertools.pairwise(points):
            for rev in decoder.feed(data[a:b]):
                assert rev.profile.ranges_m.dtype == np.float32
        decoder.finish()
    except ScanpipeError:
        pass


# -- revolutions ---------------------------------------------------------------------------

def test_profiles_round_trip_through_packets() -> None:
    ranges = np.linspace(0.5, 11.0, 360).astype(np.float32)
    ranges[[3, 50, 51]] = np.nan
    echo = (np.arange(360) % 256).astype(np.uint16)
    profiles = [Profile(frame=k, sector=0, start_angle_deg=0.0, step_deg=1.0,
                        ranges_m=ranges, echo=echo, device_time_ms=(29_900 + 100 * k) % 30_000)
                for k in range(4)]
    data = b"".join(ld.encode_profile(p) for p in profiles)
    decoded, counters = ld.decode_revolutions(data)
    assert counters.frames_decoded == 4 * 30
    assert [p.frame for p in decoded] == [0, 1, 2, 3]
    for p in decoded:
        assert p.step_deg == 1.0 and p.start_angle_deg == 0.0
        np.testing.assert_allclose(p.ranges_m, ranges, atol=0.0005)
        assert p.echo is not None and p.echo.tolist() == echo.tolist()
    # The device clock wraps at 30 000 ms: times are handed out modulo 30 000.
    assert [p.device_time_ms for p in decoded] == [29_900, 0, 100, 200]
    assert [p.device_end_time_ms for p in decoded] == [0, 100, 200, 300]  # 29 999.7 → 0


def test_jittered_head_resamples_to_the_grid_within_a_millimetre() -> None:
    data, _ = stream(2000, jitter=0.01, seed=5)
    profiles, _ = ld.decode_revolutions(data)
    beams = len(profiles[0].ranges_m)
    assert beams == 450 and all(len(p.ranges_m) == beams for p in profiles[:-1])
    assert len(profiles[-1].ranges_m) < beams  # the stream ends in the middle of a turn
    grid = np.arange(beams) * profiles[0].step_deg
    truth = 1.0 + 0.5 * np.sin(np.radians(grid))
    for p in profiles[1:-1]:
        assert np.nanmax(np.abs(p.ranges_m - truth)) < 0.0012
        assert not np.isnan(p.ranges_m).any()


def test_a_lost_packet_leaves_a_hole_not_an_interpolation() -> None:
    data, _ = stream(200)
    cut = data[:100 * 47] + data[101 * 47:]
    profiles, _ = ld.decode_revolutions(cut)
    holes = sum(int(np.isnan(p.ranges_m).sum()) for p in profiles[1:-1])
    assert 10 <= holes <= 13


def test_revolutions_follow_the_angle_wrap_and_gaps() -> None:
    data, _ = stream(3000, t0_ms=29_000)  # crosses the device's 30 000 ms wrap
    profiles, _ = ld.decode_revolutions(data)
    frames = [p.frame for p in profiles]
    assert frames == list(range(len(frames)))
    starts = np.array([p.device_time_ms for p in profiles])
    steps = np.diff(starts) % 30_000
    assert np.all(np.abs(steps - 100) <= 1)
    # A gap of whole turns (bytes lost for 0.5 s) skips frame numbers, as the head turned.
    gap = data[:1000 * 47] + data[1187 * 47:]
    frames = [p.frame for p in ld.decode_revolutions(gap)[0]]
    assert frames[-1] == len(profiles) - 1
    assert len(frames) < len(profiles)


def emulated_turns(turns: list[int]) -> tuple[bytes, list[int]]:
    """The live emulator's packets for head turns ``turns`` (each ends on its last sample; the
    first packets of turns 2 and 3 begin at 359.98° by encoder jitter), and the stream offset
    one past each turn's last packet."""
    from scanpipe.rig import default_rig
    from scanpipe.sim.ldrobot_device import LdrobotEmulated

    config = default_rig("ld06").scanner
    device = LdrobotEmulated(config)
    ranges = (2.0 + 0.3 * np.sin(np.radians(np.arange(450) * 0.8))).astype(np.float32)
    parts = [device.encode(k, ranges, None, config, k / config.scan_hz) for k in turns]
    return b"".join(parts), np.cumsum([len(part) for part in parts]).tolist()


def revolutions(data: bytes) -> list[ld.Revolution]:
    decoder = ld.RevolutionDecoder()
    return decoder.feed(data) + decoder.finish()


def test_a_revolutions_receive_time_is_the_packet_that_reaches_its_end() -> None:
    # The emulator sends a turn at once: the packet after a turn's last one comes a turn
    # later, so a revolution received with it would put the fitted device clock a turn late.
    data, turn_ends = emulated_turns([0, 1, 2, 3, 4])
    out = revolutions(data)
    assert [r.profile.frame for r in out] == [0, 1, 2, 3, 4]
    assert [r.end_offset for r in out] == turn_ends
    # A device streaming without pause (no turn boundary in its packets): the first packet
    # whose last sample is within half a grid step of the revolution's last beam.
    data, angles = stream(1200)
    out = revolutions(data)
    beams = len(out[0].profile.ranges_m)
    for r in out[:-1]:
        end = (r.profile.frame + 1) * 360.0 - 1.5 * 360.0 / beams
        assert r.end_offset == (int(np.argmax(angles[:, -1] >= end)) + 1) * ld.PACKET_BYTES


def test_a_skipped_turn_costs_coverage_not_a_revolution_of_holes() -> None:
    # Turn 2 never sent (a host too slow for the emulator); turn 3's first sample lies at
    # 359.98°, below turn 3's 0°: it is turn 3's, not a revolution 2 of one sample.
    data, turn_ends = emulated_turns([0, 1, 3, 4])
    out = revolutions(data)
    assert [r.profile.frame for r in out] == [0, 1, 3, 4]
    assert [r.end_offset for r in out] == turn_ends  # none a turn early or late
    times = [r.profile.device_time_ms for r in out]
    assert np.diff(times).tolist() == [100, 200, 100]
    for r in out:
        assert np.isfinite(r.profile.ranges_m).all()


def test_a_turn_cut_short_by_the_end_of_the_stream_ends_at_its_last_sample() -> None:
    data, _ = emulated_turns([0, 1, 2])
    cut = data[:-20 * ld.PACKET_BYTES]  # turn 2 ends after 18 of its 38 packets
    out = revolutions(cut)
    last = out[-1].profile
    assert [len(r.profile.ranges_m) for r in out] == [450, 450, 18 * 12]
    assert np.isfinite(last.ranges_m).all()
    # Its end time is its last beam's (18 packets of 12 samples at 4 500/s), not a guess a
    # turn ahead of when it was received.
    assert last.device_end_time_ms is not None and last.device_time_ms is not None
    assert abs(last.device_end_time_ms - last.device_time_ms - (18 * 12 - 1) / 4.5) <= 1.5
    assert out[-1].end_offset == len(cut)


def test_grid_is_fixed_once_per_stream() -> None:
    fast, _ = stream(900, speed_dps=4000)
    profiles, _ = ld.decode_revolutions(fast)
    assert {len(p.ranges_m) for p in profiles[:-1]} == {405}
    assert len(profiles[-1].ranges_m) < 405  # cut short by the end of the stream
    with pytest.raises(ProtocolError, match="beams"):
        ld.RevolutionAssembler(grid_beams=5)


def test_stl27l_rate_gives_2160_beams() -> None:
    data, _ = stream(2000, rate_hz=21_600)
    profiles, _ = ld.decode_revolutions(data)
    assert len(profiles[1].ranges_m) == 2160


def test_detection_needs_chained_packets() -> None:
    data, _ = stream(10)
    assert ld.detect_score(data) == 10
    lone = ld.encode_packets([3600], [100], np.full((1, 12), 900), np.zeros((1, 12)),
                             [980], [0])
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, 400, np.uint8).tobytes()
    assert ld.detect_score(noise + lone + noise + lone + noise) == 0


def test_device_times_unwrap_at_30000_against_host_time() -> None:
    from scanpipe.clock import unwrap_device_ticks

    # 100 ms revolutions, then a 45 s pause (longer than the device's wrap), then more.
    true_ms = np.concatenate([np.arange(0, 20_000, 100), 65_000 + np.arange(0, 20_000, 100)])
    host_ns = 1_700_000_000_000_000_000 + true_ms * 1_000_000 + 3_000_000
    raw = (true_ms + 29_000) % 30_000
    unwrapped = unwrap_device_ticks(raw, host_ns, ld.TIME_WRAP_MS, 1_000_000)
    assert np.array_equal(unwrapped - unwrapped[0], true_ms)


def test_profiles_of_450_beams_round_trip_with_an_overlapping_last_packet() -> None:
    ranges = (1.0 + 0.5 * np.sin(np.radians(np.arange(450) * 0.8))).astype(np.float32)
    profiles = [Profile(frame=k, sector=0, start_angle_deg=0.0, step_deg=0.8,
                        ranges_m=ranges, device_time_ms=100 * k) for k in range(4)]
    data = b"".join(ld.encode_profile(p) for p in profiles)
    assert len(data) == 4 * 38 * ld.PACKET_BYTES
    decoded, counters = ld.decode_revolutions(data)
    assert counters.frames_decoded == 4 * 38 and len(decoded) == 4
    for p in decoded:
        assert len(p.ranges_m) == 450
        np.testing.assert_allclose(p.ranges_m, ranges, atol=0.0005)
