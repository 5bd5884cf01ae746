"""Poisson meshing: the surface of an analytic room, trimmed to what the scanner could see."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.errors import ParameterError
from scanpipe.meshing.poisson import PoissonParams, poisson_mesh, seen_vertices
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.normals import estimate_normals, points_origins, points_xyz
from scanpipe.params import validate

ROOM = BoxRoom(ball_centre_m=(1.5, -0.2, 1.0), ball_radius_m=0.5)


def sphere_points(n: int, radius: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return (directions * radius).astype(np.float32)


def test_visibility_keeps_only_the_measured_range_in_measured_directions() -> None:
    points = sphere_points(40_000, 2.0)
    origins = np.zeros_like(points)
    probe_dirs = sphere_points(500, 1.0, seed=1)
    on_surface = seen_vertices(probe_dirs * 2.01, points, origins, 3.0, 0.05, 0.0)
    in_front = seen_vertices(probe_dirs * 1.5, points, origins, 3.0, 0.05, 0.0)
    behind = seen_vertices(probe_dirs * 2.5, points, origins, 3.0, 0.05, 0.0)
    assert on_surface.all()
    assert not in_front.any()  # the beam passed through there: empty space
    assert not behind.any()  # no beam reached there
    # directions without any return were never seen
    upper = points[points[:, 1] > 0]
    seen = seen_vertices(probe_dirs * 2.0, upper, np.zeros_like(upper), 3.0, 0.05, 0.0)
    assert seen[probe_dirs[:, 1] > 0.2].all()
    assert not seen[probe_dirs[:, 1] < -0.2].any()


@pytest.fixture(scope="module")
def room_scan() -> tuple[pa.Table, np.ndarray]:
    table = scan_table(ROOM, alpha_step_deg=1.5, beta_step_deg=2.0, noise_m=0.003)
    normals, _ = estimate_normals(table)
    return table, normals


def test_poisson_surface_lies_on_the_room(room_scan: tuple[pa.Table, np.ndarray]) -> None:
    table, normals = room_scan
    mesh, report = poisson_mesh(points_xyz(table), normals, points_origins(table), None,
                                PoissonParams(depth=7, point_weight=10.0), (1.5, 2.0))
    assert report["low_density_vertices_removed"] > 0
    distance = ROOM.distance_m(mesh.vertices)
    assert np.mean(distance) < 0.01
    assert np.percentile(distance, 99) < 0.05
    # Poisson overshoots a little at the room's corners; the visibility test allows
    # 5 cm + 1 % of the range (≤ 0.1 m here) beyond the measured surface.
    low, high = np.asarray(ROOM.low_m), np.asarray(ROOM.high_m)
    assert np.all(mesh.vertices > low - 0.1) and np.all(mesh.vertices < high + 0.1)
    assert mesh.colors is None
    centres = mesh.vertices[mesh.faces].mean(axis=1)  # the sensor is at the origin
    facing = np.einsum("ij,ij->i", mesh.face_normals(), -centres) > 0
    assert np.mean(facing) > 0.99


@pytest.mark.slow
def test_unseen_surface_is_removed(room_scan: tuple[pa.Table, np.ndarray]) -> None:
    table, normals = room_scan
    # a scan that skips a wedge of directions (no returns through a "window")
    alpha = table.column("alpha_deg").to_numpy()
    beta = table.column("beta_deg").to_numpy()
    window = (alpha > 60) & (alpha < 100) & (beta > 60) & (beta < 100)
    keep = np.flatnonzero(~window)
    part = table.take(pa.array(keep))
    points, origins = points_xyz(part), points_origins(part)
    params = PoissonParams(depth=7, point_weight=10.0, density_quantile=0.0)
    trimmed, report = poisson_mesh(points, normals[keep], origins, None, params, (1.5, 2.0))
    untrimmed, _ = poisson_mesh(points, normals[keep], origins, None,
                                params.model_copy(update={"remove_unseen": False}), (1.5, 2.0))
    assert report["unseen_vertices_removed"] > 0

    def in_window(vertices: np.ndarray) -> np.ndarray:
        polar = np.degrees(np.arccos(vertices[:, 1] / np.linalg.norm(vertices, axis=1)))
        azimuth = np.degrees(np.arctan2(vertices[:, 2], vertices[:, 0]))
        return (polar > 68) & (polar < 92) & (azimuth > 68) & (azimuth < 92)

    assert np.count_nonzero(in_window(untrimmed.vertices)) > 20  # Poisson closed the window
    assert np.count_nonzero(in_window(trimmed.vertices)) == 0


def test_poisson_carries_colours(room_scan: tuple[pa.Table, np.ndarray]) -> None:
    table, normals = room_scan
    colors = np.tile(np.array([[200, 100, 50]], np.uint8), (table.num_rows, 1))
    mesh, _ = poisson_mesh(points_xyz(table), normals, points_origins(table), colors,
                           PoissonParams(depth=6), (1.5, 2.0))
    assert mesh.colors is not None
    assert np.abs(mesh.colors.astype(int) - [200, 100, 50]).max() <= 2


def test_poisson_parameters_are_checked() -> None:
    with pytest.raises(ParameterError) as err:
        validate(PoissonParams, {"n_threads": 0, "depth": 20, "density_quantile": 1.0})
    message = str(err.value)
    assert "n_threads" in message and "depth" in message and "density_quantile" in message
