"""Camera channels with hostile names: a recording decoded and textured through the CLI.

The camera id is the middle of the channel name ``/camera/<id>/image``, which anything may have
written. Frames of ids the rig does not know are skipped with a warning naming each; the other
cameras texture the mesh.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from texture_scene import Recording, mesh_tables, record, room_mesh, small_rig

from benchmarks.hostile import black_png
from scanpipe.artifacts import read_artifact, write_artifact
from scanpipe.recording.writer import RecordingWriter

HOSTILE_IDS = ["../../etc/x", "with space", "ünïcødé 📷", "x" * 5000, "cam9", ""]


@pytest.fixture(scope="module")
def recording() -> Recording:
    return record(small_rig(), beta_step_deg=15.0)


def _write_mcap(path: Path, recording: Recording, extra: dict[str, list[bytes]]) -> None:
    """The recording's frames and motor states as MCAP, plus frames on hostile channels."""
    frames, motor = recording.frames.to_pylist(), recording.motor.to_pylist()
    with RecordingWriter(path, recording.rig, {"mode": "test"}) as writer:
        for m in motor:
            writer.write_motor_state(m["log_time_ns"], m["step_count"], m["target_step_count"],
                                     m["moving"], m["device_time_us"])
        for f in frames:
            writer.write_image(f["camera_id"], f["log_time_ns"], f["data"])
        for camera_id, images in extra.items():
            for k, data in enumerate(images):
                writer.write_image(camera_id, motor[0]["log_time_ns"] + 1000 * (k + 1), data)


def _decode_and_mesh(cli, tmp_path: Path, recording: Recording,
                     extra: dict[str, list[bytes]]) -> Path:
    rec = tmp_path / "rec.mcap"
    _write_mcap(rec, recording, extra)
    decoded = cli("decode", rec, "--out", tmp_path / "decode", "-q")
    assert decoded.code == 0, decoded.err
    vt, ft = mesh_tables(*room_mesh(0.5))
    for name, table in (("mesh_vertices", vt), ("mesh_faces", ft)):
        write_artifact(tmp_path / "mesh" / f"{name}.parquet", table, {"key": name})
    return tmp_path


def test_hostile_channel_names_are_skipped_with_a_warning(cli, tmp_path: Path,
                                                          recording: Recording) -> None:
    frame = recording.frames.column("data")[0].as_py()
    work = _decode_and_mesh(cli, tmp_path, recording, {c: [frame] * 2 for c in HOSTILE_IDS})
    frames = read_artifact(work / "decode" / "frames.parquet")[0]
    assert set(HOSTILE_IDS) <= set(frames.column("camera_id").to_pylist())

    for method in ("projective", "panorama"):
        out = work / f"out_{method}"
        result = cli("texture", work / "mesh", work / "decode", "--out", out, "--method", method,
                     "--json", "-q")
        assert result.code == 0, result.err
        report = json.loads(result.out)
        assert report["faces_textured"] > 0
        warnings = [line for line in result.err.splitlines() if line.startswith("warning: ")]
        assert len(warnings) == len(HOSTILE_IDS) == len(report["warnings"])
        for camera_id in HOSTILE_IDS[:3] + HOSTILE_IDS[4:]:
            assert any(f"skipped 2 frame(s) of camera {camera_id!r}: not in the rig" in w
                       for w in warnings), camera_id
        long_warning = next(w for w in warnings if "xxxx" in w)
        assert len(long_warning) < 200 and "(5000 characters)" in long_warning
        used = set(read_artifact(out / "textured_faces.parquet")[0]
                   .column("camera_id").drop_null().to_pylist())
        assert used <= {"cam0", "cam1"}
    # nothing written outside the output folders, whatever the channel names said
    assert sorted(p.name for p in work.iterdir()) == [
        "decode", "mesh", "out_panorama", "out_projective", "rec.mcap"]


def test_only_hostile_channels_is_one_clear_error(cli, tmp_path: Path,
                                                  recording: Recording) -> None:
    frame = recording.frames.column("data")[0].as_py()
    no_frames = recording.frames.slice(0, 0)
    empty = Recording(recording.rig, no_frames, recording.motor)
    work = _decode_and_mesh(cli, tmp_path, empty, {"../../etc/x": [frame]})
    result = cli("texture", work / "mesh", work / "decode", "--out", work / "out", "-q")
    assert result.code == 1
    assert result.err.strip().splitlines() == [
        "scanpipe: error: frames: none of the rig's cameras (cam0, cam1) has frames; skipped 1 "
        "frame(s) of camera '../../etc/x': not in the rig (cameras: cam0, cam1)"]
    assert not (work / "out" / "textured_faces.parquet").exists()


def test_a_hostile_frame_of_a_known_camera_is_one_clear_error(cli, tmp_path: Path,
                                                              recording: Recording) -> None:
    frames = recording.frames.to_pylist()
    frames[3]["data"] = black_png(40_000, 40_000)  # a 1.6 MB PNG claiming 1.6 Gpx
    import pyarrow as pa

    bombed = Recording(recording.rig, pa.Table.from_pylist(frames, recording.frames.schema),
                       recording.motor)
    work = _decode_and_mesh(cli, tmp_path, bombed, {})
    result = cli("texture", work / "mesh", work / "decode", "--out", work / "out", "-q")
    assert result.code == 1
    lines = result.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"scanpipe: error: frames: frame {frames[3]['sequence']} of 'cam0': the image is "
        "40000×40000 px (1600.0 Mpx), more than the limit of 33.2 Mpx")
    assert not (work / "out" / "textured_faces.parquet").exists()
