"""The ground-truth scene: built-in rooms, ray casting, textures, loading and saving."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from scanpipe.errors import SimulationError
from scanpipe.rig import Pose
from scanpipe.sim.room import box_room, builtin_room, resolve_scene
from scanpipe.sim.scene import Scene, load_scene


def _unit_directions(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _box_distance(directions: np.ndarray, origin: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray) -> np.ndarray:
    """Analytic distance from ``origin`` inside an axis-aligned box to its walls."""
    with np.errstate(divide="ignore"):
        t_hi = (hi - origin) / directions
        t_lo = (lo - origin) / directions
    t = np.where(directions > 0, t_hi, np.where(directions < 0, t_lo, np.inf))
    return t.min(axis=1)


def test_builtin_room_is_deterministic_furnished_and_sized_like_a_room() -> None:
    a, b = builtin_room(), builtin_room()
    assert np.array_equal(a.vertices, b.vertices)
    assert all(np.array_equal(x, y) for x, y in zip(a.textures, b.textures, strict=True))
    lo, hi = a.bounds
    assert hi[0] - lo[0] == pytest.approx(6.0)
    assert hi[1] - lo[1] == pytest.approx(3.0)
    assert lo[1] == pytest.approx(-1.2)
    assert 4.0 <= hi[2] - lo[2] <= 6.0  # 4 m room plus the alcove behind the doorway
    assert len(a.textures) >= 15  # walls, floor, ceiling, alcove, furniture: each its own


def test_room_textures_are_distinct_and_not_repetitive() -> None:
    textures = builtin_room().textures
    means = [t.reshape(-1, 3).mean(axis=0) for t in textures]
    for i in range(len(textures)):
        for j in range(i + 1, len(textures)):
            same_size = textures[i].shape == textures[j].shape
            assert not (same_size and np.array_equal(textures[i], textures[j]))
            assert np.abs(means[i] - means[j]).max() > 1 or not same_size
    wall = textures[2].astype(np.float64)
    half = wall.shape[1] // 2
    # no tiling: the left and right halves of a wall differ substantially
    assert np.abs(wall[:, :half] - wall[:, half:2 * half]).mean() > 10


def test_box_room_ray_casting_matches_analytic_distances() -> None:
    scene = box_room((6.0, 3.0, 4.0), -1.2)
    origin = np.array([0.3, 0.1, -0.4])
    directions = _unit_directions(5000)
    hits = scene.cast(origin, directions)
    expected = _box_distance(directions, origin, np.array([-3.0, -1.2, -2.0]),
                             np.array([3.0, 1.8, 2.0]))
    assert hits.hit.all()
    np.testing.assert_allclose(hits.t_hit_m, expected, atol=1e-4)
    assert np.allclose(np.linalg.norm(hits.normal, axis=1), 1.0, atol=1e-5)


def test_misses_are_marked() -> None:
    scene = box_room()
    hits = scene.cast(np.array([0.0, 10.0, 0.0]), np.array([[0.0, 1.0, 0.0]]))
    assert not hits.hit[0] and np.isinf(hits.t_hit_m[0]) and hits.triangle_id[0] == -1
    assert (scene.color_at(hits.triangle_id, hits.barycentric, (1, 2, 3)) == (1, 2, 3)).all()


def test_color_at_reads_the_texel_under_the_hit() -> None:
    texture = np.zeros((4, 4, 3), np.uint8)
    texture[0, 3] = (255, 0, 0)   # top right
    texture[3, 0] = (0, 255, 0)   # bottom left
    # one quad at z = 1 facing the origin, u along +x, v (image up) along +y
    vertices = [[-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]]
    uvs = [[[0, 1], [1, 1], [1, 0]], [[0, 1], [1, 0], [0, 0]]]
    scene = Scene(np.array(vertices, float), np.array([[0, 1, 2], [0, 2, 3]]), np.array(uvs),
                  np.zeros(2, np.int32), [texture])
    d = np.array([[0.9, 0.9, 1.0], [-0.9, -0.9, 1.0]])
    hits = scene.cast(np.zeros(3), d / np.linalg.norm(d, axis=1, keepdims=True))
    colors = scene.color_at(hits.triangle_id, hits.barycentric)
    assert colors[0].tolist() == [255, 0, 0]
    assert colors[1].tolist() == [0, 255, 0]


def test_distance_and_surface_samples() -> None:
    scene = box_room((6.0, 3.0, 4.0), -1.2)
    d = scene.distance_m(np.array([[0.0, 0.0, 0.0], [2.5, 1.0, 0.0]]))
    np.testing.assert_allclose(d, [1.2, 0.5], atol=1e-5)
    points = scene.sample_surface(2000, seed=3)
    assert points.shape == (2000, 3)
    assert np.array_equal(points, scene.sample_surface(2000, seed=3))
    assert scene.distance_m(points).max() < 1e-4


def test_glb_round_trip_keeps_geometry_and_texture(tmp_path: Path) -> None:
    room = builtin_room()
    path = tmp_path / "room.glb"
    room.save_glb(path)
    assert isinstance(trimesh.load(path), trimesh.Scene)
    loaded = load_scene(path)
    directions = _unit_directions(3000, seed=1)
    a, b = room.cast(np.zeros(3), directions), loaded.cast(np.zeros(3), directions)
    np.testing.assert_allclose(a.t_hit_m, b.t_hit_m, atol=1e-5)
    colors_a = room.color_at(a.triangle_id, a.barycentric).astype(int)
    colors_b = loaded.color_at(b.triangle_id, b.barycentric).astype(int)
    # PNG is lossless; only rays that land exactly on a texel border may pick the neighbour
    assert (np.abs(colors_a - colors_b).max(axis=1) == 0).mean() > 0.99


def test_pose_moves_a_loaded_scene(tmp_path: Path) -> None:
    path = tmp_path / "box.glb"
    box_room().save_glb(path)
    moved = load_scene(path, Pose(translation_m=(0.0, 0.5, 0.0), rotation_deg=(0.0, 90.0, 0.0)))
    assert moved.bounds[0][1] == pytest.approx(-0.7)
    assert moved.bounds[1][0] - moved.bounds[0][0] == pytest.approx(4.0)


OBJ_POSITIVE = """v 0 0 0
v 1 0 0
v 0 1 0
v 0 0 1
f 1 2 3
f 1 3 4
"""
OBJ_NEGATIVE = """v 0 0 0
v 1 0 0
v 0 1 0
f -3 -2 -1
v 0 0 1
f -4 -2 -1
"""


def test_negative_obj_indices_are_resolved(tmp_path: Path) -> None:
    pos, neg = tmp_path / "pos.obj", tmp_path / "neg.obj"
    pos.write_text(OBJ_POSITIVE)
    neg.write_text(OBJ_NEGATIVE)
    a, b = load_scene(pos), load_scene(neg)
    assert np.array_equal(a.vertices[a.triangles], b.vertices[b.triangles])


def test_negative_index_before_the_first_vertex_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "bad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nf -1 -2 -3\n")
    with pytest.raises(SimulationError,
                       match="line 3: face corner '-3' refers to a vertex that is not defined"):
        load_scene(path)


def test_textured_obj_with_mtl_loads(tmp_path: Path) -> None:
    room = box_room()
    room.to_trimesh().export(tmp_path / "room.obj")
    loaded = load_scene(tmp_path / "room.obj")
    directions = _unit_directions(500, seed=4)
    np.testing.assert_allclose(loaded.cast(np.zeros(3), directions).t_hit_m,
                               room.cast(np.zeros(3), directions).t_hit_m, atol=1e-4)
    assert max(t.shape[0] for t in loaded.textures) > 4  # real images, not a flat colour


@pytest.mark.parametrize(("name", "content", "message"), [
    ("missing.glb", None, "not found"),
    ("scene.ply", "ply", "unsupported scene format"),
    ("broken.glb", "not a glb", "cannot read the scene"),
    ("empty.obj", "# nothing\n", "no triangles"),
])
def test_bad_scene_files_raise_one_line_errors(tmp_path: Path, name: str, content: str | None,
                                               message: str) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(SimulationError, match=message) as info:
        load_scene(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_resolve_scene_knows_the_builtins() -> None:
    assert len(resolve_scene("box").triangles) == 12
    assert len(resolve_scene("room").triangles) == len(builtin_room().triangles)


def test_scene_instances_are_placed_like_trimesh_dump() -> None:
    """Instances are moved by their node transforms (a mirror turns faces round), uncopied."""
    from scanpipe.sim.scene import scene_from_trimesh

    box = trimesh.creation.box((1.0, 2.0, 3.0))
    moved = np.diag([-1.0, 1.0, 1.0, 1.0])  # a mirroring node
    moved[:3, 3] = (5.0, 0.0, -1.0)
    loaded = trimesh.Scene()
    loaded.add_geometry(box, geom_name="plain")
    loaded.add_geometry(box, geom_name="mirrored", transform=moved)
    scene = scene_from_trimesh(loaded)
    expected = np.concatenate([np.asarray(m.vertices)[np.asarray(m.faces)]
                               for m in loaded.dump(concatenate=False)])
    np.testing.assert_allclose(scene.vertices[scene.triangles], expected, atol=1e-12)
    assert scene.material_names == ["plain", "mirrored"]
