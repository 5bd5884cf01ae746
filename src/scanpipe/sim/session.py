"""The timeline of a simulated scan: what the host sends when, what the devices answer.

:func:`plan_session` runs the acquisition procedure (step-and-scan or continuous, docs of the
acquisition issue) against the motor controller's firmware (:class:`MotorController`) on the
platform model, in simulation time, without sockets. It yields the motor link's bytes in both
directions, the motor states the host would log, the start time of every scanner profile and
the capture times of the camera frames. Direct mode turns that into a recording.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from scanpipe.rig import Rig
from scanpipe.sim.controller import MotorController
from scanpipe.sim.motion import MotorTimeline, PlatformState
from scanpipe.sim.options import SimOptions
from scanpipe.sim.scanner import sector_duration_s

RX, TX = 0, 1


@dataclass(frozen=True)
class LinkBytes:
    """Bytes on a link at ``time_s`` (simulation seconds), ``direction`` 0 = RX, 1 = TX."""

    time_s: float
    direction: int
    data: bytes


@dataclass(frozen=True)
class HostMotorState:
    """A position report as the host logs it (at its receive time)."""

    time_s: float
    step_count: int
    target_step_count: int
    moving: bool
    device_time_us: int


@dataclass
class Session:
    """The planned session (all times in simulation seconds from its start)."""

    motor_link: list[LinkBytes] = field(default_factory=list)
    motor_states: list[HostMotorState] = field(default_factory=list)
    profile_start_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    end_s: float = 0.0
    timeline: MotorTimeline = field(default_factory=MotorTimeline)
    positions: int = 0


class _Host:
    """The host side of the motor link: sends lines, collects replies and reports in order."""

    def __init__(self, controller: MotorController, session: Session, latency_s: float) -> None:
        self.controller = controller
        self.session = session
        self.latency_s = latency_s

    def _receive(self, device_time_s: float, line: str) -> float:
        at = device_time_s + self.latency_s
        self.session.motor_link.append(LinkBytes(at, RX, (line + "\n").encode("ascii")))
        if line.startswith("POS "):
            _, count, target, moving, time_us = line.split()
            self.session.motor_states.append(HostMotorState(
                at, int(count), int(target), moving == "1", int(time_us)))
        return at

    def reports_until(self, time_s: float) -> float:
        """Deliver the reports due before ``time_s``; returns the last receive time."""
        last = -math.inf
        for report in self.controller.reports_until(time_s):
            last = self._receive(report.time_s, report.line)
        return last

    def send(self, line: str, time_s: float) -> float:
        """Send a command at ``time_s``; returns when its last reply line arrived."""
        arrive = time_s + self.latency_s
        self.reports_until(arrive)
        self.session.motor_link.append(LinkBytes(time_s, TX, (line + "\n").encode("ascii")))
        done = arrive
        for reply in self.controller.handle(line, arrive):
            done = self._receive(arrive, reply)
        return done

    def wait_until_stopped(self) -> float:
        """Deliver reports to the end of the move under way; returns the final one's time."""
        end = self.controller.next_report_s()
        last = end
        while math.isfinite(end):
            last = self.reports_until(end)
            end = self.controller.next_report_s()
        return last


def _first_profile_at_or_after(time_s: float, phase_s: float, period_s: float) -> int:
    return max(0, math.ceil((time_s - phase_s) / period_s - 1e-9))


def plan_session(options: SimOptions, true_rig: Rig) -> Session:
    """Plan the whole session (see the module docstring)."""
    scanner, motor = true_rig.scanner, true_rig.motor
    period = 1.0 / scanner.scan_hz
    sector = sector_duration_s(scanner)
    phase = float(np.random.default_rng([options.seed, 7]).uniform(0.0, period))
    latency = options.link_latency_s
    platform = PlatformState(motor.pulse_step_deg, motor.beta_offset_deg)
    controller = MotorController(motor, platform, options.report_interval_s)
    session = Session()
    host = _Host(controller, session, latency)
    step = options.motor_step_count()

    def received(k: int) -> float:  # the profile is sent when its sector is complete
        return phase + k * period + sector + latency

    t = host.send("POS?", 0.001)
    t = host.send("ZERO", t + 0.001)
    if options.mode == "step":
        positions = motor.pulse_limit // step + 1
        ready = t + motor.settle_s
        for index in range(positions):
            k = _first_profile_at_or_after(ready, phase, period)
            t = received(k) + 0.0005
            if index == positions - 1:
                break
            host.send(f"MOVE {step:+d}", t)
            stopped = host.wait_until_stopped()
            ready = stopped + motor.settle_s
        session.positions = positions
        end = t
    else:
        pulses = (motor.pulse_limit // step) * step
        rate_hz = step * scanner.scan_hz
        t = host.send(f"RATE {rate_hz:g}", t + 0.001)
        t = host.send(f"MOVE {pulses:+d}", t + 0.001)
        stopped = host.wait_until_stopped()
        k = _first_profile_at_or_after(stopped, phase, period)
        end = received(k) + 0.0005
        session.positions = 1
    host.reports_until(end)
    n_profiles = math.floor((end - latency - sector - phase) / period + 1e-9) + 1
    session.profile_start_s = phase + np.arange(max(n_profiles, 0)) * period
    session.end_s = end + 0.01
    session.timeline = platform.timeline()
    return session


def camera_times_s(fps: float, end_s: float, seed: int, camera_index: int) -> np.ndarray:
    """Capture times of one camera over the session (free-running at ``fps``)."""
    phase = float(np.random.default_rng([seed, 11, camera_index]).uniform(0.0, 1.0 / fps))
    count = math.floor((end_s - phase) * fps) + 1
    return phase + np.arange(max(count, 0)) / fps
