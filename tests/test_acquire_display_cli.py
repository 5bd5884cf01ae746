"""The live display's content, the summary text, and ``record``'s errors as one line."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

from rich.console import Console

from scanpipe.acquire.display import RecorderStatus, format_summary, status_table
from scanpipe.recording.reader import read_recording
from scanpipe.rig import default_rig, rig_to_toml


def test_display_shows_profiles_motor_frames_rate_and_time_left() -> None:
    status = RecorderStatus(
        mode="step", phase="scanning at 417", elapsed_s=75.0, profiles=321,
        positions_done=140, positions_total=1667, step_count=417, pulse_limit=5000,
        beta_deg=15.012, frames={"cam0": 90, "cam1": 88}, dropped_frames=2,
        data_rate_bps=1_250_000.0, total_bytes=48_000_000, time_left_s=3725.0, events=3,
        last_event="camera cam1: 2 frame(s) dropped (gap)")
    console = Console(file=io.StringIO(), width=120)
    console.print(status_table(status))
    text = console.file.getvalue()  # type: ignore[attr-defined]
    for expected in ("step — scanning at 417", "1:15", "1:02:05", "321", "140/1667",
                     "417/5000 pulses, β = 15.012°", "cam0 90, cam1 88 (2 dropped)",
                     "48.0 MB at 1.2 MB/s", "3 — last: camera cam1"):
        assert expected in text, expected


def test_summary_text() -> None:
    summary = {
        "files": ["scan.mcap"], "status": "scanner_disconnected", "reason": "link lost",
        "mode": "step", "dialect": "ldoem", "duration_s": 12.5, "profiles": 40, "positions": 20,
        "final_step_count": 2780, "pulse_limit": 5000, "final_beta_deg": 100.08,
        "motor_states": 300, "frames": {"cam0": 5}, "dropped_frames": {"cam0": 1},
        "stream_bytes": {"scanner RX": 2048}, "events": {"scanner_disconnected": 1},
    }
    text = format_summary(summary)
    assert "scanner_disconnected (link lost)" in text
    assert "40 (20 positions)" in text and "2780/5000 pulses" in text
    assert "cam0 5 (1 dropped)" in text and "scanner RX 2.0 kB" in text
    assert "scanner_disconnected ×1" in text


def test_record_with_an_unreachable_controller_fails_in_one_line(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    rig = default_rig()
    rig = rig.model_copy(update={
        "motor": rig.motor.model_copy(update={"serial_url": str(tmp_path / "no-such-tty")}),
        "cameras": ()})
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    out = tmp_path / "rec.mcap"
    result = cli("record", "--rig", rig_file, "--out", out, "--quiet")
    assert result.code == 1  # type: ignore[attr-defined]
    err = result.err  # type: ignore[attr-defined]
    assert err.count("\n") == 1 and err.startswith("scanpipe: error: recording failed")
    assert "no-such-tty" in err and "Traceback" not in err
    recording = read_recording(out)  # the file is finished and says what happened
    assert recording.complete
    assert [e.kind for e in recording.events] == ["device_error", "recording_end"]


def test_record_with_a_bad_rig_or_option_is_a_usage_error(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    result = cli("record", "--rig", tmp_path / "missing.toml", "--out", tmp_path / "r.mcap")
    assert result.code == 2 and "file not found" in result.err  # type: ignore[attr-defined]
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(default_rig()))
    result = cli("record", "--rig", rig_file, "--out", tmp_path / "r.mcap", "--mode", "spin")
    assert result.code == 2  # type: ignore[attr-defined]
    assert "mode" in result.err and "'step' or 'continuous'" in result.err  # type: ignore[attr-defined]
    assert not (tmp_path / "r.mcap").exists()
    (tmp_path / "r.mcap").write_bytes(b"precious")
    result = cli("record", "--rig", rig_file, "--out", tmp_path / "r.mcap")
    assert result.code == 2 and "--force" in result.err  # type: ignore[attr-defined]
    assert (tmp_path / "r.mcap").read_bytes() == b"precious"
