"""One name per idea: the motor step and the beam step, their old spellings kept as hidden,
deprecated aliases, the simulator's options derived from its model, the old rig key."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from acquire_helpers import sim_options

from scanpipe.errors import RigError
from scanpipe.planning import DEFAULT_MOTOR_STEP_DEG
from scanpipe.recording.reader import read_recording
from scanpipe.rig import default_rig, load_rig, rig_from_toml, rig_to_toml
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.options import SimOptions


def _deprecation(old: str, new: str) -> str:
    return f"scanpipe: warning: {old} is deprecated; use {new}\n"


def test_plan_angle_is_a_hidden_alias_of_motor_step(cli: Callable[..., Any]) -> None:
    new = cli("plan", "--motor-step", "6", "--json")
    old = cli("plan", "--angle", "6", "--json")
    assert new.code == old.code == 0
    assert json.loads(old.out) == json.loads(new.out)
    assert json.loads(new.out)["requested_motor_step_deg"] == 6.0
    assert new.err == "" and old.err == _deprecation("--angle", "--motor-step")
    help_text = cli("plan", "--help").out
    assert "--motor-step" in help_text and "--angle" not in help_text


def test_plan_default_motor_step_is_the_one_default(cli: Callable[..., Any]) -> None:
    result = cli("plan", "--json")
    assert result.code == 0, result.err
    assert json.loads(result.out)["requested_motor_step_deg"] == DEFAULT_MOTOR_STEP_DEG
    assert SimOptions().motor_step_deg == DEFAULT_MOTOR_STEP_DEG


@pytest.mark.parametrize("args", [
    ("plan", "--angle", "6", "--motor-step", "6"),
    ("record", "--out", "x.mcap", "--step-angle", "5", "--motor-step", "5"),
    ("simulate", "--direct", "--out", "x.mcap", "--truth", "t", "--scanner-step", "2",
     "--beam-step", "2"),
])
def test_old_and_new_spelling_together_are_refused(cli: Callable[..., Any], tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   args: tuple[str, ...]) -> None:
    monkeypatch.chdir(tmp_path)
    result = cli(*args)
    assert result.code == 2
    assert result.err.count("\n") == 1 and result.err.startswith("scanpipe: error: ")
    assert "is the old name of" in result.err and "give only" in result.err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_record_step_angle_still_records(cli: Callable[..., Any], tmp_path: Path) -> None:
    with VirtualRig(sim_options(pulse_limit=300), speedup=20.0) as rig:
        rig_file = tmp_path / "rig.toml"
        rig_file.write_text(rig_to_toml(rig.client_rig()))
        out = tmp_path / "scan.mcap"
        result = cli("record", "--rig", rig_file, "--out", out, "--step-angle", "5",
                     "--no-cameras", "--quiet", "--speedup", "20", "--json")
    assert result.code == 0, result.err
    assert result.err == _deprecation("--step-angle", "--motor-step")
    session = read_recording(out).session
    assert json.loads(session["step_count"]) == 139  # 5° / 0.036° per pulse
    assert json.loads(session["motor_step_deg"]) == pytest.approx(139 * 0.036)


def test_record_step_angle_value_is_validated_as_the_motor_step(cli: Callable[..., Any],
                                                                tmp_path: Path) -> None:
    result = cli("record", "--out", tmp_path / "x.mcap", "--step-angle", "0", "--quiet")
    assert result.code == 2
    assert result.err.splitlines()[0] == _deprecation("--step-angle", "--motor-step").strip()
    assert "motor_step_deg" in result.err.splitlines()[1]
    assert list(tmp_path.iterdir()) == []


def test_simulate_scanner_step_is_a_hidden_alias_of_beam_step(cli: Callable[..., Any],
                                                              tmp_path: Path) -> None:
    out = tmp_path / "s.mcap"
    result = cli("simulate", "--direct", "--motor-step", "10", "--scanner-step", "2",
                 "--no-cameras", "--out", out, "--truth", tmp_path / "t", "-q")
    assert result.code == 0, result.err
    assert result.err == _deprecation("--scanner-step", "--beam-step")
    assert read_recording(out).rig().scanner.beam_step_deg == 2.0


def test_simulate_help_lists_the_options_of_its_model(cli: Callable[..., Any]) -> None:
    result = cli("simulate", "--help")
    assert result.code == 0
    text = " ".join(result.out.split())
    for field in ("scene", "mode", "motor_step_deg", "beam_step_deg", "camera_scale",
                  "camera_fps", "seed"):
        info = SimOptions.model_fields[field]
        flag = "--" + field.removesuffix("_deg").replace("_", "-")
        assert flag in text
        assert info.description and " ".join(info.description.split()) in text
        if info.default is not None:
            assert f"[default: {info.default}]" in text
    assert "--cameras / --no-cameras" in text and "--scanner-step" not in text
    assert "[default: 10.0]" in text  # --noise-mm: the model's 0.01 m in millimetres


def test_rig_with_the_old_beam_step_key_loads(tmp_path: Path) -> None:
    path = tmp_path / "old.toml"
    path.write_text("[scanner]\ndialect = 'paper'\nangular_step_deg = 0.3\n")
    rig = load_rig(path)
    assert rig.scanner.beam_step_deg == 0.3
    assert "beam_step_deg = 0.3" in rig_to_toml(rig) and "angular_step_deg" not in rig_to_toml(rig)
    # The rig TOML stored in a recording written before the rename reads too.
    old_text = rig_to_toml(default_rig()).replace("beam_step_deg", "angular_step_deg")
    assert rig_from_toml(old_text, "recording") == default_rig()


def test_old_key_is_checked_against_the_device_limits(tmp_path: Path) -> None:
    path = tmp_path / "old.toml"
    path.write_text("[scanner]\nangular_step_deg = 0.3\n[motor]\ngear_ratio = -1\n")
    with pytest.raises(RigError) as info:
        load_rig(path)
    text = str(info.value)
    assert "motor.gear_ratio = -1" in text and "beam_step_deg = 0.3" in text and "0.125" in text


def test_rig_with_both_beam_step_keys_is_refused_in_one_line(cli: Callable[..., Any],
                                                            tmp_path: Path) -> None:
    path = tmp_path / "both.toml"
    text = "[scanner]\nbeam_step_deg = 0.25\nangular_step_deg = 0.25\n"
    path.write_text(text)
    result = cli("rig", "check", path)
    assert result.code == 2
    assert result.err.count("\n") == 1 and "Traceback" not in result.err
    assert str(path) in result.err
    assert "angular_step_deg is the old name of beam_step_deg: give only beam_step_deg" \
        in result.err
    assert path.read_text() == text  # nothing rewritten
