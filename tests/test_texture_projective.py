"""Projective texturing on an analytic box room with a pillar (real Open3D, real JPEG frames)."""

from __future__ import annotations

import cv2
import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from texture_scene import (
    Caster,
    Recording,
    mesh_tables,
    record,
    room_mesh,
    small_rig,
    solid_colour,
)

from scanpipe.camera import camera_pose_in_rig
from scanpipe.errors import StageError
from scanpipe.rig import rig_table
from scanpipe.schema import TEXTURE_PAGES, TEXTURED_FACES
from scanpipe.stages.texture import STAGE
from scanpipe.texturing.atlas import frame_regions, pack_shelves
from scanpipe.texturing.exposure import shared_edges, solve_gains
from scanpipe.texturing.frames import choose_frames
from scanpipe.texturing.projective import colorize_points, face_scores
from scanpipe.texturing.visibility import face_normals


@pytest.fixture(scope="module")
def caster() -> Caster:
    return Caster()


@pytest.fixture(scope="module")
def recording(caster: Caster) -> Recording:
    return record(small_rig(), beta_step_deg=6.0, caster=caster)


@pytest.fixture(scope="module")
def mesh() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return room_mesh(0.25)


def decode_pages(pages: pa.Table) -> list[np.ndarray]:
    return [cv2.imdecode(np.frombuffer(p.as_py(), np.uint8), cv2.IMREAD_COLOR)
            for p in pages.column("png")]


def face_uvs(faces_table: pa.Table) -> np.ndarray:
    return np.stack([np.stack([faces_table.column(f"u{k}").to_numpy(),
                               faces_table.column(f"v{k}").to_numpy()], 1) for k in range(3)], 1)


def sample_atlas(faces_table: pa.Table, pages: list[np.ndarray], bary: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """RGB at barycentric ``bary`` of every textured face, and the textured face indices."""
    page = faces_table.column("page").to_numpy()
    uv = np.einsum("fkc,k->fc", face_uvs(faces_table), bary)
    out = np.zeros((len(page), 3))
    for p, image in enumerate(pages):
        idx = np.flatnonzero(page == p)
        h, w = image.shape[:2]
        x = (uv[idx, 0] * w - 0.5).astype(np.float32).reshape(-1, 1)
        y = (uv[idx, 1] * h - 0.5).astype(np.float32).reshape(-1, 1)
        out[idx] = cv2.remap(image, x, y, cv2.INTER_LINEAR).reshape(-1, 3)[:, ::-1]
    textured = np.flatnonzero(page >= 0)
    return out[textured], textured


def colour_errors(result_tables: dict[str, pa.Table], vertices: np.ndarray, faces: np.ndarray
                  ) -> np.ndarray:
    """|atlas − truth| per channel at three interior points of every textured face."""
    pages = decode_pages(result_tables["texture_pages"])
    errors = []
    for bary in (np.array([1, 1, 1]) / 3, np.array([0.6, 0.2, 0.2]), np.array([0.2, 0.2, 0.6])):
        got, idx = sample_atlas(result_tables["textured_faces"], pages, bary)
        truth = solid_colour(np.einsum("fkc,k->fc", vertices[faces[idx]], bary))
        errors.append(np.abs(got - truth))
    return np.concatenate(errors)


def assert_seen(faces_table: pa.Table, vertices: np.ndarray, faces: np.ndarray,
                recording: Recording, caster: Caster) -> None:
    """Reference check: 10 points on every textured face are unobstructed from its frame's
    camera centre, against the analytic scene (not the texturing mesh)."""
    frames = recording.frames
    key = {(c, s): i for i, (c, s) in enumerate(zip(frames.column("camera_id").to_pylist(),
                                                    frames.column("sequence").to_pylist(),
                                                    strict=True))}
    from scanpipe.motion import beta_deg_at

    beta = beta_deg_at(frames.column("log_time_ns").to_numpy(), recording.motor,
                       recording.rig.motor)
    page = faces_table.column("page").to_numpy()
    cams = faces_table.column("camera_id").to_pylist()
    seqs = faces_table.column("frame").to_numpy()
    rng = np.random.default_rng(1)
    bary = rng.dirichlet((2, 2, 2), size=10) * 0.9 + 0.1 / 3
    origins, points = [], []
    for f in np.flatnonzero(page >= 0):
        row = key[(cams[f], int(seqs[f]))]
        _, centre = camera_pose_in_rig(recording.rig.camera(cams[f]), float(beta[row]))
        pts = bary @ vertices[faces[f]]
        origins.append(np.broadcast_to(centre, pts.shape))
        points.append(pts)
    o, p = np.concatenate(origins), np.concatenate(points)
    d = np.linalg.norm(p - o, axis=1)
    import open3d as o3d

    rays = np.concatenate([o, (p - o) / d[:, None]], 1).astype(np.float32)
    t = caster.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
    blocked = t < d - 0.01
    assert not blocked.any(), f"{blocked.sum()} sample points hidden from their frame"


def test_projective_colours_match_truth_and_contract(recording: Recording, mesh, caster) -> None:
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    result = STAGE.run(recording.inputs(vt, ft))
    faces_table, pages = result.tables["textured_faces"], result.tables["texture_pages"]
    assert faces_table.schema.equals(TEXTURED_FACES.arrow_schema)
    assert pages.schema.equals(TEXTURE_PAGES.arrow_schema)
    assert faces_table.column("face").to_pylist() == list(range(len(faces)))
    errors = colour_errors(result.tables, vertices, faces)
    assert errors.mean() < 3.0 and np.percentile(errors, 95) < 8.0
    report = result.report
    assert report["faces_textured"] + report["faces_untextured"] == len(faces)
    # the horizontal 65° cameras see the walls but not the floor under the rig
    assert 0.2 < report["coverage"] < 0.6
    assert report["occluded_candidates"] > 0  # the pillar hides part of the wall
    page = faces_table.column("page").to_numpy()
    untextured = page < 0
    assert faces_table.column("camera_id").null_count == untextured.sum()
    assert (faces_table.column("frame").to_numpy()[untextured] == -1).all()
    decoded = decode_pages(pages)
    for image, w, h in zip(decoded, pages.column("width").to_pylist(),
                           pages.column("height").to_pylist(), strict=True):
        assert image.shape[:2] == (h, w) and max(w, h) <= 4096
    # untextured faces point at the neutral colour of page 0
    uv = face_uvs(faces_table)[untextured].reshape(-1, 2)
    h, w = decoded[0].shape[:2]
    px = decoded[0][(uv[:, 1] * h).astype(int), (uv[:, 0] * w).astype(int)]
    assert (px == 128).all()
    assert_seen(faces_table, vertices, faces, recording, caster)


def test_occlusion_test_matters(recording: Recording, mesh) -> None:
    """Without the occlusion test some faces would take a frame in which the pillar hides them."""
    vertices, faces, normals = mesh
    frames = choose_frames(recording.frames, recording.motor, recording.rig, 4.0)
    n, _ = face_normals(vertices, faces, normals)
    scores = face_scores(vertices, faces, n, frames)
    naive = scores.frame[:, 0]
    seen = naive >= 0
    from scanpipe.texturing.visibility import MeshOcclusion

    occlusion = MeshOcclusion(vertices, faces)
    centres = np.stack([frames.centre(i) for i in range(len(frames))])
    idx = np.flatnonzero(seen)
    visible = occlusion.faces_visible(centres[naive[idx]], idx)
    assert (~visible).sum() >= 5


def test_distortion_small_pages_and_scale(caster: Caster, mesh) -> None:
    """A distorted lens, 256 px pages (many of them) and half-size texels keep UVs right."""
    rig = small_rig(distortion=(-0.15, 0.04, 0.001, -0.001, 0.0))
    rec = record(rig, beta_step_deg=10.0, caster=caster)
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    result = STAGE.run(rec.inputs(vt, ft), page_size_px=256, texel_scale=0.5,
                       frame_spacing_deg=10.0)
    pages = result.tables["texture_pages"]
    assert pages.num_rows > 2
    assert max(pages.column("width").to_pylist() + pages.column("height").to_pylist()) <= 256
    errors = colour_errors(result.tables, vertices, faces)
    assert errors.mean() < 5.0 and np.percentile(errors, 95) < 14.0


def test_exposure_gains_even_out_a_brighter_camera(caster: Caster, mesh) -> None:
    rec = record(small_rig(), beta_step_deg=6.0, gains={"cam1": 1.25}, caster=caster)
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    on = STAGE.run(rec.inputs(vt, ft))
    off = STAGE.run(rec.inputs(vt, ft), exposure=False)
    assert on.report["gain_max"] / on.report["gain_min"] == pytest.approx(1.25, rel=0.06)
    assert off.report["gain_min"] == off.report["gain_max"] == 1.0

    def seam_jump(tables: dict[str, pa.Table]) -> float:
        """Mean colour step across edges between cam0 and cam1 faces."""
        pages = decode_pages(tables["texture_pages"])
        got, idx = sample_atlas(tables["textured_faces"], pages, np.array([1, 1, 1]) / 3)
        colour = np.full((len(faces), 3), np.nan)
        colour[idx] = got - solid_colour(vertices[faces[idx]].mean(1))
        cams = np.asarray(tables["textured_faces"].column("camera_id").to_pylist(), object)
        pairs, _ = shared_edges(faces)
        a, b = pairs[:, 0], pairs[:, 1]
        cross = (cams[a] != cams[b]) & (cams[a] != None) & (cams[b] != None)  # noqa: E711
        return float(np.nanmean(np.abs(colour[a[cross]] - colour[b[cross]])))

    assert seam_jump(on.tables) < 0.5 * seam_jump(off.tables)


def test_solve_gains_recovers_known_gains() -> None:
    rng = np.random.default_rng(3)
    true = np.array([[1.0, 1.0, 1.0], [1.3, 1.2, 0.9], [0.8, 1.0, 1.1]])
    a = rng.integers(0, 3, 3000)
    b = (a + rng.integers(1, 3, 3000)) % 3
    radiance = rng.uniform(30, 200, (3000, 3))
    # a frame with gain g records radiance / g ... the gains we solve for multiply it back
    gains = solve_gains(a, b, radiance / true[a], radiance / true[b], 3, prior_weight=1e-6)
    ratio = gains / gains[0]
    np.testing.assert_allclose(ratio, true / true[0], rtol=1e-3)


def test_shared_edges_of_two_triangles() -> None:
    pairs, edge = shared_edges(np.array([[0, 1, 2], [2, 1, 3], [3, 4, 5]]))
    assert len(pairs) == 1 and sorted(pairs[0].tolist()) == [0, 1]
    assert sorted(edge[0].tolist()) == [1, 2]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 120), st.integers(1, 120)), min_size=1, max_size=60),
       st.integers(130, 400))
def test_pack_shelves_never_overlaps(sizes: list[tuple[int, int]], page_px: int) -> None:
    array = np.array(sizes, dtype=np.int64)
    page, xs, ys, used = pack_shelves(array, page_px, first=(8, int(array[:, 1].max())))
    canvas = [np.zeros((page_px, page_px), np.int32) for _ in used]
    canvas[0][: array[:, 1].max(), :8] += 1
    for r, (w, h) in enumerate(sizes):
        assert xs[r] + w <= page_px and ys[r] + h <= page_px
        canvas[page[r]][ys[r]:ys[r] + h, xs[r]:xs[r] + w] += 1
        assert used[page[r]][0] >= xs[r] + w and used[page[r]][1] >= ys[r] + h
    assert max(int(c.max()) for c in canvas) == 1


def test_frame_regions_contain_their_faces() -> None:
    rng = np.random.default_rng(5)
    corners = rng.uniform(0, 300, (200, 1, 2)) + rng.uniform(-6, 6, (200, 3, 2))
    corners = np.clip(corners, 0, 299)
    region, boxes = frame_regions(corners, 300, 200 + 100, cell_px=16, pad_px=2)
    lo, hi = corners.min(1), corners.max(1)
    assert (boxes[region, 0] <= lo[:, 0]).all() and (boxes[region, 1] <= lo[:, 1]).all()
    assert (boxes[region, 2] >= hi[:, 0]).all() and (boxes[region, 3] >= hi[:, 1]).all()
    assert len(boxes) < 200  # nearby faces share regions


def test_frame_regions_cut_a_sparse_band_into_tighter_boxes() -> None:
    # small faces along the diagonal of a 1920 × 1080 frame: one 8-connected band whose box
    # is the whole frame; cut into tiles, the boxes hold far less unused image
    t = np.linspace(0, 1, 400)
    centre = np.stack([40 + t * 1840, 40 + t * 1000], 1)
    corners = centre[:, None, :] + np.array([[0.0, 0.0], [12.0, 0.0], [0.0, 12.0]])
    region, boxes = frame_regions(corners, 1920, 1080, cell_px=32, pad_px=3)
    lo, hi = corners.min(1), corners.max(1)
    assert (boxes[region, :2] <= lo).all() and (boxes[region, 2:] >= hi).all()
    area = ((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])).sum()
    assert len(boxes) > 1 and area < 0.25 * 1920 * 1080
    # a compact blob stays one region
    grid = np.stack(np.meshgrid(np.arange(200, 600, 10.0), np.arange(200, 500, 10.0)), -1)
    blob = grid.reshape(-1, 1, 2) + np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    assert len(frame_regions(blob, 1920, 1080)[1]) == 1


def test_colorize_points(recording: Recording, caster: Caster) -> None:
    rng = np.random.default_rng(7)
    # points on the far wall z = 2 (visible), behind the pillar and on the floor below the rig
    wall = np.stack([rng.uniform(-2.5, 2.5, 300), rng.uniform(-0.3, 0.6, 300),
                     np.full(300, 1.999)], 1)
    floor = np.stack([rng.uniform(-0.2, 0.2, 50), np.full(50, -1.199),
                      rng.uniform(-0.2, 0.2, 50)], 1)
    xyz = np.concatenate([wall, floor])
    points = pa.table({c: pa.array(xyz[:, k].astype(np.float32)) for k, c in enumerate("xyz")})
    coloured = colorize_points(points, recording.frames, recording.motor, recording.rig)
    rgb = np.stack([coloured.column(c).to_numpy() for c in ("red", "green", "blue")], 1)
    assert coloured.schema.field("red").type == pa.uint8()
    assert (rgb[300:] == 128).all()  # nobody sees the floor right under the rig
    err = np.abs(rgb[:300].astype(float) - solid_colour(xyz[:300]))
    assert np.median(err) < 6.0


def test_bad_inputs_are_stage_errors(recording: Recording, mesh) -> None:
    vertices, faces, normals = mesh
    vt, ft = mesh_tables(vertices, faces, normals)
    inputs = recording.inputs(vt, ft)
    bad_faces = pa.table({"v0": pa.array([0], pa.int32()), "v1": pa.array([1], pa.int32()),
                          "v2": pa.array([len(vertices)], pa.int32())})
    with pytest.raises(StageError, match="mesh_faces: vertex indices"):
        STAGE.run({**inputs, "mesh_faces": bad_faces})
    with pytest.raises(StageError, match="no camera frames"):
        STAGE.run({**inputs, "frames": recording.frames.slice(0, 0)})
    renamed = recording.frames.set_column(
        0, "camera_id", pa.array(["cam9"] * recording.frames.num_rows, pa.string()))
    with pytest.raises(StageError, match="none of the rig's cameras .* has frames; skipped "
                       r"\d+ frame\(s\) of camera 'cam9'"):
        STAGE.run({**inputs, "frames": renamed})
    broken = recording.frames.set_column(
        recording.frames.column_names.index("data"), "data",
        pa.array([b"not a jpeg"] * recording.frames.num_rows, pa.binary()))
    with pytest.raises(StageError, match="not a decodable image"):
        STAGE.run({**inputs, "frames": broken})
    # one broken frame among good ones (rated on several threads): its error, naming it
    data = recording.frames.column("data").to_pylist()
    data[len(data) // 2] = b"not a jpeg either"
    one_broken = recording.frames.set_column(
        recording.frames.column_names.index("data"), "data", pa.array(data, pa.binary()))
    seq = recording.frames.column("sequence")[len(data) // 2].as_py()
    cam = recording.frames.column("camera_id")[len(data) // 2].as_py()
    with pytest.raises(StageError, match=f"frame {seq} of '{cam}'.*not a decodable image"):
        STAGE.run({**inputs, "frames": one_broken})
    no_cams = recording.rig.model_copy(update={"cameras": ()})
    untextured = STAGE.run({**inputs, "rig": rig_table(no_cams)})
    assert untextured.tables["texture_pages"].num_rows == 0
    assert set(untextured.tables["textured_faces"].column("page").to_pylist()) == {-1}
    assert untextured.report["warnings"] == [
        "untextured: the rig has no cameras; the model is exported without texture"]


def test_inverted_normals_are_flipped(recording: Recording, mesh) -> None:
    vertices, faces, normals = mesh
    upright = STAGE.run(recording.inputs(*mesh_tables(vertices, faces, normals)))
    inverted = STAGE.run(recording.inputs(*mesh_tables(vertices, faces, -normals)))
    assert not upright.report["normals_flipped"] and inverted.report["normals_flipped"]
    assert inverted.report["faces_textured"] == upright.report["faces_textured"]


@pytest.mark.parametrize("rotation", [(0, 0, 0), (20, 0, 0), (-30, 40, 10), (0, 0, 45),
                                      (50, 30, 60), (80, 0, 0)])
def test_view_window_holds_every_visible_direction(rotation: tuple[int, int, int]) -> None:
    from scanpipe.rig import Pose
    from scanpipe.texturing.projective import project_valid, view_window

    cam = small_rig().cameras[0].model_copy(update={"pose": Pose(rotation_deg=rotation)})
    points = np.random.default_rng(0).normal(size=(50_000, 3)) * 3
    for beta in (0.0, 37.0, 170.0):
        window = view_window(cam, beta)
        _, _, valid = project_valid(points, cam, beta, 0.0)
        if rotation == (80, 0, 0):  # looking almost straight up: every azimuth is in view
            assert window is None
            continue
        assert window is not None
        azimuth = np.degrees(np.arctan2(points[valid, 0], points[valid, 2]))
        off = np.abs((azimuth - window[0] + 180) % 360 - 180)
        assert off.max() <= window[1] < off.max() + 6.0
