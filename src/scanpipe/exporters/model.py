"""In-memory meshes and clouds built from artifact tables, the input of every exporter.

A :class:`MeshModel` is the ``mesh_vertices`` + ``mesh_faces`` artifacts, optionally with the
texture stage's ``textured_faces`` (per-corner UVs, glTF convention: v = 0 at the image top)
and ``texture_pages`` (PNG). A :class:`CloudModel` is a ``points`` artifact. Both are in the
rig frame (y up); :func:`rig_to_z_up` gives the (x, −z, y) frame of LAS and E57. Both carry
the artifact's georeference offset (``offset_m``, rig frame, :data:`scanpipe.schema.OFFSET_KEY`):
the coordinates other tools expect are ``xyz + offset_m`` (:func:`geo_z_up`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.errors import ArtifactError, ExportError
from scanpipe.schema import (
    FACE_CORNERS,
    MESH_FACES,
    MESH_VERTICES,
    NORMAL,
    POINTS,
    RGB,
    TEXTURE_PAGES,
    TEXTURED_FACES,
    XYZ,
    ZERO_OFFSET,
    Offset,
    crs_of,
    offset_of,
)

F32 = NDArray[np.float32]

#: The texture coordinates of a face's three corners, in the order of ``textured_faces``.
UV_COLUMNS = ("u0", "v0", "u1", "v1", "u2", "v2")
#: The columns of ``textured_faces`` a :class:`MeshModel` is made from (:func:`mesh_from_tables`).
TEXTURED_FACE_COLUMNS = ("face", "page", *UV_COLUMNS)
#: The columns of a points artifact a :class:`CloudModel` is made from (:func:`cloud_from_table`;
#: the beams' origins are not exported).
CLOUD_COLUMNS = (*XYZ, "echo", "time_ns", "range_m", "profile", "beta_deg", "alpha_deg",
                 "sample", *RGB, "filtered_by")


@dataclass(frozen=True)
class MeshModel:
    """A triangle mesh in the rig frame, with an optional texture atlas.

    ``face_pages[i]`` is the atlas page of face ``i`` (−1: untextured) and ``face_uvs[i, k]``
    the UV of its corner ``k`` in glTF convention (v = 0 at the top of the page).
    """

    vertices: F32
    faces: NDArray[np.int32]
    normals: F32 | None = None
    colors: NDArray[np.uint8] | None = None
    face_pages: NDArray[np.int16] | None = None
    face_uvs: F32 | None = None
    pages: dict[int, bytes] = field(default_factory=dict)
    #: Whole metres subtracted on import (rig frame): add them for georeferenced output.
    offset_m: Offset = ZERO_OFFSET

    @property
    def textured(self) -> bool:
        """Whether any face has a texture page."""
        return self.face_pages is not None and bool(np.any(self.face_pages >= 0))

    @cached_property
    def page_splits(self) -> dict[int, tuple[NDArray[np.int64], F32, NDArray[np.uint32]]]:
        """Per atlas page, :func:`split_by_uv` of its faces' corners (faces in index order):
        ``(source vertex of each page vertex, its uv, page vertex of each corner)``. Computed
        once per model: OBJ (its ``vt`` lines) and GLB (its primitives' vertices) share it."""
        if not self.textured or self.face_pages is None or self.face_uvs is None:
            return {}
        splits = {}
        for page in sorted(int(p) for p in np.unique(self.face_pages) if p >= 0):
            selected = np.flatnonzero(self.face_pages == page)
            splits[page] = split_by_uv(self.faces[selected].reshape(-1),
                                       self.face_uvs[selected].reshape(-1, 2))
        return splits

    @cached_property
    def unit_normals(self) -> F32:
        """:func:`unit_normals`, computed once per model (OBJ, GLB and PLY all write them);
        read-only."""
        normals = _unit_normals(self)
        normals.flags.writeable = False
        return normals


@dataclass(frozen=True)
class CloudModel:
    """A point cloud in the rig frame with what the points artifact carries besides xyz."""

    xyz: F32
    intensity: NDArray[np.uint16] | None = None
    colors: NDArray[np.uint8] | None = None
    time_ns: NDArray[np.int64] | None = None
    range_m: F32 | None = None
    profile: NDArray[np.int32] | None = None
    beta_deg: NDArray[np.float64] | None = None
    alpha_deg: NDArray[np.float64] | None = None
    sample: NDArray[np.int32] | None = None
    #: Whole metres subtracted on import (rig frame): add them for georeferenced output.
    offset_m: Offset = ZERO_OFFSET
    #: The imported file's coordinate system (WKT), when the points keep it.
    crs_wkt: str | None = None


#: How text formats (OBJ, MTL, PLY) mark their provenance comment: ``<tag> {json}``.
PROVENANCE_TAG = "scanpipe-provenance"


def provenance_bytes(provenance: Mapping[str, Any]) -> bytes:
    """The provenance record (scanpipe version, artifact keys, stages and parameters) as compact
    one-line JSON: what LAS VLRs, E57, OBJ/PLY comments, GLB extras and MCAP metadata carry."""
    return json.dumps(provenance, sort_keys=True, separators=(",", ":"), default=str).encode()


def rig_to_z_up(xyz: NDArray[np.floating]) -> NDArray[np.float64]:
    """Rig frame (y up) to the z-up right-handed frame of LAS and E57: (x, −z, y)."""
    p = np.asarray(xyz, dtype=np.float64)
    return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1)


def geo_z_up(xyz: NDArray[np.floating], offset_m: Offset) -> NDArray[np.float64]:
    """Rig-frame coordinates plus their georeference offset, in the z-up frame of LAS and
    E57, as float64 (exact: the offset is whole metres, the local values float32)."""
    z_up = rig_to_z_up(xyz)
    if any(offset_m):
        z_up += rig_to_z_up(np.asarray([offset_m], np.float64))
    return z_up


def _xyz(table: pa.Table, names: tuple[str, str, str]) -> F32:
    return np.stack([table.column(n).to_numpy(zero_copy_only=False) for n in names],
                    axis=1).astype(np.float32)


def _colors(table: pa.Table) -> NDArray[np.uint8] | None:
    if not all(c in table.column_names for c in RGB):
        return None
    columns = [table.column(c) for c in RGB]
    if any(c.null_count for c in columns):
        return None
    return np.stack([c.to_numpy(zero_copy_only=False) for c in columns], 1).astype(np.uint8)


def mesh_from_tables(
    vertices: pa.Table,
    faces: pa.Table,
    textured_faces: pa.Table | None = None,
    texture_pages: pa.Table | None = None,
) -> MeshModel:
    """Check the mesh (and texture) artifacts against the contract and build a model."""
    MESH_VERTICES.check(vertices)
    MESH_FACES.check(faces)
    xyz = _xyz(vertices, XYZ)
    normals = _xyz(vertices, NORMAL)
    tri = np.stack([faces.column(n).to_numpy() for n in FACE_CORNERS], 1).astype(np.int32)
    if tri.size and (int(tri.min()) < 0 or int(tri.max()) >= len(xyz)):
        raise ArtifactError(f"mesh_faces: vertex index out of range 0..{len(xyz) - 1} "
                            f"(found {int(tri.min())}..{int(tri.max())})")
    face_pages = face_uvs = None
    pages: dict[int, bytes] = {}
    if textured_faces is not None and texture_pages is not None:
        TEXTURED_FACES.check(textured_faces, TEXTURED_FACE_COLUMNS)
        TEXTURE_PAGES.check(texture_pages)
        face_index = textured_faces.column("face").to_numpy()
        if face_index.size and (int(face_index.min()) < 0 or int(face_index.max()) >= len(tri)):
            raise ArtifactError("textured_faces: face index out of range "
                                f"0..{len(tri) - 1}")
        face_pages = np.full(len(tri), -1, dtype=np.int16)
        face_pages[face_index] = textured_faces.column("page").to_numpy()
        uv_columns = [textured_faces.column(n).to_numpy(zero_copy_only=False)
                      for n in UV_COLUMNS]
        face_uvs = np.zeros((len(tri), 3, 2), dtype=np.float32)
        if np.array_equal(face_index, np.arange(len(tri))):
            # every face in order (the texture stage's output): stacked in place, no scatter
            np.stack(uv_columns, 1, out=face_uvs.reshape(-1, 6))
        else:
            face_uvs[face_index] = np.stack(uv_columns, 1).reshape(-1, 3, 2)
        page_ids = texture_pages.column("page").to_pylist()
        pngs = texture_pages.column("png").to_pylist()
        pages = {int(p): bytes(b) for p, b in zip(page_ids, pngs, strict=True)}
        missing = sorted(set(np.unique(face_pages[face_pages >= 0]).tolist()) - set(pages))
        if missing:
            raise ArtifactError(f"textured_faces: pages {missing} are not in texture_pages "
                                f"(has {sorted(pages)})")
        if not np.isfinite(face_uvs).all():  # one pass; nan_to_num alone takes five
            face_uvs = np.nan_to_num(face_uvs, nan=0.0)
    return MeshModel(xyz, tri, normals, _colors(vertices), face_pages, face_uvs, pages,
                     offset_of(vertices))


def cloud_from_table(points: pa.Table) -> CloudModel:
    """Check a points artifact and build a cloud model (rows with non-finite xyz dropped, and
    rows a filter marked in mark mode: ``filtered_by`` not null)."""
    POINTS.check(points, XYZ)
    xyz = _xyz(points, XYZ)
    keep = np.all(np.isfinite(xyz), axis=1)
    if "filtered_by" in points.column_names:
        keep &= points.column("filtered_by").is_null().to_numpy(zero_copy_only=False)

    def optional(name: str, dtype: type[np.generic]) -> NDArray[np.generic] | None:
        if name not in points.column_names or points.column(name).null_count:
            return None
        return np.asarray(points.column(name).to_numpy(zero_copy_only=False),
                          dtype=dtype)[keep]

    colors = _colors(points)
    return CloudModel(
        xyz=xyz[keep],
        intensity=optional("echo", np.uint16),  # type: ignore[arg-type]
        colors=None if colors is None else colors[keep],
        time_ns=optional("time_ns", np.int64),  # type: ignore[arg-type]
        range_m=optional("range_m", np.float32),  # type: ignore[arg-type]
        profile=optional("profile", np.int32),  # type: ignore[arg-type]
        beta_deg=optional("beta_deg", np.float64),  # type: ignore[arg-type]
        alpha_deg=optional("alpha_deg", np.float64),  # type: ignore[arg-type]
        sample=optional("sample", np.int32),  # type: ignore[arg-type]
        offset_m=offset_of(points),
        crs_wkt=crs_of(points),
    )


#: Corners handled at a time by :func:`split_by_uv` (its temporaries are of one slice).
SPLIT_SLICE = 1 << 20


def split_by_uv(corner_vertex: NDArray[np.integer], corner_uv: NDArray[np.floating]
                ) -> tuple[NDArray[np.int64], F32, NDArray[np.uint32]]:
    """Per-corner UVs to per-vertex ones: ``(source vertex of each new vertex, its uv, new
    vertex index of each corner)``; the indices are uint32, what glTF's index accessors hold.

    A corner reuses its vertex's first corner when their UVs are equal (inside a texture
    chart); corners on a seam get a vertex of their own. O(n), no sorting. OBJ uses it for
    shared ``vt`` lines, glTF to split vertices.
    """
    n = len(corner_vertex)
    if n >= 2**32:
        raise ExportError(f"{n} face corners: more than 32-bit indices (glTF's) can hold")
    first = np.zeros(int(np.max(corner_vertex, initial=0)) + 1, dtype=np.uint32)
    # the last write wins: each vertex's first corner
    first[corner_vertex[::-1]] = np.arange(n - 1, -1, -1, dtype=np.uint32)
    # compare (u, v) float32 pairs as one 64-bit word each: exact equality, half the work
    uv = np.ascontiguousarray(corner_uv, dtype=np.float32).reshape(-1, 2)
    packed = uv.view(np.uint64).ravel()
    # slice by slice: the per-corner temporaries (first corner, its uv) stay slice-sized.
    # A corner's first corner is never after it, so the running count of own vertices there
    # is known by the time the corner is reached: one pass makes both.
    # A vertex's first corner is its own, so the new index of a corner that is not its own
    # is its first corner's, written already (an earlier slice, or this slice's own corners
    # first): no array of own indices beside ``index`` (57 MB less at lab scale).
    own = np.empty(n, dtype=np.bool_)
    index = np.empty(n, dtype=np.uint32)
    count = np.uint32(0)
    for start in range(0, n, SPLIT_SLICE):
        stop = min(n, start + SPLIT_SLICE)
        first_of_corner = first[corner_vertex[start:stop]]
        own_slice = own[start:stop]
        np.not_equal(packed[start:stop], packed[first_of_corner], out=own_slice)
        own_slice |= first_of_corner == np.arange(start, stop, dtype=np.uint32)
        # the first corner is its vertex's first: the count is ≥ 1 before the − 1
        own_index = np.cumsum(own_slice, dtype=np.uint32)
        own_index += count
        own_index -= np.uint32(1)
        count = own_index[-1] + np.uint32(1)
        index_slice = index[start:stop]
        np.copyto(index_slice, own_index, where=own_slice)
        np.copyto(index_slice, index[first_of_corner], where=~own_slice)
    return np.asarray(corner_vertex[own], dtype=np.int64), uv[own], index


def unit_normals(mesh: MeshModel) -> F32:
    """Per-vertex unit normals: the mesh's own where usable, else area-weighted face normals
    (read-only; computed once per model)."""
    return mesh.unit_normals


def _unit_normals(mesh: MeshModel) -> F32:
    v = mesh.vertices.astype(np.float64)
    given = (np.zeros_like(v) if mesh.normals is None
             else np.nan_to_num(mesh.normals.astype(np.float64)))
    length = np.linalg.norm(given, axis=1)
    bad = ~(length > 1e-6)
    if np.any(bad) and len(mesh.faces):
        tri = v[mesh.faces]
        face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        acc = np.zeros_like(v)
        for k in range(3):
            np.add.at(acc, mesh.faces[:, k], face_n)
        given[bad] = acc[bad]
        length = np.linalg.norm(given, axis=1)
    still_bad = ~(length > 1e-12)
    given[still_bad] = (0.0, 1.0, 0.0)
    length[still_bad] = 1.0
    return np.asarray(given / length[:, None], dtype=np.float32)
