"""``record`` end to end over real TCP and a real pty against the emulators: both dialects,
both modes; the recording decodes to what the emulators sent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from acquire_helpers import record_against, sim_options

from scanpipe.recording.reader import read_recording
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.room import box_room
from scanpipe.sim.scene import Scene
from scanpipe.stages.decode import DecodeParams, decode_recording

SPEEDUP = 10.0  # at 20 the settle is 2.5 ms of host time: a loaded CI machine missed it
STEP = 139  # 5° in 0.036° pulses
LIMIT = 1000


@pytest.fixture(scope="module")
def scene() -> Scene:
    return box_room()


@pytest.mark.parametrize("mode", ["step", "continuous"])
@pytest.mark.parametrize("dialect", ["ldoem", "paper"])
def test_record_end_to_end(tmp_path: Path, scene: Scene, dialect: str, mode: str) -> None:
    cameras = dialect == "ldoem"  # cameras in two of the four runs keep the suite fast
    options = sim_options(dialect, mode, cameras=cameras, pulse_limit=LIMIT)
    out = tmp_path / "rec.mcap"
    with_echo = (dialect, mode) == ("ldoem", "continuous")
    with VirtualRig(options, speedup=SPEEDUP, scene=scene) as rig:
        summary = record_against(rig, out, with_echo=with_echo)
        sent = list(rig.scanner.sent)
        commands = list(rig.motor.commands)
        requests = list(rig.scanner.requests)
        final_absolute = rig.motor.controller.absolute_at(rig.clock.now_s())
    assert summary["status"] == "complete", summary
    targets = list(range(0, LIMIT + 1, STEP))
    # The platform went home at the end: the next scan starts where this one did.
    assert final_absolute == 0 == summary["final_step_count"] == summary["absolute_step_count"]
    assert summary["returned_to_start"] is True
    assert (summary["pulse_limit"], summary["limit_source"]) == (LIMIT, "rig and controller")
    assert commands[:2] == ["ID?", "TRAVEL?"] and "ZERO" in commands
    assert commands.index("ZERO") < min(i for i, c in enumerate(commands) if c.startswith("MOVE"))
    assert commands[-3:] == ["RATE 1000", f"MOVE -{targets[-1]}", "TRAVEL?"]
    if mode == "step":
        assert commands[commands.index("ZERO") + 4] == "RATE 1000"
        assert commands.count(f"MOVE +{STEP}") == len(targets) - 1
        assert summary["positions"] == len(targets)
    else:
        assert f"RATE {STEP * 5}" in commands and f"MOVE +{targets[-1]}" in commands
    if dialect == "ldoem":  # start-up, stream, CANCEL on stop
        assert requests == ["0101", "0102", "0205", "0201", "0403", "0301", "0302"]

    recording = read_recording(out)
    assert recording.complete and not recording.warnings
    assert recording.rig().scanner.dialect == dialect
    assert recording.session["mode"] == mode
    result = decode_recording(recording, DecodeParams())
    profiles = result.tables["profiles"]
    assert result.report["dialect"] == dialect
    assert (profiles.column("echo").null_count == 0) == with_echo
    assert profiles.num_rows == summary["profiles"]
    # Every profile the emulator sent arrived (paper: one may be cut off by the close).
    assert len(sent) - (1 if dialect == "paper" else 0) <= profiles.num_rows <= len(sent)
    measured = np.stack(profiles.column("ranges_m").to_numpy(zero_copy_only=False))
    truth = np.stack([s.ranges_true_m for s in sent[:profiles.num_rows]])
    both = np.isfinite(measured) & np.isfinite(truth)
    assert both.mean() > 0.95
    error = np.abs(measured[both] - truth[both])
    assert error.max() < 5 * 0.010 + 1 / 256  # 5 σ of the noise plus one quantum
    assert np.std(measured[both] - truth[both]) == pytest.approx(0.010, rel=0.25)

    motor = recording.motor
    assert motor.step_count.max() == targets[-1] <= LIMIT and motor.step_count[-1] == 0
    if mode == "step":  # the platform rested at every target
        resting = set(motor.step_count[~motor.moving].tolist())
        assert set(targets) <= resting
        # … and at every target at least one whole profile was taken at rest (from the truth:
        # the platform angle at its first and last sample is the target's).
        still = {round(s.beta_first_deg / 0.036) for s in sent[:profiles.num_rows]
                 if abs(s.beta_first_deg - s.beta_last_deg) < 1e-9}
        assert set(targets) <= still
    if cameras:
        assert set(summary["frames"]) == {"cam0", "cam1", "cam360"}
        assert all(n >= 2 for n in summary["frames"].values())
        assert len(recording.images) == sum(summary["frames"].values())
    kinds = [e.kind for e in recording.events]
    assert kinds[:4] == ["motor_connected", "motor_limit", "motor_zeroed", "scanner_connected"]
    assert kinds[-2:] == ["motor_returned", "recording_end"]
