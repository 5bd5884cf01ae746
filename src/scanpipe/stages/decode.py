"""Decode: a raw recording to the ``profiles``, ``motor``, ``frames`` and ``rig`` artifacts.

The scanner's received bytes (``/scanner/stream``, RX, in seq order) are decoded as one stream
in the chosen or detected dialect; each profile sector becomes one row. Times:

- ``recv_time_ns``: the host log time of the stream chunk that completed the frame.
- ``device_time_ns`` / ``device_end_time_ns``: the sector's start / end on the **device clock**,
  in ns: the 16-bit millisecond timestamps unwrapped (wraps every 65.536 s) into a continuous
  count that starts at the first sector's raw value. The number of wraps between two sectors is
  taken from their host receive times (scaled by the device clock's rate), so pauses longer than
  a wrap period unwrap correctly (:func:`scanpipe.clock.unwrap_device_ms`). Mapping to the host
  clock is the assemble stage's job; the report gives the fitted clock model
  (``device_clock``: offset, rate, latencies and any problem, :mod:`scanpipe.clock`).
- ``frame``: the frame (profile) number, unwrapped across its 16-bit wrap.

A recording with already-decoded profiles (``/scanner/profiles``, e.g. from
``scanpipe import-bag``) gives one row per message instead: dialect ``decoded``, sector 0,
device times as stored (0 = unknown → null), intensities as the echo.

The report (stored in the provenance of every artifact) has counts, the time span, rates, gaps,
the decoder's counters (checksum failures, resyncs, bytes skipped) and the reader's warnings.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.clock import fit_clock, unwrap_device_ticks
from scanpipe.errors import ParameterError, ProtocolError, RecordingError, StageError
from scanpipe.images import image_size
from scanpipe.params import Params
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.protocol.profile import DEVICE_TIME_WRAP_MS, Profile, unwrap_counter
from scanpipe.protocol.registry import (
    DETECTED_AS,
    DecodedFrame,
    Dialect,
    StreamDecoder,
    describe_bytes,
    get_dialect,
    resolve_dialect,
)
from scanpipe.recording.reader import (
    DecodedProfile,
    Image,
    MotorStates,
    Recording,
    StreamData,
    read_recording,
)
from scanpipe.recording.schemas import RX
from scanpipe.rig import Rig, default_rig, rig_table
from scanpipe.schema import FRAMES, MOTOR, PROFILES
from scanpipe.stage import Stage, StageResult

I64 = NDArray[np.int64]

#: What decode writes: every column of each artifact (:mod:`scanpipe.schema`).
PROFILES_SCHEMA = PROFILES.arrow_schema
MOTOR_SCHEMA = MOTOR.arrow_schema
FRAMES_SCHEMA = FRAMES.arrow_schema
#: The decoder is fed this many bytes at a time, to report progress.
_FEED_BYTES = 1 << 20


class DecodeParams(Params):
    """How the scanner stream is decoded."""

    dialect: Literal["auto", "paper", "ldoem", "cola_b", "cola_a", "ldrobot", "ldrobot_ld14",
                     "scip"] = Field(
        "auto", description="wire format of the scanner stream; auto detects it from the bytes")
    checksum: Literal["strict", "lenient"] = Field(
        "strict", description="strict drops frames whose checksum fails; lenient keeps them "
                              "with checksum_ok = false")
    max_frame_bytes: int = Field(
        1 << 18, ge=64, le=1 << 24,
        description="cap on a frame's length field: longer frames are false starts")
    gap_factor: float = Field(
        3.0, gt=1, le=1000,
        description="report an interval between profiles longer than this × the median as a gap")


def _list_array(arrays: Sequence[NDArray[Any] | None], value_type: pa.DataType) -> pa.Array:
    """A list array over one flat values array (None entries become null lists)."""
    lengths = np.fromiter((0 if a is None else len(a) for a in arrays), np.int64, len(arrays))
    offsets = np.zeros(len(arrays) + 1, np.int64)
    np.cumsum(lengths, out=offsets[1:])
    present = [a for a in arrays if a is not None]
    numpy_type = value_type.to_pandas_dtype()
    values = (np.concatenate(present).astype(numpy_type, copy=False) if present
              else np.zeros(0, numpy_type))
    list_type = pa.list_(value_type)
    if offsets[-1] > np.iinfo(np.int32).max:
        raise StageError(f"{offsets[-1]} samples exceed a list column's 32-bit offsets")
    mask = None
    if len(present) != len(arrays):
        mask = pa.array(np.fromiter((a is None for a in arrays), np.bool_, len(arrays)))
    return pa.ListArray.from_arrays(pa.array(offsets.astype(np.int32)), pa.array(values),
                                    type=list_type, mask=mask)


def _optional_ints(values: Sequence[int | None]) -> tuple[I64, NDArray[np.bool_]]:
    present = np.fromiter((v is not None for v in values), np.bool_, len(values))
    ints = np.fromiter((0 if v is None else v for v in values), np.int64, len(values))
    return ints, present


def profiles_table(frames: Sequence[DecodedFrame], stream: StreamData,
                   dialect: str) -> tuple[pa.Table, dict[str, Any]]:
    """The ``profiles`` artifact from decoded frames, and the device-clock part of the report."""
    profiles: list[Profile] = [p for f in frames for p in f.profiles]
    n = len(profiles)
    ends = np.repeat(np.fromiter((f.end_offset for f in frames), np.int64, len(frames)),
                     [len(f.profiles) for f in frames])
    recv = stream.time_at(ends)
    start_ms, has_start = _optional_ints([p.device_time_ms for p in profiles])
    end_ms, has_end = _optional_ints([p.device_end_time_ms for p in profiles])
    # One stream, one device clock: its tick and wrap come with the profiles (16-bit ms, µs …).
    tick_ns = profiles[0].device_tick_ns if n else 1_000_000
    wrap = profiles[0].device_wrap_ticks if n else DEVICE_TIME_WRAP_MS
    device_start = np.zeros(n, np.int64)
    device_start[has_start] = unwrap_device_ticks(start_ms[has_start], recv[has_start], wrap,
                                                  tick_ns) * tick_ns
    duration_ticks = (end_ms - start_ms) % wrap
    device_end = device_start + duration_ticks * tick_ns
    has_end &= has_start
    clock: dict[str, Any] = {"present": bool(has_start.any())}
    if has_start.any():
        reference = np.where(has_end, device_end, device_start)[has_start]
        clock.update(fit_clock(reference, recv[has_start]).report(),
                     device_span_s=float(device_start[has_start][-1]
                                         - device_start[has_start][0]) / 1e9)
    frame_numbers = unwrap_counter(np.fromiter((p.frame for p in profiles), np.int64, n), 1 << 16)
    table = pa.table([
        pa.array(recv, pa.int64()),
        pa.array(device_start, pa.int64(), mask=~has_start),
        pa.array(device_end, pa.int64(), mask=~has_end),
        pa.array(frame_numbers, pa.int64()),
        pa.array(np.fromiter((p.sector for p in profiles), np.int32, n), pa.int32()),
        pa.array(np.fromiter((p.start_angle_deg for p in profiles), np.float64, n)),
        pa.array(np.fromiter((p.step_deg for p in profiles), np.float64, n)),
        _list_array([p.ranges_m for p in profiles], pa.float32()),
        _list_array([p.echo for p in profiles], pa.uint16()),
        pa.array(np.fromiter((p.checksum_ok for p in profiles), np.bool_, n), pa.bool_()),
        pa.array([dialect] * n, pa.string()) if n else pa.array([], pa.string()),
    ], schema=PROFILES_SCHEMA)
    return table, clock


def decoded_profiles_table(profiles: Sequence[DecodedProfile]) -> pa.Table:
    """The ``profiles`` artifact from ``/scanner/profiles`` (profiles decoded by another tool).

    Device times of 0 are unknown (null); intensities become the echo, rounded and clipped to
    0…65535 (null when a profile has none or their count differs from the ranges').
    """
    n = len(profiles)
    start = np.fromiter((p.device_time_ns for p in profiles), np.int64, n)
    end = np.fromiter((p.device_end_time_ns for p in profiles), np.int64, n)
    echo = [np.clip(np.rint(np.nan_to_num(p.intensities)), 0, 65535).astype(np.uint16)
            if p.intensities.size == p.ranges_m.size and p.ranges_m.size else None
            for p in profiles]
    return pa.table([
        pa.array(np.fromiter((p.log_time_ns for p in profiles), np.int64, n), pa.int64()),
        pa.array(start, pa.int64(), mask=start == 0),
        pa.array(end, pa.int64(), mask=(end == 0) | (start == 0)),
        pa.array(np.fromiter((p.frame for p in profiles), np.int64, n), pa.int64()),
        pa.array(np.zeros(n, np.int32), pa.int32()),
        pa.array(np.fromiter((p.start_angle_deg for p in profiles), np.float64, n)),
        pa.array(np.fromiter((p.step_deg for p in profiles), np.float64, n)),
        _list_array([p.ranges_m for p in profiles], pa.float32()),
        _list_array(echo, pa.uint16()),
        pa.array(np.ones(n, np.bool_), pa.bool_()),
        pa.array(["decoded"] * n, pa.string()) if n else pa.array([], pa.string()),
    ], schema=PROFILES_SCHEMA)


def motor_table(recording: Recording) -> pa.Table:
    """The ``motor`` artifact: every motor state report in log-time order."""
    return motor_states_table(recording.motor)


def motor_states_table(m: MotorStates) -> pa.Table:
    """The ``motor`` artifact of motor state reports (in log-time order)."""
    return pa.table([pa.array(m.log_time_ns, pa.int64()), pa.array(m.step_count, pa.int64()),
                     pa.array(m.target_step_count, pa.int64()), pa.array(m.moving, pa.bool_()),
                     pa.array(m.device_time_us, pa.int64())], schema=MOTOR_SCHEMA)


def blobs_array(blobs: Sequence[bytes]) -> pa.ChunkedArray:
    """A binary column over ``blobs`` without copying them: one chunk per blob, each chunk's
    values buffer the ``bytes`` object itself (the frames of a recording are hundreds of MB;
    one contiguous array would hold them twice)."""
    if not blobs:
        return pa.chunked_array([], pa.binary())
    return pa.chunked_array([
        pa.Array.from_buffers(pa.binary(), 1, [None, pa.py_buffer(
            np.array([0, len(blob)], np.int32)), pa.py_buffer(blob)]) for blob in blobs],
        pa.binary())


def frames_table(images: Sequence[Image]) -> tuple[pa.Table, int]:
    """The ``frames`` artifact (the images with their sizes) and how many had no readable size.

    The encoded bytes are shared with ``images``, not copied (:func:`blobs_array`)."""
    sizes = [image_size(i.data) for i in images]
    unknown = sum(1 for s in sizes if s is None)
    table = pa.table([
        pa.array([i.camera_id for i in images], pa.string()),
        pa.array([i.log_time_ns for i in images], pa.int64()),
        pa.array([i.sequence for i in images], pa.int64()),
        pa.array([i.format or "jpeg" for i in images], pa.string()),
        pa.array([-1 if s is None else s[0] for s in sizes], pa.int32()),
        pa.array([-1 if s is None else s[1] for s in sizes], pa.int32()),
        blobs_array([i.data for i in images]),
    ], schema=FRAMES_SCHEMA)
    return table, unknown


def _gaps(times_ns: I64, factor: float) -> dict[str, Any]:
    if times_ns.size < 2:
        return {"median_interval_s": None, "max_interval_s": None, "count": 0, "largest": []}
    intervals = np.diff(np.sort(times_ns)).astype(np.float64)
    median = float(np.median(intervals))
    is_gap = intervals > factor * max(median, 1.0)
    order = np.argsort(intervals)[::-1][:5]
    largest = [{"after_ns": int(np.sort(times_ns)[i]), "seconds": float(intervals[i]) / 1e9}
               for i in order if is_gap[i]]
    return {"median_interval_s": median / 1e9, "max_interval_s": float(intervals.max()) / 1e9,
            "count": int(is_gap.sum()), "largest": largest}


def _rate(count: int, span_ns: int) -> float | None:
    return round(count / (span_ns / 1e9), 3) if span_ns > 0 else None


def _recording_rig(recording: Recording, warnings: list[str]) -> tuple[Rig, pa.Table]:
    """The rig to decode with and the ``rig`` artifact to pass on.

    No stored rig (a recording from another tool): the default rig, with a warning. A stored
    rig that is invalid is passed on as stored, so that the stages that compute with it
    refuse it with its problem (a corrected rig file via ``--rig`` replaces it); decoding
    itself only needs the dialect, taken from the default rig then.
    """
    if recording.rig_toml is None:
        warnings.append(f"{recording.path}: no rig stored; using the default rig (pass the "
                        "rig the scan was made with: scanpipe run REC --rig RIG.toml)")
        return default_rig(), rig_table(default_rig())
    try:
        rig = recording.rig()
    except RecordingError as err:
        warnings.append(f"{err}; later stages refuse it: pass a corrected rig with --rig")
        return default_rig(), pa.table({"toml": pa.array([recording.rig_toml], pa.string())})
    return rig, rig_table(rig)


def _model_variant(recording: Recording, rig: Rig, params: DecodeParams) -> Dialect | None:
    """The dialect variant the rig's scanner model needs (an LD14's stream is detected as
    ``ldrobot`` but its angles need the LD14 correction), or None. An explicit
    ``decode.dialect`` of the plain family on such a rig is refused: the angles would be
    sheared by up to 7°, silently."""
    name = rig.scanner.dialect
    if name not in DETECTED_AS:
        return None
    if params.dialect == DETECTED_AS[name]:
        raise ParameterError([
            f"decode.dialect = {params.dialect} decodes without the angle "
            f"correction the rig's scanner needs (scanner.model = {rig.scanner.model or '?'}, "
            f"dialect {name}: up to 7° of error per sample); use decode.dialect = auto or "
            f"{name} (the decode stage reads the rig stored in the recording: --rig does not "
            f"change it)"], str(recording.path))
    return get_dialect(name)


def check_rig_override(report: Mapping[str, Any], rig: Rig, source: str) -> None:
    """Refuse a rig that replaces the recording's for the later stages (``run --rig``) when
    its scanner needs the stream decoded otherwise than the decode stage did: decode reads the
    rig stored in the recording, not the override, and an LD14's stream decoded as an LD06's
    (or an LD06's with the LD14's correction) is sheared by up to 7° without a word."""
    used, wanted = report.get("dialect"), rig.scanner.dialect
    if not isinstance(used, str) or used == wanted:
        return
    if DETECTED_AS.get(wanted) == used:  # the override names the variant: it can be asked for
        raise ParameterError([
            f"its scanner ({rig.scanner.model or 'no model'}, dialect {wanted}) needs the "
            f"stream decoded as {wanted}, but the decode stage decoded it as {used} from the "
            f"rig stored in the recording (--rig does not reach decode): up to 7° of angle "
            f"error per sample; add --set decode.dialect={wanted}"], source)
    if DETECTED_AS.get(used) == wanted:
        raise ParameterError([
            f"its scanner ({rig.scanner.model or 'no model'}, dialect {wanted}) takes no "
            f"angle correction, but the stream was decoded as {used}, with it (from the rig "
            f"stored in the recording, or decode.dialect; --rig does not reach decode): up to "
            f"7° of angle error per sample"], source)


@dataclass
class DecodedStream:
    """The scanner stream (``/scanner/stream``, RX) already decoded, all of it and finished
    (``scanpipe run --follow`` decodes it while it grows): the dialect, the decoder with its
    counters, the frames."""

    dialect: Dialect
    decoder: StreamDecoder
    frames: list[DecodedFrame]


def decode_recording(recording: Recording, params: DecodeParams,
                     progress: ProgressFn = no_progress,
                     decoded: DecodedStream | None = None) -> StageResult:
    """The decode stage on a recording already read (pure: no file access); ``decoded``: its
    scanner stream decoded already, with ``params``."""
    warnings = list(recording.warnings)
    warnings += [f"{recording.path}: {w}" for w in recording.partial_scan_warnings()]
    rig, rig_artifact = _recording_rig(recording, warnings)
    stream = recording.stream("scanner", RX)
    data = stream.data
    variant = _model_variant(recording, rig, params)
    if decoded is not None and (variant is None or decoded.dialect.name == variant.name):
        dialect, decoder, frames = decoded.dialect, decoded.decoder, decoded.frames
    else:
        try:
            dialect = resolve_dialect(params.dialect, data)
        except ProtocolError as err:
            if data or not recording.profiles:
                warnings.append(f"{err}; decoding as the rig's dialect {rig.scanner.dialect!r}")
            dialect = get_dialect(rig.scanner.dialect)
        if variant is not None and dialect.name == DETECTED_AS[variant.name]:
            dialect = variant  # the bytes name the family, the rig's model the variant
        decoder = StreamDecoder(dialect, params.checksum, params.max_frame_bytes)
        frames = []
        view = memoryview(data)
        for start in range(0, len(data), _FEED_BYTES):
            frames += decoder.feed_frames(view[start:start + _FEED_BYTES])
            progress("decode scanner stream", min(start + _FEED_BYTES, len(data)), len(data))
        frames += decoder.finish_frames()
    if params.dialect != "auto" and data and decoder.counters.frames_decoded == 0:
        raise StageError(f"{recording.path}: decode.dialect = {params.dialect}: no frame of it "
                         f"in the {len(data)} bytes received from the scanner "
                         f"({decoder.counters.checksum_failures} checksum failures; "
                         f"{describe_bytes(data)}); try decode.dialect = auto")
    warnings += [f"{recording.path}: {w}" for w in decoder.warnings]
    profiles, clock = profiles_table(frames, stream, dialect.name)
    if recording.profiles:
        # Profiles another tool decoded (an imported ROS bag); a byte stream beside them is
        # kept out rather than mixed in: one scan, one source.
        if profiles.num_rows:
            warnings.append(f"{recording.path}: both /scanner/stream ({profiles.num_rows} "
                            f"profiles) and /scanner/profiles ({len(recording.profiles)}); "
                            "using /scanner/profiles")
        profiles, clock = decoded_profiles_table(recording.profiles), {"present": False}
    frames_art, unsized = frames_table(recording.images)
    if unsized:
        warnings.append(f"{unsized} camera frames have no readable JPEG/PNG size (width = -1)")
    motor = motor_table(recording)

    recv = profiles.column("recv_time_ns").to_numpy()
    span_ns = int(recv.max() - recv.min()) if recv.size else 0
    samples = int(pc.sum(pc.list_value_length(profiles.column("ranges_m")))
                  .as_py() or 0)
    cameras = Counter(i.camera_id for i in recording.images)
    motor_stream = recording.stream("motor", RX)
    report: dict[str, Any] = {
        "dialect": "decoded" if recording.profiles else dialect.name,
        "dialect_detected": params.dialect == "auto",
        "checksum_mode": params.checksum,
        "counts": {
            "profiles": profiles.num_rows, "frames": decoder.counters.frames_decoded,
            "samples": samples, "motor_states": motor.num_rows, "images": dict(cameras),
            "events": len(recording.events), "scanner_bytes": len(data),
            "motor_stream_bytes": len(motor_stream.data),
            "checksum_failed_rows": profiles.num_rows - int(
                pc.sum(profiles.column("checksum_ok")).as_py() or 0),
        },
        "counters": decoder.counters.as_dict(),
        "time_span": {
            "start_ns": int(recv.min()) if recv.size else None,
            "end_ns": int(recv.max()) if recv.size else None,
            "duration_s": span_ns / 1e9,
        },
        "rates": {
            "profiles_per_s": _rate(profiles.num_rows, span_ns),
            "samples_per_s": _rate(samples, span_ns),
            "scanner_bytes_per_s": _rate(len(data), span_ns),
            "motor_states_per_s": _rate(motor.num_rows, _span(recording.motor.log_time_ns)),
            "images_per_s": {cam: _rate(n, _span(np.array(
                [i.log_time_ns for i in recording.images if i.camera_id == cam], np.int64)))
                for cam, n in cameras.items()},
        },
        "gaps": {**_gaps(recv, params.gap_factor),
                 "missing_stream_chunks": stream.missing_chunks},
        "device_clock": clock,
        "warnings": warnings,
        "events": dict(Counter(e.kind for e in recording.events)),
        "recording": {
            "complete": recording.complete, "bytes_read": recording.bytes_read,
            "file_size": recording.file_size, "chunks_read": recording.chunks_read,
            "chunks_damaged": recording.chunks_damaged, "warnings": warnings,
            "loss": recording.loss.as_dict(),
        },
    }
    return StageResult(
        tables={"profiles": profiles, "motor": motor, "frames": frames_art,
                "rig": rig_artifact},
        report=report,
    )


def _span(times_ns: I64) -> int:
    return int(times_ns.max() - times_ns.min()) if times_ns.size > 1 else 0


def decode_stage(inputs: Mapping[str, Any], params: DecodeParams,
               progress: ProgressFn = no_progress) -> StageResult:
    """Stage function: ``inputs["recording"]`` is the path of the MCAP recording."""
    path = inputs.get("recording")
    if not isinstance(path, str | Path):
        raise StageError("decode needs inputs['recording']: the path of an MCAP recording")
    return decode_recording(read_recording(Path(path)), params, progress)


STAGE = Stage(
    name="decode",
    version=5,  # 5: a scan the recorder ended early or a part of a split recording is warned
    params=DecodeParams,
    inputs=("recording",),
    outputs=("profiles", "motor", "frames", "rig"),
    func=decode_stage,
    description="recording (MCAP) → profiles, motor states, camera frames, rig",
    libraries=("numpy", "pyarrow", "mcap", "protobuf", "zstandard"),
)
