"""The platform angle over time, from the motor states of a recording."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.errors import StageError
from scanpipe.rig import MotorConfig


def beta_deg_from_steps(step_count: NDArray[np.integer] | NDArray[np.floating],
                        motor: MotorConfig) -> NDArray[np.float64]:
    """Platform angle for step counts: ``steps × full_step / gear_ratio + beta_offset``."""
    return np.asarray(step_count, dtype=np.float64) * motor.step_deg + motor.beta_offset_deg


def beta_deg_at(times_ns: NDArray[np.int64], motor_table: pa.Table,
                motor: MotorConfig) -> NDArray[np.float64]:
    """Platform angle at each time, linearly interpolated between reported motor states.

    Before the first state and after the last the angle is held. ``motor_table`` is the
    ``motor`` artifact (``log_time_ns``, ``step_count``), in any order.
    """
    if motor_table.num_rows == 0:
        raise StageError("motor: no motor states in the recording; cannot place profiles in β")
    t = motor_table.column("log_time_ns").to_numpy().astype(np.int64)
    steps = motor_table.column("step_count").to_numpy().astype(np.float64)
    order = np.argsort(t, kind="stable")
    t, steps = t[order], steps[order]
    t0 = t[0]  # interpolate in float64 relative to the first state: ns since epoch loses bits
    interpolated = np.interp((np.asarray(times_ns, np.int64) - t0).astype(np.float64),
                             (t - t0).astype(np.float64), steps)
    return beta_deg_from_steps(interpolated, motor)
