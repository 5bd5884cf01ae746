"""Issue 19: the 360° camera model, coverage of the default rig, seams (ICM frame choice, seam
blending), photometric outliers and the texture PSNR over all of the visible surface."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest
from test_texture_projective import decode_pages, face_uvs, sample_atlas
from texture_scene import Caster, Recording, mesh_tables, record, room_mesh, small_rig, solid_colour

from scanpipe.camera import pixel_rays, project_points
from scanpipe.evaluate import Reference, texture_psnr
from scanpipe.render import RenderMesh
from scanpipe.rig import CameraConfig, Pose, default_rig, rig_table
from scanpipe.sim.camera import render_rgb, scaled_camera
from scanpipe.sim.room import builtin_room
from scanpipe.stages.texture import STAGE
from scanpipe.texturing.exposure import shared_edges
from scanpipe.texturing.photometric import Views, photometric_outliers

EQUIRECT = CameraConfig(id="pano", model="equirect", width=256, height=128,
                        pose=Pose(translation_m=(0.0, 0.4, 0.0)))


@pytest.fixture(scope="module")
def caster() -> Caster:
    return Caster()


@pytest.fixture(scope="module")
def mesh() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return room_mesh(0.25)


@pytest.fixture(scope="module")
def recording(caster: Caster) -> Recording:
    return record(small_rig(), beta_step_deg=6.0, caster=caster)


def colour_errors(tables: dict[str, pa.Table], vertices: np.ndarray, faces: np.ndarray
                  ) -> np.ndarray:
    """Largest channel error (levels) at the centroid of every textured face."""
    pages = decode_pages(tables["texture_pages"])
    got, idx = sample_atlas(tables["textured_faces"], pages, np.array([1, 1, 1]) / 3)
    return np.asarray(np.abs(got - solid_colour(vertices[faces[idx]].mean(1))).max(axis=1))


# -- the 360° camera model ----------------------------------------------------------------------

@pytest.mark.parametrize("rotation", [(0.0, 0.0, 0.0), (25.0, -70.0, 10.0), (-90.0, 0.0, 0.0)])
def test_equirect_pixel_rays_and_projection_agree(rotation: tuple[float, float, float]) -> None:
    cam = EQUIRECT.model_copy(update={"pose": Pose(translation_m=(0.1, 0.4, -0.05),
                                                   rotation_deg=rotation)})
    origin, directions = pixel_rays(cam, 33.0)
    assert directions.shape == (128, 256, 3)
    points = origin + directions.reshape(-1, 3) * np.linspace(0.5, 9.0, 256 * 128)[:, None]
    uv, depth = project_points(points, cam, 33.0)
    grid = np.stack(np.meshgrid(np.arange(256.0), np.arange(128.0)), -1).reshape(-1, 2)
    np.testing.assert_allclose(uv, grid, atol=1e-6)
    np.testing.assert_allclose(depth, np.linspace(0.5, 9.0, 256 * 128), rtol=1e-9)


def test_equirect_orientation_centre_forward_top_up() -> None:
    """The image centre looks along the camera's z (the platform's +z at β = 0), the top row
    straight up, and image-right is to the camera's right (not mirrored)."""
    cam = EQUIRECT.model_copy(update={"pose": Pose()})
    uv, _ = project_points(np.array([[0.0, 0.0, 5.0], [0.0, 5.0, 0.0], [-1.0, 0.0, 5.0]]), cam,
                           0.0)
    assert uv[0] == pytest.approx([127.5, 63.5])
    assert uv[1, 1] == pytest.approx(-0.5)
    assert uv[2, 0] > 127.5  # the platform's −x is the camera's right (geometry.CAMERA_BASE)


def test_simulated_equirect_frame_matches_the_projection() -> None:
    """The simulator's 360° frame shows each surface point where project_points puts it."""
    scene = builtin_room()
    cam = EQUIRECT.model_copy(update={"width": 512, "height": 256})
    image = render_rgb(scene, cam, 40.0).astype(np.float64)
    origin, directions = pixel_rays(cam, 40.0, stride=16)
    hits = scene.cast(np.broadcast_to(origin, directions.reshape(-1, 3).shape),
                      directions.reshape(-1, 3))
    points = origin + directions.reshape(-1, 3) * np.asarray(hits.t_hit_m)[:, None]
    uv, _ = project_points(points, cam, 40.0)
    col, row = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    expected = scene.color_at(hits.triangle_id, hits.barycentric, (0, 0, 0)).astype(np.float64)
    assert np.median(np.abs(image[row, col] - expected)) < 2.0


def test_equirect_rig_problems_are_one_line_exit_2(cli, tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    text = ('format_version = 1\n[[cameras]]\nid = "pano"\nmodel = "equirect"\nwidth = 1000\n'
            'height = 400\ndistortion = [0.1, 0, 0, 0, 0]\n')
    path.write_text(text)
    result = cli("rig", "check", path)
    assert result.code == 2
    assert "width must be twice the height; found 1000 × 400" in result.err
    assert "distortion must be [0, 0, 0, 0, 0] for an equirect camera" in result.err
    assert str(path) in result.err and "Traceback" not in result.err
    assert path.read_text() == text
    path.write_text(text.replace('"equirect"', '"fisheye"'))
    result = cli("rig", "check", path)
    assert result.code == 2 and "cameras.0.model" in result.err and "equirect" in result.err


def test_an_equirect_camera_alone_textures_floor_ceiling_and_walls(caster: Caster,
                                                                   mesh) -> None:
    rig = small_rig().model_copy(update={"cameras": (EQUIRECT,)})
    rec = record(rig, beta_step_deg=30.0, caster=caster)
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    result = STAGE.run(rec.inputs(vt, ft), equirect_spacing_deg=30.0)
    centroid_y = vertices[faces].mean(axis=1)[:, 1]
    textured = result.tables["textured_faces"].column("page").to_numpy() >= 0
    assert textured[centroid_y < -1.19].mean() > 0.9  # floor
    assert textured[centroid_y > 1.79].mean() > 0.9  # ceiling
    assert result.report["coverage"] > 0.85  # the pillar hides its far side and a wall strip
    errors = colour_errors(result.tables, vertices, faces)
    assert np.median(errors) < 12


# -- coverage of the default rig -----------------------------------------------------------------

def test_default_rig_textures_95_percent_of_what_the_scanner_sees() -> None:
    """A scanner-grid mesh of the built-in room (all of it seen from the scanner's centre),
    frames of the default camera set (two phones + the 360° camera) every 15° of 180°."""
    scene = builtin_room()
    alpha = np.radians(np.arange(0.0, 360.0, 3.0))
    beta = np.radians(np.arange(0.0, 180.0, 3.0))
    a, b = np.meshgrid(alpha, beta)
    directions = np.stack([np.sin(a) * np.cos(b), np.cos(a), np.sin(a) * np.sin(b)], -1)
    t = np.asarray(scene.cast(np.zeros((a.size, 3)), directions.reshape(-1, 3)).t_hit_m)
    vertices = directions.reshape(-1, 3) * t.reshape(-1, 1)
    idx = np.arange(a.size).reshape(a.shape)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    depth = t[faces]
    faces = faces[np.isfinite(depth).all(1) & (depth.max(1) < 1.1 * depth.min(1))]
    normals = -directions.reshape(-1, 3)
    rig = default_rig()
    cameras = tuple(scaled_camera(c, 1 / 16) for c in rig.cameras)
    rig = rig.model_copy(update={"cameras": cameras})
    t0, rows = 1_700_000_000_000_000_000, []
    steps = round(180.0 / rig.motor.pulse_step_deg)
    for cam in cameras:
        for k, beta_deg in enumerate(np.arange(0.0, 181.0, 15.0)):
            rgb = render_rgb(scene, cam, float(beta_deg))
            ok, jpeg = cv2.imencode(".jpg", rgb[:, :, ::-1])
            assert ok
            rows.append((cam.id, t0 + int(beta_deg * 1e8), k, cam.width, cam.height,
                         jpeg.tobytes()))
    types = {"camera_id": pa.string(), "log_time_ns": pa.int64(), "sequence": pa.int64(),
             "width": pa.int32(), "height": pa.int32(), "data": pa.binary()}
    frames = pa.table({n: pa.array([r[i] for r in rows], t) for i, (n, t) in
                       enumerate(types.items())})
    frames = frames.append_column("format", pa.array(["jpeg"] * len(rows)))
    motor = pa.table({"log_time_ns": [t0, t0 + 18_000_000_000],
                      "step_count": [0, steps], "target_step_count": [steps, steps],
                      "moving": [True, False], "device_time_us": [0, 18_000_000]})
    vt, ft = mesh_tables(vertices, faces, normals)
    result = STAGE.run({"mesh_vertices": vt, "mesh_faces": ft, "frames": frames,
                        "motor": motor, "rig": rig_table(rig)}, frame_spacing_deg=15.0,
                       equirect_spacing_deg=30.0)
    report = result.report
    assert report["coverage"] >= 0.95, report
    assert report["unseen_share"] == pytest.approx(1 - report["coverage"], abs=1e-6)
    used = set(result.tables["textured_faces"].column("camera_id").drop_null().to_pylist())
    assert used == {"cam0", "cam1", "cam360"}  # the phones where they reach, the 360° elsewhere


# -- seams ----------------------------------------------------------------------------------------

def test_icm_frame_choice_cuts_seams_and_keeps_quality(recording: Recording, mesh) -> None:
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    smooth = STAGE.run(recording.inputs(vt, ft))
    best = STAGE.run(recording.inputs(vt, ft), seam_weight=0.0)
    assert best.report["seam_edges"] == best.report["seam_edges_best_frame"]
    assert smooth.report["seam_edges"] < 0.85 * smooth.report["seam_edges_best_frame"]
    assert smooth.report["coverage"] == pytest.approx(best.report["coverage"], abs=0.005)
    assert np.mean(colour_errors(smooth.tables, vertices, faces)) < 1.2 * np.mean(
        colour_errors(best.tables, vertices, faces)) + 1.0


def test_seam_strip_blends_a_brighter_camera(caster: Caster, mesh) -> None:
    """Without global gains, the strip alone pulls both sides of a seam together."""
    rec = record(small_rig(), beta_step_deg=6.0, gains={"cam1": 1.3}, caster=caster)
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)

    def seam_step(tables: dict[str, pa.Table]) -> float:
        pages = decode_pages(tables["texture_pages"])
        pairs, edge = shared_edges(faces)
        cams = np.asarray(tables["textured_faces"].column("camera_id").to_pylist(), object)
        cross = (cams[pairs[:, 0]] != cams[pairs[:, 1]]) & (cams[pairs[:, 0]] != None) & (  # noqa: E711
            cams[pairs[:, 1]] != None)  # noqa: E711
        steps = []
        uvs = face_uvs(tables["textured_faces"])
        page = tables["textured_faces"].column("page").to_numpy()
        for side in (0, 1):  # each face sampled close to the shared edge's middle
            face = pairs[cross, side]
            corners = faces[face]
            on_edge = (corners == edge[cross, :1]) | (corners == edge[cross, 1:])
            weights = np.where(on_edge, 0.45, 0.1)
            uv = np.einsum("fkc,fk->fc", uvs[face], weights)
            got = np.zeros((len(face), 3))
            for p, image in enumerate(pages):
                sel = np.flatnonzero(page[face] == p)
                h, w = image.shape[:2]
                got[sel] = cv2.remap(image, (uv[sel, 0] * w - 0.5).astype(np.float32)[:, None],
                                     (uv[sel, 1] * h - 0.5).astype(np.float32)[:, None],
                                     cv2.INTER_LINEAR).reshape(-1, 3)[:, ::-1]
            steps.append(got - solid_colour(np.einsum("fk,fkc->fc", weights, vertices[corners])))
        return float(np.mean(np.abs(steps[0] - steps[1])))

    blended = STAGE.run(rec.inputs(vt, ft), exposure=False)
    plain = STAGE.run(rec.inputs(vt, ft), exposure=False, seam_strip_px=0.0)
    assert blended.report["seam_points"] > 0 and plain.report["seam_points"] == 0
    assert seam_step(blended.tables) < 0.6 * seam_step(plain.tables)


# -- photometric outliers ----------------------------------------------------------------------

def test_a_person_in_one_frame_is_rejected(caster: Caster, mesh) -> None:
    """A red figure stands in front of the camera in one frame only: with outlier rejection
    no face takes its colour; without, the faces that chose that frame do."""
    rec = record(small_rig(), beta_step_deg=6.0, caster=caster)
    frames = rec.frames
    row = 12  # cam0 at β = 72°
    image = cv2.imdecode(np.frombuffer(frames.column("data")[row].as_py(), np.uint8), 1)
    image[20:170, 60:260] = (30, 30, 230)  # BGR red
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    data = frames.column("data").to_pylist()
    data[row] = jpeg.tobytes()
    frames = frames.set_column(frames.column_names.index("data"), "data",
                               pa.array(data, pa.binary()))
    rec = Recording(rec.rig, frames, rec.motor)
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    kept = STAGE.run(rec.inputs(vt, ft), outlier_levels=0.0)
    rejected = STAGE.run(rec.inputs(vt, ft))
    assert (colour_errors(kept.tables, vertices, faces) > 80).sum() > 20
    assert (colour_errors(rejected.tables, vertices, faces) > 80).sum() == 0
    assert rejected.report["photometric_outliers"] > 20
    assert rejected.report["coverage"] == pytest.approx(kept.report["coverage"], abs=0.01)


def test_photometric_outliers_need_three_views_and_use_the_gains() -> None:
    colour = np.array([[[100, 100, 100], [104, 98, 101], [30, 30, 220], [np.nan] * 3],
                       [[100, 100, 100], [30, 30, 220], [np.nan] * 3, [np.nan] * 3],
                       [[100, 100, 100], [50, 50, 50], [101, 99, 100], [99, 100, 100]]])
    frame = np.array([[0, 1, 2, -1], [0, 1, -1, -1], [0, 3, 1, 2]])
    gains = np.ones((4, 3))
    gains[3] = 2.0  # frame 3 recorded at half the exposure: levelled, it agrees
    outlier = photometric_outliers(Views.from_levels(frame, colour), gains, 40.0)
    np.testing.assert_array_equal(outlier, [[False, False, True, False],
                                            [False, False, False, False],
                                            [False, False, False, False]])


# -- evaluation ----------------------------------------------------------------------------------

def test_psnr_over_the_visible_surface_counts_unseen_faces() -> None:
    """Half the faces untextured: the textured-only PSNR stays perfect, the visible-surface
    PSNR falls to what neutral grey against the truth gives, the unseen share ≈ their share."""
    size = 4.0
    quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32) * size
    verts, tris, uvs = [], [], []
    for k in range(4):  # four walls around the origin, 2 faces each
        angle = k * np.pi / 2
        c, s = np.cos(angle), np.sin(angle)
        wall = np.stack([quad[:, 0] * c + size * s, quad[:, 1], -quad[:, 0] * s + size * c], 1)
        verts.append(wall)
        tris += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
        uvs += [[[0, 1], [1, 1], [1, 0]], [[0, 1], [1, 0], [0, 0]]]
    vertices = np.concatenate(verts).astype(np.float32)
    faces = np.array(tris, np.int32)
    page = np.full((16, 16, 3), (200, 60, 30), np.uint8)
    truth = RenderMesh(vertices, faces, face_uvs=np.array(uvs, np.float32),
                       face_pages=np.zeros(8, np.int32), pages={0: page})
    half = np.where(np.arange(8) < 4, 0, -1).astype(np.int32)  # walls 0, 1 textured
    result = RenderMesh(vertices, faces, face_uvs=np.array(uvs, np.float32), face_pages=half,
                        pages={0: page})
    figures = texture_psnr(result, Reference(truth), views=8, width=64)
    assert figures["texture_psnr_db"] == np.inf
    assert figures["texture_unseen_share"] == pytest.approx(0.5, abs=0.1)
    grey_mse = np.mean((np.array([200, 60, 30]) - 128.0) ** 2)
    expected = 10 * np.log10(255**2 / (grey_mse * figures["texture_unseen_share"]))
    assert figures["texture_psnr_visible_db"] == pytest.approx(expected, abs=0.3)


# -- the report shows what no camera saw ---------------------------------------------------------

def test_report_shows_the_unseen_surface_in_magenta(tmp_path: Path) -> None:
    import base64
    import io
    import re

    from PIL import Image
    from result_tables import (
        box_mesh,
        faces_table,
        pages_table,
        textured_faces_table,
        vertices_table,
    )

    from scanpipe.artifacts import write_artifact
    from scanpipe.report import _glance, _previews

    xyz, tri = box_mesh()
    page = np.where(np.arange(len(tri)) < 10, 0, -1)  # the last wall: no camera saw it
    uvs = np.tile(np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]], np.float32), (len(tri), 1, 1))
    buffer = io.BytesIO()
    Image.fromarray(np.full((8, 8, 3), 90, np.uint8)).save(buffer, format="PNG")
    tables = {"mesh_vertices": vertices_table(xyz), "mesh_faces": faces_table(tri),
              "textured_faces": textured_faces_table(np.arange(len(tri)), page, uvs),
              "texture_pages": pages_table({0: buffer.getvalue()})}
    for name, table in tables.items():
        stage = "mesh" if name.startswith("mesh") else "texture"
        write_artifact(tmp_path / stage / f"{name}.parquet", table,
                       {"stage": stage, "key": stage, "seconds": 1.0, "rows": table.num_rows,
                        "report": {}})
    figures = _previews(tmp_path, 96)
    assert "unseen by every camera (magenta)" in figures[-1]
    data = re.search(r'base64,([A-Za-z0-9+/=]+)', figures[-1])
    assert data is not None
    image = np.asarray(Image.open(io.BytesIO(base64.b64decode(data.group(1)))).convert("RGB"))
    magenta = (image[:, :, 0] > 100) & (image[:, :, 1] < 40) & (image[:, :, 2] > 100)
    assert 0.03 < magenta.mean() < 0.5  # one wall of six, shaded
    rows = dict(_glance({"texture": {"coverage": 0.9, "unseen_share": 0.1, "frames_used": 3}},
                        {}, None))
    assert rows["textured"] == "90 % of the surface, 3 frames used; 10.0 % unseen (magenta " \
                               "in the previews)"


# -- faces no frame holds whole ----------------------------------------------------------------

def test_faces_larger_than_a_frame_are_textured_from_several(caster: Caster) -> None:
    """A room of 3-m triangles: no frame of the small cameras holds one whole. Texel by texel
    from several frames, they are textured, and in the right colours."""
    vertices, faces, normals = room_mesh(3.0)
    rec = record(small_rig(width=180, height=320), beta_step_deg=10.0, caster=caster)
    vt, ft = mesh_tables(vertices, faces, normals)
    whole_only = STAGE.run(rec.inputs(vt, ft), patch_texels=0)
    multiview = STAGE.run(rec.inputs(vt, ft), patch_texels=32)
    assert whole_only.report["coverage"] < 0.3  # only the pillar's sides fit a frame
    assert multiview.report["faces_multiview"] >= 6  # most walls (floor, ceiling: too near)
    assert multiview.report["coverage"] > whole_only.report["coverage"] + 0.1
    tables = multiview.tables
    pages = decode_pages(tables["texture_pages"])
    uvs = face_uvs(tables["textured_faces"])
    page = tables["textured_faces"].column("page").to_numpy()
    rng = np.random.default_rng(5)
    errors = []
    for face in np.flatnonzero(page >= 0):
        bary = rng.dirichlet((2, 2, 2), size=20)
        uv = bary @ uvs[face]
        h, w = pages[page[face]].shape[:2]
        got = cv2.remap(pages[page[face]], (uv[:, 0] * w - 0.5).astype(np.float32)[:, None],
                        (uv[:, 1] * h - 0.5).astype(np.float32)[:, None],
                        cv2.INTER_LINEAR).reshape(-1, 3)[:, ::-1]
        errors.append(np.abs(got - solid_colour(bary @ vertices[faces[face]])).max(axis=1))
    assert np.median(np.concatenate(errors)) < 15
