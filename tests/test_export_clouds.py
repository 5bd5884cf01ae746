"""PLY, LAS/LAZ and E57: each read back by its library and by a small independent reader."""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import laspy
import numpy as np
import open3d as o3d
import pyarrow as pa
import pye57
import trimesh
from result_tables import RED, points_table, textured_quad

from scanpipe.artifacts import file_bytes
from scanpipe.exporters.las import adjusted_gps_time_s
from scanpipe.exporting import write_files
from scanpipe.stages.export import export_files


def _cloud(table: pa.Table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
    rgb = np.stack([table.column(c).to_numpy() for c in ("red", "green", "blue")], 1)
    return xyz, rgb, table.column("echo").to_numpy()


def _z_up(xyz: np.ndarray) -> np.ndarray:
    return np.stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]], 1)


def _write(tables: dict, fmt: str, tmp_path: Path, stem: str = "scan") -> Path:
    return write_files(export_files(tables, fmt, stem), tmp_path)[0]  # the main file


# -- PLY ---------------------------------------------------------------------------------------


def test_ply_cloud_in_open3d_and_trimesh(tmp_path: Path) -> None:
    table = points_table()
    xyz, rgb, echo = _cloud(table)
    path = _write({"points": table}, "ply", tmp_path)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    cloud = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(cloud.points), xyz, atol=1e-6)
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, rgb, atol=0.5)
    loaded = trimesh.load(path)
    assert isinstance(loaded, trimesh.PointCloud) and len(loaded.vertices) == len(xyz)
    np.testing.assert_array_equal(loaded.metadata["_ply_raw"]["vertex"]["data"]["intensity"],
                                  echo)
    # Open3D's tensor reader keeps a float scalar property (it skipped the ushort one)
    tensor = o3d.t.io.read_point_cloud(str(path))
    assert "intensity" in tensor.point
    np.testing.assert_array_equal(tensor.point["intensity"].numpy().ravel(), echo)


def test_ply_mesh_takes_vertex_colours_from_the_texture(tmp_path: Path) -> None:
    path = _write(textured_quad(), "ply", tmp_path, "quad")
    mesh = trimesh.load(path, process=False)
    assert len(mesh.faces) == 2 and len(mesh.vertices) == 4
    top_left = int(np.argmin(np.linalg.norm(mesh.vertices - [0, 1, 0], axis=1)))
    assert tuple(mesh.visual.vertex_colors[top_left, :3]) == RED
    o3d_mesh = o3d.io.read_triangle_mesh(str(path))
    assert len(o3d_mesh.triangles) == 2 and o3d_mesh.has_vertex_colors()
    assert o3d_mesh.has_vertex_normals()
    np.testing.assert_allclose(np.asarray(o3d_mesh.vertex_normals), [[0, 0, 1]] * 4)


# -- LAS / LAZ -----------------------------------------------------------------------------------


def _las_header(data: bytes) -> dict:
    """The few LAS 1.2 header fields needed, read with struct (independent of laspy)."""
    assert data[:4] == b"LASF"
    scale = struct.unpack_from("<3d", data, 131)
    offset = struct.unpack_from("<3d", data, 155)
    bounds = struct.unpack_from("<6d", data, 179)  # max x, min x, max y, min y, max z, min z
    return {"version": (data[24], data[25]), "format": data[104] & 0x3F,
            "count": struct.unpack_from("<I", data, 107)[0], "scale": scale, "offset": offset,
            "min": bounds[1::2], "max": bounds[0::2]}


def test_las_and_laz_are_z_up_with_intensity_colour_and_time(tmp_path: Path) -> None:
    table = points_table()
    xyz, rgb, echo = _cloud(table)
    expected = _z_up(xyz)
    for fmt in ("las", "laz"):
        path = _write({"points": table}, fmt, tmp_path)
        las = laspy.read(path)
        assert las.header.point_count == len(xyz)
        np.testing.assert_allclose(np.stack([las.x, las.y, las.z], 1), expected, atol=1e-4)
        np.testing.assert_array_equal(np.asarray(las.intensity), echo)
        np.testing.assert_array_equal(np.asarray(las.red), rgb[:, 0].astype(np.uint16) * 257)
        np.testing.assert_allclose(np.asarray(las.gps_time),
                                   adjusted_gps_time_s(table.column("time_ns").to_numpy()),
                                   atol=1e-6)
        header = _las_header(path.read_bytes())
        assert header["count"] == len(xyz) and header["version"] == (1, 2)
        assert header["format"] == 3
        np.testing.assert_allclose(header["min"], expected.min(axis=0), atol=1e-4)
        np.testing.assert_allclose(header["max"], expected.max(axis=0), atol=1e-4)
    assert laspy.read(tmp_path / "scan.laz").header.are_points_compressed


def test_las_without_colour_or_echo_uses_a_plain_point_format(tmp_path: Path) -> None:
    table = points_table(colors=False, echo=False)
    las = laspy.read(_write({"points": table}, "las", tmp_path))
    assert las.header.point_format.id == 1
    assert int(np.asarray(las.intensity).max()) == 0


# -- E57 -------------------------------------------------------------------------------------------


def _e57_xml(data: bytes) -> ET.Element:
    """The XML section of an E57 file, read from its pages (1020 data bytes + CRC each)."""
    assert data[:8] == b"ASTM-E57"
    xml_offset, xml_length, page_size = struct.unpack_from("<QQQ", data, 24)
    payload, position = bytearray(), xml_offset
    while len(payload) < xml_length:
        page_start = position - position % page_size
        end = page_start + page_size - 4
        payload += data[position:end]
        position = end + 4
    text = bytes(payload[:xml_length]).decode()
    return ET.fromstring(re.sub(r'\sxmlns(:\w+)?="[^"]+"', "", text, count=0))


def test_e57_in_pye57_and_from_its_xml(tmp_path: Path) -> None:
    table = points_table()
    xyz, rgb, echo = _cloud(table)
    expected = _z_up(xyz)
    path = _write({"points": table}, "e57", tmp_path)
    reader = pye57.E57(str(path))
    assert reader.scan_count == 1
    scan = reader.read_scan_raw(0)
    np.testing.assert_allclose(np.stack([scan["cartesianX"], scan["cartesianY"],
                                         scan["cartesianZ"]], 1), expected, atol=1e-5)
    np.testing.assert_allclose(scan["intensity"], echo)
    np.testing.assert_array_equal(scan["colorRed"], rgb[:, 0])
    reader.close()
    root = _e57_xml(path.read_bytes())
    points = root.find("./data3D/vectorChild/points")
    assert points is not None and int(points.get("recordCount", "-1")) == len(xyz)
    bounds = root.find("./data3D/vectorChild/cartesianBounds")
    assert bounds is not None
    for axis, column in zip("xyz", expected.T, strict=True):
        assert abs(float(bounds.findtext(f"{axis}Minimum")) - column.min()) < 1e-5
        assert abs(float(bounds.findtext(f"{axis}Maximum")) - column.max()) < 1e-5


def test_cloud_formats_need_points() -> None:
    import pytest

    from scanpipe.errors import ArtifactError

    for fmt in ("las", "laz", "e57"):
        with pytest.raises(ArtifactError, match="needs a points artifact"):
            export_files(textured_quad(), fmt, "x")


def test_chain_cloud_ply_is_the_points_beside_a_mesh(tmp_path: Path) -> None:
    """The chain's ``cloud.ply`` holds the points, not the mesh (which is model.*)."""
    from scanpipe.progress import no_progress
    from scanpipe.stages.export import ExportStageParams, export_stage

    tables = {**textured_quad(), "points": points_table()}
    result = export_stage(tables, ExportStageParams(), no_progress)
    assert set(result.files) >= {"model.obj", "model.glb", "cloud.ply"}
    write_files(result.files, tmp_path)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    expected, colours, _ = _cloud(points_table())
    np.testing.assert_allclose(np.asarray(cloud.points), expected, atol=1e-6)
    assert b"element face" not in file_bytes(result.files["cloud.ply"])[:2000]
    np.testing.assert_array_equal(np.rint(np.asarray(cloud.colors) * 255), colours)
