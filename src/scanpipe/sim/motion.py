"""The simulated motor: pulses on a trapezoidal rate profile, and the platform angle over time.

One formula for the duration of a move: :func:`scanpipe.planning.move_time_s`. The position
during a move follows the same trapezoid (linear ramp up at ``accel_hz_per_s`` to
``pulse_rate_hz``, cruise, linear ramp down). Times are simulation seconds (see
:mod:`scanpipe.sim.clock`).
"""

from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanpipe.planning import move_time_s

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Move:
    """One move of ``pulses`` (signed) starting at ``start_s`` from ``from_steps``.

    ``cut_s`` (when set) is the time a STOP ended it: the position holds from then on.
    """

    start_s: float
    from_steps: int
    pulses: int
    pulse_rate_hz: float
    accel_hz_per_s: float
    cut_s: float | None = None

    @property
    def duration_s(self) -> float:
        """The full move's duration (the planner's trapezoid)."""
        return move_time_s(abs(self.pulses), self.pulse_rate_hz, self.accel_hz_per_s)

    @property
    def end_s(self) -> float:
        """When the motor stops: the move's end, or the STOP that cut it."""
        full = self.start_s + self.duration_s
        return full if self.cut_s is None else min(full, self.cut_s)

    @property
    def target_steps(self) -> int:
        """The position the move was asked to reach."""
        return self.from_steps + self.pulses

    def pulses_done(self, elapsed_s: ArrayLike) -> F64:
        """Pulses sent (continuous, ≥ 0) ``elapsed_s`` after the start, on the trapezoid."""
        n = abs(self.pulses)
        total = self.duration_s
        a = self.accel_hz_per_s
        peak = min(self.pulse_rate_hz, math.sqrt(n * a))
        t_ramp = peak / a
        t = np.clip(np.asarray(elapsed_s, dtype=np.float64), 0.0, total)
        ramp_n = 0.5 * a * t_ramp * t_ramp
        up = 0.5 * a * t * t
        cruise = ramp_n + peak * (t - t_ramp)
        down = n - 0.5 * a * (total - t) ** 2
        done = np.clip(np.where(t < t_ramp, up, np.where(t <= total - t_ramp, cruise, down)), 0, n)
        if self.cut_s is not None:  # a STOP holds the last whole pulse sent
            cut = self.cut_s - self.start_s
            held = math.floor(float(replace(self, cut_s=None).pulses_done(cut)) + 1e-9)
            done = np.where(t >= cut, float(held), done)
        return np.asarray(done, dtype=np.float64)

    def steps_at(self, time_s: ArrayLike) -> F64:
        """Continuous position (steps) at ``time_s``."""
        sign = 1.0 if self.pulses >= 0 else -1.0
        return self.from_steps + sign * self.pulses_done(np.asarray(time_s) - self.start_s)

    def count_at(self, time_s: float) -> int:
        """The controller's integer pulse count at ``time_s`` (whole pulses sent)."""
        sign = 1 if self.pulses >= 0 else -1
        done = float(self.pulses_done(time_s - self.start_s))
        return self.from_steps + sign * math.floor(done + 1e-9)

    def stopped_at(self, time_s: float) -> Move:
        """This move cut by a STOP at ``time_s`` (it holds the last whole pulse sent)."""
        return replace(self, cut_s=time_s)


@dataclass(frozen=True)
class MotorTimeline:
    """All moves of a session, in time order, from a zeroed position."""

    moves: tuple[Move, ...] = ()
    zero_steps: int = 0  # the position before the first move

    def steps_at(self, time_s: ArrayLike) -> F64:
        """Continuous platform position in steps at each time (vectorised over times and
        moves: the same trapezoid as :meth:`Move.pulses_done`)."""
        t = np.asarray(time_s, dtype=np.float64)
        if not self.moves:
            return np.full(t.shape, float(self.zero_steps))
        m = self.moves
        start = np.array([x.start_s for x in m])
        which = np.searchsorted(start, t, side="right") - 1
        before = which < 0
        i = np.maximum(which, 0)
        n = np.array([abs(x.pulses) for x in m], dtype=np.float64)[i]
        sign = np.array([1.0 if x.pulses >= 0 else -1.0 for x in m])[i]
        a = np.array([x.accel_hz_per_s for x in m])[i]
        total = np.array([x.duration_s for x in m])[i]
        peak = np.minimum(np.array([x.pulse_rate_hz for x in m])[i], np.sqrt(n * a))
        cut = np.array([np.inf if x.cut_s is None else x.cut_s - x.start_s for x in m])[i]
        held = np.array([float(x.pulses_done(np.inf)) if x.cut_s is not None else 0.0
                         for x in m])[i]
        from_steps = np.array([x.from_steps for x in m], dtype=np.float64)[i]
        elapsed = np.clip(t - start[i], 0.0, total)
        t_ramp = np.divide(peak, a)
        up = 0.5 * a * elapsed**2
        cruise = 0.5 * a * t_ramp**2 + peak * (elapsed - t_ramp)
        down = n - 0.5 * a * (total - elapsed) ** 2
        done = np.clip(np.where(elapsed < t_ramp, up,
                                np.where(elapsed <= total - t_ramp, cruise, down)), 0.0, n)
        done = np.where(t - start[i] >= cut, held, done)
        steps = from_steps + sign * done
        return np.where(before, float(self.zero_steps), steps)

    def move_at(self, time_s: float) -> Move | None:
        """The last move started at or before ``time_s`` (None before the first)."""
        index = bisect.bisect_right(self.moves, time_s, key=lambda m: m.start_s)
        return self.moves[index - 1] if index > 0 else None

    def count_at(self, time_s: float) -> int:
        """The controller's integer count at ``time_s``."""
        move = self.move_at(time_s)
        return self.zero_steps if move is None else move.count_at(time_s)

    def moving_at(self, time_s: float) -> bool:
        """Whether the motor is turning at ``time_s``."""
        move = self.move_at(time_s)
        return move is not None and time_s < move.end_s


class PlatformState:
    """The one platform all emulators share: thread-safe moves and the angle at any time.

    Positions are physical steps from where the platform started (the truth); the controller's
    count is that minus the position at its last ZERO.
    """

    def __init__(self, pulse_step_deg: float, beta_offset_deg: float = 0.0) -> None:
        self.pulse_step_deg = pulse_step_deg
        self.beta_offset_deg = beta_offset_deg
        self._lock = threading.Lock()
        self._moves: list[Move] = []
        self._count_zero = 0

    def timeline(self) -> MotorTimeline:
        """A snapshot of every move so far (physical steps)."""
        with self._lock:
            return MotorTimeline(tuple(self._moves))

    def beta_deg_at(self, time_s: ArrayLike) -> F64:
        """The true platform angle at each time."""
        steps = self.timeline().steps_at(time_s)
        return np.asarray(steps * self.pulse_step_deg + self.beta_offset_deg, dtype=np.float64)

    def count_at(self, time_s: float) -> int:
        """The controller's pulse count at ``time_s``."""
        return self.timeline().count_at(time_s) - self._count_zero

    def moving_at(self, time_s: float) -> bool:
        """Whether the motor turns at ``time_s``."""
        return self.timeline().moving_at(time_s)

    def start_move(self, time_s: float, pulses: int, pulse_rate_hz: float,
                   accel_hz_per_s: float) -> Move:
        """Start a move at ``time_s`` from the position then (callers check the limits)."""
        with self._lock:
            start = MotorTimeline(tuple(self._moves)).count_at(time_s)
            move = Move(time_s, start, pulses, pulse_rate_hz, accel_hz_per_s)
            self._moves.append(move)
            return move

    def stop(self, time_s: float) -> int:
        """Stop any move under way at ``time_s``; returns the count it holds."""
        with self._lock:
            if self._moves and time_s < self._moves[-1].end_s:
                self._moves[-1] = self._moves[-1].stopped_at(time_s)
            return MotorTimeline(tuple(self._moves)).count_at(time_s) - self._count_zero

    def zero(self, time_s: float) -> None:
        """Make the position at ``time_s`` the controller's zero."""
        with self._lock:
            self._count_zero = MotorTimeline(tuple(self._moves)).count_at(time_s)
