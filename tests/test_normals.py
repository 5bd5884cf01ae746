"""Normals: grid cross products and the KNN fallback, always facing each point's sensor."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.errors import StageError
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.normals import (
    NormalParams,
    estimate_normals,
    orient_toward,
    points_origins,
    points_xyz,
)

ROOM = BoxRoom()


def wall_normals(points: np.ndarray, room: BoxRoom) -> tuple[np.ndarray, np.ndarray]:
    """The inward normal of the wall each point lies on, and whether it is clear of corners."""
    low, high = np.asarray(room.low_m), np.asarray(room.high_m)
    gaps = np.concatenate([points - low, high - points], axis=1)  # (N, 6)
    order = np.sort(gaps, axis=1)
    wall = np.argmin(gaps, axis=1)
    inward = np.zeros((len(points), 3))
    axis = wall % 3
    inward[np.arange(len(points)), axis] = np.where(wall < 3, 1.0, -1.0)
    clear = order[:, 1] > 0.6  # the second-nearest wall is far: not near an edge
    return inward, clear


def without_grid(table: pa.Table) -> pa.Table:
    minus_one = pa.array(np.full(table.num_rows, -1, np.int32))
    table = table.set_column(table.schema.get_field_index("profile"), "profile", minus_one)
    return table.set_column(table.schema.get_field_index("sample"), "sample", minus_one)


def test_grid_normals_match_the_walls_and_face_the_sensor() -> None:
    table = scan_table(ROOM, alpha_step_deg=2.0, beta_step_deg=3.0)
    normals, counts = estimate_normals(table)
    points, origins = points_xyz(table), points_origins(table)
    truth, clear = wall_normals(points, ROOM)
    assert counts["grid"] > 0.95 * table.num_rows
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert np.all(np.einsum("ij,ij->i", normals, origins - points) > 0)
    agreement = np.einsum("ij,ij->i", normals, truth)[clear]
    assert np.all(agreement > 0.999)


def test_grid_normals_face_an_offset_sensor() -> None:
    table = scan_table(ROOM, 2.0, 3.0, mount_translation_m=(0.1, 0.2, 0.05), noise_m=0.002)
    normals, _ = estimate_normals(table)
    points, origins = points_xyz(table), points_origins(table)
    assert np.all(np.einsum("ij,ij->i", normals, origins - points) > 0)
    truth, clear = wall_normals(points, ROOM)
    assert np.median(np.einsum("ij,ij->i", normals, truth)[clear]) > 0.99


def test_poles_take_the_window_mean_and_stay_oriented() -> None:
    table = scan_table(ROOM, 2.0, 5.0)
    normals, counts = estimate_normals(table)
    alpha = table.column("alpha_deg").to_numpy()
    on_axis = np.abs(np.sin(np.radians(alpha))) < 1e-6
    assert counts["grid_window"] + counts["knn"] >= np.count_nonzero(on_axis)
    points, origins = points_xyz(table), points_origins(table)
    up_or_down = np.abs(normals[on_axis][:, 1])  # the poles lie on the ceiling and the floor
    assert np.all(up_or_down > 0.99)
    assert np.all(np.einsum("ij,ij->i", normals, origins - points) > 0)


@pytest.mark.slow  # Open3D's KNN on 11 k points: a few seconds on a busy 2-core machine
def test_knn_normals_for_a_cloud_without_grid() -> None:
    table = without_grid(scan_table(ROOM, 2.0, 3.0, noise_m=0.001))
    normals, counts = estimate_normals(table)
    assert counts == {"knn": table.num_rows}
    points, origins = points_xyz(table), points_origins(table)
    truth, clear = wall_normals(points, ROOM)
    # The poles are measured once per profile: a line of copies, where KNN has no surface.
    off_axis = np.abs(np.sin(np.radians(table.column("alpha_deg").to_numpy()))) > 0.2
    assert np.all(np.einsum("ij,ij->i", normals, origins - points) >= 0)
    assert np.all(np.einsum("ij,ij->i", normals, truth)[clear & off_axis] > 0.99)


def test_grid_method_on_a_cloud_without_grid_is_an_error() -> None:
    table = without_grid(scan_table(ROOM, 10.0, 10.0))
    with pytest.raises(StageError, match="no grid"):
        estimate_normals(table, NormalParams(method="grid"))


def test_orient_toward_matches_a_per_point_loop() -> None:
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(200, 3)).astype(np.float32)
    points = rng.normal(size=(200, 3)).astype(np.float32)
    origins = rng.normal(size=(200, 3)).astype(np.float32)
    expected = normals.copy()
    for i in range(len(expected)):
        if float(np.dot(expected[i], origins[i] - points[i])) < 0:
            expected[i] = -expected[i]
    assert np.array_equal(orient_toward(normals.copy(), points, origins), expected)


def test_grid_normals_do_not_depend_on_the_row_order_or_gaps() -> None:
    """Dense grid (a reshape), rows in grid order with gaps (a scatter) and shuffled rows (a
    gather) are three code paths; they must give each point the same normal."""
    table = scan_table(BoxRoom(ball_centre_m=(1.5, 0.0, 1.0)), 2.0, 3.0, noise_m=0.002)
    dense, _ = estimate_normals(table)
    keep = np.random.default_rng(5).random(table.num_rows) > 0.03
    gappy, counts = estimate_normals(table.filter(pa.array(keep)))
    assert counts["grid"] > 0.9 * np.count_nonzero(keep)
    order = np.random.default_rng(6).permutation(table.num_rows)
    shuffled, _ = estimate_normals(table.take(pa.array(order)))
    assert np.array_equal(shuffled, dense[order])
    # Gaps change the neighbours of the cells around them only: most normals stay the same.
    same = np.all(np.isclose(gappy, dense[keep], atol=1e-6), axis=1)
    assert np.count_nonzero(same) > 0.6 * len(same)
    assert np.all(np.einsum("ij,ij->i", gappy, points_origins(table)[keep]
                            - points_xyz(table)[keep]) > 0)


def _window_reference(normals: tuple[np.ndarray, ...], wanted: np.ndarray,
                      size: tuple[int, int], wrap: bool) -> tuple[np.ndarray, ...]:
    """The window fill over the whole grid, as it was written first: a uniform_filter of every
    component, normalised, copied into the wanted cells."""
    from scipy.ndimage import uniform_filter

    modes = ("nearest", "wrap" if wrap else "nearest")
    summed = [uniform_filter(np.nan_to_num(c, nan=0.0), size=size, mode=modes) for c in normals]
    norm = np.sqrt(sum(s * s for s in summed))
    fill = wanted & (norm > 1e-6)
    out = tuple(c.copy() for c in normals)
    for component, mean in zip(out, summed, strict=True):
        np.copyto(component, mean / np.where(norm > 0, norm, 1), where=fill)
    return out


@pytest.mark.parametrize(("alpha_step_deg", "lone_cells"), [(0.5, 40), (1.0, 0), (0.5, 20000)])
def test_window_fill_reads_only_what_it_needs_and_equals_the_whole_grid_filter(
        alpha_step_deg: float, lone_cells: int) -> None:
    """The pole bands (column means), lone cells (their own windows) and many lone cells (the
    whole-grid filter) give what a uniform_filter over the whole grid gives."""
    from scanpipe.grid import scan_grid
    from scanpipe.normals import _fill_from_window, _window_size, grid_normal_planes

    table = scan_table(ROOM, alpha_step_deg, 0.5, profiles=200, noise_m=0.002)
    grid = scan_grid(table)
    assert grid is not None
    planes = tuple(table.column(c).to_numpy().reshape(grid.shape) for c in "xyz")
    normals = grid_normal_planes(planes, grid)
    wanted = np.isnan(normals[0])
    band_columns = np.count_nonzero(wanted.any(axis=0))
    rng = np.random.default_rng(5)
    cells = rng.integers(0, wanted.size, lone_cells)
    for component in normals:  # gaps: a lone cell without a normal
        component.reshape(-1)[cells] = np.nan
    wanted.reshape(-1)[cells] = True
    size = _window_size(grid, 1.0)
    expected = _window_reference(normals, wanted, size, grid.wraps_alpha)
    filled = _fill_from_window(normals, wanted, grid, 1.0)
    assert 0 < band_columns < grid.shape[1] // 4
    assert filled == np.count_nonzero(~np.isnan(expected[0]) & wanted)
    for got, want in zip(normals, expected, strict=True):
        assert np.allclose(got, want, atol=2e-6, equal_nan=True)
