"""Grid triangulation: closed surfaces, depth discontinuities, seam, poles, coverage halves."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.grid import ScanGrid, scan_grid
from scanpipe.meshing.grid_mesh import GridMeshParams, triangulate_grid
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.normals import points_origins, points_xyz

EMPTY_ROOM = BoxRoom()
ROOM_WITH_BALL = BoxRoom(ball_centre_m=(1.5, 0.0, 1.0), ball_radius_m=0.5)


def triangulate(table: pa.Table, **params: object) -> tuple[np.ndarray, np.ndarray, dict]:
    grid = scan_grid(table)
    assert grid is not None
    return triangulate_grid(points_xyz(table), points_origins(table), grid,
                            GridMeshParams.model_validate(params))


def edge_uses(faces: np.ndarray) -> Counter[int]:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return Counter(counts.tolist())


def euler_characteristic(faces: np.ndarray) -> int:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    return len(np.unique(faces)) - len(np.unique(edges, axis=0)) + len(faces)


def facing_sensor(vertices: np.ndarray, origins: np.ndarray, faces: np.ndarray) -> np.ndarray:
    v0, v1, v2 = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    normal = np.cross(v1 - v0, v2 - v0)
    return np.einsum("ij,ij->i", normal, origins[faces[:, 0]] - v0) > 0


def test_a_full_scan_of_a_room_is_one_closed_surface_facing_the_sensor() -> None:
    table = scan_table(EMPTY_ROOM, alpha_step_deg=2.0, beta_step_deg=5.0, noise_m=0.003)
    vertices, faces, report = triangulate(table)
    assert report["seam_closed"] is True
    assert report["faces_broken_at_jumps"] == 0
    assert edge_uses(faces) == Counter({2: edge_uses(faces)[2]})  # every edge twice: closed
    assert euler_characteristic(faces) == 2  # a sphere: no double surface, no hole
    assert np.all(facing_sensor(vertices, points_origins(table), faces))


def test_the_poles_become_one_vertex_each() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, 5.0)
    profiles = round(180 / 5.0)
    _, faces, report = triangulate(table)
    assert report["pole_points_merged"] == 2 * (profiles - 1)
    alpha = table.column("alpha_deg").to_numpy()
    pole_rows = np.flatnonzero(np.isin(alpha, (0.0, 180.0)))
    used_pole_rows = np.intersect1d(np.unique(faces), pole_rows)
    assert len(used_pole_rows) == 2
    # without merging the copies of each pole make zero-area slivers instead
    _, unmerged, report = triangulate(table, merge_poles=False)
    assert report["pole_points_merged"] == 0
    assert len(np.intersect1d(np.unique(unmerged), pole_rows)) == 2 * profiles


def test_without_the_seam_the_surface_is_open_along_the_first_profile() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, 5.0)
    _, faces, report = triangulate(table, close_seam=False)
    assert report["seam_closed"] is False
    samples = round(360 / 2.0)
    assert edge_uses(faces)[1] == 2 * samples  # the first and the last profile, each a loop


def test_a_second_coverage_half_is_not_meshed_twice() -> None:
    half = scan_table(EMPTY_ROOM, 2.0, 5.0)
    full_turn = scan_table(EMPTY_ROOM, 2.0, 5.0, profiles=72)  # 360° of travel
    _, faces_half, _ = triangulate(half)
    _, faces, report = triangulate(full_turn)
    assert report["duplicate_profiles_dropped"] == 36
    assert report["seam_closed"] is True
    assert len(faces) == len(faces_half)
    assert edge_uses(faces) == Counter({2: edge_uses(faces)[2]})
    assert int(np.max(full_turn.column("profile").to_numpy()[np.unique(faces)])) < 36


def test_partial_travel_leaves_the_ends_open() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, 5.0, profiles=18)  # 90° of travel
    vertices, faces, report = triangulate(table)
    assert report["seam_closed"] is False
    assert edge_uses(faces)[1] > 0
    assert np.all(facing_sensor(vertices, points_origins(table), faces))


def test_depth_discontinuities_break_the_mesh() -> None:
    table = scan_table(ROOM_WITH_BALL, 1.0, 2.0, noise_m=0.003)
    vertices, faces, report = triangulate(table)
    assert report["faces_broken_at_jumps"] > 0
    on_ball = np.abs(np.linalg.norm(vertices - np.asarray(ROOM_WITH_BALL.ball_centre_m), axis=1)
                     - ROOM_WITH_BALL.ball_radius_m) < 0.05
    mixed = on_ball[faces].any(axis=1) & ~on_ball[faces].all(axis=1)
    assert not mixed.any()  # no triangle joins the ball to the wall behind it
    assert edge_uses(faces)[1] > 0  # the ball's silhouette is an open boundary
    assert euler_characteristic(faces) == 2  # room with a hole (1) + the ball's cap (1)
    assert np.all(facing_sensor(vertices, points_origins(table), faces))


def test_a_steeply_inclined_surface_stays_connected() -> None:
    # the floor far from the scanner is seen at up to ~75° incidence: no false breaks there
    room = BoxRoom(low_m=(-6.0, -1.2, -6.0), high_m=(6.0, 1.5, 6.0))
    table = scan_table(room, 1.0, 2.0, noise_m=0.003)
    _, faces, report = triangulate(table)
    assert report["faces_broken_at_jumps"] == 0
    assert edge_uses(faces) == Counter({2: edge_uses(faces)[2]})


def test_missing_points_only_remove_the_triangles_that_need_them() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, 5.0)
    rng = np.random.default_rng(1)
    kept = np.sort(rng.choice(table.num_rows, size=table.num_rows - 40, replace=False))
    sparse = table.take(pa.array(kept))
    vertices, faces, _ = triangulate(sparse)
    assert faces.max() < sparse.num_rows
    assert len(faces) < len(triangulate(table)[1])
    assert np.all(facing_sensor(vertices, points_origins(sparse), faces))
    assert edge_uses(faces).keys() <= {1, 2}


def test_an_offset_sensor_keeps_its_poles_apart_and_faces_it() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, 5.0, mount_translation_m=(0.1, 0.0, 0.0))
    vertices, faces, report = triangulate(table)
    assert report["pole_points_merged"] == 0  # the pole points are 0.2 m apart: not one point
    assert np.all(facing_sensor(vertices, points_origins(table), faces))


def reference_faces(table: pa.Table, grid: ScanGrid, params: GridMeshParams) -> set[tuple]:
    """Per-quad loop straight from the rules (no seam, no pole merge, no wrap)."""
    xyz = points_xyz(table).astype(np.float64)
    origins = points_origins(table).astype(np.float64)
    tan_inc = np.tan(np.radians(params.max_incidence_deg))

    def continuous(i: int, j: int) -> bool:
        ri, rj = np.linalg.norm(xyz[i] - origins[i]), np.linalg.norm(xyz[j] - origins[j])
        ui, uj = (xyz[i] - origins[i]) / ri, (xyz[j] - origins[j]) / rj
        return abs(ri - rj) <= min(ri, rj) * np.linalg.norm(ui - uj) * tan_inc + \
            params.jump_allowance_m

    def step(i: int, j: int) -> float:
        return abs(np.linalg.norm(xyz[i] - origins[i]) - np.linalg.norm(xyz[j] - origins[j]))

    faces = set()
    index = grid.index
    for p in range(index.shape[0] - 1):
        for s in range(index.shape[1] - 1):
            a, b, c, d = index[p, s], index[p + 1, s], index[p, s + 1], index[p + 1, s + 1]
            ad = a >= 0 and d >= 0 and continuous(a, d)
            bc = b >= 0 and c >= 0 and continuous(b, c)
            use_ad = step(a, d) <= step(b, c) if ad and bc else ad
            triangles = [(a, b, d), (a, d, c)] if use_ad else [(a, b, c), (b, d, c)]
            for tri in triangles:
                if min(tri) >= 0 and all(continuous(tri[k], tri[(k + 1) % 3]) for k in range(3)):
                    faces.add(tuple(sorted(int(v) for v in tri)))
    return faces


@pytest.mark.parametrize("seed", [0, 1])
def test_vectorised_triangulation_matches_a_per_quad_loop(seed: int) -> None:
    table = scan_table(ROOM_WITH_BALL, 4.0, 6.0, noise_m=0.01, seed=seed,
                       profiles=20)  # 120° of travel: no seam; 4° steps from 0°: poles present
    # cut away the samples on the axis and the wrap, so that the loop needs no special cases
    alpha = table.column("alpha_deg").to_numpy()
    keep = np.flatnonzero((alpha > 0) & (alpha < 180))
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(keep, size=len(keep) - 15, replace=False))
    part = table.take(pa.array(keep))
    part = part.set_column(part.schema.get_field_index("sample"), "sample",
                           pa.array(part.column("sample").to_numpy() - 1))
    grid = scan_grid(part)
    assert grid is not None and not grid.wraps_alpha
    params = GridMeshParams(fill_single_holes=False)  # the loop knows quads only
    _, faces, _ = triangulate_grid(points_xyz(part), points_origins(part), grid, params)
    assert {tuple(sorted(f)) for f in faces.tolist()} == reference_faces(part, grid, params)


def test_a_motor_turning_backwards_still_gives_faces_toward_the_sensor() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, -5.0, profiles=36)  # β = 0°, −5°, … −175°
    vertices, faces, report = triangulate(table)
    assert report["seam_closed"] is True
    assert edge_uses(faces) == Counter({2: edge_uses(faces)[2]})
    assert np.all(facing_sensor(vertices, points_origins(table), faces))


def test_lone_dropouts_are_closed_and_the_room_stays_one_closed_surface() -> None:
    table = scan_table(EMPTY_ROOM, 2.0, 5.0)
    sample = table.column("sample").to_numpy()
    profile = table.column("profile").to_numpy()
    # Lone missing samples away from the poles, the seam and each other.
    lone = (profile % 4 == 2) & (sample % 6 == 3) & (sample > 6) & (sample < 80)
    sparse = table.filter(pa.array(~lone))
    vertices, faces, report = triangulate(sparse)
    assert report["single_holes_filled"] == int(lone.sum()) > 10
    assert edge_uses(faces).keys() == {2}  # no hole left: every edge between two faces
    assert euler_characteristic(faces) == 2
    assert np.all(facing_sensor(vertices, points_origins(sparse), faces))
    _, open_faces, _ = triangulate(sparse, fill_single_holes=False)
    assert 1 in edge_uses(open_faces)


def test_the_defaults_mesh_every_point_whatever_max_vertices_says() -> None:
    from scanpipe.stages.mesh import MeshParams, mesh_points

    table = scan_table(EMPTY_ROOM, 2.0, 2.0)  # 180 samples × 91 profiles
    params = MeshParams.model_validate({"grid": {"max_vertices": 1000}})
    mesh, report = mesh_points(table, params)
    assert report["grid_stride"] == 1 and "points_meshed" not in report
    # Every point but the merged pole copies is a vertex.
    merged = report["triangulation"]["pole_points_merged"]
    assert len(mesh.vertices) == table.num_rows - merged


def test_automatic_stride_keeps_the_mesh_within_max_vertices() -> None:
    from scanpipe.stages.mesh import MeshParams, mesh_points

    table = scan_table(EMPTY_ROOM, 2.0, 2.0)  # 180 samples × 91 profiles
    full, full_report = mesh_points(table, MeshParams())
    assert full_report["method"] == "grid" and full_report["grid_stride"] == 1
    capped = MeshParams.model_validate(
        {"grid": {"stride": 0, "max_vertices": table.num_rows // 3}})
    half, report = mesh_points(table, capped)
    assert report["grid_stride"] == 2  # ceil(sqrt(3))
    assert report["points_meshed"] <= table.num_rows // 3
    assert len(half.faces) < 0.3 * len(full.faces)
    assert edge_uses(half.faces).keys() == {2}  # still one closed room at half resolution


def _with_floating_blocks(table: pa.Table, blocks: int, seed: int) -> pa.Table:
    """Pull square blocks of samples towards the sensor: small pieces cut off by range jumps."""
    rng = np.random.default_rng(seed)
    profile, sample = (table.column(c).to_numpy() for c in ("profile", "sample"))
    scale = np.ones(table.num_rows, np.float32)
    for _ in range(blocks):
        p0, s0 = rng.integers(0, profile.max() - 6), rng.integers(0, sample.max() - 6)
        size = rng.integers(2, 7)
        scale[(profile >= p0) & (profile < p0 + size) & (sample >= s0)
              & (sample < s0 + size)] = rng.uniform(0.3, 0.8)
    for axis, origin in zip("xyz", ("origin_x", "origin_y", "origin_z"), strict=True):
        x, o = table.column(axis).to_numpy(), table.column(origin).to_numpy()
        table = table.set_column(table.schema.get_field_index(axis), axis,
                                 pa.array((o + (x - o) * scale).astype(np.float32)))
    return table


@pytest.mark.parametrize(("noise_m", "merge_poles", "dropouts"),
                         [(0.0, False, 0.05), (0.0, True, 0.0), (0.003, True, 0.02)])
def test_clean_up_on_the_grid_equals_the_per_face_clean_up(noise_m: float, merge_poles: bool,
                                                           dropouts: float) -> None:
    """grid_surface's own clean-up (zero-area faces, small pieces, unused points, all on the
    grid) gives exactly the mesh of triangulate_grid followed by the generic per-face one."""
    from scanpipe.meshing.cleanup import clean_mesh
    from scanpipe.meshing.grid_mesh import grid_surface
    from scanpipe.meshing.mesh import Mesh

    table = _with_floating_blocks(scan_table(ROOM_WITH_BALL, 2.0, 2.0, noise_m=noise_m),
                                  12, seed=3)
    if dropouts:
        keep = np.random.default_rng(1).random(table.num_rows) > dropouts
        table = table.filter(pa.array(keep))
    grid = scan_grid(table)
    assert grid is not None
    points, origins = points_xyz(table), points_origins(table)
    params = GridMeshParams(merge_poles=merge_poles)
    vertices, faces, _ = triangulate_grid(points, origins, grid, params)
    expected, counts = clean_mesh(Mesh(vertices, faces), manifold_by_construction=True)
    assert counts["small_component_faces_removed"] > 0
    if not merge_poles:  # the coincident pole points of a noise-free scan: zero-area faces
        assert counts["degenerate_faces_removed"] > 0
    surface = grid_surface(points, origins, grid, params, min_component_faces=50, compact=True,
                           remove_zero_area=True)
    assert np.array_equal(surface.vertices, expected.vertices)
    assert np.array_equal(surface.faces, expected.faces)
    report = surface.report
    assert report["zero_area_faces_removed"] == counts["degenerate_faces_removed"]
    assert report["small_component_faces_removed"] == counts["small_component_faces_removed"]
    assert report["unreferenced_vertices_removed"] == counts["unreferenced_vertices_removed"]
    assert surface.kept is not None and np.count_nonzero(surface.kept) == len(surface.vertices)


def test_clean_up_on_the_grid_without_small_pieces_keeps_every_face() -> None:
    """A scan without floating pieces: the grid clean-up finds no small piece (its early way
    out) and gives the per-face clean-up's mesh, face for face."""
    from scanpipe.meshing.cleanup import clean_mesh
    from scanpipe.meshing.grid_mesh import grid_surface
    from scanpipe.meshing.mesh import Mesh

    table = scan_table(ROOM_WITH_BALL, 2.0, 2.0, noise_m=0.002)
    grid = scan_grid(table)
    assert grid is not None
    points, origins = points_xyz(table), points_origins(table)
    vertices, faces, _ = triangulate_grid(points, origins, grid)
    expected, counts = clean_mesh(Mesh(vertices, faces), manifold_by_construction=True)
    assert counts["small_component_faces_removed"] == 0
    surface = grid_surface(points, origins, grid, min_component_faces=50, compact=True,
                           remove_zero_area=True)
    assert surface.report["small_component_faces_removed"] == 0
    assert np.array_equal(surface.vertices, expected.vertices)
    assert np.array_equal(surface.faces, expected.faces)


def test_a_sensor_on_the_axis_does_not_move_whatever_the_sign_of_its_zero_origins() -> None:
    """Rotating a zero mount offset gives origins of +0.0 and −0.0: that sensor does not move,
    and the winding check for a moving sensor is not run (a real offset still counts)."""
    from scanpipe.meshing.grid_mesh import _varies

    zeros = np.zeros(1000, np.float32)
    zeros[::3] = -0.0
    assert np.signbit(zeros).any() and not _varies(zeros)
    assert not _varies(np.zeros((10, 3), np.float32)[:, 1])  # a strided column
    moved = zeros.copy()
    moved[500] = 1e-4
    assert _varies(moved)
    assert _varies(np.array([0.0, np.nan], np.float32))
    assert not _varies(np.empty(0, np.float32))
