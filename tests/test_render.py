"""The ray-casting renderer: orientation (not mirrored), texture, plan view, panorama, CLI."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
from PIL import Image
from result_tables import BLUE, GREEN, RED, WHITE, box_mesh, textured_quad

from scanpipe.artifacts import write_artifact
from scanpipe.exporters.model import mesh_from_tables
from scanpipe.render import (
    PanoramaView,
    PerspectiveView,
    PlanView,
    Renderer,
    RenderMesh,
    render_mesh_from_model,
)


def _quad_renderer() -> Renderer:
    tables = textured_quad()
    return Renderer(render_mesh_from_model(mesh_from_tables(*(tables[k] for k in (
        "mesh_vertices", "mesh_faces", "textured_faces", "texture_pages")))))


def test_perspective_shows_the_texture_upright_and_not_mirrored() -> None:
    view = PerspectiveView(eye=(0.5, 0.5, 1.2), target=(0.5, 0.5, 0.0), width=120, height=120,
                           fov_deg=60.0)
    image = _quad_renderer().render(view)
    rgb = image.rgb
    assert image.hit[60, 60] and not image.hit[0, 0]
    assert tuple(rgb[45, 45]) == RED  # upper left of the quad
    assert tuple(rgb[45, 75]) == GREEN
    assert tuple(rgb[75, 45]) == BLUE
    assert tuple(rgb[75, 75]) == WHITE
    assert abs(float(image.depth_m[60, 60]) - 1.2) < 1e-4
    assert image.textured[60, 60] and not image.textured[0, 0]


def test_untextured_mesh_is_shaded_by_incidence() -> None:
    xyz, faces = box_mesh((2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    renderer = Renderer(RenderMesh(xyz, faces))
    image = renderer.render(PerspectiveView((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 64, 48, 90.0))
    assert image.hit.all() and not image.textured.any()
    centre, corner = image.rgb[24, 32].astype(int), image.rgb[2, 2].astype(int)
    assert centre[0] > corner[0]  # head-on is brighter than grazing


def test_panorama_turns_right_from_plus_z_and_sees_every_wall() -> None:
    size = (4.0, 3.0, 6.0)  # walls at x = ±2, y = -1.5/+1.5, z = ±3
    xyz, faces = box_mesh(size, (0.0, 0.0, 0.0))
    image = Renderer(RenderMesh(xyz, faces)).render(PanoramaView((0.0, 0.0, 0.0), 360))
    depth = image.depth_m
    assert depth.shape == (180, 360) and image.hit.all()
    row = 90  # the horizon
    assert abs(depth[row, 180] - 3.0) < 0.02  # centre: +z
    assert abs(depth[row, 270] - 2.0) < 0.02  # three quarters: turned right by 90°, −x wall
    assert abs(depth[row, 90] - 2.0) < 0.02
    assert abs(depth[0, 180] - 1.5) < 0.05 and abs(depth[-1, 180] - 1.5) < 0.05
    assert abs(depth[row, 0] - 3.0) < 0.05  # behind: −z


def test_plan_view_cuts_the_ceiling_and_keeps_orientation() -> None:
    room, room_faces = box_mesh((4.0, 3.0, 2.0), (0.0, 0.0, 0.0))
    marker, marker_faces = box_mesh((0.4, 0.4, 0.4), (1.5, -1.2, -0.8), inward=False)
    xyz = np.concatenate([room, marker])
    faces = np.concatenate([room_faces, marker_faces + len(room)])
    image = Renderer(RenderMesh(xyz, faces)).render(PlanView(200))
    assert image.hit.mean() > 0.85  # the view adds a 2 % margin on every side
    height, width = image.depth_m.shape
    assert abs(height / width - 2.0 / 4.0) < 0.05
    # the marker (x = +1.5, z = −0.8) is right (+x) and up (−z) in the image: nearer the cut
    # than the floor
    col = int((1.5 + 2.08) / 4.16 * width)
    row = int((-0.8 + 1.04) / 2.08 * height)
    floor = np.median(image.depth_m[image.hit])
    assert image.depth_m[row, col] < floor - 0.3


def test_render_command_writes_pngs(cli: Callable, tmp_path: Path) -> None:
    tables = textured_quad()
    for name, table in tables.items():
        write_artifact(tmp_path / "work" / f"{name}.parquet", table, {"stage": "t"})
    out = tmp_path / "previews"
    result = cli("render", tmp_path / "work", "--out", out, "--width", "64")
    assert result.code == 0, result.err
    names = sorted(p.name for p in out.iterdir())
    assert names == ["panorama.png", "plan.png", "view_overview.png"]
    assert Image.open(out / "panorama.png").size == (64, 32)
    single = tmp_path / "one.png"
    result = cli("render", tmp_path / "work", "--out", single, "--views", "perspective",
                 "--eye", "0.5,0.5,1.2", "--target", "0.5,0.5,0", "--width", "40")
    assert result.code == 0, result.err
    pixels = np.asarray(Image.open(single).convert("RGB"))
    assert pixels.shape == (30, 40, 3) and tuple(pixels[14, 19]) in (RED, GREEN, BLUE, WHITE)


def test_render_command_errors(cli: Callable, tmp_path: Path) -> None:
    result = cli("render", tmp_path, "--out", tmp_path / "x")
    assert result.code == 1 and "no mesh to render" in result.err
    tables = textured_quad()
    for name, table in tables.items():
        write_artifact(tmp_path / f"{name}.parquet", table, {"stage": "t"})
    result = cli("render", tmp_path, "--out", tmp_path / "x", "--views", "sideways")
    assert result.code == 2 and "allowed: perspective, plan, panorama" in result.err
    result = cli("render", tmp_path, "--out", tmp_path / "x", "--eye", "1,2")
    assert result.code == 2 and "expected three numbers" in result.err
    assert not (tmp_path / "x").exists()
    _ = pa  # pyarrow is imported for the artifact helpers' types


def test_front_preview_of_a_one_sided_scan_looks_at_the_data() -> None:
    from scanpipe.render import default_perspectives

    # A scan of one wall at x = −2 (and a small patch behind the scanner, so that it stands
    # inside the bounds): a view along +z from the scanner would see nothing.
    xyz = np.array([[-2, -1, -1], [-2, 1, -1], [-2, 1, 1], [-2, -1, 1],
                    [0.5, -1, 0], [0.5, -0.9, 0], [0.5, -1, 0.1]], dtype=np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]], dtype=np.int32)
    mesh = RenderMesh(xyz, faces)
    front, _ = default_perspectives(mesh.bounds, width=80, mesh=mesh)
    assert front.name == "view_front"
    image = Renderer(mesh).render(front)
    assert image.hit.mean() > 0.4  # the 2 m × 2 m wall at 2 m fills about half the view
    assert int(image.rgb[image.hit].max()) > 0  # drawn, not background
    along_z = PerspectiveView((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 80, 60, 80.0)
    assert not Renderer(mesh).render(along_z).hit.any()  # what the old default showed
    # Data all around (a room): the front view still looks along +z.
    room_xyz, room_faces = box_mesh((4.0, 3.0, 5.0), (0.0, 0.3, 0.0))
    room = RenderMesh(room_xyz, room_faces)
    room_front, _ = default_perspectives(room.bounds, mesh=room)
    assert room_front.target == (0.0, 0.0, 1.0)
