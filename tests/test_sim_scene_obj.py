"""OBJ/MTL scenes as other tools write them: the triangles must be the file's geometry, and
what cannot be used is a warning, never a silent change."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scanpipe.errors import SimulationError
from scanpipe.rig import Pose
from scanpipe.sim.scene import Scene, load_scene

FIXTURES = Path(__file__).parent / "fixtures"
CORNELL = FIXTURES / "cornell" / "CornellBox-Original.obj"


def reference_triangles(path: Path) -> np.ndarray:
    """A slow, obvious reading of the OBJ spec: whitespace-split lines, relative indices
    against the vertices so far, polygons as fans; (T, 3, 3) corner coordinates."""
    vertices: list[list[float]] = []
    triangles: list[list[list[float]]] = []
    for line in path.read_text().splitlines():
        fields = line.split("#")[0].split()
        if fields and fields[0] == "v":
            vertices.append([float(x) for x in fields[1:4]])
        elif fields and fields[0] == "f" and len(fields) >= 4:
            index = []
            for token in fields[1:]:
                i = int(token.split("/")[0])
                index.append(i - 1 if i > 0 else len(vertices) + i)
            for k in range(1, len(index) - 1):
                triangles.append([vertices[index[0]], vertices[index[k]], vertices[index[k + 1]]])
    return np.asarray(triangles)


def corners(scene: Scene) -> np.ndarray:
    return scene.vertices[scene.triangles]


def test_cornell_box_with_tabs_reads_all_34_triangles() -> None:
    scene = load_scene(CORNELL)
    assert len(scene.triangles) == 34  # 17 quads
    np.testing.assert_array_equal(corners(scene), reference_triangles(CORNELL))
    assert scene.warnings == []
    # Kd colours from the MTL: the left wall is red, the right wall green.
    names = scene.material_names
    assert tuple(scene.textures[names.index("leftWall")][0, 0]) == (160, 16, 12)
    assert tuple(scene.textures[names.index("rightWall")][0, 0]) == (35, 114, 23)


def test_truth_written_from_a_tab_obj_has_its_geometry(tmp_path: Path) -> None:
    scene = load_scene(CORNELL)
    scene.save_glb(tmp_path / "truth.glb")
    again = load_scene(tmp_path / "truth.glb")
    assert len(again.triangles) == 34  # 17 quads
    expected = np.sort(reference_triangles(CORNELL).reshape(-1, 3), axis=0)
    np.testing.assert_allclose(np.sort(corners(again).reshape(-1, 3), axis=0), expected,
                               atol=1e-6)


def write_png(path: Path, rgb: tuple[int, int, int], size: tuple[int, int] = (8, 4)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, rgb).save(path)


def test_blender_style_obj_windows_paths_map_options(tmp_path: Path) -> None:
    # As Blender writes it (o/s/usemtl, v/vt/vn), the MTL in a sub-folder naming its texture
    # relatively with backslashes and with -s/-o options, one texture by an absolute
    # Windows path that only exists beside the MTL.
    write_png(tmp_path / "mat" / "tex" / "wood grain.png", (200, 100, 50))
    write_png(tmp_path / "mat" / "stone.png", (90, 90, 90))
    (tmp_path / "mat" / "scene.mtl").write_text(
        "# Blender MTL File\nnewmtl Wood\nKd 0.8 0.8 0.8\n"
        "map_Kd -s 2 2 1 -o 0.5 0 0 tex\\wood grain.png\n\n"
        "newmtl Stone\nKd 0.8 0.8 0.8\nmap_Kd C:\\Users\\someone\\textures\\stone.png\n")
    obj = tmp_path / "scene.obj"
    obj.write_text(
        "# Blender v3 OBJ File\nmtllib mat/scene.mtl\no Plane\n"
        "v -1.0 0.0 1.0\nv 1.0 0.0 1.0\nv -1.0 0.0 -1.0\nv 1.0 0.0 -1.0\n"
        "vt 0.0 0.0\nvt 1.0 0.0\nvt 0.0 1.0\nvt 1.0 1.0\nvn 0.0 1.0 0.0\n"
        "usemtl Wood\ns off\nf 1/1/1 2/2/1 4/4/1\nusemtl Stone\nf 1/1/1  4/4/1\t3/3/1\n")
    scene = load_scene(obj)
    assert scene.warnings == []
    wood, stone = (scene.material_names.index(n) for n in ("Wood", "Stone"))
    assert tuple(scene.textures[wood][0, 0]) == (200, 100, 50)
    assert tuple(scene.textures[stone][0, 0]) == (90, 90, 90)
    # uv scaled by 2 and offset by 0.5 in u; v flipped to the glTF convention.
    np.testing.assert_allclose(scene.triangle_uvs[0], [[0.5, 1.0], [2.5, 1.0], [2.5, -1.0]])


def test_missing_texture_and_mtl_are_warnings(tmp_path: Path) -> None:
    (tmp_path / "a.mtl").write_text("newmtl red\nKd 1 0 0\nmap_Kd -bm 0.5 gone.png\n")
    obj = tmp_path / "a.obj"
    obj.write_text("mtllib a.mtl\nmtllib nowhere.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\n"
                   "usemtl red\nf 1 2 3\nusemtl blue\nf 3 2 1\n")
    scene = load_scene(obj)
    text = "\n".join(scene.warnings)
    assert "texture 'gone.png' not found" in text
    assert "material library 'nowhere.mtl' not found" in text
    assert "'blue' not defined" in text
    assert tuple(scene.textures[scene.material_names.index("red")][0, 0]) == (255, 0, 0)


def test_two_vertex_faces_lines_and_degenerate_triangles_are_counted(tmp_path: Path) -> None:
    obj = tmp_path / "a.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\n"
                   "f 1 2 3\nf 1 2\nf 3 4\nl 1 2 3\np 1\nf 1 2 4\nf 1 1 3\n")
    scene = load_scene(obj)
    assert len(scene.triangles) == 1
    text = "\n".join(scene.warnings)
    assert "2 faces of fewer than 3 corners dropped" in text
    assert "1 lines (l) dropped" in text and "1 points (p) dropped" in text
    assert "2 degenerate triangles (zero area) dropped" in text


def test_only_lines_is_an_error(tmp_path: Path) -> None:
    obj = tmp_path / "a.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nl 1 2\nf 1 2\n")
    with pytest.raises(SimulationError, match="contains no triangles"):
        load_scene(obj)


def test_trimesh_and_open3d_exports_read_back_equal(tmp_path: Path) -> None:
    import open3d as o3d
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.export(tmp_path / "tm.obj")
    scene = load_scene(tmp_path / "tm.obj")
    np.testing.assert_allclose(corners(scene), box.vertices[box.faces], atol=1e-7)
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    o3d.io.write_triangle_mesh(str(tmp_path / "o3d.obj"), mesh, write_triangle_uvs=False)
    scene = load_scene(tmp_path / "o3d.obj")
    np.testing.assert_allclose(corners(scene),
                               np.asarray(mesh.vertices)[np.asarray(mesh.triangles)], atol=1e-7)


def test_z_up_and_pose(tmp_path: Path) -> None:
    obj = tmp_path / "a.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 0 2\nf 1 2 3\n")
    assert load_scene(obj, up="z").bounds[1][1] == pytest.approx(2.0)
    moved = load_scene(obj, Pose(translation_m=(0.0, 0.0, 3.0), rotation_deg=(0.0, 0.0, 90.0)))
    np.testing.assert_allclose(moved.vertices[1], [0.0, 1.0, 3.0], atol=1e-12)
