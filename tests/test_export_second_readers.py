"""Second, independent readers of the exported point clouds and the provenance in every format.

laspy (scanpipe's own writer library) is not the only judge of a LAS file: LAS/LAZ 1.2 are read
by loaders.gl (the JavaScript loader of deck.gl and kepler.gl, with its own LAS parser and
laz-perf; installed into .cache/ by ./run.sh setup) and COPC by copc-lib (C++ with its own
LAZ decoder, Python wheel ``copclib``). Each must give back the same points, intensities and
colours scanpipe wrote."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from collections.abc import Callable
from pathlib import Path

import copclib
import numpy as np
import pyarrow as pa
import pytest
from result_tables import points_table, textured_box

from scanpipe.artifacts import PROVENANCE_KEY, write_artifact
from scanpipe.exporters.model import PROVENANCE_TAG, rig_to_z_up
from scanpipe.exporting import write_files
from scanpipe.stages.export import export_files

REPO = Path(__file__).resolve().parents[1]
#: Installed by ./run.sh setup (npm install into .cache/loaders-gl).
LOADERS_GL = Path(os.environ.get("SCANPIPE_LOADERS_GL",
                                 REPO / ".cache" / "loaders-gl" / "node_modules"))
READ_JS = """
const {createRequire} = require('module');
const load = createRequire(process.argv[1] + '/');
(async () => {
  const {parse} = load('@loaders.gl/core');
  const {LASLoader} = load('@loaders.gl/las');
  const data = require('fs').readFileSync(process.argv[2]);
  const table = await parse(data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength),
                            LASLoader, {las: {shape: 'mesh', fp64: true}, worker: false});
  const a = table.attributes;
  console.log(JSON.stringify({
    count: table.header.vertexCount,
    position: Array.from(a.POSITION.value),
    intensity: a.intensity ? Array.from(a.intensity.value) : null,
    color: a.COLOR_0 ? Array.from(a.COLOR_0.value) : null,
    colorSize: a.COLOR_0 ? a.COLOR_0.size : 0,
  }));
})().catch(err => { console.error(String(err)); process.exit(3); });
"""


def read_with_loaders_gl(path: Path) -> dict:
    node = shutil.which("node")
    assert node, "node is needed for the loaders.gl test"
    assert (LOADERS_GL / "@loaders.gl" / "las").is_dir(), (
        f"loaders.gl not installed at {LOADERS_GL}: run ./run.sh setup")
    done = subprocess.run([node, "-e", READ_JS, str(LOADERS_GL), str(path)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    return dict(json.loads(done.stdout))


def _cloud(table: pa.Table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], 1)
    rgb = np.stack([table.column(c).to_numpy() for c in ("red", "green", "blue")], 1)
    return rig_to_z_up(xyz), table.column("echo").to_numpy().astype(np.int64), rgb


@pytest.mark.parametrize("fmt", ["las", "laz"])
def test_loaders_gl_reads_las_12_points_intensity_and_colour(fmt: str, tmp_path: Path) -> None:
    table = points_table(profiles=12, samples=40)
    write_files(export_files({"points": table}, fmt, "scan"), tmp_path)
    got = read_with_loaders_gl(tmp_path / f"scan.{fmt}")
    xyz, echo, rgb = _cloud(table)
    assert got["count"] == len(xyz)
    np.testing.assert_allclose(np.reshape(got["position"], (-1, 3)), xyz, atol=0.6e-4)
    np.testing.assert_array_equal(got["intensity"], echo)
    colors = np.reshape(got["color"], (-1, got["colorSize"]))[:, :3]
    np.testing.assert_array_equal(colors, rgb)


def test_copclib_reads_laz_14_points_intensity_colour_and_time(tmp_path: Path) -> None:
    """LAS 1.4 (which loaders.gl refuses) through copc-lib's plain LAZ reader."""
    table = points_table(profiles=12, samples=40)
    write_files(export_files({"points": table}, "laz", "scan", las_version="1.4"), tmp_path)
    reader = copclib.LazReader(str(tmp_path / "scan.laz"))
    header = reader.laz_config.las_header
    xyz, echo, rgb = _cloud(table)
    assert (header.point_count, header.point_format_id) == (len(xyz), 7)
    # copclib finds the WKT record (its text is read 6 bytes late: copc-lib takes the 60-byte
    # EVLR header for this 54-byte VLR; laspy and the ASPRS struct reader read it whole)
    assert 'LOCAL_DATUM["scanpipe turntable"' in reader.laz_config.wkt
    points = reader.GetPoints()
    np.testing.assert_allclose(np.stack([points.x, points.y, points.z], 1), xyz, atol=0.6e-4)
    np.testing.assert_array_equal([p.intensity for p in points], echo)
    np.testing.assert_array_equal(np.stack([points.red, points.green, points.blue], 1) // 257,
                                  rgb)
    times = np.array([p.gps_time for p in points])
    assert np.all(np.diff(times) >= 0) and np.ptp(times) > 0


def _vector(v: copclib.Vector3) -> list[float]:
    return [v.x, v.y, v.z]


def test_copclib_reads_the_copc_hierarchy_points_intensity_and_colour(tmp_path: Path) -> None:
    table = points_table(profiles=60, samples=200)
    write_files(export_files({"points": table}, "copc", "scan"), tmp_path)
    reader = copclib.FileReader(str(tmp_path / "scan.copc.laz"))
    header = reader.copc_config.las_header
    xyz, echo, rgb = _cloud(table)
    assert header.point_count == len(xyz)
    np.testing.assert_allclose(_vector(header.min), xyz.min(axis=0), atol=1e-4)
    np.testing.assert_allclose(_vector(header.max), xyz.max(axis=0), atol=1e-4)
    nodes = reader.GetAllNodes()
    assert sum(node.point_count for node in nodes) == len(xyz)
    assert any(str(node.key) == "(0, 0, 0, 0)" for node in nodes)
    assert max(node.key.d for node in nodes) >= 1  # an octree, not one node
    points = reader.GetAllPoints()
    got = np.stack([points.x, points.y, points.z], 1)
    got_echo = np.array([p.intensity for p in points], np.int64)
    got_rgb = np.stack([points.red, points.green, points.blue], 1) // 257
    # COPC orders points by node: match them to the originals by position
    order_got = np.lexsort(got.T[::-1])
    order_want = np.lexsort(np.round(xyz, 4).T[::-1])
    np.testing.assert_allclose(got[order_got], xyz[order_want], atol=0.6e-4)
    np.testing.assert_array_equal(got_echo[order_got], echo[order_want])
    np.testing.assert_array_equal(got_rgb[order_got], rgb[order_want])
    # every node's points lie inside its octree cube
    # every node's points lie inside its octree cube, as the COPC spec defines it from the info
    # VLR's centre and half size (copclib's own Box(key, header) derives cubes from the header
    # bounds instead, its writer's convention, not the spec's)
    info = reader.copc_config.copc_info
    centre = np.array([info.center_x, info.center_y, info.center_z])
    assert np.all(centre - info.halfsize <= xyz.min(axis=0) + 1e-4)
    assert np.all(centre + info.halfsize >= xyz.max(axis=0) - 1e-4)
    for node in nodes:
        node_points = reader.GetPoints(node)
        inside = np.stack([node_points.x, node_points.y, node_points.z], 1)
        edge = 2 * info.halfsize / 2**node.key.d
        low = centre - info.halfsize + np.array([node.key.x, node.key.y, node.key.z]) * edge
        assert np.all((inside >= low - 1e-4) & (inside <= low + edge + 1e-4)), str(node.key)


def _workdir(root: Path) -> Path:
    """A workdir whose artifacts carry provenance (key, stage, parameters) as a run writes."""
    tables = {**textured_box(), "points": points_table()}
    for name, table in tables.items():
        stage = ("mesh" if name.startswith("mesh") else "filter" if name == "points"
                 else "texture")
        write_artifact(root / stage / f"{name}.parquet", table,
                       {"stage": stage, "key": f"{stage}-key-{name}", "seconds": 0.1,
                        "rows": table.num_rows, "params": {"p": 1}})
    return root


def _ply_provenance(data: bytes) -> dict:
    """The record from its comment lines (joined in order; each short enough for rply)."""
    header = data[:data.index(b"end_header\n")].decode()
    lines = [ln for ln in header.splitlines() if ln.startswith(f"comment {PROVENANCE_TAG} ")]
    assert lines and max(len(ln) for ln in lines) < 1000
    return dict(json.loads("".join(ln.split(" ", 2)[2] for ln in lines)))


def _obj_provenance(text: str) -> dict:
    (line,) = [ln for ln in text.splitlines() if ln.startswith(f"# {PROVENANCE_TAG} ")]
    return dict(json.loads(line.split(" ", 2)[2]))


def _glb_provenance(data: bytes) -> dict:
    (length,) = struct.unpack_from("<I", data, 12)
    return dict(json.loads(data[20:20 + length])["asset"]["extras"]["scanpipe"])


def _mcap_provenance(path: Path) -> dict:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        (record,) = [m for m in make_reader(stream).iter_metadata()
                     if m.name == "scanpipe.provenance"]
    return dict(json.loads(record.metadata["json"]))


def test_every_export_names_the_artifacts_it_was_made_from(cli: Callable,
                                                           tmp_path: Path) -> None:
    work = _workdir(tmp_path / "work")
    out = tmp_path / "out"
    for fmt, name in (("obj", "m.obj"), ("glb", "m.glb"), ("ply", "m.ply"), ("mcap", "a.mcap"),
                      ("las", "c.las"), ("e57", "c.e57")):
        result = cli("export", str(work), "-f", fmt, "-o", str(out / name))
        assert result.code == 0, (fmt, result.err)
    mesh_keys = {"mesh_vertices": "mesh-key-mesh_vertices", "mesh_faces": "mesh-key-mesh_faces",
                 "textured_faces": "texture-key-textured_faces",
                 "texture_pages": "texture-key-texture_pages"}
    found = {
        "obj": _obj_provenance((out / "m.obj").read_text()),
        "mtl": _obj_provenance((out / "m.mtl").read_text()),
        "glb": _glb_provenance((out / "m.glb").read_bytes()),
        "ply": _ply_provenance((out / "m.ply").read_bytes()),
    }
    for fmt, record in found.items():
        assert {k: v["key"] for k, v in record["artifacts"].items()} == mesh_keys, fmt
        assert record["artifacts"]["mesh_faces"]["params"] == {"p": 1}
        assert record["scanpipe"]
    mcap = _mcap_provenance(out / "a.mcap")
    assert mcap["artifacts"]["points"]["key"] == "filter-key-points"
    assert mcap["artifacts"]["mesh_faces"]["key"] == "mesh-key-mesh_faces"
    import laspy

    las = laspy.read(out / "c.las")
    vlr = [v for v in las.vlrs if v.user_id == "scanpipe"]
    assert json.loads(bytes(vlr[0].record_data))["artifacts"]["points"]["key"] == (
        "filter-key-points")
    assert b"filter-key-points" in (out / "c.e57").read_bytes()
    # a cloud PLY carries the points' provenance
    write_files(export_files({"points": pa.table(points_table()).replace_schema_metadata(
        {PROVENANCE_KEY: json.dumps({"key": "k1", "stage": "filter", "params": {}})})},
        "ply", "cloud"), tmp_path)
    record = _ply_provenance((tmp_path / "cloud.ply").read_bytes())
    assert record["artifacts"]["points"]["key"] == "k1"
    # a record of several comment lines (a run's parameters) still opens in Open3D (rply)
    import open3d as o3d

    long_params = {f"parameter_{i}": "x" * 40 for i in range(60)}
    write_files(export_files({"points": pa.table(points_table()).replace_schema_metadata(
        {PROVENANCE_KEY: json.dumps({"key": "k2", "stage": "filter", "params": long_params})})},
        "ply", "long"), tmp_path)
    data = (tmp_path / "long.ply").read_bytes()
    assert _ply_provenance(data)["artifacts"]["points"]["params"] == long_params
    assert len(o3d.io.read_point_cloud(str(tmp_path / "long.ply")).points) == 60
