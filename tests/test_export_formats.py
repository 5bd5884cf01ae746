"""LAS 1.2/1.4 records, the PDAL pipeline, structured E57 and COLMAP, each read back by its
library and by a small independent reader written from the format's documentation; and
``run`` and ``export`` giving the same points, colours and intensities."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import laspy
import numpy as np
import pyarrow.parquet as pq
import pye57
import pytest
from result_tables import points_table
from test_export_clouds import _e57_xml, _write, _z_up

from scanpipe.camera import intrinsic_matrix, project_points
from scanpipe.errors import ExportError
from scanpipe.exporters.e57 import E57Image, E57Scan, write_e57
from scanpipe.exporters.las import (
    LOCAL_WKT,
    adjusted_gps_time_s,
    scan_angle_from_nadir_deg,
    unix_time_ns,
)
from scanpipe.exporters.model import cloud_from_table
from scanpipe.rig import rig_from_table
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.stages.export import export_files
from scanpipe.texturing.frames import choose_frames, pinhole_frames

# -- LAS: an independent header and VLR reader (ASPRS LAS 1.2 / 1.4 specifications) ----------


def _las_records(data: bytes) -> dict:
    assert data[:4] == b"LASF"
    header_size = struct.unpack_from("<H", data, 94)[0]
    n_vlrs = struct.unpack_from("<I", data, 100)[0]
    vlrs, pos = {}, header_size
    for _ in range(n_vlrs):
        user = data[pos + 2:pos + 18].rstrip(b"\0").decode()
        record_id, length = struct.unpack_from("<HH", data, pos + 18)
        vlrs[(user, record_id)] = data[pos + 54:pos + 54 + length]
        pos += 54 + length
    return {"version": (data[24], data[25]),
            "global_encoding": struct.unpack_from("<H", data, 6)[0],
            "format": data[104] & 0x3F, "vlrs": vlrs,
            "software": data[58:90].rstrip(b"\0").decode()}


@pytest.mark.parametrize("version", ["1.2", "1.4"])
def test_las_records_time_source_angle_and_provenance(tmp_path: Path, version: str) -> None:
    table = points_table()
    files = export_files({"points": table}, "las", "scan", las_version=version)
    assert list(files) == ["scan.las", "scan.las.pipeline.json"]
    data = files["scan.las"]
    head = _las_records(data)
    assert head["version"] == (1, int(version[2]))
    assert head["format"] == (3 if version == "1.2" else 7)
    assert head["global_encoding"] & 1  # adjusted standard GPS time
    assert bool(head["global_encoding"] & 16) == (version == "1.4")  # WKT bit (1.4 only)
    assert head["vlrs"][("LASF_Projection", 2112)].rstrip(b"\0").decode() == LOCAL_WKT
    record = json.loads(head["vlrs"][("scanpipe", 1)])
    assert record["scanpipe"] and head["software"] == "scanpipe"
    path = tmp_path / "scan.las"
    path.write_bytes(data)
    las = laspy.read(path)
    np.testing.assert_array_equal(np.asarray(las.intensity), table.column("echo").to_numpy())
    np.testing.assert_array_equal(np.asarray(las.point_source_id),
                                  table.column("profile").to_numpy() + 1)
    time_ns = table.column("time_ns").to_numpy()
    assert np.max(np.abs(unix_time_ns(np.asarray(las.gps_time)) - time_ns)) < 1000  # < 1 µs
    gps_s = time_ns[0] / 1e9 - 315964800 + 18  # seconds since the GPS epoch
    assert abs(float(np.asarray(las.gps_time)[0]) - (gps_s - 1e9)) < 1e-6
    angle = scan_angle_from_nadir_deg(table.column("alpha_deg").to_numpy())
    if version == "1.2":
        np.testing.assert_array_equal(np.asarray(las.scan_angle_rank),
                                      np.clip(np.rint(angle), -90, 90))
    else:
        np.testing.assert_allclose(np.asarray(las.scan_angle) * 0.006, angle, atol=0.003)


def test_gps_time_conversion_and_scan_angle_are_exact_at_known_values() -> None:
    # 1980-01-06T00:00:00Z + 1e9 GPS s, minus the 18 leap seconds, as Unix time
    unix_ns = np.array([(315_964_800 + 1_000_000_000 - 18) * 10**9], np.int64)
    assert adjusted_gps_time_s(unix_ns)[0] == 0.0
    assert unix_time_ns(np.array([0.0]))[0] == unix_ns[0]
    np.testing.assert_array_equal(scan_angle_from_nadir_deg(np.array([180.0, 90.0, 270.0, 0.0])),
                                  [0.0, -90.0, 90.0, -180.0])


def test_pdal_pipeline_reads_the_file_beside_it(tmp_path: Path) -> None:
    path = _write({"points": points_table()}, "laz", tmp_path)
    pipeline = json.loads((tmp_path / "scan.laz.pipeline.json").read_text())
    (reader,) = pipeline["pipeline"]
    assert reader["type"] == "readers.las" and reader["default_srs"] == LOCAL_WKT
    assert (tmp_path / reader["filename"]).samefile(path)


# -- E57 -------------------------------------------------------------------------------------------


def test_e57_scan_keeps_the_grid_intensity_colour_and_provenance(tmp_path: Path) -> None:
    table = points_table()
    path = _write({"points": table}, "e57", tmp_path)
    reader = pye57.E57(str(path))
    scan = reader.read_scan_raw(0)
    np.testing.assert_array_equal(scan["rowIndex"], table.column("profile").to_numpy())
    np.testing.assert_array_equal(scan["columnIndex"], table.column("sample").to_numpy())
    np.testing.assert_array_equal(scan["intensity"], table.column("echo").to_numpy())
    np.testing.assert_array_equal(scan["colorGreen"], table.column("green").to_numpy())
    reader.close()
    node = _e57_xml(path.read_bytes()).find("./data3D/vectorChild")
    assert node is not None and node.findtext("sensorVendor") == "scanpipe"
    assert "scanpipe" in json.loads(node.findtext("sensorModel") or "{}")
    bounds = node.find("indexBounds")
    assert bounds is not None and int(bounds.findtext("rowMaximum") or -1) == 5
    assert int(bounds.findtext("columnMaximum") or -1) == 9
    names = {child.tag for child in node.find("points").find("prototype")}  # type: ignore[union-attr]
    assert {"rowIndex", "columnIndex", "intensity", "colorRed"} <= names


def test_write_e57_writes_one_scan_per_position_with_its_pose(tmp_path: Path) -> None:
    first, second = (cloud_from_table(points_table(seed=s)) for s in (0, 1))
    half = np.sqrt(0.5)
    path = tmp_path / "site.e57"
    write_e57(path, [E57Scan(first, "position 1"),
                     E57Scan(second, "position 2", (half, 0.0, 0.0, half), (5.0, -2.0, 0.0))])
    reader = pye57.E57(str(path))
    assert reader.scan_count == 2
    pose = reader.get_header(1)
    np.testing.assert_allclose(pose.translation, [5.0, -2.0, 0.0])
    np.testing.assert_allclose(pose.rotation, [half, 0, 0, half])
    local = reader.read_scan_raw(1)
    np.testing.assert_allclose(local["cartesianX"], _z_up(second.xyz.astype(float))[:, 0],
                               atol=1e-6)
    reader.close()
    scans = _e57_xml(path.read_bytes()).findall("./data3D/vectorChild")
    assert [s.findtext("name") for s in scans] == ["position 1", "position 2"]
    assert float(scans[1].findtext("pose/translation/x") or 0) == 5.0


def test_write_e57_keeps_a_png_frame_and_its_description(tmp_path: Path) -> None:
    import cv2

    ok, png = cv2.imencode(".png", np.arange(16 * 24 * 3, dtype=np.uint8).reshape(16, 24, 3))
    assert ok
    image = E57Image(png.tobytes(), 24, 16, 30.0, 32.0, 11.5, 7.5, (1.0, 0.0, 0.0, 0.0),
                     (0.5, -1.0, 2.0), "cam0_000001.png", "png", "lens distortion: 0.1")
    path = tmp_path / "site.e57"
    write_e57(path, [E57Scan(cloud_from_table(points_table()))], [image])
    reader = pye57.E57(str(path))
    node = reader.image_file.root()["images2D"][0]
    blob = node["pinholeRepresentation"]["pngImage"]
    data = np.zeros(blob.byteCount(), np.uint8)
    blob.read(data, 0, blob.byteCount())
    assert data.tobytes() == png.tobytes()
    assert node["description"].value() == "lens distortion: 0.1"
    assert not node["pinholeRepresentation"].isDefined("jpegImage")
    assert [node["pose"]["translation"][a].value() for a in "xyz"] == [0.5, -1.0, 2.0]
    reader.close()


def test_write_e57_refuses_an_image_format_it_cannot_name(tmp_path: Path) -> None:
    image = E57Image(b"BM..", 16, 16, 20.0, 20.0, 7.5, 7.5, (1.0, 0.0, 0.0, 0.0),
                     (0.0, 0.0, 0.0), "cam0_000001.bmp", "bmp")
    path = tmp_path / "site.e57"
    with pytest.raises(ExportError, match=r"image 'cam0_000001.bmp': format 'bmp'; "
                                          r"allowed: jpeg, png"):
        write_e57(path, [E57Scan(cloud_from_table(points_table()))], [image])
    assert not path.exists()


# -- the chain: run and export agree; COLMAP ----------------------------------------------------


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("formats")
    simulate_direct(root / "scan.mcap", root / "truth", SimOptions(
        beam_step_deg=4.0, motor_step_deg=10.0, camera_scale=0.125, camera_fps=0.5, seed=2))
    return root


def test_run_and_export_give_the_same_points_colours_and_intensities(cli, workdir: Path,  # type: ignore[no-untyped-def]
                                                                     tmp_path: Path) -> None:
    work = tmp_path / "w"
    done = cli("run", workdir / "scan.mcap", "--workdir", work, "--set", "mesh.method=grid",
               "--set", 'export.cloud_formats=["las", "e57", "colmap"]',
               "--set", 'export.mesh_formats=["glb"]')
    assert done.code == 0, done.err
    ran = laspy.read(work / "export" / "cloud.las")
    assert int(np.asarray(ran.intensity).max()) > 0  # the simulated echo, end to end
    assert len(np.unique(np.asarray(ran.red))) > 10  # coloured from the frames
    for fmt in ("las", "e57"):
        exported = cli("export", work, "-f", fmt, "--out", tmp_path / f"x.{fmt}")
        assert exported.code == 0, exported.err
    las = laspy.read(tmp_path / "x.las")
    for field in ("X", "Y", "Z", "intensity", "red", "green", "blue", "gps_time"):
        np.testing.assert_array_equal(np.asarray(las[field]), np.asarray(ran[field]))
    a, b = pye57.E57(str(tmp_path / "x.e57")), pye57.E57(str(work / "export" / "cloud.e57"))
    sa, sb = a.read_scan_raw(0), b.read_scan_raw(0)
    for key in ("cartesianX", "intensity", "colorRed", "rowIndex"):
        np.testing.assert_array_equal(sa[key], sb[key])
    a.close()
    b.close()
    for e57 in (tmp_path / "x.e57", work / "export" / "cloud.e57"):
        _check_e57_images(e57, work)
    key = pq.read_schema(work / "filter" / "points.parquet").metadata[b"scanpipe.provenance"]
    record = json.loads(laspy.read(tmp_path / "x.las").header.vlrs[1].record_data)
    assert record["artifacts"]["points"]["key"] == json.loads(key)["key"]
    _check_colmap(work / "export" / "cloud_colmap", work)


def _check_e57_images(path: Path, work: Path) -> None:
    """The frames as images2D read back with pye57.libe57: blob bytes, pinhole intrinsics, and
    the pose + pinhole read as CloudCompare's E57 reader does (ccCameraSensor: depth = −z,
    u = cx + f·x/depth, v = cy − f·y/depth) put the file's points where scanpipe projects
    them."""
    frames, rig, _ = pinhole_frames(pq.read_table(work / "decode" / "frames.parquet"),
                                    rig_from_table(pq.read_table(work / "decode" / "rig.parquet")))
    chosen = choose_frames(frames, pq.read_table(work / "decode" / "motor.parquet"), rig, 5.0)
    reader = pye57.E57(str(path))
    scan = reader.read_scan_raw(0)
    file_xyz = np.stack([scan[f"cartesian{a}"] for a in "XYZ"], axis=1)
    rig_xyz = np.stack([file_xyz[:, 0], file_xyz[:, 2], -file_xyz[:, 1]], axis=1)  # z-up → rig
    images = reader.image_file.root()["images2D"]
    assert images.childCount() == len(chosen) > 0
    checked = 0
    for k in range(images.childCount()):
        node, cam = images[k], chosen.cameras[k]
        pinhole = node["pinholeRepresentation"]
        blob = pinhole["jpegImage"]
        data = np.zeros(blob.byteCount(), np.uint8)
        blob.read(data, 0, blob.byteCount())
        assert data.tobytes() == chosen.encoded[k]
        assert (pinhole["imageWidth"].value(), pinhole["imageHeight"].value()) == (
            cam.width, cam.height)
        f_m = pinhole["focalLength"].value()
        fx, fy = f_m / pinhole["pixelWidth"].value(), f_m / pinhole["pixelHeight"].value()
        cx, cy = pinhole["principalPointX"].value(), pinhole["principalPointY"].value()
        np.testing.assert_allclose([fx, fy, cx, cy], [cam.fx, cam.fy, cam.cx, cam.cy],
                                   rtol=1e-12)
        q = np.array([node["pose"]["rotation"][a].value() for a in "wxyz"])
        t = np.array([node["pose"]["translation"][a].value() for a in "xyz"])
        assert abs(np.linalg.norm(q) - 1) < 1e-9
        cam_xyz = (file_xyz - t) @ _rotation(q)  # file → camera: Rᵀ (p − t)
        ours, depth = project_points(rig_xyz, cam, float(chosen.beta_deg[k]))
        seen = ((-cam_xyz[:, 2] > 0.1) & (ours[:, 0] >= 0) & (ours[:, 0] < cam.width)
                & (ours[:, 1] >= 0) & (ours[:, 1] < cam.height))
        cc_depth = -cam_xyz[seen, 2]
        uv = np.stack([cx + fx * cam_xyz[seen, 0] / cc_depth,
                       cy - fy * cam_xyz[seen, 1] / cc_depth], axis=1)
        np.testing.assert_allclose(uv, ours[seen], atol=0.01)
        np.testing.assert_allclose(cc_depth, depth[seen], atol=1e-6)
        checked += int(seen.sum())
    reader.close()
    assert checked > 50


def _read_colmap(folder: Path) -> tuple[dict, list, np.ndarray]:
    """cameras.txt, images.txt, points3D.txt per COLMAP's documented text format."""
    def lines(name: str) -> list[str]:
        text = (folder / "sparse" / "0" / name).read_text().split("\n")
        return [line for line in text if not line.startswith("#")]

    cameras = {}
    for line in lines("cameras.txt"):
        if line.strip():
            cid, model, width, height, *params = line.split()
            cameras[int(cid)] = (model, int(width), int(height), [float(p) for p in params])
    body = lines("images.txt")
    images = []
    for k in range(0, len(body) - 1, 2):  # two lines per image, the second (POINTS2D) empty
        if not body[k].strip():
            break
        iid, qw, qx, qy, qz, tx, ty, tz, cid, name = body[k].split()
        assert body[k + 1] == ""
        images.append((int(iid), np.array([qw, qx, qy, qz], float), np.array([tx, ty, tz], float),
                       int(cid), name))
    points = np.array([[float(v) for v in line.split()[:7]] for line in lines("points3D.txt")
                       if line.strip()])
    return cameras, images, points


def _rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _check_colmap(folder: Path, work: Path) -> None:
    cameras, images, points = _read_colmap(folder)
    assert cameras and images and len(points) > 100
    assert np.all(points[:, 4:7] <= 255) and np.all(np.diff(points[:, 0]) == 1)
    frames, rig, _ = pinhole_frames(pq.read_table(work / "decode" / "frames.parquet"),
                                    rig_from_table(pq.read_table(work / "decode" / "rig.parquet")))
    chosen = choose_frames(frames, pq.read_table(work / "decode" / "motor.parquet"), rig, 5.0)
    assert len(images) == len(chosen)
    cams = {c.id: c for c in rig.cameras}
    for k, (_, q, t, cid, name) in enumerate(images):
        assert (folder / "images" / name).read_bytes() == chosen.encoded[k]
        assert abs(np.linalg.norm(q) - 1) < 1e-9
        model, width, height, params = cameras[cid]
        cam = cams[name.rsplit("_", 1)[0]]
        assert model == "OPENCV" and len(params) == 8 and cam.id == chosen.cameras[k].id
        assert (width, height) == (cam.width, cam.height)
        # COLMAP puts the centre of the top-left pixel at (0.5, 0.5) (its docs, "Cameras";
        # its feature detector), scanpipe (as OpenCV and ROS) at (0, 0): cx, cy move by half
        # a pixel.
        np.testing.assert_allclose(params[:4], intrinsic_matrix(cam)[[0, 1, 0, 1], [0, 1, 2, 2]]
                                   + [0, 0, 0.5, 0.5])
        # COLMAP's world→camera pose and pinhole put every point where scanpipe projects it
        cam_xyz = points[:, 1:4] @ _rotation(q).T + t
        front = cam_xyz[:, 2] > 0.1
        uv = cam_xyz[front, :2] / cam_xyz[front, 2:] * params[:2] + params[2:4] - 0.5
        ours, depth = project_points(points[front, 1:4], cam, float(chosen.beta_deg[k]))
        np.testing.assert_allclose(ours, uv, atol=1e-3)
        np.testing.assert_allclose(depth, cam_xyz[front, 2], atol=1e-6)


def test_bad_las_version_and_colmap_without_frames_are_one_line_errors(  # type: ignore[no-untyped-def]
        cli, tmp_path: Path) -> None:
    folder = tmp_path / "flat"
    folder.mkdir()
    pq.write_table(points_table(), folder / "points.parquet")
    kept = tmp_path / "x.las"
    kept.write_bytes(b"valid before")
    bad = cli("export", folder, "-f", "las", "--las-version", "1.3", "--out", kept, "--force")
    assert bad.code == 2
    assert bad.err.strip() == ("scanpipe: error: --las-version '1.3': allowed: 1.2, 1.4")
    assert kept.read_bytes() == b"valid before"
    no_frames = cli("export", folder, "-f", "colmap", "--out", tmp_path / "c")
    assert no_frames.code != 0 and len(no_frames.err.strip().splitlines()) == 1
    assert "colmap export needs camera frames" in no_frames.err
    assert not (tmp_path / "c" / "scan_colmap").exists()


# -- COPC: laspy's CopcReader, and the specification's invariants read with struct -------------


def test_copc_reads_in_laspy_and_keeps_the_spec_invariants(tmp_path: Path) -> None:
    table = points_table(profiles=40, samples=60)
    path = _write({"points": table}, "copc", tmp_path)
    assert path.name == "scan.copc.laz"
    assert json.loads((tmp_path / "scan.copc.laz.pipeline.json").read_text())[
        "pipeline"][0]["type"] == "readers.copc"
    data = path.read_bytes()
    plain = laspy.read(_write({"points": table}, "las", tmp_path))
    with laspy.CopcReader.open(path) as reader:
        everything = reader.query()
        coarse = reader.query(resolution=float(reader.copc_info.spacing))
    assert len(everything) == len(table) and 0 < len(coarse) < len(table)
    # the same points as the LAS export, in octree order
    key = np.lexsort((np.asarray(plain.Z), np.asarray(plain.Y), np.asarray(plain.X)))
    got = np.lexsort((np.asarray(everything.Z), np.asarray(everything.Y),
                      np.asarray(everything.X)))
    for field in ("X", "Y", "Z", "intensity", "red", "gps_time", "point_source_id"):
        np.testing.assert_array_equal(np.asarray(everything[field])[got],
                                      np.asarray(plain[field])[key])
    # spec: LAS 1.4, format 6/7 with the LAZ bit, the COPC info VLR first at byte 375
    assert (data[24], data[25]) == (1, 4) and data[104] & 0x3F == 7 and data[104] & 0x80
    assert data[375 + 2:375 + 6] == b"copc" and struct.unpack_from("<H", data, 375 + 18)[0] == 1
    info = struct.unpack_from("<5d2Q2d", data, 375 + 54)
    center, halfsize, root_offset, root_size = np.array(info[:3]), info[3], info[5], info[6]
    evlr_start, n_evlrs = struct.unpack_from("<QI", data, 235)
    assert n_evlrs == 1 and data[evlr_start + 2:evlr_start + 6] == b"copc"
    assert struct.unpack_from("<H", data, evlr_start + 18)[0] == 1000
    assert root_offset == evlr_start + 60 and root_size % 32 == 0
    entries = [struct.unpack_from("<4iQii", data, root_offset + 32 * k)
               for k in range(root_size // 32)]
    keys = {e[:4] for e in entries}
    assert (0, 0, 0, 0) in keys and sum(e[6] for e in entries) == len(table)
    for d, x, y, z in keys - {(0, 0, 0, 0)}:  # every node's parent is in the hierarchy
        assert (d - 1, x // 2, y // 2, z // 2) in keys
    point_start = struct.unpack_from("<I", data, 96)[0]
    offsets = [e[4] for e in entries]
    assert offsets[0] == point_start + 8  # after the chunk-table offset
    sizes = [e[5] for e in entries]
    assert all(a + s == b for a, s, b in zip(offsets[:-1], sizes[:-1], offsets[1:], strict=True))
    # the points of each node (file order) lie inside its voxel
    whole = laspy.read(path)
    xyz = np.column_stack([whole.x, whole.y, whole.z])
    start = 0
    for d, x, y, z, _, _, count in entries:
        size = 2 * halfsize / 2**d
        low = center - halfsize + size * np.array([x, y, z])
        inside = xyz[start:start + count]
        assert np.all(inside >= low - 1e-9) and np.all(inside <= low + size + 1e-9)
        start += count


def test_e57_frames_are_undistorted_to_the_pinhole_they_are_written_with() -> None:
    """E57's pinhole has no distortion terms: a frame from a lens with distortion is written
    undistorted, so a point seen at its distorted pixel in the recorded frame lies at the
    plain pinhole pixel K·(x/z, y/z) of the written one."""
    import cv2

    from scanpipe.camera import project_points
    from scanpipe.images import decode_image_bytes, encode_png
    from scanpipe.rig import default_cameras
    from scanpipe.stages.export import pinhole_image

    cam = default_cameras()[0]
    cam = cam.model_copy(update={"width": 640, "height": 360, "fx": 500.0, "fy": 500.0,
                                 "cx": 320.0, "cy": 180.0,
                                 "distortion": (-0.28, 0.09, 0.001, -0.0008, 0.0)})
    no_lens = cam.model_copy(update={"distortion": (0.0, 0.0, 0.0, 0.0, 0.0)})
    rng = np.random.default_rng(1)
    # points on a wall 3 m in front of the camera, towards the image corners
    from scanpipe.camera import pixel_rays

    origins, rays = pixel_rays(no_lens, 0.0, stride=1)
    rays = rays.reshape(cam.height, cam.width, 3)
    picks = [(40, 60), (300, 580), (50, 600), (320, 40)]
    for row, col in picks:
        target = origins.reshape(-1, 3)[0] + 3.0 * rays[row, col] * (1 + 0.1 * rng.random())
        distorted, _ = project_points(target[None, :], cam, 0.0)
        ideal, _ = project_points(target[None, :], no_lens, 0.0)
        frame = np.zeros((cam.height, cam.width, 3), np.uint8)
        cv2.circle(frame, tuple(round(float(v)) for v in distorted[0]), 3, (255, 255, 255), -1)
        written = decode_image_bytes(pinhole_image(encode_png(frame), "png", cam), "test")
        ys, xs = np.nonzero(written[:, :, 0] > 60)
        weights = written[ys, xs, 0].astype(np.float64)
        centre = [np.average(xs, weights=weights), np.average(ys, weights=weights)]
        # the dot was drawn at the distorted pixel rounded to whole pixels: within 1 px
        np.testing.assert_allclose(centre, ideal[0], atol=1.0)
        assert np.linalg.norm(distorted[0] - ideal[0]) > 3  # the lens did move it
    # without distortion the bytes are passed through unchanged
    data = encode_png(np.zeros((8, 8, 3), np.uint8))
    assert pinhole_image(data, "png", no_lens) is data


def test_run_writes_a_manifest_of_the_files_as_written(cli, workdir: Path,  # type: ignore[no-untyped-def]
                                                       tmp_path: Path) -> None:
    """The user's path: ``scanpipe run`` with the default exports (the OBJ streamed while it
    is written): the manifest names every file beside it with its size and digest on disk,
    and a second run reuses the export."""
    import hashlib

    import pyarrow.parquet as pq

    work = tmp_path / "w"
    done = cli("run", workdir / "scan.mcap", "--workdir", work, "--set", "mesh.method=grid")
    assert done.code == 0, done.err
    folder = work / "export"
    rows = pq.read_table(folder / "export_manifest.parquet").to_pylist()
    assert {"model.obj", "model.glb", "cloud.ply"} <= {row["file"] for row in rows}
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        [row["file"] for row in rows] + ["export_manifest.parquet"])
    for row in rows:
        data = (folder / row["file"]).read_bytes()
        assert (row["bytes"], row["sha256"]) == (len(data), hashlib.sha256(data).hexdigest())
    obj = (folder / "model.obj").read_text()
    assert obj.count("\nf ") > 100 and obj.endswith("\n")
    before = (folder / "model.obj").stat().st_mtime_ns
    again = cli("run", workdir / "scan.mcap", "--workdir", work, "--set", "mesh.method=grid")
    assert again.code == 0, again.err
    assert (folder / "model.obj").stat().st_mtime_ns == before  # reused by key
