"""OBJ + MTL + PNG export: two readers (trimesh, Open3D), upright texture, names, speed path."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from result_tables import (
    BLUE,
    GREEN,
    RED,
    WHITE,
    faces_table,
    points_table,
    textured_box,
    textured_quad,
    vertices_table,
)

from scanpipe.artifacts import file_bytes
from scanpipe.exporters.textfmt import BLOCK_ROWS, Fixed, Ints, render_lines
from scanpipe.exporting import write_files
from scanpipe.stages.export import export_files

CORNERS = {(0.0, 1.0, 0.0): RED, (1.0, 1.0, 0.0): GREEN, (0.0, 0.0, 0.0): BLUE,
           (1.0, 0.0, 0.0): WHITE}


def _export(tables: dict, tmp_path: Path, stem: str = "quad") -> Path:
    write_files(export_files(tables, "obj", stem), tmp_path)
    return tmp_path / f"{stem}.obj"


def test_obj_files_are_named_after_the_stem_with_relative_references(tmp_path: Path) -> None:
    files = export_files(textured_quad(), "obj", "my room")
    assert list(files) == ["my room.obj", "my_room.mtl", "my_room_page0.png"]
    obj = file_bytes(files["my room.obj"]).decode()
    mtl = file_bytes(files["my_room.mtl"]).decode()
    assert "mtllib my_room.mtl\n" in obj
    assert "usemtl my_room_page0\n" in obj
    assert "map_Kd my_room_page0.png" in mtl
    assert "Kd 1 1 1" in mtl
    assert "/" not in re.findall(r"map_Kd (.*)", mtl)[0]


def test_texture_is_upright_and_not_mirrored_in_trimesh(tmp_path: Path) -> None:
    mesh = trimesh.load(_export(textured_quad(), tmp_path), process=False)
    image = mesh.visual.material.image
    for corner, rgb in CORNERS.items():
        i = int(np.argmin(np.linalg.norm(mesh.vertices - np.array(corner), axis=1)))
        uv = mesh.visual.uv[i]
        inside = uv * 0.96 + 0.02  # a texel just inside the corner
        color = trimesh.visual.color.uv_to_color(inside[None, :], image)[0, :3]
        assert tuple(int(c) for c in color) == rgb, (corner, uv)


def test_texture_is_upright_in_open3d(tmp_path: Path) -> None:
    mesh = o3d.io.read_triangle_mesh(str(_export(textured_quad(), tmp_path)), True)
    assert len(mesh.triangles) == 2 and mesh.has_textures()
    image = np.asarray(mesh.textures[0])
    height, width = image.shape[:2]
    vertices = np.asarray(mesh.vertices)
    uvs = np.asarray(mesh.triangle_uvs).reshape(-1, 3, 2)
    for t, tri in enumerate(np.asarray(mesh.triangles)):
        for k, v in enumerate(tri):
            u, vv = uvs[t, k] * 0.96 + 0.02
            # Open3D keeps OBJ's v-up coordinates and flips the image rows on load instead.
            texel = image[int(vv * height), int(u * width)]
            assert tuple(int(c) for c in texel[:3]) == CORNERS[tuple(vertices[v])]


def test_box_with_pages_and_untextured_faces_reads_back_in_two_readers(tmp_path: Path) -> None:
    tables = textured_box(pages=2, untextured_faces=2)
    path = _export(tables, tmp_path, "box")
    text = path.read_text()
    assert text.count("usemtl ") == 3  # untextured, page0, page1
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "box.mtl", "box.obj", "box_page0.png", "box_page1.png", "box_untextured.png"]
    loaded = trimesh.load(path, process=False, force="mesh", group_material=False)
    xyz = tables["mesh_vertices"]
    bounds = np.array([[min(xyz.column(c).to_pylist()) for c in "xyz"],
                       [max(xyz.column(c).to_pylist()) for c in "xyz"]])
    np.testing.assert_allclose(loaded.bounds, bounds, atol=1e-6)
    assert len(loaded.faces) == 12
    o3d_mesh = o3d.io.read_triangle_mesh(str(path), True)
    assert len(o3d_mesh.triangles) == 12
    np.testing.assert_allclose(o3d_mesh.get_min_bound(), bounds[0], atol=1e-6)
    np.testing.assert_allclose(o3d_mesh.get_max_bound(), bounds[1], atol=1e-6)
    assert len(o3d_mesh.textures) >= 2
    # Every face carries a UV and every material an image, or Open3D drops the texture.
    assert o3d_mesh.has_textures() and len(o3d_mesh.triangle_uvs) == 36


def test_two_exports_into_one_folder_do_not_collide(tmp_path: Path) -> None:
    _export(textured_quad(), tmp_path, "a")
    _export(textured_box(), tmp_path, "b")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["a.mtl", "a.obj", "a_page0.png", "b.mtl", "b.obj", "b_page0.png",
                     "b_page1.png", "b_untextured.png"]
    assert len(trimesh.load(tmp_path / "a.obj", process=False).faces) == 2
    assert "mtllib b.mtl" in (tmp_path / "b.obj").read_text()


def test_untextured_mesh_keeps_vertex_colours(tmp_path: Path) -> None:
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)
    tables = {"mesh_vertices": vertices_table(xyz, np.tile([0, 0, 1.0], (3, 1)), colors),
              "mesh_faces": faces_table(np.array([[0, 1, 2]]))}
    files = export_files(tables, "obj", "tri")
    assert list(files) == ["tri.obj"]
    path = _export(tables, tmp_path, "tri")
    mesh = trimesh.load(path, process=False)
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], colors)
    assert np.asarray(o3d.io.read_triangle_mesh(str(path)).vertex_colors).shape == (3, 3)


def test_obj_needs_a_mesh() -> None:
    from scanpipe.errors import ArtifactError

    with pytest.raises(ArtifactError, match="obj export needs a mesh"):
        export_files({"points": points_table()}, "obj", "x")


# -- the vectorised formatter against Python's own formatting ---------------------------------


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 2**40), min_size=1, max_size=40))
def test_integer_columns_match_python(values: list[int]) -> None:
    column = np.array(values, dtype=np.int64)
    text = render_lines(len(values), [b"f ", Ints(column), b"/", Ints(column[::-1].copy())])
    expected = "".join(f"f {a}/{b}\n" for a, b in zip(values, values[::-1], strict=True))
    assert text.decode() == expected


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4, allow_nan=False), min_size=1, max_size=40))
def test_float_columns_parse_back_to_the_value(values: list[float]) -> None:
    x = np.array(values)
    lines = render_lines(len(values), [b"v ", Fixed(x, 6)]).decode().splitlines()
    assert len(lines) == len(values)
    parsed = np.array([float(line.split()[1]) for line in lines])
    np.testing.assert_allclose(parsed, x, atol=5.01e-7, rtol=0)
    for line in lines:
        assert re.fullmatch(r"v -?\d+\.\d{6}", line), line


def fixed_reference(x: float, decimals: int) -> str:
    """The formatter's rule spelled out with Python integers: ``rint(|x|·10^d)`` printed with
    ``d`` decimals, the sign only on a non-zero result."""
    quantised = int(np.rint(abs(x) * 10**decimals))
    whole, frac = divmod(quantised, 10**decimals)
    sign = "-" if x < 0 and quantised else ""
    return f"{sign}{whole}" + (f".{frac:0{decimals}d}" if decimals else "")


@settings(max_examples=80, deadline=None)
@given(st.lists(st.one_of(st.floats(-2e6, 2e6, allow_nan=False),
                          st.floats(-1e-3, 1e-3, allow_nan=False),
                          st.sampled_from([0.0, -0.0, 0.5, -0.5, 999.9999999, -999.99999,
                                           1000.0, -1e6, 0.0005, -0.00049])),
                min_size=1, max_size=30),
       st.integers(0, 7))
def test_fixed_columns_follow_the_rule_at_every_precision(values: list[float],
                                                          decimals: int) -> None:
    # whole parts below and above 1000 (the sign is then a word of its own), every number of
    # decimals (partial three-digit groups), separators after each
    x = np.array(values)
    text = render_lines(len(values), [b"p ", Fixed(x, decimals), b" ", Fixed(-x, decimals),
                                      b"|"]).decode()
    expected = "".join(f"p {fixed_reference(a, decimals)} {fixed_reference(-a, decimals)}|\n"
                       for a in values)
    assert text == expected


def test_lines_across_blocks_with_repeated_columns_and_separators() -> None:
    # more rows than one block; a column used twice in a line (OBJ's v/vt/v) keeps no
    # separator of its first use; literals of one byte, several bytes and none between numbers
    rows = 2 * BLOCK_ROWS + 7
    rng = np.random.default_rng(5)
    a = rng.integers(0, 10**9, rows) // rng.integers(1, 10**8, rows)
    b = rng.integers(0, 2**40, rows)
    x = rng.standard_normal(rows) * 10.0 ** rng.integers(-3, 5, rows)
    column = Ints(a)
    text = render_lines(rows, [b"f ", column, b"/", Ints(b), b"/", column, b" ", Fixed(x, 3),
                               b"ab", Fixed(x, 0), column, b"long literal"]).decode()
    lines = text.split("\n")
    assert lines[-1] == "" and len(lines) == rows + 1
    for i in (0, 1, BLOCK_ROWS - 1, BLOCK_ROWS, rows // 2, rows - 1):
        assert lines[i] == (f"f {a[i]}/{b[i]}/{a[i]} {fixed_reference(x[i], 3)}ab"
                            f"{fixed_reference(x[i], 0)}{a[i]}long literal"), i


@pytest.mark.parametrize("slice_corners", [1 << 20, 7])
def test_split_by_uv_keeps_every_corner_uv_and_shares_inside_charts(
        slice_corners: int, monkeypatch: pytest.MonkeyPatch) -> None:
    from scanpipe.exporters import model
    from scanpipe.exporters.model import split_by_uv

    monkeypatch.setattr(model, "SPLIT_SLICE", slice_corners)  # one slice, or many

    rng = np.random.default_rng(7)
    corner_vertex = rng.integers(0, 50, 600)
    vertex_uv = rng.random((50, 2)).astype(np.float32)
    corner_uv = vertex_uv[corner_vertex].copy()
    seams = rng.random(600) < 0.1
    corner_uv[seams] = rng.random((int(seams.sum()), 2)).astype(np.float32)
    source, vt_uv, vt_index = split_by_uv(corner_vertex, corner_uv)
    assert vt_index.dtype == np.uint32  # glTF's index type: GLB writes it as it is
    np.testing.assert_array_equal(vt_uv[vt_index], corner_uv)  # every corner keeps its uv
    np.testing.assert_array_equal(source[vt_index], corner_vertex)  # and its vertex
    # slow reference: a corner needs its own vt unless it repeats its vertex's first uv
    first: dict[int, int] = {}
    own = 0
    for i, v in enumerate(corner_vertex.tolist()):
        if v not in first:
            first[v] = i
            own += 1
        elif not np.array_equal(corner_uv[i], corner_uv[first[v]]):
            own += 1
    assert len(vt_uv) == own
