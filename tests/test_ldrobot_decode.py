"""The ldrobot dialect through the registry, the decode stage and ``scanpipe frames``."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scanpipe.artifacts import read_artifact
from scanpipe.pipeline import execute, get_stage
from scanpipe.protocol import ldoem, ldrobot, paper
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import DIALECTS, StreamDecoder, decode_bytes, detect_dialect
from scanpipe.recording.schemas import RX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import default_rig
from scanpipe.stages.decode import DecodeParams

T0 = 1_700_000_000_000_000_000


def ld06_stream(seconds: float, t0_ms: int = 0, seed: int = 0) -> bytes:
    """An LD06-like stream: 4 500 samples/s at 10 Hz, ranges 2 + sin(angle) m."""
    n = int(seconds * 4500 / 12)
    rng = np.random.default_rng(seed)
    t = np.arange(n * 12) / 4500.0
    angle = (t * 3600.0).reshape(n, 12)
    dist = np.rint((2.0 + np.sin(np.radians(angle))) * 1000).astype(int)
    dist[rng.random(dist.shape) < 0.01] = 0
    return ldrobot.encode_packets(
        np.full(n, 3600), np.rint(angle[:, 0] * 100).astype(int) % 36000, dist,
        np.full(dist.shape, 180), np.rint(angle[:, -1] * 100).astype(int) % 36000,
        (t0_ms + np.floor(t[::12] * 1000).astype(int)) % 30000)


def test_registered_with_its_own_framing() -> None:
    d = DIALECTS["ldrobot"]
    assert d.reader_factory is not None and d.detect_score is not None
    profiles, counters = decode_bytes(ld06_stream(1.0), "ldrobot")
    assert len(profiles) == 10 and counters.frames_decoded == 10  # revolutions
    assert all(len(p.ranges_m) == 450 and p.device_wrap_ticks == 30_000 for p in profiles)


def test_auto_finds_ldrobot_and_nothing_else_takes_it() -> None:
    assert detect_dialect(b"\x00\x13" + ld06_stream(0.5)) == "ldrobot"
    # The other dialects' streams are not mistaken for it, and it is not mistaken for them.
    sector = Profile(frame=1, sector=0, start_angle_deg=0.0, step_deg=0.25,
                     ranges_m=np.full(1440, 84.0 / 256, np.float32),  # 0x54 0x00 everywhere
                     device_time_ms=44, device_end_time_ms=44)
    for name, encode in (("ldoem", ldoem.encode_profile), ("paper", paper.encode_profile)):
        data = b"".join(encode(sector) for _ in range(20))
        assert detect_dialect(data) == name
        assert not DIALECTS["ldrobot"].detect(data)
    assert not DIALECTS["ldoem"].detect(ld06_stream(0.5))
    assert not DIALECTS["paper"].detect(ld06_stream(0.5))


def test_stream_decoder_any_split_and_lenient() -> None:
    data = ld06_stream(1.0)
    broken = bytearray(data)
    broken[47 * 100 + 20] ^= 0x04
    whole = StreamDecoder("ldrobot").feed_frames(bytes(broken))
    decoder = StreamDecoder("ldrobot")
    split = []
    for a in range(0, len(broken), 997):
        split += decoder.feed_frames(bytes(broken[a:a + 997]))
    split += decoder.finish_frames()
    assert [f.profiles[0].frame for f in split][:len(whole)] == [
        f.profiles[0].frame for f in whole]
    assert decoder.counters.checksum_failures == 1
    # A damaged packet's samples are never used, in either mode: its turn has a hole.
    lenient = StreamDecoder("ldrobot", "lenient")
    frames = lenient.feed_frames(bytes(broken)) + lenient.finish_frames()
    assert all(f.checksum_ok for f in frames) and len(frames) == len(split)
    intact = decode_bytes(data, "ldrobot")[0]
    extra = [int(np.isnan(f.profiles[0].ranges_m).sum() - np.isnan(p.ranges_m).sum())
             for f, p in zip(frames, intact, strict=True)]
    assert sorted(extra)[-1] >= 11 and sorted(extra)[:-1] == [0] * (len(extra) - 1)


def write_recording(path: Path, data: bytes, bytes_per_s: float) -> None:
    """``data`` received in uneven serial reads at its byte rate."""
    rng = np.random.default_rng(1)
    with RecordingWriter(path, default_rig(), {"mode": "test"}) as writer:
        at = 0
        while at < len(data):
            n = int(rng.integers(1, 600))
            writer.write_stream("scanner", data[at:at + n], RX,
                                T0 + int((at + n) / bytes_per_s * 1e9))
            at += n


def test_decode_stage_unwraps_the_30000_ms_clock(tmp_path: Path) -> None:
    data = ld06_stream(40.0, t0_ms=25_000)  # the device clock wraps twice
    rec = tmp_path / "ld06.mcap"
    write_recording(rec, data, 375 * 47.0)
    for dialect in ("ldrobot", "auto"):
        record = execute(get_stage("decode"), {"recording": rec}, tmp_path / dialect,
                         DecodeParams.model_validate({"dialect": dialect}), force=True)
        profiles = read_artifact(record.outputs["profiles"])[0]
        assert record.report["dialect"] == "ldrobot"
        assert profiles.num_rows == 400
        start = profiles.column("device_time_ns").to_numpy()
        steps_ms = np.diff(start) / 1e6
        assert np.all(np.abs(steps_ms - 100) <= 1.0)  # 10 Hz turns, no wrap left
        end = profiles.column("device_end_time_ns").to_numpy()
        assert np.all(np.abs((end - start) / 1e6 - 99.8) <= 1.0)
        assert record.report["device_clock"]["rate"] == pytest.approx(1.0, abs=1e-3)
        assert set(profiles.column("dialect").to_pylist()) == {"ldrobot"}
        assert profiles.column("frame").to_pylist() == list(range(400))


def test_cli_frames_on_an_ldrobot_capture(tmp_path: Path, cli: Callable[..., Any]) -> None:
    capture = tmp_path / "ld06.bin"
    capture.write_bytes(ld06_stream(0.35))
    result = cli("frames", capture, "--dialect", "auto")
    assert result.code == 0, result.err
    assert "dialect ldrobot" in result.out and "step 0.8°" in result.out
    result = cli("frames", capture, "--dialect", "ldrobot", "--json")
    assert result.code == 0 and '"dialect": "ldrobot"' in result.out


def test_cli_frames_ldrobot_on_other_bytes_is_one_line(tmp_path: Path,
                                                       cli: Callable[..., Any]) -> None:
    capture = tmp_path / "not-ld.bin"
    payload = bytes(range(256)) * 4
    capture.write_bytes(payload)
    result = cli("frames", capture, "--dialect", "ldrobot")
    assert result.code == 1
    assert result.err.count("\n") == 1 and "no ldrobot frame" in result.err
    assert "Traceback" not in result.err
    assert capture.read_bytes() == payload
