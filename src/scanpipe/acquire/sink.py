"""The recorder's one way into the recording: a thread-safe writer with counters and splitting.

Every driver thread (scanner, motor, cameras) writes through one :class:`RecordingSink`. It
serialises calls to the :class:`~scanpipe.recording.writer.RecordingWriter` (which is not meant
for concurrent use), counts what went in (for the live display and the summary), and, when asked,
closes the current file and opens the next part once a size or duration is reached.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

from scanpipe.errors import RecordingError
from scanpipe.recording.writer import PART_CONTINUES_EVENT
from scanpipe.rig import Rig

Link = Literal["scanner", "motor"]
RX, TX = 0, 1



def part_path(out: Path, index: int) -> Path:
    """The path of part ``index`` of a split recording: ``scan.mcap`` → ``scan-001.mcap``.

    Part 0 is ``out`` itself, so an unsplit recording and the first part share a name.
    """
    if index == 0:
        return out
    return out.with_name(f"{out.stem}-{index:03d}{out.suffix}")


@dataclass
class SinkStats:
    """What has been written so far, over all parts."""

    stream_bytes: Counter[str] = field(default_factory=Counter)  # "scanner RX" → bytes
    motor_states: int = 0
    images: Counter[str] = field(default_factory=Counter)  # camera id → frames
    image_bytes: int = 0
    events: Counter[str] = field(default_factory=Counter)  # kind → count
    event_log: list[dict[str, Any]] = field(default_factory=list)

    @property
    def total_bytes(self) -> int:
        """Payload bytes written: streams and images (what the data rate is computed from)."""
        return sum(self.stream_bytes.values()) + self.image_bytes


class SinkTap(Protocol):
    """Sees what goes into the recording (the live view): called under the sink's lock, so it
    must only hand the data on (a queue), never block."""

    def on_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None: ...

    def on_motor_state(self, log_time_ns: int, step_count: int) -> None: ...

    def on_image(self, camera_id: str, log_time_ns: int, data: bytes) -> None: ...

    def on_event(self, kind: str, message: str, data: Mapping[str, Any],
                 log_time_ns: int) -> None: ...


class RecordingSink:
    """Thread-safe front of the recording writer: counts, events, optional splitting.

    ``writer_factory(path, rig, session)`` opens one part; it is the recording package's
    ``RecordingWriter`` in production. ``split_bytes`` / ``split_s`` (None = never) start a new
    part once the current one is that large or that old; every part carries the rig and the
    session metadata (with ``part`` set), so each decodes on its own.

    When the writer fails (a full disk, an I/O error) the sink keeps its
    :class:`RecordingError` in :attr:`failure` and closes: the write that hit it and every later
    one are ignored (driver threads never see it), and the error is raised exactly once, by the
    next :meth:`flush` (the recorder's flush loop then stops the recording) or else by
    :meth:`close`, unless :meth:`take_failure` took it first. What reached the disk stays
    readable by the tolerant reader.
    """

    def __init__(
        self,
        out: Path,
        rig: Rig,
        session: Mapping[str, Any],
        writer_factory: Callable[[Path, Rig, Mapping[str, Any]], Any],
        split_bytes: int | None = None,
        split_s: float | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        taps: Sequence[SinkTap] = (),
    ) -> None:
        self.out = out
        self.taps = list(taps)
        self.rig = rig
        self.session = dict(session)
        self._factory = writer_factory
        self.split_bytes = split_bytes
        self.split_s = split_s
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self.stats = SinkStats()
        self.paths: list[Path] = []
        self._closed = False
        self._writer: Any = None
        self.failure: RecordingError | None = None
        self._failure_raised = False
        self._part_started_ns = 0
        self._open_part(0)

    def _open_part(self, index: int) -> None:
        path = part_path(self.out, index)
        session = dict(self.session)
        if self.split_bytes is not None or self.split_s is not None:
            session["part"] = index
        try:
            self._writer = self._factory(path, self.rig, session)
        except OSError as err:
            raise RecordingError(f"{path}: cannot be written ({err.strerror or err})") from None
        self.paths.append(path)
        self._part_started_ns = self._clock_ns()

    def _maybe_split(self, now_ns: int) -> None:
        """Start the next part if the current one is big or old enough (lock held)."""
        too_old = self.split_s is not None and now_ns - self._part_started_ns >= self.split_s * 1e9
        too_big = False
        if self.split_bytes is not None:
            try:
                too_big = os.path.getsize(self.paths[-1]) >= self.split_bytes
            except OSError:
                too_big = False
        if too_old or too_big:
            # Each part decodes on its own: say in it that the scan goes on elsewhere, so a
            # reader of one part can tell it holds only part of the scan.
            following = part_path(self.out, len(self.paths))
            data = {"part": len(self.paths) - 1, "next_part": len(self.paths),
                    "next_file": following.name}
            message = f"the recording continues in {following.name}"
            self._keep_event(now_ns, PART_CONTINUES_EVENT, message, data)
            self._writer.write_event(now_ns, PART_CONTINUES_EVENT, message, data)
            self._writer.close()
            self._open_part(len(self.paths))

    def write_stream(self, link: Link, data: bytes, direction: int, log_time_ns: int) -> None:
        """Raw bytes of a link, as read (RX) or written (TX)."""
        with self._lock:
            if self._closed:
                return
            with self._failing():
                self._maybe_split(log_time_ns)
                self._writer.write_stream(link, data, direction, log_time_ns)
            self.stats.stream_bytes[f"{link} {'RX' if direction == RX else 'TX'}"] += len(data)
            for tap in self.taps:
                tap.on_stream(link, data, direction, log_time_ns)

    def write_motor_state(self, log_time_ns: int, step_count: int, target_step_count: int,
                          moving: bool, device_time_us: int) -> None:
        """One position report of the motor controller."""
        with self._lock:
            if self._closed:
                return
            with self._failing():
                self._writer.write_motor_state(log_time_ns, step_count, target_step_count,
                                               moving, device_time_us)
            self.stats.motor_states += 1
            for tap in self.taps:
                tap.on_motor_state(log_time_ns, step_count)

    def write_image(self, camera_id: str, log_time_ns: int, jpeg: bytes,
                    frame_id: str = "") -> None:
        """One JPEG frame, stamped with its capture time."""
        with self._lock:
            if self._closed:
                return
            with self._failing():
                self._maybe_split(log_time_ns)
                self._writer.write_image(camera_id, log_time_ns, jpeg, frame_id)
            self.stats.images[camera_id] += 1
            self.stats.image_bytes += len(jpeg)
            for tap in self.taps:
                tap.on_image(camera_id, log_time_ns, jpeg)

    def event(self, kind: str, message: str, data: Mapping[str, Any] | None = None,
              log_time_ns: int | None = None) -> None:
        """Record a notable event on ``/events`` and keep it for the summary."""
        when = self._clock_ns() if log_time_ns is None else log_time_ns
        with self._lock:
            self._keep_event(when, kind, message, data)
            if not self._closed:
                with self._failing():
                    self._writer.write_event(when, kind, message, dict(data or {}))

    def _keep_event(self, when_ns: int, kind: str, message: str,
                    data: Mapping[str, Any] | None) -> None:
        """An event into the summary and to the taps (the lock held; the caller writes it)."""
        self.stats.events[kind] += 1
        self.stats.event_log.append(
            {"time_ns": when_ns, "kind": kind, "message": message, "data": dict(data or {})})
        for tap in self.taps:
            tap.on_event(kind, message, dict(data or {}), when_ns)

    def flush(self) -> None:
        """Flush and fsync the current part now."""
        with self._lock:
            if not self._closed:
                with self._failing():
                    self._writer.flush()
            self._raise_failure()

    def close(self) -> None:
        """Finish the current part (summary section, fsync). Later writes are ignored."""
        with self._lock:
            if not self._closed:
                with self._failing():
                    self._closed = True
                    self._writer.close()
            self._raise_failure()

    @contextlib.contextmanager
    def _failing(self) -> Iterator[None]:
        """Keep a writer failure as the sink's one failure and stop writing (lock held)."""
        try:
            yield
        except (RecordingError, OSError) as err:
            self.failure = err if isinstance(err, RecordingError) else RecordingError(
                f"{self.paths[-1]}: cannot be written ({err.strerror or err})")
            self._closed = True
            with contextlib.suppress(RecordingError, OSError):
                self._writer.close()

    def take_failure(self) -> RecordingError | None:
        """The writer's failure, if any; the caller reports it, so flush and close will not."""
        with self._lock:
            self._failure_raised = True
            return self.failure

    def _raise_failure(self) -> None:
        """Raise the kept failure if it has not been raised yet (lock held)."""
        if self.failure is not None and not self._failure_raised:
            self._failure_raised = True
            raise self.failure
