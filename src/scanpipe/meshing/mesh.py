"""The in-memory triangle mesh the meshing code passes around, and its artifact tables."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.schema import FACE_CORNERS, NORMAL, RGB, XYZ

F32 = NDArray[np.float32]
I32 = NDArray[np.int32]
U8 = NDArray[np.uint8]
B = NDArray[np.bool_]


def face_cross(vertices: F32, faces: I32) -> F32:
    """``(v1 − v0) × (v2 − v0)`` per face, float32 ``(K, 3)`` (length = twice the area).

    One gather per corner and the cross product written column by column: ``np.cross`` and
    its temporaries cost ~3× more at millions of faces.
    """
    v = np.asarray(vertices, dtype=np.float32)
    e1 = v[faces[:, 1]]
    e2 = v[faces[:, 2]]
    v0 = v[faces[:, 0]]
    e1 -= v0
    e2 -= v0
    out = v0  # reused: v0 is no longer needed
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        column: F32 = out[:, k]
        np.multiply(e1[:, i], e2[:, j], out=column)
        np.subtract(column, e1[:, j] * e2[:, i], out=column)
    return out


@dataclass(frozen=True)
class Mesh:
    """Vertices ``(N, 3)``, faces ``(K, 3)`` indexing them, optional per-vertex normals and
    colours. Faces wind counter-clockwise seen from the side the normals point to."""

    vertices: F32
    faces: I32
    normals: F32 | None = None
    colors: U8 | None = None

    def select_vertices(self, keep: B) -> Mesh:
        """Drop the vertices not in ``keep`` and every face that uses one of them."""
        remap = np.cumsum(keep, dtype=np.int64) - 1
        face_ok = keep[self.faces].all(axis=1)
        return Mesh(
            vertices=self.vertices[keep],
            faces=remap[self.faces[face_ok]].astype(np.int32),
            normals=None if self.normals is None else self.normals[keep],
            colors=None if self.colors is None else self.colors[keep],
        )

    def select_faces(self, keep: B) -> Mesh:
        """Keep only the faces in ``keep`` (vertices stay; see :meth:`compact`)."""
        return replace(self, faces=self.faces[keep])

    def compact(self) -> Mesh:
        """Drop vertices that no face uses."""
        used = np.zeros(len(self.vertices), dtype=bool)
        used[self.faces.reshape(-1)] = True
        if used.all():
            return self
        # Every face keeps its vertices here: renumber them, no per-face test.
        remap = np.cumsum(used, dtype=np.int64)
        remap -= 1
        return Mesh(
            vertices=self.vertices[used],
            faces=np.take(remap, self.faces).astype(np.int32, copy=False),
            normals=None if self.normals is None else self.normals[used],
            colors=None if self.colors is None else self.colors[used],
        )

    def face_normals(self) -> F32:
        """Unnormalised face normals (length = twice the area)."""
        return face_cross(self.vertices, self.faces)

    def with_vertex_normals(self) -> Mesh:
        """Area-weighted vertex normals from the faces (existing ones kept where no face is)."""
        face_n = self.face_normals().astype(np.float64)
        summed = np.stack([
            np.bincount(self.faces.ravel(), weights=np.repeat(face_n[:, k], 3),
                        minlength=len(self.vertices)) for k in range(3)], axis=1)
        norm = np.linalg.norm(summed, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            normals = (summed / norm).astype(np.float32)
        lonely = ~(norm[:, 0] > 0)
        if self.normals is not None:
            normals[lonely] = self.normals[lonely]
        else:
            normals[lonely] = 0.0
        return replace(self, normals=normals)

    def to_open3d(self) -> Any:
        """An ``open3d.geometry.TriangleMesh`` with the same data."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices.astype(np.float64)),
            o3d.utility.Vector3iVector(self.faces.astype(np.int32)))
        if self.normals is not None:
            mesh.vertex_normals = o3d.utility.Vector3dVector(self.normals.astype(np.float64))
        if self.colors is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(self.colors / 255.0)
        return mesh

    @staticmethod
    def from_open3d(mesh: Any) -> Mesh:
        """The :class:`Mesh` of an ``open3d.geometry.TriangleMesh``."""
        normals = np.asarray(mesh.vertex_normals, dtype=np.float32) \
            if mesh.has_vertex_normals() else None
        colors = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(
            np.uint8) if mesh.has_vertex_colors() else None
        return Mesh(
            vertices=np.asarray(mesh.vertices, dtype=np.float32),
            faces=np.asarray(mesh.triangles, dtype=np.int32).reshape(-1, 3),
            normals=normals,
            colors=colors,
        )

    def to_tables(self) -> tuple[pa.Table, pa.Table]:
        """The ``mesh_vertices`` and ``mesh_faces`` artifact tables."""
        normals = self.normals if self.normals is not None else np.zeros_like(self.vertices)
        columns: dict[str, pa.Array] = {}
        for k, name in enumerate(XYZ):
            columns[name] = pa.array(np.ascontiguousarray(self.vertices[:, k], np.float32))
        for k, name in enumerate(NORMAL):
            columns[name] = pa.array(np.ascontiguousarray(normals[:, k], np.float32))
        if self.colors is not None:
            for k, name in enumerate(RGB):
                columns[name] = pa.array(np.ascontiguousarray(self.colors[:, k], np.uint8))
        faces = {name: pa.array(np.ascontiguousarray(self.faces[:, k], np.int32))
                 for k, name in enumerate(FACE_CORNERS)}
        return pa.table(columns), pa.table(faces)
