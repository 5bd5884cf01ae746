"""The rig description: defaults, TOML round trip, validation that reports every problem."""

from __future__ import annotations

from pathlib import Path

import pytest

from scanpipe.errors import RigError
from scanpipe.rig import default_rig, load_rig, rig_to_toml


def test_default_rig_is_the_papers() -> None:
    rig = default_rig()
    assert rig.motor.pulse_step_deg == pytest.approx(0.036)
    assert rig.motor.pulse_limit == 5000
    assert rig.scanner.beam_step_deg == 0.25
    assert rig.scanner.samples_per_profile == 1440
    assert [c.id for c in rig.cameras] == ["cam0", "cam1", "cam360"]
    assert [c.model for c in rig.cameras] == ["pinhole", "pinhole", "equirect"]


def test_toml_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text(rig_to_toml(default_rig()))
    assert load_rig(path) == default_rig()


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def test_every_problem_reported_at_once(tmp_path: Path) -> None:
    path = _write(tmp_path, "[scanner]\nbeam_step_deg = 0.3\nscan_hz = 8.5\nbogus = 1\n"
                            "[motor]\ngear_ratio = -1\npulse_limt = 3\n")
    with pytest.raises(RigError) as info:
        load_rig(path)
    problems = info.value.problems
    assert len(problems) == 5
    text = str(info.value)
    assert str(path) in text
    assert "unknown key 'scanner.bogus'" in text
    assert "motor.gear_ratio = -1" in text
    assert "did you mean pulse_limit" in text
    assert "scan_hz = 8.5" in text and "5–20 Hz" in text
    assert "beam_step_deg = 0.3" in text and "0.125" in text


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[scanner]\ndialect = 'lms'\n", "scanner.dialect"),
        ("[scanner]\nport = 70000\n", "scanner.port = 70000"),
        ("[scanner]\nstart_angle_deg = 90\nend_angle_deg = 45\n", "end_angle_deg (45.0)"),
        ("[[cameras]]\nid = 'a'\n[[cameras]]\nid = 'a'\n", "repeated: a"),
        ("[[cameras]]\nid = 'bad id'\n", "cameras.0.id"),
        ("format_version = 2\n", "format_version = 2"),
        ("[motor]\npulse_limit = 'many'\n", "motor.pulse_limit"),
        ("[scanner\n", "not valid TOML"),
    ],
)
def test_bad_files(tmp_path: Path, text: str, needle: str) -> None:
    with pytest.raises(RigError) as info:
        load_rig(_write(tmp_path, text))
    assert needle in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="file not found"):
        load_rig(tmp_path / "nope.toml")


def test_paper_dialect_skips_ldoem_limits(tmp_path: Path) -> None:
    rig = load_rig(_write(tmp_path, "[scanner]\ndialect = 'paper'\nbeam_step_deg = 0.3\n"))
    assert rig.scanner.beam_step_deg == 0.3


def test_cli_rig_init_and_check(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "rig.toml"
    assert cli("rig", "init", path).code == 0
    checked = cli("rig", "check", path)
    assert checked.code == 0 and "ok" in checked.out
    original = path.read_text()
    again = cli("rig", "init", path)
    assert again.code == 2 and "already exists" in again.err
    assert path.read_text() == original  # nothing valid overwritten


def test_cli_rig_check_bad_file_exit_code(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    path = _write(tmp_path, "[motor]\nfull_step_deg = 0\n")
    result = cli("rig", "check", path)
    assert result.code == 2
    assert f"{path}: motor.full_step_deg = 0" in result.err
    assert "Traceback" not in result.err
