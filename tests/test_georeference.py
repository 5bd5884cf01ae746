"""Georeferenced imports end to end: the import's offset travels with the points through
filter and mesh, every exporter writes the imported coordinates (or records the offset), and
scans with different offsets are never merged."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pye57
import pytest
from scipy.spatial import cKDTree

from scanpipe.artifacts import read_artifact
from scanpipe.errors import ArtifactError
from scanpipe.exporters.las import GEO_WKT, SCALE_M
from scanpipe.params import Params
from scanpipe.pointio import float32_error_m, float32_safe_offset, points_table
from scanpipe.poses import poses_table
from scanpipe.schema import MESH_VERTICES, OFFSET_KEY, ZERO_OFFSET, offset_of, with_offset
from scanpipe.stage import Stage, StageResult

Cli = Callable[..., Any]
AUTZEN = Path(__file__).parent / "fixtures" / "laspy" / "autzen_geo_proj.las"
RNG = np.random.default_rng(21)


def autzen_metres() -> np.ndarray:
    """The Autzen sample's points (international feet in the file) in metres, z-up."""
    las = laspy.read(str(AUTZEN))
    return np.stack([las.x, las.y, las.z], axis=1) * 0.3048


def las_xyz(path: Path) -> np.ndarray:
    las = laspy.read(str(path))
    return np.stack([las.x, las.y, las.z], axis=1)


def e57_xyz(path: Path, scan: int = 0) -> np.ndarray:
    data = pye57.E57(str(path)).read_scan(scan, transform=True, ignore_missing_fields=True)
    return np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1)


def ply_vertices(path: Path) -> tuple[str, np.ndarray]:
    """The header and the x, y, z of a binary PLY (doubles or floats), rig frame."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode()
    types = {"float": "<f4", "double": "<f8", "uchar": "u1", "ushort": "<u2"}
    fields, count, element = [], 0, ""
    for line in header.splitlines():
        words = line.split()
        if words[:1] == ["element"]:
            element = words[1]
            count = int(words[2]) if element == "vertex" else count
        elif words[:1] == ["property"] and element == "vertex":
            fields.append((words[2], types[words[1]]))
    vertices = np.frombuffer(raw, dtype=fields, count=count, offset=end)
    return header, np.stack([vertices[n].astype(np.float64) for n in "xyz"], axis=1)


def z_up_from_rig(xyz: np.ndarray) -> np.ndarray:
    return np.stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]], axis=1)


def exact_bound_m(local_max_m: float) -> float:
    """What an exported coordinate may differ by from the input: LAS's half scale step plus
    float32's rounding of the local (shifted) coordinate in the artifact."""
    return SCALE_M / 2 + float32_error_m(local_max_m) + 1e-9


def glb_document(path: Path) -> dict[str, Any]:
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    document: dict[str, Any] = json.loads(data[20:20 + length])
    return document


def test_autzen_las_comes_back_at_its_own_coordinates(tmp_path: Path, cli: Cli) -> None:
    # Autzen (laspy's public sample, Oregon Lambert in feet): ~10⁵ m coordinates. Before, the
    # import shifted it by whole metres and every export landed kilometres away.
    truth = autzen_metres()
    result = cli("import-points", AUTZEN, "--out", tmp_path / "pts", "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["offset_z_up_m"] == [194000.0, 259000.0, 0.0]
    # its CRS is in feet; the exports are in metres: not claimed
    assert report["crs_carried"] is False
    table, _ = read_artifact(tmp_path / "pts" / "points.parquet")
    assert offset_of(table) == (194000.0, 0.0, -259000.0)  # rig frame: (x, z, −y)
    local = float(np.max(np.abs(truth - [194000.0, 259000.0, 0.0])))
    for fmt, name in (("las", "c.las"), ("laz", "c.laz"), ("copc", "c.copc.laz"),
                      ("e57", "c.e57"), ("ply", "c.ply")):
        done = cli("export", tmp_path / "pts", "-f", fmt, "-o", tmp_path / name, "--json")
        assert done.code == 0, done.err
        assert json.loads(done.out)["offset_z_up_m"] == {"cloud": [194000.0, 259000.0, 0.0]}
        if fmt == "e57":
            back = e57_xyz(tmp_path / name)
            bound = float32_error_m(local) + 1e-9  # doubles + the pose's translation
        elif fmt == "ply":
            header, rig = ply_vertices(tmp_path / name)
            assert "property double x" in header
            assert "comment scanpipe-offset-m 194000 0 -259000" in header
            back = z_up_from_rig(rig)
            bound = float32_error_m(local) + 1e-9
        else:
            back = las_xyz(tmp_path / name)
            bound = exact_bound_m(local)
        assert back.shape == truth.shape, fmt
        if fmt == "copc":  # points in octree order: each input point's nearest
            back = back[cKDTree(back).query(truth)[1]]
        error = np.abs(back - truth).max()
        assert error <= bound, (fmt, error)
        assert error <= 1e-4, (fmt, error)  # the bar: within 0.1 mm
    # the E57 read back by scanpipe (its pose applied): the same cloud, the same offset
    again = cli("import-points", tmp_path / "c.e57", "--out", tmp_path / "again", "--json")
    assert again.code == 0, again.err
    assert json.loads(again.out)["offset_z_up_m"] == [194000.0, 259000.0, 0.0]
    back_table, _ = read_artifact(tmp_path / "again" / "points.parquet")
    first_table, _ = read_artifact(tmp_path / "pts" / "points.parquet")
    for axis in "xyz":
        np.testing.assert_allclose(back_table.column(axis).to_numpy(),
                                   first_table.column(axis).to_numpy(), atol=1e-4, rtol=0)
    header = laspy.read(str(tmp_path / "c.las")).header
    wkt = next(v for v in header.vlrs if v.record_id == 2112)
    assert wkt.string == GEO_WKT  # not the rig frame's LOCAL_CS
    # Autzen's CRS is in feet: the LAS must not send the user to assign it to metres (it said
    # "assign the source CRS": done, the cloud lands 3.28 times too far from the origin)
    assert "in metres" in wkt.string and "source CRS in feet" in wkt.string
    assert np.all(header.offsets == np.floor(truth.min(axis=0)))


def test_the_offset_travels_through_filter_and_mesh_to_every_export(tmp_path: Path,
                                                                       cli: Cli) -> None:
    truth = autzen_metres()
    assert cli("import-points", AUTZEN, "--out", tmp_path / "pts", "-q").code == 0
    filtered = cli("filter", tmp_path / "pts", "--out", tmp_path / "flt", "-q",
                   "--set", "range_gate.enabled=false")
    assert filtered.code == 0, filtered.err
    assert cli("mesh", tmp_path / "flt", "--out", tmp_path / "mesh", "-q").code == 0
    offset_rig = (194000.0, 0.0, -259000.0)
    for artifact in ("flt/points.parquet", "mesh/mesh_vertices.parquet"):
        schema = pq.read_schema(tmp_path / artifact)
        assert OFFSET_KEY in (schema.metadata or {}), artifact
        assert offset_of(schema.empty_table()) == offset_rig
    # the filtered cloud: every point one of the input's, at its own coordinates
    assert cli("export", tmp_path / "flt", "-f", "las", "-o", tmp_path / "c.las").code == 0
    back = las_xyz(tmp_path / "c.las")
    distance, _ = cKDTree(truth).query(back)
    assert len(back) > 0.9 * len(truth) and distance.max() <= 1e-4
    # Poisson closes a surface around these 100 sparse points: its mesh reaches beyond them,
    # but not by the cloud's extent (without the offset it would be 200 km away)
    margin = np.ptp(truth, axis=0).max()
    low, high = truth.min(axis=0) - margin, truth.max(axis=0) + margin
    # GLB: local float32 vertices, the offset as the node's translation (glTF is y up)
    assert cli("export", tmp_path / "mesh", "-f", "glb", "-o", tmp_path / "m.glb").code == 0
    document = glb_document(tmp_path / "m.glb")
    assert document["nodes"][0]["translation"] == list(offset_rig)
    bounds = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"][
        "POSITION"]]
    for corner in (bounds["min"], bounds["max"]):  # local y-up + offset → a z-up point
        geo_corner = z_up_from_rig(np.array([corner]) + offset_rig)[0]
        assert np.all((geo_corner >= low) & (geo_corner <= high)), corner
    # OBJ: local vertices, the offset in a comment and the sidecar (its frame: y up)
    obj = cli("export", tmp_path / "mesh", "-f", "obj", "-o", tmp_path / "m.obj")
    assert obj.code == 0 and "georeferenced" in obj.err
    sidecar = (tmp_path / "m_offset.xyz").read_text().split()
    assert [float(v) for v in sidecar] == list(offset_rig)
    text = (tmp_path / "m.obj").read_text()
    assert "# scanpipe-offset-m 194000 0 -259000" in text
    v = np.array([line.split()[1:4] for line in text.splitlines() if line.startswith("v ")],
                 dtype=np.float64)
    geo = z_up_from_rig(v + offset_rig)
    assert np.all((geo >= low) & (geo <= high))
    # mesh PLY: double coordinates, the imported ones
    assert cli("export", tmp_path / "mesh", "-f", "ply", "-o", tmp_path / "m.ply").code == 0
    header, rig = ply_vertices(tmp_path / "m.ply")
    assert "property double x" in header and "element face" in header
    geo_ply = z_up_from_rig(rig)
    assert np.all((geo_ply >= low) & (geo_ply <= high))
    # a format without room for the offset says so
    mcap = cli("export", tmp_path / "mesh", "-f", "mcap", "-o", tmp_path / "m.mcap")
    assert mcap.code == 0 and "written in the local frame" in mcap.err


def write_site_las(path: Path, low: np.ndarray, size_m: float = 10.0) -> np.ndarray:
    """A LAS at 1 mm resolution: two walls and a floor of a ``size_m`` corner at ``low``
    (z-up, UTM-like); returns the points as stored."""
    n = 1500
    u, v = RNG.uniform(0, size_m, (2, n))
    floor = np.stack([u, v, np.zeros(n)], axis=1)
    wall_x = np.stack([np.zeros(n), u, v / 3], axis=1)
    wall_y = np.stack([u, np.zeros(n), v / 3], axis=1)
    points = np.concatenate([floor, wall_x, wall_y]) + low
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(low)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.write(str(path))
    return las_xyz(path)


#: Two scan positions of one site 200 m apart that straddle a kilometre line: their
#: automatic offsets differ by 1 km on x and y.
SITE_A = np.array([637_400.25, 849_400.5, 80.0])
SITE_B = np.array([637_600.75, 849_600.5, 80.0])


def test_two_files_far_apart_keep_their_relative_positions(tmp_path: Path, cli: Cli) -> None:
    a = write_site_las(tmp_path / "a.las", SITE_A)
    b = write_site_las(tmp_path / "b.las", SITE_B)
    # each on its own: different offsets, each exported at its own coordinates
    offsets = []
    for name, truth in (("a", a), ("b", b)):
        result = cli("import-points", tmp_path / f"{name}.las", "--out", tmp_path / name,
                     "--json")
        assert result.code == 0, result.err
        offsets.append(json.loads(result.out)["offset_z_up_m"])
        assert cli("export", tmp_path / name, "-f", "las", "-o",
                   tmp_path / f"{name}_out.las").code == 0
        assert np.abs(las_xyz(tmp_path / f"{name}_out.las") - truth).max() <= 1e-4
        assert cli("export", tmp_path / name, "-f", "e57", "-o",
                   tmp_path / f"{name}_out.e57").code == 0
        assert np.abs(e57_xyz(tmp_path / f"{name}_out.e57") - truth).max() <= 1e-4
    assert offsets == [[637000.0, 849000.0, 0.0], [638000.0, 850000.0, 0.0]]
    # merged into one artifact: one offset, both files where they were
    both = cli("import-points", tmp_path / "a.las", tmp_path / "b.las", "--out",
               tmp_path / "ab", "-q")
    assert both.code == 0, both.err
    assert cli("export", tmp_path / "ab", "-f", "las", "-o", tmp_path / "ab.las").code == 0
    assert np.abs(las_xyz(tmp_path / "ab.las") - np.concatenate([a, b])).max() <= 1e-4
    # register refuses scans whose offsets differ, naming both, and writes nothing
    refused = cli("register", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "site")
    assert refused.code == 2
    assert refused.err.count("\n") == 1 and refused.err.startswith("scanpipe: error: register")
    assert "637000,849000,0" in refused.err and "638000,850000,0" in refused.err
    assert "--offset" in refused.err
    assert not (tmp_path / "site" / "poses.parquet").exists()
    # one --offset for both: they share it
    for name in ("a", "b"):
        result = cli("import-points", tmp_path / f"{name}.las", "--out", tmp_path / f"{name}2",
                     "--offset", "637000,849000,0", "--json")
        assert result.code == 0, result.err
        assert json.loads(result.out)["offset_z_up_m"] == [637000.0, 849000.0, 0.0]


def test_bad_offsets_are_refused_in_one_line(tmp_path: Path, cli: Cli) -> None:
    write_site_las(tmp_path / "a.las", SITE_A)
    out = tmp_path / "pts"
    assert cli("import-points", tmp_path / "a.las", "--out", out, "-q").code == 0
    before = (out / "points.parquet").read_bytes()
    for value, wanted in (("637000,849000", "three numbers"),
                          ("a,b,c", "three numbers"),
                          ("637000,849000,nan", "three numbers"),
                          ("0,0,0", "float32 rounds"),
                          ("600000,849000,0", "float32 rounds")):
        result = cli("import-points", tmp_path / "a.las", "--out", out, "--force",
                     "--offset", value)
        assert result.code == 2, (value, result.err)
        assert result.err.count("\n") == 1 and wanted in result.err, result.err
        assert "--offset" in result.err
        assert (out / "points.parquet").read_bytes() == before  # nothing valid lost


def mesh_workdir(tmp_path: Path, cli: Cli, name: str, offset: str | None) -> Path:
    """A scan's workdir from a georeferenced file: import-points/, mesh/."""
    work = tmp_path / name
    extra = ["--offset", offset] if offset else []
    assert cli("import-points", tmp_path / f"{name}.las", "--out", work / "import-points",
               "-q", *extra).code == 0
    made = cli("mesh", work / "import-points", "--out", work / "mesh", "-q",
               "--set", "poisson.depth=6")
    assert made.code == 0, made.err
    return work


def test_site_model_keeps_the_shared_offset_and_refuses_different_ones(tmp_path: Path,
                                                                         cli: Cli) -> None:
    a = write_site_las(tmp_path / "a.las", SITE_A, 4.0)
    b = write_site_las(tmp_path / "b.las", SITE_B, 4.0)
    shared = "637000,849000,0"
    work = [mesh_workdir(tmp_path, cli, n, shared) for n in ("a", "b")]
    poses = tmp_path / "poses.parquet"
    pq.write_table(poses_table(["a", "b"], [np.eye(4), np.eye(4)]), poses)
    site = tmp_path / "site"
    result = cli("site-model", *work, "--out", site, "--poses", poses, "--json")
    assert result.code == 0, result.err
    assert json.loads(result.out)["offset_z_up_m"] == [637000.0, 849000.0, 0.0]
    truth = np.concatenate([a, b])
    merged = las_xyz(site / "site.las")
    distance, _ = cKDTree(truth).query(merged)
    assert distance.max() <= 1e-4
    for scan, own in ((0, a), (1, b)):  # one E57 scan per position, offset in its pose
        distance, _ = cKDTree(own).query(e57_xyz(site / "site.e57", scan))
        assert distance.max() <= 1e-4
    assert glb_document(site / "site.glb")["nodes"][0]["translation"] == [637000.0, 0.0,
                                                                         -849000.0]
    # the same scans imported with their own (automatic) offsets: refused, nothing written
    (tmp_path / "auto").mkdir()
    for name in ("a", "b"):
        (tmp_path / "auto" / f"{name}.las").write_bytes((tmp_path / f"{name}.las").read_bytes())
    auto = [mesh_workdir(tmp_path / "auto", cli, n, None) for n in ("a", "b")]
    site2 = tmp_path / "site2"
    refused = cli("site-model", *auto, "--out", site2, "--poses", poses)
    assert refused.code == 2 and refused.err.count("\n") == 1, refused.err
    assert "637000,849000,0" in refused.err and "638000,850000,0" in refused.err
    assert not site2.exists() or not any(site2.iterdir())


class _NoParams(Params):
    """A toy stage's parameters: none."""


def _passthrough(inputs: Mapping[str, Any], params: Any, progress: Any) -> StageResult:
    """A toy stage that makes a new table (no metadata) from its points."""
    return StageResult({"points": pa.table(inputs["points"].to_pydict(),
                                           schema=inputs["points"].schema.remove_metadata())})


def test_every_stage_passes_the_offset_on_and_refuses_two() -> None:
    toy = Stage("toy", 1, _NoParams, ("points", "mesh_vertices"), ("points",), _passthrough,
                "test")
    points = points_table(np.zeros((3, 3)), None, (0.0, 0.0, 0.0))
    vertices = MESH_VERTICES.arrow_schema.empty_table()
    made = toy.run({"points": with_offset(points, (1000.0, 0.0, -2000.0)),
                    "mesh_vertices": vertices})
    assert offset_of(made.tables["points"]) == (1000.0, 0.0, -2000.0)
    assert offset_of(toy.run({"points": points, "mesh_vertices": vertices}).tables["points"]) \
        == ZERO_OFFSET
    with pytest.raises(ArtifactError, match=r"stage 'toy'.*1000,2000,0.*1000,3000,0"):
        toy.run({"points": with_offset(points, (1000.0, 0.0, -2000.0)),
                 "mesh_vertices": with_offset(vertices, (1000.0, 0.0, -3000.0))})


def test_automatic_offsets_are_whole_kilometres_unless_the_cloud_is_too_large() -> None:
    near = np.array([[637_400.2, 80.0, -849_400.7], [637_420.9, 90.0, -849_380.1]])
    assert float32_safe_offset(near).tolist() == [637_000.0, 0.0, -849_000.0]
    # a position 70 m away, in the same kilometre cell: the same offset
    assert float32_safe_offset(near + np.array([50.0, 0.0, -50.0])).tolist() == [
        637_000.0, 0.0, -849_000.0]
    # 5 km across: a kilometre-rounded centre could leave 2.5 km (0.12 mm); whole metres
    wide = np.array([[600_000.4, 0.0, 0.0], [605_000.9, 1.0, 1.0]])
    assert float32_safe_offset(wide).tolist() == [602_501.0, 0.0, 0.0]
    # near the origin: nothing
    assert float32_safe_offset(np.array([[-3.0, 0.0, 2000.0]])).tolist() == [0.0, 0.0, 0.0]


def test_points_shifted_by_an_older_import_are_refused(tmp_path: Path, cli: Cli) -> None:
    # An import made before the offset travelled: its report names offset_m, the table
    # carries none. Filtering or exporting it would silently keep the shifted coordinates.
    assert cli("import-points", AUTZEN, "--out", tmp_path / "pts", "-q").code == 0
    path = tmp_path / "pts" / "points.parquet"
    table = pq.read_table(path)
    metadata = dict(table.schema.metadata)
    del metadata[OFFSET_KEY]
    pq.write_table(table.replace_schema_metadata(metadata), path)
    before = path.read_bytes()
    for args in (("filter", tmp_path / "pts", "--out", tmp_path / "flt"),
                 ("export", tmp_path / "pts", "-f", "las", "-o", tmp_path / "c.las")):
        result = cli(*args)
        assert result.code == 1 and result.err.count("\n") == 1, result.err
        assert "re-run import-points" in result.err and "194000" in result.err
    assert not (tmp_path / "c.las").exists() and not (tmp_path / "flt" / "points.parquet").exists()
    assert path.read_bytes() == before


#: WGS 84 / UTM zone 32N (EPSG:32632), metres, as a LAS WKT VLR holds it.
UTM32_WKT = (
    'PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
    '6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
    'PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],'
    'PARAMETER["central_meridian",9],PARAMETER["scale_factor",0.9996],'
    'PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1],'
    'AXIS["Easting",EAST],AXIS["Northing",NORTH],AUTHORITY["EPSG","32632"]]')


def write_utm_las(path: Path, low: np.ndarray) -> np.ndarray:
    """A LAS 1.4 with its CRS as a WKT VLR (UTM 32N, metres) near ``low``."""
    points = low + RNG.uniform(0, [30.0, 30.0, 5.0], (500, 3))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(low)
    header.global_encoding.wkt = True
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(UTM32_WKT))
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.write(str(path))
    return las_xyz(path)


def test_a_metre_crs_is_carried_to_the_las_exports(tmp_path: Path, cli: Cli) -> None:
    truth = write_utm_las(tmp_path / "utm.las", np.array([512_345.0, 5_401_234.0, 230.0]))
    result = cli("import-points", tmp_path / "utm.las", "--out", tmp_path / "pts", "--json")
    assert result.code == 0, result.err
    assert json.loads(result.out)["crs_carried"] is True
    assert cli("filter", tmp_path / "pts", "--out", tmp_path / "flt", "-q",
               "--set", "range_gate.enabled=false").code == 0
    for name in ("c.las", "c.copc.laz"):
        fmt = "copc" if name.endswith("copc.laz") else "las"
        assert cli("export", tmp_path / "flt", "-f", fmt, "-o", tmp_path / name).code == 0
        header = laspy.read(str(tmp_path / name)).header
        wkt = next(v for v in header.vlrs if v.record_id == 2112)
        assert wkt.string.rstrip("\0") == UTM32_WKT, name
        pipeline = json.loads((tmp_path / f"{name}.pipeline.json").read_text())
        assert pipeline["pipeline"][0]["default_srs"] == UTM32_WKT
    back = las_xyz(tmp_path / "c.las")
    assert len(back) > 0.9 * len(truth) and cKDTree(truth).query(back)[0].max() <= 1e-4
    # out of its axes (--up y) or out of its unit (--units ft): the CRS is not claimed
    for extra, why in ((("--up", "y"), "moved the points"), (("--units", "ft"), "not the metre")):
        moved = cli("import-points", tmp_path / "utm.las", "--out", tmp_path / "other",
                    "--force", "--json", *extra)
        assert moved.code == 0, moved.err
        report = json.loads(moved.out)
        assert report["crs_carried"] is False
        assert any(why in w and "not carried" in w for w in report["warnings"])
        # the advice fits the reason: a CRS in feet is not to be assigned to metres as is
        warning = next(w for w in report["warnings"] if "not carried" in w)
        assert "assign the CRS there" not in warning
        assert ("metre equivalent" in warning) == (why == "not the metre")
        assert cli("export", tmp_path / "other", "-f", "las", "-o", tmp_path / "o.las",
                   "--force").code == 0
        wkt = next(v for v in laspy.read(str(tmp_path / "o.las")).header.vlrs
                   if v.record_id == 2112)
        assert "UTM" not in wkt.string


def e57_coordinate_metadata(path: Path) -> str:
    """The E57 root's ``coordinateMetadata`` string (the file's coordinate system)."""
    e57 = pye57.E57(str(path))
    try:
        value = e57.root["coordinateMetadata"].value()
    finally:
        e57.close()
    assert isinstance(value, str)
    return value


def test_a_metre_crs_is_carried_to_the_e57_exports(tmp_path: Path, cli: Cli) -> None:
    """E57's root ``coordinateMetadata`` names the coordinate system of the file's frame (ASTM
    E2807: a WKT string, or empty). It was always empty, even when the points kept a metre CRS
    that the LAS exports carry; a point cloud's georeference was lost in E57."""
    truth = write_utm_las(tmp_path / "utm.las", np.array([512_345.0, 5_401_234.0, 230.0]))
    assert cli("import-points", tmp_path / "utm.las", "--out", tmp_path / "pts", "-q").code == 0
    assert cli("export", tmp_path / "pts", "-f", "e57", "-o", tmp_path / "c.e57").code == 0
    assert e57_coordinate_metadata(tmp_path / "c.e57") == UTM32_WKT
    back = e57_xyz(tmp_path / "c.e57")  # the pose applied: the file's own coordinates
    assert cKDTree(truth).query(back)[0].max() <= 1e-4
    # a CRS not carried (feet: the exports are in metres) is not claimed
    assert cli("import-points", AUTZEN, "--out", tmp_path / "ft", "-q").code == 0
    assert cli("export", tmp_path / "ft", "-f", "e57", "-o", tmp_path / "ft.e57").code == 0
    assert e57_coordinate_metadata(tmp_path / "ft.e57") == ""
