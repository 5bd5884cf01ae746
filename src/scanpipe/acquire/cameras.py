"""Camera capture: OpenCV ``VideoCapture`` (device index, file or URL) or the virtual camera.

Each camera runs in its own thread for the whole recording. A frame is stamped with the host
clock at the moment the driver hands it over (between ``grab`` and ``retrieve`` when the source
has them, so JPEG decoding and encoding never delay the stamp), encoded as JPEG with OpenCV and
written to ``/camera/<id>/image``. Failed reads and gaps longer than 1.5 frame periods count as
dropped frames and go to ``/events``; a source that stays silent is reported lost, and so is
one whose read does not return (:meth:`CameraThread.watchdog`, called by the recorder).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from scanpipe.errors import DeviceError
from scanpipe.images import encode_jpeg
from scanpipe.rig import CameraConfig

#: A source failing to deliver for this long is reported lost and its thread ends ...
LOST_AFTER_S = 3.0
#: ... or for this many of its frame periods, when longer (a live camera at a low frame rate
#: blocks in each read for a period: at 0.25 fps a read of 4 s is no hang).
LOST_AFTER_PERIODS = 3.0
#: At most one ``camera_frames_dropped`` event per camera per this many seconds (the rest are
#: counted and reported in the next event and the summary).
DROP_EVENT_INTERVAL_S = 1.0


class FrameSource(Protocol):
    """The part of ``cv2.VideoCapture`` acquisition uses (the virtual camera has it too)."""

    def read(self) -> tuple[bool, Any]: ...

    def release(self) -> None: ...


class FrameSink(Protocol):
    """Where frames and events go (:class:`scanpipe.acquire.sink.RecordingSink`)."""

    def write_image(self, camera_id: str, log_time_ns: int, jpeg: bytes,
                    frame_id: str = "") -> None: ...

    def event(self, kind: str, message: str, data: dict[str, Any] | None = None,
              log_time_ns: int | None = None) -> None: ...


def is_device_index(source: str) -> bool:
    """A source of digits only is a device index (``"0"`` → ``/dev/video0``)."""
    return source.strip().isdigit()


def open_capture(cam: CameraConfig) -> FrameSource:
    """Open a camera's OpenCV source: a device index, a video file or a stream URL.

    For a device, ask for the rig's size and rate (the device may pick the nearest it has).
    """
    source = cam.source.strip()
    _quiet_opencv()
    try:
        if is_device_index(source):
            capture = cv2.VideoCapture(int(source))
            if capture.isOpened():
                capture.set(cv2.CAP_PROP_FRAME_WIDTH, cam.width)
                capture.set(cv2.CAP_PROP_FRAME_HEIGHT, cam.height)
                capture.set(cv2.CAP_PROP_FPS, cam.fps)
        else:
            capture = cv2.VideoCapture(source)
    except cv2.error as err:
        raise DeviceError(f"camera {cam.id}: cannot open source {source!r} ({err})") from err
    if not capture.isOpened():
        raise DeviceError(
            f"camera {cam.id}: cannot open source {source!r} (a device index such as 0, "
            "a video file or a stream URL); check cameras.source in the rig file"
        )
    return capture  # type: ignore[no-any-return]


def _quiet_opencv() -> None:
    """OpenCV prints its own warnings for sources it cannot open; ours say it in one line."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is not None:
        logging.setLogLevel(logging.LOG_LEVEL_ERROR)


@dataclass
class CameraStats:
    """Counters of one camera thread."""

    frames: int = 0
    dropped: int = 0
    failures: int = 0
    lost: bool = False
    ended: bool = False


class CameraThread(threading.Thread):
    """Capture one camera until ``stop`` is set: stamp, encode, write; count what is dropped.

    ``pace`` spaces reads at ``fps`` (for files, URLs and the virtual camera, which would
    otherwise deliver as fast as they are asked); a live device paces itself. ``period_s`` is
    the expected frame spacing in host time, for gap detection. ``lost_after_s``: no frame
    (or a read not returning) for this long is a lost camera; at least
    :data:`LOST_AFTER_PERIODS` frame periods.
    """

    def __init__(
        self,
        camera_id: str,
        source: FrameSource,
        sink: FrameSink,
        stop: threading.Event,
        period_s: float,
        pace: bool,
        jpeg_quality: int = 90,
        clock_ns: Callable[[], int] = time.time_ns,
        lost_after_s: float = LOST_AFTER_S,
    ) -> None:
        super().__init__(name=f"camera-{camera_id}", daemon=True)
        self.camera_id = camera_id
        self.source = source
        self.sink = sink
        self.stop_event = stop
        self.period_s = period_s
        self.pace = pace
        self.jpeg_quality = jpeg_quality
        self.clock_ns = clock_ns
        self.stats = CameraStats()
        self.lost_after_s = max(lost_after_s, LOST_AFTER_PERIODS * period_s)
        self._pending_drops = 0
        self._last_drop_event_ns = 0
        self._lost_lock = threading.Lock()
        self._reading_since: float | None = None  # monotonic time a read began (None: idle)

    def _report_lost(self, message: str) -> bool:
        """Say once that the camera is lost; False when it was said already."""
        with self._lost_lock:
            if self.stats.lost:
                return False
            self.stats.lost = True
        self.sink.event("camera_lost", f"camera {self.camera_id}: {message}",
                        {"camera_id": self.camera_id}, self.clock_ns())
        return True

    def watchdog(self) -> None:
        """Called now and then from another thread (the recorder's flusher): a read that has
        not returned for ``lost_after_s`` (a driver that hangs: the capture loop cannot see
        it) is reported as a lost camera; a frame it delivers later is not written."""
        since = self._reading_since
        if since is not None and self.is_alive() and \
                time.monotonic() - since > self.lost_after_s:
            self._report_lost(f"a read did not return for {self.lost_after_s:g} s (the driver "
                              "hangs); no frame is taken from it any more")

    def _capture(self) -> tuple[bool, Any, int]:
        """One frame and its capture stamp."""
        grab = getattr(self.source, "grab", None)
        retrieve = getattr(self.source, "retrieve", None)
        if callable(grab) and callable(retrieve):
            if not grab():
                return False, None, self.clock_ns()
            stamp = self.clock_ns()
            ok, image = retrieve()
            return bool(ok), image, stamp
        ok, image = self.source.read()
        return bool(ok), image, self.clock_ns()

    def _drops(self, count: int, now_ns: int, reason: str) -> None:
        self.stats.dropped += count
        self._pending_drops += count
        if now_ns - self._last_drop_event_ns >= DROP_EVENT_INTERVAL_S * 1e9:
            self.sink.event("camera_frames_dropped",
                            f"camera {self.camera_id}: {self._pending_drops} frame(s) dropped "
                            f"({reason})",
                            {"camera_id": self.camera_id, "count": self._pending_drops},
                            now_ns)
            self._pending_drops = 0
            self._last_drop_event_ns = now_ns

    def run(self) -> None:
        """The capture loop (runs in the thread)."""
        period_ns = int(self.period_s * 1e9)
        next_due = time.monotonic()
        last_stamp: int | None = None
        last_success = time.monotonic()
        live = is_live(self.source)
        try:
            while not self.stop_event.is_set():
                if self.pace:
                    wait = next_due - time.monotonic()
                    if wait > 0 and self.stop_event.wait(wait):
                        break
                    next_due = max(next_due + self.period_s, time.monotonic() - self.period_s)
                self._reading_since = time.monotonic()
                try:
                    ok, image, stamp = self._capture()
                except cv2.error as err:
                    ok, image, stamp = False, None, self.clock_ns()
                    self.stats.failures += 1
                    self.sink.event("camera_error", f"camera {self.camera_id}: {err}",
                                    {"camera_id": self.camera_id}, stamp)
                finally:
                    self._reading_since = None
                if self.stats.lost or self.stop_event.is_set():
                    break  # reported lost by the watchdog, or the recording has ended
                if not ok or image is None:
                    if not live and self.stats.frames > 0:
                        self.stats.ended = True
                        self.sink.event("camera_end", f"camera {self.camera_id}: end of source",
                                        {"camera_id": self.camera_id}, stamp)
                        break
                    self._drops(1, stamp, "read failed")
                    if time.monotonic() - last_success > self.lost_after_s:
                        self._report_lost(f"no frame for {self.lost_after_s:g} s; stopped "
                                          "capturing it")
                        break
                    self.stop_event.wait(min(self.period_s, 0.1))
                    continue
                last_success = time.monotonic()
                # A file never drops frames (reading late is not losing them); a live source does.
                if last_stamp is not None and period_ns > 0 and live:
                    missed = round((stamp - last_stamp) / period_ns) - 1
                    if (stamp - last_stamp) > 1.5 * period_ns and missed > 0:
                        self._drops(missed, stamp, "gap")
                last_stamp = stamp
                jpeg = encode_jpeg(np.ascontiguousarray(image), self.jpeg_quality)
                self.sink.write_image(self.camera_id, stamp, jpeg, str(self.stats.frames))
                self.stats.frames += 1
        finally:
            if self._pending_drops:
                self.sink.event("camera_frames_dropped",
                                f"camera {self.camera_id}: {self._pending_drops} frame(s) dropped",
                                {"camera_id": self.camera_id, "count": self._pending_drops},
                                self.clock_ns())
                self._pending_drops = 0


def is_live(source: FrameSource) -> bool:
    """Whether a source keeps producing (a device, a stream, the virtual camera), as opposed to
    a file that ends. Sources may declare it with an ``is_live`` attribute."""
    declared = getattr(source, "is_live", None)
    if isinstance(declared, bool):
        return declared
    if isinstance(source, cv2.VideoCapture):
        frame_count = source.get(cv2.CAP_PROP_FRAME_COUNT)
        return not frame_count or frame_count <= 0
    return True
