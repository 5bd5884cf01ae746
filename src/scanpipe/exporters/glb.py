"""glTF 2.0 binary (GLB) with the texture pages embedded as PNG, written directly.

One mesh with one primitive per atlas page (its own material and texture) and one for the
untextured faces. The texture stage gives UVs per face corner, glTF needs them per vertex, so a
vertex is split where its corners carry different UVs (unique (vertex, u, v) triples).
Everything the Khronos glTF-Validator checks is respected: 4-byte alignment, POSITION min/max,
unit normals, buffer-view targets, index bounds.

With ``draco`` each primitive's geometry is one Draco bitstream (``KHR_draco_mesh_compression``,
encoded by DracoPy, Google's Draco library): positions quantised to 16 bits over the model's
extent (0.15 mm over a 10 m room, far below a scanner's noise), texture coordinates to 14 bits
(a quarter texel of a 4096-pixel page), normals to 10 bits. The accessors then carry counts and
bounds of the *decoded* data, read back from the bitstream (Draco may reorder and, at
non-manifold edges, duplicate vertices).

A georeferenced mesh (``offset_m``, an import shifted so float32 keeps 0.1 mm) keeps its local
float32 positions; its node's ``translation`` is the offset (JSON numbers: doubles, exact), so
a glTF viewer or Blender places the model at the imported coordinates while the vertices keep
their precision; ``asset.extras.scanpipe_offset_m`` names it too.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe import __version__
from scanpipe.artifacts import Stream, file_bytes
from scanpipe.errors import ExportError
from scanpipe.exporters.model import MeshModel, unit_normals

FLOAT, UNSIGNED_BYTE, UNSIGNED_INT = 5126, 5121, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, LINEAR_MIPMAP_LINEAR, CLAMP_TO_EDGE = 9729, 9987, 33071
DRACO = "KHR_draco_mesh_compression"
#: Draco quantisation (bits) of positions, texture coordinates and normals: see the docstring.
POSITION_BITS, TEXCOORD_BITS, NORMAL_BITS = 16, 14, 10
#: Draco's speed/size trade-off, 0..10: on the demo model 4 gives the size of 7 (7.4 MiB) in
#: two thirds of its time; 10 saves 0.5 % more.
DRACO_LEVEL = 4
#: Draco's attribute types, by which the decoded attributes are matched to glTF's names.
_DRACO_TYPES = {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2, "TEXCOORD_0": 3}


#: Rows of a gathered attribute made at a time while the GLB is written.
GATHER_ROWS = 1 << 18

_Blob = bytes | memoryview | Callable[[], Iterator[bytes | memoryview]]


class _Builder:
    """Accumulates buffer views and accessors into one binary buffer."""

    def __init__(self) -> None:
        self.blobs: list[_Blob] = []
        self.offset = 0
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def view(self, data: _Blob, target: int | None = None, nbytes: int = 0) -> int:
        """A buffer view of ``data``: bytes, or a maker of its pieces, ``nbytes`` long."""
        length = nbytes if callable(data) else len(data)
        view: dict[str, Any] = {"buffer": 0, "byteOffset": self.offset, "byteLength": length}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        padding = (-length) % 4
        self.blobs += [data, b"\0" * padding]
        self.offset += length + padding
        return len(self.views) - 1

    def gathered(self, base: NDArray[Any], rows: NDArray[np.integer], kind: str,
                 component: int, target: int, bounds: bool = False) -> int:
        """An accessor of ``base[rows]`` that is gathered only while the file is written,
        :data:`GATHER_ROWS` rows at a time (the same bytes as the gathered array)."""

        def pieces() -> Iterator[memoryview]:
            for part in _parts(rows):
                yield np.ascontiguousarray(base[part]).data.cast("B")

        count = len(rows)
        row_bytes = base.dtype.itemsize * int(np.prod(base.shape[1:], dtype=np.int64))
        accessor: dict[str, Any] = {
            "bufferView": self.view(pieces, target, count * row_bytes),
            "componentType": component,
            "count": count,
            "type": kind,
        }
        if bounds:  # the gathered rows' bounds, slice by slice
            flat = base.reshape(base.shape[0], -1)
            lows = [flat[part].min(axis=0) for part in _parts(rows)]
            highs = [flat[part].max(axis=0) for part in _parts(rows)]
            accessor["min"] = [_number(v) for v in np.min(lows, axis=0).astype(base.dtype)]
            accessor["max"] = [_number(v) for v in np.max(highs, axis=0).astype(base.dtype)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def accessor(self, array: NDArray[Any], kind: str, component: int, target: int,
                 normalized: bool = False, bounds: bool = False) -> int:
        data = np.ascontiguousarray(array)
        accessor: dict[str, Any] = {
            "bufferView": self.view(data.data.cast("B"), target),  # a view: no copy
            "componentType": component,
            "count": int(data.shape[0]),
            "type": kind,
        }
        if normalized:
            accessor["normalized"] = True
        if bounds:
            flat = data.reshape(data.shape[0], -1)
            accessor["min"] = [_number(v) for v in flat.min(axis=0)]
            accessor["max"] = [_number(v) for v in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def draco_primitive(self, positions: NDArray[np.float32], normals: NDArray[np.float32],
                        triangles: NDArray[np.integer], uv: NDArray[np.float32] | None,
                        rgba: NDArray[np.uint8] | None) -> dict[str, Any]:
        """A primitive whose geometry is one Draco bitstream, and its data-less accessors."""
        import DracoPy as draco  # here, not at import: only a Draco GLB needs it
        encoded = draco.encode(
            positions.astype(np.float64), triangles.reshape(-1, 3).astype(np.uint32),
            quantization_bits=POSITION_BITS, compression_level=DRACO_LEVEL,
            tex_coord=None if uv is None else uv.astype(np.float64),
            tex_coord_quantization_bits=TEXCOORD_BITS,
            normals=normals.astype(np.float64), normal_quantization_bits=NORMAL_BITS,
            colors=rgba)
        decoded = draco.decode(encoded)
        by_type = {a["attribute_type"]: a for a in decoded.attributes}
        names = ["POSITION", "NORMAL"] + (["TEXCOORD_0"] if uv is not None else []) + (
            ["COLOR_0"] if rgba is not None and uv is None else [])
        count = len(decoded.points)
        shapes = {"POSITION": ("VEC3", FLOAT), "NORMAL": ("VEC3", FLOAT),
                  "TEXCOORD_0": ("VEC2", FLOAT), "COLOR_0": ("VEC4", UNSIGNED_BYTE)}
        attributes: dict[str, int] = {}
        for name in names:
            kind, component = shapes[name]
            accessor: dict[str, Any] = {"componentType": component, "count": count,
                                        "type": kind}
            if name == "POSITION":
                points = np.asarray(decoded.points, dtype=np.float32)
                accessor["min"] = [float(v) for v in points.min(axis=0)]
                accessor["max"] = [float(v) for v in points.max(axis=0)]
            if name == "COLOR_0":
                accessor["normalized"] = True
            self.accessors.append(accessor)
            attributes[name] = len(self.accessors) - 1
        self.accessors.append({"componentType": UNSIGNED_INT,
                               "count": int(np.asarray(decoded.faces).size), "type": "SCALAR"})
        extension = {"bufferView": self.view(bytes(encoded)),
                     "attributes": {name: int(by_type[_DRACO_TYPES[name]]["unique_id"])
                                    for name in names}}
        return {"attributes": attributes, "indices": len(self.accessors) - 1,
                "extensions": {DRACO: extension}}


def _parts(rows: NDArray[np.integer]) -> Iterator[NDArray[np.integer]]:
    """``rows`` in slices of :data:`GATHER_ROWS`."""
    for start in range(0, len(rows), GATHER_ROWS):
        yield rows[start:start + GATHER_ROWS]


def _number(value: np.generic) -> float | int:
    return int(value) if np.issubdtype(value.dtype, np.integer) else float(value)


def glb_bytes(mesh: MeshModel, name: str = "scan", provenance: Mapping[str, Any] | None = None,
              draco: bool = False) -> bytes:
    """:func:`glb_pieces` joined: the GLB as one bytes object (to embed it elsewhere)."""
    return file_bytes(glb_pieces(mesh, name, provenance, draco))


def glb_pieces(mesh: MeshModel, name: str = "scan",
               provenance: Mapping[str, Any] | None = None, draco: bool = False) -> Stream:
    """The mesh as one GLB file, made piece by piece as it is written (the arrays' buffers
    are not joined; positions and normals are gathered per vertex only then):
    ``provenance`` in ``asset.extras.scanpipe``, the geometry Draco-compressed with
    ``draco``."""
    if len(mesh.faces) == 0:
        raise ExportError("mesh has no faces: a glTF mesh needs at least one triangle")
    normals = unit_normals(mesh)
    builder = _Builder()
    primitives: list[dict[str, Any]] = []
    materials: list[dict[str, Any]] = []
    images: list[dict[str, Any]] = []
    textures: list[dict[str, Any]] = []
    pages = mesh.face_pages if mesh.textured else None
    page_ids = [] if pages is None else sorted(int(p) for p in np.unique(pages) if p >= 0)

    def add_primitive(source: NDArray[np.int64], indices: NDArray[np.integer],
                      uv: NDArray[np.float32] | None, material: int) -> None:
        rgba = None if uv is not None or mesh.colors is None else np.concatenate(
            [mesh.colors[source], np.full((len(source), 1), 255, np.uint8)], axis=1)
        if draco:
            primitive = builder.draco_primitive(mesh.vertices[source].astype(np.float32),
                                                normals[source], indices, uv, rgba)
            primitives.append({**primitive, "material": material, "mode": 4})
            return
        # positions and normals gathered while the file is written; the rest are views
        attributes = {
            "POSITION": builder.gathered(np.asarray(mesh.vertices, np.float32), source, "VEC3",
                                         FLOAT, ARRAY_BUFFER, bounds=True),
            "NORMAL": builder.gathered(normals, source, "VEC3", FLOAT, ARRAY_BUFFER),
        }
        if uv is not None:
            attributes["TEXCOORD_0"] = builder.accessor(np.asarray(uv, np.float32), "VEC2",
                                                        FLOAT, ARRAY_BUFFER)
        elif rgba is not None:
            attributes["COLOR_0"] = builder.accessor(rgba, "VEC4", UNSIGNED_BYTE,
                                                     ARRAY_BUFFER, normalized=True)
        index_accessor = builder.accessor(np.asarray(indices, np.uint32), "SCALAR",
                                          UNSIGNED_INT, ELEMENT_ARRAY_BUFFER)
        primitives.append({"attributes": attributes, "indices": index_accessor,
                           "material": material, "mode": 4})

    for page in page_ids:
        assert pages is not None and mesh.face_uvs is not None
        source, uv, inverse = mesh.page_splits[page]  # shared with OBJ
        image = len(images)
        images.append({"bufferView": builder.view(mesh.pages[page]), "mimeType": "image/png",
                       "name": f"page{page}"})
        textures.append({"sampler": 0, "source": image})
        materials.append({
            "name": f"page{page}",
            "pbrMetallicRoughness": {"baseColorTexture": {"index": len(textures) - 1},
                                     "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "doubleSided": True,
        })
        add_primitive(source, inverse, uv, len(materials) - 1)

    plain = (np.arange(len(mesh.faces)) if pages is None
             else np.flatnonzero(pages < 0))
    if len(plain):
        corners = mesh.faces[plain].reshape(-1).astype(np.int64)
        plain_source, plain_index = np.unique(corners, return_inverse=True)
        grey = 1.0 if mesh.colors is not None else 0.7
        materials.append({
            "name": "untextured",
            "pbrMetallicRoughness": {"baseColorFactor": [grey, grey, grey, 1.0],
                                     "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "doubleSided": True,
        })
        add_primitive(plain_source.astype(np.int64), plain_index.ravel(), None,
                      len(materials) - 1)

    node: dict[str, Any] = {"name": name, "mesh": 0}
    extras: dict[str, Any] = {"scanpipe": dict(provenance or {})}
    if any(mesh.offset_m):  # glTF is y up, as the rig frame: the offset as it is
        node["translation"] = [float(v) for v in mesh.offset_m]
        extras["scanpipe_offset_m"] = node["translation"]
    document: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": f"scanpipe {__version__}",
                  "extras": extras},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0]}],
        "nodes": [node],
        "meshes": [{"name": name, "primitives": primitives}],
        "materials": materials,
        "accessors": builder.accessors,
        "bufferViews": builder.views,
        "buffers": [{"byteLength": builder.offset}],
    }
    if draco:
        document["extensionsUsed"] = document["extensionsRequired"] = [DRACO]
    if images:
        document["images"] = images
        document["textures"] = textures
        document["samplers"] = [{"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR,
                                 "wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE}]
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    total = 12 + 8 + len(text) + 8 + builder.offset
    head = (struct.pack("<4sII", b"glTF", 2, total), struct.pack("<I4s", len(text), b"JSON"),
            text, struct.pack("<I4s", builder.offset, b"BIN\0"))
    blobs = builder.blobs

    def pieces() -> Iterator[bytes | memoryview]:
        # neither the binary chunk nor the file is assembled; gathers are made one by one
        yield from head
        for blob in blobs:
            if callable(blob):
                yield from blob()
            else:
                yield blob

    return Stream(pieces)
