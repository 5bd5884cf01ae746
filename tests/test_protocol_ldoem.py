"""The LD-OEM 1000 dialect: profile replies for every format mask bit, requests, USP framing."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scanpipe.errors import ProtocolError
from scanpipe.protocol import ldoem
from scanpipe.protocol.framing import xor_checksum
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import decode_bytes


def usp(payload: bytes) -> bytes:
    """A USP frame built by hand, independent of the encoder."""
    return b"\x02USP" + struct.pack(">I", len(payload)) + payload + bytes([xor_checksum(payload)])


def sector(n: int, sector_index: int = 0, echo: bool = False, t_ms: int = 1000,
           frame: int = 7) -> Profile:
    rng = np.random.default_rng(n + sector_index)
    wire = rng.integers(1, 65535, n)
    wire[::7] = 0  # no return
    ranges = np.where(wire == 0, np.nan, wire / 256).astype(np.float32)
    return Profile(frame=frame, sector=sector_index, start_angle_deg=90.0 * sector_index,
                   step_deg=0.25, ranges_m=ranges,
                   echo=rng.integers(0, 65535, n).astype(np.uint16) if echo else None,
                   device_time_ms=t_ms, device_end_time_ms=(t_ms + 50) & 0xFFFF)


def test_hand_built_0x39ff_reply() -> None:
    """Layout of mask 0x39FF from the device facts: header, sector fields, points, trailer."""
    distances = [256, 0, 512 + 128]
    payload = (bytes([0x83, 0x01]) + struct.pack(">HH", 0x39FF, 1)
               + struct.pack(">HHH", 11, 4242, 0)  # PROFILESENT, PROFILECOUNT, LAYERNUM
               + struct.pack(">HHHHH", 0, 4, 3, 65000, 1440)  # SECTORNUM…STARTDIR
               + struct.pack(">3H", *distances)
               + struct.pack(">HH", 464, 1448)  # TEND, ENDDIR
               + bytes([0, 0, 0, 0x03]))  # SENSTAT: motor OK, sensor MEASURE
    (p,), counters = decode_bytes(usp(payload), "ldoem")
    assert counters.frames_decoded == 1
    assert p.frame == 4242 and p.sector == 0
    assert p.step_deg == 0.25 and p.start_angle_deg == 90.0
    assert np.array_equal(p.ranges_m, [1.0, np.nan, 2.5], equal_nan=True)
    assert p.echo is None
    assert p.device_time_ms == 65000 and p.device_end_time_ms == 464
    reply = ldoem.decode_profile_reply(payload)
    assert (reply.profile_sent, reply.layer) == (11, 0)
    assert (reply.sensor_mode, reply.motor_mode) == (ldoem.SENSOR_MEASURE, ldoem.MOTOR_OK)


def test_hand_built_0x3dff_reply_interleaves_distance_and_echo() -> None:
    payload = (bytes([0x83, 0x01]) + struct.pack(">HH", 0x3DFF, 1)
               + struct.pack(">HHH", 0, 9, 0) + struct.pack(">HHHHH", 2, 8, 2, 5, 0)
               + struct.pack(">4H", 300, 17, 600, 18) + struct.pack(">HH", 6, 8)
               + bytes([0, 0, 0, 0x93]))
    (p,), _ = decode_bytes(usp(payload), "ldoem")
    assert p.ranges_m.tolist() == [300 / 256, 600 / 256]
    assert p.echo is not None and p.echo.tolist() == [17, 18]
    assert p.sector == 2 and p.step_deg == 0.5
    assert ldoem.decode_profile_reply(payload).motor_mode == ldoem.MOTOR_SPIN_TOO_HIGH


@pytest.mark.parametrize("mask", [ldoem.MASK_RANGES, ldoem.MASK_RANGES_ECHO])
def test_common_masks_round_trip_several_sectors(mask: int) -> None:
    echo = bool(mask & ldoem.ECHO)
    sectors = [sector(1440, 0, echo), sector(10, 1, echo), sector(0, 2, echo)]
    frame = ldoem.encode_profile_reply(sectors, mask=mask, profile_sent=3)
    decoded, counters = decode_bytes(frame, "ldoem")
    assert counters.frames_decoded == 1 and len(decoded) == 3
    for got, sent in zip(decoded, sectors, strict=True):
        assert got.same_as(sent)


@pytest.mark.parametrize("bit", range(14))
def test_every_mask_bit_is_parsed_or_skipped(bit: int) -> None:
    """Toggle each bit of 0x3DFF: what the mask keeps round-trips, what it drops is absent."""
    mask = ldoem.MASK_RANGES_ECHO ^ (1 << bit)
    sent = sector(25, 3, echo=True, t_ms=65530, frame=999)
    (got,), counters = decode_bytes(ldoem.encode_profile_reply([sent], mask=mask), "ldoem")
    assert counters.frames_decoded == 1 and counters.malformed_frames == 0
    has = mask.__and__
    assert got.frame == (999 if has(ldoem.PROFILECOUNT) else 0)
    assert got.sector == (3 if has(ldoem.SECTORNUM) else 0)
    assert got.step_deg == 0.25  # from DIRSTEP, else from the per-point DIRECTION
    assert got.start_angle_deg == 270.0
    assert len(got.ranges_m) == 25  # from POINTNUM, else from the payload length
    if has(ldoem.DISTANCE):
        assert np.array_equal(got.ranges_m, sent.ranges_m, equal_nan=True)
    else:
        assert np.isnan(got.ranges_m).all()
    assert (got.echo is not None) == bool(has(ldoem.ECHO))
    assert got.device_time_ms == (65530 if has(ldoem.TSTART) else None)
    assert got.device_end_time_ms == (sent.device_end_time_ms if has(ldoem.TEND) else None)


def test_direction_field_gives_angles_without_dirstep_and_startdir() -> None:
    mask = (ldoem.MASK_RANGES | ldoem.DIRECTION) & ~(ldoem.DIRSTEP | ldoem.STARTDIR)
    sent = sector(5, 1)
    (got,), _ = decode_bytes(ldoem.encode_profile_reply([sent], mask=mask), "ldoem")
    assert (got.start_angle_deg, got.step_deg) == (90.0, 0.25)


@settings(max_examples=80, deadline=None)
@given(mask=st.integers(0, ldoem.ALL_MASK_BITS), sizes=st.lists(st.integers(0, 40), min_size=1,
                                                                 max_size=4))
def test_any_mask_round_trips_or_is_refused(mask: int, sizes: list[int]) -> None:
    sectors = [sector(n, i, echo=True) for i, n in enumerate(sizes)]
    frame = ldoem.encode_profile_reply(sectors, mask=mask)
    decoded, counters = decode_bytes(frame, "ldoem")
    ambiguous = (not mask & ldoem.POINTNUM and len(sizes) > 1
                 and mask & (ldoem.DISTANCE | ldoem.DIRECTION | ldoem.ECHO))
    if ambiguous:  # several sectors without point counts cannot be cut apart
        assert decoded == [] and counters.malformed_frames == 1
        return
    assert len(decoded) == len(sizes)
    for got, sent in zip(decoded, sectors, strict=True):
        same_size = got.ranges_m.size == sent.ranges_m.size
        if mask & ldoem.DISTANCE and (mask & ldoem.POINTNUM or same_size):
            assert np.array_equal(got.ranges_m, sent.ranges_m, equal_nan=True)


def test_leftover_or_missing_bytes_are_malformed() -> None:
    payload = ldoem.encode_profile(sector(4))[8:-1]
    with pytest.raises(ProtocolError, match="left over"):
        ldoem.decode_profile_reply(payload + b"\x00\x00")
    with pytest.raises(ProtocolError, match="ends inside"):
        ldoem.decode_profile_reply(payload[:-6])
    with pytest.raises(ProtocolError, match="only bits 0x3FFF"):
        ldoem.decode_profile_reply(payload[:2] + b"\xc0\x00" + payload[4:])


def test_requests_and_replies_parse() -> None:
    cases = [
        (ldoem.get_profile_request(0, ldoem.MASK_RANGES_ECHO), (0x03, 0x01, False)),
        (ldoem.cancel_profile_request(), (0x03, 0x02, False)),
        (ldoem.get_status_request(), (0x01, 0x02, False)),
        (ldoem.get_ident_request(), (0x01, 0x01, False)),
        (ldoem.get_config_request(0x10), (0x02, 0x02, False)),
        (ldoem.set_config_request(0x10, b"\x00\x05"), (0x02, 0x01, False)),
        (ldoem.set_time_abs_request(1234), (0x02, 0x03, False)),
        (ldoem.set_time_rel_request(-5), (0x02, 0x04, False)),
        (ldoem.get_sync_clock_request(), (0x02, 0x05, False)),
        (ldoem.rotate_request(5), (0x04, 0x03, False)),
        (ldoem.working_mode_request(ldoem.WORKING_MEASURE), (0x04, 0x04, False)),
        (ldoem.status_reply(ldoem.SENSOR_ROTATE, ldoem.MOTOR_OK), (0x01, 0x02, True)),
    ]
    reader = ldoem.FrameReader()
    frames = reader.feed(b"".join(frame for frame, _ in cases))
    assert len(frames) == len(cases) and all(f.checksum_ok for f in frames)
    for raw, (_, expected) in zip(frames, cases, strict=True):
        message = ldoem.parse_payload(raw.payload)
        assert (message.service, message.sub, message.is_reply) == expected
    assert ldoem.parse_get_profile_request(ldoem.parse_payload(frames[0].payload)) == (0, 0x3DFF)
    assert ldoem.parse_status_reply(ldoem.parse_payload(frames[-1].payload)) == (2, 0)
    assert ldoem.parse_payload(frames[7].payload).u16(0) == 0xFFFB


def test_other_replies_count_as_other_frames() -> None:
    stream = ldoem.status_reply() + ldoem.encode_profile(sector(3)) + ldoem.get_status_request()
    profiles, counters = decode_bytes(stream, "ldoem")
    assert len(profiles) == 1
    assert counters.other_frames == 2 and counters.frames_decoded == 1


def test_bad_requests_are_refused() -> None:
    with pytest.raises(ProtocolError, match="n_profiles"):
        ldoem.get_profile_request(70000)
    with pytest.raises(ProtocolError, match="format mask"):
        ldoem.get_profile_request(1, 0x4000)
    with pytest.raises(ProtocolError, match="time shift"):
        ldoem.set_time_rel_request(40000)
    with pytest.raises(ProtocolError, match="unknown service"):
        ldoem.parse_payload(b"\x09\x01")
    with pytest.raises(ProtocolError, match="at least one sector"):
        ldoem.encode_profile_reply([])
