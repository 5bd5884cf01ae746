"""What is in a recording: channels, counts, durations, rates, gaps, events, the rig.

:func:`recording_info` is pure over a :class:`~scanpipe.recording.reader.Recording` (the
tolerant reader's result), so a recording whose writer was killed is described as far as it
could be read, with the reader's warnings.
"""

from __future__ import annotations

import contextlib
from collections import Counter
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.acquire.display import format_bytes, format_duration
from scanpipe.errors import ProtocolError, RecordingError
from scanpipe.recording.reader import Recording
from scanpipe.recording.writer import EVENTS, MOTOR_STATE, MOTOR_STREAM, SCANNER_STREAM


def time_figures(times_ns: NDArray[np.int64], gap_s: float) -> dict[str, Any]:
    """First/last time, duration, mean rate, largest gap and gaps longer than ``gap_s``."""
    t = np.sort(np.asarray(times_ns, dtype=np.int64))
    if t.size == 0:
        return {"first_ns": None, "last_ns": None, "duration_s": 0.0, "rate_hz": 0.0,
                "max_gap_s": 0.0, "gaps": 0}
    steps_s = np.diff(t) / 1e9
    duration = float((t[-1] - t[0]) / 1e9)
    return {
        "first_ns": int(t[0]),
        "last_ns": int(t[-1]),
        "duration_s": duration,
        "rate_hz": (t.size - 1) / duration if duration > 0 else 0.0,
        "max_gap_s": float(steps_s.max()) if steps_s.size else 0.0,
        "gaps": int(np.count_nonzero(steps_s > gap_s)),
    }


def _profile_figures(recording: Recording) -> dict[str, Any]:
    """Decode the scanner's RX stream only to count profiles (the decode stage does the rest)."""
    from scanpipe.protocol.registry import StreamDecoder, detect_dialect, rig_variant

    data = recording.stream("scanner").data
    if not data and recording.profiles:  # already decoded (/scanner/profiles: import-bag)
        return {"count": len(recording.profiles), "sectors": len(recording.profiles),
                "dialect": "decoded"}
    if not data:
        return {"count": 0, "dialect": None}
    try:
        dialect = detect_dialect(data)
    except ProtocolError:
        return {"count": 0, "dialect": None, "note": "no scanner frames recognised"}
    # An LD14's bytes read as an LD06's: its stored rig names it (none or an invalid one:
    # the bytes' dialect).
    with contextlib.suppress(RecordingError):
        dialect = rig_variant(dialect, recording.rig().scanner.dialect)
    decoder = StreamDecoder(dialect)
    frames = decoder.feed_frames(data) + decoder.finish_frames()
    counters = decoder.counters.as_dict()
    return {"count": len(frames), "sectors": sum(len(f.profiles) for f in frames),
            "dialect": dialect, **counters}


def recording_info(recording: Recording, gap_s: float = 1.0) -> dict[str, Any]:
    """Everything ``scanpipe info`` shows, as plain data (see the module docstring)."""
    channels: dict[str, dict[str, Any]] = {}
    for topic, link in ((SCANNER_STREAM, "scanner"), (MOTOR_STREAM, "motor")):
        rx, tx = recording.stream(link, 0), recording.stream(link, 1)
        times = np.concatenate([rx.log_time_ns, tx.log_time_ns])
        channels[topic] = {
            "messages": int(times.size), "rx_bytes": len(rx.data), "tx_bytes": len(tx.data),
            "missing_chunks": rx.missing_chunks + tx.missing_chunks,
            **time_figures(rx.log_time_ns, gap_s),
        }
    if recording.profiles:
        profile_times = np.array([p.log_time_ns for p in recording.profiles], np.int64)
        channels["/scanner/profiles"] = {"messages": len(recording.profiles),
                                         **time_figures(profile_times, gap_s)}
    channels[MOTOR_STATE] = {"messages": int(recording.motor.log_time_ns.size),
                             **time_figures(recording.motor.log_time_ns, gap_s)}
    by_camera: dict[str, list[int]] = {}
    image_bytes: Counter[str] = Counter()
    for image in recording.images:
        by_camera.setdefault(image.camera_id, []).append(image.log_time_ns)
        image_bytes[image.camera_id] += len(image.data)
    dropped: Counter[str] = Counter()
    for event in recording.events:
        if event.kind == "camera_frames_dropped":
            dropped[str(event.data.get("camera_id", "?"))] += int(event.data.get("count", 1))
    cameras = {}
    for camera_id, camera_times in sorted(by_camera.items()):
        figures = time_figures(np.array(camera_times, np.int64), gap_s)
        cameras[camera_id] = {"frames": len(camera_times), "bytes": image_bytes[camera_id],
                              "dropped": dropped[camera_id], **figures}
        channels[f"/camera/{camera_id}/image"] = {"messages": len(camera_times), **figures}
    channels[EVENTS] = {"messages": len(recording.events),
                        **time_figures(np.array([e.log_time_ns for e in recording.events],
                                                np.int64), gap_s)}
    firsts = [c["first_ns"] for c in channels.values() if c.get("first_ns") is not None]
    lasts = [c["last_ns"] for c in channels.values() if c.get("last_ns") is not None]
    motor = recording.motor
    rig: dict[str, Any] = {"toml": recording.rig_toml}
    try:
        parsed = recording.rig()
        rig.update(name=parsed.name, dialect=parsed.scanner.dialect,
                   beam_step_deg=parsed.scanner.beam_step_deg,
                   scan_hz=parsed.scanner.scan_hz, pulse_limit=parsed.motor.pulse_limit,
                   pulse_step_deg=parsed.motor.pulse_step_deg,
                   cameras=[c.id for c in parsed.cameras])
    except RecordingError as err:
        rig["error"] = str(err)
    return {
        "path": str(recording.path),
        "complete": recording.complete,
        "file_size": recording.file_size,
        "bytes_read": recording.bytes_read,
        "chunks_read": recording.chunks_read,
        "chunks_damaged": recording.chunks_damaged,
        "loss": recording.loss.as_dict(),
        "warnings": [*recording.warnings, *recording.partial_scan_warnings()],
        "session": recording.session,
        "rig": rig,
        "start_ns": min(firsts) if firsts else None,
        "end_ns": max(lasts) if lasts else None,
        "duration_s": (max(lasts) - min(firsts)) / 1e9 if firsts else 0.0,
        "channels": channels,
        "profiles": _profile_figures(recording),
        "motor": {
            "states": int(motor.log_time_ns.size),
            "first_step_count": int(motor.step_count[0]) if motor.step_count.size else None,
            "last_step_count": int(motor.step_count[-1]) if motor.step_count.size else None,
            "max_step_count": int(motor.step_count.max()) if motor.step_count.size else None,
        },
        "cameras": cameras,
        "events": [{"time_ns": e.log_time_ns, "kind": e.kind, "message": e.message,
                    "data": e.data} for e in recording.events],
        "event_counts": dict(Counter(e.kind for e in recording.events)),
    }


def format_info(info: dict[str, Any], max_events: int = 20) -> str:
    """The info as text for a terminal."""
    state = "complete" if info["complete"] else "INCOMPLETE (writer did not finish)"
    lines = [
        f"recording   {info['path']} — {state}",
        f"size        {format_bytes(info['file_size'])}, {info['chunks_read']} chunks read"
        + (f", {info['chunks_damaged']} damaged" if info["chunks_damaged"] else ""),
        f"duration    {format_duration(info['duration_s'])} ({info['duration_s']:.3f} s)",
    ]
    loss = info["loss"]
    if loss["chunks"] or loss["bytes"]:
        bound = "" if loss["exact"] else "at least "
        lines.append(f"lost        {bound}{loss['chunks']} chunks, {format_bytes(loss['bytes'])}, "
                     f"{bound}{loss['time_s']:.3f} s of log time (damage or a cut)")
    session = info["session"]
    if session:
        lines.append("session     " + ", ".join(f"{k}={v}" for k, v in sorted(session.items())
                                                if k in ("mode", "host", "scanpipe_version",
                                                         "step_count", "format_version")))
    rig = info["rig"]
    if "name" in rig:
        lines.append(f"rig         {rig['name']}: {rig['dialect']} scanner, beam step "
                     f"{rig['beam_step_deg']:g}° at {rig['scan_hz']:g} Hz, pulse step "
                     f"{rig['pulse_step_deg']:g}°, pulse limit {rig['pulse_limit']}, cameras: "
                     f"{', '.join(rig['cameras']) or 'none'}")
    else:
        lines.append(f"rig         {rig.get('error', 'none stored')}")
    profiles = info["profiles"]
    lines.append(f"profiles    {profiles['count']}"
                 + (f" ({profiles['dialect']}, {profiles.get('checksum_failures', 0)} checksum "
                    f"failures, {profiles.get('resyncs', 0)} resyncs)"
                    if profiles.get("dialect") else ""))
    motor = info["motor"]
    if motor["states"]:
        lines.append(f"motor       {motor['states']} states, count {motor['first_step_count']} → "
                     f"{motor['last_step_count']} (max {motor['max_step_count']})")
    lines.append("channels:")
    lines.append(f"  {'topic':24} {'messages':>9} {'duration':>9} {'rate':>10} {'max gap':>9} "
                 f"{'gaps':>5}")
    for topic, c in info["channels"].items():
        lines.append(f"  {topic:24} {c['messages']:>9} {c['duration_s']:>8.2f}s "
                     f"{c['rate_hz']:>8.2f}Hz {c['max_gap_s']:>8.3f}s {c['gaps']:>5}")
    for camera_id, c in info["cameras"].items():
        lines.append(f"camera      {camera_id}: {c['frames']} frames, "
                     f"{format_bytes(c['bytes'])}, {c['dropped']} dropped")
    counts = info["event_counts"]
    lines.append("events      " + (", ".join(f"{k} ×{n}" for k, n in sorted(counts.items()))
                                   or "none"))
    start = info["start_ns"] or 0
    for event in info["events"][:max_events]:
        lines.append(f"  {(event['time_ns'] - start) / 1e9:+9.3f} s  {event['kind']}: "
                     f"{event['message']}")
    if len(info["events"]) > max_events:
        lines.append(f"  … {len(info['events']) - max_events} more (--json lists all)")
    for warning in info["warnings"]:
        lines.append(f"warning     {warning}")
    return "\n".join(lines)
