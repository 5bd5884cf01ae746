"""The platform angle over time, from the motor states of a recording."""

from __future__ import annotations

from collections.abc import Sequence
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


#: A platform counts as turning at an end of its log when its position there differs from
#: its position this long before the end (after the start): a slow turn may report one step
#: count several times in a row, a platform at rest for this long is at rest.
TURNING_WINDOW_NS = 1_000_000_000


def turning_at_ends(times_ns: NDArray[np.int64], positions: NDArray[np.floating] | NDArray[
        np.integer], moving: Sequence[bool | None] | None = None) -> tuple[bool, bool]:
    """Whether a platform was turning at the first and at the last of its position reports
    (in time order): the position changed within :data:`TURNING_WINDOW_NS` of that end, and
    the report's ``moving`` flag (when known) does not say it was at rest."""
    t = np.asarray(times_ns, np.int64)
    x = np.asarray(positions, np.float64)
    if t.size < 2:
        return False, False
    at_start = x[: int(np.searchsorted(t, t[0] + TURNING_WINDOW_NS, side="right")) or 1]
    at_end = x[int(np.searchsorted(t, t[-1] - TURNING_WINDOW_NS, side="left")):]
    changed_start = bool(np.any(at_start != x[0]))
    changed_end = bool(np.any(at_end != x[-1]))
    flag_start = None if moving is None else moving[0]
    flag_end = None if moving is None else moving[-1]
    return (changed_start and flag_start is not False, changed_end and flag_end is not False)


def beyond_log(start_ns: NDArray[np.int64], end_ns: NDArray[np.int64],
               times_ns: NDArray[np.int64], positions: NDArray[np.floating] | NDArray[np.integer],
               moving: Sequence[bool | None] | None = None) -> NDArray[np.bool_]:
    """True for each time span ``[start, end]`` reaching beyond a position log (reports at
    ``times_ns``, in time order) at an end where the platform was turning
    (:func:`turning_at_ends`): held at the end's position such a span would be misplaced,
    by the turn's speed times its distance from the log (no tolerance: a log that ends at
    rest, as every complete one does, never drops anything)."""
    start = np.asarray(start_ns, np.int64)
    end = np.asarray(end_ns, np.int64)
    t = np.asarray(times_ns, np.int64)
    if t.size < 2:
        return np.zeros(start.shape, bool)
    turning_first, turning_last = turning_at_ends(t, positions, moving)
    before = (start < t[0]) if turning_first else np.zeros(start.shape, bool)
    after = (end > t[-1]) if turning_last else np.zeros(end.shape, bool)
    return np.asarray(before | after, bool)


def beyond_motor_log(start_ns: NDArray[np.int64], end_ns: NDArray[np.int64],
                     motor_table: pa.Table) -> NDArray[np.bool_]:
    """:func:`beyond_log` over a ``motor`` artifact: :func:`beta_deg_at` holds the angle
    beyond the log, which is right for a platform at rest and wrong (silently misplaced
    points) for one still turning — a motor log that ended early (a lost controller) or
    started late."""
    if motor_table.num_rows < 2:
        return np.zeros(np.shape(start_ns), bool)
    t = motor_times_ns(motor_table)
    order = np.argsort(t, kind="stable")
    steps = motor_table.column("step_count").to_numpy().astype(np.int64)[order]
    flags = motor_table.column("moving").to_pylist()
    return beyond_log(start_ns, end_ns, t[order], steps, [flags[i] for i in order])


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
