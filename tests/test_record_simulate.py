"""``scanpipe simulate`` without ``--direct``: emulators + the recorder + the truth folder."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from scanpipe.recording.reader import read_recording
from scanpipe.rig import default_rig, rig_to_toml
from scanpipe.sim.truth import load_truth
from scanpipe.stages.decode import DecodeParams, decode_recording


@pytest.mark.slow
def test_simulate_through_the_emulators(tmp_path: Path, cli: Callable[..., object]) -> None:
    rig = default_rig()
    rig = rig.model_copy(update={"motor": rig.motor.model_copy(update={"pulse_limit": 1000})})
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    out, truth_dir = tmp_path / "sim.mcap", tmp_path / "truth"
    result = cli("simulate", "--out", out, "--truth", truth_dir, "--rig", rig_file,
                 "--scene", "box", "--beam-step", "2", "--motor-step", "5",
                 "--camera-scale", "0.04", "--camera-fps", "2", "--speedup", "20", "--json")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    summary = json.loads(result.out)  # type: ignore[attr-defined]
    assert summary["status"] == "complete" and summary["positions"] == 1000 // 139 + 1
    truth = load_truth(truth_dir)
    recording = read_recording(out)
    assert recording.complete
    assert recording.rig().scanner.beam_step_deg == 2.0  # the nominal rig is recorded
    profiles = decode_recording(recording, DecodeParams()).tables["profiles"]
    assert profiles.num_rows == truth.profiles.num_rows == summary["profiles"]
    # Each profile is received after the truth says its sector ended. (How long after depends
    # on the load: on 2 cores the camera renders can delay the emulator by a few 100 ms.)
    recv = profiles.column("recv_time_ns").to_numpy()
    end = truth.profiles.column("time_end_ns").to_numpy()
    assert np.all(recv >= end) and np.all(recv - end < 2e9)
    measured = np.stack(profiles.column("ranges_m").to_numpy(zero_copy_only=False))
    true = truth.ranges_true_m()
    both = np.isfinite(measured) & np.isfinite(true)
    assert np.abs(measured[both] - true[both]).max() < 0.05 + 1 / 256
    assert set(summary["frames"]) == {"cam0", "cam1", "cam360"}
    assert truth.meta["speedup"] == 20.0
