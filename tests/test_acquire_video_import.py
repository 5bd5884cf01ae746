"""``scanpipe import-video``: frames added with their times, everything else kept, errors safe."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
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


# Videos written by ffmpeg (tests/fixtures/README.md): 64 × 48 px, grey with a white 16 × 12 box
# in the top-left corner of the picture as stored, 10 frames at 10 fps unless said.
VIDEOS = Path(__file__).parent / "fixtures" / "video"


def _frames(rec: Path, camera: str = "phone") -> list[Any]:
    return [i for i in read_recording(rec).images if i.camera_id == camera]


def _pixels(image: Any) -> Any:
    return cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_GRAYSCALE)


def test_rotation_tag_gives_upright_frames_as_players_show_them(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    """A phone held upright stores landscape pixels and a display rotation: the frames are
    upright, as ffmpeg shows them (its own rendering of rotated90.mp4 puts the box at the
    bottom left), the orientation the rig's camera poses describe (the default rig's phones
    are upright); a rig camera held the other way is warned about at once."""
    rec = _recording(tmp_path / "rec.mcap")  # its cameras are 64 × 48, landscape
    result = cli("import-video", VIDEOS / "rotated90.mp4", "--into", rec, "--start-time",
                 str(T0 / 1e9), "--camera", "phone", "--json")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    assert '"display_rotation_deg": 270' in result.out  # type: ignore[attr-defined]
    frames = _frames(rec)
    assert len(frames) == 10
    first = _pixels(frames[0])
    assert first.shape == (64, 48)
    assert first[-12:, :12].mean() > 240 and first[:12, :12].mean() < 160
    assert "frames are 48×64 px, camera 'phone' of the recording's rig is 64×48" in result.err  # type: ignore[attr-defined]
    assert "the phone was held upright (portrait)" in result.err  # type: ignore[attr-defined]


def test_variable_frame_rate_uses_the_containers_times(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    result = cli("import-video", VIDEOS / "vfr.mkv", "--into", rec, "--start-time",
                 str(T0 / 1e9), "--camera", "phone")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    times_s = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.9, 1.1, 1.3]  # not index / fps
    assert [i.log_time_ns for i in _frames(rec)] == pytest.approx(
        [T0 + round(t * 1e9) for t in times_s], abs=1_000_000)
    assert "warning" not in result.err  # type: ignore[attr-defined]


def test_ten_bit_video_is_read(tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    result = cli("import-video", VIDEOS / "yuv420p10.mp4", "--into", rec, "--start-time",
                 str(T0 / 1e9), "--camera", "phone")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    first = _pixels(_frames(rec)[0])
    assert first[:12, :16].mean() > 240 and 100 < first[-12:, -16:].mean() < 160
    assert "more than 8 bits per sample (phones record HDR video" in result.err  # type: ignore[attr-defined]


def test_non_square_pixels_are_warned(tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    result = cli("import-video", VIDEOS / "sar4to3.mp4", "--into", rec, "--start-time",
                 str(T0 / 1e9), "--camera", "phone", "--json")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    assert "not square (sample aspect ratio 4:3)" in result.err  # type: ignore[attr-defined]
    assert "85×48 picture players show" in result.err  # type: ignore[attr-defined]
    assert len(_frames(rec)) == 10


def test_cut_video_is_warned_with_what_was_decoded(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    """A 3 s MP4 (index at its start) cut in half: the frames before the cut are imported, and
    the line says the file ends before the duration its container announces."""
    rec = _recording(tmp_path / "rec.mcap")
    result = cli("import-video", VIDEOS / "cut.mp4", "--into", rec, "--start-time",
                 str(T0 / 1e9), "--camera", "phone")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    count = len(_frames(rec))
    assert 0 < count < 30
    assert f"{count} frames could be decoded" in result.err  # type: ignore[attr-defined]
    assert "of the 3.00 s (30 frames) its container announces" in result.err  # type: ignore[attr-defined]


def test_video_trimmed_without_reencoding_is_not_taken_for_cut(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    """An MP4 trimmed by an edit list counts the frames before its trim point too (30 announced,
    22 shown): not a cut file."""
    rec = _recording(tmp_path / "rec.mcap")
    result = cli("import-video", VIDEOS / "trimmed.mp4", "--into", rec, "--start-time",
                 str(T0 / 1e9), "--camera", "phone")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    assert len(_frames(rec)) == 22 and "warning" not in result.err  # type: ignore[attr-defined]


def test_audio_only_file_is_refused_and_the_recording_kept(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = _recording(tmp_path / "rec.mcap")
    digest = _digest(rec)
    result = cli("import-video", VIDEOS / "audio_only.m4a", "--into", rec, "--start-time",
                 "recording")
    assert result.code == 1  # type: ignore[attr-defined]
    assert "audio_only.m4a" in result.err and "no video stream" in result.err  # type: ignore[attr-defined]
    assert result.err.count("\n") == 1  # type: ignore[attr-defined]
    assert _digest(rec) == digest


def test_frames_the_rig_camera_cannot_texture_are_warned(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    """A 16:9 video into a 4:3 camera: texture would refuse it; import says so at once."""
    rec = _recording(tmp_path / "rec.mcap")
    video = write_video(tmp_path / "wide.avi", frames=3, size=(64, 36))
    result = cli("import-video", video, "--into", rec, "--start-time", "recording",
                 "--camera", "phone")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    assert "frames are 64×36 px, camera 'phone' of the recording's rig is 64×48" in result.err  # type: ignore[attr-defined]


def test_unstitched_dual_fisheye_into_an_equirect_camera_is_warned(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    """A 360° camera's raw video is 2:1 too (two fisheye discs): the size check passes it, and
    texture would map the discs as a panorama."""
    from scanpipe.rig import CameraConfig

    rec = tmp_path / "rec.mcap"
    pano = CameraConfig(id="pano", source="1", model="equirect", width=128, height=64, fps=10)
    with RecordingWriter(rec, rig_with_cameras(pano), {"mode": "step"}) as writer:
        for i in range(5):
            writer.write_motor_state(T0 + i * 100_000_000, i, i, False, i * 1000)
    discs = np.zeros((64, 128, 3), np.uint8)
    for cx in (32, 96):
        cv2.circle(discs, (cx, 32), 31, (150, 160, 170), -1)
    stitched = np.tile(np.linspace(60, 200, 64, dtype=np.uint8)[:, None, None], (1, 128, 3))
    for name, frame in (("raw.avi", discs), ("pano.avi", stitched)):
        writer_ = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*"MJPG"), 10.0,
                                  (128, 64))
        for _ in range(3):
            writer_.write(frame)
        writer_.release()
    raw = cli("import-video", tmp_path / "raw.avi", "--into", rec, "--start-time", "recording",
              "--camera", "pano")
    assert raw.code == 0, raw.err  # type: ignore[attr-defined]
    assert "looks like two unstitched fisheye circles" in raw.err  # type: ignore[attr-defined]
    pano_run = cli("import-video", tmp_path / "pano.avi", "--into", rec, "--start-time",
                   "recording", "--camera", "pano", "--replace")
    assert pano_run.code == 0 and "warning" not in pano_run.err  # type: ignore[attr-defined]


def test_frames_that_miss_the_recording_are_refused(tmp_path: Path,
                                                    cli: Callable[..., object]) -> None:
    """A start time in local time (UTC+1) read as UTC: every frame an hour after the scan."""
    rec = _recording(tmp_path / "rec.mcap")
    digest = _digest(rec)
    video = write_video(tmp_path / "phone.avi", frames=4)
    result = cli("import-video", video, "--into", rec, "--start-time",
                 "2026-01-01T01:00:00", "--camera", "phone")
    assert result.code == 2  # type: ignore[attr-defined]
    assert "begin 3598.1 s after the recording ends" in result.err  # type: ignore[attr-defined]
    assert "(about 1.0 h: a time zone?)" in result.err  # type: ignore[attr-defined]
    assert result.err.count("\n") == 1  # type: ignore[attr-defined]
    assert _digest(rec) == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["phone.avi", "rec.mcap"]


def test_a_second_take_for_one_camera_is_refused_or_replaces(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    """Imported twice, two takes interleaved under one camera without a word."""
    rec = _recording(tmp_path / "rec.mcap")
    first = write_video(tmp_path / "take1.avi", frames=6)
    second = write_video(tmp_path / "take2.avi", frames=4)
    start = str(T0 / 1e9)
    assert cli("import-video", first, "--into", rec, "--start-time", start,  # type: ignore[attr-defined]
               "--camera", "phone").code == 0
    digest = _digest(rec)
    again = cli("import-video", second, "--into", rec, "--start-time", start, "--camera",
                "phone")
    assert again.code == 2  # type: ignore[attr-defined]
    assert "already holds 6 frames of camera phone" in again.err  # type: ignore[attr-defined]
    assert "--replace" in again.err and _digest(rec) == digest  # type: ignore[attr-defined]
    replaced = cli("import-video", second, "--into", rec, "--start-time", start, "--camera",
                   "phone", "--replace", "--json")
    assert replaced.code == 0, replaced.err  # type: ignore[attr-defined]
    assert '"replaced_frames": 6' in replaced.out  # type: ignore[attr-defined]
    assert len(_frames(rec)) == 4
    assert read_recording(rec).complete and not read_recording(rec).warnings


@pytest.mark.parametrize(("args", "needle"), [
    (["--start-time", "recording", "--offset", "nan"], "--offset nan: allowed"),
    (["--start-time", "recording", "--offset", "1e300"], "is not a time between 1970 and 9999"),
    (["--start-time", "1e30"], "is not a time between 1970 and 9999"),
    (["--start-time", "-5"], "is not a time between 1970 and 9999"),
])
def test_a_frame_time_outside_any_clock_is_refused_in_one_line(
        tmp_path: Path, cli: Callable[..., object], args: list[str], needle: str) -> None:
    """A NaN or huge --offset was a traceback; a --start-time past year 9999 blamed the
    recording ("damaged or incomplete")."""
    rec = _recording(tmp_path / "rec.mcap")
    digest = _digest(rec)
    video = write_video(tmp_path / "phone.avi", frames=3)
    result = cli("import-video", video, "--into", rec, *args, "--camera", "phone")
    assert result.code == 2, result.err  # type: ignore[attr-defined]
    assert needle in result.err, result.err  # type: ignore[attr-defined]
    assert result.err.startswith("scanpipe: error: ")  # type: ignore[attr-defined]
    assert result.err.count("\n") == 1  # type: ignore[attr-defined]
    assert _digest(rec) == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["phone.avi", "rec.mcap"]
