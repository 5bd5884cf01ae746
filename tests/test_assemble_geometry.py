"""Assemble geometry: the paper's eq. 14–16 through the whole stage, and the fast path against a
slow per-point reference straight from scanpipe.geometry (with a mount pose and zero offsets)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from scan_tables import T0_NS, make_rig, motor_table, positions_scan, profiles_table

from scanpipe.geometry import scan_point_to_rig, sensor_origin_in_rig
from scanpipe.rig import rig_table
from scanpipe.stages.assemble import STAGE, AssembleParams

PAPER_VECTORS = [  # r, α, β → x, y, z (shared/paper/NOTES.md)
    (2.0, 90.0, 0.0, (2.0, 0.0, 0.0)),
    (2.0, 90.0, 90.0, (0.0, 0.0, 2.0)),
    (2.0, 0.0, 37.0, (0.0, 2.0, 0.0)),
    (2.0, 30.0, 45.0, (0.70711, 1.73205, 0.70711)),
    (1.5, 200.0, 120.0, (0.25652, -1.40954, -0.44430)),
]

CONTRACT = {
    "x": pa.float32(), "y": pa.float32(), "z": pa.float32(), "range_m": pa.float32(),
    "alpha_deg": pa.float64(), "beta_deg": pa.float64(), "time_ns": pa.int64(),
    "profile": pa.int32(), "sample": pa.int32(), "origin_x": pa.float32(),
    "origin_y": pa.float32(), "origin_z": pa.float32(),
}


def test_paper_vectors_through_the_stage() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=10.0)  # 1° per pulse: β in whole steps
    samples = rig.scanner.samples_per_profile
    ranges = np.full((len(PAPER_VECTORS), samples), 3.0)
    for k, (r, alpha, _, _) in enumerate(PAPER_VECTORS):
        ranges[k, round(alpha / 10)] = r
    inputs = positions_scan(rig, [round(v[2]) for v in PAPER_VECTORS], ranges)
    result = STAGE.run(inputs)
    points = result.tables["points"]
    assert result.report["mode"] == "step"
    assert result.report["grid"] == {"profiles": len(PAPER_VECTORS), "samples": samples}
    for k, (r, alpha, beta, expected) in enumerate(PAPER_VECTORS):
        row = points.slice(k * samples + round(alpha / 10), 1).to_pylist()[0]
        assert (row["profile"], row["sample"]) == (k, round(alpha / 10))
        assert row["alpha_deg"] == pytest.approx(alpha)
        assert row["beta_deg"] == pytest.approx(beta)
        assert row["range_m"] == pytest.approx(r)
        np.testing.assert_allclose([row["x"], row["y"], row["z"]], expected, atol=1e-5)


def test_output_follows_the_points_contract() -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=30.0)
    inputs = positions_scan(rig, [0, 1, 2], np.full((3, 12), 2.0))
    points = STAGE.run(inputs).tables["points"]
    for name, dtype in CONTRACT.items():
        assert points.schema.field(name).type == dtype, name
    assert "echo" not in points.column_names  # absent from the input, absent from the output
    assert points.column("profile").to_pylist() == [p for p in range(3) for _ in range(12)]
    assert points.column("sample").to_pylist() == list(range(12)) * 3


def slow_reference(ranges: np.ndarray, alphas: np.ndarray, betas: np.ndarray,
                   translation: tuple[float, float, float],
                   rotation: tuple[float, float, float]) -> np.ndarray:
    """Per-point loop over scanpipe.geometry.scan_point_to_rig."""
    out = np.empty((*ranges.shape, 3))
    for p in range(ranges.shape[0]):
        for s in range(ranges.shape[1]):
            out[p, s] = scan_point_to_rig(float(ranges[p, s]), float(alphas[s]), float(betas[p]),
                                          translation, rotation)
    return out


def test_fast_path_matches_the_slow_reference_with_a_mount_pose_and_offsets() -> None:
    translation, rotation = (0.04, -0.03, 0.07), (1.2, -0.8, 2.5)
    rig = make_rig(pulse_step_deg=0.5, beam_step_deg=7.5, translation_m=translation,
                   rotation_deg=rotation, alpha_offset_deg=0.7, beta_offset_deg=-1.3)
    rng = np.random.default_rng(3)
    steps = [0, 7, 40, 111, 250, 333]
    ranges = rng.uniform(0.6, 40.0, (len(steps), rig.scanner.samples_per_profile))
    points = STAGE.run(positions_scan(rig, steps, ranges)).tables["points"]
    alphas = np.arange(ranges.shape[1]) * 7.5 + 0.7
    betas = np.asarray(steps) * 0.5 - 1.3
    expected = slow_reference(ranges.astype(np.float32), alphas, betas, translation, rotation)
    got = np.stack([points.column(c).to_numpy() for c in "xyz"], axis=1)
    np.testing.assert_allclose(got, expected.reshape(-1, 3), atol=2e-5 * 40)
    origins = np.stack([points.column(f"origin_{c}").to_numpy() for c in "xyz"], axis=1)
    expected_origins = np.repeat(sensor_origin_in_rig(betas, translation), ranges.shape[1], axis=0)
    np.testing.assert_allclose(origins, expected_origins, atol=1e-6)
    np.testing.assert_allclose(points.column("alpha_deg").to_numpy(), np.tile(alphas, len(steps)))
    # The origin really is where the beam starts: range = |point − origin|.
    np.testing.assert_allclose(np.linalg.norm(got - origins, axis=1),
                               points.column("range_m").to_numpy(), rtol=1e-5)


def test_calibration_changes_the_points() -> None:
    ranges = np.full((2, 12), 3.0)
    plain = STAGE.run(positions_scan(make_rig(beam_step_deg=30.0), [0, 10], ranges))
    tilted = STAGE.run(positions_scan(make_rig(beam_step_deg=30.0, rotation_deg=(0, 0, 1.0)),
                                      [0, 10], ranges))
    a = plain.tables["points"].column("x").to_numpy()
    b = tilted.tables["points"].column("x").to_numpy()
    assert np.max(np.abs(a - b)) > 0.04  # 1° of tilt at 3 m ≈ 5 cm


def test_no_returns_stay_in_the_grid_as_nan() -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=30.0)
    ranges = np.full((2, 12), 2.0)
    ranges[1, 4] = np.nan
    result = STAGE.run(positions_scan(rig, [0, 1], ranges))
    points = result.tables["points"]
    assert points.num_rows == 24
    assert result.report["no_return"] == 1
    assert np.isnan(points.column("x").to_numpy()[12 + 4])


def test_continuous_mode_interpolates_beta_per_sample() -> None:
    rig = make_rig(pulse_step_deg=0.1, beam_step_deg=10.0, scan_hz=5.0)
    samples = rig.scanner.samples_per_profile
    rate_steps_per_s = 50.0  # 5°/s: β changes by ~1° over one head turn
    t_motor = T0_NS + np.arange(0, 41) * 100_000_000
    steps = np.rint((t_motor - T0_NS) / 1e9 * rate_steps_per_s).astype(np.int64)
    motor = motor_table(t_motor, steps, np.ones(t_motor.size, bool), np.full(t_motor.size, 200))
    period = 200_000_000
    window = round((samples - 1) * 10.0 / 360 / 5.0 * 1e9)
    starts = T0_NS + 300_000_000 + np.arange(15) * period
    device = starts - T0_NS  # the device clock starts at T0
    profiles = profiles_table(np.full((15, samples), 2.5), 0.0, 10.0, starts + window,
                              device_time_ns=device, device_end_time_ns=device + window)
    result = STAGE.run({"profiles": profiles, "motor": motor, "rig": rig_table(rig)},
                       AssembleParams(clock_offset_ns=T0_NS))
    assert result.report["mode"] == "continuous"
    points = result.tables["points"]
    t = points.column("time_ns").to_numpy()
    expected_beta = (t - T0_NS) / 1e9 * rate_steps_per_s * 0.1
    beta = points.column("beta_deg").to_numpy()
    np.testing.assert_allclose(beta, expected_beta, atol=0.2 * 0.1)  # steps are rounded
    assert np.ptp(beta[:samples]) > 0.5  # it really changes within one profile
    assert np.all(np.diff(t[:samples]) > 0)
    assert t[0] == starts[0] and t[samples - 1] == starts[0] + window
    x = points.column("x").to_numpy()
    z = points.column("z").to_numpy()
    alpha = np.radians(points.column("alpha_deg").to_numpy())
    np.testing.assert_allclose(x, 2.5 * np.sin(alpha) * np.cos(np.radians(beta)), atol=1e-5)
    np.testing.assert_allclose(z, 2.5 * np.sin(alpha) * np.sin(np.radians(beta)), atol=1e-5)
