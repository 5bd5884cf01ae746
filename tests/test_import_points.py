"""import-points: PLY, XYZ/CSV and LAS/LAZ into a points artifact without a grid."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import laspy
import numpy as np
import open3d as o3d
import pyarrow as pa
import pytest

from scanpipe.artifacts import read_artifact
from scanpipe.errors import ArtifactError, UsageError
from scanpipe.pointio import ImportParams, import_points

POINTS = np.array([[0.70711, 1.73205, 0.70711], [2.0, 0.0, 0.0], [0.0, 0.0, 2.0],
                   [-1.0, -2.0, 0.5]])
COLOURS = np.array([[255, 0, 0], [0, 128, 0], [0, 0, 64], [10, 20, 30]], np.uint8)


def xyz(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1)


def rgb(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in ("red", "green", "blue")], axis=1)


def test_ply_with_colours(tmp_path: Path) -> None:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(POINTS))
    cloud.colors = o3d.utility.Vector3dVector(COLOURS / 255.0)
    path = tmp_path / "cloud.ply"
    assert o3d.io.write_point_cloud(str(path), cloud)
    table, report = import_points(path, ImportParams())
    np.testing.assert_allclose(xyz(table), POINTS, atol=1e-6)
    np.testing.assert_array_equal(rgb(table), COLOURS)
    assert report["points"] == 4 and report["colours"] is True and report["grid"] is None
    assert set(table.column("profile").to_pylist()) == {-1}
    assert set(table.column("sample").to_pylist()) == {-1}
    # Directions invert the paper's eq. 14–16: (0.70711, 1.73205, 0.70711) is α 30°, β 45°.
    assert table.column("alpha_deg")[0].as_py() == pytest.approx(30.0, abs=1e-3)
    assert table.column("beta_deg")[0].as_py() == pytest.approx(45.0, abs=1e-3)
    assert table.column("range_m")[0].as_py() == pytest.approx(2.0, abs=1e-5)


def test_xyz_without_header_with_and_without_colours(tmp_path: Path) -> None:
    plain = tmp_path / "plain.xyz"
    np.savetxt(plain, POINTS, fmt="%.6f")
    table, report = import_points(plain, ImportParams(origin_m=(1.0, 0.0, 0.0)))
    np.testing.assert_allclose(xyz(table), POINTS, atol=1e-6)
    assert report["colours"] is False and "red" not in table.column_names
    np.testing.assert_allclose(table.column("origin_x").to_numpy(), 1.0)
    np.testing.assert_allclose(table.column("range_m").to_numpy(),
                               np.linalg.norm(POINTS - (1.0, 0.0, 0.0), axis=1), rtol=1e-6)
    coloured = tmp_path / "coloured.txt"
    np.savetxt(coloured, np.hstack([POINTS, COLOURS]), fmt="%.6f %.6f %.6f %d %d %d")
    table, _ = import_points(coloured, ImportParams())
    np.testing.assert_array_equal(rgb(table), COLOURS)


def test_csv_with_header_finds_columns_by_name(tmp_path: Path) -> None:
    path = tmp_path / "cloud.csv"
    lines = ["//X,Y,Z,R,G,B,Intensity"] + [
        f"{p[0]},{p[1]},{p[2]},{c[0]},{c[1]},{c[2]},7" for p, c in zip(POINTS, COLOURS,
                                                                          strict=True)]
    path.write_text("\n".join(lines) + "\n")
    table, _ = import_points(path, ImportParams())
    np.testing.assert_allclose(xyz(table), POINTS, atol=1e-6)
    np.testing.assert_array_equal(rgb(table), COLOURS)
    semicolons = tmp_path / "semi.csv"
    semicolons.write_text("z;y;x\n1;2;3\n4;5;6\n")
    table, _ = import_points(semicolons, ImportParams())
    np.testing.assert_allclose(xyz(table), [[3, 2, 1], [6, 5, 4]])


def write_las(path: Path, points_z_up: np.ndarray) -> None:
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.0001, 0.0001, 0.0001])
    header.offsets = np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points_z_up[:, 0], points_z_up[:, 1], points_z_up[:, 2]
    las.red, las.green, las.blue = (COLOURS[:, k].astype(np.uint16) * 257 for k in range(3))
    las.write(str(path))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_and_laz_are_z_up(tmp_path: Path, suffix: str) -> None:
    # The export maps rig (x, y, z) to LAS (x, −z, y); import must invert it.
    las_points = np.stack([POINTS[:, 0], -POINTS[:, 2], POINTS[:, 1]], axis=1)
    path = tmp_path / f"cloud{suffix}"
    write_las(path, las_points)
    table, report = import_points(path, ImportParams())
    np.testing.assert_allclose(xyz(table), POINTS, atol=2e-4)
    np.testing.assert_array_equal(rgb(table), COLOURS)
    assert report["z_up_converted"] is True
    as_is, _ = import_points(path, ImportParams(up="y"))
    np.testing.assert_allclose(xyz(as_is), las_points, atol=2e-4)


@pytest.mark.parametrize(("name", "content", "error", "message"), [
    ("cloud.obj", b"v 1 2 3\n", UsageError, "unknown point file type '.obj'"),
    ("bad.ply", b"not a ply at all", ArtifactError, "not a PLY file"),
    ("bad.las", b"LASF but not really", ArtifactError, "not a readable LAS/LAZ file"),
    ("bad.xyz", b"1 2 3\n4 5 six\n", ArtifactError, "not a table of numbers"),
    ("two.xyz", b"1 2\n3 4\n", ArtifactError, "2 columns; need at least x, y, z"),
    ("noz.csv", b"x,y,w\n1,2,3\n", ArtifactError, "header has no column z"),
    ("empty.csv", b"x,y,z\n", ArtifactError, "no points"),
])
def test_bad_files_are_one_clear_error(tmp_path: Path, name: str, content: bytes,
                                       error: type[Exception], message: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(error, match=message):
        import_points(path, ImportParams())


def test_cli_writes_an_artifact_with_provenance(tmp_path: Path,
                                                cli: Callable[..., object]) -> None:
    path = tmp_path / "cloud.xyz"
    np.savetxt(path, POINTS)
    out = tmp_path / "out"
    result = cli("import-points", path, "--out", out, "--origin", "0,1,0", "-q")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    table, provenance = read_artifact(out / "points.parquet")
    assert table.num_rows == 4
    assert provenance["stage"] == "import-points" and provenance["params"]["origin_m"] == [0, 1, 0]
    assert provenance["report"]["points"] == 4 and len(provenance["key"]) == 24
    np.testing.assert_allclose(table.column("origin_y").to_numpy(), 1.0)


def test_cli_errors_exit_non_zero_without_traceback(tmp_path: Path,
                                                    cli: Callable[..., object]) -> None:
    path = tmp_path / "cloud.xyz"
    np.savetxt(path, POINTS)
    bad_origin = cli("import-points", path, "--out", tmp_path / "o", "--origin", "1,2")
    assert bad_origin.code == 2  # type: ignore[attr-defined]
    assert "expected three numbers" in bad_origin.err  # type: ignore[attr-defined]
    missing = cli("import-points", tmp_path / "nope.ply", "--out", tmp_path / "o")
    assert missing.code == 2 and "not found" in missing.err  # type: ignore[attr-defined]
    assert "Traceback" not in missing.err  # type: ignore[attr-defined]
    assert not (tmp_path / "o" / "points.parquet").exists()
