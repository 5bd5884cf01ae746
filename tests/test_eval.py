"""Evaluation against ground truth on constructed cases with known answers."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from PIL import Image
from result_tables import box_mesh, faces_table, pages_table, textured_faces_table, vertices_table

from scanpipe.artifacts import write_artifact
from scanpipe.evaluate import (
    Reference,
    SurfaceDistance,
    distance_stats,
    mesh_metrics,
    sample_surface,
    texture_psnr,
    visible_from,
)
from scanpipe.exporters.glb import glb_bytes
from scanpipe.exporters.model import mesh_from_tables
from scanpipe.render import RenderMesh, load_mesh_file, render_mesh_from_model

SIZE, CENTRE = (4.0, 3.0, 5.0), (0.0, 0.3, 0.0)
X_WALL_SHARE = 30.0 / 94.0  # the ±x walls' share of the room's area


def _texture(seed: int, offset: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    image = rng.integers(20, 230, (48, 48, 3)).astype(np.int16) + offset
    buffer = io.BytesIO()
    Image.fromarray(image.astype(np.uint8)).save(buffer, format="PNG")
    return buffer.getvalue()


def room_tables(shift_x_m: float = 0.0, texture_offset: int = 0) -> dict[str, pa.Table]:
    xyz, faces = box_mesh(SIZE, CENTRE)
    xyz = xyz + np.array([shift_x_m, 0.0, 0.0], dtype=np.float32)
    uvs = np.tile(np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]], np.float32), (len(faces), 1, 1))
    return {
        "mesh_vertices": vertices_table(xyz),
        "mesh_faces": faces_table(faces),
        "textured_faces": textured_faces_table(np.arange(len(faces)), np.arange(len(faces)) % 2,
                                               uvs),
        "texture_pages": pages_table({0: _texture(1, texture_offset),
                                      1: _texture(2, texture_offset)}),
    }


def _model(tables: dict[str, pa.Table]) -> RenderMesh:
    return render_mesh_from_model(mesh_from_tables(*(tables[k] for k in (
        "mesh_vertices", "mesh_faces", "textured_faces", "texture_pages"))))


@pytest.fixture(scope="module")
def truth_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A truth folder whose scene.glb is the textured room (read back through trimesh)."""
    folder = tmp_path_factory.mktemp("truth")
    tables = room_tables()
    mesh = mesh_from_tables(*(tables[k] for k in ("mesh_vertices", "mesh_faces",
                                                  "textured_faces", "texture_pages")))
    (folder / "scene.glb").write_bytes(glb_bytes(mesh))
    return folder


def test_identical_mesh_is_perfect(truth_dir: Path) -> None:
    reference = Reference(load_mesh_file(truth_dir / "scene.glb"))
    metrics = mesh_metrics(_model(room_tables()), reference, tau_m=0.005, samples=20_000)
    assert metrics["mesh_mean_m"] < 1e-5
    assert metrics["precision"] == metrics["completeness"] == metrics["fscore"] == 1.0
    assert metrics["visible_truth_share"] == 1.0


def test_shifted_mesh_has_the_known_accuracy_and_fscore(truth_dir: Path) -> None:
    reference = Reference(load_mesh_file(truth_dir / "scene.glb"))
    metrics = mesh_metrics(_model(room_tables(shift_x_m=0.01)), reference, tau_m=0.005,
                           samples=50_000)
    assert metrics["mesh_mean_m"] == pytest.approx(0.01 * X_WALL_SHARE, rel=0.03)
    assert metrics["precision"] == pytest.approx(1 - X_WALL_SHARE, abs=0.01)
    assert metrics["completeness"] == pytest.approx(1 - X_WALL_SHARE, abs=0.01)
    assert metrics["fscore"] == pytest.approx(1 - X_WALL_SHARE, abs=0.01)
    relaxed = mesh_metrics(_model(room_tables(shift_x_m=0.01)), reference, tau_m=0.02,
                           samples=20_000)
    assert relaxed["fscore"] == 1.0


def test_point_errors_match_the_noise(truth_dir: Path) -> None:
    xyz, faces = box_mesh(SIZE, CENTRE)
    surface = SurfaceDistance(RenderMesh(xyz, faces))
    rng = np.random.default_rng(5)
    on_walls = sample_surface(xyz, faces, 20_000, seed=4)
    # move every point along its wall's normal: the coordinate that sits on a wall plane
    half, centre = np.asarray(SIZE) / 2, np.asarray(CENTRE)
    axis = np.argmin(np.abs(np.abs(on_walls - centre) - half), axis=1)
    noisy = on_walls.copy()
    sigma = 0.01
    noisy[np.arange(len(noisy)), axis] += rng.normal(0, sigma, len(noisy))
    stats = distance_stats(surface.distance_m(noisy))
    assert stats["rms_m"] == pytest.approx(sigma, rel=0.03)
    assert stats["mean_m"] == pytest.approx(sigma * math.sqrt(2 / math.pi), rel=0.03)
    assert stats["p95_m"] == pytest.approx(1.96 * sigma, rel=0.05)
    assert stats["count"] == 20_000


def test_visibility_excludes_what_an_occluder_hides() -> None:
    room, room_faces = box_mesh(SIZE, CENTRE)
    block, block_faces = box_mesh((0.5, 0.5, 0.2), (0.0, 0.0, 1.0), inward=False)
    mesh = RenderMesh(np.concatenate([room, block]),
                      np.concatenate([room_faces, block_faces + len(room)]))
    surface = SurfaceDistance(mesh)
    wall_z = CENTRE[2] + SIZE[2] / 2
    points = np.array([[0.0, 0.0, wall_z], [1.5, 0.0, wall_z], [0.0, 0.0, 0.9]])
    np.testing.assert_array_equal(visible_from(surface, points, (0, 0, 0)), [False, True, True])
    np.testing.assert_array_equal(visible_from(surface, points, (0, 0, 0), min_range_m=1.0),
                                  [False, True, False])


def test_texture_psnr_of_a_known_offset(truth_dir: Path) -> None:
    reference = Reference(load_mesh_file(truth_dir / "scene.glb"))
    same = texture_psnr(_model(room_tables()), reference, views=8, width=64)
    assert same["texture_psnr_db"] > 60 and same["texture_views"] == 8
    brighter = texture_psnr(_model(room_tables(texture_offset=10)), reference, views=8, width=64)
    assert brighter["texture_psnr_db"] == pytest.approx(10 * math.log10(255**2 / 100), abs=0.2)
    assert brighter["texture_pixels"] > 8 * 64 * 48 * 0.9


def _workdir(root: Path, tables: dict[str, pa.Table], points: np.ndarray | None) -> Path:
    stages = {"mesh_vertices": "mesh", "mesh_faces": "mesh", "textured_faces": "texture",
              "texture_pages": "texture"}
    for name, table in tables.items():
        stage = stages[name]
        write_artifact(root / stage / f"{name}.parquet", table,
                       {"stage": stage, "key": f"k-{stage}", "seconds": 1.5})
    if points is not None:
        p = points.astype(np.float32)
        write_artifact(root / "filter" / "points.parquet",
                       pa.table({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}),
                       {"stage": "filter", "key": "k-filter", "seconds": 0.25})
    return root


@pytest.mark.slow
def test_eval_command_json(cli: Callable, truth_dir: Path, tmp_path: Path) -> None:
    xyz, faces = box_mesh(SIZE, CENTRE)
    points = sample_surface(xyz, faces, 2000, seed=9)
    work = _workdir(tmp_path / "w", room_tables(), points)
    result = cli("eval", work, "--truth", truth_dir, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    for key in ("points_rms_m", "mesh_mean_m", "completeness", "precision", "fscore",
                "texture_psnr_db"):
        assert key in report
    assert report["points_rms_m"] < 1e-5 and report["points_count"] == 2000
    assert report["fscore"] == 1.0 and report["texture_psnr_db"] > 60
    assert report["stage_seconds"] == {"mesh": 1.5, "texture": 1.5, "filter": 0.25}
    text = cli("eval", work, "--truth", truth_dir / "scene.glb")
    assert text.code == 0 and "F 1.000" in text.out and "PSNR" in text.out


def test_eval_without_texture_gives_null_psnr(cli: Callable, truth_dir: Path,
                                              tmp_path: Path) -> None:
    tables = {k: v for k, v in room_tables().items() if k.startswith("mesh_")}
    work = _workdir(tmp_path / "w", tables, None)
    report = json.loads(cli("eval", work, "--truth", truth_dir, "--json").out)
    assert report["texture_psnr_db"] is None and report["points_rms_m"] is None
    assert report["fscore"] == 1.0


def test_eval_errors(cli: Callable, truth_dir: Path, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    result = cli("eval", empty, "--truth", truth_dir)
    assert result.code == 1 and "neither points nor a mesh" in result.err
    result = cli("eval", empty, "--truth", tmp_path / "nowhere")
    assert result.code == 2 and "not found" in result.err
    result = cli("eval", empty, "--truth", empty)
    assert result.code == 1 and "no scene.glb" in result.err
