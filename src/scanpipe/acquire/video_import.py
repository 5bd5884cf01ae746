"""Add a separately recorded video (a phone, as in the paper) to a recording as camera frames.

MCAP files cannot be appended to in place. :func:`import_video` rewrites the recording into a
temporary file beside it, with every original record (schemas, channels, messages, metadata,
attachments) plus the video's frames on ``/camera/<id>/image`` merged in time order, and renames
it over the original only when everything succeeded: on any error the original is untouched.

Frame times: ``start_time_ns + offset_s + the frame's position in the video`` (OpenCV's
``CAP_PROP_POS_MSEC``: the container's presentation time of each frame, so variable frame rates
and edit lists are followed; ``index / fps`` when the container gives none).

Frames are taken as players show them: a container's display rotation (a phone held upright
stores landscape pixels and a rotation tag) is applied, so the frames are upright whichever way
the phone was turned — the orientation a rig camera's pose describes (the default rig's phones
are upright, 1080 × 1920), and the one calibrate-camera reads photos in (EXIF orientation
applied). The rotation is in the report (``display_rotation_deg``). What a container says that
the frames alone do not show — non-square pixels, more than 8 bits per sample, fewer frames
decodable than it announces (a cut file) — and a frame size the rig's camera cannot texture are
in the report's ``warnings``.

A rough offset (within about a second) is enough: :func:`refine_offset` finds the exact one
before the frames are written, by aligning the scan's depth edges with the video's image edges
(:mod:`scanpipe.camera_selfcal`) over a search window around the rough one.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Generator
from datetime import UTC, datetime
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.artifacts import atomic_path
from scanpipe.errors import DeviceError, RecordingError, StageError, UsageError
from scanpipe.images import MAX_FRAME_PX, check_pixels, encode_jpeg, image_size
from scanpipe.rig import CameraConfig, rig_from_table

#: Everything mcap's stream reader raises on a damaged file (see shared notes).
_MCAP_DAMAGE: tuple[type[BaseException], ...] = (ValueError, KeyError, IndexError,
                                                 OverflowError, UnicodeDecodeError, EOFError)


def parse_start_time(text: str, recording_start_ns: int | None = None) -> int:
    """A start time as integer ns since the Unix epoch.

    Accepts ISO 8601 (``2026-11-22T08:00:00.5+00:00``; no zone = UTC), seconds since the epoch
    (``1795334400.25``), nanoseconds since the epoch (an integer above 10¹⁷), or ``recording``
    (the first message of the recording, when ``recording_start_ns`` is given).
    """
    value = text.strip()
    if value == "recording":
        if recording_start_ns is None:
            raise UsageError("--start-time recording: the recording has no messages")
        return recording_start_ns
    if re.fullmatch(r"[+-]?\d+", value) and abs(int(value)) > 10**17:
        return int(value)
    try:  # Decimal: a float loses the nanoseconds of an epoch time
        seconds = Decimal(value)
        if seconds.is_finite():
            return int(seconds * 1_000_000_000)
    except InvalidOperation:
        pass
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        raise UsageError(
            f"--start-time {text!r}: not a time; allowed: ISO 8601 (2026-11-22T08:00:00+00:00), "
            "seconds or nanoseconds since the Unix epoch, or 'recording'") from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    delta = moment - datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


#: The latest first-frame time taken (ns since the epoch, 9999-01-01): a frame's time is written
#: as a protobuf Timestamp, which ends with the year 9999.
LATEST_START_NS = 253_370_764_800 * 1_000_000_000


def first_frame_ns(start_ns: int, offset_s: float, start_text: str) -> int:
    """The first frame's time: ``start_ns`` (from ``--start-time start_text``) plus
    ``offset_s`` seconds; :class:`UsageError` for an offset that is not finite or a time
    before 1970 or after 9999 (no clock the recording's frames can be written with)."""
    if not math.isfinite(offset_s):
        raise UsageError(f"--offset {offset_s:g}: allowed a finite number of seconds")
    first_s = start_ns / 1e9 + offset_s  # checked in float: a huge offset has no int ns
    if not 0 <= first_s <= LATEST_START_NS / 1e9:
        raise UsageError(f"--start-time {start_text!r} with --offset {offset_s:g} s: the first "
                         f"frame at {first_s:g} s since the epoch is not a time between 1970 "
                         "and 9999; give the time the video's first frame was taken")
    return start_ns + round(offset_s * 1e9)


def open_video(video: Path) -> cv2.VideoCapture:
    """An OpenCV capture of ``video``, or a one-line error naming the file."""
    if not video.is_file():
        raise UsageError(f"{video}: video file not found")
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise DeviceError(f"{video}: OpenCV cannot open this video (unknown container or codec, "
                          "or no video stream: an audio-only file)")
    # Upright frames, as players show them (OpenCV's default since 4.5; pinned: the rig's camera
    # poses and calibrate-camera's photos are in that orientation).
    capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
    return capture


def display_rotation_deg(capture: Any) -> int:
    """The container's display rotation (0, 90, 180, 270; OpenCV's sense), applied to frames."""
    return round(float(capture.get(cv2.CAP_PROP_ORIENTATION_META) or 0.0)) % 360


def container_warnings(capture: Any, video: Path) -> list[str]:
    """What the container says about the picture that the decoded frames do not show: more
    than 8 bits per sample (HDR) and non-square pixels."""
    warnings = []
    width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH) or 0)
    height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT) or 0)
    if _high_bit_depth(int(capture.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT) or 0)):
        warnings.append(
            f"{video}: more than 8 bits per sample (phones record HDR video — HLG or PQ — this "
            "way): OpenCV reads it as 8-bit without tone mapping, so an HDR video's colours "
            "come out flat and dim; film with HDR video off, or convert it to SDR first")
    sar_num = float(capture.get(cv2.CAP_PROP_SAR_NUM) or 0.0)
    sar_den = float(capture.get(cv2.CAP_PROP_SAR_DEN) or 0.0)
    if sar_num > 0 and sar_den > 0 and abs(sar_num / sar_den - 1.0) > 1e-3:
        warnings.append(
            f"{video}: its pixels are not square (sample aspect ratio {sar_num:g}:{sar_den:g}); "
            f"the frames are kept as stored ({width}×{height} px): the camera's fx and fy must "
            "be for these pixels (calibrate-camera on frames of this video), not for the "
            f"{round(width * sar_num / sar_den)}×{height} picture players show")
    return warnings


def _high_bit_depth(tag: int) -> bool:
    """A decoded pixel format of more than 8 bits per sample: FFmpeg's raw tags for them end
    (little-endian formats) or begin (big-endian) with the bit depth, after ``Y1``/``Y0``/
    ``Y3`` (yuv420p10le is ``Y3`` 11 10, yuv444p12le ``Y3`` 0 12)."""
    raw = tag.to_bytes(4, "little")
    return ((raw[:2] in (b"Y1", b"Y0", b"Y3") and 8 < raw[3] <= 16)
            or (raw[2:] in (b"1Y", b"0Y", b"3Y") and 8 < raw[0] <= 16))


def cut_warning(video: Path, frames: int, last_offset_ns: int, frame_count: float,
                fps: float) -> str | None:
    """A warning when the frames decoded end well before the duration the container announces
    (``frame_count / fps``): a file cut short (a recording stopped by a full card or a crash)
    or damaged mid-way; None when they reach it within 1.5 s and 5 %. The margin: a video
    trimmed without re-encoding (an MP4 edit list) still counts the frames from the keyframe
    before its trim point, up to one keyframe interval (about 1 s in phones' videos)."""
    if frame_count <= 0 or fps <= 0 or frames == 0:
        return None
    announced_s = frame_count / fps
    decoded_s = last_offset_ns / 1e9 + 1.0 / fps
    if announced_s - decoded_s <= max(1.5, 0.05 * announced_s):
        return None
    return (f"{video}: {frames} frames could be decoded, up to {decoded_s:.2f} s of the "
            f"{announced_s:.2f} s ({frame_count:.0f} frames) its container announces: the file "
            "is cut short or damaged; the frames after that are missing")


def video_frames(video: Path, start_ns: int, jpeg_quality: int = 90,
                 warnings: list[str] | None = None, facts: dict[str, Any] | None = None
                 ) -> Generator[tuple[int, bytes, int], None, None]:
    """``(time_ns, jpeg, index)`` for every frame of a video file, in order, upright (its
    display rotation applied, ``facts["display_rotation_deg"]``); what the container says that
    the frames do not show goes into ``warnings`` (:func:`container_warnings`, and
    :func:`cut_warning` once all are read)."""
    capture = open_video(video)
    try:
        # The container's size, before any frame is decoded (0 when it does not say).
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH) or 0)
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT) or 0)
        if width > 0 and height > 0:
            check_pixels(width, height, str(video), MAX_FRAME_PX, UsageError)
        fps = capture.get(cv2.CAP_PROP_FPS) or 0.0
        frame_count = float(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0)
        if warnings is not None:
            warnings.extend(container_warnings(capture, video))
        if facts is not None:
            facts["display_rotation_deg"] = display_rotation_deg(capture)
        index = 0
        last_ns = -1
        offset_ns = 0
        while True:
            ok, image = capture.read()
            if not ok or image is None:
                if warnings is not None:
                    cut = cut_warning(video, index, offset_ns, frame_count, fps)
                    warnings.extend([cut] if cut else [])
                break
            # a stream may change size mid-way: every frame is held to the limit
            check_pixels(image.shape[1], image.shape[0], f"{video}: frame {index}",
                         MAX_FRAME_PX, UsageError)
            offset_ns = _frame_offset_ns(capture, index, fps, video)
            stamp = start_ns + offset_ns
            if stamp <= last_ns:  # some containers repeat a time; keep frames in order
                stamp = last_ns + 1
            last_ns = stamp
            yield stamp, encode_jpeg(image, jpeg_quality), index
            index += 1
    finally:
        capture.release()


def _frame_offset_ns(capture: Any, index: int, fps: float, video: Path) -> int:
    """The frame's time in the video (the container's, else ``index / fps``)."""
    position_ms = capture.get(cv2.CAP_PROP_POS_MSEC)
    if position_ms > 0 or (index == 0 and position_ms == 0):
        return round(float(position_ms) * 1e6)
    if fps > 0:
        return round(index / fps * 1e9)
    raise DeviceError(f"{video}: the video gives neither frame times nor a rate")


def sample_video(video: Path, start_ns: int, count: int,
                 still_ns: tuple[int, int] | None = None,
                 window_ns: int = 0, motion_reach_ns: int = 0
                 ) -> tuple[list[tuple[int, Any]], list[tuple[int, Any]]]:
    """``(time_ns, BGR image)`` of up to ``count`` frames spread over the video; with
    ``still_ns`` (and ``window_ns``), as :func:`scanpipe.camera_selfcal.frame_rows` chooses
    them (a share from before and after the platform turns, and from where it starts and
    stops). Second, with ``still_ns`` and ``motion_reach_ns``, ``(time_ns, small grey image)``
    of every frame within that of the start and stop
    (:func:`scanpipe.camera_selfcal.motion_clock`'s frames)."""
    from scanpipe.camera_selfcal import motion_grey

    motion: list[tuple[int, Any]] = []
    capture = open_video(video)
    try:
        total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        fps = capture.get(cv2.CAP_PROP_FPS) or 0.0
        wanted = set(range(total))
        if total > count:
            import pyarrow as pa

            from scanpipe.camera_selfcal import frame_rows

            rate = fps if fps > 0 else 30.0
            guess = pa.table({"camera_id": ["video"] * total, "log_time_ns": [
                start_ns + round(i / rate * 1e9) for i in range(total)]})
            wanted = set(frame_rows(guess, "video", count, still_ns, window_ns).tolist())
        chosen: list[tuple[int, Any]] = []
        index = 0
        while capture.grab():
            stamp = start_ns + _frame_offset_ns(capture, index, fps, video)
            near = still_ns is not None and motion_reach_ns > 0 and min(
                abs(stamp - still_ns[0]), abs(stamp - still_ns[1])) <= motion_reach_ns
            if total <= 0 or index in wanted or near:
                ok, image = capture.retrieve()
                if ok and image is not None:
                    check_pixels(image.shape[1], image.shape[0], f"{video}: frame {index}",
                                 MAX_FRAME_PX, UsageError)
                    if near:
                        motion.append((stamp, motion_grey(image)))
                    if total <= 0 or index in wanted:
                        chosen.append((stamp, image))
            index += 1
    finally:
        capture.release()
    if total <= 0 and len(chosen) > count:  # a container that does not say its length
        keep = {round(k * (len(chosen) - 1) / (count - 1)) for k in range(count)}
        chosen = [c for i, c in enumerate(chosen) if i in keep]
    if not chosen:
        raise DeviceError(f"{video}: no frames could be read")
    return chosen, motion


_NO_STILL_FRAMES = (
    "{video}: no frame shows the platform standing still (before or after the scan, allowing "
    "for --window), so the clock offset cannot be told from a turn of the camera; film a few "
    "seconds before and after the scan, or give the exact --offset without --refine")


def refine_offset(video: Path, recording: Path, start_ns: int, camera_id: str,
                  window_s: float = 1.0, frames: int = 48) -> dict[str, Any]:
    """The video's clock offset found from the data: ``start_ns`` is the rough start (within
    ``window_s``); the scan in ``recording`` is decoded and assembled in memory, ``frames``
    video frames are aligned with its depth edges. A report with ``offset_s`` (to add to
    ``start_ns``), its 1σ, and the alignment before and after."""
    from scanpipe.camera_selfcal import (
        MotorTrack,
        calibrate_camera,
        depth_edges,
        motion_clock,
        motion_reach_ns,
        observe,
    )
    from scanpipe.stages.assemble import STAGE as ASSEMBLE
    from scanpipe.stages.decode import STAGE as DECODE
    from scanpipe.texturing.frames import camera_for_size

    decoded = DECODE.run({"recording": recording}).tables
    rig = rig_from_table(decoded["rig"])
    camera = rig.camera(camera_id)
    points = ASSEMBLE.run({n: decoded[n] for n in ("profiles", "motor", "rig")}).tables["points"]
    track = MotorTrack(decoded["motor"], rig)
    first, last = track.moving_span_ns()
    margin = round(window_s * 1e9)
    sampled, moving = sample_video(video, start_ns, frames, (first, last), margin,
                                   motion_reach_ns(track, window_s))
    # the clock from the video's own motion where it films the platform start and stop
    motion = motion_clock(np.array([t for t, _ in moving], np.int64),
                          [image for _, image in moving], track, 0.0, window_s)
    trusted = motion is not None and motion.trusted
    if not trusted and not any(t < first - margin or t > last + margin for t, _ in sampled):
        raise StageError(_NO_STILL_FRAMES.format(video=video))
    height, width = sampled[0][1].shape[:2]
    sized = camera_for_size(camera, width, height)
    observed = [observe(sized, t, image) for t, image in sampled
                if image.shape[:2] == (height, width)]
    result = calibrate_camera(depth_edges(points), observed, track, fit_time_offset=True,
                              time_window_s=window_s, motion=motion)
    offset = next(p for p in result.parameters if p.name == "time_offset_s")
    if not result.still_frames:
        raise StageError(_NO_STILL_FRAMES.format(video=video))
    if not offset.observable:
        raise StageError(f"{video}: the clock offset could not be found from the data "
                         f"(1σ {offset.sigma or float('nan'):.3g} s); give the exact --offset "
                         "(see docs/calibration.md: film a few seconds before and after the "
                         "scan)")
    report = result.report()
    report["offset_s"] = offset.change
    report["offset_sigma_s"] = offset.sigma
    return report


def recording_start_ns(path: Path) -> int | None:
    """Log time of the first message of a recording (None when it has none)."""
    from scanpipe.recording.reader import read_recording

    recording = read_recording(path)
    times = [t for s in recording.streams.values() for t in s.log_time_ns[:1].tolist()]
    times += recording.motor.log_time_ns[:1].tolist()
    times += [i.log_time_ns for i in recording.images[:1]]
    return min(times) if times else None


def looks_dual_fisheye(grey: NDArray[np.uint8]) -> bool:
    """A 2:1 frame that is two fisheye discs side by side (a 360° camera's raw, unstitched
    video) rather than an equirectangular panorama: the corners of both square halves are
    black and their centres are not. An equirectangular frame's corners are the poles, which
    a scene (sky, ceiling, floor) does not leave black at eight places at once."""
    height, width = grey.shape[:2]
    half = width // 2
    patch = max(height // 16, 1)
    corners = [grey[y:y + patch, x:x + patch]
               for x0 in (0, half) for x in (x0, x0 + half - patch)
               for y in (0, height - patch)]
    centres = [grey[height // 2 - patch:height // 2 + patch,
                    x0 + half // 2 - patch:x0 + half // 2 + patch] for x0 in (0, half)]
    return (max(int(c.max()) for c in corners) < 16
            and min(float(c.mean()) for c in centres) > 40.0)


def frame_size_warning(video: Path, width: int, height: int, camera: CameraConfig,
                       rotation_deg: int) -> str | None:
    """A warning when frames of ``width`` × ``height`` cannot be textured with ``camera`` (a
    different aspect ratio: :func:`scanpipe.texturing.frames.camera_for_size` refuses them)."""
    from scanpipe.texturing.frames import camera_for_size

    try:
        camera_for_size(camera, width, height)
    except StageError:
        pass
    else:
        return None
    held = "upright (portrait)" if height > width else "level (landscape)"
    turned = (f"; the phone was held {held} (its display rotation, {rotation_deg}°, is "
              f"applied, as players show it): the rig's camera must be {held} too"
              if abs(width / height - camera.height / camera.width) < 0.01 else "")
    return (f"{video}: frames are {width}×{height} px, camera {camera.id!r} of the recording's "
            f"rig is {camera.width}×{camera.height} (a different aspect ratio): texture will "
            f"refuse them unless given a rig with this camera calibrated at {width}×{height} "
            f"(scanpipe calibrate-camera, then texture --rig){turned}")


def import_video(video: Path, recording: Path, start_ns: int, camera_id: str,
                 jpeg_quality: int = 90, camera: CameraConfig | None = None,
                 replace: bool = False) -> dict[str, Any]:
    """Rewrite ``recording`` with the frames of ``video`` added as ``camera_id`` (with
    ``replace``, instead of the frames it held for that camera); a report.

    ``camera`` (the rig's ``camera_id``) is checked against the frames' size: a warning when
    texture would refuse them. The report's ``warnings`` hold that and what the container says
    that the frames do not show (:func:`video_frames`)."""
    from mcap.records import Attachment, Channel, DataEnd, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    from scanpipe.recording import schemas
    from scanpipe.recording.writer import CHANNELS_METADATA, PROFILE, camera_topic

    if not recording.is_file():
        raise RecordingError(f"{recording}: recording not found")
    topic = camera_topic(camera_id)
    warnings: list[str] = []
    facts: dict[str, Any] = {}
    frames = video_frames(video, start_ns, jpeg_quality, warnings, facts)
    pending = next(frames, None)
    if pending is None:
        raise DeviceError(f"{video}: no frames could be read")
    report: dict[str, Any] = {"video": str(video), "recording": str(recording),
                              "camera_id": camera_id, "topic": topic, "frames": 0,
                              "first_time_ns": pending[0], "last_time_ns": pending[0],
                              "original_messages": 0, "warnings": warnings,
                              "display_rotation_deg": facts.get("display_rotation_deg", 0)}
    size = image_size(pending[1])
    if camera is not None and size is not None:
        mismatch = frame_size_warning(video, *size, camera, report["display_rotation_deg"])
        warnings.extend([mismatch] if mismatch else [])
        if camera.model == "equirect" and mismatch is None:
            first = cv2.imdecode(np.frombuffer(pending[1], np.uint8), cv2.IMREAD_GRAYSCALE)
            if first is not None and looks_dual_fisheye(np.asarray(first, np.uint8)):
                warnings.append(
                    f"{video}: camera {camera.id!r} is equirect, but the first frame looks like "
                    "two unstitched fisheye circles (black outside two discs: a 360° camera's "
                    "raw video); texture would map it as an equirectangular panorama: stitch "
                    "it to equirectangular with the camera's own software first")
    try:
        with atomic_path(recording) as tmp, recording.open("rb") as source, \
                tmp.open("wb") as target:
            writer = McapWriter(target, compression=CompressionType.ZSTD)
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            topics: dict[int, str] = {}
            image_channel: int | None = None
            started = False
            scan_span = [2**63 - 1, -1]  # the recording's own messages but cameras', ns
            for record in StreamReader(source, skip_magic=False).records:
                if not started:
                    writer.start(profile=getattr(record, "profile", PROFILE),
                                 library=getattr(record, "library", "scanpipe"))
                    started = True
                if isinstance(record, DataEnd):
                    break  # the summary section only repeats what was copied
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(record.name, record.encoding,
                                                                   record.data)
                elif isinstance(record, Channel) and record.id not in channel_ids:
                    if record.topic == topic and image_channel is not None:
                        channel_ids[record.id] = image_channel
                        continue
                    new_id = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_ids.get(record.schema_id, 0), record.metadata)
                    channel_ids[record.id] = new_id
                    topics[new_id] = record.topic
                    if record.topic == topic:
                        image_channel = new_id
                elif isinstance(record, Message):
                    while pending is not None and pending[0] <= record.log_time:
                        image_channel = _write_frame(writer, image_channel, topic, pending,
                                                     schemas, report)
                        topics[image_channel] = topic
                        pending = next(frames, None)
                    if replace and topics.get(channel_ids.get(record.channel_id, -1)) == topic:
                        report["replaced_frames"] = report.get("replaced_frames", 0) + 1
                    elif record.channel_id in channel_ids:
                        writer.add_message(channel_ids[record.channel_id], record.log_time,
                                           record.data, record.publish_time, record.sequence)
                        report["original_messages"] += 1
                        if not topics[channel_ids[record.channel_id]].startswith("/camera/"):
                            scan_span[0] = min(scan_span[0], record.log_time)
                            scan_span[1] = max(scan_span[1], record.log_time)
                elif isinstance(record, Metadata) and record.name != CHANNELS_METADATA:
                    writer.add_metadata(record.name, record.metadata)
                elif isinstance(record, Attachment):
                    writer.add_attachment(record.create_time, record.log_time, record.name,
                                          record.media_type, record.data)
            if not started:
                raise RecordingError(f"{recording}: no MCAP header")
            while pending is not None:
                image_channel = _write_frame(writer, image_channel, topic, pending, schemas,
                                             report)
                topics[image_channel] = topic
                pending = next(frames, None)
            _check_overlap(video, recording, report, scan_span)
            # Channel ids may have changed: write the id → topic map afresh.
            writer.add_metadata(CHANNELS_METADATA, {str(k): v for k, v in topics.items()})
            writer.finish()  # type: ignore[no-untyped-call]
            target.flush()
            os.fsync(target.fileno())
    except RecordingError:
        raise
    except _MCAP_DAMAGE as err:
        raise RecordingError(
            f"{recording}: cannot be rewritten, it is damaged or incomplete "
            f"({type(err).__name__}: {err}); the original is unchanged") from None
    except OSError as err:
        raise RecordingError(f"{recording}: cannot be rewritten ({err.strerror or err}); "
                             "the original is unchanged") from None
    finally:
        with contextlib.suppress(Exception):
            frames.close()
    return report


def _check_overlap(video: Path, recording: Path, report: dict[str, Any],
                   scan_span: list[int]) -> None:
    """:class:`UsageError` when the frames' times miss the recording's span altogether: a
    --start-time in local time read as UTC, or the wrong day, would texture every frame at
    the platform's first or last angle."""
    lo, hi = scan_span
    first, last = report["first_time_ns"], report["last_time_ns"]
    if hi < lo or (first <= hi and last >= lo):
        return
    gap_s = (lo - last if last < lo else first - hi) / 1e9
    where = ("end {:.1f} s before the recording begins" if last < lo else
             "begin {:.1f} s after the recording ends").format(gap_s)
    hours = f" (about {gap_s / 3600:.1f} h: a time zone?)" if gap_s > 1800 else ""
    raise UsageError(
        f"{video}: its frames ({_utc(first)} … {_utc(last)}) {where} ({_utc(lo)} … "
        f"{_utc(hi)}){hours}; none would see the scan. --start-time "
        "without a zone is UTC; give the time the video's first frame was taken; "
        f"{recording} is unchanged")


def _utc(time_ns: int) -> str:
    return datetime.fromtimestamp(time_ns / 1e9, UTC).isoformat(timespec="milliseconds")


def _write_frame(writer: Any, channel: int | None, topic: str, frame: tuple[int, bytes, int],
                 schemas: Any, report: dict[str, Any]) -> int:
    """Write one imported frame (registering the camera channel when the recording lacks it)."""
    time_ns, jpeg, index = frame
    if channel is None:
        cls = schemas.CompressedImage
        schema = writer.register_schema(cls.DESCRIPTOR.full_name, "protobuf",
                                        schemas.file_descriptor_set(cls))
        channel = int(writer.register_channel(topic, "protobuf", schema))
    message = schemas.CompressedImage(frame_id=f"import:{index}", data=jpeg, format="jpeg")
    message.timestamp.FromNanoseconds(time_ns)
    writer.add_message(channel, time_ns, message.SerializeToString(), time_ns, index)
    report["frames"] += 1
    report["last_time_ns"] = time_ns
    return channel
