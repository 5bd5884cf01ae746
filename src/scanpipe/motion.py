"""The platform angle over time, from the motor states of a recording."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.clock import ClockModel, fit_clock
from scanpipe.errors import StageError
from scanpipe.rig import MotorConfig


def beta_deg_from_steps(step_count: NDArray[np.integer] | NDArray[np.floating],
                        motor: MotorConfig) -> NDArray[np.float64]:
    """Platform angle for step counts: ``steps × full_step / gear_ratio + beta_offset``."""
    return np.asarray(step_count, dtype=np.float64) * motor.pulse_step_deg + motor.beta_offset_deg


def beta_deg_at(times_ns: NDArray[np.int64], motor_table: pa.Table,
                motor: MotorConfig) -> NDArray[np.float64]:
    """Platform angle at each time, linearly interpolated between reported motor states.

    Before the first state and after the last the angle is held. ``motor_table`` is the
    ``motor`` artifact (``log_time_ns``, ``step_count``), in any order; the states' times are
    those of :func:`motor_times_ns`.
    """
    if motor_table.num_rows == 0:
        raise StageError("motor: no motor states in the recording; cannot place profiles in β")
    t = motor_times_ns(motor_table)
    steps = motor_table.column("step_count").to_numpy().astype(np.float64)
    order = np.argsort(t, kind="stable")
    t, steps = t[order], steps[order]
    t0 = t[0]  # interpolate in float64 relative to the first state: ns since epoch loses bits
    interpolated = np.interp((np.asarray(times_ns, np.int64) - t0).astype(np.float64),
                             (t - t0).astype(np.float64), steps)
    return beta_deg_from_steps(interpolated, motor)


#: A time is beyond the motor log when it lies more than this many of the log's typical report
#: intervals before its first or after its last state.
BEYOND_LOG_INTERVALS = 2.0
#: ... and at least this much (a log of very frequent reports still jitters by a few ms).
BEYOND_LOG_MIN_NS = 50_000_000


def beyond_motor_log(start_ns: NDArray[np.int64], end_ns: NDArray[np.int64],
                     motor_table: pa.Table) -> NDArray[np.bool_]:
    """True for each time span reaching beyond the motor log at an end where the platform
    was turning: :func:`beta_deg_at` holds the angle there, which is right for a platform
    at rest and wrong (silently misplaced points) for one that was still moving — a motor
    log that ended early (a lost controller) or started late.

    "Moving" at an end is the end state's ``moving`` flag, or, where it is null, a step
    count that differs from its neighbour's.
    """
    start = np.asarray(start_ns, np.int64)
    end = np.asarray(end_ns, np.int64)
    if motor_table.num_rows < 2:
        return np.zeros(start.shape, bool)
    t = motor_times_ns(motor_table)
    order = np.argsort(t, kind="stable")
    t = t[order]
    steps = motor_table.column("step_count").to_numpy().astype(np.int64)[order]
    flags = motor_table.column("moving").to_pylist()
    first_flag, last_flag = flags[order[0]], flags[order[-1]]
    moving_at_start = bool(first_flag) if first_flag is not None else steps[0] != steps[1]
    moving_at_end = bool(last_flag) if last_flag is not None else steps[-1] != steps[-2]
    tolerance_ns = max(BEYOND_LOG_INTERVALS * float(np.median(np.diff(t))), BEYOND_LOG_MIN_NS)
    before = (start < t[0] - tolerance_ns) if moving_at_start else np.zeros(start.shape, bool)
    after = (end > t[-1] + tolerance_ns) if moving_at_end else np.zeros(end.shape, bool)
    return np.asarray(before | after, bool)


def motor_clock(motor_table: pa.Table) -> ClockModel | None:
    """The controller's own clock fitted to the states' receive times; None when unusable.

    The host stamps a state when it reads it, late by the serial link's and its own latency,
    which varies; the controller stamps it when it happened (``device_time_us``). Unusable
    when a state has no device time, the device time runs backwards (a controller reset) or
    mostly stands still (a controller that does not stamp).
    """
    if "device_time_us" not in motor_table.column_names or motor_table.num_rows < 2:
        return None
    column = motor_table.column("device_time_us")
    if column.null_count:
        return None
    log = motor_table.column("log_time_ns").to_numpy().astype(np.int64)
    device_ns = column.to_numpy().astype(np.int64) * 1000
    steps = np.diff(device_ns)  # in the order the states were read
    if np.any(steps < 0) or np.count_nonzero(steps > 0) < 0.5 * steps.size:
        return None  # a reset, or a controller that does not stamp (zeros)
    model = fit_clock(device_ns, log)
    return replace(model, name="the motor controller's clock")


def motor_times_ns(motor_table: pa.Table) -> NDArray[np.int64]:
    """Host times of the motor states, in table order, without the receive jitter.

    The controller's clock mapped by :func:`motor_clock` when it is usable, else the log
    (receive) times.
    """
    clock = motor_clock(motor_table)
    if clock is None:
        return np.asarray(motor_table.column("log_time_ns").to_numpy(), np.int64)
    return clock.to_host_ns(motor_table.column("device_time_us").to_numpy().astype(
        np.int64) * 1000)
