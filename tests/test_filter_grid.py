"""The filters, one by one, on small assembled grids with known defects, and mark mode."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from scan_tables import make_rig, positions_scan

from scanpipe.errors import ParameterError
from scanpipe.geometry import platform_rotation, scan_plane_direction
from scanpipe.params import validate
from scanpipe.rig import Rig
from scanpipe.stages import assemble
from scanpipe.stages.filter import STAGE, FilterParams

ALL_OFF = {name: {"enabled": False} for name in (
    "no_return", "range_gate", "depth_edges", "grid_median", "smoothing", "double_coverage",
    "statistical_outlier", "voxel")}


def only(**settings: dict[str, object]) -> FilterParams:
    """Parameters with every filter off except the ones given."""
    data: dict[str, object] = {**ALL_OFF}
    for name, values in settings.items():
        data[name] = {"enabled": True, **values}
    return validate(FilterParams, data)


def assembled(ranges: np.ndarray, rig: Rig, steps: list[int]) -> pa.Table:
    return assemble.STAGE.run(positions_scan(rig, steps, ranges)).tables["points"]


def wall_scan(noise_m: float = 0.0, seed: int = 0) -> tuple[pa.Table, np.ndarray]:
    """A 20 × 36 grid of ranges (2° × 2°... in α 10°) with a nearer block in the middle."""
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=10.0)
    ranges = np.full((20, 36), 4.0)
    ranges[:, 12:18] = 2.0  # a box in front: depth edges at samples 11|12 and 17|18
    ranges += np.random.default_rng(seed).normal(0, noise_m, ranges.shape)
    return assembled(ranges, rig, list(range(20))), ranges


def taken(report: dict[str, object], name: str) -> int:
    return int(report["filters"][name]["taken"])  # type: ignore[index]


def test_no_return_and_range_gate_count_exactly() -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=30.0)
    ranges = np.full((4, 12), 3.0)
    ranges[0, :3] = np.nan
    ranges[1, :2] = 0.2
    ranges[2, 5] = 300.0
    points = assembled(ranges, rig, [0, 1, 2, 3])
    result = STAGE.run({"points": points},
                       only(no_return={}, range_gate={"min_range_m": 0.5, "max_range_m": 250}))
    assert taken(result.report, "no_return") == 3
    assert taken(result.report, "range_gate") == 3
    assert result.tables["points"].num_rows == 48 - 6
    assert result.report["points_out"] == 42


def test_depth_edges_take_the_far_side_of_a_jump_and_nothing_on_smooth_surfaces() -> None:
    points, _ = wall_scan()
    result = STAGE.run({"points": points}, only(depth_edges={}))
    out = result.tables["points"]
    samples = set(out.column("sample").to_pylist())
    assert {11, 18}.isdisjoint(samples)  # the far neighbours of the block's edges
    assert {12, 17, 10, 19}.issubset(samples)  # the block itself and the wall beyond
    assert taken(result.report, "depth_edges") == 2 * 20
    both = STAGE.run({"points": points}, only(depth_edges={"remove": "both"}))
    assert taken(both.report, "depth_edges") == 4 * 20


def test_depth_edges_catch_a_mixed_pixel() -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=2.0)
    ranges = np.full((5, 180), 4.0)
    ranges[:, 60:80] = 2.0
    ranges[:, 80] = 3.0  # between foreground and background: a mixed pixel
    points = assembled(ranges, rig, [0, 1, 2, 3, 4])
    out = STAGE.run({"points": points}, only(depth_edges={})).tables["points"]
    assert 80 not in set(out.column("sample").to_pylist())


def test_noise_alone_is_no_depth_edge() -> None:
    points, _ = wall_scan(noise_m=0.01)
    flat = points.filter(pa.compute.less(points.column("sample"), 10))
    result = STAGE.run({"points": flat}, only(depth_edges={}))
    assert taken(result.report, "depth_edges") == 0


def test_grid_median_removes_a_spike_or_replaces_it() -> None:
    points, ranges = wall_scan(noise_m=0.005)
    spiked = ranges.copy()
    spiked[7, 3] += 0.8
    points = assembled(spiked, make_rig(pulse_step_deg=2.0, beam_step_deg=10.0), list(range(20)))
    removed = STAGE.run({"points": points}, only(grid_median={}))
    assert taken(removed.report, "grid_median") == 1
    assert (7, 3) not in set(zip(removed.tables["points"].column("profile").to_pylist(),
                                 removed.tables["points"].column("sample").to_pylist(),
                                 strict=True))
    replaced = STAGE.run({"points": points}, only(grid_median={"action": "replace"}))
    r = replaced.tables["points"].column("range_m").to_numpy().reshape(20, 36)
    assert abs(r[7, 3] - 4.0) < 0.03
    # Moved along its beam: the direction from the origin is unchanged.
    x = replaced.tables["points"].column("x").to_numpy().reshape(20, 36)
    x0 = points.column("x").to_numpy().reshape(20, 36)
    assert x[7, 3] / x0[7, 3] == pytest.approx(r[7, 3] / spiked[7, 3], rel=1e-5)


def test_grid_median_takes_isolated_points() -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=30.0)
    ranges = np.full((5, 12), np.nan)
    ranges[2, 5] = 3.0
    ranges[0:2, 0:4] = 3.0
    points = assembled(ranges, rig, list(range(5)))
    result = STAGE.run({"points": points}, only(no_return={}, grid_median={}))
    assert result.report["filters"]["grid_median"]["isolated"] == 1
    assert result.tables["points"].num_rows == 8


def test_smoothing_reduces_noise_and_keeps_edges() -> None:
    points, _ = wall_scan(noise_m=0.01, seed=4)
    result = STAGE.run({"points": points},
                       only(smoothing={"radius": 2, "sigma_cells": 1.5, "sigma_range_m": 0.03}))
    before = points.column("range_m").to_numpy().reshape(20, 36)
    after = result.tables["points"].column("range_m").to_numpy().reshape(20, 36)
    inner = (slice(3, 17), slice(24, 34))
    assert np.std(after[inner]) < 0.6 * np.std(before[inner])
    # The two sides of an edge do not bleed into each other.
    assert np.all(np.abs(after[:, 11] - 4.0) < 0.05)
    assert np.all(np.abs(after[:, 12] - 2.0) < 0.05)
    assert result.tables["points"].num_rows == points.num_rows
    assert result.report["filters"]["smoothing"]["moved"] > 0


def plane_scan(translation: tuple[float, float, float]) -> pa.Table:
    """360° of travel in 10° steps over the plane y = −1 (a floor), scanner offset from the axis."""
    rig = make_rig(pulse_step_deg=10.0, beam_step_deg=10.0, translation_m=translation)
    steps = list(range(36))
    alphas = np.arange(36) * 10.0
    ranges = np.full((36, 36), np.nan)
    for p, step in enumerate(steps):
        rot = platform_rotation(step * 10.0)
        origin = rot @ np.asarray(translation)
        directions = scan_plane_direction(alphas) @ rot.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (-1.0 - origin[1]) / directions[:, 1]
        ranges[p] = np.where((t > 0) & (t < 8), t, np.nan)
    return assembled(ranges, rig, steps)


def test_double_coverage_keep_merge_best() -> None:
    points = plane_scan((0.3, 0.0, 0.0))
    keep = STAGE.run({"points": points}, only(no_return={}, double_coverage={"action": "keep"}))
    pairs = keep.report["filters"]["double_coverage"]["pairs"]
    assert pairs > 100 and taken(keep.report, "double_coverage") == 0
    merge = STAGE.run({"points": points}, only(no_return={}, double_coverage={"action": "merge"}))
    assert taken(merge.report, "double_coverage") == pairs
    best = STAGE.run({"points": points}, only(no_return={}, double_coverage={"action": "best"}))
    assert taken(best.report, "double_coverage") == pairs
    # The kept view of each pair meets the floor (normal +y) more steeply.
    out = best.tables["points"]
    dropped = set(zip(keep.tables["points"].column("profile").to_pylist(),
                      keep.tables["points"].column("sample").to_pylist(), strict=True)) - set(
        zip(out.column("profile").to_pylist(), out.column("sample").to_pylist(), strict=True))
    table = keep.tables["points"]
    cos = np.abs(table.column("y").to_numpy() - table.column("origin_y").to_numpy()) / \
        table.column("range_m").to_numpy()
    lookup = dict(zip(zip(table.column("profile").to_pylist(), table.column("sample").to_pylist(),
                          strict=True), cos, strict=True))
    right = 0
    for p, s in dropped:
        partner = ((p + 18) % 36, (36 - s) % 36)
        if partner in lookup and lookup[partner] >= lookup[(p, s)] - 1e-6:
            right += 1
    assert right >= 0.9 * len(dropped)


def test_double_coverage_needs_more_than_180_degrees() -> None:
    points, _ = wall_scan()  # 38° of travel
    result = STAGE.run({"points": points}, only(double_coverage={"action": "merge"}))
    assert result.report["filters"]["double_coverage"]["pairs"] == 0


def test_voxel_keeps_one_point_per_voxel_nearest_its_centroid() -> None:
    rng = np.random.default_rng(2)
    xyz = rng.uniform(0, 1, (2000, 3)).astype(np.float32)
    table = cloud_without_grid(xyz)
    result = STAGE.run({"points": table}, only(voxel={"size_m": 0.25}))
    out = result.tables["points"]
    assert out.num_rows == len(np.unique(np.floor(xyz / 0.25), axis=0))
    kept = np.stack([out.column(c).to_numpy() for c in "xyz"], axis=1)
    keys = np.floor(kept / 0.25)
    for key, point in zip(keys[:20], kept[:20], strict=True):
        members = xyz[np.all(np.floor(xyz / 0.25) == key, axis=1)]
        centroid = members.mean(axis=0)
        nearest = members[np.argmin(np.linalg.norm(members - centroid, axis=1))]
        np.testing.assert_allclose(point, nearest)


def cloud_without_grid(xyz: np.ndarray) -> pa.Table:
    from scanpipe.pointio import points_table

    return points_table(xyz.astype(np.float64), None, (0.0, 0.0, 0.0))


def test_statistical_outliers_only_without_a_grid_by_default() -> None:
    rng = np.random.default_rng(5)
    cluster = rng.normal(0, 0.05, (500, 3)) + np.array([2.0, 0.0, 0.0])
    outliers = np.array([[2.0, 3.0, 0.0], [5.0, 5.0, 5.0], [-3.0, 1.0, 2.0]])
    table = cloud_without_grid(np.concatenate([cluster, outliers]))
    result = STAGE.run({"points": table})
    out = result.tables["points"]
    assert result.report["grid"] is None
    assert set(result.report["skipped"]) == {"depth_edges", "grid_median", "double_coverage",
                                             "smoothing", "range_gate"}
    x = out.column("x").to_numpy()
    assert not np.any(x > 4.0) and not np.any(x < 0)
    assert taken(result.report, "statistical_outlier") >= 3
    gridded, _ = wall_scan()
    report = STAGE.run({"points": gridded}).report
    assert "statistical_outlier" in report["skipped"]


def test_mark_mode_keeps_every_row_and_names_the_filter() -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=30.0)
    ranges = np.full((4, 12), 3.0)
    ranges[0, :3] = np.nan
    ranges[1, :2] = 0.2
    points = assembled(ranges, rig, [0, 1, 2, 3])
    marked = STAGE.run({"points": points}, FilterParams(mode="mark"))
    out = marked.tables["points"]
    assert out.num_rows == points.num_rows
    names = out.column("filtered_by").to_pylist()
    assert names.count("no_return") == 3 and names.count("range_gate") == 2
    assert names.count(None) == marked.report["kept"] == 43
    removed = STAGE.run({"points": points}, FilterParams())
    assert removed.tables["points"].num_rows == 43
    # A marked table filtered again: the earlier marks count as taken and are kept.
    again = STAGE.run({"points": out}, FilterParams(mode="mark"))
    assert again.report["previously_marked"] == 5
    assert again.tables["points"].column("filtered_by").to_pylist() == names
    dropped = STAGE.run({"points": out}, FilterParams())
    assert dropped.tables["points"].num_rows == 43
    assert "filtered_by" not in dropped.tables["points"].column_names


def test_parameters_are_validated_together() -> None:
    with pytest.raises(ParameterError) as err:
        validate(FilterParams, {"mode": "delete", "voxel": {"size_m": -1},
                                "range_gate": {"min_range_m": 5, "max_range_m": 1},
                                "depth_edge": {}})
    message = str(err.value)
    assert "mode" in message and "voxel.size_m" in message
    assert "max_range_m (1.0) must be greater" in message and "depth_edges" in message


def _bilateral_reference(grid: np.ndarray, radius: int, sigma_cells: float,
                         sigma_range_m: float, relative: float, wrap: bool) -> np.ndarray:
    """bilateral_smooth straight from its formula, one cell and one neighbour at a time."""
    profiles, samples = grid.shape
    out = np.full_like(grid, np.nan, dtype=np.float64)
    for p in range(profiles):
        for s in range(samples):
            centre = float(grid[p, s])
            if np.isnan(centre):
                continue
            sigma_r = sigma_range_m + relative * centre
            total = weights = 0.0
            for dp in range(-radius, radius + 1):
                for ds in range(-radius, radius + 1):
                    q, t = p + dp, s + ds
                    if wrap:
                        t %= samples
                    if not (0 <= q < profiles and 0 <= t < samples) or np.isnan(grid[q, t]):
                        continue
                    value = float(grid[q, t])
                    weight = (np.exp(-(dp * dp + ds * ds) / (2 * sigma_cells ** 2))
                              * np.exp(-((value - centre) ** 2) / (2 * sigma_r ** 2)))
                    total += weight * value
                    weights += weight
            out[p, s] = total / weights
    return out


@pytest.mark.parametrize(("shape", "radius", "relative", "wrap"), [
    ((9, 12), 1, 0.0, False), ((9, 12), 1, 0.0, True), ((7, 5), 2, 0.0, True),
    ((6, 3), 3, 0.0, True), ((8, 10), 2, 0.01, True), ((5, 6), 1, 0.02, False)])
def test_bilateral_smoothing_matches_a_per_cell_loop(shape: tuple[int, int], radius: int,
                                                     relative: float, wrap: bool) -> None:
    """The padded views and the shared pair weights give the per-cell formula: NaN cells,
    the grid's ends, the wrap of a 360° profile (even one narrower than the window) and a
    range-dependent σ_r."""
    from scanpipe.grid import bilateral_smooth

    rng = np.random.default_rng(sum(shape) + radius)
    grid = (2.0 + rng.normal(0, 0.01, shape) + 0.05 * (rng.random(shape) < 0.2)).astype(
        np.float32)
    grid[rng.random(shape) < 0.15] = np.nan
    got = bilateral_smooth(grid, radius, 1.3, 0.02, relative, wrap_samples=wrap)
    expected = _bilateral_reference(grid, radius, 1.3, 0.02, relative, wrap)
    assert np.array_equal(np.isnan(got), np.isnan(grid))
    assert np.allclose(got, expected, atol=2e-6, equal_nan=True)
