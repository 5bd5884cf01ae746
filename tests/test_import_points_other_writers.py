"""import-points on files as other tools write them: georeferenced LAS (laspy), Leica PTS and
CloudCompare-style text (x y z intensity r g b), intensities as 0–1 floats or PTS's
−2048…2047, LAS intensity. Each case was once read silently wrong."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyarrow as pa

from scanpipe.artifacts import read_artifact
from scanpipe.pointio import ImportParams, import_points

Cli = Callable[..., Any]
RNG = np.random.default_rng(7)
N = 400
#: A small site in a projected CRS: 10 m around (637 000 E, 849 000 N), 400 m up (z-up).
GEO_LOW = np.array([637_000.0, 849_000.0, 400.0])


def xyz(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)


def rgb(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in ("red", "green", "blue")], axis=1)


def write_geo_las(path: Path) -> np.ndarray:
    """A LAS file at 1 mm resolution in UTM-like coordinates; returns the z-up points."""
    points = RNG.uniform(GEO_LOW, GEO_LOW + np.array([10.0, 10.0, 5.0]), (N, 3))
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = GEO_LOW
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.intensity = RNG.integers(0, 65536, N).astype(np.uint16)
    las.write(str(path))
    back = laspy.read(str(path))
    return np.stack([back.x, back.y, back.z], axis=1)


def test_georeferenced_las_keeps_millimetres_by_shifting_and_says_so(tmp_path: Path) -> None:
    # float32 at 849 000 m has a 6 cm spacing: read as is, every point moved by up to 3 cm.
    path = tmp_path / "site.las"
    geo = write_geo_las(path)
    table, report = import_points(path, ImportParams())
    offset = np.asarray(report["offset_m"])
    rig = np.stack([geo[:, 0], geo[:, 2], -geo[:, 1]], axis=1)  # z-up → rig (x, z, −y)
    np.testing.assert_allclose(xyz(table) + offset, rig, atol=2e-4, rtol=0)
    # Only the axes that need it move, by whole kilometres (nearby files share the offset):
    # heights (400 m) stay as they are.
    assert np.all(np.abs(xyz(table)[:, [0, 2]]) < 1000.0) and offset[1] == 0.0
    assert np.all(offset == np.round(offset / 1000.0) * 1000.0)
    assert any("shifted" in w and "float32" in w for w in report["warnings"])  # type: ignore
    # A cloud near the origin is not shifted.
    near = tmp_path / "near.xyz"
    np.savetxt(near, RNG.uniform(-3, 3, (N, 3)))
    _, report = import_points(near, ImportParams(up="y"))
    assert report["offset_m"] == [0.0, 0.0, 0.0]


def test_las_intensity_becomes_echo(tmp_path: Path) -> None:
    path = tmp_path / "site.las"
    write_geo_las(path)
    table, _ = import_points(path, ImportParams())
    np.testing.assert_array_equal(table.column("echo").to_numpy(),
                                  laspy.read(str(path)).intensity)


def intensity_rgb_rows() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    points = RNG.uniform(-3.0, 3.0, (N, 3))
    intensity = RNG.integers(-2048, 2048, N)
    colours = RNG.integers(0, 256, (N, 3))
    return points, intensity, colours


def write_rows(path: Path, points: np.ndarray, intensity: np.ndarray, colours: np.ndarray,
               count_line: bool) -> None:
    lines = [f"{len(points)}"] if count_line else []
    lines += [f"{p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {i} {c[0]} {c[1]} {c[2]}"
              for p, i, c in zip(points, intensity, colours, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def test_leica_pts_with_its_count_line_is_x_y_z_intensity_r_g_b(tmp_path: Path) -> None:
    points, intensity, colours = intensity_rgb_rows()
    for count_line in (True, False):
        path = tmp_path / f"scan{int(count_line)}.pts"
        write_rows(path, points, intensity, colours, count_line)
        table, report = import_points(path, ImportParams(up="y"))
        np.testing.assert_allclose(xyz(table), points, atol=1e-4)
        np.testing.assert_array_equal(rgb(table), colours)
        # PTS intensity is −2048…2047: shifted into the echo's 0…4095, nothing clipped.
        np.testing.assert_array_equal(table.column("echo").to_numpy(), intensity + 2048)
        assert report["points"] == N


def test_pts_count_line_that_disagrees_is_warned(tmp_path: Path) -> None:
    points, intensity, colours = intensity_rgb_rows()
    path = tmp_path / "scan.pts"
    write_rows(path, points, intensity, colours, count_line=True)
    text = path.read_text().splitlines()
    path.write_text("\n".join([str(N + 5), *text[1:]]) + "\n")
    _, report = import_points(path, ImportParams(up="y"))
    assert any("says 405 points" in w and "400" in w for w in report["warnings"])  # type: ignore


def test_headerless_seven_columns_are_not_silently_taken_as_x_y_z_r_g_b_a(
        tmp_path: Path) -> None:
    # CloudCompare's "x y z intensity r g b" without a header: columns 4–6 look like colours
    # too, so the guess is warned about and --columns settles it.
    points, _, colours = intensity_rgb_rows()
    intensity = RNG.integers(0, 256, N)
    path = tmp_path / "cloud.xyz"
    write_rows(path, points, intensity, colours, count_line=False)
    table, report = import_points(path, ImportParams(up="y"))
    assert any("--columns x,y,z,intensity,red,green,blue" in w
               for w in report["warnings"])  # type: ignore[union-attr]
    table, report = import_points(path, ImportParams(
        up="y", columns="x,y,z,intensity,red,green,blue"))
    np.testing.assert_array_equal(rgb(table), colours)
    np.testing.assert_array_equal(table.column("echo").to_numpy(), intensity)


def test_intensity_as_a_fraction_is_scaled_not_rounded_to_0_or_1(tmp_path: Path) -> None:
    points = RNG.uniform(-3.0, 3.0, (N, 3))
    fraction = RNG.uniform(0.0, 1.0, N)
    path = tmp_path / "cloud.csv"
    lines = ["x,y,z,intensity"] + [f"{p[0]},{p[1]},{p[2]},{f:.6f}"
                                    for p, f in zip(points, fraction, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    table, report = import_points(path, ImportParams(up="y"))
    np.testing.assert_allclose(table.column("echo").to_numpy(), fraction * 65535, atol=1.0)
    assert any("0…1" in w for w in report["warnings"])  # type: ignore[union-attr]


def test_negative_intensities_are_warned_not_clipped_silently(tmp_path: Path) -> None:
    points = RNG.uniform(-3.0, 3.0, (N, 3))
    values = RNG.integers(-100, 100, N)
    path = tmp_path / "cloud.csv"
    lines = ["x,y,z,intensity"] + [f"{p[0]},{p[1]},{p[2]},{v}"
                                    for p, v in zip(points, values, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    _, report = import_points(path, ImportParams(up="y"))
    assert any("negative" in w and "intensit" in w for w in report["warnings"])  # type: ignore


def test_cli_prints_the_shift_of_a_georeferenced_file(tmp_path: Path, cli: Cli) -> None:
    path = tmp_path / "site.las"
    write_geo_las(path)
    out = tmp_path / "out"
    result = cli("import-points", path, "--out", out, "-q")
    assert result.code == 0, result.err
    assert "shifted" in result.err and result.err.count("\n") >= 1
    table, provenance = read_artifact(out / "points.parquet")
    assert provenance["report"]["offset_m"][0] == 637000.0  # whole kilometres
    assert table.num_rows == N


FIXTURES = Path(__file__).parent / "fixtures" / "laspy"


def test_public_las_in_feet_is_read_in_metres(tmp_path: Path) -> None:
    # Autzen (laspy's test data): NAD83(HARN) / Oregon Lambert (ft); its WKT says
    # UNIT["foot",0.3048] and its GeoKeys ProjLinearUnits 9002. Read as metres, the cloud
    # came out 3.28× too large with a hint at centimetres.
    path = FIXTURES / "autzen_geo_proj.las"
    las = laspy.read(str(path))
    table, report = import_points(path, ImportParams())
    feet = np.stack([las.x, las.y, las.z], axis=1)
    rig = np.stack([feet[:, 0], feet[:, 2], -feet[:, 1]], axis=1) * 0.3048
    np.testing.assert_allclose(xyz(table) + np.asarray(report["offset_m"]), rig, atol=2e-4,
                               rtol=0)
    assert report["units"] == ["ft"]
    notes = " ".join(report["warnings"])  # type: ignore[arg-type]
    assert "foot" in notes and "0.3048" in notes
    assert "centimetres or millimetres" not in notes
    # --units says otherwise: the file's unit is named in a warning, the user's is used.
    table, report = import_points(path, ImportParams(units="m"))
    np.testing.assert_allclose(xyz(table) + np.asarray(report["offset_m"]), rig / 0.3048,
                               atol=2e-4, rtol=0)
    assert any("--units m" in w and "foot" in w for w in report["warnings"])  # type: ignore


def test_las_geokeys_alone_give_the_unit(tmp_path: Path) -> None:
    # A LAS with GeoTIFF keys only (no WKT): ProjLinearUnitsGeoKey 9003 is the US survey foot.
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.zeros(3)
    keys = laspy.vlrs.known.GeoKeyDirectoryVlr()
    keys.geo_keys_header.number_of_keys = 1
    entry = laspy.vlrs.geotiff.GeoKeyEntryStruct()
    entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = 3076, 0, 1, 9003
    keys.geo_keys = [entry]
    header.vlrs.append(keys)
    las = laspy.LasData(header)
    points = RNG.uniform(0.0, 30.0, (N, 3))
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    path = tmp_path / "survey_feet.las"
    las.write(str(path))
    table, report = import_points(path, ImportParams())
    back = laspy.read(str(path))
    rig = np.stack([back.x, back.z, -np.asarray(back.y)], axis=1) * (1200.0 / 3937.0)
    np.testing.assert_allclose(xyz(table), rig, atol=1e-5)
    assert report["units"] == ["us-ft"]


def test_public_las_with_8_bit_values_in_its_16_bit_colour(tmp_path: Path) -> None:
    # laspy's simple.las stores colours 0…249 in the 16-bit fields (a writer's habit).
    path = FIXTURES / "simple.las"
    las = laspy.read(str(path))
    table, report = import_points(path, ImportParams())
    np.testing.assert_array_equal(rgb(table)[:, 0], np.asarray(las.red))
    np.testing.assert_array_equal(table.column("echo").to_numpy(), np.asarray(las.intensity))
    assert report["points"] == 1065 and report["units"] == ["m"]


def test_ply_intensity_as_cloudcompare_and_pdal_name_it(tmp_path: Path) -> None:
    # CloudCompare writes a scalar field as "scalar_Intensity" (float), PDAL as "intensity"
    # (ushort): both are the echo; before, the PLY reader dropped them.
    points = RNG.uniform(-3.0, 3.0, (N, 3)).astype(np.float32)
    values = RNG.integers(0, 4096, N)
    for name, kind, code in (("scalar_Intensity", "float", "<f4"),
                             ("intensity", "ushort", "<u2")):
        path = tmp_path / f"{name}.ply"
        header = ("ply\nformat binary_little_endian 1.0\ncomment written like CloudCompare\n"
                  f"element vertex {N}\nproperty float x\nproperty float y\nproperty float z\n"
                  f"property {kind} {name}\nend_header\n").encode()
        records = np.zeros(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", code)])
        records["x"], records["y"], records["z"] = points.T
        records["i"] = values
        path.write_bytes(header + records.tobytes())
        table, _ = import_points(path, ImportParams(up="y"))
        np.testing.assert_array_equal(table.column("echo").to_numpy(), values)


def _las_with_wkt(path: Path, wkt: str) -> np.ndarray:
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.zeros(3)
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(wkt))
    las = laspy.LasData(header)
    points = RNG.uniform(0.0, 30.0, (N, 3))
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.write(str(path))
    back = laspy.read(str(path))
    return np.stack([back.x, back.y, back.z], axis=1)


def test_compound_wkt_with_heights_in_us_feet_and_a_unit_whose_factor_is_wrong(
        tmp_path: Path) -> None:
    # As in laspy's simple.copc.laz: metres horizontally, NAVD88 heights in US survey feet.
    compound = ('COMPD_CS["x",PROJCS["NAD83 / Oregon LCC (m)",GEOGCS["NAD83",UNIT["degree",'
                '0.0174532925199433]],UNIT["metre",1],AXIS["Easting",EAST]],VERT_CS["NAVD88 '
                'height (ftUS)",UNIT["US survey foot",0.304800609601219]]]')
    path = tmp_path / "compound.las"
    zup = _las_with_wkt(path, compound)
    table, report = import_points(path, ImportParams())
    us_ft = 1200.0 / 3937.0
    np.testing.assert_allclose(xyz(table), np.stack([zup[:, 0], zup[:, 2] * us_ft, -zup[:, 1]],
                                                    axis=1), atol=1e-5)
    notes = " ".join(report["warnings"])  # type: ignore[arg-type]
    assert "metre horizontally, US survey foot vertically" in notes
    # As in laspy's test1_4.las (liblas): VERTCS UNIT["US survey foot",1.0]: the name wins.
    broken = ('PROJCS["NAD83(HARN) / New Mexico Central (ftUS)",GEOGCS["NAD83(HARN)",UNIT['
              '"degree",0.0174532925199433]],UNIT["US survey foot",0.3048006096012192],'
              'VERTCS["NAVD88",UNIT["US survey foot",1.0]]]')
    path = tmp_path / "broken.las"
    zup = _las_with_wkt(path, broken)
    table, report = import_points(path, ImportParams())
    np.testing.assert_allclose(xyz(table), np.stack([zup[:, 0], zup[:, 2], -zup[:, 1]],
                                                    axis=1) * us_ft, atol=1e-5)
    assert any("US survey foot" in w and "1.0" in w and "disagree" in w
               for w in report["warnings"])  # type: ignore[union-attr]


def test_a_crs_code_in_the_unit_key_is_named_as_such(tmp_path: Path) -> None:
    # laspy's simple1_3.las has ProjLinearUnitsGeoKey = 32632 (a CRS, UTM 32N).
    header = laspy.LasHeader(point_format=0, version="1.2")
    keys = laspy.vlrs.known.GeoKeyDirectoryVlr()
    keys.geo_keys_header.number_of_keys = 1
    entry = laspy.vlrs.geotiff.GeoKeyEntryStruct()
    entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = 3076, 0, 1, 32632
    keys.geo_keys = [entry]
    header.vlrs.append(keys)
    las = laspy.LasData(header)
    points = RNG.uniform(0.0, 30.0, (N, 3))
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    path = tmp_path / "utm.las"
    las.write(str(path))
    _, report = import_points(path, ImportParams())
    assert report["units"] == ["m"]
    assert any("EPSG:32632" in w and "not a length unit" in w and "nan" not in w
               for w in report["warnings"])  # type: ignore[union-attr]
