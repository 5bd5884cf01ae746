"""``scanpipe import-video``: frames added with their times, everything else kept, errors safe."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import pytest
from acquire_helpers import rig_with_cameras, small_camera, write_video

from scanpipe.acquire.video_import import parse_start_time
from scanpipe.recording.reader import read_recording
from scanpipe.recording.writer import RecordingWriter

T0 = 1_767_225_600_000_000_000


def _recording(path: Path) -> Path:
    rig = rig_with_cameras(small_camera("cam0"), small_camera("phone"))
    with RecordingWriter(path, rig, {"mode": "step"}) as writer:
        for i in range(20):
            t = T0 + i * 100_000_000
            writer.write_stream("scanner", bytes([i]) * 10, 0, t)
            writer.write_motor_state(t, i, i, False, i * 1000)
        writer.write_event(T0 + 5, "scanner_connected", "hello", {"a": 1})
    return path


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_import_adds_frames_with_times_and_keeps_everything(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    before = read_recording(rec)
    video = write_video(tmp_path / "phone.avi", frames=12, fps=10.0)
    result = cli("import-video", video, "--into", rec, "--start-time", str(T0 / 1e9),
                 "--offset", "0.25", "--camera", "phone")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    after = read_recording(rec)
    assert after.complete and not after.warnings
    phone = [i for i in after.images if i.camera_id == "phone"]
    assert len(phone) == 12
    expected = [T0 + 250_000_000 + k * 100_000_000 for k in range(12)]
    assert [i.log_time_ns for i in phone] == pytest.approx(expected, abs=1000)
    assert after.stream("scanner").data == before.stream("scanner").data
    assert after.motor.step_count.tolist() == before.motor.step_count.tolist()
    assert [(e.kind, e.data) for e in after.events] == [(e.kind, e.data) for e in before.events]
    assert after.metadata["scanpipe.rig"] == before.metadata["scanpipe.rig"]
    assert after.metadata["scanpipe.session"] == before.metadata["scanpipe.session"]


def test_unknown_camera_leaves_the_recording_untouched(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    digest = _digest(rec)
    video = write_video(tmp_path / "v.avi")
    result = cli("import-video", video, "--into", rec, "--start-time", "recording",
                 "--camera", "nope")
    assert result.code == 2  # type: ignore[attr-defined]
    assert "no camera 'nope'" in result.err and "cam0, phone" in result.err  # type: ignore[attr-defined]
    assert _digest(rec) == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mcap", "v.avi"]


def test_unreadable_video_leaves_the_recording_untouched(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    digest = _digest(rec)
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video at all" * 100)
    result = cli("import-video", bad, "--into", rec, "--start-time", "recording")
    assert result.code == 1  # type: ignore[attr-defined]
    assert "bad.avi" in result.err  # type: ignore[attr-defined]
    assert _digest(rec) == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.avi", "rec.mcap"]


def test_start_time_forms() -> None:
    assert parse_start_time("2026-01-01T00:00:00Z") == T0
    assert parse_start_time("2026-01-01T01:00:00.5+01:00") == T0 + 500_000_000
    assert parse_start_time("2026-01-01T00:00:00") == T0
    assert parse_start_time(str(T0)) == T0
    assert parse_start_time("1767225600.25") == T0 + 250_000_000
    assert parse_start_time("recording", 42) == 42
    from scanpipe.errors import UsageError

    with pytest.raises(UsageError, match="not a time"):
        parse_start_time("yesterday")
