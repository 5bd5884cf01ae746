"""Sensor models: scanner ranges and noise, motor motion, camera rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scanpipe.camera import project_points
from scanpipe.geometry import platform_rotation, scan_point_to_rig
from scanpipe.images import encode_jpeg_rgb
from scanpipe.planning import move_time_s
from scanpipe.rig import CameraConfig, Pose, ScannerConfig
from scanpipe.sim.camera import CameraModel, render_rgb, scaled_camera
from scanpipe.sim.motion import MotorTimeline, Move, PlatformState
from scanpipe.sim.room import box_room, builtin_room
from scanpipe.sim.scanner import (
    MeasurementModel,
    TrueProfiles,
    beam_angles_deg,
    measure,
    sample_time_offsets_s,
    true_ranges,
)

ROOM_LO = np.array([-3.0, -1.2, -2.0])
ROOM_HI = np.array([3.0, 1.8, 2.0])


def _analytic_range(alpha: float, beta: float, scanner: ScannerConfig) -> float:
    """Slow reference: the ray of one sample intersected with the box room's walls."""
    origin = scan_point_to_rig(0.0, 0.0, beta, scanner.mount.translation_m,
                               scanner.mount.rotation_deg)
    tip = scan_point_to_rig(1.0, alpha + scanner.alpha_offset_deg, beta,
                            scanner.mount.translation_m, scanner.mount.rotation_deg)
    direction = tip - origin
    best = math.inf
    for axis in range(3):
        if abs(direction[axis]) < 1e-12:
            continue
        wall = ROOM_HI[axis] if direction[axis] > 0 else ROOM_LO[axis]
        best = min(best, (wall - origin[axis]) / direction[axis])
    return best


@pytest.mark.parametrize("mount", [
    Pose(),
    Pose(translation_m=(0.05, 0.12, -0.03), rotation_deg=(1.5, -2.0, 0.7)),
])
def test_noise_free_ranges_equal_analytic_distances_in_a_box_room(mount: Pose) -> None:
    scanner = ScannerConfig(beam_step_deg=3.0, mount=mount, alpha_offset_deg=0.4,
                            min_range_m=0.0)
    betas = np.array([0.0, 17.3, 95.0, 179.9])
    beta_grid = np.repeat(betas[:, None], scanner.samples_per_profile, axis=1)
    truth = true_ranges(box_room((6.0, 3.0, 4.0), -1.2), scanner, beta_grid)
    alphas = beam_angles_deg(scanner)
    expected = np.array([[_analytic_range(a, b, scanner) for a in alphas] for b in betas])
    np.testing.assert_allclose(truth.ranges_m, expected, atol=1e-3)


def test_min_and_max_range_blank_the_truth() -> None:
    scanner = ScannerConfig(beam_step_deg=2.0, min_range_m=1.3, max_range_m=2.5)
    truth = true_ranges(box_room(), scanner, np.zeros((1, scanner.samples_per_profile)))
    finite = truth.ranges_m[np.isfinite(truth.ranges_m)]
    assert finite.min() >= 1.3 and finite.max() <= 2.5
    assert np.isnan(truth.ranges_m).any()


def _flat_truth(profiles: int, samples: int, range_m: float = 3.0) -> TrueProfiles:
    return TrueProfiles(np.full((profiles, samples), range_m),
                        np.ones((profiles, samples), np.float32))


def test_noise_statistics_match_sigma() -> None:
    scanner = ScannerConfig(beam_step_deg=0.25)
    model = MeasurementModel(noise_sigma_m=0.010, dropout_rate=0.0, seed=5)
    measured = measure(_flat_truth(100, 1440), model, 0, scanner)
    error = measured.astype(np.float64) - 3.0
    n = error.size
    assert abs(error.mean()) < 4 * 0.010 / math.sqrt(n)
    # the sample σ of 144 000 draws is within ±1 % of σ with overwhelming probability
    assert error.std() == pytest.approx(0.010, rel=0.01)


def test_measurement_is_deterministic_per_seed_and_profile() -> None:
    scanner = ScannerConfig(beam_step_deg=1.0)
    truth = _flat_truth(6, 360)
    model = MeasurementModel(seed=9)
    whole = measure(truth, model, 10, scanner)
    tail = measure(TrueProfiles(truth.ranges_m[3:], truth.cos_incidence[3:]), model, 13, scanner)
    assert np.array_equal(whole[3:], tail, equal_nan=True)  # batching does not matter
    other = measure(truth, MeasurementModel(seed=10), 10, scanner)
    assert not np.array_equal(whole, other, equal_nan=True)


def test_dropouts_base_rate_and_grazing() -> None:
    scanner = ScannerConfig(beam_step_deg=0.25)
    model = MeasurementModel(noise_sigma_m=0.0, dropout_rate=0.05, grazing_start_deg=75, seed=1)
    cosines = np.tile(np.cos(np.radians([0.0, 80.0, 89.9])).astype(np.float32), (200, 480))
    truth = TrueProfiles(np.full(cosines.shape, 3.0), cosines)
    measured = measure(truth, model, 0, scanner)
    rates = np.isnan(measured).reshape(200, 480, 3).mean(axis=(0, 1))
    assert rates[0] == pytest.approx(0.05, abs=0.01)
    expected_80 = 0.05 + 0.95 * (np.cos(np.radians(75)) - np.cos(np.radians(80))) / np.cos(
        np.radians(75))
    assert rates[1] == pytest.approx(expected_80, abs=0.02)
    assert rates[2] > 0.99


def test_mixed_pixels_lie_between_the_two_surfaces() -> None:
    scanner = ScannerConfig(beam_step_deg=1.0)
    ranges = np.where(np.arange(360) % 20 < 10, 2.0, 5.0)[None, :].repeat(50, axis=0)
    truth = TrueProfiles(ranges, np.ones(ranges.shape, np.float32))
    model = MeasurementModel(noise_sigma_m=0.0, dropout_rate=0.0, mixed_pixels=True, seed=2)
    measured = measure(truth, model, 0, scanner)
    between = (measured > 2.0 + 1e-6) & (measured < 5.0 - 1e-6)
    assert between.any()
    edges = np.abs(np.diff(ranges, axis=1)) > 0.2
    assert not between[:, :-1][~edges].any()  # only at depth edges
    clean = measure(truth, MeasurementModel(noise_sigma_m=0.0, dropout_rate=0.0), 0, scanner)
    np.testing.assert_array_equal(clean, ranges.astype(np.float32))


def test_sample_times_follow_the_head_rotation() -> None:
    scanner = ScannerConfig(beam_step_deg=0.25, scan_hz=5)
    offsets = sample_time_offsets_s(scanner)
    assert offsets[0] == 0.0
    assert offsets[-1] == pytest.approx(0.2 * 1439 / 1440)


@given(pulses=st.integers(1, 6000), rate=st.floats(50, 5000), accel=st.floats(100, 50_000))
@settings(max_examples=60, deadline=None)
def test_move_follows_the_planners_trapezoid(pulses: int, rate: float, accel: float) -> None:
    move = Move(2.0, 10, pulses, rate, accel)
    assert move.duration_s == move_time_s(pulses, rate, accel)
    times = 2.0 + np.linspace(-0.1, move.duration_s + 0.1, 401)
    steps = move.steps_at(times)
    assert steps[0] == 10 and steps[-1] == pytest.approx(10 + pulses)
    assert np.all(np.diff(steps) >= -1e-9)  # monotonic
    speed = np.diff(steps) / np.diff(times)
    assert speed.max() <= min(rate, math.sqrt(pulses * accel)) * (1 + 1e-6) + 1e-6


def test_timeline_vectorised_equals_per_move_reference() -> None:
    moves = (Move(1.0, 0, 3, 1000, 5000), Move(2.0, 3, 300, 800, 4000),
             Move(3.0, 303, -200, 1000, 5000).stopped_at(3.1))
    timeline = MotorTimeline(moves)
    times = np.linspace(0.0, 4.0, 2001)
    reference = [0.0 if timeline.move_at(t) is None else float(timeline.move_at(t).steps_at(t))
                 for t in times]
    np.testing.assert_allclose(timeline.steps_at(times), reference, atol=1e-9)
    assert timeline.count_at(3.5) == 303 - math.floor(float(moves[2].pulses_done(0.1)))


def test_platform_state_zero_stop_and_angle() -> None:
    platform = PlatformState(pulse_step_deg=0.036, beta_offset_deg=1.0)
    platform.start_move(0.0, 1000, 1000.0, 5000.0)
    assert platform.moving_at(0.5) and not platform.moving_at(1.3)
    count = platform.stop(0.5)
    assert count == platform.count_at(10.0)
    assert float(platform.beta_deg_at(10.0)) == pytest.approx(count * 0.036 + 1.0)
    platform.zero(11.0)
    assert platform.count_at(12.0) == 0
    assert float(platform.beta_deg_at(12.0)) == pytest.approx(count * 0.036 + 1.0)  # physical


def test_rendered_frame_agrees_with_project_points() -> None:
    scene = builtin_room()
    cam = scaled_camera(CameraConfig(distortion=(-0.12, 0.03, 0.001, -0.0005, 0.0),
                                     pose=Pose(translation_m=(0.0, 0.25, 0.0))), 0.25)
    beta = 40.0
    image = render_rgb(scene, cam, beta)
    assert image.shape == (cam.height, cam.width, 3)
    points = scene.sample_surface(20000, seed=4)
    uv, depth = project_points(points, cam, beta)
    inside = (depth > 0.1) & (uv[:, 0] > 2) & (uv[:, 1] > 2) & (uv[:, 0] < cam.width - 3) & (
        uv[:, 1] < cam.height - 3)
    # keep points that are the first surface along their pixel's ray (not hidden)
    origin = platform_rotation(beta) @ np.asarray(cam.pose.translation_m)
    to_point = points[inside] - origin
    dist = np.linalg.norm(to_point, axis=1)
    hits = scene.cast(origin, to_point / dist[:, None])
    visible = np.abs(hits.t_hit_m - dist) < 1e-3
    colors = scene.color_at(hits.triangle_id[visible], hits.barycentric[visible]).astype(int)
    px = np.rint(uv[inside][visible]).astype(int)
    rendered = image[px[:, 1], px[:, 0]].astype(int)
    agree = np.abs(rendered - colors).max(axis=1) <= 2
    assert visible.sum() > 500
    assert agree.mean() > 0.95  # pixels at texture and depth edges may see the neighbour


def test_camera_noise_exposure_and_jpeg() -> None:
    scene = box_room()
    cam = scaled_camera(CameraConfig(), 0.1)
    clean = render_rgb(scene, cam, 0.0)
    noisy = render_rgb(scene, cam, 0.0, CameraModel(noise_sigma=5.0),
                       np.random.default_rng(1)).astype(float)
    assert (noisy - clean).std() == pytest.approx(5.0, rel=0.15)
    darker = render_rgb(scene, cam, 0.0, CameraModel(exposure_gain=0.5))
    assert darker.mean() == pytest.approx(clean.mean() * 0.5, rel=0.02)
    means = [render_rgb(scene, cam, 0.0, CameraModel(exposure_jitter=0.2),
                        np.random.default_rng(i)).mean() for i in range(8)]
    assert np.std(means) / clean.mean() == pytest.approx(0.2, rel=0.6)
    jpeg = encode_jpeg_rgb(clean)
    assert jpeg[:2] == b"\xff\xd8"
