"""PLY, binary little-endian: meshes with vertex colours, and point clouds.

A textured mesh without vertex colours gets them from its texture (the mean of the texels at
the vertex's corners), so the PLY shows the same colours a textured viewer would.

A georeferenced model (``offset_m``, an import shifted so float32 keeps 0.1 mm) is written with
``double`` x, y, z holding the imported coordinates (local + offset; float32 would round them
to centimetres), and a ``comment scanpipe-offset-m X Y Z`` line naming the offset added.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from scanpipe import __version__
from scanpipe.artifacts import Pieces, file_bytes
from scanpipe.errors import ExportError
from scanpipe.exporters.model import (
    PROVENANCE_TAG,
    CloudModel,
    MeshModel,
    provenance_bytes,
    unit_normals,
)
from scanpipe.images import MAX_TEXTURE_PX, probe_image
from scanpipe.schema import Offset


def decode_png(data: bytes, where: str) -> NDArray[np.uint8]:
    """An RGB image ``(H, W, 3)`` from PNG bytes; ExportError when it is not an image or is
    larger than an atlas page may be (checked from the header, before decoding)."""
    probe_image(data, where, MAX_TEXTURE_PX, ExportError)
    try:
        with Image.open(io.BytesIO(data)) as image:
            pixels: NDArray[np.uint8] = np.asarray(image.convert("RGB"), dtype=np.uint8)
            return pixels
    except (OSError, ValueError) as err:
        raise ExportError(f"{where}: not a readable PNG ({err})") from None


def sample_texture(image: NDArray[np.uint8], uv: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Nearest texels at glTF-convention UVs (v = 0 at the top row)."""
    height, width = image.shape[:2]
    u = np.clip(np.asarray(uv[:, 0], np.float64), 0.0, 1.0)
    v = np.clip(np.asarray(uv[:, 1], np.float64), 0.0, 1.0)
    col = np.minimum((u * width).astype(np.int64), width - 1)
    row = np.minimum((v * height).astype(np.int64), height - 1)
    return np.asarray(image[row, col], dtype=np.uint8)


def vertex_colors_from_texture(mesh: MeshModel) -> NDArray[np.uint8] | None:
    """Per-vertex colours: the mean texel over each vertex's textured corners."""
    if not mesh.textured or mesh.face_pages is None or mesh.face_uvs is None:
        return None
    total = np.zeros((len(mesh.vertices), 3), dtype=np.float64)
    count = np.zeros(len(mesh.vertices), dtype=np.float64)
    for page in sorted(int(p) for p in np.unique(mesh.face_pages) if p >= 0):
        image = decode_png(mesh.pages[page], f"texture page {page}")
        selected = np.flatnonzero(mesh.face_pages == page)
        corners = mesh.faces[selected].reshape(-1)
        texels = sample_texture(image, mesh.face_uvs[selected].reshape(-1, 2))
        for channel in range(3):
            total[:, channel] += np.bincount(corners, texels[:, channel].astype(np.float64),
                                             minlength=len(mesh.vertices))
        count += np.bincount(corners, minlength=len(mesh.vertices))
    seen = count > 0
    colors = np.full((len(mesh.vertices), 3), 178, dtype=np.uint8)
    colors[seen] = np.rint(total[seen] / count[seen, None]).astype(np.uint8)
    return colors


#: Characters of the provenance record per PLY comment line.
PLY_COMMENT_CHARS = 200


def _header(comment: str, vertex_count: int, properties: list[str],
            face_count: int | None, provenance: Mapping[str, Any] | None,
            extra_comments: list[str] | None = None) -> bytes:
    record = provenance_bytes(provenance or {}).decode()
    # PLY readers keep header lines short (rply, Open3D's reader, aborts past 1024 bytes): the
    # record goes over as many comment lines as it needs, to be joined back in order.
    chunks = [record[i:i + PLY_COMMENT_CHARS] for i in range(0, len(record), PLY_COMMENT_CHARS)]
    lines = ["ply", "format binary_little_endian 1.0", f"comment {comment}",
             *(f"comment {extra}" for extra in extra_comments or ()),
             *(f"comment {PROVENANCE_TAG} {chunk}" for chunk in chunks),
             f"element vertex {vertex_count}", *properties]
    if face_count is not None:
        lines += [f"element face {face_count}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode()


#: The header comment that names a georeferenced file's offset (rig frame, y up, metres).
OFFSET_TAG = "scanpipe-offset-m"


def _positions(xyz: NDArray[np.float32], offset_m: Offset
               ) -> tuple[list[tuple[str, str]], list[str], NDArray[Any], list[str]]:
    """The x, y, z fields, properties and values, and the comment lines: float32 as they are,
    or float64 with the georeference offset added."""
    names = ("x", "y", "z")
    if not any(offset_m):
        return [(n, "<f4") for n in names], [f"property float {n}" for n in names], xyz, []
    values = xyz.astype(np.float64) + np.asarray(offset_m, np.float64)
    comment = f"{OFFSET_TAG} " + " ".join(f"{float(v):.17g}" for v in offset_m)
    return ([(n, "<f8") for n in names], [f"property double {n}" for n in names], values,
            [comment])


def _raw(records: NDArray[Any]) -> memoryview:
    """The bytes of a contiguous array of records, without a copy."""
    raw: Any = np.ascontiguousarray(records).view(np.uint8)
    return memoryview(raw)


def ply_mesh_bytes(mesh: MeshModel, provenance: Mapping[str, Any] | None = None) -> bytes:
    """:func:`ply_mesh_pieces` joined into one bytes object."""
    return file_bytes(ply_mesh_pieces(mesh, provenance))


def ply_mesh_pieces(mesh: MeshModel, provenance: Mapping[str, Any] | None = None) -> Pieces:
    """A binary PLY of the mesh with normals and vertex colours (from the texture if needed),
    the ``provenance`` record in a header comment."""
    colors = mesh.colors if mesh.colors is not None else vertex_colors_from_texture(mesh)
    fields, properties, positions, comments = _positions(mesh.vertices, mesh.offset_m)
    fields += [(n, "<f4") for n in ("nx", "ny", "nz")]
    properties += [f"property float {n}" for n in ("nx", "ny", "nz")]
    if colors is not None:
        fields += [(n, "u1") for n in ("red", "green", "blue")]
        properties += [f"property uchar {n}" for n in ("red", "green", "blue")]
    vertices = np.empty(len(mesh.vertices), dtype=fields)
    normals = unit_normals(mesh)
    for j, n in enumerate(("x", "y", "z")):
        vertices[n] = positions[:, j]
        vertices["n" + n] = normals[:, j]
    if colors is not None:
        for j, n in enumerate(("red", "green", "blue")):
            vertices[n] = colors[:, j]
    faces = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = mesh.faces
    header = _header(f"scanpipe {__version__} mesh; y up, metres", len(vertices), properties,
                     len(faces), provenance, comments)
    return Pieces((header, _raw(vertices), _raw(faces)))


def ply_cloud_bytes(cloud: CloudModel, provenance: Mapping[str, Any] | None = None) -> bytes:
    """:func:`ply_cloud_pieces` joined into one bytes object."""
    return file_bytes(ply_cloud_pieces(cloud, provenance))


def ply_cloud_pieces(cloud: CloudModel, provenance: Mapping[str, Any] | None = None
                     ) -> Pieces:
    """A binary PLY of the points with intensity (echo) and colour when present, the
    ``provenance`` record in a header comment."""
    fields, properties, positions, comments = _positions(cloud.xyz, cloud.offset_m)
    if cloud.intensity is not None:
        # float, not ushort: Open3D's readers skip an integer scalar property (the echo's
        # 0…65535 are exact in float32); CloudCompare and PCL (PointXYZI) read float
        fields.append(("intensity", "<f4"))
        properties.append("property float intensity")
    if cloud.colors is not None:
        fields += [(n, "u1") for n in ("red", "green", "blue")]
        properties += [f"property uchar {n}" for n in ("red", "green", "blue")]
    vertices = np.empty(len(cloud.xyz), dtype=fields)
    for j, n in enumerate(("x", "y", "z")):
        vertices[n] = positions[:, j]
    if cloud.intensity is not None:
        vertices["intensity"] = cloud.intensity
    if cloud.colors is not None:
        for j, n in enumerate(("red", "green", "blue")):
            vertices[n] = cloud.colors[:, j]
    header = _header(f"scanpipe {__version__} points; y up, metres", len(vertices),
                     properties, None, provenance, comments)
    return Pieces((header, _raw(vertices)))
