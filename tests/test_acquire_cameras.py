"""Camera capture into a real recording: timestamps, JPEG, end of a file source, drops."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from acquire_helpers import rig_with_cameras, small_camera, write_video

from scanpipe.acquire.cameras import CameraThread, open_capture
from scanpipe.acquire.sink import RecordingSink
from scanpipe.errors import DeviceError
from scanpipe.recording.reader import read_recording
from scanpipe.recording.writer import RecordingWriter


def _sink(path: Path, rig) -> RecordingSink:  # type: ignore[no-untyped-def]
    return RecordingSink(path, rig, {"mode": "test"},
                         lambda p, r, s: RecordingWriter(p, r, s, fsync_interval_s=0.2))


def test_file_source_is_captured_with_increasing_stamps(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=8, fps=50.0)
    cam = small_camera(source=str(video), fps=50.0)
    rig = rig_with_cameras(cam)
    sink = _sink(tmp_path / "rec.mcap", rig)
    stop = threading.Event()
    thread = CameraThread(cam.id, open_capture(cam), sink, stop, period_s=0.02, pace=True)
    thread.start()
    thread.join(timeout=10)
    assert not thread.is_alive()
    sink.close()
    assert thread.stats.frames == 8 and thread.stats.ended
    recording = read_recording(tmp_path / "rec.mcap")
    images = [i for i in recording.images if i.camera_id == "cam0"]
    assert len(images) == 8
    stamps = np.array([i.log_time_ns for i in images])
    assert np.all(np.diff(stamps) > 0)
    # Paced at 50 fps: a late frame may be followed by a quick one (catching up by at most one
    # period), so 8 frames span at least 6 periods.
    assert stamps[-1] - stamps[0] >= 6 * 20e6
    levels = [int(cv2.imdecode(np.frombuffer(i.data, np.uint8), cv2.IMREAD_GRAYSCALE).mean())
              for i in images]
    assert levels == pytest.approx([20 * i for i in range(8)], abs=3)
    assert [e.kind for e in recording.events] == ["camera_end"]


class _Flaky:
    """A live source that fails every third read."""

    is_live = True

    def __init__(self) -> None:
        self.reads = 0

    def read(self) -> tuple[bool, np.ndarray | None]:
        self.reads += 1
        if self.reads % 3 == 0:
            return False, None
        return True, np.zeros((8, 8, 3), np.uint8)

    def release(self) -> None:
        pass


def test_failed_reads_are_counted_and_reported(tmp_path: Path) -> None:
    cam = small_camera()
    rig = rig_with_cameras(cam)
    sink = _sink(tmp_path / "rec.mcap", rig)
    stop = threading.Event()
    thread = CameraThread(cam.id, _Flaky(), sink, stop, period_s=0.01, pace=True)
    thread.start()
    time.sleep(0.4)
    stop.set()
    thread.join(timeout=5)
    sink.close()
    assert thread.stats.dropped >= 5
    recording = read_recording(tmp_path / "rec.mcap")
    reported = sum(e.data["count"] for e in recording.events if e.kind == "camera_frames_dropped")
    assert reported == thread.stats.dropped
    assert len(recording.images) == thread.stats.frames


def test_unopenable_source_is_a_device_error(tmp_path: Path) -> None:
    cam = small_camera(source=str(tmp_path / "missing.avi"))
    with pytest.raises(DeviceError, match="cannot open source"):
        open_capture(cam)


class _Hanging:
    """A live source whose reads block after ``good`` frames (a USB or RTSP driver that hangs:
    ``read`` never returns), until ``release``."""

    is_live = True

    def __init__(self, good: int) -> None:
        self.good = good
        self.reads = 0
        self.released = threading.Event()

    def read(self) -> tuple[bool, np.ndarray | None]:
        self.reads += 1
        if self.reads > self.good:
            self.released.wait(30)
            return True, np.zeros((8, 8, 3), np.uint8)  # a late frame after the end
        return True, np.zeros((8, 8, 3), np.uint8)

    def release(self) -> None:
        self.released.set()


def test_a_read_that_never_returns_is_reported_lost(tmp_path: Path) -> None:
    cam = small_camera()
    rig = rig_with_cameras(cam)
    sink = _sink(tmp_path / "rec.mcap", rig)
    stop = threading.Event()
    source = _Hanging(good=3)
    thread = CameraThread(cam.id, source, sink, stop, period_s=0.01, pace=True,
                          lost_after_s=0.3)
    thread.start()
    deadline = time.monotonic() + 5.0
    while not thread.stats.lost and time.monotonic() < deadline:
        thread.watchdog()  # the recorder's flusher calls it
        time.sleep(0.05)
    assert thread.stats.lost and thread.stats.frames == 3
    stop.set()
    thread.join(timeout=0.5)
    assert thread.is_alive()  # still stuck in the driver
    sink.close()
    source.release()  # the driver returns a frame after the recording was closed
    thread.join(timeout=5)
    assert not thread.is_alive() and thread.stats.frames == 3  # not written
    recording = read_recording(tmp_path / "rec.mcap")
    lost = [e for e in recording.events if e.kind == "camera_lost"]
    assert len(lost) == 1 and "cam0" in lost[0].message and "did not return" in lost[0].message
    assert len(recording.images) == 3
    # decode, info and run say it: the camera's texture covers only what it saw before
    assert any(w.startswith("camera cam0 was lost") for w in recording.partial_scan_warnings())


class _Slow:
    """A live camera slower than the lost limit: each read blocks for its frame period
    (a camera at a low frame rate pacing itself: a DSLR, a triggered industrial camera)."""

    is_live = True

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s

    def read(self) -> tuple[bool, np.ndarray | None]:
        time.sleep(self.period_s)
        return True, np.zeros((8, 8, 3), np.uint8)

    def release(self) -> None:
        pass


def test_a_camera_slower_than_the_lost_limit_is_not_taken_for_a_hanging_one(
        tmp_path: Path) -> None:
    """The watchdog allows a read a few of the camera's own frame periods: a live camera at
    0.25 fps (a read of 4 s) was reported lost at the default 3 s and its frames dropped."""
    cam = small_camera()
    rig = rig_with_cameras(cam)
    sink = _sink(tmp_path / "rec.mcap", rig)
    stop = threading.Event()
    thread = CameraThread(cam.id, _Slow(0.2), sink, stop, period_s=0.2, pace=False,
                          lost_after_s=0.1)
    thread.start()
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        thread.watchdog()  # the recorder's flusher calls it
        time.sleep(0.02)
    stop.set()
    thread.join(timeout=5)
    sink.close()
    assert not thread.stats.lost
    assert thread.stats.frames >= 3
    assert not [e for e in read_recording(tmp_path / "rec.mcap").events
                if e.kind == "camera_lost"]


def test_file_source_frames_are_upright_as_import_video_takes_them(tmp_path: Path) -> None:
    """A phone video with a display rotation tag as a camera source: frames upright (the
    rotation applied), as import-video takes them (tests/fixtures/video/rotated90.mp4: stored
    64 × 48, shown 48 × 64 with the box bottom left)."""
    video = Path(__file__).parent / "fixtures" / "video" / "rotated90.mp4"
    capture = open_capture(small_camera(source=str(video)))
    ok, image = capture.read()
    assert ok and image.shape == (64, 48, 3)
    assert image[-12:, :12].mean() > 240
