"""The crash-safe recording writer: MCAP, protobuf messages, zstd chunks, regular fsync.

A chunk holds at most ``chunk_s`` of log time (1 s) and about ``chunk_bytes`` of records, so one
damaged byte or a cut loses at most about a second of data: :mod:`scanpipe.recording.reader`
skips a damaged chunk and reads every intact one after it. The file is fsynced at least every
``fsync_interval_s`` of wall time (checked on every write; call :meth:`RecordingWriter.flush`
from an idle loop if writes can pause), so a writer killed at any moment loses at most about
that much. The Python mcap writer never fsyncs by itself.

A failed write, flush, fsync or close (a full disk, an I/O error) raises one
:class:`~scanpipe.errors.RecordingError` naming the file and the error; the writer is then
failed: later writes raise the same error, :meth:`RecordingWriter.close` only releases the file
(it never raises a second error), and what reached the disk stays readable by the tolerant
reader.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from scanpipe import __version__
from scanpipe.errors import RecordingError
from scanpipe.recording import schemas
from scanpipe.rig import Rig, rig_to_toml

FORMAT_VERSION = 1
PROFILE = "scanpipe"
SCANNER_STREAM = "/scanner/stream"
MOTOR_STREAM = "/motor/stream"
MOTOR_STATE = "/motor/state"
#: Already-decoded profiles (``scanpipe.Profile``), e.g. imported from a ROS bag.
SCANNER_PROFILES = "/scanner/profiles"
EVENTS = "/events"
#: The event the recorder writes when the scan has ended (scanner and cameras stopped), before
#: the platform returns to the start: a follower (``run --follow``) finishes the model then.
SCAN_END_EVENT = "scan_end"
#: The event that ends every part of a split recording but the last (``record --split-*``;
#: data: ``part``, ``next_part``, ``next_file``).
PART_CONTINUES_EVENT = "recording_continues"
#: The recorder's last event, with the recording's status ("complete", "interrupted", …).
RECORDING_END_EVENT = "recording_end"
RIG_METADATA = "scanpipe.rig"
RIG_KEY = "rig.toml"
SESSION_METADATA = "scanpipe.session"
CHANNELS_METADATA = "scanpipe.channels"
#: Uncompressed bytes after which a chunk is closed regardless of time.
DEFAULT_CHUNK_BYTES = 1 << 20
#: Log time a chunk may span: what one damaged byte or a cut can lose at most (about).
DEFAULT_CHUNK_S = 1.0

Link = Literal["scanner", "motor"]
_STREAM_TOPICS: dict[str, str] = {"scanner": SCANNER_STREAM, "motor": MOTOR_STREAM}


def camera_topic(camera_id: str) -> str:
    """The channel of a camera's images."""
    return f"/camera/{camera_id}/image"


class RecordingWriteError(RecordingError):
    """The recording's file could not be written (a full disk, an I/O error)."""

    def __init__(self, path: Path, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: cannot be written ({reason}); the recording ends with what "
                         "reached the disk")


class RecordingWriter:
    """Writes one recording; a context manager. Thread-safe: devices may write concurrently.

    ``session`` is stored as the ``scanpipe.session`` metadata (values that are not strings are
    stored as JSON); the format version and the scanpipe version are added.
    """

    def __init__(self, path: Path, rig: Rig, session: Mapping[str, Any],
                 fsync_interval_s: float = 1.0, chunk_bytes: int = DEFAULT_CHUNK_BYTES,
                 chunk_s: float = DEFAULT_CHUNK_S) -> None:
        if fsync_interval_s <= 0:
            raise RecordingError(f"fsync_interval_s {fsync_interval_s!r}: must be > 0")
        if chunk_s <= 0:
            raise RecordingError(f"chunk_s {chunk_s!r}: must be > 0")
        if chunk_bytes <= 0:
            raise RecordingError(f"chunk_bytes {chunk_bytes!r}: must be > 0")
        self.path = Path(path)
        self.fsync_interval_s = fsync_interval_s
        self._chunk_ns = round(chunk_s * 1e9)
        self._chunk_start_ns: int | None = None  # earliest log time in the open chunk
        self._lock = threading.Lock()
        self._closed = False
        self._failure: RecordingError | None = None
        self._seq: dict[tuple[str, int], int] = {}
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._camera_seq: dict[str, int] = {}
        try:
            self._file: IO[bytes] = self.path.open("wb")
        except OSError as err:
            raise RecordingError(f"{self.path}: cannot be created ({_errno_meaning(err)})"
                                 ) from None
        try:
            self._start(rig, session, chunk_bytes)
        except OSError as err:
            raise self._fail(err) from None

    def _start(self, rig: Rig, session: Mapping[str, Any], chunk_bytes: int) -> None:
        """Header, metadata and channels, then a first fsync."""
        self._mcap = McapWriter(self._file, chunk_size=chunk_bytes,
                                compression=CompressionType.ZSTD, enable_crcs=True)
        self._mcap.start(profile=PROFILE, library=f"scanpipe {__version__}")
        self._mcap.add_metadata(RIG_METADATA, {RIG_KEY: rig_to_toml(rig)})
        session_data = {k: v if isinstance(v, str) else json.dumps(v, default=str)
                        for k, v in session.items()}
        session_data.setdefault("format_version", str(FORMAT_VERSION))
        session_data.setdefault("scanpipe_version", __version__)
        self._mcap.add_metadata(SESSION_METADATA, session_data)
        # Register every channel known now, and record the id → topic map outside any chunk,
        # so that messages stay attributable even if the chunk holding the channel records is lost.
        for topic, cls in [(SCANNER_STREAM, schemas.ByteChunk), (MOTOR_STREAM, schemas.ByteChunk),
                           (MOTOR_STATE, schemas.MotorState), (EVENTS, schemas.Event),
                           *((camera_topic(c.id), schemas.CompressedImage) for c in rig.cameras)]:
            self._channel(topic, cls)
        self._mcap.add_metadata(CHANNELS_METADATA, {
            str(cid): topic for topic, cid in self._channels.items()})
        self._last_sync = time.monotonic()
        self._sync()

    # -- public API -----------------------------------------------------------------------

    def write_stream(self, link: Link, data: bytes, direction: int, log_time_ns: int) -> None:
        """Bytes read from (``direction=RX``, 0) or written to (``TX``, 1) a device link."""
        topic = _STREAM_TOPICS.get(link)
        if topic is None:
            raise RecordingError(f"link {link!r}: allowed scanner, motor")
        if direction not in (schemas.RX, schemas.TX):
            raise RecordingError(f"direction {direction!r}: allowed 0 (RX), 1 (TX)")
        with self._lock:
            seq = self._seq.get((link, direction), 0)
            self._seq[(link, direction)] = seq + 1
            message = schemas.ByteChunk(seq=seq, data=bytes(data), direction=direction)
            self._write(topic, message, log_time_ns, seq)

    def skip_stream_chunk(self, link: Link, direction: int) -> None:
        """Leave one sequence number of a link unused: bytes known lost (a capture's gap), which
        readers then count as a missing chunk instead of joining across it silently."""
        with self._lock:
            self._seq[(link, direction)] = self._seq.get((link, direction), 0) + 1

    def write_motor_state(self, log_time_ns: int, step_count: int, target_step_count: int,
                          moving: bool, device_time_us: int) -> None:
        """One position report of the motor controller."""
        message = schemas.MotorState(step_count=step_count, target_step_count=target_step_count,
                                     moving=moving, device_time_us=device_time_us)
        with self._lock:
            self._write(MOTOR_STATE, message, log_time_ns, 0)

    def write_profile(self, log_time_ns: int, profile: Any) -> None:
        """One already-decoded profile (a ``schemas.Profile`` message) on ``/scanner/profiles``."""
        with self._lock:
            self._write(SCANNER_PROFILES, profile, log_time_ns, int(profile.frame))

    def write_image(self, camera_id: str, log_time_ns: int, jpeg: bytes,
                    frame_id: str = "", image_format: str = "jpeg") -> None:
        """One JPEG (or PNG) frame of a camera, as ``foxglove.CompressedImage``."""
        message = schemas.CompressedImage(frame_id=frame_id, data=bytes(jpeg),
                                          format=image_format)
        message.timestamp.FromNanoseconds(log_time_ns)
        with self._lock:
            seq = self._camera_seq.get(camera_id, 0)
            self._camera_seq[camera_id] = seq + 1
            self._write(camera_topic(camera_id), message, log_time_ns, seq)

    def write_event(self, log_time_ns: int, kind: str, message: str,
                    data: Mapping[str, Any] | None = None) -> None:
        """A notable event (disconnect, dropped frames, motor error …) with optional details."""
        event = schemas.Event(kind=kind, message=message,
                              data_json=json.dumps(dict(data), default=str) if data else "")
        with self._lock:
            self._write(EVENTS, event, log_time_ns, 0)

    def flush(self) -> None:
        """Close the chunk in progress, write it out and fsync the file."""
        with self._lock:
            if self._failure is not None:
                raise self._failure
            if not self._closed:
                try:
                    self._sync()
                except OSError as err:
                    raise self._fail(err) from None

    @property
    def failed(self) -> RecordingError | None:
        """The error that ended writing (a full disk …), or None."""
        return self._failure

    def close(self) -> None:
        """Write the summary and close the file (idempotent).

        After a failed write it only releases the file: the error was raised already.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._failure is not None:
                return
            try:
                self._mcap.finish()  # type: ignore[no-untyped-call]
                self._file.flush()
                os.fsync(self._file.fileno())
                self._file.close()
            except OSError as err:
                raise self._fail(err) from None

    def _fail(self, err: OSError) -> RecordingError:
        """Enter the failed state after an OSError: release the file, keep one error."""
        self._closed = True
        self._failure = RecordingWriteError(self.path, _errno_meaning(err))
        with contextlib.suppress(OSError):  # close() flushes the buffer: fails again if full
            self._file.close()
        return self._failure

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- internals (called with the lock held) ---------------------------------------------

    def _channel(self, topic: str, cls: Any) -> int:
        if topic not in self._channels:
            name = cls.DESCRIPTOR.full_name
            if name not in self._schemas:
                self._schemas[name] = self._mcap.register_schema(
                    name=name, encoding="protobuf", data=schemas.file_descriptor_set(cls))
            self._channels[topic] = self._mcap.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=self._schemas[name])
        return self._channels[topic]

    def _write(self, topic: str, message: Any, log_time_ns: int, sequence: int) -> None:
        if self._failure is not None:
            raise self._failure
        if self._closed:
            raise RecordingError(f"{self.path}: write after close")
        try:
            channel = self._channel(topic, type(message))
            start = self._chunk_start_ns
            if start is not None and abs(log_time_ns - start) >= self._chunk_ns:
                self._mcap.flush()  # type: ignore[no-untyped-call]  # closes the chunk
                start = None
            self._chunk_start_ns = log_time_ns if start is None else min(start, log_time_ns)
            self._mcap.add_message(channel_id=channel, log_time=log_time_ns,
                                   data=message.SerializeToString(), publish_time=log_time_ns,
                                   sequence=sequence & 0xFFFFFFFF)
            if time.monotonic() - self._last_sync >= self.fsync_interval_s:
                self._sync()
        except OSError as err:
            raise self._fail(err) from None

    def _sync(self) -> None:
        self._mcap.flush()  # type: ignore[no-untyped-call]
        self._chunk_start_ns = None
        os.fsync(self._file.fileno())
        self._last_sync = time.monotonic()


def _errno_meaning(err: OSError) -> str:
    """``errno ENOSPC: No space left on device`` (or the error's text without an errno)."""
    if err.errno is None:
        return str(err) or type(err).__name__
    name = errno.errorcode.get(err.errno, str(err.errno))
    return f"errno {name}: {err.strerror or os.strerror(err.errno)}"
