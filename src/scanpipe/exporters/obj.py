"""Wavefront OBJ + MTL + PNG, the paper's output format, written with numpy.

- ``vt`` has v = 0 at the image *bottom* (OBJ), so the glTF-convention UVs of the texture
  stage are flipped: ``v_obj = 1 − v_gltf``.
- Each atlas page is one material (``Kd 1 1 1`` with ``map_Kd``: the texture is multiplied by
  Kd, so anything but white would tint it); faces are grouped per page under ``usemtl``.
- Every file name derives from the output stem (``room.obj``, ``room.mtl``,
  ``room_page0.png``), with relative paths, so two exports into one folder never collide.
- A georeferenced mesh (``offset_m``, an import shifted so float32 keeps 0.1 mm) keeps its
  local vertices (Blender, MeshLab and most OBJ readers hold float32: the imported coordinates
  would be rounded to centimetres and lie kilometres from the origin); the offset, in the OBJ's
  own frame (y up), is a ``# scanpipe-offset-m X Y Z`` comment and the sidecar
  ``<stem>_offset.xyz`` (one line ``X Y Z``: add it to every ``v``).
- Lines are formatted column-wise with numpy (:mod:`scanpipe.exporters.textfmt`), block by
  block while the file is written (:class:`~scanpipe.artifacts.Stream`): the text is never
  held whole (≈ 500 MB for the lab scan's 4.8 M faces), and its digest is taken on the way.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe import __version__
from scanpipe.artifacts import FileData, Stream
from scanpipe.errors import ExportError
from scanpipe.exporters.model import (
    PROVENANCE_TAG,
    MeshModel,
    provenance_bytes,
    unit_normals,
)
from scanpipe.exporters.textfmt import Fixed, Ints, Part, float_rows, iter_blocks
from scanpipe.images import encode_png

#: Untextured faces get a 2×2 map of this grey (0.7 of full scale): readers such as Open3D
#: treat a mesh as textured only when every material has an image.
UNTEXTURED_GREY = 179


#: The comment that names a georeferenced OBJ's offset (its own frame: y up, metres).
OFFSET_TAG = "scanpipe-offset-m"


def offset_file_name(stem: str) -> str:
    """The sidecar holding a georeferenced export's offset (``X Y Z``, the OBJ's frame)."""
    return f"{safe_stem(stem)}_offset.xyz"


def safe_stem(stem: str) -> str:
    """The stem with characters that OBJ/MTL statements cannot carry replaced by ``_``."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]", "_", stem)
    return cleaned or "model"


def page_file_name(stem: str, page: int) -> str:
    """The PNG file name of atlas page ``page`` for an export called ``stem``."""
    return f"{safe_stem(stem)}_page{page}.png"


#: Faces formatted per slice: the index columns :func:`_face_lines` makes (six of them, with
#: the ``+ 1``) are temporaries of one slice, not of the whole mesh (≈ 300 MB at 4.8 M faces).
FACE_SLICE = 1 << 18


def _face_lines(faces: NDArray[np.integer], rows: NDArray[np.integer] | None,
                vt: NDArray[np.integer] | int | None, with_normals: bool,
                vt_offset: int = 0) -> Iterator[bytes]:
    """``f`` lines for the faces ``faces[rows]`` (all with ``rows`` None; 0-based) with
    1-based ``v[/vt][/vn]`` references, block by block as asked for; ``vt`` gives each
    corner's texture coordinate (an array of ``(len(rows), 3)``, 0-based, plus ``vt_offset``)
    or one for every corner (an int)."""
    count = len(faces) if rows is None else len(rows)
    for start in range(0, count, FACE_SLICE):
        stop = min(count, start + FACE_SLICE)
        group = faces[start:stop] if rows is None else faces[rows[start:stop]]
        corners = (None if vt is None else
                   np.full(group.shape, vt) if isinstance(vt, int) else vt[start:stop] + vt_offset)
        parts: list[Part] = [b"f "]
        for k in range(3):
            if k:
                parts.append(b" ")
            v = Ints(group[:, k] + 1)
            parts.append(v)
            if corners is not None:
                parts += [b"/", Ints(corners[:, k] + 1)]
                if with_normals:
                    parts += [b"/", v]
            elif with_normals:
                parts += [b"//", v]
        yield from iter_blocks(stop - start, parts)


def obj_files(mesh: MeshModel, stem: str,
              provenance: Mapping[str, Any] | None = None) -> dict[str, FileData]:
    """The OBJ export of ``mesh`` as ``{file name: content}`` (``<stem>.obj`` comes first, as
    a :class:`~scanpipe.artifacts.Stream`: its text is formatted block by block while it is
    written, never held whole), with the ``provenance`` record as a
    ``# scanpipe-provenance {json}`` comment in OBJ and MTL."""
    finite = np.isfinite(mesh.vertices).all(axis=1)
    if not finite.all():  # OBJ text has no number for them: refuse rather than print garbage
        bad = np.flatnonzero(~finite)
        raise ExportError(f"mesh_vertices: {len(bad)} vertices have non-finite coordinates "
                          f"(first: vertex {int(bad[0])}); an OBJ needs finite numbers: "
                          "re-run the mesh stage")
    base = safe_stem(stem)
    obj_name, mtl_name = f"{stem}.obj", f"{base}.mtl"
    record = f"{PROVENANCE_TAG} {provenance_bytes(provenance or {}).decode()}"
    head = f"# scanpipe {__version__} OBJ export; y up, metres\n# {record}\n"
    sidecar: dict[str, FileData] = {}
    if any(mesh.offset_m):
        text = " ".join(f"{float(v):.17g}" for v in mesh.offset_m)
        head += (f"# {OFFSET_TAG} {text}\n# georeferenced: add the offset above to every v for "
                 f"the imported coordinates (also in {offset_file_name(stem)})\n")
        sidecar[offset_file_name(stem)] = f"{text}\n".encode()
    if not mesh.textured:
        return {obj_name: Stream(lambda: _plain_obj(mesh, head)), **sidecar}
    assert mesh.face_pages is not None
    # the pages in use (−1: untextured faces), in the order their faces are written
    used = np.flatnonzero(np.bincount(mesh.face_pages.astype(np.int64) + 1)) - 1
    mtl: list[str] = [f"# scanpipe {__version__} materials for {obj_name}", f"# {record}"]
    files: dict[str, FileData] = {}
    for page in used.tolist():
        material, image = (f"{base}_untextured", f"{base}_untextured.png") if page < 0 else (
            f"{base}_page{page}", page_file_name(stem, page))
        mtl += ["", f"newmtl {material}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "d 1",
                "illum 1", f"map_Kd {image}"]
        files[image] = (encode_png(np.full((2, 2, 3), UNTEXTURED_GREY, np.uint8)) if page < 0
                        else mesh.pages[page])
    return {obj_name: Stream(lambda: _textured_obj(mesh, head + f"mtllib {mtl_name}\n", base)),
            mtl_name: ("\n".join(mtl) + "\n").encode(), **files, **sidecar}


def _plain_obj(mesh: MeshModel, head: str) -> Iterator[bytes]:
    """The text of an untextured OBJ, block by block: ``v`` (with colours when the mesh has
    them), ``vn``, ``f v//vn``."""
    yield head.encode()
    if mesh.colors is not None:
        # The widespread "v x y z r g b" extension (MeshLab, trimesh, Blender) with 0..1 colours.
        parts: list[Part] = [b"v "]
        for j in range(3):
            parts += [Fixed(mesh.vertices[:, j], 6), b" "]
        for j in range(3):
            parts += [Fixed(mesh.colors[:, j].astype(np.float64) / 255.0, 4)]
            if j < 2:
                parts.append(b" ")
        yield from iter_blocks(len(mesh.vertices), parts)
    else:
        yield from float_rows(b"v ", mesh.vertices, 6)
    yield from float_rows(b"vn ", unit_normals(mesh), 5)
    yield from _face_lines(mesh.faces, None, None, True)


def _textured_obj(mesh: MeshModel, head: str, base: str) -> Iterator[bytes]:
    """The text of a textured OBJ, block by block: ``v``, ``vn``, the ``vt`` of every page
    (a vertex's corners on one page with one UV share one: the split GLB uses) and one for
    the untextured faces, then each page's faces under its ``usemtl``."""
    assert mesh.face_pages is not None and mesh.face_uvs is not None
    yield head.encode()
    yield from float_rows(b"v ", mesh.vertices, 6)
    yield from float_rows(b"vn ", unit_normals(mesh), 5)
    splits = mesh.page_splits
    vt_uv = np.concatenate([splits[page][1] for page in sorted(splits)])
    vt_counts = [len(splits[page][1]) for page in sorted(splits)]
    vt_start = dict(zip(sorted(splits), np.cumsum([0, *vt_counts[:-1]]).tolist(), strict=True))
    uv_obj = np.stack([vt_uv[:, 0].astype(np.float64), 1.0 - vt_uv[:, 1].astype(np.float64)],
                      axis=1)
    del vt_uv
    # Untextured faces get one shared vt too: readers such as Open3D drop every UV of a mesh in
    # which some faces have none. It samples their material's plain grey map.
    plain_vt = len(uv_obj)
    yield from float_rows(b"vt ", np.vstack([uv_obj, [[0.0, 0.0]]]), 6)
    del uv_obj
    order = np.argsort(mesh.face_pages, kind="stable")
    page_ids, starts, counts = np.unique(mesh.face_pages[order], return_index=True,
                                         return_counts=True)
    for page, start, count in zip(page_ids.tolist(), starts.tolist(), counts.tolist(),
                                  strict=True):
        rows = order[start:start + count]
        if page < 0:
            yield f"usemtl {base}_untextured\n".encode()
            yield from _face_lines(mesh.faces, rows, plain_vt, True)
            continue
        yield f"usemtl {base}_page{page}\n".encode()
        # the page's faces in index order, as its split has its corners
        yield from _face_lines(mesh.faces, rows, splits[page][2].reshape(-1, 3), True,
                               vt_start[page])
