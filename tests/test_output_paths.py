"""The output-path policy of every writing command: paths used as given, no device, no silent
overwrite, never an input. Each refusal is exit 2, one line, and the existing bytes unchanged."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from result_tables import points_table, textured_quad

from scanpipe.artifacts import write_artifact
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import default_rig, rig_to_toml

Cli = Callable[..., Any]


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def refused(result: Any, message: str, code: int = 2) -> None:
    """Exit ``code``, one ``scanpipe: error:`` line holding ``message``, no traceback."""
    assert result.code == code, result.err
    assert result.err.startswith("scanpipe: error: ") and result.err.count("\n") == 1, result.err
    assert message in result.err, result.err
    assert "Traceback" not in result.err


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """A workdir as ``scanpipe run`` lays it out: its decode artifacts name the recording."""
    recording = tmp_path / "scan.mcap"
    with RecordingWriter(recording, default_rig(), {"mode": "step"}) as writer:
        writer.write_stream("scanner", b"\x00" * 10, 0, 1_000)
    work = tmp_path / "work"
    write_artifact(work / "decode" / "profiles.parquet", points_table(), {
        "stage": "decode", "input_paths": {"recording": str(recording)}})
    write_artifact(work / "assemble" / "points.parquet", points_table(seed=1), {
        "stage": "assemble", "input_paths": {"profiles": str(work / "decode/profiles.parquet")}})
    quad = textured_quad()
    for name in ("mesh_vertices", "mesh_faces"):
        write_artifact(work / "mesh" / f"{name}.parquet", quad[name], {"stage": "mesh"})
    return work


def test_export_never_replaces_the_workdirs_recording(cli: Cli, workdir: Path) -> None:
    recording = workdir.parent / "scan.mcap"
    before = digest(recording)
    for extra in ((), ("--force",)):
        result = cli("export", workdir, "--format", "mcap", "--out", recording, *extra)
        refused(result, "is also an input of this command")
    # Through another spelling of the same file (a symlink) too.
    link = workdir.parent / "link.mcap"
    link.symlink_to(recording)
    refused(cli("export", workdir, "-f", "mcap", "-o", link, "--force"), "is also an input")
    refused(cli("export", workdir, "-f", "ply", "-o", workdir / "assemble" / "points.parquet"),
            "the extension .parquet does not match --format ply")
    assert digest(recording) == before


def test_export_appends_no_suffix_and_refuses_devices(cli: Cli, workdir: Path,
                                                     tmp_path: Path) -> None:
    refused(cli("export", workdir, "-f", "ply", "-o", "/dev/null"), "is a device")
    assert not Path("/dev/null.ply").exists()
    (tmp_path / "model").write_bytes(b"a file without a suffix")
    refused(cli("export", workdir, "-f", "ply", "-o", tmp_path / "model", "--force"),
            "is a file without a suffix; give a file name ending in .ply, or a folder")
    assert (tmp_path / "model").read_bytes() == b"a file without a suffix"
    assert not list(tmp_path.glob("model.*"))
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    refused(cli("export", workdir, "-f", "ply", "-o", fifo, "--force"), "is a pipe (FIFO)")
    result = cli("export", workdir, "-f", "ply", "-o", tmp_path / "new")
    assert result.code == 0, result.err  # a path without a suffix is a folder
    assert (tmp_path / "new" / "scan.ply").is_file()


def test_export_overwrites_only_with_force(cli: Cli, workdir: Path, tmp_path: Path) -> None:
    target = tmp_path / "room.ply"
    target.write_bytes(b"an earlier export")
    refused(cli("export", workdir, "-f", "ply", "-o", target), "already exists; pass --force")
    assert target.read_bytes() == b"an earlier export"
    assert cli("export", workdir, "-f", "ply", "-o", target, "--force").code == 0
    assert target.read_bytes().startswith(b"ply")
    assert not list(tmp_path.glob(".room.ply.*"))  # no temporary left


def test_render_and_report_paths(cli: Cli, workdir: Path, tmp_path: Path) -> None:
    png = tmp_path / "view.png"
    png.write_bytes(b"old image")
    refused(cli("render", workdir, "-o", png, "--views", "plan", "--width", "32"),
            "already exists; pass --force")
    assert png.read_bytes() == b"old image"
    refused(cli("render", workdir, "-o", tmp_path / "view.jpg", "--width", "32"),
            "expected a file name ending in .png")
    assert not (tmp_path / "view.jpg").exists()
    result = cli("render", workdir, "-o", png, "--views", "plan", "--width", "32", "--force")
    assert result.code == 0, result.err
    assert png.read_bytes().startswith(b"\x89PNG")
    html = tmp_path / "report.html"
    html.write_bytes(b"old report")
    refused(cli("report", workdir, "-o", html), "already exists; pass --force")
    refused(cli("report", workdir, "-o", tmp_path / "report.txt"), "ending in .html or .htm")
    refused(cli("report", workdir, "-o", "/dev/null", "--force"), "is a device")
    assert html.read_bytes() == b"old report"


def test_import_points_overwrites_only_with_force(cli: Cli, tmp_path: Path) -> None:
    cloud = tmp_path / "cloud.xyz"
    np.savetxt(cloud, np.eye(3))
    out = tmp_path / "out"
    assert cli("import-points", cloud, "--out", out, "-q").code == 0
    before = digest(out / "points.parquet")
    refused(cli("import-points", cloud, "--out", out, "-q"), "already exists; pass --force")
    assert digest(out / "points.parquet") == before
    assert cli("import-points", cloud, "--out", out, "-q", "--force").code == 0
    refused(cli("import-points", cloud, "--out", cloud, "-q"), "is a file; give a folder")
    assert cloud.read_text().startswith("1.0")


def test_simulate_keeps_an_existing_recording(cli: Cli, tmp_path: Path) -> None:
    out, truth = tmp_path / "s.mcap", tmp_path / "t"
    out.write_bytes(b"a precious recording")
    args = ("simulate", "--direct", "--motor-step", "10", "--beam-step", "2", "--no-cameras",
            "--truth", truth, "-q")
    refused(cli(*args, "--out", out), "already exists; pass --force")
    refused(cli(*args, "--out", tmp_path / "s.bag"), "expected a file name ending in .mcap")
    refused(cli(*args, "--out", "/dev/null", "--force"), "is a device")
    assert out.read_bytes() == b"a precious recording" and not truth.exists()
    assert cli(*args, "--out", out, "--force").code == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"
    assert not list(tmp_path.glob(".s.mcap.*"))
    recorded = out.read_bytes()
    # The truth files are outputs too: a second run needs --force for them.
    refused(cli(*args, "--out", tmp_path / "other.mcap"), "already exists; pass --force")
    assert out.read_bytes() == recorded and not (tmp_path / "other.mcap").exists()


@pytest.mark.parametrize(("option", "value", "message"), [
    ("--speedup", "0", "speedup = 0.0"),
    ("--speedup", "-3", "speedup"),
    ("--speedup", "nan", "speedup"),
    ("--speedup", "inf", "speedup"),
    ("--speedup", "1e9", "speedup"),
    ("--motor-step", "0", "motor_step_deg"),
    ("--motor-step", "nan", "motor_step_deg"),
    ("--beam-step", "-1", "beam_step_deg"),
    ("--noise-mm", "inf", "noise_sigma_m"),
    ("--camera-scale", "0", "camera_scale"),
    ("--camera-fps", "nan", "camera_fps"),
    ("--seed", "-1", "seed"),
])
def test_simulate_bad_numbers_exit_2(cli: Cli, tmp_path: Path, option: str, value: str,
                                     message: str) -> None:
    for direct in ((), ("--direct",)):
        result = cli("simulate", *direct, "--out", tmp_path / "s.mcap", "--truth",
                     tmp_path / "t", "-q", option, value)
        refused(result, message)
    assert not (tmp_path / "s.mcap").exists() and not (tmp_path / "t").exists()


def test_rig_init_record_calibrate_and_import_video_paths(cli: Cli, tmp_path: Path) -> None:
    refused(cli("rig", "init", "/dev/null", "--force"), "is a device")
    refused(cli("rig", "init", tmp_path / "rig.yaml"), "expected a file name ending in .toml")
    refused(cli("rig", "init", tmp_path), "is a folder")
    rig = tmp_path / "rig.toml"
    rig.write_text(rig_to_toml(default_rig()))
    before = digest(rig)
    refused(cli("record", "--out", rig, "--force", "--rig", rig),
            "expected a file name ending in .mcap")
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"an earlier scan")
    refused(cli("record", "--out", existing), "already exists; pass --force")
    refused(cli("record", "--out", "/dev/null", "--force"), "is a device")
    assert existing.read_bytes() == b"an earlier scan"
    refused(cli("calibrate-camera", tmp_path / "a.png", "--rig", tmp_path), "is a folder")
    refused(cli("calibrate-camera", rig, "--rig", rig), "is also an input")
    refused(cli("import-video", existing, "--into", "/dev/null", "--start-time", "0"),
            "is a device")
    refused(cli("import-video", existing, "--into", existing, "--start-time", "0"),
            "is also an input")
    assert digest(rig) == before and existing.read_bytes() == b"an earlier scan"
