"""The public Python API of ``scanpipe`` (docs/api.md): light to import, lazily resolved,
documented, and working on a real recording."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import scanpipe
from scanpipe.errors import MissingDependencyError, ParameterError
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions


def test_import_scanpipe_is_light() -> None:
    code = ("import sys, scanpipe; print(sorted(m for m in ('numpy', 'pyarrow', 'open3d', "
            "'mcap', 'foxglove', 'serial') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_public_names_resolve_and_are_documented() -> None:
    from scanpipe.recording.reader import read_recording
    from scanpipe.stages import registry

    assert scanpipe.read_recording is read_recording
    assert scanpipe.registry is registry
    for name in scanpipe.__all__:
        value = getattr(scanpipe, name)
        assert name == "__version__" or (value.__doc__ or "").strip(), name
        assert name in dir(scanpipe)
    assert list(scanpipe.registry())[:1] == ["decode"]
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        _ = scanpipe.nothing_here  # type: ignore[attr-defined]
    api_doc = (Path(__file__).resolve().parents[1] / "docs" / "api.md").read_text()
    for name in scanpipe.__all__:
        if name != "__version__":
            assert f"scanpipe.{name}" in api_doc, name


def test_run_and_read_recording_on_a_simulated_scan(tmp_path: Path) -> None:
    recording = tmp_path / "scan.mcap"
    simulate_direct(recording, tmp_path / "truth",
                    SimOptions(motor_step_deg=10.0, beam_step_deg=2.0, cameras=False))
    read = scanpipe.read_recording(recording)
    assert read.complete and read.rig().scanner.beam_step_deg == 2.0
    records = scanpipe.run(recording, tmp_path / "work", {"assemble": {}}, to="assemble")
    assert [r.stage for r in records] == ["decode", "calibrate", "assemble"]
    assert records[-1].outputs["points"].is_file()
    again = scanpipe.run(recording, tmp_path / "work", to="assemble")
    assert all(r.reused for r in again)
    with pytest.raises(ParameterError, match="unknown stage 'mesher'"):
        scanpipe.run(recording, tmp_path / "work", {"mesher": {}})


def test_missing_optional_package_gives_the_install_hint(monkeypatch: pytest.MonkeyPatch,
                                                         cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from scanpipe.extras import require

    monkeypatch.setitem(sys.modules, "foxglove", None)  # as if foxglove-sdk were not installed
    with pytest.raises(MissingDependencyError,
                       match=r"needs the optional package 'foxglove-sdk'.*"
                             r"pip install 'scanpipe\[live\]'"):
        require("foxglove", "the live view (--live)")
    out = tmp_path / "sim.mcap"
    result = cli("simulate", "--live", "0", "--out", out, "--truth", tmp_path / "truth",
                 "--scene", "box")
    assert result.code == 1
    assert result.err.startswith("scanpipe: error: the live view (--live) needs the optional "
                                 "package 'foxglove-sdk'")
    assert "pip install 'scanpipe[live]'" in result.err and result.err.count("\n") == 1
    assert not out.exists()
    monkeypatch.setitem(sys.modules, "serial", None)
    with pytest.raises(MissingDependencyError, match=r"pip install 'scanpipe\[acquire\]'"):
        require("serial", "the motor link")


def test_bare_scanpipe_prints_its_help(cli) -> None:  # type: ignore[no-untyped-def]
    result = cli()
    assert result.code == 2  # as typer itself: help, exit code 2
    assert result.out.startswith("Usage: scanpipe [OPTIONS] COMMAND [ARGS]...")
    assert "Commands" in result.out and "recover" in result.out
    assert result.err == ""
    group = cli("rig")
    assert group.code == 2 and group.out.startswith("Usage: scanpipe rig") and group.err == ""
