"""Mesh clean-up and simplification, vectorised.

Open3D has each of these operations, but on a lab-scale grid mesh (≈ 5 M faces) its duplicate
and non-manifold removal take 5–25 s and its connected components ~40 s; the numpy versions
below (sorts and a sparse connected-components call) take well under a second each. Only the
quadric decimation is Open3D's.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import StageError
from scanpipe.meshing.mesh import Mesh
from scanpipe.params import Params

I64 = NDArray[np.int64]
B = NDArray[np.bool_]


class CleanupParams(Params):
    """What the clean-up removes, and the decimation target."""

    remove_degenerate: bool = Field(True, description="faces with a repeated vertex or no area")
    remove_duplicates: bool = Field(True, description="faces over the same three vertices")
    remove_non_manifold: bool = Field(
        True, description="faces beyond the two largest on an edge shared by more than two")
    min_component_faces: int = Field(
        50, ge=0, description="drop connected pieces with fewer faces (0 keeps all)")
    target_faces: int | None = Field(
        None, ge=4, description="quadric decimation down to this many faces (none: keep all)")


def degenerate_faces(mesh: Mesh) -> B:
    """Faces with a repeated vertex index or zero area."""
    f = mesh.faces
    repeated = f[:, 0] == f[:, 1]
    repeated |= f[:, 1] == f[:, 2]
    repeated |= f[:, 0] == f[:, 2]
    cross = mesh.face_normals()
    area2 = cross[:, 0] * cross[:, 0]
    area2 += cross[:, 1] * cross[:, 1]
    area2 += cross[:, 2] * cross[:, 2]
    repeated |= ~(area2 > 0)  # NaN corners count as degenerate too
    return np.asarray(repeated, dtype=bool)


def duplicate_faces(faces: NDArray[np.integer]) -> B:
    """Faces over the same vertex set as an earlier face (any winding)."""
    ordered = np.sort(faces.astype(np.int64), axis=1)
    order = np.lexsort((ordered[:, 2], ordered[:, 1], ordered[:, 0]))
    sorted_rows = ordered[order]
    same_as_previous = np.zeros(len(faces), dtype=bool)
    same_as_previous[1:] = (sorted_rows[1:] == sorted_rows[:-1]).all(axis=1)
    duplicate = np.zeros(len(faces), dtype=bool)
    duplicate[order] = same_as_previous
    return duplicate


def _edge_keys(faces: NDArray[np.integer], n_vertices: int) -> I64:
    """One int64 key per directed face edge, ``(3K,)``, the same for both directions."""
    f = faces.astype(np.int64)
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    return np.asarray(np.minimum(a, b) * n_vertices + np.maximum(a, b), dtype=np.int64)


def non_manifold_faces(mesh: Mesh) -> B:
    """Faces to drop so that no edge has more than two faces: all but the two largest."""
    n_faces = len(mesh.faces)
    drop = np.zeros(n_faces, dtype=bool)
    if n_faces == 0:
        return drop
    keys = _edge_keys(mesh.faces, len(mesh.vertices))
    sorted_keys = np.sort(keys)
    crowded = np.unique(sorted_keys[2:][sorted_keys[2:] == sorted_keys[:-2]])
    if crowded.size == 0:
        return drop
    # Rank only the incidences of the (few) crowded edges by face area.
    incidence = np.flatnonzero(np.isin(keys, crowded))
    face_of = incidence % n_faces
    v, f = mesh.vertices, mesh.faces[face_of]
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    order = np.lexsort((-area, keys[incidence]))
    grouped = keys[incidence][order]
    starts = np.ones(len(grouped), dtype=bool)
    starts[1:] = grouped[1:] != grouped[:-1]
    positions = np.arange(len(grouped))
    rank = positions - np.maximum.accumulate(np.where(starts, positions, 0))
    drop[face_of[order][rank >= 2]] = True
    return drop


def small_component_faces(mesh: Mesh, min_faces: int) -> B:
    """Faces of connected pieces (sharing vertices) with fewer than ``min_faces`` faces.

    (A grid mesh is cleaned on its grid instead: ``grid_mesh.grid_surface``.)
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(mesh.vertices)
    f = mesh.faces
    if len(f) == 0 or min_faces <= 1:
        return np.zeros(len(f), dtype=bool)
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    face_label = np.take(labels, f[:, 0])
    sizes = np.bincount(face_label)
    return np.asarray(np.take(sizes, face_label) < min_faces)


def decimate(mesh: Mesh, target_faces: int) -> Mesh:
    """Quadric decimation (Open3D) to at most ``target_faces`` faces."""
    if len(mesh.faces) <= target_faces:
        return mesh
    try:
        simplified = mesh.to_open3d().simplify_quadric_decimation(
            target_number_of_triangles=int(target_faces))
    except RuntimeError as err:
        raise StageError(f"mesh: quadric decimation to {target_faces} faces failed ({err})") \
            from err
    return Mesh.from_open3d(simplified)


def clean_mesh(mesh: Mesh, params: CleanupParams | None = None,
               manifold_by_construction: bool = False,
               done: Mapping[str, int] | None = None) -> tuple[Mesh, dict[str, Any]]:
    """Apply the clean-up steps in order; report how many faces each one removed.

    ``manifold_by_construction``: the caller guarantees no duplicate faces and no edge with
    more than two faces (the grid triangulation), so those two searches are skipped.
    ``done``: steps the caller has applied already, by report name (``degenerate_faces_removed``,
    ``small_component_faces_removed``, ``unreferenced_vertices_removed``) with their counts;
    they are skipped and their counts reported.
    """
    params = params or CleanupParams()
    done = done or {}
    report: dict[str, Any] = {"faces_in": len(mesh.faces)}
    search = not manifold_by_construction
    steps: list[tuple[str, bool, Any]] = [
        ("degenerate_faces_removed", params.remove_degenerate, degenerate_faces),
        ("duplicate_faces_removed", params.remove_duplicates and search,
         lambda m: duplicate_faces(m.faces)),
        ("non_manifold_faces_removed", params.remove_non_manifold and search,
         non_manifold_faces),
        ("small_component_faces_removed", params.min_component_faces > 1,
         lambda m: small_component_faces(m, params.min_component_faces)),
    ]
    for name, enabled, find in steps:
        if not enabled:
            continue
        if name in done:
            report[name] = int(done[name])
            continue
        drop = find(mesh)
        report[name] = int(np.count_nonzero(drop))
        if report[name]:
            mesh = mesh.select_faces(~drop)
    if "unreferenced_vertices_removed" in done:
        report["unreferenced_vertices_removed"] = int(done["unreferenced_vertices_removed"])
    else:
        vertices_before = len(mesh.vertices)
        mesh = mesh.compact()
        report["unreferenced_vertices_removed"] = vertices_before - len(mesh.vertices)
    if params.target_faces is not None and len(mesh.faces) > params.target_faces:
        before = len(mesh.faces)
        mesh = decimate(mesh, params.target_faces)
        report["faces_removed_by_decimation"] = before - len(mesh.faces)
    report["faces_out"] = len(mesh.faces)
    return mesh, report
