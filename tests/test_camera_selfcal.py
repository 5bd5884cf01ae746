"""Camera self-calibration: the scan's depth edges against the frames' image edges.

The virtual rig is simulated with the TRUE rig (its cameras render the frames); the fit starts
from a rig whose camera is turned by 2° and moved by 3 cm, as a user's rig would be. The scan is
coarse (fast), so the bars here are looser than the benchmark's (benchmarks/bench_camcal.py).
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest

from scanpipe.camera_selfcal import (
    Alignment,
    camera_with,
    depth_edges,
    edge_distance_map,
    frame_rows,
    image_edges,
)
from scanpipe.cli.main import main
from scanpipe.evaluate import edge_alignment, edge_metrics
from scanpipe.rig import load_rig, rig_to_toml
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_camcal import (
    error_vector,
    perturbed,
    rotation_error_deg,
    video_frames,
    with_camera,
    write_video,
)

OPTIONS = SimOptions(motor_step_deg=1.0, beam_step_deg=0.5, camera_scale=0.2, camera_fps=0.5)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("camcal")
    simulate_direct(folder / "scan.mcap", folder / "truth", OPTIONS)
    assert main(["run", str(folder / "scan.mcap"), "--workdir", str(folder / "w"), "--to",
                 "assemble", "-q"]) == 0
    true_rig = OPTIONS.true_rig()
    wrong = with_camera(true_rig, perturbed(true_rig.camera("cam0"), 0))
    (folder / "wrong.toml").write_text(rig_to_toml(wrong))
    return {"folder": folder, "workdir": folder / "w", "true": true_rig, "wrong": wrong}


# -- pieces, no simulation -------------------------------------------------------------------

def _grid_points(ranges: np.ndarray, alpha_deg: np.ndarray, beta_deg: np.ndarray) -> pa.Table:
    """A gridded points table of a scanner at the origin (α in the x-y plane, β about y)."""
    b, a = np.meshgrid(np.radians(beta_deg), np.radians(alpha_deg), indexing="ij")
    x = ranges * np.sin(a) * np.cos(b)
    y = ranges * np.cos(a)
    z = ranges * np.sin(a) * np.sin(b)
    profiles, samples = ranges.shape
    zero = np.zeros(ranges.size, np.float32)
    return pa.table({
        "x": x.ravel().astype(np.float32), "y": y.ravel().astype(np.float32),
        "z": z.ravel().astype(np.float32), "range_m": ranges.ravel().astype(np.float32),
        "alpha_deg": np.degrees(a).ravel(), "beta_deg": np.degrees(b).ravel(),
        "time_ns": np.zeros(ranges.size, np.int64),
        "profile": np.repeat(np.arange(profiles), samples).astype(np.int32),
        "sample": np.tile(np.arange(samples), profiles).astype(np.int32),
        "origin_x": zero, "origin_y": zero, "origin_z": zero})


def test_depth_edges_find_a_jump_between_the_cells_and_no_edge_on_a_flat_wall() -> None:
    alpha = np.arange(60.0, 120.0, 0.5)
    beta = np.arange(0.0, 20.0, 0.5)
    ranges = np.full((beta.size, alpha.size), 3.0)
    ranges[:, alpha >= 90.0] = 2.0  # a step at α = 90°: a nearer surface beyond it
    edges = depth_edges(_grid_points(ranges, alpha, beta))
    assert edges.occluding.sum() == beta.size and not (~edges.occluding).any()
    jump = edges.xyz[edges.occluding]
    # the nearer range, halfway between the two beams (89.75°): not the nearer cell's 90°
    angle = np.degrees(np.arctan2(np.hypot(jump[:, 0], jump[:, 2]), jump[:, 1]))
    assert np.allclose(angle, 89.75, atol=1e-3)
    assert np.allclose(np.linalg.norm(jump, axis=1), 2.0, atol=1e-6)
    # the edge runs across the profiles (about the turntable's axis): its line is horizontal
    assert np.all(np.abs(edges.tangent[:, 1]) < 0.05)


def test_depth_edges_drop_isolated_points() -> None:
    alpha = np.arange(60.0, 120.0, 0.5)
    beta = np.arange(0.0, 20.0, 0.5)
    ranges = np.full((beta.size, alpha.size), 3.0)
    ranges[10, 60] = 2.0  # one stray return: jumps both ways, but on no edge line
    # a small box in front of the wall: its jumps are edges
    ranges[20:30, 30:40] = 2.5
    edges = depth_edges(_grid_points(ranges, alpha, beta))
    b, a = np.radians(beta[10]), np.radians(alpha[60])
    stray = np.array([np.sin(a) * np.cos(b), np.cos(a), np.sin(a) * np.sin(b)])
    directions = edges.xyz / np.linalg.norm(edges.xyz, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(directions @ stray, -1, 1))).min() > 0.6
    assert edges.occluding.sum() >= 20 and not (~edges.occluding).any()
    assert np.allclose(np.linalg.norm(edges.tangent, axis=1), 1.0)


def test_image_edges_are_placed_to_a_fraction_of_a_pixel() -> None:
    # a vertical step at x = 30.3 (area-sampled: the pixel it crosses is mixed), and one at
    # y = 20.7 in another channel
    image = np.zeros((40, 60, 3), np.uint8)
    image[:, 31:, 0] = 200
    image[:, 30, 0] = round(200 * 0.7)
    found = image_edges(image)
    vertical = np.abs(found.normal[:, 0]) > 0.99
    assert vertical.sum() >= 30
    rows = found.uv[vertical, 1]
    middle = (rows > 5) & (rows < 35)
    assert np.allclose(found.uv[vertical][middle, 0], 29.8, atol=0.15)  # pixel centres at k
    assert found.distance[:, 29:31].min() == 0 and found.distance[20, 5] >= 20
    # a sharp step between two pixels is placed halfway, not on either pixel
    sharp = np.zeros((40, 60), np.uint8)
    sharp[21:] = 180
    rows = image_edges(sharp).uv[:, 1]
    assert np.allclose(rows[(rows > 0)], 20.5, atol=0.1)


def test_the_distance_map_is_centred_on_the_edge_not_on_cannys_side() -> None:
    """Canny marks the pixel before a step on both axes; a distance map of its pixels put
    every straight edge half a pixel up and to the left (a turn of the camera the coarse
    passes then made). The map's zero now straddles the sub-pixel edge."""
    from scipy.ndimage import gaussian_filter

    for step in ("vertical", "horizontal"):
        image = np.zeros((64, 64), np.uint8)
        if step == "vertical":
            image[:, 32:] = 200  # the step lies at u = 31.5
        else:
            image[32:] = 200
        found = image_edges(image)
        profile = found.distance[32, 26:38] if step == "vertical" else found.distance[26:38, 32]
        assert profile.tolist() == profile[::-1].tolist(), step  # symmetric about 31.5
        assert profile[5] == profile[6] == 0.0
        blurred = gaussian_filter(found.distance, 1.0)
        line = blurred[32, 26:38] if step == "vertical" else blurred[26:38, 32]
        assert np.allclose(line, line[::-1], atol=1e-5), step


def test_depth_edges_find_a_crease() -> None:
    alpha = np.arange(30.0, 150.0, 0.5)
    beta = np.arange(0.0, 10.0, 0.5)
    # a corner: the plane y = 1 (ceiling) meets the plane x = 1 (wall) at α = 45°
    a = np.radians(alpha)
    wall = 1.0 / np.sin(a)
    ceiling = 1.0 / np.abs(np.cos(a))
    r = np.where(alpha < 45.0, ceiling, wall)
    ranges = np.tile(np.minimum(r, 10.0), (beta.size, 1))
    edges = depth_edges(_grid_points(ranges, alpha, beta))
    creases = edges.xyz[~edges.occluding]
    assert len(creases) >= beta.size
    # every crease point lies on the corner line (x = y = 1 in the β = 0 plane, turned)
    horizontal = np.hypot(creases[:, 0], creases[:, 2])
    assert np.allclose(horizontal, 1.0, atol=0.01) and np.allclose(creases[:, 1], 1.0, atol=0.01)


def test_a_crease_between_a_grazing_and_a_facing_surface_is_placed_on_the_corner() -> None:
    """The ceiling y = 3 seen head-on meets the wall x = 1 seen at a grazing 71°: the peak of
    the turn lies off the corner, always to the same side for such a corner (the grazing arm
    spans more space per cell): the crease is placed where the arms' lines meet instead (the
    peak alone put them up to 14 mm off, a bias that tilted the camera)."""
    alpha = np.arange(2.0, 60.0, 0.25) + 0.1  # the corner (α = 18.43°) between two cells
    beta = np.arange(0.0, 10.0, 0.5)
    a = np.radians(alpha)
    r = np.minimum(1.0 / np.sin(a), 3.0 / np.cos(a))
    ranges = np.tile(r, (beta.size, 1))
    edges = depth_edges(_grid_points(ranges, alpha, beta))
    creases = edges.xyz[~edges.occluding]
    assert len(creases) >= beta.size
    horizontal = np.hypot(creases[:, 0], creases[:, 2])
    assert np.abs(horizontal - 1.0).max() < 0.002 and np.abs(creases[:, 1] - 3.0).max() < 0.002


def test_edge_distance_map_sees_a_colour_edge_of_equal_brightness() -> None:
    image = np.zeros((40, 60, 3), np.uint8)
    image[:, :30] = (200, 40, 100)  # BGR, grey ≈ 76
    image[:, 30:] = (30, 100, 70)  # grey ≈ 83
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert abs(int(grey[0, 0]) - int(grey[0, 59])) < 10
    assert not cv2.Canny(grey, 40, 120, L2gradient=True).any()
    distance = edge_distance_map(image)
    assert distance[:, 29:31].min() == 0 and distance[20, 5] >= 20


def test_alignment_figures() -> None:
    figures = edge_alignment(np.array([0.5, 1.0, 1.5, 3.0, np.nan]))
    assert figures == {"edge_median_px": 1.25, "edge_within_2px": 0.75, "edge_points": 4}
    assert edge_alignment(np.zeros(0))["edge_median_px"] is None
    matched = Alignment.of(np.array([0.5, 1.0, 50.0]), 10.0)
    assert matched.as_dict()["edge_points"] == 3 and matched.unmatched == 1
    assert matched.median_px == 0.75


def test_frame_rows_take_still_frames_first_when_asked() -> None:
    times = np.arange(100) * 1_000_000_000
    table = pa.table({"camera_id": ["c"] * 100, "log_time_ns": times})
    even = frame_rows(table, "c", 8)
    assert even.tolist() == np.round(np.linspace(0, 99, 8)).astype(int).tolist()
    rows = frame_rows(table, "c", 8, (times[10], times[90]))
    assert sum(r < 10 for r in rows) == 2 and sum(r > 90 for r in rows) == 2 and len(rows) == 8
    # with the clock's window: also frames where the platform starts and stops (a stepping
    # platform repeats itself every step; only those tell a clock one step off from a turn)
    rows = frame_rows(table, "c", 16, (times[10], times[90]), 3_000_000_000)
    assert len(rows) == 16 and len(set(rows.tolist())) == 16
    assert sum(r < 7 for r in rows) == 2 and sum(r > 93 for r in rows) == 2
    assert sum(7 <= r <= 13 for r in rows) == 2 and sum(87 <= r <= 93 for r in rows) == 2


def test_the_line_passes_use_every_visible_edge_not_the_distance_maps_subset() -> None:
    """The point-to-line passes start on every edge point the frames see, not on the subset
    the last distance map kept within its truncation at ITS minimum: that subset agrees with
    that minimum, and the line passes stayed near it (lab scale, Full-HD: the map ended 0.57°
    off along the tilt–height valley and the line passes stopped at 0.20°; on every visible
    point 0.04°). Here a dolly–zoom valley, exactly flat for a wall facing the camera: a far
    ring of edges, 6.4 px off at the valley's start, is all that tells it from the truth."""
    from scipy.optimize import brentq

    from scanpipe.camera import camera_pose_in_rig, project_points
    from scanpipe.camera_selfcal import (
        CameraFit,
        DepthEdges,
        FrameObservation,
        MotorTrack,
        _distance_to,
        _final_fit,
        _line_passes,
    )

    rig = SimOptions().true_rig()  # cam0 at 540 × 960, 754 px focal length
    cam = rig.camera("cam0")
    rotation, origin = camera_pose_in_rig(cam, 0.0)

    def lifted(u: np.ndarray, v: np.ndarray, depth_m: float) -> np.ndarray:
        x, y = (u - cam.cx) / cam.fx * depth_m, (v - cam.cy) / cam.fy * depth_m
        return (rotation @ np.stack([x, y, np.full_like(x, depth_m)])).T + origin

    run = np.linspace(0.0, 1.0, 400)
    width, height = cam.width, cam.height
    parts, tangents = [], []
    for u0 in width * np.array([0.15, 0.5, 0.85]):  # a wall 1.5 m away: a grid of edges
        parts.append(lifted(np.full(run.size, u0), height * (0.05 + 0.9 * run), 1.5))
        tangents.append(np.tile(rotation[:, 1], (run.size, 1)))
    for v0 in height * np.array([0.1, 0.3, 0.5, 0.7, 0.9]):
        parts.append(lifted(width * (0.05 + 0.9 * run), np.full(run.size, v0), 1.5))
        tangents.append(np.tile(rotation[:, 0], (run.size, 1)))
    near = sum(len(p) for p in parts)
    radius = 0.4 * min(width, height)
    for phi in np.radians(np.arange(0, 360, 30)):  # short arcs 4 m away, around the centre
        angle = phi + np.linspace(-0.1, 0.1, 60)
        arc = lifted(cam.cx + radius * np.cos(angle), cam.cy + radius * np.sin(angle), 4.0)
        along = np.gradient(arc, axis=0)
        parts.append(arc)
        tangents.append(along / np.linalg.norm(along, axis=1, keepdims=True))
    xyz, tangent = np.concatenate(parts), np.concatenate(tangents)
    edges = DepthEdges(xyz, np.zeros(len(xyz), bool), xyz, tangent)
    uv, _ = project_points(xyz, cam, 0.0)
    ahead, _ = project_points(xyz + 0.001 * tangent, cam, 0.0)
    direction = (ahead - uv) / np.linalg.norm(ahead - uv, axis=1, keepdims=True)
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    frames = [FrameObservation(cam, 0, _distance_to(uv, (height, width)), uv, normal)
              for _ in range(2)]
    motor = pa.table({"log_time_ns": np.array([0, 10**9], np.int64),
                      "step_count": np.zeros(2, np.int64)})
    fit = CameraFit(edges, frames, MotorTrack(motor, rig), ["tz_m", "focal_scale"])

    def wall_spread(scale: float, tz_m: float) -> float:  # the wall's grid grown (+) or shrunk
        moved, _ = project_points(xyz[:near], camera_with(cam, fit.full(
            np.array([tz_m / 0.005, (scale - 1.0) / 0.001]))), 0.0)
        return float(np.sum((moved - uv[:near])[:, 0] * np.sign(uv[:near, 0] - cam.cx)))

    tz_m = 0.07  # moved along the view, zoomed so that the wall fits exactly
    scale = brentq(lambda s: wall_spread(s, tz_m), 0.7, 1.3)
    start = np.array([tz_m / 0.005, (scale - 1.0) / 0.001])
    moved, _ = project_points(xyz[near:], camera_with(cam, fit.full(start)), 0.0)
    assert np.hypot(*(moved - uv[near:]).T) == pytest.approx(6.4, abs=0.1)
    level, gate_px = (1.0, 5.0), 4.0  # the map's truncation 5 px, the first line gate 8 px
    fit.select_visible(fit.full(start), gate_px=level[1])  # as the distance maps leave it
    stuck, _ = _final_fit(fit, start, gate_px, level, True)
    assert fit.full(stuck)[5] == pytest.approx(tz_m, abs=0.005)  # the biased estimator
    fit.select_visible(fit.full(start), gate_px=level[1])
    x, _, other = _line_passes(fit, start, gate_px, level)
    assert fit.full(x)[5] == pytest.approx(0.0, abs=1e-4)
    assert fit.full(x)[6] == pytest.approx(1.0, abs=1e-4)
    assert fit.full(other)[5] == pytest.approx(tz_m, abs=0.005)  # the map's subset's end


def test_an_edge_line_between_two_profiles_shares_one_placement_and_one_cell() -> None:
    """A vertical silhouette between two profiles: every sample along it is placed with ONE
    error (the same fraction of a motor step), so its points form one line, and each point
    carries the cell (the two beams apart at its range) it lies anywhere within."""
    alpha = np.arange(60.0, 120.0, 0.5)
    beta = np.arange(0.0, 20.0, 0.5)
    ranges = np.full((beta.size, alpha.size), 3.0)
    ranges[beta >= 10.0, :] = 2.0  # a nearer surface from β = 10°: a silhouette at 9.75°
    edges = depth_edges(_grid_points(ranges, alpha, beta))
    jump = edges.occluding
    assert jump.sum() == alpha.size and np.unique(edges.line[jump]).size == 1
    assert edges.line[jump][0] >= 0
    # one cell across the profiles at 2 m: 2 m × 0.5° about the axis
    cell = np.linalg.norm(edges.cell[jump], axis=1) / np.hypot(edges.xyz[jump, 0],
                                                               edges.xyz[jump, 2])
    assert np.allclose(cell, np.radians(0.5), rtol=1e-3)
    assert np.all(np.abs(edges.cell[jump, 1]) < 1e-6)  # about the axis, not up or down
    # a horizontal edge (across the samples of a profile) changes its elevation along it, and
    # its placement error with it: each point on its own
    ranges = np.full((beta.size, alpha.size), 3.0)
    ranges[:, alpha >= 90.0] = 2.0
    edges = depth_edges(_grid_points(ranges, alpha, beta))
    assert edges.occluding.all() and np.all(edges.line == -1)
    assert np.unique(edges.line_ids()).size == len(edges.xyz)


def _silhouettes(offset_cells: np.ndarray, points: tuple[int, ...]) -> tuple[Any, ...]:
    """Vertical silhouettes on a wall 2 m in front of cam0, each of ``points`` edge points
    placed ``offset_cells`` of a 1 cm cell sideways (the scan's placement error); the frames'
    image edges where the true silhouettes are."""
    from scanpipe.camera import camera_pose_in_rig, project_points
    from scanpipe.camera_selfcal import CameraFit, DepthEdges, FrameObservation, MotorTrack

    rig = SimOptions().true_rig()
    cam = rig.camera("cam0")
    rotation, origin = camera_pose_in_rig(cam, 0.0)
    parts, lines = [], []
    for k, n in enumerate(points):
        u0 = cam.width * (0.1 + 0.8 * k / (len(points) - 1))
        v = cam.height * np.linspace(0.1, 0.9, n)
        x, y = (u0 - cam.cx) / cam.fx * 2.0, (v - cam.cy) / cam.fy * 2.0
        parts.append((rotation @ np.stack([np.full(n, x), y, np.full(n, 2.0)])).T + origin)
        lines.append(np.full(n, k))
    true = np.concatenate(parts)
    line = np.concatenate(lines)
    tangent = np.tile(rotation[:, 1], (len(true), 1))
    cell = np.tile(0.01 * rotation[:, 0], (len(true), 1))
    uv, _ = project_points(true, cam, 0.0)
    normal = np.tile([1.0, 0.0], (len(true), 1))
    motor = pa.table({"log_time_ns": np.array([0, 10**9], np.int64),
                      "step_count": np.zeros(2, np.int64)})
    track = MotorTrack(motor, rig)

    def fit_for(offsets: np.ndarray) -> Any:
        xyz = true + offsets[line][:, None] * cell
        edges = DepthEdges(xyz, np.ones(len(xyz), bool), xyz, tangent, cell, line)
        frames = [FrameObservation(cam, 0, np.zeros((cam.height, cam.width), np.float32), uv,
                                   normal) for _ in range(2)]
        fit = CameraFit(edges, frames, track, ["rot_y_deg"])
        fit.select_visible(fit.full(np.zeros(1)))
        return fit

    return fit_for(offset_cells), fit_for


def test_a_long_silhouette_counts_as_one_line_not_as_its_many_points() -> None:
    """The scan places a silhouette's points with one shared error; counted point by point, a
    long one seen by many frames outweighed the room and the pan followed where the scan
    happened to sample it (benchmark, 0.25° steps: one silhouette held 190 of cam0's 436
    motor-direction edge points, 0.39 of a step off). Weighed by line, it counts as one."""
    from scanpipe.camera_selfcal import _final_fit, _weigh_edge_lines

    offsets = np.zeros(7)
    offsets[3] = 0.45  # the long one in the middle, nearly half a cell off
    fit, _ = _silhouettes(offsets, (30, 30, 30, 600, 30, 30, 30))
    level, gate_px = (1.0, 5.0), 4.0
    per_point, _ = _final_fit(fit, np.zeros(1), gate_px, level, True)
    _weigh_edge_lines(fit, np.zeros(1))
    per_line, _ = _final_fit(fit, np.zeros(1), gate_px, level, True)
    # 1 cm at 2 m is 0.29°: the long line alone pulls the pan 0.45 × 0.29° × 600 / 780
    assert abs(fit.full(per_point)[1]) == pytest.approx(0.099, abs=0.01)  # the old estimator
    assert abs(fit.full(per_line)[1]) < 0.35 * abs(fit.full(per_point)[1])


def test_the_placement_sigma_covers_the_scans_sampling_of_its_edge_lines() -> None:
    """Each edge line off by a uniform fraction of a cell (one draw per line, shared by its
    points and every frame): the spread of the fitted pan over many such draws is what the
    placement 1σ reports (the curvature counts every point as independent and reads far
    less)."""
    from scanpipe.camera_selfcal import (
        _UNITS,
        _curvature_sigma,
        _final_fit,
        _placement_sigma,
        _weigh_edge_lines,
    )

    counts = (20, 80, 40, 300, 60, 20, 120)
    level, gate_px = (1.0, 5.0), 4.0
    spreads = []
    for by_line in (False, True):  # point by point (the fit's default) and weighed by line
        rng = np.random.default_rng(5)
        pans, sigmas, curvatures = [], [], []
        for _ in range(40):
            fit, _ = _silhouettes(rng.uniform(-0.5, 0.5, len(counts)), counts)
            if by_line:
                _weigh_edge_lines(fit, np.zeros(1))
            x, result = _final_fit(fit, np.zeros(1), gate_px, level, True)
            pans.append(fit.full(x)[1])
            sigmas.append(float(_placement_sigma(fit, x, gate_px)[0] * _UNITS[1]))
            curvatures.append(float(_curvature_sigma(result)[0] * _UNITS[1]))
        spread = float(np.std(pans, ddof=1))
        assert np.median(sigmas) == pytest.approx(spread, rel=0.3)
        assert np.median(curvatures) < 0.2 * spread  # blind to the scan's sampling
        spreads.append(spread)
    assert spreads[1] < spreads[0]  # weighed by line, the pan spreads less


# -- on the virtual rig ----------------------------------------------------------------------

@pytest.mark.slow
def test_calibrate_cameras_recovers_a_wrong_mount(scan: dict[str, Any],
                                                  cli: Callable[..., Any]) -> None:
    folder = scan["folder"]
    rig_before = _digest(folder / "wrong.toml")
    result = cli("calibrate-cameras", scan["workdir"], "--rig", folder / "wrong.toml",
                 "--camera", "cam0", "--write", folder / "fixed.toml", "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    cam = report["cameras"][0]
    assert cam["camera_id"] == "cam0" and report["written"] == str(folder / "fixed.toml")
    fixed = load_rig(folder / "fixed.toml").camera("cam0")
    true = scan["true"].camera("cam0")
    assert rotation_error_deg(scan["wrong"].camera("cam0"), true) == pytest.approx(2.0)
    # this coarse scan (1° motor steps, 0.19° per pixel) leaves the depth along the view and
    # the focal length undetermined (kept at the rig's, 3 cm and 2 % off) and the tilt takes
    # their errors: within 0.7°, and every rotation axis within 3σ or reported not determined
    # (never a confident wrong number)
    assert rotation_error_deg(fixed, true) < 0.7
    errors = error_vector(fixed, true)
    for p, error in zip(cam["parameters"][:3], errors[:3], strict=True):
        assert not p["observable"] or abs(error) <= 3 * p["sigma"] + 0.02, cam
        # a rotation the data pin no better than 0.1° (at 2σ) is said to be so, by name
        if p["observable"] and 2 * p["sigma"] > 0.1:
            assert any(f"{p['name']} is known only to ±{p['sigma']:.3f}°" in w
                       for w in cam["warnings"]), cam["warnings"]
            assert f"{p['name']} is known only to" in result.err
    before, after = cam["alignment_before"], cam["alignment_after"]
    assert after["edge_median_px"] < before["edge_median_px"]
    assert after["edge_within_2px"] > before["edge_within_2px"]
    assert {p["name"] for p in cam["parameters"]} == {
        "rot_x_deg", "rot_y_deg", "rot_z_deg", "tx_m", "ty_m", "tz_m", "focal_scale"}
    # the covariance says which values trade: a tilt against a height at one distance
    correlation = cam["correlation"]
    assert correlation["names"] == [p["name"] for p in cam["parameters"]]
    matrix = np.array(correlation["matrix"])
    assert np.allclose(matrix, matrix.T) and np.allclose(np.diag(matrix), 1.0)
    names = correlation["names"]
    assert matrix[names.index("rot_x_deg"), names.index("ty_m")] > 0.8
    assert all(abs(t["correlation"]) >= 0.9 for t in cam["trade_offs"])
    assert _digest(folder / "wrong.toml") == rig_before  # the input rig is never rewritten
    # the other camera keeps its values
    assert load_rig(folder / "fixed.toml").camera("cam1") == scan["wrong"].camera("cam1")
    # the text output names the values, their 1σ and the alignment
    text = cli("calibrate-cameras", scan["workdir"], "--rig", folder / "wrong.toml",
               "--camera", "cam0", "--frames", "8")
    assert text.code == 0, text.err
    assert "rot_y_deg" in text.out and "±" in text.out and "edges: median" in text.out


@pytest.mark.slow
def test_calibrating_the_true_rig_changes_little(scan: dict[str, Any]) -> None:
    """Started from the true rig, the fit stays near it (an unbiased estimator): on this coarse
    scan (1° motor steps, where an occlusion boundary is placed to ±0.5°) within 0.35°."""
    from scanpipe.artifacts import read_artifact
    from scanpipe.camera_selfcal import calibrate_cameras

    w = scan["workdir"]
    tables = {n: read_artifact(p)[0] for n, p in (
        ("points", w / "assemble" / "points.parquet"), ("frames", w / "decode" / "frames.parquet"),
        ("motor", w / "decode" / "motor.parquet"))}
    result = calibrate_cameras(tables["points"], tables["frames"], tables["motor"], scan["true"],
                               ["cam0"], max_frames=24)[0]
    true = scan["true"].camera("cam0")
    assert rotation_error_deg(result.after, true) < 0.35
    assert np.linalg.norm(np.subtract(result.after.pose.translation_m,
                                      true.pose.translation_m)) < 0.03
    assert result.alignment_after.median_px is not None
    assert result.alignment_after.median_px <= result.alignment_before.median_px + 0.05


@pytest.mark.slow
def test_calibrate_cameras_finds_a_video_clock_offset(scan: dict[str, Any]) -> None:
    from scanpipe.artifacts import read_artifact
    from scanpipe.camera_selfcal import calibrate_cameras

    w = scan["workdir"]
    points = read_artifact(w / "assemble" / "points.parquet")[0]
    motor = read_artifact(w / "decode" / "motor.parquet")[0]
    true_cam = scan["true"].camera("cam0")
    frames = video_frames(OPTIONS, true_cam, 24, 0.5)  # stamped 0.5 s late
    result = calibrate_cameras(points, frames, motor, scan["true"], ["cam0"],
                               fit_time_offset=True, max_frames=24)[0]
    assert result.time_offset_s is not None
    # read from the video's motion around the platform's start and stop (30 fps there):
    # within the 20 ms, the mount fitted at that clock
    assert result.time_offset_s == pytest.approx(-0.5, abs=0.02)
    assert result.motion_clock is not None and result.motion_clock["determined"]
    offset = next(p for p in result.parameters if p.name == "time_offset_s")
    assert offset.observable and offset.sigma is not None and offset.sigma <= 0.02
    assert result.time_offset_determined is True
    assert result.report()["motion_clock"]["offset_s"] == result.time_offset_s
    assert rotation_error_deg(result.after, true_cam) < 0.5
    assert not any("clock offset is not determined" in w for w in result.warnings)


def test_coarse_basins_keep_a_rival_valley_and_merge_wiggles() -> None:
    from scanpipe.camera_selfcal import _coarse_basins

    t = np.linspace(-1.0, 1.0, 101)
    # two valleys (a clock offset and a turn about the axis trading off): both kept, best first
    two = 10 - 8 * np.exp(-((t + 0.5) / 0.1) ** 2) - 7.5 * np.exp(-((t - 0.3) / 0.1) ** 2)
    assert [round(float(t[i]), 2) for i in _coarse_basins(two)] == [-0.5, 0.3]
    # a far shallower second valley does not compete
    shallow = 10 - 8 * np.exp(-((t + 0.5) / 0.1) ** 2) - 1.0 * np.exp(-((t - 0.3) / 0.1) ** 2)
    assert _coarse_basins(shallow) == [int(np.argmin(shallow))]
    # ripples along one valley are one basin
    one = (t + 0.5) ** 2 + 0.01 * np.sin(t * 80)
    assert _coarse_basins(one) == [int(np.argmin(one))]


def test_pick_basin_names_rivals_that_fit_alike() -> None:
    from scanpipe.camera_selfcal import _pick_basin

    pick, rivals = _pick_basin(np.array([-0.13, -0.50]), np.array([1.00, 0.70]))
    assert pick == 1 and rivals.size == 0  # the final cost decides
    pick, rivals = _pick_basin(np.array([-0.13, -0.50]), np.array([1.00, 1.02]))
    assert pick == 0 and rivals.tolist() == [1]  # alike: a rival
    pick, rivals = _pick_basin(np.array([-0.50, -0.49]), np.array([1.00, 1.00]))
    assert rivals.size == 0  # the same basin reached twice


def _video_fit_inputs(scan: dict[str, Any]) -> tuple[pa.Table, pa.Table, pa.Table]:
    from scanpipe.artifacts import read_artifact

    w = scan["workdir"]
    points = read_artifact(w / "assemble" / "points.parquet")[0]
    motor = read_artifact(w / "decode" / "motor.parquet")[0]
    return points, video_frames(OPTIONS, scan["true"].camera("cam0"), 24, 0.5), motor


@pytest.mark.slow
def test_a_wrong_clock_basin_is_refined_and_loses(scan: dict[str, Any],
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import scanpipe.camera_selfcal as selfcal

    points, frames, motor = _video_fit_inputs(scan)
    found = selfcal._coarse_basins

    def wrong_first(costs: np.ndarray) -> list[int]:
        # the coarse scan settles 0.42 s off (benchmark seed 2), the right valley second
        best = found(costs)[0]
        return [best + 21 if best + 21 < len(costs) else best - 21, best]

    monkeypatch.setattr(selfcal, "_coarse_basins", wrong_first)
    result = selfcal.calibrate_cameras(points, frames, motor, scan["true"], ["cam0"],
                                       fit_time_offset=True, max_frames=24,
                                       clock_from_motion=False)[0]
    assert result.time_offset_s == pytest.approx(-0.5, abs=0.1)
    assert result.time_offset_determined is True
    assert not any("clock offset is not determined" in w for w in result.warnings)


@pytest.mark.slow
def test_two_clock_basins_that_fit_alike_leave_the_offset_undetermined(
        scan: dict[str, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    import scanpipe.camera_selfcal as selfcal

    points, frames, motor = _video_fit_inputs(scan)
    found = selfcal._coarse_basins

    def two(costs: np.ndarray) -> list[int]:
        best = found(costs)[0]
        return [best, best + 21 if best + 21 < len(costs) else best - 21]

    monkeypatch.setattr(selfcal, "_coarse_basins", two)
    # data that cannot tell the two apart: both basins' final costs alike
    monkeypatch.setattr(selfcal, "_basin_score", lambda *args: 1.0)
    result = selfcal.calibrate_cameras(points, frames, motor, scan["true"], ["cam0"],
                                       fit_time_offset=True, max_frames=24,
                                       clock_from_motion=False)[0]
    offset = next(p for p in result.parameters if p.name == "time_offset_s")
    assert result.time_offset_determined is False
    assert any("clock offset is not determined" in w for w in result.warnings)
    # the 1σ covers both basins (the second, refined, ends some 0.3 s away; over the limit:
    # the start offset kept, never a confident wrong number)
    assert offset.sigma is not None and offset.sigma >= 0.2
    assert not offset.observable and result.time_offset_s == 0.0
    assert result.report()["time_offset_determined"] is False
    # the mount was fitted at that kept offset: its turn about the axis is not known either
    # (benchmark seeds 3 and 5 once reported mounts 2° and 6° off as determined)
    turns = {p.name: p.observable for p in result.parameters}
    assert not any(turns[n] for n in ("rot_x_deg", "rot_y_deg", "rot_z_deg"))
    assert any("neither is the mount's turn" in w for w in result.warnings)


@pytest.mark.slow
def test_eval_reports_the_edge_figures(scan: dict[str, Any]) -> None:
    figures = edge_metrics(scan["workdir"])
    assert figures["edge_points"] > 100
    assert figures["edge_median_px"] is not None and figures["edge_median_px"] < 2.0
    assert figures["edge_within_2px"] is not None and figures["edge_within_2px"] > 0.5
    # every camera is measured, the 360° one too, each on its own
    cameras = figures["edge_cameras"]
    assert set(cameras) == {"cam0", "cam1", "cam360"}
    assert cameras["cam360"]["edge_points"] > 100
    assert cameras["cam360"]["edge_median_px"] < 2.0
    assert sum(c["edge_points"] for c in cameras.values()) == figures["edge_points"]


def test_calibrate_cameras_refuses_bad_input_and_keeps_files(
        tmp_path: Path, cli: Callable[..., Any]) -> None:
    empty = tmp_path / "w"
    empty.mkdir()
    result = cli("calibrate-cameras", empty)
    assert result.code == 2
    assert "no points artifact" in result.err and result.err.count("\n") == 1
    missing = cli("calibrate-cameras", tmp_path / "nope")
    assert missing.code == 2 and "not a folder" in missing.err
    existing = tmp_path / "rig2.toml"
    existing.write_text("keep me")
    refused = cli("calibrate-cameras", empty, "--write", existing)
    assert refused.code == 2 and "--force" in refused.err
    assert existing.read_text() == "keep me"


@pytest.mark.slow
def test_calibrate_cameras_names_an_unknown_camera(scan: dict[str, Any],
                                                   cli: Callable[..., Any]) -> None:
    result = cli("calibrate-cameras", scan["workdir"], "--camera", "nope")
    assert result.code == 2
    assert "no camera 'nope'" in result.err and "cam0, cam1" in result.err


@pytest.mark.slow
def test_import_video_refines_a_rough_offset(scan: dict[str, Any], tmp_path: Path,
                                             cli: Callable[..., Any]) -> None:
    rec = tmp_path / "scan.mcap"
    rec.write_bytes((scan["folder"] / "scan.mcap").read_bytes())
    video = tmp_path / "phone.avi"
    first_ns = write_video(OPTIONS, scan["true"].camera("cam0"), video, fps=1.0)
    # the phone's clock says its first frame came 0.5 s later than it did
    result = cli("import-video", video, "--into", rec, "--start-time", str(first_ns),
                 "--offset", "0.5", "--camera", "cam0", "--refine", "--json",
                 "--replace")  # the simulated cam0 frames: the video stands in for them
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["offset_s"] == pytest.approx(0.0, abs=0.1)
    assert report["first_time_ns"] == pytest.approx(first_ns, abs=0.1e9)
    assert report["refined"]["alignment_after"]["edge_median_px"] < 2.0


@pytest.mark.slow
def test_import_video_refuses_to_refine_without_still_frames(
        scan: dict[str, Any], tmp_path: Path, cli: Callable[..., Any]) -> None:
    rec = tmp_path / "scan.mcap"
    rec.write_bytes((scan["folder"] / "scan.mcap").read_bytes())
    digest = _digest(rec)
    video = tmp_path / "phone.avi"
    # a video of a platform that never stands still in it: frames only while it turns
    options = OPTIONS.model_copy()
    first_ns = write_video(options, scan["true"].camera("cam0"), video, fps=1.0)
    trimmed = tmp_path / "moving.avi"
    capture = cv2.VideoCapture(str(video))
    writer = cv2.VideoWriter(str(trimmed), cv2.VideoWriter_fourcc(*"MJPG"), 1.0,
                             (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
                              int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))))
    index = 0
    total = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    while True:
        ok, image = capture.read()
        if not ok:
            break
        if 6 <= index < total - 6:
            writer.write(image)
        index += 1
    writer.release()
    capture.release()
    result = cli("import-video", trimmed, "--into", rec, "--start-time",
                 str(first_ns + 6_000_000_000), "--camera", "cam0", "--refine", "--replace")
    assert result.code == 1
    assert "standing still" in result.err and result.err.count("\n") == 1
    assert _digest(rec) == digest


@pytest.mark.slow
def test_a_360_camera_mount_is_recovered(scan: dict[str, Any]) -> None:
    """The default rig's 360° (equirect) camera, turned by 2° and moved by 3 cm, is calibrated
    like a pinhole one (no focal length: its scale is the sphere's), and says how sure it is:
    each rotation axis is within 3σ of the truth or reported not determined. (This coarse scan,
    1° motor steps and frames of 2.1 px/°, leaves it about a degree off; see
    docs/calibration.md, "Cameras".)"""
    from scanpipe.artifacts import read_artifact
    from scanpipe.camera_selfcal import calibrate_cameras

    w = scan["workdir"]
    tables = {n: read_artifact(p)[0] for n, p in (
        ("points", w / "assemble" / "points.parquet"), ("frames", w / "decode" / "frames.parquet"),
        ("motor", w / "decode" / "motor.parquet"))}
    true = scan["true"].camera("cam360")
    assert true.model == "equirect"
    wrong = with_camera(scan["true"], perturbed(true, 0))
    result = calibrate_cameras(tables["points"], tables["frames"], tables["motor"], wrong,
                               ["cam360"], max_frames=8)[0]
    assert rotation_error_deg(wrong.camera("cam360"), true) == pytest.approx(2.0)
    assert rotation_error_deg(result.after, true) < 1.2, result.report()
    assert {p.name for p in result.parameters} == {
        "rot_x_deg", "rot_y_deg", "rot_z_deg", "tx_m", "ty_m", "tz_m"}
    assert result.after.fx == true.fx
    errors = error_vector(result.after, true)
    for p, error in zip(result.parameters[:3], errors[:3], strict=True):
        assert not p.observable or abs(error) <= 3 * (p.sigma or 0.0) + 0.02, result.report()
    before, after = result.alignment_before, result.alignment_after
    assert after.median_px is not None and before.median_px is not None
    assert after.median_px < before.median_px


# -- the clock from the video's own motion ---------------------------------------------------

_T0_NS = 1_700_000_000_000_000_000


def _stepping_track() -> Any:
    """A platform that stands still for 2 s, makes 12 moves of 7 pulses (60 ms each) every
    0.4 s, and stands still again; states every 20 ms as a controller reports them."""
    from scanpipe.camera_selfcal import MotorTrack

    times_s = np.arange(0.0, 9.0, 0.02)
    since = times_s - 2.0
    moves = np.clip(np.floor(since / 0.4), -1, 11)
    within = np.clip((since - np.maximum(moves, 0) * 0.4) / 0.06, 0.0, 1.0)
    steps = np.where(since < 0, 0, np.round(7 * (moves + np.where(moves >= 11, 1.0, within))))
    motor = pa.table({"log_time_ns": (_T0_NS + np.round(times_s * 1e9)).astype(np.int64),
                      "step_count": steps.astype(np.int64)})
    return MotorTrack(motor, OPTIONS.true_rig())


def _moving_frames(track: Any, times_s: np.ndarray, late_s: float) -> tuple[np.ndarray, list]:
    """Grey frames of a textured wall turning with the platform (20 px per degree), taken at
    ``times_s`` and stamped ``late_s`` late."""
    from scanpipe.camera_selfcal import motion_grey

    rng = np.random.default_rng(7)
    wall = cv2.GaussianBlur(rng.uniform(0, 255, (120, 200)).astype(np.float32), (0, 0), 1.5)
    true_ns = (_T0_NS + np.round(times_s * 1e9)).astype(np.int64)
    frames = []
    for beta in track.beta_deg(true_ns):
        shift = np.float32([[1, 0, -20.0 * beta], [0, 1, 0]])
        image = cv2.warpAffine(wall, shift, (160, 120), flags=cv2.INTER_LINEAR)
        noisy = np.clip(image + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
        frames.append(motion_grey(noisy))
    return true_ns + np.int64(round(late_s * 1e9)), frames


def test_motion_clock_reads_the_offset_from_the_start_and_stop() -> None:
    from scanpipe.camera_selfcal import motion_clock

    track = _stepping_track()
    assert track.step_period_s() == pytest.approx(0.4, abs=0.021)
    # a 30 fps video around the start (2 s) and the stop (6.46 s), its clock 0.5 s late and
    # its frames at a phase of their own
    times = np.concatenate([np.arange(0.6, 3.4, 1 / 30), np.arange(5.1, 7.9, 1 / 30)]) + 0.013
    stamps, frames = _moving_frames(track, times, 0.5)
    clock = motion_clock(stamps, frames, track, 0.0, 1.0)
    assert clock is not None and clock.determined
    assert clock.offset_s == pytest.approx(-0.5, abs=0.02)
    assert 0.0 < clock.sigma_s <= 0.02 and clock.score > clock.rival_score + 0.1
    assert 0 < clock.moving_pairs < clock.pairs
    # the offset's search window around a rough value
    clock = motion_clock(stamps, frames, track, -0.3, 0.5)
    assert clock is not None and clock.offset_s == pytest.approx(-0.5, abs=0.02)


def test_motion_clock_needs_close_frames_and_the_start_or_stop() -> None:
    from scanpipe.camera_selfcal import motion_clock

    track = _stepping_track()
    # one frame a second (a camera, not a video): no pairs to compare
    sparse = np.arange(0.5, 8.5, 1.0)
    stamps, frames = _moving_frames(track, sparse, 0.5)
    assert motion_clock(stamps, frames, track, 0.0, 1.0) is None
    # a video of the steady stepping only: it repeats every step period, a clock one period
    # off fits alike — reported, never as determined
    steady = np.arange(3.0, 5.5, 1 / 30) + 0.013
    stamps, frames = _moving_frames(track, steady, 0.5)
    clock = motion_clock(stamps, frames, track, 0.0, 1.0)
    assert clock is not None and not clock.determined


def test_sample_video_also_reads_every_frame_near_the_start_and_stop(tmp_path: Path) -> None:
    from scanpipe.acquire.video_import import sample_video

    video = tmp_path / "phone.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    rng = np.random.default_rng(3)
    for _ in range(150):  # 5 s
        writer.write(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    writer.release()
    start = _T0_NS
    still = (start + 1_000_000_000, start + 4_000_000_000)  # the platform turns 1 s … 4 s
    chosen, moving = sample_video(video, start, 10, still, 200_000_000, 300_000_000)
    assert len(chosen) == 10 and chosen[0][1].shape == (48, 64, 3)
    times = np.array([t for t, _ in moving])
    # every frame within 0.3 s of the start and of the stop, as small grey images
    near = [t for t in start + np.round(np.arange(150) / 30 * 1e9).astype(np.int64)
            if min(abs(t - still[0]), abs(t - still[1])) <= 300_000_000]
    assert len(times) == len(near) and np.allclose(times, near, atol=2e6)
    assert moving[0][1].ndim == 2 and moving[0][1].dtype == np.float32
    # without a reach, none
    assert sample_video(video, start, 10, still, 200_000_000)[1] == []


def test_a_determined_motion_clock_over_its_limit_is_not_reported_as_used() -> None:
    """A clock the motion determines with a 1σ over the clock's limit is not used (the edge
    fit is): its report says so (``trusted``), and calibrate-cameras does not label the fitted
    offset as the motion's."""
    from scanpipe.camera_selfcal import SIGMA_LIMITS, MotionClock

    wide = MotionClock(0.1, 0.1, 0.1, 40, 10, 0.8, 0.3, True,
                       bootstrap_s=2 * SIGMA_LIMITS["time_offset_s"])
    assert wide.determined and not wide.trusted
    assert wide.as_dict()["determined"] and not wide.as_dict()["trusted"]
    narrow = MotionClock(0.1, 0.1, 0.1, 40, 10, 0.8, 0.3, True, bootstrap_s=0.005)
    assert narrow.as_dict()["trusted"]


def test_unknown_correlations_are_null_not_independent() -> None:
    """A singular curvature gives NaN correlations: reported as None (JSON null), never as a
    0 that reads "uncorrelated", and no trade-off is claimed from them."""
    from types import SimpleNamespace

    from scanpipe.camera_selfcal import (
        CameraCalibration,
        _known_correlations,
        _parameter_correlation,
    )

    singular = SimpleNamespace(jac=np.array([[1.0, 2.0], [2.0, 4.0], [3.0, 6.0]]))
    matrix = _known_correlations(_parameter_correlation(singular))
    assert matrix == [[None, None], [None, None]]
    known = _known_correlations(_parameter_correlation(
        SimpleNamespace(jac=np.array([[1.0, 1.0], [1.0, 1.01], [1.0, 0.99]]))))
    assert known[0][0] == 1.0 and known[0][1] is not None
    report = SimpleNamespace(correlation_names=["a", "b"], correlation=matrix)
    assert CameraCalibration.trade_offs(report) == []  # type: ignore[arg-type]
