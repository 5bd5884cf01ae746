"""A cut frame followed by intact ones: no intact frame lost, no false frame passed as good.

An 8-bit XOR passes one random span in 256, so a frame cut short whose claimed length reaches
into the frames after it sometimes "passes the checksum". These tests build such streams in
both dialects (and force the rare coincidences on purpose) and score the decode against the
profiles actually sent.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_decode_stage import CliRunner, write_scan

from scanpipe.protocol import ldoem
from scanpipe.protocol.framing import xor_checksum
from scanpipe.protocol.profile import TICKS_PER_TURN, Profile
from scanpipe.protocol.registry import (
    DIALECTS,
    ChecksumMode,
    RecoveryScore,
    StreamDecoder,
    decode_bytes,
    score_recovery,
)

# The shared framing (marker, length, payload, XOR); CoLa-A has its own (test_protocol_sick_cola).
DIALECT_NAMES = sorted(d for d, v in DIALECTS.items() if v.reader_factory is None)


def random_profile(rng: np.random.Generator, frame: int, samples: int,
                   max_step_ticks: int = TICKS_PER_TURN) -> Profile:
    """A plausible profile with random ranges (so every span has a random XOR)."""
    wire = rng.integers(0, 1 << 16, samples)
    step = int(rng.integers(1, min(TICKS_PER_TURN // max(samples - 1, 1), max_step_ticks) + 1))
    t_ms = int(rng.integers(0, 1 << 16))
    return Profile(frame=frame & 0xFFFF, sector=0,
                   start_angle_deg=int(rng.integers(0, TICKS_PER_TURN)) / 16,
                   step_deg=step / 16,
                   ranges_m=np.where(wire == 0, np.nan, wire / 256).astype(np.float32),
                   device_time_ms=t_ms, device_end_time_ms=(t_ms + 50) & 0xFFFF)


def encode(dialect: str, rng: np.random.Generator, frame: int,
           samples: int) -> tuple[bytes, list[Profile]]:
    """One intact frame and its profiles as the dialect decodes them from it alone."""
    # SICK steps are u16 in 1/10000°: at most 6.5535° (104/16°).
    p = random_profile(rng, frame, samples, 104 if dialect.startswith("cola") else TICKS_PER_TURN)
    if dialect == "ldoem" and rng.random() < 0.3:
        data = ldoem.encode_profile_reply([p], mask=ldoem.MASK_RANGES_ECHO)
    else:
        data = DIALECTS[dialect].encode_profile(p)
    profiles = DIALECTS[dialect].decode_payload(data[8:-1], True)
    assert profiles is not None
    return data, profiles


def cut_case(dialect: str, rng: np.random.Generator) -> tuple[bytes, list[Profile]]:
    """[intact] + a frame cut at a random point + 1…3 intact frames, consecutive counters."""
    first = int(rng.integers(0, 1 << 16))
    n_before, n_after = int(rng.integers(0, 2)), int(rng.integers(1, 4))
    parts, expected = [], []
    for k in range(n_before + 1 + n_after):
        data, profiles = encode(dialect, rng, first + k, int(rng.integers(0, 40)))
        if k == n_before:
            data = data[:int(rng.integers(1, len(data)))]
        else:
            expected += profiles
        parts.append(data)
    return b"".join(parts), expected


def decode_split(data: bytes, dialect: str, cuts: list[int],
                 checksum: ChecksumMode = "strict", confirm: bool = True
                 ) -> tuple[list[Profile], StreamDecoder]:
    decoder = StreamDecoder(dialect, checksum, confirm=confirm)
    bounds = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    out = []
    for a, b in itertools.pairwise(bounds):
        out += decoder.feed(data[a:b])
    return out + decoder.finish(), decoder


def score(data: bytes, expected: list[Profile], dialect: str, cuts: list[int] | None = None,
          checksum: ChecksumMode = "strict", confirm: bool = True) -> RecoveryScore:
    profiles, decoder = decode_split(data, dialect, cuts or [], checksum, confirm)
    return score_recovery(expected, profiles, decoder.counters)


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_ten_thousand_cut_frames_lose_nothing_and_pass_nothing_false(dialect: str) -> None:
    rng = np.random.default_rng(20261123)
    lost = false_good = implausible = 0
    for _ in range(10_000):
        data, expected = cut_case(dialect, rng)
        s = score(data, expected, dialect)
        lost += s.lost
        false_good += s.false_good
        implausible += s.counters.implausible_frames
    assert (lost, false_good) == (0, 0)
    assert implausible > 0  # the XOR did pass some cut frames: the other checks caught them


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_the_xor_alone_passes_false_frames(dialect: str) -> None:
    """The control: without the checks beyond the XOR, the same cases go wrong (issue text)."""
    rng = np.random.default_rng(20261123)
    bad = 0
    for _ in range(1500):
        data, expected = cut_case(dialect, rng)
        s = score(data, expected, dialect, confirm=False)
        bad += s.lost + s.false_good
    assert bad > 0


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), cuts=st.lists(st.integers(0, 1000), max_size=8),
       checksum=st.sampled_from(["strict", "lenient"]))
def test_cut_frame_then_intact_frames_any_split(dialect: str, seed: int, cuts: list[int],
                                                checksum: ChecksumMode) -> None:
    data, expected = cut_case(dialect, np.random.default_rng(seed))
    s = score(data, expected, dialect, cuts, checksum)
    assert (s.lost, s.false_good) == (0, 0)
    whole, _ = decode_split(data, dialect, [], checksum)
    split, _ = decode_split(data, dialect, cuts, checksum)
    assert len(whole) == len(split)
    assert all(a.same_as(b) for a, b in zip(whole, split, strict=True))


def forced_cases(dialect: str, kind: str, count: int) -> list[tuple[bytes, list[Profile]]]:
    """Cut-frame streams in which the cut frame's claimed span passes the XOR.

    ``inside``: the span ends inside the next frame; ``boundary``: it ends exactly where an
    intact frame ends, with another frame after it; ``end``: the same at the end of the stream.
    """
    rng = np.random.default_rng(7)
    found: list[tuple[bytes, list[Profile]]] = []
    while len(found) < count:
        frame = int(rng.integers(0, 1 << 16))
        a, _ = encode(dialect, rng, frame, int(rng.integers(60, 80)))
        b, b_profiles = encode(dialect, rng, frame + 1, int(rng.integers(0, 15)))
        c, c_profiles = encode(dialect, rng, frame + 2, int(rng.integers(0, 15)))
        if kind == "inside":
            cut = int(rng.integers(len(a) - len(b) + 9, len(a)))  # span ends in b's data
            data, expected = a[:cut] + b + c, b_profiles + c_profiles
        else:
            cut = len(a) - len(b)  # the span covers b exactly
            tail = c if kind == "boundary" else b""
            data = a[:cut] + b + tail
            expected = b_profiles + (c_profiles if tail else [])
        span = data[8:len(a) - 1]  # with its header kept whole, the cut frame parses
        if cut >= 40 and xor_checksum(span) == data[len(a) - 1]:
            found.append((data, expected))
    return found


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
@pytest.mark.parametrize("kind", ["inside", "boundary", "end"])
def test_cut_frames_that_pass_the_xor_are_caught(dialect: str, kind: str) -> None:
    for data, expected in forced_cases(dialect, kind, 12):
        for cuts in ([], [len(data) - 3], [len(data) // 2, len(data) - 8]):
            trusting = score(data, expected, dialect, cuts, confirm=False)
            if not dialect.startswith("cola"):  # CoLa's strict layout refuses the cut too
                assert trusting.lost + trusting.false_good > 0  # the XOR alone is fooled
            s = score(data, expected, dialect, cuts)
            assert (s.lost, s.false_good, s.recovered) == (0, 0, len(expected)), (kind, cuts)
            # CoLa's strict layout refuses the cut frame as malformed before the checks
            assert s.counters.implausible_frames + (
                s.counters.malformed_frames + s.counters.length_mismatches
                if dialect.startswith("cola") else 0) == 1


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_intact_frame_followed_by_garbage_with_a_marker_inside_it_is_kept(dialect: str) -> None:
    """A marker inside a frame's data is harmless unless it is followed by a sane length."""
    marker = DIALECTS[dialect].marker
    wire = np.frombuffer(marker * 3 + b"\xff\xff", dtype=">u2")
    inner = Profile(frame=3, sector=0, start_angle_deg=0.0, step_deg=1.0,
                    ranges_m=(wire / 256).astype(np.float32))
    frame = DIALECTS[dialect].encode_profile(inner)
    profiles, counters = decode_bytes(frame + b"garbage" + frame, dialect)
    assert [p.frame for p in profiles] == [3, 3]
    assert counters.implausible_frames == 0


def test_a_held_frame_is_released_by_the_next_bytes_or_the_end() -> None:
    rng = np.random.default_rng(1)
    a, _ = encode("paper", rng, 1, 5)
    b, _ = encode("paper", rng, 2, 5)
    decoder = StreamDecoder("paper")
    assert decoder.feed(a) == []  # the 7 bytes after it decide: held
    assert [p.frame for p in decoder.feed(b[:7])] == [1]
    assert decoder.feed(b[7:]) == []
    assert [p.frame for p in decoder.finish()] == [2]
    unconfirmed = StreamDecoder("paper", confirm=False)
    assert [p.frame for p in unconfirmed.feed(a)] == [1]


def test_ldoem_reader_for_request_reply_links_does_not_hold() -> None:
    reader = ldoem.FrameReader(accept_unknown=True)
    assert len(reader.feed(ldoem.get_status_request())) == 1


# CoLa-B refuses such a cut frame by its layout (malformed), not by the checks: counted there.
@pytest.mark.parametrize("dialect", [d for d in DIALECT_NAMES if not d.startswith("cola")])
def test_counters_reach_the_cli_and_the_decode_report(tmp_path: Path, cli: CliRunner,
                                                      dialect: str) -> None:
    data, expected = forced_cases(dialect, "inside", 1)[0]
    capture = tmp_path / "capture.bin"
    capture.write_bytes(data)
    result = cli("frames", capture, "--dialect", dialect, "--checksum", "strict", "--json")
    assert result.code == 0, result.err
    out = json.loads(result.out)
    assert [f["frame"] for f in out["frames"]] == [p.frame for p in expected]
    assert out["counters"]["implausible_frames"] == 1
    assert out["counters"]["length_mismatches"] == 0
    assert capture.read_bytes() == data  # the capture is only read

    write_scan(tmp_path / "s.mcap", [data])
    result = cli("decode", tmp_path / "s.mcap", "--out", tmp_path / "out", "-q",
                 "--set", f"dialect={dialect}")
    assert result.code == 0, result.err
    assert "rejected frames     0 length mismatches, 1 implausible" in result.out
    report = json.loads(cli("decode", tmp_path / "s.mcap", "--out", tmp_path / "out", "-q",
                            "--set", f"dialect={dialect}", "--json").out)
    assert report["counters"]["implausible_frames"] == 1
    assert report["counts"]["profiles"] == len(expected)
