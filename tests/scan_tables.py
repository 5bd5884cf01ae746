"""Test helper: ``profiles``, ``motor`` and ``rig`` tables built directly from chosen values.

Follows docs/artifacts.md, so the assemble and filter tests do not depend on the decode stage.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.rig import MotorConfig, Pose, Rig, ScannerConfig, rig_table

T0_NS = 1_700_000_000_000_000_000


def make_rig(pulse_step_deg: float = 1.0, scan_hz: float = 5.0, settle_s: float = 0.05,
             beam_step_deg: float = 2.0, translation_m: tuple[float, float, float] = (0, 0, 0),
             rotation_deg: tuple[float, float, float] = (0, 0, 0), alpha_offset_deg: float = 0.0,
             beta_offset_deg: float = 0.0, pulse_limit: int = 100_000) -> Rig:
    """A rig whose pulse step is ``pulse_step_deg`` (gear ratio 0.72 / step)."""
    return Rig(
        scanner=ScannerConfig(dialect="paper", beam_step_deg=beam_step_deg,
                              scan_hz=scan_hz, alpha_offset_deg=alpha_offset_deg,
                              mount=Pose(translation_m=translation_m, rotation_deg=rotation_deg)),
        motor=MotorConfig(gear_ratio=0.72 / pulse_step_deg, settle_s=settle_s,
                          beta_offset_deg=beta_offset_deg, pulse_limit=pulse_limit,
                          unlimited_travel=True),
    )


def profiles_table(ranges_m: NDArray[np.floating], start_angle_deg: float | NDArray[Any],
                   step_deg: float, recv_time_ns: NDArray[np.int64],
                   device_time_ns: NDArray[np.int64] | None = None,
                   device_end_time_ns: NDArray[np.int64] | None = None,
                   frame: NDArray[np.int64] | None = None,
                   sector: NDArray[np.int64] | None = None,
                   checksum_ok: NDArray[np.bool_] | None = None,
                   echo: NDArray[np.uint16] | None = None) -> pa.Table:
    """A ``profiles`` artifact; ``ranges_m`` is (rows, samples) or a list of 1-D arrays."""
    rows = [np.asarray(r, np.float32) for r in ranges_m]
    n = len(rows)
    lengths = np.array([len(r) for r in rows], np.int32)
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    flat = np.concatenate(rows) if rows else np.zeros(0, np.float32)
    ranges = pa.ListArray.from_arrays(pa.array(offsets), pa.array(flat, pa.float32()))
    if echo is None:
        echo_col = pa.array([None] * n, pa.list_(pa.uint16()))
    else:
        echo_col = pa.ListArray.from_arrays(pa.array(offsets),
                                            pa.array(np.concatenate(list(echo)), pa.uint16()))

    def optional(values: NDArray[np.int64] | None) -> pa.Array:
        return pa.array([None] * n, pa.int64()) if values is None else pa.array(values, pa.int64())

    return pa.table({
        "recv_time_ns": pa.array(recv_time_ns, pa.int64()),
        "device_time_ns": optional(device_time_ns),
        "device_end_time_ns": optional(device_end_time_ns),
        "frame": pa.array(np.arange(n) if frame is None else frame, pa.int64()),
        "sector": pa.array(np.zeros(n) if sector is None else sector, pa.int32()),
        "start_angle_deg": pa.array(np.broadcast_to(start_angle_deg, n), pa.float64()),
        "step_deg": pa.array(np.full(n, step_deg), pa.float64()),
        "ranges_m": ranges,
        "echo": echo_col,
        "checksum_ok": pa.array(np.ones(n, bool) if checksum_ok is None else checksum_ok),
        "dialect": pa.array(["paper"] * n),
    })


def motor_table(log_time_ns: NDArray[np.int64], step_count: NDArray[np.int64],
                moving: NDArray[np.bool_],
                target_step_count: NDArray[np.int64] | None = None) -> pa.Table:
    """A ``motor`` artifact."""
    n = len(log_time_ns)
    return pa.table({
        "log_time_ns": pa.array(log_time_ns, pa.int64()),
        "step_count": pa.array(step_count, pa.int64()),
        "target_step_count": pa.array(step_count if target_step_count is None
                                      else target_step_count, pa.int64()),
        "moving": pa.array(moving, pa.bool_()),
        "device_time_us": pa.array(np.zeros(n), pa.int64()),
    })


@dataclass
class StepScan:
    """A step-and-scan recording as tables, with what each profile row really saw."""

    profiles: pa.Table
    motor: pa.Table
    rig: pa.Table
    #: per profile row: True when its window lies wholly inside a settled stationary interval
    clean: NDArray[np.bool_]
    #: per profile row: the position index it was measured at (−1 when the platform moved)
    position: NDArray[np.int64]


def step_scan(rig: Rig, positions: int, pulses_per_position: int,
              range_fn: Callable[[NDArray[np.float64], float], NDArray[np.float64]],
              profiles_per_dwell: int = 2, move_s: float = 0.1,
              with_device_time: bool = False) -> StepScan:
    """A step-and-scan run: the head streams a profile every 1/scan_hz all the time.

    The platform moves ``pulses_per_position`` steps (motor states: moving, then OK), settles,
    and dwells long enough for ``profiles_per_dwell`` whole profiles. Profiles during a move
    get ranges of 99 m, so one that leaks into the output is easy to see. ``range_fn(alpha,
    beta)`` gives the ranges of a stationary profile.
    """
    scanner, motor = rig.scanner, rig.motor
    samples = scanner.samples_per_profile
    alpha = scanner.start_angle_deg + np.arange(samples) * scanner.beam_step_deg
    period_ns = round(1e9 / scanner.scan_hz)
    window_ns = round((samples - 1) * scanner.beam_step_deg / 360 / scanner.scan_hz * 1e9)
    dwell_ns = round(motor.settle_s * 1e9) + (profiles_per_dwell + 1) * period_ns
    move_ns = round(move_s * 1e9)
    times, steps, moving, targets = [], [], [], []
    intervals = []  # (settled_from, until, position)
    t = T0_NS
    for k in range(positions):
        step = k * pulses_per_position
        if k:
            times.append(t)
            steps.append(step - pulses_per_position)
            targets.append(step)
            moving.append(True)
            t += move_ns
        times.append(t)
        steps.append(step)
        targets.append(step)
        moving.append(False)
        last = k == positions - 1  # the platform stays at its last position
        intervals.append((t + round(motor.settle_s * 1e9), 2**62 if last else t + dwell_ns, k))
        t += dwell_ns
    end = t
    starts = np.arange(T0_NS - period_ns // 3, end, period_ns, dtype=np.int64)
    rows, clean, position = [], [], []
    for s in starts:
        e = s + window_ns
        hit = [k for a, b, k in intervals if a <= s and e < b]
        k = hit[0] if hit else -1
        beta = k * pulses_per_position * motor.pulse_step_deg + motor.beta_offset_deg
        rows.append(range_fn(alpha, beta) if k >= 0 else np.full(samples, 99.0))
        clean.append(k >= 0)
        position.append(k)
    ranges = np.asarray(rows, np.float32)
    recv = starts + window_ns + 2_000_000
    device = (starts - T0_NS + 5_000_000) if with_device_time else None
    device_end = (device + window_ns) if device is not None else None
    return StepScan(
        profiles=profiles_table(ranges, scanner.start_angle_deg, scanner.beam_step_deg, recv,
                                device_time_ns=device, device_end_time_ns=device_end),
        motor=motor_table(np.array(times), np.array(steps), np.array(moving), np.array(targets)),
        rig=rig_table(rig),
        clean=np.array(clean),
        position=np.array(position),
    )


def positions_scan(rig: Rig, step_counts: list[int], ranges_m: NDArray[np.floating],
                   dwell_s: float = 1.0) -> dict[str, pa.Table]:
    """One clean profile per platform position (step counts in order): the assemble inputs.

    ``ranges_m`` is (positions, samples); each profile starts 0.1 s after its position settled.
    """
    scanner = rig.scanner
    dwell_ns = round(dwell_s * 1e9)
    ok = T0_NS + np.arange(len(step_counts), dtype=np.int64) * dwell_ns
    window_ns = round((ranges_m.shape[1] - 1) * scanner.beam_step_deg / 360
                      / scanner.scan_hz * 1e9)
    settle_ns = round(rig.motor.settle_s * 1e9)
    recv = ok + settle_ns + 100_000_000 + window_ns
    steps = np.asarray(step_counts, np.int64)
    moves = ok[1:] - 1000  # the move to the next position begins just before it is reported
    motor = motor_table(np.concatenate([ok, moves]), np.concatenate([steps, steps[:-1]]),
                        np.concatenate([np.zeros(len(ok), bool), np.ones(len(moves), bool)]),
                        np.concatenate([steps, steps[1:]]))
    return {
        "profiles": profiles_table(ranges_m, scanner.start_angle_deg, scanner.beam_step_deg,
                                   recv),
        "motor": motor,
        "rig": rig_table(rig),
    }
