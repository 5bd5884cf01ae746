"""Face normals and areas (scanpipe.texturing.visibility.face_normals, written out in columns)
against the plain (faces, 3, 3) formula: winding, turned to the vertex normals, slivers."""

from __future__ import annotations

import numpy as np

from scanpipe.texturing.visibility import face_normals


def plain(vertices: np.ndarray, faces: np.ndarray, vertex_normals: np.ndarray | None
          ) -> tuple[np.ndarray, np.ndarray]:
    corners = vertices.astype(np.float64)[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(length, 1e-20)[:, None]
    if vertex_normals is not None:
        mean = vertex_normals.astype(np.float64)[faces].sum(axis=1)
        mean_length = np.linalg.norm(mean, axis=1)
        agreement = np.einsum("ij,ij->i", normals, mean)
        normals[agreement < 0] *= -1
        unreliable = (np.abs(agreement) < 0.5 * mean_length) & (mean_length > 1e-12)
        normals[unreliable] = mean[unreliable] / mean_length[unreliable, None]
    return normals, 0.5 * length


def test_face_normals_are_the_plain_formula() -> None:
    rng = np.random.default_rng(7)
    vertices = rng.normal(size=(3000, 3)).astype(np.float32)
    faces = rng.integers(0, len(vertices), size=(8000, 3))
    faces[:50, 2] = faces[:50, 1]  # degenerate: no area, the vertex normals decide
    vertex_normals = rng.normal(size=(len(vertices), 3)).astype(np.float32)
    for given in (None, vertex_normals):
        normals, areas = face_normals(vertices, faces, given)
        expected, expected_areas = plain(vertices, faces, given)
        np.testing.assert_allclose(normals, expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(areas, expected_areas, rtol=1e-12, atol=1e-15)
    # some faces were turned and some (slivers) took the mean: the test covers both
    winding, _ = plain(vertices, faces, None)
    assert (np.einsum("ij,ij->i", normals, winding) < -0.999).sum() > 1000
    assert (np.abs(np.einsum("ij,ij->i", normals, winding)) < 0.999).sum() > 100
