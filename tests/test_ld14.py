"""LDRobot LD14 / LD14P: the LD06's packets, each sample's angle corrected by the vendor SDK's
distance-dependent shift (ldlidar_sl_ros2, ``SlTransform``), as their own dialect
``ldrobot_ld14`` that the rig's model names (the bytes cannot tell an LD14 from an LD06)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from scanpipe.evaluate import SurfaceDistance, load_reference
from scanpipe.protocol import ldrobot as ld
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import (
    DIALECTS,
    StreamDecoder,
    decode_bytes,
    detect_dialect,
    get_dialect,
)
from scanpipe.recording.reader import read_recording
from scanpipe.recording.schemas import RX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import load_rig
from scanpipe.scanner_models import SCANNER_MODELS, limit_problems
from scanpipe.sim.ldrobot_device import LdrobotHead, cast_beams, ldrobot_model
from scanpipe.sim.motion import PlatformState
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.scanner import MeasurementModel
from scanpipe.stages.decode import DecodedStream, DecodeParams, decode_recording


def test_the_shift_is_the_sdks_formula_computed_by_hand() -> None:
    # SlTransform (LD_14, LD_14P_*): x = d + 5.9, y = d · 0.11923 − 18.975571 (d in mm),
    # shift = atan(y / x) · 180 / 3.14159; the SDK's angle = packet angle − shift.
    # d = 200: y / x = 4.870429 / 205.9 = 0.0236543 → 1.35504°
    # d = 1000: 100.254429 / 1005.9 = 0.0996664 → 5.69167°
    # d = 5000: 577.174429 / 5005.9 = 0.1152988 → 6.57710°
    shift = ld.sl_angle_shift_deg(np.array([200, 1000, 5000]))
    np.testing.assert_allclose(shift, [1.35504, 5.69167, 6.57710], atol=2e-5)
    # Below ~159 mm the shift changes sign (the laser crosses the receiver's axis there).
    assert ld.sl_angle_shift_deg(np.array([150]))[0] < 0 < ld.sl_angle_shift_deg(
        np.array([170]))[0]
    assert pytest.approx(6.79928, abs=1e-4) == ld.SL_MAX_SHIFT_DEG


def _turns(ranges_mm: Callable[[np.ndarray], np.ndarray], turns: int = 5,
           samples: int = 384) -> bytes:
    """Packets of a head at 6 turns/s whose sample at packet angle a reads ranges_mm(a)."""
    step = 360.0 / samples
    angle = np.arange(turns * samples) * step
    per = ld.POINTS_PER_PACKET
    rows = np.arange(angle.size // per)[:, None] * per + np.arange(per)
    a = angle[rows]
    cdeg = np.rint(a * 100).astype(np.int64) % ld.TURN_CDEG
    stamp = np.rint(a[:, 0] / 2.16).astype(np.int64) % ld.TIME_WRAP_MS  # 2160 °/s
    mm = ranges_mm(a % 360.0).astype(np.int64)
    return ld.encode_packets(np.full(len(rows), 2160), cdeg[:, 0], mm,
                             np.full(mm.shape, 200), cdeg[:, -1], stamp)


def test_the_correction_turns_samples_by_minus_the_shift() -> None:
    # A wall at 2 m with a 1 m post at packet angles 100…110°: with the correction the post
    # lies at 100 − 5.69° … 110 − 5.69° (sign and unit as the SDK's), without it at 100°.
    def ranges(a: np.ndarray) -> np.ndarray:
        return np.where((a >= 100) & (a < 110), 1000, 2000)

    data = _turns(ranges)
    for correct, first_deg in ((True, 100 - 5.69167), (False, 100.0)):
        profiles, _ = ld.decode_revolutions(data, sl_correction=correct)
        p = profiles[2]
        near = np.flatnonzero(p.ranges_m < 1.5)
        angles = near * p.step_deg
        assert angles[0] == pytest.approx(first_deg, abs=p.step_deg), correct
        assert angles[-1] == pytest.approx(first_deg + 10, abs=1.5 * p.step_deg), correct
    # The wall: every beam is 2 m or 1 m (the correction reorders, but invents no range).
    p = ld.decode_revolutions(data, sl_correction=True)[0][2]
    assert set(np.round(p.ranges_m[np.isfinite(p.ranges_m)], 3).tolist()) <= {1.0, 2.0}


def test_a_turn_skipped_whole_is_no_revolution_of_holes() -> None:
    # A turn missing from the stream (a host that read too late, a head the emulator skipped):
    # the next turn's first samples, far away, are corrected up to 6.8° below its 0°, into the
    # missing turn's end. They must not make that turn a revolution of its last 2 % (it was
    # handed out, and every later profile matched the truth one turn early).
    n = 384
    truth = np.full(n, 4.0, np.float32)
    data = b"".join(ld.encode_profile_sl(Profile(
        frame=k, sector=0, start_angle_deg=0.0, step_deg=360.0 / n, ranges_m=truth,
        device_time_ms=100 * k)) for k in (0, 1, 3, 4))
    profiles, _ = decode_bytes(data, "ldrobot_ld14")
    assert [p.frame for p in profiles] == [0, 1, 3, 4]
    for p in profiles[1:-1]:
        assert np.isfinite(p.ranges_m).mean() > 0.95
        assert np.nanmax(np.abs(p.ranges_m - truth)) < 0.002


def test_a_profile_round_trips_through_the_ld14_dialect() -> None:
    n = 384
    angle = np.arange(n) * (360.0 / n)
    truth = (1.5 + 0.6 * np.sin(np.radians(3 * angle))).astype(np.float32)
    dialect = DIALECTS["ldrobot_ld14"]
    data = b"".join(dialect.encode_profile(Profile(
        frame=k, sector=0, start_angle_deg=0.0, step_deg=360.0 / n, ranges_m=truth,
        device_time_ms=100 * k)) for k in range(5))
    profiles, _ = decode_bytes(data, "ldrobot_ld14")
    assert len(profiles) == 5
    for p in profiles[:-1]:
        assert np.nanmax(np.abs(p.ranges_m - truth)) < 0.002
    # The same bytes read as an LD06: sheared by the shift, centimetres off on the slopes.
    sheared, _ = decode_bytes(data, "ldrobot")
    assert np.nanmax(np.abs(sheared[1].ranges_m - truth)) > 0.05
    # The bytes cannot tell: auto detection names the family, never the LD14.
    assert detect_dialect(data) == "ldrobot"


@pytest.mark.parametrize("model", ["ld14", "ld14p"])
def test_the_simulated_ld14_head_decodes_to_the_scene(model: str) -> None:
    m = ldrobot_model(model)
    low, high = SCANNER_MODELS[model].range_m
    rig = load_rig(None)
    head = LdrobotHead(m, resolve_scene("room"), rig.scanner.model_copy(update={
        "min_range_m": low, "max_range_m": high}), PlatformState(rig.motor.pulse_step_deg),
        MeasurementModel(dropout_rate=0.0, seed=4))
    data = head.packets(0, 800).data  # 2.4–4.2 s, 14–25 turns
    rms = {}
    for correct in (True, False):
        profiles, _ = ld.decode_revolutions(data, sl_correction=correct)
        err = []
        for p in profiles[1:-1]:
            grid = np.arange(len(p.ranges_m)) * p.step_deg
            truth, _ = cast_beams(head.scene, head.scanner, grid, np.zeros(grid.size))
            both = np.isfinite(truth) & np.isfinite(p.ranges_m)
            err.append(p.ranges_m[both] - truth[both])
        e = np.concatenate(err)
        assert e.size > 5000
        rms[correct] = float(np.sqrt(np.mean(np.square(e))))
    assert rms[True] <= 1.1 * m.noise_sigma_m, rms  # within the head's noise
    assert rms[False] > 3 * rms[True], rms  # read as an LD06: sheared


@pytest.mark.parametrize(("stored", "given"), [("ld06", "ld14"), ("ld14p", "ld19")])
def test_run_refuses_a_rig_override_of_the_other_variant(tmp_path: Path, cli: Callable[..., Any],
                                                         stored: str, given: str) -> None:
    """``run --rig`` replaces the stored rig for the stages after decode only: decode reads the
    rig stored in the recording. An LD14 recorded under an LD06 rig (or the reverse) and given
    the right rig with --rig was decoded with the stored rig's dialect and assembled with the
    override's scanner: sheared by up to 7°, without a word. Now one line, exit 2."""
    for name in (stored, given):
        assert cli("rig", "init", tmp_path / f"{name}.toml", "--scanner", name).code == 0
    rec, work = tmp_path / "rec.mcap", tmp_path / "work"
    with RecordingWriter(rec, load_rig(tmp_path / f"{stored}.toml"), {"mode": "test"}) as writer:
        writer.write_stream("scanner", _turns(lambda a: np.full(a.shape, 2000)), RX,
                            1_700_000_000_000_000_000)
    override = tmp_path / f"{given}.toml"
    result = cli("run", rec, "--workdir", work, "--rig", override, "--to", "decode", "--quiet")
    assert result.code == 2, result.err
    errors = [line for line in result.err.splitlines() if line.startswith("scanpipe: error:")]
    assert len(errors) == 1 and str(override) in errors[0] and "7°" in errors[0], result.err
    assert "Traceback" not in result.err
    wanted = load_rig(override).scanner.dialect
    if wanted == "ldrobot_ld14":  # the advice works: the stream decoded with the correction
        assert f"--set decode.dialect={wanted}" in errors[0]
        again = cli("run", rec, "--workdir", work, "--rig", override, "--to", "decode",
                    "--set", f"decode.dialect={wanted}", "--quiet")
        assert again.code == 0, again.err
    # the rig stored, given again, is the same scanner: no refusal
    same = cli("run", rec, "--workdir", work, "--rig", tmp_path / f"{stored}.toml", "--to",
               "decode", "--quiet")
    assert same.code == 0, same.err


def test_the_ld14_models_and_their_limits(tmp_path: Path, cli: Callable[..., Any]) -> None:
    for name, baud, hz_step in (("ld14", 115_200, 360 * 6 / 2300),
                                ("ld14p", 230_400, 360 * 6 / 4000)):
        assert cli("rig", "init", tmp_path / f"{name}.toml", "--scanner", name).code == 0
        scanner = load_rig(tmp_path / f"{name}.toml").scanner
        assert (scanner.model, scanner.dialect, scanner.baudrate) == (name, "ldrobot_ld14", baud)
        assert scanner.scan_hz == 6.0 and scanner.beam_step_deg == pytest.approx(hz_step)
        assert limit_problems(scanner) == []
        fast = scanner.model_copy(update={"scan_hz": 10.0,
                                          "beam_step_deg": 10 / 6 * hz_step})
        assert any("scan_hz" in p and "2–8 Hz" in p for p in limit_problems(fast))


@pytest.mark.slow
def test_simulate_ld14_direct_then_run_is_within_the_noise(tmp_path: Path,
                                                           cli: Callable[..., Any]) -> None:
    """The direct simulator (no emulator) for an LD14 at its 6 Hz: the packets carry that
    speed (they said 10 Hz, so every other turn was read as skipped: half the points no
    return, no mesh) and the beams off their angles; run's points lie on the room."""
    rec, truth, work = tmp_path / "rec.mcap", tmp_path / "truth", tmp_path / "work"
    assert cli("simulate", "--scanner", "ld14", "--direct", "--out", rec, "--truth", truth,
               "--mode", "continuous", "--motor-step", "2", "--no-cameras", "--seed", "3",
               "--quiet").code == 0
    result = cli("run", rec, "--workdir", work, "--quiet")
    assert result.code == 0, result.err
    assert "no receipt was prompt" not in result.err  # a turn's receipt is its own packets'
    profiles = pq.read_table(work / "decode" / "profiles.parquet", columns=["dialect",
                                                                            "ranges_m"])
    assert set(profiles.column("dialect").to_pylist()) == {"ldrobot_ld14"}
    info = cli("info", rec, "--json")  # its rig names the variant there too
    assert info.code == 0 and json.loads(info.out)["profiles"]["dialect"] == "ldrobot_ld14"
    table = pq.read_table(work / "assemble" / "points.parquet", columns=["x", "y", "z"])
    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    assert len(xyz) > 0.8 * sum(len(r) for r in profiles.column("ranges_m").to_pylist()) / 2
    distances = SurfaceDistance(load_reference(truth).mesh).distance_m(xyz)
    rms = float(np.sqrt(np.mean(np.square(distances))))
    assert rms <= 1.1 * SCANNER_MODELS["ld14"].noise_sigma_m, rms

    # A stream decoded while it was recorded (run --follow) detects the plain family from
    # the bytes: the decode stage does not take it for an LD14 rig, it decodes with the
    # correction (the same profiles as the batch decode).
    recording = read_recording(rec)
    params = DecodeParams()
    plain = get_dialect("ldrobot")
    decoder = StreamDecoder(plain)
    frames = decoder.feed_frames(recording.stream("scanner", RX).data)
    frames += decoder.finish_frames()
    followed = decode_recording(recording, params, decoded=DecodedStream(plain, decoder, frames))
    batch = decode_recording(recording, params)
    assert followed.report["dialect"] == batch.report["dialect"] == "ldrobot_ld14"
    a, b = followed.tables["profiles"], batch.tables["profiles"]
    assert a.schema == b.schema and a.num_rows == b.num_rows, (a.schema, b.schema)
    for name in a.column_names:  # lists flattened (with their lengths): NaN equals NaN
        x, y = a.column(name).combine_chunks(), b.column(name).combine_chunks()
        if pa.types.is_list(x.type):
            assert x.value_lengths().equals(y.value_lengths()), name
            x, y = x.flatten(), y.flatten()
        np.testing.assert_array_equal(x.to_numpy(zero_copy_only=False),
                                      y.to_numpy(zero_copy_only=False), name)
