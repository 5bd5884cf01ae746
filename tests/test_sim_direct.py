"""``simulate --direct``: the recording decodes to the truth, the truth folder, determinism, CLI."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest
from mcap.reader import make_reader

from scanpipe.errors import SimulationError
from scanpipe.motion import beta_deg_at
from scanpipe.rig import Pose, load_rig, rig_from_table
from scanpipe.sim.direct import chunk_stream, simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.truth import load_truth
from scanpipe.stages.decode import STAGE as DECODE

QUANTUM_M = 1.0 / 256
SMALL = {"beam_step_deg": 2.0, "motor_step_deg": 5.0, "cameras": False}


def _run(tmp_path: Path, name: str = "a", **options: Any) -> tuple[dict[str, Any], Path, Path]:
    rec, truth = tmp_path / f"{name}.mcap", tmp_path / f"{name}-truth"
    summary = simulate_direct(rec, truth, SimOptions.model_validate({**SMALL, **options}))
    return summary, rec, truth


def _ranges(table: pa.Table) -> np.ndarray:
    return np.array(table.column("ranges_m").to_pylist(), dtype=np.float64)


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with path.open("rb") as handle:
        reader = make_reader(handle)
        return [(channel.topic, message.log_time, message.data)
                for _, channel, message in reader.iter_messages(log_time_order=False)]


@pytest.fixture(scope="module")
def noise_free(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path, Path]:
    tmp = tmp_path_factory.mktemp("noise-free")
    return _run(tmp, noise_sigma_m=0.0, dropout_rate=0.0, grazing_start_deg=90.0,
                cameras=True, camera_scale=0.05, camera_fps=0.5)


def test_direct_recording_decodes_to_the_truth_up_to_quantisation(
        noise_free: tuple[dict[str, Any], Path, Path]) -> None:
    summary, rec, truth_dir = noise_free
    decoded = DECODE.run({"recording": rec})
    truth = load_truth(truth_dir)
    measured, expected = _ranges(decoded.tables["profiles"]), truth.ranges_true_m()
    assert measured.shape == expected.shape == (summary["profiles"], 180)
    assert np.array_equal(np.isfinite(measured), np.isfinite(expected))
    finite = np.isfinite(expected)
    assert np.abs(measured[finite] - expected[finite]).max() <= QUANTUM_M / 2 + 1e-6
    assert decoded.report["gaps"]["missing_stream_chunks"] == 0
    assert decoded.tables["profiles"].column("checksum_ok").to_numpy().all()


def test_motor_states_give_the_true_platform_angle_of_stationary_profiles(
        noise_free: tuple[dict[str, Any], Path, Path]) -> None:
    _, rec, truth_dir = noise_free
    decoded = DECODE.run({"recording": rec})
    truth = load_truth(truth_dir)
    motor_table = decoded.tables["motor"]
    assert motor_table.num_rows > 36 * 2  # reports while moving plus a final one per move
    times = truth.profiles.column("time_ns").to_numpy()
    true_beta = truth.profiles.column("beta_deg").to_numpy()
    still = truth.profiles.column("beta_end_deg").to_numpy() == true_beta
    estimated = beta_deg_at(times, motor_table, truth.rig.motor)
    # stationary profiles: the last report before them holds the exact count
    assert np.abs(estimated[still] - true_beta[still]).max() < 1e-9
    assert still.sum() >= 37  # at least one stationary profile per position


def test_cameras_and_truth_folder(noise_free: tuple[dict[str, Any], Path, Path]) -> None:
    summary, rec, truth_dir = noise_free
    decoded = DECODE.run({"recording": rec})
    frames = decoded.tables["frames"]
    assert frames.num_rows == summary["frames"] > 0
    assert set(frames.column("camera_id").to_pylist()) == {"cam0", "cam1", "cam360"}
    # The default cameras stand upright: 1080 × 1920 at the test's 1/20 scale.
    assert frames.column("width").to_pylist()[0] == 54
    assert frames.column("height").to_pylist()[0] == 96
    truth = load_truth(truth_dir)
    assert truth.meta["seed"] == 0 and truth.meta["options"]["beam_step_deg"] == 2.0
    assert len(truth.scene.triangles) > 100
    names = truth.profiles.schema.names
    assert names == ["profile", "time_ns", "time_end_ns", "beta_deg", "beta_end_deg",
                     "ranges_true_m"]
    assert truth.profiles.column("profile").to_pylist() == list(range(summary["profiles"]))


def test_noise_in_the_recording_matches_sigma(tmp_path: Path) -> None:
    _, rec, truth_dir = _run(tmp_path, beam_step_deg=0.5, motor_step_deg=10.0,
                             noise_sigma_m=0.02)
    measured = _ranges(DECODE.run({"recording": rec}).tables["profiles"])
    error = (measured - load_truth(truth_dir).ranges_true_m())[
        np.isfinite(measured)]
    assert error.size > 20_000
    # σ of the sum of noise and quantisation (uniform, variance q²/12)
    expected = np.sqrt(0.02**2 + QUANTUM_M**2 / 12)
    assert error.std() == pytest.approx(expected, rel=0.03)
    assert abs(error.mean()) < 0.001


def test_same_seed_same_bytes_other_seed_other_noise(tmp_path: Path) -> None:
    _, a, _ = _run(tmp_path, "a", seed=4)
    _, b, _ = _run(tmp_path, "b", seed=4)
    _, c, _ = _run(tmp_path, "c", seed=5)
    assert _messages(a) == _messages(b)
    stream = [m for m in _messages(a) if m[0] == "/scanner/stream"]
    assert stream != [m for m in _messages(c) if m[0] == "/scanner/stream"]


def test_true_mount_differs_from_the_nominal_rig(tmp_path: Path) -> None:
    mount = Pose(translation_m=(0.05, 0.0, 0.02), rotation_deg=(0.0, 0.0, 1.0))
    _, rec, truth_dir = _run(tmp_path, true_mount=mount, true_beta_offset_deg=0.5)
    truth_rig = load_rig(truth_dir / "rig.toml")
    assert truth_rig.scanner.mount == mount and truth_rig.motor.beta_offset_deg == 0.5
    nominal = rig_from_table(DECODE.run({"recording": rec}).tables["rig"])
    assert nominal.scanner.mount == Pose() and nominal.motor.beta_offset_deg == 0.0
    assert load_truth(truth_dir).profiles.column("beta_deg").to_numpy().min() == 0.5


def test_continuous_mode_turns_through_the_scan(tmp_path: Path) -> None:
    _, rec, truth_dir = _run(tmp_path, mode="continuous", motor_step_deg=2.0)
    truth = load_truth(truth_dir)
    first = truth.profiles.column("beta_deg").to_numpy()
    last = truth.profiles.column("beta_end_deg").to_numpy()
    assert np.all(np.diff(first) >= 0) and first[-1] > 175
    cruising = (last - first)[len(first) // 2]
    assert cruising == pytest.approx(2.016 * 179 / 180, rel=0.01)  # one step per head turn
    motor = DECODE.run({"recording": rec}).tables["motor"]
    assert motor.column("moving").to_numpy().sum() > 100


def test_chunking_keeps_every_byte_in_order() -> None:
    frames = [bytes([i]) * (10 + i) for i in range(50)]
    chunks = chunk_stream(frames, [float(i) for i in range(50)], np.random.default_rng(0))
    assert b"".join(c for _, c in chunks) == b"".join(frames)
    assert 50 < len(chunks) < 100
    assert [t for t, _ in chunks] == sorted(t for t, _ in chunks)


def test_settings_the_device_refuses_are_reported(tmp_path: Path) -> None:
    from scanpipe.errors import RigError

    with pytest.raises(RigError, match=r"multiple of 0\.125"):
        _run(tmp_path, beam_step_deg=0.3)


def test_bad_scene_is_a_simulation_error(tmp_path: Path) -> None:
    with pytest.raises(SimulationError, match="scene file not found"):
        _run(tmp_path, scene=str(tmp_path / "nope.glb"))


def test_load_truth_of_a_folder_that_is_not_one(tmp_path: Path) -> None:
    with pytest.raises(SimulationError, match="not a truth folder"):
        load_truth(tmp_path)


def test_cli_simulate_direct(cli: Callable[..., Any], tmp_path: Path) -> None:
    result = cli("simulate", "--direct", "--motor-step", "10", "--beam-step", "2",
                 "--no-cameras", "--seed", "3", "--out", tmp_path / "s.mcap",
                 "--truth", tmp_path / "t", "-q", "--json")
    assert result.code == 0, result.err
    summary = json.loads(result.out)
    assert summary["profiles"] > 18 and (tmp_path / "t" / "truth.parquet").is_file()
    assert load_truth(tmp_path / "t").meta["seed"] == 3


@pytest.mark.parametrize(("args", "message"), [
    (("--scene", "missing.obj"), "scene file not found"),
    (("--noise-mm", "-1"), "noise_sigma_m"),
    (("--mode", "spiral"), "mode"),
])
def test_cli_simulate_bad_input_is_one_line(cli: Callable[..., Any], tmp_path: Path,
                                            args: tuple[str, ...], message: str) -> None:
    result = cli("simulate", "--direct", "--out", tmp_path / "s.mcap", "--truth",
                 tmp_path / "t", "-q", *args)
    assert result.code != 0
    assert message in result.err and result.err.count("\n") <= 2
    assert "Traceback" not in result.err
    assert not (tmp_path / "s.mcap").exists()


@pytest.mark.slow
def test_cli_simulate_live_records_through_the_emulators(cli: Callable[..., Any],
                                                         tmp_path: Path) -> None:
    result = cli("simulate", "--motor-step", "30", "--beam-step", "2", "--speedup", "25",
                 "--no-cameras", "--noise-mm", "0", "--out", tmp_path / "s.mcap", "--truth",
                 tmp_path / "t", "-q", "--json")
    assert result.code == 0, result.err
    assert json.loads(result.out)["status"] == "complete"
    truth = load_truth(tmp_path / "t")
    measured = _ranges(DECODE.run({"recording": tmp_path / "s.mcap"}).tables["profiles"])
    expected = truth.ranges_true_m()
    assert measured.shape == expected.shape and len(measured) >= 7
    both = np.isfinite(measured) & np.isfinite(expected)
    assert both.mean() > 0.95
    assert np.abs(measured[both] - expected[both]).max() <= QUANTUM_M / 2 + 1e-6
