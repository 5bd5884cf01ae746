"""``simulate --direct``: a recording as the emulators would produce it, without sockets.

The session is planned in simulation time (:func:`scanpipe.sim.session.plan_session`); every
profile's samples are cast in large batches at the platform angle of their instant, measured,
encoded with the dialect's wire encoder and cut into chunks at random boundaries as a TCP
receiver would see them; the motor link's bytes and position reports, and the cameras' JPEG
frames go in too, all in time order. The truth folder is written beside it.
"""

from __future__ import annotations

import json
import platform as platform_module
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe import __version__
from scanpipe.errors import SimulationError
from scanpipe.images import encode_jpeg_rgb
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.rig import Rig, ScannerConfig, rig_from_dict, rig_to_dict
from scanpipe.sim.camera import CameraModel, render_rgb
from scanpipe.sim.ldoem_device import LdoemDevice
from scanpipe.sim.options import SimOptions
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.scanner import (
    echo_amplitude,
    measure,
    packet_beams,
    sample_time_offsets_s,
    sector_duration_s,
    true_ranges,
)
from scanpipe.sim.scene import Scene
from scanpipe.sim.session import RX, TX, Session, camera_times_s, plan_session
from scanpipe.sim.truth import truth_table, write_truth
from scanpipe.sim.wire import SCANNER_CLOCK_ORIGIN_MS, device_clock_ms, profile_frame

#: How much earlier the first part of a frame read in two parts arrives.
PARTIAL_READ_LEAD_S = 50e-6
#: Rays per ray-casting call: large enough to keep Open3D busy, small enough for memory.
RAYS_PER_BATCH = 400_000


@dataclass(frozen=True)
class ProfileBatch:
    """Consecutive profiles: measured ranges, truth, and the angles at their first/last sample."""

    first: int
    measured_m: NDArray[np.float32]
    true_m: NDArray[np.float64]
    beta_first_deg: NDArray[np.float64]
    beta_last_deg: NDArray[np.float64]
    #: Echo amplitude of every measured sample (0 = no return).
    echo: NDArray[np.uint16] | None = None


def checked_rigs(options: SimOptions) -> tuple[Rig, Rig]:
    """The nominal and true rigs, validated (device limits included)."""
    nominal = rig_from_dict(rig_to_dict(options.nominal_rig()), "simulation rig")
    true = rig_from_dict(rig_to_dict(options.true_rig()), "simulation true rig")
    return nominal, true


#: Below this share of rays returning (over a full turn), the scene is not where the scanner
#: can see it. A small object alone in front of the scanner still returns a few percent.
MIN_RETURN_SHARE = 0.01
#: Profiles cast by the check, evenly over a full turn.
CHECK_PROFILES = 36


def check_scene_in_view(scene: Scene, scanner_true: ScannerConfig, name: str) -> None:
    """:class:`SimulationError` in one line when (nearly) every ray of a full turn returns
    nothing: the scene is not around the scanner, or it is in millimetres, or the scanner sits
    inside a closed mesh nearer than its minimum range."""
    beta = np.broadcast_to(np.linspace(0.0, 360.0, CHECK_PROFILES, endpoint=False)[:, None],
                           (CHECK_PROFILES, scanner_true.samples_per_profile))
    unlimited = scanner_true.model_copy(update={"min_range_m": 0.0, "max_range_m": np.inf})
    ranges = true_ranges(scene, unlimited, beta).ranges_m
    share = float(((ranges >= scanner_true.min_range_m)
                   & (ranges <= scanner_true.max_range_m)).mean())
    if share < MIN_RETURN_SHARE:
        low, high = scene.bounds
        near = float((ranges < scanner_true.min_range_m).mean())
        far = float((ranges > scanner_true.max_range_m).mean())
        raise SimulationError(
            f"scene {name}: only {share:.1%} of the scanner's rays return ({near:.0%} hit "
            f"nearer than its minimum range {scanner_true.min_range_m:g} m, {far:.0%} beyond "
            f"{scanner_true.max_range_m:g} m, {1 - share - near - far:.0%} hit nothing; the "
            f"scene spans {np.round(low, 3).tolist()} to {np.round(high, 3).tolist()} m, the "
            "scanner is at the origin): place the scene around the scanner with --scene-pose "
            "(not touching the origin), or convert it to metres if it is in millimetres")


def simulate_profiles(scene: Scene, scanner_true: ScannerConfig, session: Session,
                      options: SimOptions, progress: ProgressFn = no_progress
                      ) -> Iterator[ProfileBatch]:
    """Cast, measure and yield the session's profiles in batches (in order)."""
    offsets = sample_time_offsets_s(scanner_true)
    starts = session.profile_start_s
    per_batch = max(1, RAYS_PER_BATCH // len(offsets))
    model = options.measurement()
    beta_offset = options.true_rig().motor.beta_offset_deg
    step = options.rig.motor.pulse_step_deg
    total = len(starts)
    for first in range(0, total, per_batch):
        times = starts[first:first + per_batch, None] + offsets[None, :]
        beta = session.timeline.steps_at(times) * step + beta_offset
        truth = true_ranges(scene, scanner_true, beta)
        beams = packet_beams(scene, scanner_true, beta) if scanner_true.dialect == \
            "ldrobot_ld14" else truth  # an LD14's samples: its beams off their angles
        measured = measure(beams, model, first, scanner_true)
        yield ProfileBatch(first, measured, truth.ranges_m, beta[:, 0].copy(), beta[:, -1].copy(),
                           echo_amplitude(measured, beams))
        progress("scanner profiles", min(first + per_batch, total), total)


def _write_event(writer: Any, t_ns: int, kind: str, payload: tuple[Any, ...], scene: Scene,
                 camera_model: CameraModel, seed: int) -> None:
    if kind in ("scanner", "motor"):
        data, direction = payload
        writer.write_stream(kind, data, direction, t_ns)
    elif kind == "state":
        (state,) = payload
        writer.write_motor_state(t_ns, state.step_count, state.target_step_count, state.moving,
                                 state.device_time_us)
    else:
        cam, beta, index, j = payload
        image_rng = np.random.default_rng([seed, 13, index, j])
        rgb = render_rgb(scene, cam, beta, camera_model, image_rng)
        writer.write_image(cam.id, t_ns, encode_jpeg_rgb(rgb, camera_model.jpeg_quality),
                           frame_id=cam.id)


def chunk_stream(frames: list[bytes], times: list[float], rng: np.random.Generator
                 ) -> list[tuple[float, bytes]]:
    """Cut frames into the chunks a socket reader would get: a frame sent at once arrives by
    its end, but often in two reads (the first a little earlier), split at a random byte."""
    chunks: list[tuple[float, bytes]] = []
    for frame, t_s in zip(frames, times, strict=True):
        if len(frame) > 2 and rng.random() < 0.5:
            cut = int(rng.integers(1, len(frame)))
            chunks.append((t_s - PARTIAL_READ_LEAD_S, frame[:cut]))
            chunks.append((t_s, frame[cut:]))
        else:
            chunks.append((t_s, frame))
    return chunks


def _ldoem_startup(scanner: ScannerConfig, options: SimOptions
                   ) -> tuple[list[tuple[float, int, bytes]], LdoemDevice]:
    """The acquisition client's start-up requests and the device's replies, in time order."""
    from scanpipe.protocol import ldoem

    device = LdoemDevice(scanner)
    exchange: list[tuple[float, int, bytes]] = []
    t = 0.0
    for request in (ldoem.get_ident_request(), ldoem.get_status_request(),
                    ldoem.rotate_request(int(scanner.scan_hz)),
                    ldoem.get_profile_request(0, ldoem.MASK_RANGES_ECHO)):
        exchange.append((t, TX, request))
        t += options.link_latency_s
        payload = request[8:-1]
        for reply in device.handle(payload, device_clock_ms(t)):
            exchange.append((t, RX, reply))
        t += options.link_latency_s
    return exchange, device


def simulate_direct(out: Path, truth_dir: Path, options: SimOptions | None = None,
                    progress: ProgressFn = no_progress,
                    recording_name: str | None = None) -> dict[str, Any]:
    """Write a simulated recording to ``out`` and its ground truth to ``truth_dir``.

    Returns a summary (counts, sizes, seconds).
    """
    from scanpipe.recording.writer import RecordingWriter

    options = options if options is not None else SimOptions()
    started = time.perf_counter()
    nominal, true = checked_rigs(options)
    scene = resolve_scene(options.scene, options.scene_pose, options.scene_up)
    check_scene_in_view(scene, true.scanner, options.scene)
    session = plan_session(options, true)
    scanner = true.scanner
    dialect = nominal.scanner.dialect
    rng = np.random.default_rng([options.seed, 3])

    def wall_ns(time_s: float) -> int:
        return options.start_time_ns + round(time_s * 1e9)

    # What to write, as (time_ns, order, kind, payload); sorted by time before writing.
    events: list[tuple[int, int, str, tuple[Any, ...]]] = []

    def add(time_s: float, kind: str, *payload: Any) -> None:
        events.append((wall_ns(time_s), len(events), kind, payload))

    for item in session.motor_link:
        add(item.time_s, "motor", item.data, item.direction)
    for state in session.motor_states:
        add(state.time_s, "state", state)

    device = None
    if dialect == "ldoem":
        exchange, device = _ldoem_startup(scanner, options)
        for t_s, direction, data in exchange:
            add(t_s, "scanner", data, direction)

    true_rows: list[ProfileBatch] = []
    frames: list[bytes] = []
    recv_s: list[float] = []
    sector = sector_duration_s(scanner)
    # what the recorder asks for by default: ranges and echo amplitudes
    from scanpipe.protocol.ldoem import MASK_RANGES_ECHO
    ldoem_mask = MASK_RANGES_ECHO if dialect == "ldoem" else None
    for batch in simulate_profiles(scene, scanner, session, options, progress):
        true_rows.append(batch)
        for row in range(batch.measured_m.shape[0]):
            k = batch.first + row
            frames.append(profile_frame(
                dialect, k, batch.measured_m[row], scanner, float(session.profile_start_s[k]),
                mask=ldoem_mask, echo=None if batch.echo is None else batch.echo[row]))
            recv_s.append(float(session.profile_start_s[k]) + sector + options.link_latency_s)
    scanner_bytes = 0
    for t_s, chunk in chunk_stream(frames, recv_s, rng):
        scanner_bytes += len(chunk)
        add(t_s, "scanner", chunk, RX)
    if device is not None:
        from scanpipe.protocol import ldoem

        cancel_s = session.end_s - 0.005
        cancel = ldoem.cancel_profile_request()
        add(cancel_s, "scanner", cancel, TX)
        reply_s = cancel_s + options.link_latency_s
        for reply in device.handle(cancel[8:-1], device_clock_ms(reply_s)):
            add(reply_s, "scanner", reply, RX)

    n_frames = 0
    if options.cameras:
        step = options.rig.motor.pulse_step_deg
        for index, cam in enumerate(true.cameras):
            times = camera_times_s(cam.fps, session.end_s, options.seed, index)
            betas = session.timeline.steps_at(times) * step + true.motor.beta_offset_deg
            for j, (t_s, beta) in enumerate(zip(times, betas, strict=True)):
                n_frames += 1
                add(float(t_s), "image", cam, float(beta), index, j)

    events.sort(key=lambda e: (e[0], e[1]))
    session_meta = {
        "simulated": True, "mode": options.mode, "seed": options.seed,
        "motor_step_count": options.motor_step_count(), "scene": options.scene,
        "start_time_ns": options.start_time_ns,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    written_frames = 0
    with RecordingWriter(out, nominal, session_meta) as writer:
        camera_model = options.camera_model()
        for index, (t_ns, _, kind, payload) in enumerate(events):
            _write_event(writer, t_ns, kind, payload, scene, camera_model, options.seed)
            if index % 2000 == 0:
                progress("writing", index, len(events))
        progress("writing", len(events), len(events))
        written_frames = n_frames

    ranges_true = (np.concatenate([b.true_m for b in true_rows]) if true_rows
                   else np.zeros((0, scanner.samples_per_profile)))
    starts = session.profile_start_s
    profiles = truth_table(
        np.array([wall_ns(float(s)) for s in starts], dtype=np.int64),
        np.array([wall_ns(float(s) + float(sample_time_offsets_s(scanner)[-1])) for s in starts],
                 dtype=np.int64),
        np.concatenate([b.beta_first_deg for b in true_rows]) if true_rows else np.zeros(0),
        np.concatenate([b.beta_last_deg for b in true_rows]) if true_rows else np.zeros(0),
        ranges_true)
    summary: dict[str, Any] = {
        # The name the recording will have when ``out`` is a temporary file renamed after.
        "recording": recording_name or str(out), "truth": str(truth_dir), "mode": options.mode,
        "dialect": dialect, "profiles": len(starts),
        "samples_per_profile": scanner.samples_per_profile, "positions": session.positions,
        "motor_step_count": options.motor_step_count(),
        "motor_states": len(session.motor_states), "frames": written_frames,
        "scanner_bytes": scanner_bytes, "duration_s": round(session.end_s, 3),
        "warnings": list(scene.warnings),
    }
    meta = {
        "seed": options.seed, "options": json.loads(options.model_dump_json()),
        "versions": versions(), "summary": summary,
        "scanner_clock_origin_ms": SCANNER_CLOCK_ORIGIN_MS,
    }
    write_truth(Path(truth_dir), scene, true, profiles, meta)
    summary["seconds"] = round(time.perf_counter() - started, 3)
    summary["recording_bytes"] = out.stat().st_size
    return summary


def versions() -> dict[str, str]:
    """Versions of what a simulated result depends on (for the truth meta)."""
    import open3d

    return {"scanpipe": __version__, "numpy": np.__version__, "open3d": open3d.__version__,
            "python": platform_module.python_version()}
