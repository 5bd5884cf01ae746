"""Scan after scan the platform stays within its travel: each record starts at home, turns at
most to the limit the host obeys, and comes back (also when stopped); a platform left away from
home is refused, or brought home first with ``home_first``. Real pty and TCP emulators."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from acquire_helpers import record_against, sim_options

from scanpipe.acquire.motor_client import MotorClient
from scanpipe.acquire.recorder import Recorder, RecordOptions
from scanpipe.motion import beta_deg_at
from scanpipe.pipeline import get_stage
from scanpipe.recording.reader import read_recording
from scanpipe.rig import rig_to_toml
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.room import box_room
from scanpipe.sim.scene import Scene

SPEEDUP = 25.0
LIMIT = 1000
STEP = 333  # 12° in 0.036° pulses: 4 positions, a quick scan
ANGLE = 12.0


class _NoSink:
    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        pass

    def write_motor_state(self, *args: Any) -> None:
        pass


@pytest.fixture(scope="module")
def scene() -> Scene:
    return box_room()


def _max_absolute(rig: VirtualRig) -> int:
    """The truth: the farthest the platform ever was from its power-on position."""
    moves = rig.platform.timeline().moves
    return max([0, *(max(m.from_steps, m.target_steps) for m in moves)])


def _absolute(rig: VirtualRig) -> int:
    return rig.motor.controller.absolute_at(rig.clock.now_s())


def test_consecutive_records_stay_within_the_limit(tmp_path: Path, scene: Scene) -> None:
    # The issue: every record re-zeroed and nothing went home (340° after two, 880° later).
    with VirtualRig(sim_options("paper", pulse_limit=LIMIT), speedup=SPEEDUP, scene=scene) as rig:
        for index, mode in enumerate(["step", "continuous", "step"]):
            out = tmp_path / f"scan{index}.mcap"
            summary = record_against(rig, out, mode=mode, motor_step_deg=ANGLE)
            assert summary["status"] == "complete", summary
            assert summary["returned_to_start"] is True
            assert _absolute(rig) == 0 == summary["absolute_step_count"]  # home after each
            assert _max_absolute(rig) == 3 * STEP <= LIMIT
            # The recording still reads as a scan from its start: counts 0 … end while the
            # scanner streams, and the way home only after the last profile.
            tables = get_stage("decode").run({"recording": out}).tables
            motor, profiles = tables["motor"], tables["profiles"]
            steps = motor.column("step_count").to_numpy()
            log_ns = motor.column("log_time_ns").to_numpy()
            assert steps[0] == 0 and steps.max() == 3 * STEP and steps[-1] == 0
            at_end = int(np.argmax(steps == 3 * STEP))
            back = log_ns[at_end + int(np.argmax(steps[at_end:] < 3 * STEP))]  # homing starts
            recv_ns = profiles.column("recv_time_ns").to_numpy()
            assert profiles.num_rows > 0 and recv_ns.max() < back
            beta = beta_deg_at(recv_ns, motor, rig.nominal.motor)
            assert beta.min() >= 0.0 and beta.max() <= 3 * STEP * 0.036 + 1e-9


def test_away_from_home_the_next_scan_is_refused(tmp_path: Path, scene: Scene) -> None:
    with VirtualRig(sim_options("paper", pulse_limit=LIMIT), speedup=SPEEDUP, scene=scene) as rig:
        first = record_against(rig, tmp_path / "a.mcap", motor_step_deg=ANGLE,
                               return_to_start=False)
        assert first["status"] == "complete" and _absolute(rig) == 3 * STEP
        moves_before = len(rig.platform.timeline().moves)
        refused = record_against(rig, tmp_path / "b.mcap", motor_step_deg=ANGLE)
        assert len(rig.platform.timeline().moves) == moves_before  # nothing moved
        assert refused["status"] == "failed"
        reason = str(refused["reason"])
        assert reason.startswith(f"motor: the platform stands {3 * STEP} pulses (35.964°) from "
                                 "home") and "--home-first" in reason and "\n" not in reason
        assert not any(c.startswith("ZERO") for c in rig.motor.commands[-6:])  # no blind re-zero
        # Asked to, the recorder brings it home first, scans from there and comes back.
        homed = record_against(rig, tmp_path / "c.mcap", motor_step_deg=ANGLE, home_first=True)
        assert homed["status"] == "complete", homed
        assert _absolute(rig) == 0 and _max_absolute(rig) == 3 * STEP
    kinds = [e.kind for e in read_recording(tmp_path / "c.mcap").events]
    assert kinds.index("motor_homed") < kinds.index("motor_zeroed")


def test_a_stopped_scan_still_returns_home(tmp_path: Path, scene: Scene,
                                           cli: Callable[..., Any]) -> None:
    with VirtualRig(sim_options("paper", pulse_limit=LIMIT), speedup=SPEEDUP, scene=scene) as rig:
        options = RecordOptions(mode="step", motor_step_deg=5.0, speedup=SPEEDUP, cameras=False,
                                install_signal_handlers=False)
        recorder = Recorder(rig.client_rig(), tmp_path / "rec.mcap", options)
        summary: dict[str, object] = {}
        thread = threading.Thread(target=lambda: summary.update(recorder.run()), daemon=True)
        thread.start()
        deadline = time.monotonic() + 10.0
        while recorder.positions_done < 3:
            assert time.monotonic() < deadline, "the recorder never got going"
            time.sleep(0.01)
        recorder.request_stop("stopped by the test")  # what SIGINT does
        thread.join(timeout=20)
        assert not thread.is_alive()
        assert summary["status"] == "interrupted"
        events = " | ".join(f"{e.kind}: {e.message}"
                            for e in read_recording(tmp_path / "rec.mcap").events)
        assert summary["returned_to_start"] is True and _absolute(rig) == 0, events
        assert "STOP" in rig.motor.commands
        # The next scan is accepted (it stands at home).
        again = record_against(rig, tmp_path / "again.mcap", motor_step_deg=ANGLE)
        assert again["status"] == "complete" and _max_absolute(rig) <= LIMIT
    # The workstation is told that the model will be partial (it was made without a word).
    cut = cli("run", tmp_path / "rec.mcap", "--workdir", tmp_path / "w", "--to", "decode")
    assert cut.code == 0, cut.err
    assert "the scan ended interrupted (stopped by the test) before its sweep was done" in cut.err
    whole = get_stage("decode").run({"recording": tmp_path / "again.mcap"}).report["warnings"]
    assert not any("before its sweep was done" in w for w in whole)


def test_an_unlimited_rig_and_controller_may_turn_past_a_turn(tmp_path: Path,
                                                              scene: Scene) -> None:
    # A slip ring (the later 360° issue): the sweep is pulse_limit from wherever it stands.
    options = sim_options("paper", pulse_limit=12_000)
    motor = options.rig.motor.model_copy(update={"unlimited_travel": True})
    options = options.model_copy(update={"rig": options.rig.model_copy(update={"motor": motor})})
    with VirtualRig(options, speedup=200.0, scene=scene) as rig:
        assert rig.motor.controller.pulse_limit is None
        summary = record_against(rig, tmp_path / "rec.mcap", mode="continuous",
                                 motor_step_deg=108.0, cameras=False)
        assert summary["status"] == "complete", summary
        assert (summary["limit_source"], summary["pulse_limit"]) == ("none", 12_000)
        assert _max_absolute(rig) == 12_000 and _absolute(rig) == 0  # 432°, then back


def test_a_second_sigint_stops_the_way_back(tmp_path: Path, scene: Scene) -> None:
    # Ctrl-C once: stop and go back; Ctrl-C again while it goes back: STOP where it is.
    # Speed-up 2: the way back takes ~1 s of host time, a window a loaded machine cannot miss.
    # A signal that still arrived after the recorder had finished would interrupt whatever
    # test this worker runs next: the test's own handler catches it, and the presser never
    # signals once the recorder is done.
    done = threading.Event()
    late: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda *_: late.append(1))
    try:
        with VirtualRig(sim_options("paper", pulse_limit=5000), speedup=2.0, scene=scene) as rig:
            options = RecordOptions(mode="step", motor_step_deg=36.0, speedup=2.0,
                                    cameras=False, install_signal_handlers=True)
            recorder = Recorder(rig.client_rig(), tmp_path / "rec.mcap", options)

            def press_ctrl_c_twice() -> None:
                deadline = time.monotonic() + 60.0
                while recorder.positions_done < 3 and time.monotonic() < deadline:
                    time.sleep(0.002)
                if done.is_set():
                    return
                os.kill(os.getpid(), signal.SIGINT)
                while (recorder.phase != "returning to the start" and not done.is_set()
                       and time.monotonic() < deadline):
                    time.sleep(0.001)
                away = _absolute(rig)
                # Wait until the way back has begun for real (the ramp's first pulses).
                while (_absolute(rig) > away - 20 and not done.is_set()
                       and time.monotonic() < deadline):
                    time.sleep(0.001)
                if not done.is_set():
                    os.kill(os.getpid(), signal.SIGINT)

            presser = threading.Thread(target=press_ctrl_c_twice, daemon=True)
            presser.start()
            summary = recorder.run()  # in the main thread: the signal handlers are installed
            done.set()
            presser.join(timeout=70)
            absolute = _absolute(rig)
            moving = rig.platform.moving_at(rig.clock.now_s())
            commands = list(rig.motor.commands)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert not presser.is_alive() and late == []
    assert summary["status"] == "interrupted" and summary["returned_to_start"] is False
    assert commands[-1] == "STOP" and commands[-2].startswith("MOVE -")
    way_back = -int(commands[-2].split()[1])
    assert not moving and 0 < absolute < way_back  # stopped on the way back
    failed = [e for e in read_recording(tmp_path / "rec.mcap").events
              if e.kind == "motor_return_failed"]
    assert failed and "stopped by a second signal" in failed[0].message


def test_cli_refuses_away_from_home_in_one_line_and_home_first_fixes_it(
        tmp_path: Path, scene: Scene, cli: Callable[..., Any]) -> None:
    with VirtualRig(sim_options("paper", pulse_limit=LIMIT), speedup=SPEEDUP, scene=scene) as rig:
        rig_file = tmp_path / "rig.toml"
        rig_file.write_text(rig_to_toml(rig.client_rig()))
        # Someone turned the platform and left it there (another program, a lost link).
        client = MotorClient(rig.client_rig().motor, _NoSink())
        client.connect()
        try:
            client.move(500)
            assert client.wait_for_state(lambda s: s.step_count == 500 and not s.moving, 5.0)
        finally:
            client.close()
        out = tmp_path / "scan.mcap"
        args = ("record", "--rig", rig_file, "--out", out, "--motor-step", str(ANGLE),
                "--no-cameras", "--quiet", "--speedup", str(SPEEDUP))
        refused = cli(*args)
        assert refused.code == 1
        assert refused.err.count("\n") == 1 and "Traceback" not in refused.err
        assert refused.err.startswith("scanpipe: error: recording failed: motor: the platform "
                                      "stands 500 pulses (18.000°) from home")
        assert "--home-first" in refused.err and _absolute(rig) == 500  # nothing moved
        done = cli(*args, "--force", "--home-first")
        assert done.code == 0, done.err
        assert _absolute(rig) == 0 and _max_absolute(rig) == 3 * STEP
