"""import-points of E57 (pye57 / libE57Format, our export and files pye57 writes the way other
scanners' software does: spherical, invalid points, float intensity with limits, several posed
scans) and PCD (PCL's ascii, binary and binary_compressed; organised clouds; VIEWPOINT)."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import pyarrow as pa
import pye57
import pytest

from scanpipe.errors import ArtifactError
from scanpipe.exporters.e57 import E57Scan, write_e57
from scanpipe.exporters.model import CloudModel
from scanpipe.pointio import ImportParams, import_points

Cli = Callable[..., Any]
RNG = np.random.default_rng(11)


def xyz(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)


def rgb(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in ("red", "green", "blue")], axis=1)


def grid_cloud(rows: int = 12, cols: int = 20) -> CloudModel:
    n = rows * cols
    points = RNG.uniform((-3.0, -1.0, -2.0), (3.0, 2.0, 4.0), (n, 3)).astype(np.float32)
    index = np.arange(n, dtype=np.int32)
    return CloudModel(points, intensity=RNG.integers(0, 65536, n).astype(np.uint16),
                      colors=RNG.integers(0, 256, (n, 3)).astype(np.uint8),
                      profile=index // cols, sample=index % cols)


def test_our_e57_export_imports_with_every_field(tmp_path: Path) -> None:
    cloud = grid_cloud()
    path = tmp_path / "scan.e57"
    write_e57(path, [E57Scan(cloud)])
    table, report = import_points(path, ImportParams())
    # E57 is z-up like the export: the import turns it back into the rig frame.
    np.testing.assert_allclose(xyz(table), cloud.xyz, atol=1e-6)
    np.testing.assert_array_equal(table.column("echo").to_numpy(), cloud.intensity)
    np.testing.assert_array_equal(rgb(table), cloud.colors)
    np.testing.assert_array_equal(table.column("profile").to_numpy(), cloud.profile)
    np.testing.assert_array_equal(table.column("sample").to_numpy(), cloud.sample)
    assert report["grid"] == {"profiles": 12, "samples": 20}
    assert report["up_reason"] == "the format's convention"


def test_several_posed_e57_scans_merge_with_their_own_sensor_origins(tmp_path: Path) -> None:
    first, second = grid_cloud(), grid_cloud(6, 10)
    half = np.sqrt(0.5)
    path = tmp_path / "site.e57"
    write_e57(path, [E57Scan(first, "a"),
                     E57Scan(second, "b", rotation_wxyz=(half, 0.0, 0.0, half),  # 90° about z
                             translation_m=(5.0, 1.0, 0.0))])
    table, report = import_points(path, ImportParams())
    assert table.num_rows == 240 + 60 and report["grid"] is None
    # Scan b: its z-up points (x, −z, y) turned 90° about z, then moved; back to the rig frame.
    zup = np.stack([second.xyz[:, 0], -second.xyz[:, 2], second.xyz[:, 1]], axis=1)
    turned = np.stack([-zup[:, 1], zup[:, 0], zup[:, 2]], axis=1) + np.array([5.0, 1.0, 0.0])
    rig = np.stack([turned[:, 0], turned[:, 2], -turned[:, 1]], axis=1)
    np.testing.assert_allclose(xyz(table)[240:], rig, atol=1e-5)
    origins = np.stack([table.column(f"origin_{a}").to_numpy() for a in "xyz"], axis=1)
    np.testing.assert_allclose(origins[:240], 0.0)
    np.testing.assert_allclose(origins[240:], np.tile((5.0, 0.0, -1.0), (60, 1)))
    assert any("2 E57 scans merged" in w for w in report["warnings"])  # type: ignore


def test_e57_with_invalid_points_and_float_intensity_in_its_limits(tmp_path: Path) -> None:
    # As scanner software writes it: an invalid state for no-returns (their xyz is filler),
    # intensity a float within its intensityLimits (pye57 writes the data's extremes).
    n = 300
    points = RNG.uniform(-4.0, 4.0, (n, 3))
    state = (RNG.uniform(size=n) < 0.1).astype(np.int8) * 2
    points[state != 0] = 0.0
    fraction = RNG.uniform(0.1, 0.9, n)
    path = tmp_path / "scanner.e57"
    writer = pye57.E57(str(path), mode="w")
    writer.write_scan_raw({"cartesianX": points[:, 0], "cartesianY": points[:, 1],
                           "cartesianZ": points[:, 2], "intensity": fraction.astype(np.float32),
                           "cartesianInvalidState": state}, name="s")
    writer.close()
    table, report = import_points(path, ImportParams())
    ok = state == 0
    assert table.num_rows == int(ok.sum())
    assert report["dropped_no_return"] == int(np.count_nonzero(state))
    rig = np.stack([points[ok, 0], points[ok, 2], -points[ok, 1]], axis=1)
    np.testing.assert_allclose(xyz(table), rig, atol=1e-6)
    low, high = fraction.astype(np.float32).min(), fraction.astype(np.float32).max()
    expected = (fraction[ok].astype(np.float32) - low) / (high - low) * 65535.0
    np.testing.assert_allclose(table.column("echo").to_numpy(), expected, atol=1.0)
    assert any("intensityLimits" in w for w in report["warnings"])  # type: ignore


def test_not_an_e57_and_a_cut_e57_are_one_line(tmp_path: Path, cli: Cli) -> None:
    bad = tmp_path / "bad.e57"
    bad.write_bytes(b"not an e57 file at all")
    with pytest.raises(ArtifactError, match="not an E57 file"):
        import_points(bad, ImportParams())
    good = tmp_path / "good.e57"
    write_e57(good, [E57Scan(grid_cloud())])
    cut = tmp_path / "cut.e57"
    cut.write_bytes(good.read_bytes()[:3000])
    result = cli("import-points", cut, "--out", tmp_path / "out")
    assert result.code != 0 and result.err.count("\n") == 1, result.err
    assert "cut.e57" in result.err and "Traceback" not in result.err
    assert not (tmp_path / "out" / "points.parquet").exists()


# -- PCD ----------------------------------------------------------------------------------------

def pcd_header(fields: str, size: str, kind: str, width: int, height: int, data: str,
               viewpoint: str = "0 0 0 1 0 0 0") -> bytes:
    count = " ".join("1" for _ in fields.split())
    return (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\n"
            f"SIZE {size}\nTYPE {kind}\nCOUNT {count}\nWIDTH {width}\nHEIGHT {height}\n"
            f"VIEWPOINT {viewpoint}\nPOINTS {width * height}\nDATA {data}\n").encode()


def packed_rgb(colours: np.ndarray) -> np.ndarray:
    c = colours.astype(np.uint32)
    return (0xFF << 24) | (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]


def test_pcl_ascii_rgb_written_as_an_integer_keeps_its_colours(tmp_path: Path) -> None:
    # PCL's writer puts the packed rgb of an ascii PCD as an unsigned integer although its
    # TYPE is F; Open3D's reader takes the number as a float and makes other colours.
    n = 50
    points = RNG.uniform(-2.0, 2.0, (n, 3)).astype(np.float32)
    colours = RNG.integers(0, 256, (n, 3))
    intensity = RNG.integers(0, 256, n)
    lines = [f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {v} {i}"
             for p, v, i in zip(points, packed_rgb(colours), intensity, strict=True)]
    path = tmp_path / "pcl.pcd"
    path.write_bytes(pcd_header("x y z rgb intensity", "4 4 4 4 4", "F F F F F", n, 1, "ascii")
                     + ("\n".join(lines) + "\n").encode())
    opened = o3d.t.io.read_point_cloud(str(path))
    assert not np.array_equal(opened.point.colors.numpy(), colours)  # the reader we avoid
    table, _ = import_points(path, ImportParams(up="y"))
    np.testing.assert_allclose(xyz(table), points, atol=1e-6)
    np.testing.assert_array_equal(rgb(table), colours)
    np.testing.assert_array_equal(table.column("echo").to_numpy(), intensity)


def test_binary_organised_pcd_keeps_its_grid_and_viewpoint(tmp_path: Path) -> None:
    width, height = 8, 4
    n = width * height
    points = RNG.uniform(-2.0, 2.0, (n, 3)).astype(np.float32)
    points[[3, 17]] = np.nan  # no returns of an organised cloud
    colours = RNG.integers(0, 256, (n, 3))
    body = b"".join(struct.pack("<fffI", *p, c)
                    for p, c in zip(points.tolist(), packed_rgb(colours).tolist(), strict=True))
    path = tmp_path / "organised.pcd"
    path.write_bytes(pcd_header("x y z rgb", "4 4 4 4", "F F F U", width, height, "binary",
                                "0.5 0.25 -1 1 0 0 0") + body)
    table, report = import_points(path, ImportParams(up="y"))
    keep = np.isfinite(points).all(axis=1)
    assert table.num_rows == n - 2
    np.testing.assert_allclose(xyz(table), points[keep], atol=1e-6)
    np.testing.assert_array_equal(rgb(table), colours[keep])
    index = np.arange(n)[keep]
    np.testing.assert_array_equal(table.column("profile").to_numpy(), index // width)
    np.testing.assert_array_equal(table.column("sample").to_numpy(), index % width)
    np.testing.assert_allclose(table.column("origin_x").to_numpy(), 0.5)
    assert report["grid"] == {"profiles": height, "samples": width}


def test_a_default_pcd_viewpoint_leaves_the_given_origin(tmp_path: Path) -> None:
    # The review's case: PCL writes VIEWPOINT 0 0 0 1 0 0 0 for every cloud, and --origin was
    # silently dropped for every PCD file (ranges and angles taken from 0,0,0).
    points = RNG.uniform(-2.0, 2.0, (20, 3)).astype(np.float32)
    path = tmp_path / "plain.pcd"
    path.write_bytes(pcd_header("x y z", "4 4 4", "F F F", 20, 1, "ascii")
                     + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode())
    table, _ = import_points(path, ImportParams(up="y", origin_m=(0.3, 1.2, -0.4)))
    np.testing.assert_allclose(table.column("origin_x").to_numpy(), 0.3)
    np.testing.assert_allclose(table.column("origin_y").to_numpy(), 1.2)


def test_open3d_binary_compressed_pcd(tmp_path: Path) -> None:
    points = RNG.uniform(-2.0, 2.0, (200, 3))
    colours = RNG.integers(0, 256, (200, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.colors = o3d.utility.Vector3dVector(colours / 255.0)
    path = tmp_path / "compressed.pcd"
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=False, compressed=True)
    assert b"DATA binary_compressed" in path.read_bytes()[:400]
    table, _ = import_points(path, ImportParams(up="y"))
    np.testing.assert_allclose(xyz(table), points, atol=1e-6)
    np.testing.assert_array_equal(rgb(table), colours)


@pytest.mark.parametrize(("content", "message"), [
    (b"hello", "not a PCD file"),
    (pcd_header("x y z", "4 4 4", "F F F", 1000, 1, "binary") + b"\0" * 100,
     "'POINTS 1000' needs at least 12000 bytes"),
    (pcd_header("a b c", "4 4 4", "F F F", 1, 1, "ascii") + b"1 2 3\n", "no x, y, z"),
    (pcd_header("x y z", "4 4 4", "F F Q", 1, 1, "ascii") + b"1 2 3\n", "header is not valid"),
    (pcd_header("x y z", "4 4 4", "F F F", 2, 1, "ascii") + b"1 2 3\n4 5 six\n",
     "not a table"),
])
def test_bad_pcd_files_are_one_line(tmp_path: Path, cli: Cli, content: bytes,
                                    message: str) -> None:
    path = tmp_path / "bad.pcd"
    path.write_bytes(content)
    with pytest.raises(ArtifactError, match=message):
        import_points(path, ImportParams())
    out = tmp_path / "out"
    out.mkdir()
    (out / "points.parquet").write_bytes(b"keep me")
    result = cli("import-points", path, "--out", out, "--force")
    assert result.code != 0 and result.err.count("\n") == 1 and message.split("'")[0] in \
        result.err
    assert (out / "points.parquet").read_bytes() == b"keep me"


E57_FIXTURES = Path(__file__).parent / "fixtures" / "e57"


def _libe57_read(path: Path, fields: dict[str, str]) -> dict[str, np.ndarray]:
    """Fields read with libE57Format's own buffers (pye57's uint8 colour buffer fails)."""
    from pye57 import libe57

    reader = pye57.E57(str(path))
    header = reader.get_header(0)
    data, buffers = {}, libe57.VectorSourceDestBuffer()
    for name, code in fields.items():
        data[name] = np.empty(header.point_count, code)
        buffers.append(libe57.SourceDestBuffer(reader.image_file, name, data[name],
                                               header.point_count, True, True))
    header.points.reader(buffers).read()
    return data


def test_third_party_e57_with_16_bit_colour(tmp_path: Path) -> None:
    # las2e57's output (libE57Format's test data): colours 0…65280 with the prototype's
    # 0…65535 and no colorLimits; pye57 cannot read it, and taken as 8-bit it saturates.
    path = E57_FIXTURES / "ColourRepresentation.e57"
    raw = _libe57_read(path, {"cartesianX": "d", "cartesianY": "d", "cartesianZ": "d",
                              "colorRed": "H", "colorGreen": "H", "colorBlue": "H"})
    table, report = import_points(path, ImportParams())
    assert table.num_rows == 153 and report["colours"] is True
    rig = np.stack([raw["cartesianX"], raw["cartesianZ"], -raw["cartesianY"]], axis=1)
    np.testing.assert_allclose(xyz(table), rig, atol=1e-6)
    expected = np.stack([raw[f"color{c}"] >> 8 for c in ("Red", "Green", "Blue")], axis=1)
    np.testing.assert_array_equal(rgb(table), expected)
    assert len(np.unique(rgb(table), axis=0)) > 2  # not all saturated


def test_e57_with_zero_points_is_one_line(tmp_path: Path, cli: Cli) -> None:
    path = E57_FIXTURES / "ZeroPoints.e57"
    with pytest.raises(ArtifactError, match="no points"):
        import_points(path, ImportParams())
    result = cli("import-points", path, "--out", tmp_path / "out")
    assert result.code != 0 and result.err.count("\n") == 1 and "no points" in result.err
    assert not (tmp_path / "out" / "points.parquet").exists()
