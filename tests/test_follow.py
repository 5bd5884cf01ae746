"""``scanpipe run --follow``: the tail reader, the stream decoded as it grows, the follower's
result equal to the batch run (a live simulation followed from another process, a file
growing in pieces), a recording that stops growing, and bad input as one line."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from table_equality import table_differences, workdir_differences

from scanpipe.acquire.display import RecorderStatus, status_lines
from scanpipe.follow import FOLLOW_FOLDER, MODEL_FILE, StreamFollower, follow_chain
from scanpipe.pipeline import run_chain
from scanpipe.recording.reader import RecordingTail, read_recording
from scanpipe.recording.schemas import RX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import default_rig, rig_to_toml
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.stages.decode import DecodeParams, decode_recording

SCANPIPE = [sys.executable, "-m", "scanpipe.cli.main"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    path = root / "scan.mcap"
    simulate_direct(path, root / "truth", SimOptions(
        beam_step_deg=2.0, motor_step_deg=3.0, camera_scale=0.05, camera_fps=0.5, seed=7))
    return path


def _grow(source: bytes, target: Path, pieces: int, pause_s: float, seed: int = 1,
          stop_at: int | None = None) -> None:
    """Append ``source`` to ``target`` in ``pieces`` random pieces (up to ``stop_at``)."""
    end = len(source) if stop_at is None else stop_at
    cuts = [*sorted(random.Random(seed).sample(range(1, end), pieces - 1)), end]
    done = 0
    with target.open("ab") as out:
        for cut in cuts:
            out.write(source[done:cut])
            out.flush()
            done = cut
            time.sleep(pause_s)


def test_tail_of_a_file_growing_in_pieces_reads_as_the_batch_reader(
        recording: Path, tmp_path: Path) -> None:
    source = recording.read_bytes()
    grown = tmp_path / "grown.mcap"
    grown.write_bytes(b"")
    batch = read_recording(recording)
    stream = StreamFollower(DecodeParams())
    rng = random.Random(3)
    with grown.open("ab") as out, grown.open("rb") as handle:
        tail = RecordingTail(grown, handle)
        done = 0
        while done < len(source):
            step = rng.randint(1, len(source) // 40)
            out.write(source[done:done + step])
            out.flush()
            done += step
            tail.poll()
            stream.add(tail.new_stream_parts("scanner", RX))
            assert tail.stuck is None
        assert tail.complete
        whole = tail.recording()
    for name in ("metadata", "message_counts", "warnings", "complete", "bytes_read",
                 "chunks_read", "loss"):
        assert getattr(whole, name) == getattr(batch, name), name
    assert whole.stream("scanner").data == batch.stream("scanner").data
    assert np.array_equal(whole.motor.step_count, batch.motor.step_count)
    decoded = stream.finish(whole.stream("scanner", RX).data)
    assert decoded is not None, stream.why
    follow = decode_recording(whole, DecodeParams(), decoded=decoded).tables
    expected = decode_recording(batch, DecodeParams()).tables
    for name, table in expected.items():
        assert table_differences(follow[name], table) == [], name


def test_follow_a_file_growing_in_pieces_equals_the_batch_run(
        recording: Path, tmp_path: Path, cli: Callable[..., Any]) -> None:
    rec = tmp_path / "scan.mcap"
    rec.write_bytes(b"")
    writer = threading.Thread(target=_grow, args=(recording.read_bytes(), rec, 30, 0.03))
    writer.start()
    result = follow_chain(rec, tmp_path / "follow", {}, to="mesh", timeout_s=5, poll_s=0.02)
    writer.join()
    assert result.complete and result.decode == "incremental", result.decode
    assert [r.stage for r in result.records] == ["decode", "calibrate", "assemble", "filter",
                                                "mesh"]
    run_chain(rec, tmp_path / "batch", {}, to="mesh")
    differences = workdir_differences(tmp_path / "follow", tmp_path / "batch")
    assert len(differences) == 10 and all(not d for d in differences.values()), differences
    again = cli("run", rec, "--workdir", tmp_path / "follow", "--to", "mesh")
    assert again.code == 0 and " ran in " not in again.err  # same keys: all reused


def test_follow_a_writers_temporary_file_renamed_over_an_older_recording(
        recording: Path, tmp_path: Path) -> None:
    rec = tmp_path / "scan.mcap"
    rec.write_bytes(b"an older recording of the same name")
    temporary = tmp_path / ".scan.mcap.x1y2.tmp"  # how simulate writes (artifacts.atomic_path)
    temporary.write_bytes(b"")

    def write_then_rename() -> None:
        _grow(recording.read_bytes(), temporary, 20, 0.03)
        os.replace(temporary, rec)

    writer = threading.Thread(target=write_then_rename)
    writer.start()
    result = follow_chain(rec, tmp_path / "follow", {}, to="assemble", timeout_s=5,
                          poll_s=0.02)
    writer.join()
    assert result.complete and result.decode == "incremental" and result.warnings == []
    run_chain(rec, tmp_path / "batch", {}, to="assemble")
    differences = workdir_differences(tmp_path / "follow", tmp_path / "batch")
    assert differences and all(not d for d in differences.values()), differences


def test_a_followed_file_deleted_by_its_writer_is_an_error(
        recording: Path, tmp_path: Path, cli: Callable[..., Any]) -> None:
    rec = tmp_path / "scan.mcap"
    temporary = tmp_path / ".scan.mcap.x1y2.tmp"
    temporary.write_bytes(recording.read_bytes()[:5000])

    def abandon() -> None:
        time.sleep(0.5)
        temporary.unlink()

    writer = threading.Thread(target=abandon)
    writer.start()
    result = cli("run", rec, "-w", tmp_path / "w", "--follow", "--follow-timeout", "1",
                 "--quiet")
    writer.join()
    _one_line_error(result, 1, str(temporary), "deleted by its writer", "abandoned")
    assert not (tmp_path / "w" / "decode").exists()


@pytest.mark.slow
def test_a_live_simulation_followed_from_another_process_equals_the_batch_run(
        tmp_path: Path, cli: Callable[..., Any]) -> None:
    rig = default_rig()
    rig = rig.model_copy(update={"motor": rig.motor.model_copy(update={"pulse_limit": 1000})})
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    rec = tmp_path / "live.mcap"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    # The follower first, and the scan only once it says it follows: started together, the
    # two processes' start-up raced, and on a loaded host the scan could end before the
    # follower looked (no live preview to check). What the follower then sees of the scan
    # no longer depends on which process the host started first.
    follow = subprocess.Popen(
        [*SCANPIPE, "run", str(rec), "--workdir", str(tmp_path / "follow"), "--to", "mesh",
         "--follow", "--follow-timeout", "60", "--json"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert follow.stderr is not None
        first_line = follow.stderr.readline()
        assert "(following the recording)" in first_line, first_line
        simulate = subprocess.Popen(
            [*SCANPIPE, "simulate", "--out", str(rec), "--truth", str(tmp_path / "truth"),
             "--rig", str(rig_file), "--scene", "box", "--beam-step", "2", "--motor-step", "2",
             "--camera-scale", "0.04", "--camera-fps", "2", "--speedup", "10", "--quiet"],
            env=env, stderr=subprocess.PIPE, text=True)
        assert simulate.wait(timeout=60) == 0, simulate.stderr.read()  # type: ignore[union-attr]
        stdout, stderr = follow.communicate(timeout=120)
    finally:
        if follow.poll() is None:
            follow.kill()
    assert follow.returncode == 0, stderr
    report = json.loads(stdout)["follow"]
    assert report["complete"] and report["decode"] == "incremental", report
    assert report["scan_end_seen_ns"] is not None  # the recorder's scan_end event was read
    # The mesh at the scan's end is the final one, or the JSON says which input changed after it
    # (the way back's motor states can move the clock fits on a loaded host).
    changed = report["changed_after_scan_end"]
    assert "mesh" in report["reused_from_scan_end"] or changed.get("mesh"), report
    # a change is in the content: never the runner's provenance stamp (then nothing was reused)
    assert not any(c == ["schema"] for stage in changed.values() for c in stage.values()), changed
    assert report["model_latency_s"] is not None and report["model_latency_s"] > 0
    assert report["preview"]["positions"] > 0 and report["preview"]["problem"] is None
    assert report["visible_lag_s"]["count"] > 0
    assert (tmp_path / "follow" / FOLLOW_FOLDER / MODEL_FILE).stat().st_size > 0
    batch = cli("run", rec, "--workdir", tmp_path / "batch", "--to", "mesh")
    assert batch.code == 0, batch.err
    differences = workdir_differences(tmp_path / "follow", tmp_path / "batch")
    assert len(differences) == 10 and all(not d for d in differences.values()), differences


def test_a_recording_that_stops_growing_is_processed_after_the_timeout(
        recording: Path, tmp_path: Path, cli: Callable[..., Any]) -> None:
    source = recording.read_bytes()
    rec = tmp_path / "killed.mcap"
    rec.write_bytes(source[: len(source) * 3 // 4])  # a recorder killed three quarters in
    started = time.monotonic()
    result = cli("run", rec, "--workdir", tmp_path / "w", "--to", "decode", "--follow",
                 "--follow-timeout", "1", "--json")
    assert result.code == 0, result.err
    assert time.monotonic() - started < 30
    assert ("warning: follow: " + f"{rec}: stopped growing 1 s ago without an end record"
            in result.err)
    report = json.loads(result.out)
    assert not report["follow"]["complete"] and report["follow"]["decode"].startswith("batch")
    assert report["stages"][0]["report"]["recording"]["complete"] is False
    assert rec.read_bytes() == source[: len(source) * 3 // 4]  # the input is untouched


def _one_line_error(result: Any, code: int, *parts: str) -> None:
    assert result.code == code, (result.code, result.err)
    assert result.err.count("\n") == 1 and result.err.startswith("scanpipe: error: ")
    assert "Traceback" not in result.err
    for part in parts:
        assert part in result.err, (part, result.err)


def test_follow_bad_input_is_one_line(tmp_path: Path, cli: Callable[..., Any]) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    _one_line_error(cli("run", text, "-w", tmp_path / "w1", "--follow", "--quiet"), 1,
                    str(text), "not an MCAP file")
    assert text.read_text() == "not a recording\n" and not (tmp_path / "w1" / "decode").exists()

    missing = tmp_path / "later.mcap"
    _one_line_error(cli("run", missing, "-w", tmp_path / "w2", "--follow", "--quiet",
                        "--follow-timeout", "0.3"), 1,
                    str(missing), "no recording appeared within 0.3 s", "--follow-timeout")

    folder = tmp_path / "folder.mcap"
    folder.mkdir()
    _one_line_error(cli("run", folder, "-w", tmp_path / "w3", "--follow", "--quiet"), 1,
                    str(folder), "is a directory")

    part = tmp_path / "split.mcap"
    with RecordingWriter(part, default_rig(), {"part": 0}) as writer:
        writer.write_event(1, "test", "a part of a split recording")
    _one_line_error(cli("run", part, "-w", tmp_path / "w4", "--follow", "--quiet"), 2,
                    "part 0 of a split recording", "--split-size-mb")

    result = cli("run", part, "-w", tmp_path / "w5", "--follow", "--follow-timeout", "0")
    assert result.code == 2 and "Traceback" not in result.err


def test_the_recorder_display_shows_the_coverage_so_far() -> None:
    status = RecorderStatus(
        mode="step", phase="scanning", elapsed_s=10.0, profiles=90, positions_done=40,
        positions_total=160, step_count=1250, pulse_limit=5000, beta_deg=27.0,
        start_count=0, samples_per_profile=1440)
    rows = dict(status_lines(status))
    assert rows["coverage"] == "25% of the planned range, 57,600 points so far"
    before = RecorderStatus(mode="continuous", phase="connecting", elapsed_s=1.0, profiles=0,
                            positions_done=0, positions_total=None, step_count=0,
                            pulse_limit=5000, beta_deg=0.0)
    assert dict(status_lines(before))["coverage"] == "?, 0 points so far"


def test_tables_identical_compares_bits_and_metadata() -> None:
    import pyarrow as pa

    from scanpipe.follow import tables_identical

    nan = np.array([1.0, np.nan, 3.0], np.float32)
    table = pa.table({"x": nan, "n": pa.array([1, None, 3])})
    assert tables_identical(table, pa.table({"x": nan.copy(), "n": pa.array([1, None, 3])}))
    assert not tables_identical(table, pa.table({"x": nan, "n": pa.array([1, 2, 3])}))
    other_nan = nan.copy()
    other_nan.view(np.uint32)[1] = 0x7FC00001  # another NaN: not the same bits
    assert not tables_identical(table, pa.table({"x": other_nan, "n": pa.array([1, None, 3])}))
    assert not tables_identical(table, table.replace_schema_metadata({b"k": b"v"}))


def test_the_runners_provenance_is_no_change_after_the_scan_end() -> None:
    """A stage is taken from the scan's end when its inputs' content is the same: the
    provenance the runner stamps into a table handed on (made when, from which files) is not
    content, other schema metadata (a scanner's range, a CRS) is."""
    import pyarrow as pa

    from scanpipe.artifacts import PROVENANCE_KEY
    from scanpipe.follow import _changed_columns

    table = pa.table({"x": np.arange(3.0)})
    at_scan_end = table.replace_schema_metadata({PROVENANCE_KEY: b'{"created_ns": 1}'})
    final = table.replace_schema_metadata({PROVENANCE_KEY: b'{"created_ns": 2}',
                                           b"scanpipe.scanner_range_m": b"[0.5, 10]"})
    assert _changed_columns(final.replace_schema_metadata({PROVENANCE_KEY: b"{}"}),
                            at_scan_end) == []
    assert _changed_columns(table, at_scan_end) == []
    assert _changed_columns(final, at_scan_end) == ["schema"]
    assert _changed_columns(pa.table({"x": np.arange(3.0) + 1}), at_scan_end) == ["x"]
