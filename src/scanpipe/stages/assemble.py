"""Assemble: profiles and motor states to a calibrated 3-D point cloud that keeps its grid.

Time association decides which profile belongs to which platform angle:

- *step-and-scan* (``mode = step``): the motor stands still between moves. A stationary interval
  begins at the first motor state that reports the platform at rest at its target (the
  controller's OK) plus the settle time, and ends at the next motor state that reports motion or
  a new target. A profile counts only if its whole acquisition window lies inside one such
  interval; the others are dropped and counted (``moving``, ``settling``). Each interval with a
  complete profile becomes one grid profile at ``β = steps × step + β offset``: the first
  complete profile (``step_profile = first``) or the mean of the valid returns of all complete
  profiles there (``average``; time and echo then come from the first).
- *continuous*: every sample gets its own time and its platform angle interpolated from the
  motor states at that time (:func:`scanpipe.motion.beta_deg_at`); one grid profile per head turn.
- ``auto`` picks step when at least 3 stationary intervals, and at least half of them, hold a
  complete profile (a continuous scan stands still only before and after its one move), or
  when at least half the profiles lie inside stationary intervals.

Sample times come from the device's sector timestamps when the profiles carry them, mapped to
the host clock by a fitted model ``host = offset + rate · device`` (:mod:`scanpipe.clock`:
the rate is fitted, not assumed to be 1, and the fit's problems are reported), else from the
receive time (the end of the sector, less ``receive_latency_s``) and the head turn: one beam
step takes ``step / 360`` of a turn. Receive times jitter with the host's load, so the frame
counter is read as a clock ticking once per turn and fitted to them the same way
(:func:`frame_clock`); that also measures the turn on the host clock.

Geometry (:mod:`scanpipe.geometry`): the return at range r and beam angle
``α = start + i·step + α offset`` lies at ``R_mount · r (sin α, cos α, 0) + t_mount`` in the
platform frame, turned by β about y. The trig runs once per sample angle and once per platform
angle (per sample in continuous mode, in float32) and is broadcast over the grid.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.clock import ClockModel, fit_clock
from scanpipe.errors import StageError
from scanpipe.geometry import rotation_matrix_deg, scan_plane_direction
from scanpipe.motion import (
    beta_deg_at,
    beta_deg_from_steps,
    beyond_motor_log,
    motor_clock,
    motor_times_ns,
)
from scanpipe.params import Params
from scanpipe.progress import ProgressFn
from scanpipe.rig import Rig, rig_from_table
from scanpipe.schema import MOTOR, ORIGIN, PROFILES, XYZ
from scanpipe.stage import Stage, StageResult

I64 = NDArray[np.int64]
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
B = NDArray[np.bool_]



class AssembleParams(Params):
    """How profiles are placed in time and in β."""

    mode: Literal["auto", "step", "continuous"] = Field(
        "auto", description="step-and-scan, continuous rotation, or decide from the motor log")
    step_profile: Literal["first", "average"] = Field(
        "first", description="step mode: the first complete profile per position, or the mean "
                             "of all complete ones")
    time_source: Literal["auto", "device", "receive"] = Field(
        "auto", description="sample times from the device's sector timestamps or from the "
                            "receive time; auto = device when every profile has them")
    clock_offset_ns: int | None = Field(
        None, description="host time = clock_rate × device time + this; None = fit it (the "
                          "lower envelope of receive minus sector end)")
    clock_rate: float | None = Field(
        None, gt=0, le=1000, description="host ns per device ns; None = fit it (1 when "
                                         "clock_offset_ns alone is given)")
    receive_latency_s: float = Field(
        0.0, ge=0, le=10, description="receive time source: delay from a sector's last sample "
                                      "to its receipt")
    settle_s: float | None = Field(
        None, ge=0, le=10, description="wait after a move before a profile counts; "
                                       "None = the rig's motor.settle_s")
    keep_bad_checksum: bool = Field(
        False, description="use profiles whose checksum failed (lenient decode)")


@dataclass(frozen=True)
class ScanLines:
    """The profile rows as arrays: timing, angular placement, and the flat ranges."""

    start_ns: I64  # time of the first sample (host clock)
    sample_dt_ns: F64  # time between consecutive samples (host clock)
    lengths: I64
    row_starts: I64  # offset of each row's first sample in ``ranges``
    ranges: F32
    echo: NDArray[np.uint16] | None
    start_angle_deg: F64
    step_deg: F64
    sector: I64
    frame: I64
    usable: B
    dropped: dict[str, int]
    time_source: str
    #: Device → host time: the sector timestamps' clock (device source), or the frame counter
    #: fitted to the receive times (receive source); None without either.
    clock: ClockModel | None
    turn_s: float  # one head turn on the host clock
    #: Host seconds per physical second: the motor controller's clock rate, else the scanner's,
    #: else 1. 1 for real hardware; a simulated speed-up shows here. Durations from the rig
    #: file (the head turn, the settle time) are physical and are scaled by it.
    time_scale: float

    @property
    def end_ns(self) -> I64:
        """Time of each row's last sample."""
        span = np.maximum(self.lengths - 1, 0) * self.sample_dt_ns
        return self.start_ns + np.rint(span).astype(np.int64)


def _int_column(table: pa.Table, name: str, default: int) -> tuple[I64, B]:
    """An integer column as int64 with ``default`` for nulls, and the mask of present values."""
    if name not in table.column_names:
        return np.full(table.num_rows, default, np.int64), np.zeros(table.num_rows, bool)
    column = table.column(name)
    present = ~column.is_null().to_numpy(zero_copy_only=False)
    values = column.fill_null(default).to_numpy().astype(np.int64)
    return values, present


def _flatten_lists(column: pa.ChunkedArray) -> tuple[NDArray[Any], I64]:
    """Values and per-row lengths of a list column (null rows have length 0)."""
    array = column.combine_chunks()
    lengths = array.value_lengths().fill_null(0).to_numpy().astype(np.int64)
    return array.flatten().to_numpy(zero_copy_only=False), lengths


def scan_lines(profiles: pa.Table, rig: Rig, params: AssembleParams,
               motor_rate: float | None = None) -> ScanLines:
    """Per-row timing and placement of the ``profiles`` artifact (see the module docstring).

    ``motor_rate`` is the motor controller's fitted clock rate (host per physical second),
    when it has a clock.
    """
    PROFILES.check(profiles)
    ranges, lengths = _flatten_lists(profiles.column("ranges_m"))
    ranges = ranges.astype(np.float32, copy=False)
    row_starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    echo = None
    if "echo" in profiles.column_names and profiles.column("echo").null_count < profiles.num_rows:
        echo_values, echo_lengths = _flatten_lists(profiles.column("echo"))
        if np.array_equal(echo_lengths, lengths):
            echo = echo_values.astype(np.uint16, copy=False)
    recv, _ = _int_column(profiles, "recv_time_ns", 0)
    dev_start, has_start = _int_column(profiles, "device_time_ns", 0)
    dev_end, has_end = _int_column(profiles, "device_end_time_ns", 0)
    frame, _ = _int_column(profiles, "frame", 0)
    sector, _ = _int_column(profiles, "sector", 0)
    start_angle = profiles.column("start_angle_deg").to_numpy().astype(np.float64)
    step = profiles.column("step_deg").to_numpy().astype(np.float64)
    nominal_turn_ns = 1e9 / rig.scanner.scan_hz

    usable = lengths > 0
    dropped = {"empty": int(np.count_nonzero(~usable))}
    if "checksum_ok" in profiles.column_names and not params.keep_bad_checksum:
        ok = profiles.column("checksum_ok").fill_null(False).to_numpy(zero_copy_only=False)
        dropped["checksum"] = int(np.count_nonzero(usable & ~ok))
        usable &= ok

    source = params.time_source
    if source == "auto":
        source = "device" if profiles.num_rows and bool(has_start.all()) else "receive"
    if source == "device" and not has_start[usable].all():
        raise StageError("profiles: time_source = 'device' but some profiles have no "
                         "device_time_ns; use 'receive' or 'auto'")
    clock: ClockModel | None
    if source == "device":
        fit_rows = usable if usable.any() else np.ones(usable.size, bool)
        device_end = np.where(has_end, dev_end, dev_start)
        clock = fit_clock(device_end[fit_rows], recv[fit_rows], params.clock_rate,
                          params.clock_offset_ns)
        beam_dt_ns = step / 360.0 * nominal_turn_ns * clock.rate
        with np.errstate(invalid="ignore", divide="ignore"):
            measured_dt = (dev_end - dev_start) / np.maximum(lengths - 1, 1).astype(np.float64)
        sample_dt = np.where(has_end & (lengths > 1), measured_dt * clock.rate, beam_dt_ns)
        start = clock.to_host_ns(dev_start)
        time_scale = motor_rate if motor_rate is not None else clock.rate
        turn_s = nominal_turn_ns * clock.rate / 1e9
    else:
        time_scale = motor_rate if motor_rate is not None else 1.0
        turn_s = nominal_turn_ns * time_scale / 1e9
        clock = frame_clock(recv, frame, nominal_turn_ns, params.clock_rate,
                            max_latency_s=turn_s / 2)
        # Receive times without their jitter, where the frame counter fits them.
        end = recv if clock is None else clock.to_host_ns(
            np.rint(frame * nominal_turn_ns).astype(np.int64))
        end = end - round(params.receive_latency_s * 1e9)
        sample_dt = step / 360.0 * turn_s * 1e9
        start = end - np.rint(np.maximum(lengths - 1, 0) * sample_dt).astype(np.int64)
    return ScanLines(
        start_ns=start.astype(np.int64), sample_dt_ns=np.asarray(sample_dt, np.float64),
        lengths=lengths, row_starts=row_starts, ranges=ranges, echo=echo,
        start_angle_deg=start_angle, step_deg=step, sector=sector, frame=frame, usable=usable,
        dropped=dropped, time_source=source, clock=clock, turn_s=turn_s,
        time_scale=time_scale,
    )


def frame_clock(recv_ns: I64, frame: I64, nominal_turn_ns: float, rate: float | None = None,
                max_latency_s: float = 0.1, min_frames: int = 8) -> ClockModel | None:
    """The frame counter fitted to the receive times, to take the receive jitter out.

    A streaming scanner ends frame ``n`` at ``t0 + n · turn``; the host receives it some
    latency later. Fitting ``host = offset + rate · n · turn`` to the receive times (the lower
    envelope, :func:`scanpipe.clock.fit_clock`) gives each frame's time without the jitter.
    None — use the raw receive times — with fewer than ``min_frames`` frames, a counter that
    does not rise (a restarted device), or frames that do not follow one clock (sent on
    request at irregular times: the median latency exceeds ``max_latency_s``; a loaded host
    delays some receipts far more, so not the 99th percentile).
    """
    new_frame = np.concatenate([[True], frame[1:] != frame[:-1]]) if frame.size else frame
    numbers, first_recv = frame[new_frame], recv_ns[new_frame]
    if numbers.size < min_frames or np.any(np.diff(numbers) <= 0):
        return None
    model = fit_clock(np.rint(numbers * nominal_turn_ns).astype(np.int64), first_recv, rate)
    if model.median_latency_s > max_latency_s:
        return None
    return replace(model, name="the frame counter (a frame per head turn at the rig's scan_hz)")


@dataclass(frozen=True)
class StationaryIntervals:
    """Runs of motor states at rest at one step count: ``[first_ns, end_ns)`` with settle."""

    first_ns: I64  # time of the first state of the run (the controller's OK)
    end_ns: I64  # time of the next state after the run (motion or a new target); int64 max
    step_count: I64


def stationary_intervals(motor: pa.Table) -> StationaryIntervals:
    """The motor log's stationary runs (see :class:`StationaryIntervals`)."""
    MOTOR.check(motor)
    if motor.num_rows == 0:
        raise StageError("motor: no motor states in the recording; cannot place profiles in β")
    t = motor_times_ns(motor)
    order = np.argsort(t, kind="stable")
    t = t[order]
    steps = motor.column("step_count").to_numpy().astype(np.int64)[order]
    moving = motor.column("moving").fill_null(True).to_numpy(zero_copy_only=False)[order]
    target, has_target = _int_column(motor, "target_step_count", 0)
    target = np.where(has_target, target, motor.column("step_count").to_numpy())[order]
    at_rest = ~moving & (steps == target)
    previous_rest = np.concatenate([[False], at_rest[:-1]])
    previous_steps = np.concatenate([[steps[0] - 1], steps[:-1]])
    run_start = at_rest & ~(previous_rest & (previous_steps == steps))
    next_rest = np.concatenate([at_rest[1:], [False]])
    next_steps = np.concatenate([steps[1:], [steps[-1] - 1]])
    run_last = at_rest & ~(next_rest & (next_steps == steps))
    starts = np.flatnonzero(run_start)
    lasts = np.flatnonzero(run_last)
    after = lasts + 1
    end = np.where(after < t.size, t[np.minimum(after, t.size - 1)], np.iinfo(np.int64).max)
    return StationaryIntervals(first_ns=t[starts], end_ns=end.astype(np.int64),
                               step_count=steps[starts])


def associate_steps(lines: ScanLines, intervals: StationaryIntervals,
                    settle_ns: int) -> tuple[I64, dict[str, int]]:
    """Each row's stationary interval (−1 when it overlaps motion or settling) and drop counts."""
    start, end = lines.start_ns, lines.end_ns
    if intervals.first_ns.size == 0:  # the platform never stood still
        moving_rows = int(np.count_nonzero(lines.usable))
        return np.full(start.size, -1, np.int64), {"moving": moving_rows, "settling": 0,
                                                   "before_motor_log": 0}
    run = np.searchsorted(intervals.first_ns, start, side="right") - 1
    has_run = run >= 0
    safe = np.maximum(run, 0)
    before_log = ~has_run
    moving = has_run & (end >= intervals.end_ns[safe])
    settling = has_run & ~moving & (start < intervals.first_ns[safe] + settle_ns)
    inside = has_run & ~moving & ~settling
    usable = lines.usable
    counts = {
        "moving": int(np.count_nonzero(usable & moving)),
        "settling": int(np.count_nonzero(usable & settling)),
        "before_motor_log": int(np.count_nonzero(usable & before_log)),
    }
    return np.where(usable & inside, run, -1).astype(np.int64), counts


def _first_per_group(keys: I64) -> B:
    """True for the first occurrence (in row order) of each key."""
    first = np.zeros(keys.size, dtype=bool)
    _, index = np.unique(keys, return_index=True)
    first[index] = True
    return first


@dataclass(frozen=True)
class GridLayout:
    """Which row goes to which grid profile and column, and the grid's angles and times."""

    rows: I64  # rows that contribute, in grid-profile order
    profile_of_row: I64  # grid profile of each contributing row
    first_rows: B  # per contributing row: the first of its (profile, sector), giving the echo
    column0: I64  # grid column of each contributing row's first sample
    samples: int
    alpha0_deg: float
    step_deg: float
    time0_ns: I64  # per grid profile: time of column 0 (extrapolated along the head turn)
    sample_dt_ns: F64  # per grid profile


def grid_layout(lines: ScanLines, rows: I64, profile_of_row: I64, first_rows: B) -> GridLayout:
    """Place contributing rows in the grid by their start angle (sectors side by side)."""
    if rows.size == 0:
        raise StageError("profiles: no profile could be placed (see the drop counts)")
    steps = lines.step_deg[rows]
    step = float(np.median(steps))
    if np.any(np.abs(steps - step) > 1e-9 * max(1.0, abs(step))):
        raise StageError(f"profiles: mixed angular steps {sorted(set(steps.tolist()))}; "
                         "one scan must use one step")
    alpha0 = float(np.min(lines.start_angle_deg[rows]))
    column0 = np.rint((lines.start_angle_deg[rows] - alpha0) / step).astype(np.int64)
    samples = int(np.max(column0 + lines.lengths[rows]))
    n_profiles = int(profile_of_row.max()) + 1
    time0 = np.zeros(n_profiles, np.int64)
    dt = np.zeros(n_profiles, np.float64)
    # Time runs along the head turn: extrapolate each grid profile's first row over all columns.
    timing = _first_per_group(profile_of_row)
    gp = profile_of_row[timing]
    dt[gp] = lines.sample_dt_ns[rows[timing]]
    time0[gp] = lines.start_ns[rows[timing]] - np.rint(column0[timing] * dt[gp]).astype(np.int64)
    return GridLayout(rows, profile_of_row, first_rows, column0, samples, alpha0, step,
                      time0, dt)


def _cells(lines: ScanLines, layout: GridLayout, which: B) -> tuple[I64, I64]:
    """Flat grid cells and flat sample indices of the contributing rows selected by ``which``."""
    rows = layout.rows[which]
    n = lines.lengths[rows]
    base = layout.profile_of_row[which] * layout.samples + layout.column0[which]
    total = int(n.sum())
    within = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(n) - n, n)
    return np.repeat(base, n) + within, np.repeat(lines.row_starts[rows], n) + within


def range_grid(lines: ScanLines, layout: GridLayout, average: bool) -> tuple[F32, B]:
    """The (P, S) range image (NaN = no return) and the mask of cells any profile measured."""
    n_profiles = int(layout.time0_ns.size)
    shape = (n_profiles, layout.samples)
    every_row_full = bool(np.all(lines.lengths == layout.samples))
    simple = (not average and every_row_full and np.all(layout.column0 == 0)
              and np.array_equal(layout.profile_of_row, np.arange(layout.rows.size)))
    if simple:  # the common case: one full sector per profile, a reshape and a row take
        ranges = lines.ranges.reshape(-1, layout.samples)[layout.rows]
        return ranges, np.ones(shape, bool)
    cells, flat = _cells(lines, layout, np.ones(layout.rows.size, bool))
    measured = np.zeros(shape[0] * shape[1], bool)
    measured[cells] = True
    values = lines.ranges[flat]
    if average:
        finite = np.isfinite(values)
        size = shape[0] * shape[1]
        sums = np.bincount(cells[finite], weights=values[finite], minlength=size)
        counts = np.bincount(cells[finite], minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan).astype(np.float32)
    else:
        out = np.full(shape[0] * shape[1], np.nan, np.float32)
        out[cells] = values
    return out.reshape(shape), measured.reshape(shape)


def echo_grid(lines: ScanLines, layout: GridLayout) -> NDArray[np.uint16] | None:
    """The (P, S) echo image from each grid profile's first row; 0 where unmeasured."""
    if lines.echo is None:
        return None
    out = np.zeros(int(layout.time0_ns.size) * layout.samples, np.uint16)
    cells, flat = _cells(lines, layout, layout.first_rows)
    out[cells] = lines.echo[flat]
    return out.reshape(-1, layout.samples)


def points_from_grid(ranges: F32, alpha_deg: F64, beta_deg: F64, rig: Rig) -> dict[str, F32]:
    """Rig-frame x, y, z and the sensor origin for a range image (the fast path).

    ``alpha_deg`` is per sample ``(S,)`` with the α offset already added; ``beta_deg`` is per
    profile ``(P,)`` or per cell ``(P, S)`` with the β offset already added. Arrays are
    ``(P, S)`` float32; the trig of α runs once per sample, that of β once per entry given.
    """
    mount = rig.scanner.mount
    beams = scan_plane_direction(alpha_deg) @ rotation_matrix_deg(mount.rotation_deg).T
    dx, dy, dz = (beams[:, k].astype(np.float32) for k in range(3))
    tx, ty, tz = (np.float32(v) for v in mount.translation_m)
    beta = np.radians(beta_deg)
    if beta.ndim == 1:
        beta = beta[:, None]
    cos_b = np.cos(beta).astype(np.float32) if beta.shape[1] == 1 else np.cos(
        beta.astype(np.float32))
    sin_b = np.sin(beta).astype(np.float32) if beta.shape[1] == 1 else np.sin(
        beta.astype(np.float32))
    px = ranges * dx
    py = ranges * dy
    pz = ranges * dz
    if tx or ty or tz:
        px += tx
        py += ty
        pz += tz
    shape = ranges.shape
    x, y, z = XYZ
    ox, oy, oz = ORIGIN
    return {
        x: px * cos_b - pz * sin_b,
        y: py,
        z: px * sin_b + pz * cos_b,
        ox: np.broadcast_to(tx * cos_b - tz * sin_b, shape),
        oy: np.broadcast_to(np.float32(ty), shape),
        oz: np.broadcast_to(tx * sin_b + tz * cos_b, shape),
    }


def choose_mode(params: AssembleParams, lines: ScanLines, intervals: StationaryIntervals,
                runs: I64) -> tuple[str, str]:
    """The association mode to use and why."""
    if params.mode != "auto":
        return params.mode, "requested"
    stationary = int(intervals.first_ns.size)
    served = int(np.unique(runs[runs >= 0]).size)
    inside = int(np.count_nonzero(runs >= 0))
    usable = max(1, int(np.count_nonzero(lines.usable)))
    # A continuous scan stands still only before and after its one long move; a step scan
    # stands still at many positions (and may stream profiles while it moves, too).
    many_positions = served >= 3 and served >= 0.5 * stationary
    step = many_positions or (served >= 1 and inside >= 0.5 * usable)
    return ("step" if step else "continuous",
            f"{served} of {stationary} stationary intervals hold a complete profile; "
            f"{inside} of {usable} profiles lie inside one")


def assemble_stage(inputs: Mapping[str, Any], params: AssembleParams,
             progress: ProgressFn) -> StageResult:
    """The assemble stage: ``profiles``, ``motor``, ``rig`` → ``points`` (a full grid)."""
    rig = rig_from_table(inputs["rig"])
    profiles: pa.Table = inputs["profiles"]
    motor: pa.Table = inputs["motor"]
    if profiles.num_rows == 0:
        raise StageError("profiles: no profiles in the input; nothing to assemble")
    progress("assemble", 0, 4)
    motor_clock_model = motor_clock(motor)
    lines = scan_lines(profiles, rig, params,
                       None if motor_clock_model is None else motor_clock_model.rate)
    intervals = stationary_intervals(motor)
    settle_s = rig.motor.settle_s if params.settle_s is None else params.settle_s
    runs, step_drops = associate_steps(lines, intervals,
                                       round(settle_s * lines.time_scale * 1e9))
    mode, why = choose_mode(params, lines, intervals, runs)
    progress("assemble", 1, 4)

    dropped = dict(lines.dropped)
    positions_without = 0
    if mode == "step":
        dropped.update(step_drops)
        rows = np.flatnonzero(runs >= 0)
        used_positions, profile_of_row = np.unique(runs[rows], return_inverse=True)
        positions_without = int(intervals.first_ns.size - used_positions.size)
    else:
        beyond = lines.usable & beyond_motor_log(lines.start_ns, lines.end_ns, motor)
        dropped["beyond_motor_log"] = int(np.count_nonzero(beyond))
        rows = np.flatnonzero(lines.usable & ~beyond)
        frames = lines.frame[rows]
        new_turn = np.concatenate([[True], frames[1:] != frames[:-1]])
        profile_of_row = np.cumsum(new_turn) - 1
    if rows.size == 0:
        raise StageError(f"profiles: none of the {profiles.num_rows} profiles could be placed "
                         f"(mode {mode}; dropped: {dropped})")
    profile_of_row = profile_of_row.astype(np.int64)
    first = _first_per_group(profile_of_row * (int(lines.sector.max()) + 1) + lines.sector[rows])
    average = mode == "step" and params.step_profile == "average"
    extra = 0 if average else int(np.count_nonzero(~first))
    if not average:
        rows, profile_of_row, first = rows[first], profile_of_row[first], first[first]
    layout = grid_layout(lines, rows, profile_of_row, first)
    ranges, measured = range_grid(lines, layout, average)
    progress("assemble", 2, 4)

    n_profiles, n_samples = ranges.shape
    alpha_deg: F64 = (layout.alpha0_deg + np.arange(n_samples, dtype=np.float64) * layout.step_deg
                      + rig.scanner.alpha_offset_deg)
    sample_index = np.arange(n_samples, dtype=np.float64)
    time_ns = layout.time0_ns[:, None] + np.rint(
        layout.sample_dt_ns[:, None] * sample_index[None, :]).astype(np.int64)
    if mode == "step":
        beta_deg = beta_deg_from_steps(intervals.step_count[used_positions], rig.motor)
        beta_column = np.repeat(beta_deg, n_samples)
    else:
        beta_deg = beta_deg_at(time_ns.ravel(), motor, rig.motor).reshape(ranges.shape)
        beta_column = beta_deg.ravel()
    coords = points_from_grid(ranges, alpha_deg, beta_deg, rig)
    progress("assemble", 3, 4)

    columns: dict[str, pa.Array] = {
        name: pa.array(coords[name].ravel()) for name in XYZ
    }
    columns["range_m"] = pa.array(ranges.ravel())
    columns["alpha_deg"] = pa.array(np.tile(alpha_deg, n_profiles))
    columns["beta_deg"] = pa.array(beta_column)
    columns["time_ns"] = pa.array(time_ns.ravel())
    columns["profile"] = pa.array(np.repeat(np.arange(n_profiles, dtype=np.int32), n_samples))
    columns["sample"] = pa.array(np.tile(np.arange(n_samples, dtype=np.int32), n_profiles))
    for name in ORIGIN:
        columns[name] = pa.array(np.ascontiguousarray(coords[name]).ravel())
    echo = echo_grid(lines, layout)
    if echo is not None:
        columns["echo"] = pa.array(echo.ravel())
    table = pa.table(columns)

    no_return = int(np.count_nonzero(measured & np.isnan(ranges)))
    report = {
        "mode": mode,
        "mode_reason": why,
        "time_source": lines.time_source,
        "clock_offset_ns": (lines.clock.offset_ns if lines.clock is not None
                            and lines.time_source == "device" else None),
        "clock": None if lines.clock is None else lines.clock.report(),
        "head_turn_s": lines.turn_s,
        "motor_clock": None if motor_clock_model is None else motor_clock_model.report(),
        "grid": {"profiles": n_profiles, "samples": n_samples},
        "profiles_in": profiles.num_rows,
        "profiles_used": int(rows.size),
        "profiles_dropped": {k: v for k, v in dropped.items() if v},
        "profiles_extra_at_position": extra,
        "positions_without_profile": positions_without,
        "points": table.num_rows,
        "no_return": no_return,
        "not_measured": int(np.count_nonzero(~measured)),
        "beta_deg_range": [float(np.min(beta_column)), float(np.max(beta_column))],
        "warnings": [*([] if lines.clock is None else lines.clock.problems()),
                     *([] if motor_clock_model is None else motor_clock_model.problems()),
                     *([f"{dropped['beyond_motor_log']} profiles lie beyond the motor log while "
                        "the platform was turning (the log ended early or began late: a lost "
                        "motor controller?); their platform angle is unknown, so they were "
                        "dropped"] if dropped.get("beyond_motor_log") else [])],
    }
    progress("assemble", 4, 4)
    # The filter's range gate defaults to the scanner's own limits, carried with the points.
    from scanpipe.stages.filter import SCANNER_RANGE_KEY

    table = table.replace_schema_metadata({
        **(table.schema.metadata or {}),
        SCANNER_RANGE_KEY: json.dumps([rig.scanner.min_range_m, rig.scanner.max_range_m]).encode(),
    })
    return StageResult(tables={"points": table}, report=report)


STAGE = Stage(
    name="assemble",
    version=5,
    params=AssembleParams,
    inputs=("profiles", "motor", "rig"),
    outputs=("points",),
    func=assemble_stage,
    description="profiles + motor states + rig calibration → points on the profile × sample grid",
)
