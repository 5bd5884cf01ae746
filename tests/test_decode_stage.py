"""The decode stage and its commands: recordings written with RecordingWriter, to Parquet."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest

from scanpipe.artifacts import read_artifact
from scanpipe.clock import unwrap_device_ms
from scanpipe.pipeline import execute, get_stage, registry
from scanpipe.protocol import ldoem, paper
from scanpipe.protocol.profile import Profile
from scanpipe.recording.schemas import RX, TX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import Rig, ScannerConfig, default_rig, rig_from_table
from scanpipe.stages.decode import (
    FRAMES_SCHEMA,
    MOTOR_SCHEMA,
    PROFILES_SCHEMA,
    DecodeParams,
    image_size,
)

T0 = 1_700_000_000_000_000_000
PERIOD_NS = 200_000_000  # 5 Hz


def scan_profiles(count: int, samples: int = 180, start_ms: int = 60_000) -> list[Profile]:
    """Profiles at 5 Hz whose 16-bit device clock wraps (start near 65.536 s)."""
    out = []
    for i in range(count):
        t_ms = (start_ms + 200 * i) & 0xFFFF
        wire = (np.arange(samples) * 7 + i) % 2000 + 100
        wire[::9] = 0
        out.append(Profile(frame=i, sector=0, start_angle_deg=0.0, step_deg=360 / samples,
                           ranges_m=np.where(wire == 0, np.nan, wire / 256).astype(np.float32),
                           echo=(wire // 3).astype(np.uint16),
                           device_time_ms=t_ms, device_end_time_ms=(t_ms + 199) & 0xFFFF))
    return out


def write_scan(path: Path, frames: list[bytes | None], rig: Rig | None = None,
               images: int = 3) -> None:
    """Frames sent in uneven chunks, one per 5 Hz period (None: nothing sent in that period),
    plus motor states and images."""
    rng = np.random.default_rng(0)
    jpeg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    with RecordingWriter(path, rig or default_rig(), {"mode": "test"}) as writer:
        writer.write_stream("scanner", ldoem.get_profile_request(0, 0x3DFF), TX, T0)
        for i, frame in enumerate(frames):
            t = T0 + (i + 1) * PERIOD_NS
            if frame is None:
                continue
            cut = int(rng.integers(1, len(frame)))
            writer.write_stream("scanner", frame[:cut], RX, t - 1000)
            writer.write_stream("scanner", frame[cut:], RX, t)
            writer.write_motor_state(t, 3 * i, 3 * i + 3, i % 2 == 1, i * 200_000)
        for k in range(images):
            writer.write_image("cam0", T0 + k * 10_000_000, jpeg)
        writer.write_image("cam1", T0, b"not a jpeg")
        writer.write_event(T0, "note", "test event")


def decode(rec: Path, out: Path, **params: Any) -> tuple[dict[str, pa.Table], dict[str, Any]]:
    record = execute(get_stage("decode"), {"recording": rec}, out, DecodeParams(**params),
                     force=True)
    tables = {name: read_artifact(path)[0] for name, path in record.outputs.items()}
    return tables, record.report


def test_decode_writes_the_artifacts_of_the_contract(tmp_path: Path) -> None:
    sent = scan_profiles(400)  # 80 s: the device clock wraps once
    frames: list[bytes | None] = [
        ldoem.encode_profile_reply([p], mask=ldoem.MASK_RANGES_ECHO) for p in sent]
    write_scan(tmp_path / "scan.mcap", frames)
    tables, report = decode(tmp_path / "scan.mcap", tmp_path / "out")

    profiles = tables["profiles"]
    assert profiles.schema.remove_metadata().equals(PROFILES_SCHEMA)
    assert profiles.num_rows == 400
    assert profiles.column("frame").to_pylist() == list(range(400))
    assert profiles.column("dialect").unique().to_pylist() == ["ldoem"]
    ranges = profiles.column("ranges_m").to_pylist()
    for got, p in zip(ranges[::37], sent[::37], strict=True):
        assert np.array_equal(np.array(got, np.float32), p.ranges_m, equal_nan=True)
    assert profiles.column("echo")[5].as_py() == sent[5].echo.tolist()  # type: ignore[union-attr]
    recv = profiles.column("recv_time_ns").to_numpy()
    assert recv.tolist() == [T0 + (i + 1) * PERIOD_NS for i in range(400)]
    device = profiles.column("device_time_ns").to_numpy()
    assert np.all(np.diff(device) == 200_000_000)  # unwrapped across 65.536 s
    assert device[0] == 60_000 * 1_000_000
    end = profiles.column("device_end_time_ns").to_numpy()
    assert np.all(end - device == 199_000_000)

    motor = tables["motor"]
    assert motor.schema.remove_metadata().equals(MOTOR_SCHEMA)
    assert motor.column("step_count").to_pylist() == [3 * i for i in range(400)]
    frames_art = tables["frames"]
    assert frames_art.schema.remove_metadata().equals(FRAMES_SCHEMA)
    assert frames_art.column("camera_id").to_pylist() == ["cam0"] * 3 + ["cam1"]
    assert frames_art.column("sequence").to_pylist() == [0, 1, 2, 0]
    assert frames_art.column("width").to_pylist() == [64, 64, 64, -1]
    assert frames_art.column("height").to_pylist()[0] == 48
    assert rig_from_table(tables["rig"]) == default_rig()

    assert report["counts"]["profiles"] == 400 and report["counts"]["samples"] == 400 * 180
    assert report["counters"]["checksum_failures"] == 0
    assert report["counters"]["bytes_skipped"] == 0
    assert report["dialect"] == "ldoem" and report["dialect_detected"]
    assert report["time_span"]["duration_s"] == pytest.approx(399 * 0.2)
    assert report["rates"]["profiles_per_s"] == pytest.approx(5.0, rel=0.01)
    assert report["gaps"]["count"] == 0
    assert report["device_clock"]["offset_ns"] == T0 + PERIOD_NS - 60_199 * 1_000_000
    assert report["recording"]["complete"] is True
    assert any("no readable JPEG" in w for w in report["recording"]["warnings"])


def test_decode_paper_dialect_with_damage_and_a_gap(tmp_path: Path) -> None:
    sent = scan_profiles(30, samples=40)
    frames: list[bytes | None] = [paper.encode_profile(p) for p in sent]
    seventh, twelfth = paper.encode_profile(sent[7]), paper.encode_profile(sent[12])
    frames[7] = seventh[:-1] + bytes([seventh[-1] ^ 1])  # checksum failure
    frames[12] = b"\x02\x02\x02\x02\xff\xff\xff\xff" + twelfth  # absurd length
    frames[20:25] = [None] * 5  # a gap of 6 periods
    write_scan(tmp_path / "paper.mcap", frames)
    tables, report = decode(tmp_path / "paper.mcap", tmp_path / "strict")
    profiles = tables["profiles"]
    kept = [i for i in range(30) if i != 7 and not 20 <= i < 25]
    assert profiles.column("frame").to_pylist() == kept
    assert profiles.column("device_time_ns").null_count == profiles.num_rows
    assert profiles.column("echo").null_count == profiles.num_rows
    assert report["dialect"] == "paper"
    assert report["counters"]["checksum_failures"] == 1
    assert report["counters"]["resyncs"] == 1
    assert report["gaps"]["count"] == 1
    assert report["gaps"]["largest"][0]["seconds"] == pytest.approx(1.2)

    tables, report = decode(tmp_path / "paper.mcap", tmp_path / "lenient", checksum="lenient")
    ok = tables["profiles"].column("checksum_ok").to_pylist()
    assert tables["profiles"].column("frame").to_pylist()[7] == 7 and ok[7] is False
    assert report["counts"]["checksum_failed_rows"] == 1


def test_unwrap_device_time_across_long_pauses() -> None:
    """A pause longer than 65.536 s is unwrapped from the host clock, not guessed."""
    true_ms = np.array([1_000, 1_200, 1_400, 200_000, 200_200], np.int64)
    host_ns = T0 + true_ms * 1_000_000 + 3_000_000
    raw = true_ms % 65_536
    assert unwrap_device_ms(raw, host_ns).tolist() == true_ms.tolist()


def test_image_size_of_real_encodings() -> None:
    image = np.zeros((30, 50, 3), np.uint8)
    for ext in (".jpg", ".png"):
        assert image_size(cv2.imencode(ext, image)[1].tobytes()) == (50, 30)
    assert image_size(b"\xff\xd8\xff") is None and image_size(b"") is None


def test_decode_is_registered_and_params_are_validated() -> None:
    stage = registry()["decode"]
    assert stage.inputs == ("recording",)
    assert stage.outputs == ("profiles", "motor", "frames", "rig")
    with pytest.raises(ValueError, match="checksum"):
        DecodeParams(checksum="loose")  # type: ignore[arg-type]


def test_recording_without_scanner_bytes_and_stored_dialect(tmp_path: Path) -> None:
    rig = Rig(scanner=ScannerConfig(dialect="paper"))
    with RecordingWriter(tmp_path / "m.mcap", rig, {}) as writer:
        writer.write_motor_state(T0, 1, 1, False, 0)
    tables, report = decode(tmp_path / "m.mcap", tmp_path / "out")
    assert tables["profiles"].num_rows == 0
    assert tables["profiles"].schema.remove_metadata().equals(PROFILES_SCHEMA)
    assert report["dialect"] == "paper"
    assert tables["motor"].num_rows == 1


CliRunner = Callable[..., Any]


def test_cli_decode_prints_the_report(tmp_path: Path, cli: CliRunner) -> None:
    frames: list[bytes | None] = [ldoem.encode_profile(p)
                                  for p in scan_profiles(20, samples=30)]
    write_scan(tmp_path / "s.mcap", frames)
    result = cli("decode", tmp_path / "s.mcap", "--out", tmp_path / "out", "-q")
    assert result.code == 0, result.err
    assert "profiles            20" in result.out
    assert (tmp_path / "out" / "profiles.parquet").exists()
    result = cli("decode", tmp_path / "s.mcap", "--out", tmp_path / "out", "-q", "--json",
                 "--set", "checksum=lenient")
    assert json.loads(result.out)["checksum_mode"] == "lenient"
    result = cli("decode", tmp_path / "s.mcap", "--out", tmp_path / "out", "--set", "dialekt=x")
    assert result.code == 2 and "did you mean dialect" in result.err
    result = cli("decode", tmp_path / "missing.mcap", "--out", tmp_path / "out")
    assert result.code != 0 and "not found" in result.err and "Traceback" not in result.err


def test_cli_frames_json_keys(tmp_path: Path, cli: CliRunner) -> None:
    capture = tmp_path / "capture.bin"
    capture.write_bytes(b"junk" + b"".join(ldoem.encode_profile(p)
                                            for p in scan_profiles(3, samples=4)))
    result = cli("frames", capture, "--json")
    assert result.code == 0, result.err
    data = json.loads(result.out)
    assert set(data) >= {"frames", "counters"}
    assert len(data["frames"]) == 3
    for frame in data["frames"]:
        assert {"frame", "start_angle_deg", "step_deg", "ranges_m", "checksum_ok"} <= set(frame)
    assert data["frames"][0]["ranges_m"][0] is None  # NaN (no return) as null
    assert data["counters"]["bytes_skipped"] == 4
    assert data["dialect"] == "ldoem"


def test_cli_frames_text_shows_the_golden_mismatch(tmp_path: Path, cli: CliRunner) -> None:
    capture = tmp_path / "golden.bin"
    capture.write_bytes(bytes.fromhex(
        "020202020000001f7352410062000c81ba010113da000004800005000000190"
        "17a0170017001818a"))
    result = cli("frames", capture, "--dialect", "auto")
    assert result.code == 0
    assert "frame 5082" in result.out and "step 72°" in result.out
    assert "MISMATCH (received 0x8a, computed 0x9f)" in result.out
    result = cli("frames", capture, "--dialect", "cola")
    assert result.code == 2
    assert "allowed paper, ldoem, cola_b, cola_a, ldrobot, ldrobot_ld14, scip, auto" in result.err


def test_scip_without_a_pp_reply_warns_of_the_assumed_geometry(tmp_path: Path) -> None:
    """A SCIP capture whose PP reply was not recorded decodes with the UST/UTM geometry: said,
    not silent (a URG-04LX's angles would be wrong); with the PP reply in front, no warning."""
    from scanpipe.protocol import scip

    ust = [Profile(frame=i, sector=0, start_angle_deg=-135.0, step_deg=0.25,
                   ranges_m=np.full(1081, 2.0, np.float32), echo=None,
                   device_time_ms=1000 + 25 * i, device_end_time_ms=1000 + 25 * i + 20)
           for i in range(5)]
    rig = default_rig()
    rig = rig.model_copy(update={"scanner": rig.scanner.model_copy(update={"dialect": "scip"})})
    bare = [scip.encode_profile(p) for p in ust]
    write_scan(tmp_path / "bare.mcap", list(bare), rig)
    tables, report = decode(tmp_path / "bare.mcap", tmp_path / "out1", dialect="scip")
    assert tables["profiles"].num_rows == 5
    assert any("no SCIP PP reply" in w and "ARES 1440" in w for w in report["warnings"])
    pp = scip.parameter_reply(b"PP", scip.pp_fields(scip.UST_GEOMETRY, "UST-10LX", 60, 10000,
                                                    1440, 2400))
    write_scan(tmp_path / "pp.mcap", [pp + bare[0], *bare[1:]], rig)
    tables, report = decode(tmp_path / "pp.mcap", tmp_path / "out2", dialect="scip")
    assert tables["profiles"].num_rows == 5
    assert not any("no SCIP PP reply" in w for w in report["warnings"])
