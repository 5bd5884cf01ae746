"""import-points trusts no header: lying counts, bad offsets and garbage are one line each,
refused before anything is allocated; valid files written by other libraries import exactly."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import laspy
import numpy as np
import open3d as o3d
import pyarrow as pa
import pytest
import trimesh

from scanpipe.errors import ArtifactError
from scanpipe.pointio import ImportParams, import_points, read_point_file

POINTS = np.array([[0.5, 1.25, -0.75], [2.0, 0.0, 0.0], [0.0, 0.0, 2.0], [-1.0, -2.0, 0.5],
                   [3.0, 1.0, -2.0]])
COLOURS = np.array([[255, 0, 0], [0, 128, 0], [0, 0, 64], [10, 20, 30], [1, 2, 3]], np.uint8)


def xyz(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1)


def ply_claiming(count: int, fmt: str = "binary_little_endian", size: int = 242) -> bytes:
    """A PLY whose header claims ``count`` vertices, padded with data to ``size`` bytes."""
    header = (f"ply\nformat {fmt} 1.0\nelement vertex {count}\nproperty float x\n"
              "property float y\nproperty float z\nend_header\n").encode()
    body = (b"1 2 3\n" * size) if fmt == "ascii" else np.arange(size, dtype=np.uint8).tobytes()
    return (header + body)[:size]


def write_las(path: Path, version: str = "1.2", point_format: int = 3) -> None:
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = POINTS[:, 0], POINTS[:, 1], POINTS[:, 2]
    las.red, las.green, las.blue = (COLOURS[:, k].astype(np.uint16) * 257 for k in range(3))
    las.write(str(path))


def patch(path: Path, offset: int, fmt: str, value: int) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))


def las_claiming(path: Path, count: int, version: str = "1.2") -> Path:
    write_las(path, version, 3 if version == "1.2" else 7)
    if count < 2**32:
        patch(path, 107, "<I", count)
    if version == "1.4":
        patch(path, 247, "<Q", count)
    return path


@pytest.mark.parametrize(("count", "fmt", "size"), [
    (10_000_000, "binary_little_endian", 242),
    (2_000_000_000, "binary_big_endian", 242),
    (1_000_000_000, "ascii", 242),
    (100, "ascii", 242),  # 100 × 3 values need ≥ 600 characters
])
def test_ply_header_counts_are_checked_against_the_size(tmp_path: Path, count: int, fmt: str,
                                                        size: int) -> None:
    path = tmp_path / "liar.ply"
    path.write_bytes(ply_claiming(count, fmt, size))
    assert path.stat().st_size == size
    with pytest.raises(ArtifactError, match=rf"liar.ply: PLY header field 'element vertex "
                                            rf"{count}' needs at least \d+ bytes"):
        read_point_file(path)


def test_ascii_ply_with_fewer_lines_than_claimed_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "short.ply"
    # 40 vertices × 3 values fit the size bound (long lines), but there are only 2 lines.
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 40\nproperty float x\n"
                     b"property float y\nproperty float z\nend_header\n"
                     + b"1.000000000000 2 3\n" * 2 + b" " * 300)
    with pytest.raises(ArtifactError, match=r"'element vertex 40'.*2 lines of 3 numbers"):
        read_point_file(path)


@pytest.mark.parametrize(("content", "message"), [
    (b"ply\nformat binary_little_endian 1.0\nelement vertex -5\nend_header\n",
     "header line 3 'element vertex -5' is not valid"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quad x\nend_header\n",
     "header line 4 'property quad x' is not valid"),
    (b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n",
     "PLY format 'binary_middle_endian'"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n" + b"\xff" * 40,
     "no 'end_header' line"),
    (b"ply\nformat ascii 1.0\nelement face 1\nproperty float x\nend_header\n1\n",
     "no 'vertex' element"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
     b"end_header\n1 2\n", "no property z"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n1 2 3\n\xff\xfe 5 6\n", "not a table of 3 numbers"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
     b"property float y\nproperty float z\nend_header\n", "0 vertices"),
])
def test_malformed_ply_is_one_clear_error(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(ArtifactError, match=message):
        read_point_file(path)


@pytest.mark.parametrize(("count", "version"), [(100_000_000, "1.2"), (4_000_000_000, "1.2"),
                                                (4_000_000_000, "1.4")])
def test_las_point_count_is_checked_against_the_size(tmp_path: Path, count: int,
                                                     version: str) -> None:
    path = las_claiming(tmp_path / "liar.las", count, version)
    assert path.stat().st_size < 1000
    with pytest.raises(ArtifactError, match=rf"liar.las: LAS header field 'number of point "
                                            rf"records' is {count}: .* exceed"):
        read_point_file(path)


def test_laz_point_count_is_bounded_by_the_size(tmp_path: Path) -> None:
    path = tmp_path / "liar.laz"
    write_las(path)
    patch(path, 107, "<I", 100_000_000)
    with pytest.raises(ArtifactError, match=r"'number of point records' is 100000000; .* cannot "
                                            r"hold that many"):
        read_point_file(path)


@pytest.mark.parametrize(("offset", "message"), [
    (10**6, "'offset to point data' is 1000000; allowed 227…"),
    (100, "'offset to point data' is 100; allowed 227…"),
])
def test_bad_point_offset_is_refused(tmp_path: Path, offset: int, message: str) -> None:
    path = tmp_path / "offset.las"
    write_las(path)
    patch(path, 96, "<I", offset)
    with pytest.raises(ArtifactError, match=message):
        read_point_file(path)


def test_point_offset_past_the_points_is_refused(tmp_path: Path) -> None:
    # Inside the file but too late for the 5 points it claims: laspy once imported 0 points.
    path = tmp_path / "late.las"
    write_las(path)
    size = path.stat().st_size
    patch(path, 96, "<I", size - 10)
    with pytest.raises(ArtifactError, match=r"'number of point records' is 5: .* exceed"):
        read_point_file(path)


def test_garbage_laz_is_one_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "garbage.laz"
    write_las(path)
    data = bytearray(path.read_bytes())
    offset = struct.unpack_from("<I", data, 96)[0]
    rng = np.random.default_rng(0)
    data[offset:] = rng.integers(0, 256, len(data) - offset, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match=r"garbage\.laz: not a readable LAS/LAZ file"):
        read_point_file(path)
    path.write_bytes(rng.integers(0, 256, 500, dtype=np.uint8).tobytes())
    with pytest.raises(ArtifactError, match=r"garbage\.laz: not a readable LAS/LAZ file"):
        read_point_file(path)


def test_valid_files_of_other_libraries_still_import_exactly(tmp_path: Path) -> None:
    # trimesh: binary PLY with a face element after the vertices, uchar colours with alpha.
    mesh = trimesh.Trimesh(POINTS, [[0, 1, 2], [2, 3, 4]], vertex_colors=COLOURS,
                           process=False)
    binary = tmp_path / "trimesh.ply"
    binary.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
    points, colours, _ = read_point_file(binary)
    np.testing.assert_array_equal(points, POINTS.astype(np.float32))
    np.testing.assert_array_equal(colours, COLOURS)
    ascii_path = tmp_path / "trimesh_ascii.ply"
    ascii_path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="ascii"))
    points, colours, _ = read_point_file(ascii_path)
    np.testing.assert_allclose(points, POINTS, atol=1e-6)
    np.testing.assert_array_equal(colours, COLOURS)
    # Open3D: double coordinates, ASCII and binary.
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(POINTS))
    cloud.colors = o3d.utility.Vector3dVector(COLOURS / 255.0)
    for ascii_flag in (True, False):
        path = tmp_path / f"o3d_{ascii_flag}.ply"
        assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=ascii_flag)
        points, colours, _ = read_point_file(path)
        np.testing.assert_allclose(points, POINTS, atol=1e-12 if not ascii_flag else 1e-6)
        np.testing.assert_array_equal(colours, COLOURS)
    # laspy: LAS 1.2 format 3, LAS 1.4 format 7, LAZ.
    for name, version, point_format in (("a.las", "1.2", 3), ("b.las", "1.4", 7),
                                        ("c.laz", "1.4", 7)):
        path = tmp_path / name
        write_las(path, version, point_format)
        points, colours, z_up = read_point_file(path)
        np.testing.assert_allclose(points, POINTS, atol=1e-9)
        np.testing.assert_array_equal(colours, COLOURS)
        assert z_up
    table, report = import_points(binary, ImportParams())
    assert report["points"] == len(POINTS)
    np.testing.assert_allclose(xyz(table), POINTS, atol=1e-6)


HOSTILE = {
    "ply1e7.ply": lambda p: p.write_bytes(ply_claiming(10_000_000)),
    "ply2e9.ply": lambda p: p.write_bytes(ply_claiming(2_000_000_000)),
    "ascii1e9.ply": lambda p: p.write_bytes(ply_claiming(1_000_000_000, "ascii")),
    "las1e8.las": lambda p: las_claiming(p, 100_000_000),
    "las4e9.las": lambda p: las_claiming(p, 4_000_000_000, "1.4"),
    "garbage.laz": lambda p: p.write_bytes(b"LASF" + bytes(range(256)) * 2),
}


@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_cli_refuses_hostile_files_in_one_line_and_keeps_the_old_artifact(
        tmp_path: Path, cli: Callable[..., object], name: str) -> None:
    good = tmp_path / "good.xyz"
    np.savetxt(good, POINTS)
    out = tmp_path / "out"
    assert cli("import-points", good, "--out", out, "-q").code == 0  # type: ignore[attr-defined]
    before = (out / "points.parquet").read_bytes()
    path = tmp_path / name
    HOSTILE[name](path)
    result = cli("import-points", path, "--out", out, "--force", "-q")
    assert result.code == 1, result.err  # type: ignore[attr-defined]
    err = result.err  # type: ignore[attr-defined]
    assert err.startswith(f"scanpipe: error: {path}: ") and err.count("\n") == 1
    assert "Traceback" not in err
    assert (out / "points.parquet").read_bytes() == before
