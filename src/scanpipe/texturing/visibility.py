"""Is a surface point seen from a camera centre? Rays against the mesh (Open3D RaycastingScene).

A face counts as visible from a camera only when seven points on it are all unobstructed: its
centroid, and points near its corners and the middles of its edges (pulled 15 % towards the
centroid, so that shared edges do not decide). A face half hidden behind an edge or a thin
object is not textured from that frame.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import StageError

F64 = NDArray[np.float64]
#: Where the corner samples sit between the centroid (0) and the corner (1).
CORNER_INSET = 0.85


class MeshOcclusion:
    """Occlusion tests against one triangle mesh."""

    def __init__(self, vertices: NDArray[np.floating], faces: NDArray[np.integer]) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(faces, dtype=np.uint32)
        import open3d as o3d  # here, not at import: every command would pay ~0.8 s for it

        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        if len(self.faces):
            try:
                self._scene.add_triangles(o3d.core.Tensor.from_numpy(self.vertices),
                                          o3d.core.Tensor.from_numpy(self.faces))
            except RuntimeError as err:
                raise StageError(f"mesh: Open3D could not build a ray-casting scene ({err})"
                                 ) from err

    def face_samples(self, face_ids: NDArray[np.integer]) -> NDArray[np.float32]:
        """``(len(face_ids), 7, 3)``: centroid, inset corners and inset edge middles per face."""
        corners = self.vertices[self.faces[face_ids]]
        centroid = corners.mean(axis=1, keepdims=True)
        middles = 0.5 * (corners + np.roll(corners, -1, axis=1))
        inset = centroid + CORNER_INSET * (np.concatenate([corners, middles], axis=1) - centroid)
        return np.concatenate([centroid, inset], axis=1)

    def unobstructed(self, origins: NDArray[np.floating], points: NDArray[np.floating],
                     face_ids: NDArray[np.integer], abs_tol_m: float = 0.01,
                     rel_tol: float = 0.005) -> NDArray[np.bool_]:
        """True where the segment origin → point reaches the point (or its face) first.

        ``origins`` and ``points`` are ``(M, 3)``; ``face_ids`` ``(M,)`` the face each point lies
        on. A hit on that very face, or no closer than ``abs_tol_m + rel_tol · distance`` before
        the point, counts as unobstructed.
        """
        if len(points) == 0:
            return np.zeros(0, dtype=bool)
        delta = np.asarray(points, np.float64) - np.asarray(origins, np.float64)
        distance = np.linalg.norm(delta, axis=1)
        direction = delta / np.maximum(distance, 1e-12)[:, None]
        rays = np.concatenate([origins, direction], axis=1).astype(np.float32)
        hits = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        t_hit = hits["t_hit"].numpy().astype(np.float64)
        primitive = hits["primitive_ids"].numpy().astype(np.int64)
        tolerance = abs_tol_m + rel_tol * distance
        return np.asarray((primitive == face_ids) | (t_hit >= distance - tolerance))

    def faces_visible(self, origins: NDArray[np.floating], face_ids: NDArray[np.integer],
                      abs_tol_m: float = 0.01, rel_tol: float = 0.005) -> NDArray[np.bool_]:
        """True where face ``face_ids[i]`` is wholly visible from camera centre ``origins[i]``."""
        face_ids = np.asarray(face_ids, dtype=np.int64)
        samples = self.face_samples(face_ids)
        k = samples.shape[1]
        ok = self.unobstructed(np.repeat(np.asarray(origins, np.float64), k, axis=0),
                               samples.reshape(-1, 3), np.repeat(face_ids, k),
                               abs_tol_m, rel_tol)
        return np.asarray(ok.reshape(-1, k).all(axis=1))


def face_normals(vertices: NDArray[np.floating], faces: NDArray[np.integer],
                 vertex_normals: NDArray[np.floating] | None = None) -> tuple[F64, F64]:
    """Unit face normals and face areas (m²).

    The winding decides a normal's sign unless ``vertex_normals`` are given: then each face
    normal is turned to agree with the mean of its vertices' normals (the mesh stage's normals
    point towards the scanner).
    """
    corners = np.asarray(vertices, np.float64)[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(length, 1e-20)[:, None]
    if vertex_normals is not None:
        mean = np.asarray(vertex_normals, np.float64)[faces].sum(axis=1)
        flip = np.einsum("ij,ij->i", normals, mean) < 0
        normals[flip] *= -1
    return normals, 0.5 * length
