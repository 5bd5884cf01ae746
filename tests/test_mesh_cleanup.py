"""Mesh clean-up: degenerate, duplicate and non-manifold faces, small pieces, decimation."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from scanpipe.meshing.cleanup import (
    CleanupParams,
    clean_mesh,
    degenerate_faces,
    duplicate_faces,
    non_manifold_faces,
    small_component_faces,
)
from scanpipe.meshing.mesh import Mesh


def grid_sheet(n: int, offset: float = 0.0) -> Mesh:
    """A flat n × n vertex sheet in the z = offset plane, two triangles per cell."""
    xs, ys = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.full(n * n, offset, np.float32)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                            np.stack([a, d, c], -1).reshape(-1, 3)]).astype(np.int32)
    return Mesh(vertices, faces)


def join(*meshes: Mesh) -> Mesh:
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
                .astype(np.int32))


def test_degenerate_faces_are_repeated_indices_or_zero_area() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 3], [0, 0, 3], [0, 1, 2], [1, 3, 1]], np.int32)
    assert degenerate_faces(Mesh(vertices, faces)).tolist() == [False, True, True, True]


def test_duplicate_faces_keep_the_first_of_any_winding() -> None:
    faces = np.array([[0, 1, 2], [2, 1, 0], [1, 2, 0], [0, 1, 3], [3, 1, 0]], np.int32)
    assert duplicate_faces(faces).tolist() == [False, True, True, False, True]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6), st.integers(0, 6)),
                min_size=1, max_size=60))
def test_duplicate_faces_match_a_set_based_loop(rows: list[tuple[int, int, int]]) -> None:
    seen: set[tuple[int, ...]] = set()
    expected = []
    for row in rows:
        key = tuple(sorted(row))
        expected.append(key in seen)
        seen.add(key)
    assert duplicate_faces(np.array(rows, np.int32)).tolist() == expected


def test_an_edge_with_three_faces_loses_the_smallest() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 0.1]],
                        np.float32)
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]], np.int32)  # edge 0–1 three times
    drop = non_manifold_faces(Mesh(vertices, faces))
    assert drop.tolist() == [False, False, True]
    assert not non_manifold_faces(grid_sheet(5)).any()


def test_small_pieces_are_removed() -> None:
    big, small = grid_sheet(10), grid_sheet(3, offset=5.0)
    mesh = join(big, small)
    drop = small_component_faces(mesh, min_faces=50)
    assert np.count_nonzero(drop) == len(small.faces)
    assert drop[len(big.faces):].all()


def test_clean_mesh_reports_what_each_step_removed() -> None:
    mesh = join(grid_sheet(10), grid_sheet(2, offset=3.0))
    extra = np.array([[0, 1, 20], [20, 1, 0], [0, 0, 5]], np.int32)
    dirty = Mesh(mesh.vertices, np.concatenate([mesh.faces, extra]))
    cleaned, report = clean_mesh(dirty, CleanupParams(min_component_faces=10))
    assert report["degenerate_faces_removed"] == 1
    assert report["duplicate_faces_removed"] == 1
    assert report["small_component_faces_removed"] == 2
    assert report["unreferenced_vertices_removed"] == 4
    assert report["faces_out"] == len(cleaned.faces) == len(dirty.faces) - 4 - \
        report["non_manifold_faces_removed"]
    assert cleaned.faces.max() < len(cleaned.vertices)


def test_decimation_reaches_the_target_and_keeps_the_shape() -> None:
    sheet = grid_sheet(40)
    cleaned, report = clean_mesh(sheet, CleanupParams(target_faces=300))
    assert len(cleaned.faces) <= 300
    assert report["faces_removed_by_decimation"] == len(sheet.faces) - len(cleaned.faces)
    assert np.allclose(cleaned.vertices[:, 2], 0.0, atol=1e-5)  # still the flat sheet
    lo, hi = cleaned.vertices.min(axis=0), cleaned.vertices.max(axis=0)
    assert np.allclose(lo[:2], 0.0, atol=1e-4) and np.allclose(hi[:2], 39.0, atol=1e-4)


def test_vertex_normals_follow_the_winding() -> None:
    sheet = grid_sheet(4).with_vertex_normals()
    assert sheet.normals is not None
    assert np.allclose(sheet.normals, [0.0, 0.0, 1.0], atol=1e-6)
