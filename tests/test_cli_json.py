"""``--json`` on every command (one JSON object on stdout), checked over the whole command tree
and on the commands that gained it: run, export, render's siblings, rig init/check."""

from __future__ import annotations

import json
from pathlib import Path

import typer.main
from result_tables import points_table, textured_quad

from scanpipe.artifacts import write_artifact
from scanpipe.cli.main import app
from scanpipe.rig import default_rig, rig_to_toml
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions


def _leaf_commands() -> dict[str, object]:
    found: dict[str, object] = {}

    def walk(command: object, prefix: str) -> None:
        for name, sub in sorted(getattr(command, "commands", {}).items()):
            if hasattr(sub, "commands"):
                walk(sub, f"{prefix}{name} ")
            else:
                found[prefix + name] = sub

    walk(typer.main.get_command(app), "")
    return found


def test_every_command_takes_json() -> None:
    commands = _leaf_commands()
    assert {"run", "export", "report", "info", "plan", "rig check", "eval", "recover",
            "record", "simulate"} <= set(commands)
    missing = [name for name, command in commands.items()
               if "--json" not in [o for p in command.params for o in p.opts]]  # type: ignore[attr-defined]
    assert missing == []


def test_rig_init_and_check_json(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "rig.toml"
    result = cli("rig", "init", path, "--json")
    assert result.code == 0 and json.loads(result.out) == {"wrote": str(path)}
    result = cli("rig", "check", path, "--json")
    info = json.loads(result.out)
    assert result.code == 0 and info["valid"] is True
    assert info["rig"]["scanner"]["dialect"] == default_rig().scanner.dialect
    text = rig_to_toml(default_rig())
    assert "beam_step_deg = 0.25" in text
    path.write_text(text.replace("beam_step_deg = 0.25", "beam_step_deg = -3"))
    bad = cli("rig", "check", path, "--json")
    assert bad.code == 2 and bad.out == "" and bad.err.startswith("scanpipe: error: ")


def test_export_json_lists_the_files(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    folder = tmp_path / "art"
    folder.mkdir()
    for name, table in {"points": points_table(), **textured_quad()}.items():
        write_artifact(folder / f"{name}.parquet", table, {"key": name})
    result = cli("export", folder, "-f", "mcap", "--out", tmp_path / "scan.mcap", "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["format"] == "mcap"
    assert report["files"] == [str(tmp_path / "scan.mcap"), str(tmp_path / "scan.layout.json")]
    assert all(report["bytes"][f] > 0 for f in report["files"])


def test_run_json_reports_every_stage(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    recording = tmp_path / "scan.mcap"
    simulate_direct(recording, tmp_path / "truth",
                    SimOptions(motor_step_deg=10.0, beam_step_deg=2.0, cameras=False))
    result = cli("run", recording, "--workdir", tmp_path / "work", "--to", "assemble", "-q",
                 "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert [s["stage"] for s in report["stages"]] == ["decode", "calibrate", "assemble"]
    assert report["ran"] == 3 and report["reused"] == 0
    assert Path(report["stages"][2]["outputs"]["points"]).is_file()
    again = json.loads(cli("run", recording, "--workdir", tmp_path / "work", "--to", "assemble",
                           "-q", "--json").out)
    assert again["reused"] == 3
