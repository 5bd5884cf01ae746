"""The exporters' bytes are pinned: a speed-up must not change one byte of OBJ, MTL, GLB or PLY.

The digests were computed with the exporters before they were optimised (issue 20); the version
string is pinned so that a release does not change them.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from result_tables import (
    faces_table,
    pages_table,
    points_table,
    quadrant_png,
    textured_faces_table,
    vertices_table,
)

from scanpipe.artifacts import file_sha256
from scanpipe.exporters import glb, obj, ply, textfmt
from scanpipe.stages.export import export_files


def golden_mesh(textured: bool, seed: int = 3) -> dict[str, pa.Table]:
    """A seeded mesh of 30 000 vertices in ±12 m (indices of 1–5 digits, negative and
    sub-millimetre coordinates, some zero normals), on two pages with seams and untextured
    faces when ``textured``, else with vertex colours."""
    rng = np.random.default_rng(seed)
    n_vertices, n_faces = 30_000, 60_000
    xyz = (rng.standard_normal((n_vertices, 3)) * 4.0).clip(-12, 12).astype(np.float32)
    xyz[:50] = rng.random((50, 3)) * 1e-4 - 5e-5
    normals = rng.standard_normal((n_vertices, 3)).astype(np.float32)
    normals[::7] = 0.0  # rebuilt from the faces
    faces = rng.integers(0, n_vertices, (n_faces, 3), dtype=np.int32)
    colours = rng.integers(0, 256, (n_vertices, 3), dtype=np.uint8)
    tables = {"mesh_vertices": vertices_table(xyz, normals, None if textured else colours),
              "mesh_faces": faces_table(faces)}
    if textured:
        face = np.arange(n_faces)
        page = rng.integers(-1, 2, n_faces).astype(np.int16)
        # few distinct UVs so that corners share them (and vertices split at seams)
        uvs = (rng.integers(0, 64, (n_faces, 3, 2)) / 64.0).astype(np.float32)
        tables["textured_faces"] = textured_faces_table(face, page, uvs)
        tables["texture_pages"] = pages_table({0: quadrant_png(32), 1: quadrant_png(48)})
    return tables


#: sha256 (first 16 hex digits) of each file, by (format, textured), before the speed-up.
GOLDEN_MESH: dict[tuple[str, bool], dict[str, str]] = {
    # vt lines shared per atlas page since export stage v6 (one UV split per model for
    # OBJ and GLB): a vertex's corners on its second page that repeat one UV share a vt
    # instead of each getting its own (was "18df2bbb0f302eac")
    ("obj", True): {"golden.obj": "4263638b94693cbb", "golden.mtl": "6b13c4d17422de26"},
    ("obj", False): {"golden.obj": "3c63c77af02b1c2b"},
    ("glb", True): {"golden.glb": "2f91a60d485688ab"},
    ("glb", False): {"golden.glb": "ae160a9183555f96"},
    ("ply", True): {"golden.ply": "df8c6cc32e140706"},
    ("ply", False): {"golden.ply": "c2ca7ea85684d435"},
}
GOLDEN_CLOUD = {"golden.ply": "9e32e6d2500e6ff1"}  # intensity as float (Open3D)


def _digests(tables: dict[str, pa.Table], fmt: str) -> dict[str, str]:
    # the manifest's piece-by-piece hash: the digest of the bytes written
    return {name: file_sha256(data)[:16]
            for name, data in export_files(tables, fmt, "golden").items()
            if not name.endswith(".png")}  # pages pass through; the grey map is the encoder's


@pytest.mark.parametrize("textured", [True, False])
@pytest.mark.parametrize("fmt", ["obj", "glb", "ply"])
def test_mesh_exports_are_byte_identical(monkeypatch: pytest.MonkeyPatch, fmt: str,
                                         textured: bool) -> None:
    for module in (obj, glb, ply):
        monkeypatch.setattr(module, "__version__", "golden")
    got = _digests(golden_mesh(textured), fmt)
    assert got == GOLDEN_MESH[(fmt, textured)]


@pytest.mark.parametrize("textured", [True, False])
def test_obj_in_small_slices_and_blocks_is_byte_identical(monkeypatch: pytest.MonkeyPatch,
                                                          textured: bool) -> None:
    """Faces formatted slice by slice (and lines block by block) give the same file."""
    monkeypatch.setattr(obj, "__version__", "golden")
    tables = golden_mesh(textured)
    assert tables["mesh_faces"].num_rows > 3 * 37  # several slices, one cut mid-page
    monkeypatch.setattr(obj, "FACE_SLICE", 37)
    monkeypatch.setattr(textfmt, "BLOCK_ROWS", 11)
    assert _digests(tables, "obj") == GOLDEN_MESH[("obj", textured)]


def test_cloud_ply_is_byte_identical(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ply, "__version__", "golden")
    assert _digests({"points": points_table(40, 500)}, "ply") == GOLDEN_CLOUD
