"""The paper dialect: the golden frame printed in the paper, encoder round trips, frame sizes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scanpipe.errors import ProtocolError
from scanpipe.planning import frame_bytes
from scanpipe.protocol import ldoem, paper
from scanpipe.protocol.framing import LengthMismatch, xor_checksum
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import decode_bytes, detect_dialect

#: The frame printed in the paper, byte for byte (shared/paper/NOTES.md).
GOLDEN = bytes.fromhex(
    "02020202 0000001f 73524100 62000c81 ba0101 13da 0000 0480 0005 0000"
    "0019 017a 0170 0170 0181 8a".replace(" ", "")
)
GOLDEN_RANGES_M = [0.09765625, 1.4765625, 1.4375, 1.4375, 1.50390625]


def test_golden_frame_is_a_checksum_mismatch_in_strict_mode() -> None:
    profiles, counters = decode_bytes(GOLDEN, "paper", "strict")
    assert profiles == []
    assert counters.checksum_failures == 1
    assert counters.frames_decoded == 0
    assert counters.bytes_skipped == len(GOLDEN)


def test_golden_frame_values_in_lenient_mode() -> None:
    profiles, counters = decode_bytes(GOLDEN, "paper", "lenient")
    assert counters.checksum_failures == 1 and counters.frames_decoded == 1
    (p,) = profiles
    assert p.frame == 5082
    assert p.step_deg == 72.0
    assert p.start_angle_deg == 0.0
    assert p.sector == 0
    assert p.ranges_m.dtype == np.float32
    assert p.ranges_m.tolist() == GOLDEN_RANGES_M
    assert p.checksum_ok is False
    assert p.echo is None and p.device_time_ms is None


def test_golden_checksum_printed_and_computed() -> None:
    data = GOLDEN[8:-1]
    assert len(data) == 0x1F
    assert GOLDEN[-1] == 0x8A
    assert xor_checksum(data) == 0x9F
    assert xor_checksum(GOLDEN[:-1]) == 0x80  # over the whole frame, as the notes say


def test_golden_frame_is_detected_as_paper() -> None:
    assert detect_dialect(GOLDEN) == "paper"


def test_encoder_reproduces_the_golden_frame_with_a_correct_checksum() -> None:
    profile = Profile(frame=5082, sector=0, start_angle_deg=0.0, step_deg=72.0,
                      ranges_m=np.array(GOLDEN_RANGES_M, np.float32))
    frame = paper.encode_profile(profile)
    assert frame[:-1] == GOLDEN[:-1]
    assert frame[-1] == 0x9F


ranges = st.lists(st.one_of(st.floats(0.004, 255.0), st.just(float("nan"))), max_size=200)


@settings(max_examples=60, deadline=None)
@given(frame=st.integers(0, 0xFFFF), step=st.integers(1, 1440), start=st.integers(0, 5760),
       values=ranges)
def test_round_trip(frame: int, step: int, start: int, values: list[float]) -> None:
    values = values[: 5760 // step + 1]  # a 360° scanner: samples span at most one turn
    wire = np.rint(np.array(values, np.float64) * 256) / 256  # representable ranges
    profile = Profile(frame=frame, sector=0, start_angle_deg=start / 16, step_deg=step / 16,
                      ranges_m=wire.astype(np.float32))
    (decoded,), counters = decode_bytes(paper.encode_profile(profile), "paper")
    assert counters.checksum_failures == 0
    assert decoded.same_as(profile)


def test_frame_bytes_matches_the_encoders() -> None:
    for samples in (0, 1, 5, 1440, 2881):
        profile = Profile(frame=1, sector=0, start_angle_deg=0.0, step_deg=0.25,
                          ranges_m=np.ones(samples, np.float32))
        assert len(paper.encode_profile(profile)) == frame_bytes("paper", samples)
        assert len(ldoem.encode_profile(profile)) == frame_bytes("ldoem", samples)
        echo = ldoem.encode_profile_reply([profile], mask=ldoem.MASK_RANGES_ECHO)
        assert len(echo) == frame_bytes("ldoem", samples, with_echo=True)


def test_malformed_payload_is_a_protocol_error() -> None:
    with pytest.raises(LengthMismatch, match=r"declares 5 samples: expected 21 \+ 2·samples"):
        paper.decode_payload(GOLDEN[8:-2])
    with pytest.raises(ProtocolError, match=r"'sRA' header"):
        paper.decode_payload(b"sRB" + GOLDEN[11:-1])


def test_sample_count_disagreeing_with_length_is_rejected_and_counted() -> None:
    """A frame whose good checksum covers a payload of the wrong length for its sample count."""
    good = paper.encode_profile(Profile(frame=1, sector=0, start_angle_deg=0.0, step_deg=1.0,
                                        ranges_m=np.ones(4, np.float32)))
    payload = bytearray(good[8:-1])
    payload[18] = 5  # declares 5 samples, carries 4
    forged = paper.MARKER + len(payload).to_bytes(4, "big") + bytes(payload)
    forged += bytes([xor_checksum(bytes(payload))])
    for mode in ("strict", "lenient"):
        profiles, counters = decode_bytes(forged + good, "paper", mode)  # type: ignore[arg-type]
        assert [p.frame for p in profiles] == [1]
        assert counters.length_mismatches == 1 and counters.malformed_frames == 0
    # With a bad checksum the lenient path counts it too, and strict drops it as a failure.
    damaged = forged[:-1] + bytes([forged[-1] ^ 1])
    profiles, counters = decode_bytes(damaged, "paper", "lenient")
    assert profiles == [] and counters.length_mismatches == 1


@pytest.mark.parametrize(("start_deg", "step_deg", "samples"), [
    (360.0625, 1.0, 3),  # start past a turn
    (0.0, 400.0, 1),  # step past a turn
    (0.0, 0.0, 3),  # several samples at one angle
    (10.0, 1.0, 362),  # 361° of samples
])
def test_implausible_angles_are_rejected_and_counted(start_deg: float, step_deg: float,
                                                      samples: int) -> None:
    bad = Profile(frame=1, sector=0, start_angle_deg=start_deg, step_deg=step_deg,
                  ranges_m=np.ones(samples, np.float32))
    good = Profile(frame=2, sector=0, start_angle_deg=0.0, step_deg=1.0,
                   ranges_m=np.ones(3, np.float32))
    data = paper.encode_profile(bad) + paper.encode_profile(good)
    profiles, counters = decode_bytes(data, "paper")
    assert [p.frame for p in profiles] == [2]
    assert counters.implausible_frames == 1 and counters.resyncs == 1
    # The edges of the device's range are fine: 0…360° start, a whole turn of samples.
    edge = Profile(frame=3, sector=0, start_angle_deg=360.0, step_deg=0.25,
                   ranges_m=np.ones(1441, np.float32))
    assert [p.frame for p in decode_bytes(paper.encode_profile(edge), "paper")[0]] == [3]


def test_angles_out_of_range_are_refused() -> None:
    profile = Profile(frame=1, sector=0, start_angle_deg=-1.0, step_deg=1.0,
                      ranges_m=np.ones(3, np.float32))
    with pytest.raises(ProtocolError, match=r"angle -1\.0"):
        paper.encode_profile(profile)
