"""Assemble time association: step-and-scan drops profiles that overlap motion, device clocks,
checksums, averaging, sectors, and the errors a user sees."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from scan_tables import T0_NS, make_rig, motor_table, positions_scan, profiles_table, step_scan

from scanpipe.errors import ArtifactError, StageError
from scanpipe.rig import rig_table
from scanpipe.stages.assemble import STAGE, AssembleParams


def flat_range(alpha: np.ndarray, beta: float) -> np.ndarray:
    """A range that encodes β, so a profile from the wrong position is visible."""
    return np.full(alpha.shape, 1.0 + beta / 100.0)


def run_step_scan(**options: object) -> tuple[dict[str, object], pa.Table, object]:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=30.0)
    with_device = bool(options.pop("with_device_time", False))
    scan = step_scan(rig, positions=6, pulses_per_position=5, range_fn=flat_range,
                     with_device_time=with_device)
    params = AssembleParams(**options)  # type: ignore[arg-type]
    result = STAGE.run({"profiles": scan.profiles, "motor": scan.motor, "rig": scan.rig}, params)
    return result.report, result.tables["points"], scan


def test_step_mode_drops_every_profile_that_overlaps_motion() -> None:
    report, points, scan = run_step_scan(receive_latency_s=0.002, mode="step")
    assert report["grid"] == {"profiles": 6, "samples": 12}
    dropped = report["profiles_dropped"]
    clean = int(np.count_nonzero(scan.clean))
    assert report["profiles_used"] + report["profiles_extra_at_position"] == clean
    assert sum(dropped.values()) == scan.profiles.num_rows - clean
    assert dropped["moving"] > 0 and dropped["before_motor_log"] == 1
    ranges = points.column("range_m").to_numpy().reshape(6, 12)
    assert not np.any(ranges > 50)  # no profile taken during a move (those read 99 m)
    np.testing.assert_allclose(ranges[:, 0], 1.0 + np.arange(6) * 5 / 100.0, rtol=1e-6)
    np.testing.assert_allclose(points.column("beta_deg").to_numpy()[::12], np.arange(6) * 5.0)


def test_first_profile_per_position_is_the_earliest_complete_one() -> None:
    _, points, scan = run_step_scan(receive_latency_s=0.002)
    times = points.column("time_ns").to_numpy().reshape(6, 12)[:, 0]
    starts = scan.profiles.column("recv_time_ns").to_numpy() - 2_000_000
    window = round(11 * 30.0 / 360 / 5.0 * 1e9)
    first_clean = [starts[scan.position == k][0] - window for k in range(6)]
    np.testing.assert_array_equal(times, first_clean)


def test_settle_time_counts() -> None:
    short, _, _ = run_step_scan(receive_latency_s=0.002, settle_s=0.0, mode="step")
    long, _, _ = run_step_scan(receive_latency_s=0.002, settle_s=0.3, mode="step")
    assert short["profiles_dropped"].get("settling", 0) == 0
    assert long["profiles_dropped"]["settling"] > 0
    assert long["profiles_extra_at_position"] < short["profiles_extra_at_position"]


def test_device_clock_offset_is_estimated_or_taken_as_given() -> None:
    estimated, points_a, _ = run_step_scan(with_device_time=True)
    assert estimated["time_source"] == "device"
    # Device time = host time − T0 + 5 ms and receipt 2 ms after the last sample, so the
    # smallest receive-minus-end delay is T0 − 3 ms.
    assert estimated["clock_offset_ns"] == T0_NS - 3_000_000
    given, points_b, _ = run_step_scan(with_device_time=True, clock_offset_ns=T0_NS - 5_000_000)
    assert given["clock_offset_ns"] == T0_NS - 5_000_000
    diff = points_a.column("time_ns").to_numpy() - points_b.column("time_ns").to_numpy()
    assert np.all(diff == 2_000_000)
    receive, _, _ = run_step_scan(with_device_time=True, time_source="receive")
    assert receive["time_source"] == "receive" and receive["clock_offset_ns"] is None


def test_average_mode_averages_the_complete_profiles_at_a_position() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=30.0)
    noise = iter(np.random.default_rng(0).normal(0, 0.05, 1000))
    scan = step_scan(rig, 4, 3, lambda a, b: 2.0 + next(noise) + 0 * a, profiles_per_dwell=4)
    inputs = {"profiles": scan.profiles, "motor": scan.motor, "rig": scan.rig}
    first = STAGE.run(inputs, AssembleParams(receive_latency_s=0.002))
    mean = STAGE.run(inputs, AssembleParams(receive_latency_s=0.002, step_profile="average"))
    ranges = scan.profiles.column("ranges_m").to_pylist()
    for k in range(4):
        rows = [r[0] for r, pos in zip(ranges, scan.position, strict=True) if pos == k]
        assert len(rows) >= 3
        got_first = first.tables["points"].column("range_m")[k * 12].as_py()
        got_mean = mean.tables["points"].column("range_m")[k * 12].as_py()
        assert got_first == pytest.approx(rows[0])
        assert got_mean == pytest.approx(np.mean(rows), abs=1e-6)
    assert mean.report["profiles_used"] > first.report["profiles_used"]


def test_bad_checksums_are_dropped_unless_kept() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=30.0)
    inputs = positions_scan(rig, [0, 1, 2], np.full((3, 12), 2.0))
    bad = inputs["profiles"].set_column(
        inputs["profiles"].schema.get_field_index("checksum_ok"), "checksum_ok",
        pa.array([True, False, True]))
    result = STAGE.run({**inputs, "profiles": bad})
    assert result.report["profiles_dropped"] == {"checksum": 1}
    assert result.report["grid"]["profiles"] == 2
    assert result.report["positions_without_profile"] == 1
    kept = STAGE.run({**inputs, "profiles": bad}, AssembleParams(keep_bad_checksum=True))
    assert kept.report["grid"]["profiles"] == 3


def test_auto_mode_picks_step_for_step_and_scan() -> None:
    report, _, _ = run_step_scan(receive_latency_s=0.002)
    assert report["mode"] == "step" and "stationary" in report["mode_reason"]


def test_sectors_are_placed_side_by_side_by_angle() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=10.0)
    inputs = positions_scan(rig, [0], np.full((1, 36), 2.0))
    recv = inputs["profiles"].column("recv_time_ns").to_numpy()[0]
    # One head turn in two sectors (0–90° and 180–260°), the second with an echo.
    profiles = profiles_table([np.full(10, 2.0), np.full(9, 3.0)], np.array([0.0, 180.0]), 10.0,
                              np.array([recv - 100_000_000, recv]), frame=np.array([7, 7]),
                              sector=np.array([0, 1]),
                              echo=[np.full(10, 5, np.uint16), np.full(9, 6, np.uint16)])
    result = STAGE.run({**inputs, "profiles": profiles})
    points = result.tables["points"]
    assert result.report["grid"] == {"profiles": 1, "samples": 27}
    ranges = points.column("range_m").to_numpy()
    assert np.all(ranges[:10] == 2.0) and np.all(ranges[18:] == 3.0)
    assert np.all(np.isnan(ranges[10:18]))
    assert result.report["not_measured"] == 8 and result.report["no_return"] == 0
    assert points.column("echo").to_pylist()[:10] == [5] * 10
    assert points.column("echo").to_pylist()[18:] == [6] * 9


def test_no_motor_states_is_a_clear_error() -> None:
    rig = make_rig()
    inputs = positions_scan(rig, [0], np.full((1, 180), 2.0))
    empty = inputs["motor"].slice(0, 0)
    with pytest.raises(StageError, match="no motor states"):
        STAGE.run({**inputs, "motor": empty})


def test_no_usable_profile_is_a_clear_error() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=30.0)
    inputs = positions_scan(rig, [0], np.full((1, 12), 2.0))
    motor = motor_table(np.array([T0_NS + 10**12]), np.array([0]), np.array([False]))
    with pytest.raises(StageError, match=r"none of the 1 profiles.*before_motor_log"):
        STAGE.run({**inputs, "motor": motor}, AssembleParams(mode="step"))


def test_mixed_beam_steps_are_refused() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=30.0)
    inputs = positions_scan(rig, [0, 1], np.full((2, 12), 2.0))
    profiles = inputs["profiles"].set_column(
        inputs["profiles"].schema.get_field_index("step_deg"), "step_deg", pa.array([30.0, 15.0]))
    with pytest.raises(StageError, match="mixed angular steps"):
        STAGE.run({**inputs, "profiles": profiles})


def test_missing_columns_are_named() -> None:
    rig = make_rig(pulse_step_deg=1.0, beam_step_deg=30.0)
    inputs = positions_scan(rig, [0], np.full((1, 12), 2.0))
    with pytest.raises(ArtifactError, match="missing column 'ranges_m'"):
        STAGE.run({**inputs, "profiles": inputs["profiles"].drop_columns(["ranges_m"])})


def test_the_rig_artifact_supplies_the_calibration() -> None:
    ranges = np.full((1, 12), 2.0)
    inputs = positions_scan(make_rig(pulse_step_deg=1.0, beam_step_deg=30.0), [0], ranges)
    shifted = rig_table(make_rig(pulse_step_deg=1.0, beam_step_deg=30.0,
                                 translation_m=(0.0, 0.5, 0.0)))
    y0 = STAGE.run(inputs).tables["points"].column("y").to_numpy()
    y1 = STAGE.run({**inputs, "rig": shifted}).tables["points"].column("y").to_numpy()
    np.testing.assert_allclose(y1 - y0, 0.5, atol=1e-6)
