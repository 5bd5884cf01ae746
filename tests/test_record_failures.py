"""What goes wrong on a real rig: the scanner drops the link, a move past the pulse limit,
the LD-OEM refusing settings. Every case ends in a finished file with the incident in /events."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from acquire_helpers import record_against, sim_options

from scanpipe.acquire.motor_client import MotorClient
from scanpipe.acquire.recorder import Recorder, RecordOptions
from scanpipe.errors import DeviceError
from scanpipe.recording.reader import read_recording
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.room import box_room
from scanpipe.sim.scene import Scene
from scanpipe.stages.decode import DecodeParams, decode_recording

SPEEDUP = 10.0


@pytest.fixture(scope="module")
def scene() -> Scene:
    return box_room()


def _record_and_disturb(rig: VirtualRig, out: Path, after_profiles: int,
                        disturb: Callable[[], None]) -> dict[str, object]:
    """Record in a thread; once ``after_profiles`` profiles arrived, call ``disturb``."""
    recorder = _recorder(rig, out)
    summary: dict[str, object] = {}
    thread = threading.Thread(target=lambda: summary.update(recorder.run()), daemon=True)
    thread.start()
    deadline = time.monotonic() + 10.0
    while recorder.scanner is None or recorder.scanner.stats.profiles < after_profiles:
        assert time.monotonic() < deadline, "the recorder never got going"
        time.sleep(0.01)
    disturb()
    thread.join(timeout=20)
    assert not thread.is_alive()
    return summary


def _recorder(rig: VirtualRig, out: Path, **options: object) -> Recorder:
    settings = {"mode": "step", "motor_step_deg": 5.0, "speedup": rig.clock.speedup,
                "install_signal_handlers": False, "cameras": False, "reconnect_delay_s": 0.05,
                **options}
    return Recorder(rig.client_rig(), out, RecordOptions(**settings))  # type: ignore[arg-type]


def test_scanner_gone_mid_scan_stops_motor_and_closes_file(tmp_path: Path, scene: Scene) -> None:
    out = tmp_path / "rec.mcap"
    with VirtualRig(sim_options("ldoem", pulse_limit=5000), speedup=SPEEDUP, scene=scene) as rig:
        # The scanner goes away for good: connection and server.
        summary = _record_and_disturb(rig, out, 8, rig.scanner.stop)
        commands = list(rig.motor.commands)
        moving = rig.platform.moving_at(rig.clock.now_s())
    assert summary["status"] == "scanner_disconnected"
    assert "STOP" in commands and not moving
    assert summary["final_step_count"] == 0 and summary["returned_to_start"] is True
    assert "motor_returned" in summary["events"]
    recording = read_recording(out)
    assert recording.complete and not recording.warnings
    kinds = [e.kind for e in recording.events]
    assert "scanner_disconnected" in kinds
    assert kinds.count("scanner_reconnect_failed") == 2
    assert kinds[-1] == "recording_end"
    assert recording.events[-1].data["status"] == "scanner_disconnected"
    # The partial scan still decodes.
    profiles = decode_recording(recording, DecodeParams()).tables["profiles"]
    assert profiles.num_rows == summary["profiles"] >= 8


def test_scanner_reconnects_and_the_scan_completes(tmp_path: Path, scene: Scene) -> None:
    out = tmp_path / "rec.mcap"
    with VirtualRig(sim_options("paper", pulse_limit=1000), speedup=SPEEDUP, scene=scene) as rig:
        # A glitch: the scanner is back at once.
        summary = _record_and_disturb(rig, out, 6, rig.scanner.drop_connections)
    assert summary["status"] == "complete", summary
    assert summary["positions"] == 1000 // 139 + 1
    kinds = [e.kind for e in read_recording(out).events]
    assert kinds.count("scanner_disconnected") == 1 and kinds.count("scanner_reconnected") == 1
    assert summary["events"]["scanner_reconnected"] == 1


def test_a_smaller_controller_limit_is_obeyed_and_named(tmp_path: Path, scene: Scene) -> None:
    out = tmp_path / "rec.mcap"
    with VirtualRig(sim_options("ldoem", pulse_limit=400), speedup=SPEEDUP, scene=scene) as rig:
        # The rig file claims a larger limit than the controller has: the smaller one applies.
        client_rig = rig.client_rig()
        wrong = client_rig.model_copy(update={
            "motor": client_rig.motor.model_copy(update={"pulse_limit": 5000})})
        summary = record_against(rig, out, rig=wrong)
        moves = rig.platform.timeline().moves
        commands = list(rig.motor.commands)
    assert summary["status"] == "complete", summary
    assert (summary["pulse_limit"], summary["limit_source"]) == (400, "controller")
    assert summary["positions"] == 400 // 139 + 1
    assert max(m.target_steps for m in moves) == 2 * 139 <= 400  # never past the controller's
    assert not any(c.startswith("MOVE") and "ERR" in c for c in commands)
    recording = read_recording(out)
    assert recording.complete
    assert not [e for e in recording.events if e.kind == "motor_error"]  # nothing was refused
    limit = next(e for e in recording.events if e.kind == "motor_limit")
    assert limit.data == {"pulse_limit": 400, "source": "controller", "rig": 5000,
                          "controller": 400}
    assert "travel limit 400 pulses from home (the controller's own limit)" in limit.message
    mismatch = next(e for e in recording.events if e.kind == "motor_limit_mismatch")
    assert mismatch.data == {"controller": 400, "rig": 5000}
    assert "the smaller one applies" in mismatch.message


def test_client_never_sends_a_move_past_the_limit(tmp_path: Path, scene: Scene) -> None:
    with VirtualRig(sim_options("paper", pulse_limit=1000), speedup=SPEEDUP, scene=scene) as rig:
        sent: list[bytes] = []

        class Sink:
            def write_stream(self, link: str, data: bytes, direction: int, t: int) -> None:
                if direction == 1:
                    sent.append(data)

            def write_motor_state(self, *args: object) -> None:
                pass

        client = MotorClient(rig.client_rig().motor, Sink())  # type: ignore[arg-type]
        client.connect()
        try:
            client.zero()
            with pytest.raises(DeviceError, match="outside 0…1000"):
                client.move(1001)
            assert b"MOVE" not in b"".join(sent)
            # Sent raw, the controller refuses it too, and nothing moves.
            reply = client.command("MOVE +1001")
            assert not reply.ok and reply.text.startswith("LIMIT")
            assert client.query_position().step_count == 0
        finally:
            client.close()


def test_ldoem_limits_are_checked_before_connecting(tmp_path: Path, scene: Scene) -> None:
    with VirtualRig(sim_options("ldoem"), speedup=SPEEDUP, scene=scene) as rig:
        client_rig = rig.client_rig()
        bad = client_rig.model_copy(update={
            "scanner": client_rig.scanner.model_copy(update={"scan_hz": 25.0})})
        summary = record_against(rig, tmp_path / "rec.mcap", rig=bad)
        requests = list(rig.scanner.requests)
    assert summary["status"] == "failed"
    assert "scan_hz = 25 is outside the LD-OEM limit" in str(summary["reason"])
    assert requests == []  # nothing was sent to the scanner
