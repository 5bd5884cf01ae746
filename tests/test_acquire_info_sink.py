"""``scanpipe info`` on whole and cut recordings; the recorder's sink splits files."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from acquire_helpers import rig_with_cameras, small_camera

from scanpipe.acquire.sink import RecordingSink, part_path
from scanpipe.pipeline import get_stage
from scanpipe.protocol import paper
from scanpipe.protocol.profile import Profile
from scanpipe.recording.reader import read_recording
from scanpipe.recording.writer import RecordingWriter

T0 = 1_767_225_600_000_000_000


def _paper_stream(n: int) -> bytes:
    return b"".join(paper.encode_profile(Profile(k, 0, 0.0, 2.0, np.full(180, 1.5, np.float32)))
                    for k in range(n))


def _write(path: Path) -> None:
    rig = rig_with_cameras(small_camera("cam0"))
    stream = _paper_stream(10)
    with RecordingWriter(path, rig, {"mode": "step"}) as writer:
        for i in range(0, len(stream), 700):  # chunks that split frames anywhere
            writer.write_stream("scanner", stream[i:i + 700], 0, T0 + i * 100_000)
        for i in range(5):
            writer.write_motor_state(T0 + i * 10**9, 3 * i, 3 * i, False, i)
        # A 3 s pause in the motor reports: one gap.
        writer.write_motor_state(T0 + 7 * 10**9, 15, 15, False, 7)
        writer.write_image("cam0", T0 + 1, b"\xff\xd8jpeg", "0")
        writer.write_event(T0 + 2, "camera_frames_dropped", "2 dropped",
                           {"camera_id": "cam0", "count": 2})


def test_info_json(tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = tmp_path / "rec.mcap"
    _write(rec)
    result = cli("info", rec, "--json")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    info = json.loads(result.out)  # type: ignore[attr-defined]
    assert info["complete"] is True
    assert info["profiles"]["count"] == 10 and info["profiles"]["dialect"] == "paper"
    motor = info["channels"]["/motor/state"]
    assert motor["messages"] == 6 and motor["gaps"] == 1 and motor["max_gap_s"] == 3.0
    assert motor["duration_s"] == 7.0
    assert info["cameras"]["cam0"]["frames"] == 1 and info["cameras"]["cam0"]["dropped"] == 2
    assert info["channels"]["/camera/cam0/image"]["messages"] == 1
    assert info["channels"]["/scanner/stream"]["messages"] == info["channels"][
        "/scanner/stream"]["rx_bytes"] // 700 + 1
    assert info["event_counts"] == {"camera_frames_dropped": 1}
    assert info["rig"]["cameras"] == ["cam0"] and "rig.toml" not in info["rig"]
    assert info["motor"]["last_step_count"] == 15
    text = cli("info", rec)
    assert text.code == 0 and "profiles    10 (paper" in text.out  # type: ignore[attr-defined]


def test_info_on_a_cut_recording_warns(tmp_path: Path, cli: Callable[..., object]) -> None:
    rec = tmp_path / "rec.mcap"
    _write(rec)
    data = rec.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: data.index(b"\x0f", len(data) // 3)])  # before the data end record
    result = cli("info", cut)
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    assert "INCOMPLETE" in result.out and "warning" in result.out  # type: ignore[attr-defined]


def test_info_on_a_missing_file_is_one_line(tmp_path: Path, cli: Callable[..., object]) -> None:
    result = cli("info", tmp_path / "none.mcap")
    assert result.code == 1  # type: ignore[attr-defined]
    assert result.err.count("\n") == 1 and "not found" in result.err  # type: ignore[attr-defined]


def test_sink_splits_by_size_and_every_part_decodes(tmp_path: Path) -> None:
    rig = rig_with_cameras()
    out = tmp_path / "scan.mcap"
    sink = RecordingSink(out, rig, {"mode": "step"},
                         lambda p, r, s: RecordingWriter(p, r, s, fsync_interval_s=0.01,
                                                         chunk_bytes=4096),
                         split_bytes=20_000)
    payload = np.random.default_rng(1).bytes(2048)  # incompressible
    for i in range(60):
        sink.write_stream("scanner", payload, 0, T0 + i)
        sink.flush()
    sink.event("recording_end", "done")
    sink.close()
    assert len(sink.paths) >= 3
    assert sink.paths[0] == out and sink.paths[1] == part_path(out, 1) == tmp_path / "scan-001.mcap"
    total = 0
    for index, path in enumerate(sink.paths):
        part = read_recording(path)
        assert part.complete and part.rig_toml is not None
        assert json.loads(part.session["part"]) == index
        total += len(part.stream("scanner").data)
    assert total == 60 * len(payload)
    assert sink.stats.stream_bytes["scanner RX"] == total


def test_sink_splits_by_duration(tmp_path: Path) -> None:
    now = [T0]
    sink = RecordingSink(tmp_path / "scan.mcap", rig_with_cameras(), {"mode": "continuous"},
                         lambda p, r, s: RecordingWriter(p, r, s), split_s=2.0,
                         clock_ns=lambda: now[0])
    for second in range(7):  # one chunk of bytes per second, 7 s → parts of 2 s
        now[0] = T0 + second * 10**9
        sink.write_stream("motor", b"POS 0 0 0 0\n", 0, now[0])
    sink.close()
    assert [p.name for p in sink.paths] == ["scan.mcap", "scan-001.mcap", "scan-002.mcap",
                                            "scan-003.mcap"]
    counts = [len(read_recording(p).stream("motor").log_time_ns) for p in sink.paths]
    assert counts == [2, 2, 2, 1]


def test_every_part_but_the_last_says_where_the_scan_continues(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    # `scanpipe run scan.mcap` on the first part of a split recording made a model of that
    # part alone with no word said; each part now carries the fact, and info says it.
    now = [T0]
    sink = RecordingSink(tmp_path / "scan.mcap", rig_with_cameras(), {"mode": "step"},
                         lambda p, r, s: RecordingWriter(p, r, s), split_s=2.0,
                         clock_ns=lambda: now[0])
    for second in range(5):
        now[0] = T0 + second * 10**9
        sink.write_stream("motor", b"POS 0 0 0 0\n", 0, now[0])
    sink.close()
    assert len(sink.paths) == 3
    for index, path in enumerate(sink.paths):
        events = [e for e in read_recording(path).events if e.kind == "recording_continues"]
        if index < len(sink.paths) - 1:
            assert len(events) == 1
            assert events[0].data["next_file"] == sink.paths[index + 1].name
            assert events[0].data["part"] == index
        else:
            assert events == []
    assert sink.stats.events["recording_continues"] == 2
    first = cli("info", sink.paths[0], "--json")
    assert first.code == 0, first.err  # type: ignore[attr-defined]
    warnings = json.loads(first.out)["warnings"]  # type: ignore[attr-defined]
    assert any("continues in scan-001.mcap" in w for w in warnings)
    last = json.loads(cli("info", sink.paths[-1], "--json").out)  # type: ignore[attr-defined]
    assert any("part 2 of a split recording" in w for w in last["warnings"])
    # … and decode, so that `scanpipe run` on one part says so.
    decoded = get_stage("decode").run({"recording": sink.paths[0]}).report["warnings"]
    assert any("continues in scan-001.mcap" in w for w in decoded)
    # An unsplit recording has no such warning, nor one recorded with a split limit that the
    # scan never reached (it is part 0 with no next part: the whole scan).
    whole = tmp_path / "whole.mcap"
    _write(whole)
    assert json.loads(cli("info", whole, "--json").out)["warnings"] == []  # type: ignore
    now[0] = T0
    single = RecordingSink(tmp_path / "single.mcap", rig_with_cameras(), {"mode": "step"},
                           lambda p, r, s: RecordingWriter(p, r, s), split_s=1000.0,
                           clock_ns=lambda: now[0])
    single.write_stream("motor", b"POS 0 0 0 0\n", 0, now[0])
    single.close()
    assert single.paths == [tmp_path / "single.mcap"]
    assert read_recording(single.paths[0]).session.get("part") is not None
    assert read_recording(single.paths[0]).partial_scan_warnings() == []
