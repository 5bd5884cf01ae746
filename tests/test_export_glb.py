"""GLB export: the Khronos glTF-Validator, trimesh and Open3D, and the container's structure."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from result_tables import RED, points_table, textured_box, textured_quad

from scanpipe.exporting import write_files
from scanpipe.stages.export import export_files

REPO = Path(__file__).resolve().parents[1]
#: Installed by ./run.sh setup (npm install into .cache/gltf-validator).
VALIDATOR = Path(os.environ.get("SCANPIPE_GLTF_VALIDATOR",
                                REPO / ".cache" / "gltf-validator" / "node_modules"
                                / "gltf-validator"))
VALIDATE_JS = """
const validator = require(process.argv[1]);
const data = new Uint8Array(require('fs').readFileSync(process.argv[2]));
validator.validateBytes(data, {maxIssues: 200})
  .then(report => console.log(JSON.stringify(report.issues)))
  .catch(err => { console.error(String(err)); process.exit(3); });
"""


def _glb(tables: dict, tmp_path: Path, stem: str = "model") -> Path:
    write_files(export_files(tables, "glb", stem), tmp_path)
    return tmp_path / f"{stem}.glb"


def _chunks(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_length % 4 == 0
    document = json.loads(data[20:20 + json_length])
    bin_length, bin_type = struct.unpack_from("<I4s", data, 20 + json_length)
    assert bin_type == b"BIN\0" and bin_length % 4 == 0
    binary = data[28 + json_length:28 + json_length + bin_length]
    assert len(binary) == bin_length == document["buffers"][0]["byteLength"]
    return document, binary


def validate(path: Path) -> dict:
    node = shutil.which("node")
    assert node, "node is needed for the glTF-Validator test"
    assert VALIDATOR.is_dir(), (f"glTF-Validator not installed at {VALIDATOR}: run ./run.sh setup "
                                "(npm install --prefix .cache/gltf-validator gltf-validator)")
    done = subprocess.run([node, "-e", VALIDATE_JS, str(VALIDATOR), str(path)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    return dict(json.loads(done.stdout))


def test_khronos_validator_reports_no_errors_or_warnings(tmp_path: Path) -> None:
    for name, tables in (("quad", textured_quad()), ("box", textured_box(pages=3)),
                         ("plain", {k: v for k, v in textured_box().items()
                                    if k.startswith("mesh_")})):
        issues = validate(_glb(tables, tmp_path, name))
        assert issues["numErrors"] == 0, (name, issues["messages"])
        assert issues["numWarnings"] == 0, (name, issues["messages"])


def test_structure_alignment_bounds_and_embedded_pngs(tmp_path: Path) -> None:
    tables = textured_box(pages=2, untextured_faces=2)
    document, binary = _chunks(_glb(tables, tmp_path).read_bytes())
    assert document["asset"]["version"] == "2.0"
    primitives = document["meshes"][0]["primitives"]
    assert len(primitives) == 3  # two pages and the untextured faces
    assert sum(document["accessors"][p["indices"]]["count"] for p in primitives) == 12 * 3
    for view in document["bufferViews"]:
        assert view["byteOffset"] % 4 == 0
    pngs = tables["texture_pages"].column("png").to_pylist()
    for image, png in zip(document["images"], pngs, strict=True):
        view = document["bufferViews"][image["bufferView"]]
        assert image["mimeType"] == "image/png"
        assert binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]] == png
    for primitive in primitives:
        position = document["accessors"][primitive["attributes"]["POSITION"]]
        view = document["bufferViews"][position["bufferView"]]
        xyz = np.frombuffer(binary, np.float32, position["count"] * 3,
                            view["byteOffset"]).reshape(-1, 3)
        assert position["min"] == xyz.min(axis=0).tolist()
        assert position["max"] == xyz.max(axis=0).tolist()


def test_trimesh_reads_counts_bounds_and_an_upright_texture(tmp_path: Path) -> None:
    scene = trimesh.load(_glb(textured_quad(), tmp_path), process=False)
    (mesh,) = scene.geometry.values()
    assert len(mesh.faces) == 2
    np.testing.assert_allclose(mesh.bounds, [[0, 0, 0], [1, 1, 0]], atol=1e-7)
    image = mesh.visual.material.baseColorTexture
    assert image.size == (64, 64)
    i = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 1, 0], axis=1)))
    color = trimesh.visual.color.uv_to_color((mesh.visual.uv[i] * 0.96 + 0.02)[None], image)
    assert tuple(int(c) for c in color[0, :3]) == RED


def test_open3d_reads_counts_bounds_and_textures(tmp_path: Path) -> None:
    tables = textured_box(pages=2)
    path = _glb(tables, tmp_path)
    mesh = o3d.io.read_triangle_mesh(str(path), True)
    assert len(mesh.triangles) == 12
    np.testing.assert_allclose(mesh.get_min_bound(), [-2.0, -1.2, -2.5], atol=1e-6)
    np.testing.assert_allclose(mesh.get_max_bound(), [2.0, 1.8, 2.5], atol=1e-6)
    model = o3d.io.read_triangle_model(str(path))
    assert len(model.materials) == 3
    assert sum(1 for m in model.materials if m.albedo_img is not None) == 2


def test_glb_needs_a_mesh_with_faces() -> None:
    import pytest

    from scanpipe.errors import ArtifactError, ExportError

    with pytest.raises(ArtifactError, match="glb export needs a mesh"):
        export_files({"points": points_table()}, "glb", "x")
    tables = textured_quad()
    empty = {"mesh_vertices": tables["mesh_vertices"],
             "mesh_faces": tables["mesh_faces"].slice(0, 0)}
    with pytest.raises(ExportError, match="no faces"):
        export_files(empty, "glb", "x")


def _draco_glb(tables: dict, tmp_path: Path, stem: str) -> Path:
    write_files(export_files(tables, "glb", stem, draco=True), tmp_path)
    return tmp_path / f"{stem}.glb"


def _plain_rows(document: dict, binary: bytes, primitive: dict) -> np.ndarray:
    """Per vertex (x, y, z, u, v) of an uncompressed primitive (u = v = 0 untextured)."""
    def read(accessor_index: int, width: int) -> np.ndarray:
        accessor = document["accessors"][accessor_index]
        view = document["bufferViews"][accessor["bufferView"]]
        return np.frombuffer(binary, np.float32, accessor["count"] * width,
                             view["byteOffset"]).reshape(-1, width)

    xyz = read(primitive["attributes"]["POSITION"], 3)
    uv = (read(primitive["attributes"]["TEXCOORD_0"], 2) if "TEXCOORD_0" in
          primitive["attributes"] else np.zeros((len(xyz), 2), np.float32))
    return np.hstack([xyz, uv]).astype(np.float64)


def _canonical_triangles(corners: np.ndarray) -> np.ndarray:
    """Triangles (n, 3 corners, xyz) as rows that ignore which corner comes first but keep the
    winding: each rotated to start at its smallest corner, then the rows sorted."""
    rounded = np.round(corners, 3)
    key = rounded @ np.array([1e6, 1e3, 1.0])
    first = np.argmin(key, axis=1)
    order = (first[:, None] + np.arange(3)[None, :]) % 3
    rotated = np.take_along_axis(rounded, order[:, :, None], axis=1).reshape(len(corners), 9)
    return rotated[np.lexsort(rotated.T[::-1])]


def test_draco_glb_passes_the_validator_and_decodes_to_the_same_mesh(tmp_path: Path) -> None:
    """KHR_draco_mesh_compression: the validator checks the document around the bitstreams (it
    cannot decode them and says so as an info); Draco's own decoder gives back every triangle
    with positions within the 16-bit quantum and texture coordinates within the 14-bit one."""
    import DracoPy
    from scipy.spatial import cKDTree

    for name, tables in (("quad", textured_quad()), ("box", textured_box(pages=3)),
                         ("plain", {k: v for k, v in textured_box().items()
                                    if k.startswith("mesh_")})):
        packed = _draco_glb(tables, tmp_path / "draco", name)
        issues = validate(packed)
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, (name, issues)
        codes = {m["code"] for m in issues["messages"]}
        assert "UNSUPPORTED_EXTENSION" in codes  # the validator did not decode the geometry
        document, binary = _chunks(packed.read_bytes())
        plain_document, plain_binary = _chunks(_glb(tables, tmp_path, name).read_bytes())
        assert document["extensionsRequired"] == ["KHR_draco_mesh_compression"]
        primitives = document["meshes"][0]["primitives"]
        plain_primitives = plain_document["meshes"][0]["primitives"]
        assert len(primitives) == len(plain_primitives)
        assert len(packed.read_bytes()) > 0
        for primitive, plain in zip(primitives, plain_primitives, strict=True):
            extension = primitive["extensions"]["KHR_draco_mesh_compression"]
            assert "bufferView" not in document["accessors"][primitive["indices"]]
            view = document["bufferViews"][extension["bufferView"]]
            mesh = DracoPy.decode(binary[view["byteOffset"]:view["byteOffset"]
                                         + view["byteLength"]])
            by_id = {a["unique_id"]: np.asarray(a["data"]) for a in mesh.attributes}
            xyz = by_id[extension["attributes"]["POSITION"]]
            uv = (by_id[extension["attributes"]["TEXCOORD_0"]]
                  if "TEXCOORD_0" in extension["attributes"] else np.zeros((len(xyz), 2)))
            rows = np.hstack([xyz, uv])
            expected = _plain_rows(plain_document, plain_binary, plain)
            position = document["accessors"][primitive["attributes"]["POSITION"]]
            assert position["count"] == len(xyz)
            np.testing.assert_allclose(position["min"], xyz.min(axis=0), atol=1e-6)
            np.testing.assert_allclose(position["max"], xyz.max(axis=0), atol=1e-6)
            extent = float(np.ptp(expected[:, :3], axis=0).max())
            tolerance = extent / 2**16 + 1 / 2**14
            # every decoded vertex is an original one and every original is decoded
            assert cKDTree(expected).query(rows)[0].max() <= tolerance, name
            assert cKDTree(rows).query(expected)[0].max() <= tolerance, name
            # the same triangles, as sets of corner positions
            faces = np.asarray(mesh.faces).reshape(-1, 3)
            plain_count = plain_document["accessors"][plain["indices"]]["count"] // 3
            assert len(faces) == plain_count
            corners = _canonical_triangles(xyz[faces])
            indices_view = plain_document["bufferViews"][
                plain_document["accessors"][plain["indices"]]["bufferView"]]
            plain_faces = np.frombuffer(plain_binary, np.uint32, plain_count * 3,
                                        indices_view["byteOffset"]).reshape(-1, 3)
            want = _canonical_triangles(expected[plain_faces, :3])
            np.testing.assert_allclose(corners, want, atol=2e-3)


def test_draco_makes_a_large_mesh_several_times_smaller(tmp_path: Path) -> None:
    from scanpipe.exporters.glb import glb_bytes
    from scanpipe.exporters.model import MeshModel

    n = 200
    u, v = np.meshgrid(np.linspace(0, 4, n), np.linspace(0, 3, n))
    vertices = np.stack([u.ravel(), v.ravel(), 0.05 * np.sin(u.ravel() * 3)], 1)
    cell = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([cell, cell + 1, cell + n], 1),
                            np.stack([cell + 1, cell + n + 1, cell + n], 1)]).astype(np.int32)
    mesh = MeshModel(vertices.astype(np.float32), faces)
    plain, packed = glb_bytes(mesh), glb_bytes(mesh, draco=True)
    assert len(packed) * 5 < len(plain), (len(packed), len(plain))


def test_glb_carries_its_provenance_in_asset_extras(tmp_path: Path) -> None:
    from scanpipe.exporters.glb import glb_bytes
    from scanpipe.exporters.model import mesh_from_tables

    tables = textured_quad()
    mesh = mesh_from_tables(tables["mesh_vertices"], tables["mesh_faces"])
    record = {"scanpipe": "9.9", "artifacts": {"mesh_faces": {"key": "abc", "stage": "mesh"}}}
    for draco in (False, True):
        document, _ = _chunks(glb_bytes(mesh, "m", record, draco=draco))
        assert document["asset"]["extras"]["scanpipe"] == record
