"""Wavefront OBJ + MTL + PNG, the paper's output format, written with numpy.

- ``vt`` has v = 0 at the image *bottom* (OBJ), so the glTF-convention UVs of the texture
  stage are flipped: ``v_obj = 1 − v_gltf``.
- Each atlas page is one material (``Kd 1 1 1`` with ``map_Kd``: the texture is multiplied by
  Kd, so anything but white would tint it); faces are grouped per page under ``usemtl``.
- Every file name derives from the output stem (``room.obj``, ``room.mtl``,
  ``room_page0.png``), with relative paths, so two exports into one folder never collide.
- Lines are formatted column-wise with numpy (:mod:`scanpipe.exporters.textfmt`), in blocks
  that stay apart (:class:`~scanpipe.artifacts.Pieces`): the text is held once, never joined.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe import __version__
from scanpipe.artifacts import FileData, Pieces
from scanpipe.errors import ExportError
from scanpipe.exporters.model import (
    PROVENANCE_TAG,
    MeshModel,
    provenance_bytes,
    unit_normals,
)
from scanpipe.exporters.textfmt import Fixed, Ints, Part, float_rows, render_blocks
from scanpipe.images import encode_png

#: Untextured faces get a 2×2 map of this grey (0.7 of full scale): readers such as Open3D
#: treat a mesh as textured only when every material has an image.
UNTEXTURED_GREY = 179


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
                vt_offset: int = 0) -> list[bytes]:
    """``f`` lines for the faces ``faces[rows]`` (all with ``rows`` None; 0-based) with
    1-based ``v[/vt][/vn]`` references; ``vt`` gives each corner's texture coordinate (an
    array of ``(len(rows), 3)``, 0-based, plus ``vt_offset``) or one for every corner (an
    int)."""
    count = len(faces) if rows is None else len(rows)
    out: list[bytes] = []
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
        out += render_blocks(stop - start, parts)
    return out


def obj_files(mesh: MeshModel, stem: str,
              provenance: Mapping[str, Any] | None = None) -> dict[str, FileData]:
    """The OBJ export of ``mesh`` as ``{file name: content}`` (``<stem>.obj`` comes first, as
    :class:`~scanpipe.artifacts.Pieces`), with
    the ``provenance`` record as a ``# scanpipe-provenance {json}`` comment in OBJ and MTL."""
    finite = np.isfinite(mesh.vertices).all(axis=1)
    if not finite.all():  # OBJ text has no number for them: refuse rather than print garbage
        bad = np.flatnonzero(~finite)
        raise ExportError(f"mesh_vertices: {len(bad)} vertices have non-finite coordinates "
                          f"(first: vertex {int(bad[0])}); an OBJ needs finite numbers: "
                          "re-run the mesh stage")
    base = safe_stem(stem)
    obj_name, mtl_name = f"{stem}.obj", f"{base}.mtl"
    record = f"{PROVENANCE_TAG} {provenance_bytes(provenance or {}).decode()}"
    chunks: list[bytes] = [f"# scanpipe {__version__} OBJ export; y up, metres\n# {record}\n"
                           .encode()]
    files: dict[str, FileData] = {}
    normals = unit_normals(mesh)
    textured = mesh.textured
    if textured:
        chunks.append(f"mtllib {mtl_name}\n".encode())
    if mesh.colors is not None and not textured:
        # The widespread "v x y z r g b" extension (MeshLab, trimesh, Blender) with 0..1 colours.
        parts: list[Part] = [b"v "]
        for j in range(3):
            parts += [Fixed(mesh.vertices[:, j], 6), b" "]
        for j in range(3):
            parts += [Fixed(mesh.colors[:, j].astype(np.float64) / 255.0, 4)]
            if j < 2:
                parts.append(b" ")
        chunks += render_blocks(len(mesh.vertices), parts)
    else:
        chunks += float_rows(b"v ", mesh.vertices, 6)
    chunks += float_rows(b"vn ", normals, 5)
    if not textured:
        chunks += _face_lines(mesh.faces, None, None, True)
        files[obj_name] = Pieces(tuple(chunks))
        return files

    assert mesh.face_pages is not None and mesh.face_uvs is not None
    order = np.argsort(mesh.face_pages, kind="stable")
    pages_sorted = mesh.face_pages[order]
    # a vertex's corners on one page with one UV share a vt (the split GLB uses too)
    splits = mesh.page_splits
    vt_uv = np.concatenate([splits[page][1] for page in sorted(splits)])
    vt_counts = [len(splits[page][1]) for page in sorted(splits)]
    vt_start = dict(zip(sorted(splits), np.cumsum([0, *vt_counts[:-1]]).tolist(), strict=True))
    uv_obj = np.stack([vt_uv[:, 0].astype(np.float64), 1.0 - vt_uv[:, 1].astype(np.float64)],
                      axis=1)
    # Untextured faces get one shared vt too: readers such as Open3D drop every UV of a mesh in
    # which some faces have none. It samples their material's plain grey map.
    plain_vt = len(uv_obj)
    chunks += float_rows(b"vt ", np.vstack([uv_obj, [[0.0, 0.0]]]), 6)
    del uv_obj, vt_uv  # the text holds them now
    mtl: list[str] = [f"# scanpipe {__version__} materials for {obj_name}", f"# {record}"]
    page_ids, starts, counts = np.unique(pages_sorted, return_index=True, return_counts=True)
    for page, start, count in zip(page_ids.tolist(), starts.tolist(), counts.tolist(),
                                  strict=True):
        rows = order[start:start + count]
        if page < 0:
            material = f"{base}_untextured"
            plain_name = f"{base}_untextured.png"
            mtl += ["", f"newmtl {material}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0",
                    "d 1", "illum 1", f"map_Kd {plain_name}"]
            files[plain_name] = encode_png(np.full((2, 2, 3), UNTEXTURED_GREY, np.uint8))
            chunks.append(f"usemtl {material}\n".encode())
            chunks += _face_lines(mesh.faces, rows, plain_vt, True)
            continue
        material = f"{base}_page{page}"
        png = page_file_name(stem, page)
        mtl += ["", f"newmtl {material}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "d 1",
                "illum 1", f"map_Kd {png}"]
        files[png] = mesh.pages[page]
        chunks.append(f"usemtl {material}\n".encode())
        # the page's faces in index order, as its split has its corners
        chunks += _face_lines(mesh.faces, rows, splits[page][2].reshape(-1, 3), True,
                              vt_start[page])
    files = {obj_name: Pieces(tuple(chunks)), mtl_name: ("\n".join(mtl) + "\n").encode(), **files}
    return files
