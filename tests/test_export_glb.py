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
