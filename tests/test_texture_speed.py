"""The texture stage's faster paths decide as the plain ones do: shared edges in one sort, the
occlusion test with shared corner/edge rays and Open3D's any-hit query, and ICM that only looks
at the faces near a seam."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np
import pytest
from texture_scene import Caster, mesh_tables, record, room_mesh, small_rig

from scanpipe.stages.texture import STAGE
from scanpipe.texturing.exposure import shared_edges
from scanpipe.texturing.frames import worker_count
from scanpipe.texturing.labels import Smoothing, face_neighbours, seam_edge_count, smooth_labels
from scanpipe.texturing.projective import FaceScores
from scanpipe.texturing.visibility import MeshOcclusion, mesh_edges


def grid_faces(rows: int, cols: int, start: int = 0) -> np.ndarray:
    """Two triangles per cell of a rows × cols grid of vertices (row-major), offset by start."""
    idx = np.arange(rows * cols).reshape(rows, cols) + start
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def wall_and_pole() -> tuple[np.ndarray, np.ndarray]:
    """A 0.9 m × 0.9 m wall of 30 × 30 cells (3 cm) at z = 3 m and a 6 cm wide pole at
    z = 1.5 m before its middle (its edges off the lines through the wall's vertices, so no
    ray grazes an edge): what the pole hides depends on where the camera stands."""
    xs, ys = np.meshgrid(np.linspace(-0.45, 0.45, 31), np.linspace(-0.45, 0.45, 31))
    wall = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)], 1)
    px, py = np.meshgrid([-0.0317, 0.0283], np.linspace(-1.03, 0.97, 5))
    pole = np.stack([px.ravel(), py.ravel(), np.full(px.size, 1.5)], 1)
    faces = np.concatenate([grid_faces(31, 31), grid_faces(5, 2, start=len(wall))])
    return np.concatenate([wall, pole]), faces


def segments_blocked(origin: np.ndarray, points: np.ndarray, tri: np.ndarray,
                     limit: np.ndarray) -> np.ndarray:
    """Plain Möller–Trumbore, every segment against every triangle: does the segment
    origin → point hit a triangle before ``limit`` (metres from the origin)?"""
    direction = (points - origin) / np.linalg.norm(points - origin, axis=1)[:, None]  # (P, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]  # (T, 3)
    p = np.cross(direction[:, None], e2[None])  # (P, T, 3)
    det = np.einsum("tc,ptc->pt", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - tri[:, 0]  # (T, 3)
    u = np.einsum("tc,ptc->pt", s, p) * inv
    q = np.cross(s, e1)  # (T, 3)
    v = (direction @ q.T) * inv
    t = (e2 * q).sum(axis=1)[None] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < limit[:, None])
    return np.asarray(hit.any(axis=1))


def plain_faces_visible(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray,
                        face_ids: np.ndarray, abs_tol_m: float = 0.01, rel_tol: float = 0.005
                        ) -> np.ndarray:
    """Centroid, corners and edge middles of each face, each tested on its own."""
    c = vertices[faces[face_ids]]  # (F, 3, 3)
    points = np.concatenate([c.mean(axis=1)[:, None], c, 0.5 * (c + np.roll(c, -1, axis=1))],
                            axis=1).reshape(-1, 3)
    limit = np.linalg.norm(points - origin, axis=1) * (1 - rel_tol) - abs_tol_m
    blocked = np.concatenate([
        segments_blocked(origin, points[k:k + 500], vertices[faces], limit[k:k + 500])
        for k in range(0, len(points), 500)])
    return np.asarray(~blocked.reshape(len(face_ids), 7).any(axis=1))


def test_shared_edges_match_a_plain_count() -> None:
    """Pairs of faces on edges used exactly twice, in edge order; edges of one face or of three
    faces (non-manifold) left out."""
    faces = np.concatenate([grid_faces(4, 5), [[0, 1, 30], [7, 8, 31], [7, 8, 32]]])
    pairs, edge_vertices = shared_edges(faces)
    owners: dict[tuple[int, int], list[int]] = defaultdict(list)
    for f, tri in enumerate(faces.tolist()):
        for k in range(3):
            a, b = sorted((tri[k], tri[(k + 1) % 3]))
            owners[(a, b)].append(f)
    expected = sorted((edge, fs) for edge, fs in owners.items() if len(fs) == 2)
    assert [tuple(e) for e in edge_vertices.tolist()] == [e for e, _ in expected]
    assert np.sort(pairs, axis=1).tolist() == [fs for _, fs in expected]
    assert (7, 8) not in {tuple(e) for e in edge_vertices.tolist()}  # three faces


ORIGINS = [(0.0011, 0.0023, 0.0), (0.1513, 0.2017, 0.5), (-0.2009, -0.3013, 0.0)]


@pytest.mark.parametrize("origin", ORIGINS)
def test_shared_rays_decide_as_each_face_alone(origin: tuple[float, float, float]) -> None:
    vertices, faces = wall_and_pole()
    wall = np.arange(2 * 30 * 30)
    occlusion = MeshOcclusion(vertices, faces)
    at = np.asarray(origin)
    shared = occlusion.faces_visible(np.tile(at, (len(wall), 1)), wall,
                                     views=np.zeros(len(wall)))
    assert 0 < (~shared).sum() < len(wall) // 4  # the pole hides a band, no more
    np.testing.assert_array_equal(shared, plain_faces_visible(vertices, faces, at, wall))
    assert occlusion.rays_cast < 4 * len(wall)  # corners and edges shared: not 7 per face


def test_blocks_follow_the_mesh_not_the_face_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """A scan grid lists a quad's two triangles half the mesh apart: cast in blocks of faces,
    the faces are grouped by their lowest vertex, so a block shares its corners' and edges'
    rays (~3 per face, not ~5 in face order), and the answers do not depend on the blocks."""
    import scanpipe.texturing.visibility as visibility

    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, 61), np.linspace(-0.6, 0.6, 61))
    wall = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)], 1)
    _, pole_faces = wall_and_pole()
    pole = wall_and_pole()[0][31 * 31:]
    vertices = np.concatenate([wall, pole])
    faces = np.concatenate([grid_faces(61, 61), pole_faces[2 * 30 * 30:] - 31 * 31 + len(wall)])
    on_wall = np.arange(2 * 60 * 60)
    origin = np.array(ORIGINS[1])
    origins = np.tile(origin, (len(on_wall), 1))
    whole = MeshOcclusion(vertices, faces).faces_visible(origins, on_wall)
    monkeypatch.setattr(visibility, "FACES_PER_CAST", 1024)
    occlusion = MeshOcclusion(vertices, faces)
    blocked = occlusion.faces_visible(origins, on_wall)
    np.testing.assert_array_equal(blocked, whole)
    assert 0 < (~blocked).sum() < len(on_wall) // 4
    assert occlusion.rays_cast < 3.4 * len(on_wall)  # 5.1 per face in face order
    rank = occlusion.locality_rank()
    assert sorted(rank.tolist()) == list(range(len(faces)))


def test_views_group_the_rays_and_only_group_them() -> None:
    """Faces from several origins in any order: each decided from its own origin; views found
    from the origins when not given."""
    vertices, faces = wall_and_pole()
    origins = np.array(ORIGINS)
    rng = np.random.default_rng(3)
    face_ids = rng.permutation(np.repeat(np.arange(1800), 3))
    view = rng.integers(0, 3, len(face_ids))
    occlusion = MeshOcclusion(vertices, faces)
    got = occlusion.faces_visible(origins[view], face_ids, views=view)
    alone = np.empty(len(face_ids), dtype=bool)
    for k in range(3):
        mine = view == k
        alone[mine] = MeshOcclusion(vertices, faces).faces_visible(
            origins[view[mine]], face_ids[mine], views=np.zeros(int(mine.sum())))
    np.testing.assert_array_equal(got, alone)
    np.testing.assert_array_equal(occlusion.faces_visible(origins[view], face_ids), got)


def test_unobstructed_tolerance() -> None:
    """A point on the wall, or within 1 cm + 0.5 % behind it, is reached; 5 cm behind is not;
    a point at the camera is."""
    vertices, faces = wall_and_pole()
    occlusion = MeshOcclusion(vertices, faces)
    points = np.array([[0.2, 0.2, 3.0], [0.2, 0.2, 3.02], [0.2, 0.2, 3.05], [0.2, 0.2, 0.0]])
    ok = occlusion.unobstructed(np.zeros((4, 3)), points)
    assert ok.tolist() == [True, True, False, True]


class _Frames:
    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def centre(self, index: int) -> np.ndarray:
        return np.array([float(index), 0.0, 0.0])


class _EveryThirdHidden:
    """Occlusion stand-in: a face is hidden from a frame when (face + frame) % 3 == 0."""

    def faces_visible(self, origins: np.ndarray, face_ids: np.ndarray, *_: Any,
                      views: np.ndarray | None = None) -> np.ndarray:
        frame = origins[:, 0].astype(np.int64)
        return np.asarray((face_ids + frame) % 3 != 0)

    def faces_visible_from(self, centres: np.ndarray, views: np.ndarray, face_ids: np.ndarray,
                           *_: Any) -> np.ndarray:
        return self.faces_visible(centres[views], face_ids)


def plain_icm(scores: np.ndarray, labels: np.ndarray, neighbours: np.ndarray, n_frames: int,
              seam_weight: float, rounds: int) -> np.ndarray:
    """ICM scanning every face each round (the rule of scanpipe.texturing.labels)."""
    labels = labels.copy()
    rng = np.random.default_rng(0)
    textured = labels >= 0
    reference = np.zeros(len(labels))
    reference[textured] = scores[labels[textured], np.flatnonzero(textured)]

    def cost(candidate: np.ndarray, active: np.ndarray, nb: np.ndarray, counted: np.ndarray
             ) -> np.ndarray:
        score = scores[np.maximum(candidate, 0), active].astype(np.float64)
        data = 1.0 - score / np.maximum(reference[active], 1e-12)
        data[(candidate < 0) | (score <= 0)] = np.inf
        return np.asarray(data + seam_weight * (counted & (nb != candidate[:, None])).sum(1))

    for _ in range(rounds):
        lab_n = np.where(neighbours >= 0, labels[np.maximum(neighbours, 0)], -1)
        lab_n[labels < 0] = -1
        counted = lab_n >= 0
        active = np.flatnonzero((labels >= 0) & np.any(counted & (lab_n != labels[:, None]), 1))
        if len(active) == 0:
            break
        own, nb, cnt = labels[active], lab_n[active], counted[active]
        current = cost(own, active, nb, cnt)
        options = np.stack([cost(nb[:, k], active, nb, cnt) for k in range(3)], 1)
        options[nb == own[:, None]] = np.inf
        best = np.argmin(options, axis=1)
        gain = options[np.arange(len(active)), best] - current
        move = (gain < -1e-9) & (rng.random(len(active)) < 0.5)
        if not move.any():
            if not (gain < -1e-9).any():
                break
            continue
        face, target = active[move], nb[move, best[move]]
        visible = (face + target) % 3 != 0
        labels[face[visible]] = target[visible]
        scores[target[~visible], face[~visible]] = 0.0
    return labels


def test_icm_on_the_seam_neighbourhood_moves_as_a_full_scan() -> None:
    faces = grid_faces(30, 30)
    neighbours = face_neighbours(faces)
    rng = np.random.default_rng(7)
    n_frames = 6
    scores = rng.uniform(0.2, 1.0, (n_frames, len(faces))).astype(np.float32)
    scores[rng.random(scores.shape) < 0.2] = 0.0
    labels = np.where(scores.max(axis=0) > 0, np.argmax(scores, axis=0), -1).astype(np.int64)
    expected = plain_icm(scores.copy(), labels, neighbours, n_frames, 0.3, 10)
    frames: Any = _Frames(n_frames)
    occlusion: Any = _EveryThirdHidden()
    kept = FaceScores.from_dense(scores, n_frames)  # every frame kept: as the dense matrix
    result = smooth_labels(kept, labels, neighbours, frames, occlusion, 0.3, 10)
    assert isinstance(result, Smoothing)
    assert result.moved > 100
    np.testing.assert_array_equal(result.labels, expected)
    assert seam_edge_count(result.labels, neighbours) < seam_edge_count(labels, neighbours)
    # the mesh's edges instead of the neighbour table (as the stage calls it): the same moves
    edges = mesh_edges(faces)
    again = smooth_labels(FaceScores.from_dense(scores, n_frames), labels, edges, frames,
                          _EveryThirdHidden(), 0.3, 10)
    np.testing.assert_array_equal(again.labels, expected)
    assert (again.seam_edges_before, again.seam_edges_after, again.moved) == (
        result.seam_edges_before, result.seam_edges_after, result.moved)
    assert seam_edge_count(result.labels, edges) == result.seam_edges_after
    np.testing.assert_array_equal(edges.neighbours(np.array([5, 0, 899])), neighbours[[5, 0, 899]])


def test_worker_count_takes_a_batch_workers_share(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert worker_count(100) == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert worker_count(100) == 3
    assert worker_count(2) == 2
    assert worker_count(0) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert 1 <= worker_count(100) <= 4


def test_threads_do_not_change_the_texture(monkeypatch: pytest.MonkeyPatch) -> None:
    """The stage's threaded loops (scores, samples, candidates, outliers, occlusion blocks,
    atlas regions) give the same artifacts on one thread and on four."""
    caster = Caster()
    rec = record(small_rig(), beta_step_deg=6.0, caster=caster)
    vertices, faces, normals = room_mesh(0.25)
    vt, ft = mesh_tables(vertices, faces, normals)
    results = []
    for threads in ("1", "4"):
        monkeypatch.setenv("OMP_NUM_THREADS", threads)
        results.append(STAGE.run(rec.inputs(vt, ft)))
    one, four = results
    assert one.report["faces_textured"] > 1000
    for name in ("textured_faces", "texture_pages"):
        assert one.tables[name].equals(four.tables[name]), name


def plain_neighbours(faces: np.ndarray) -> list[list[int]]:
    """Per face the faces sharing a two-face edge with it: first the edges it is the first
    owner of (lower corner slot ``k · faces + face``), then those it is second in, each group
    in the order of the edge's sorted vertex pair."""
    n = len(faces)
    owners: dict[tuple[int, int], list[int]] = defaultdict(list)
    for k in range(3):
        for f, tri in enumerate(faces.tolist()):
            owners[tuple(sorted((tri[k], tri[(k + 1) % 3])))].append(k * n + f)  # type: ignore
    firsts: list[list[int]] = [[] for _ in range(n)]
    seconds: list[list[int]] = [[] for _ in range(n)]
    for _, slots in sorted(owners.items()):
        if len(slots) == 2:
            a, b = sorted(slots)
            firsts[a % n].append(b % n)
            seconds[b % n].append(a % n)
    return [(firsts[f] + seconds[f] + [-1, -1, -1])[:3] for f in range(n)]


def test_mesh_edges_give_shared_edges_and_neighbours_in_one_sort() -> None:
    """One sort of the edge keys gives the occlusion test's edge ids, shared_edges' pairs and
    edge vertices (same order) and each face's neighbours as a plain walk over the edges
    lists them: boundary, non-manifold (three faces) and a face with a repeated vertex."""
    rng = np.random.default_rng(5)
    faces = np.concatenate([grid_faces(6, 7), [[0, 1, 50], [8, 9, 51], [8, 9, 52], [3, 3, 4]]])
    faces = faces[rng.permutation(len(faces))]
    faces = np.where(rng.random(faces.shape[0])[:, None] < 0.5, faces, faces[:, [1, 2, 0]])
    edges = mesh_edges(faces)
    pairs, edge_vertices = shared_edges(faces)
    np.testing.assert_array_equal(edges.pairs(), pairs)
    np.testing.assert_array_equal(edges.vertices(faces), edge_vertices)
    assert edges.neighbours().tolist() == plain_neighbours(faces)
    np.testing.assert_array_equal(face_neighbours(faces), edges.neighbours())
    # ids: one per undirected edge, numbered in the order of the sorted vertex pairs
    keys = sorted({tuple(sorted((a, b))) for tri in faces.tolist()
                   for a, b in zip(tri, tri[1:] + tri[:1], strict=True)})
    for f, tri in enumerate(faces.tolist()):
        for k in range(3):
            key = tuple(sorted((tri[k], tri[(k + 1) % 3])))
            assert edges.ids[f, k] == keys.index(key)
    assert edges.count == len(keys)


def test_a_triangle_soup_has_no_neighbours_and_no_seams() -> None:
    """Faces that share no edge (an imported mesh with its vertices unshared): every neighbour
    is −1, no seam, and ICM moves nothing (it used to index an empty pair list)."""
    faces = np.arange(12).reshape(4, 3)
    edges = mesh_edges(faces)
    assert edges.pairs().shape == (0, 2)
    assert (edges.neighbours() == -1).all() and (edges.neighbours(np.array([2])) == -1).all()
    labels = np.array([0, 1, 0, 1])
    assert edges.seam_faces(labels)[1] == 0
    scores = FaceScores.from_dense(np.ones((2, 4), np.float32), 2)
    result = smooth_labels(scores, labels, edges, _Frames(2), _EveryThirdHidden(), 0.3, 10)
    np.testing.assert_array_equal(result.labels, labels)
    assert (result.moved, result.seam_edges_before, result.seam_edges_after) == (0, 0, 0)


def test_atlas_regions_match_a_cell_by_cell_painting() -> None:
    """frame_regions (difference grid by bincounts, corner min/max elementwise) covers exactly
    the cells a plain per-face painting covers, and each region's box is its faces' boxes."""
    import math

    import cv2

    from scanpipe.texturing.atlas import frame_regions

    rng = np.random.default_rng(2)
    width, height, cell, pad = 640, 480, 32, 3
    centre = rng.uniform([0, 0], [width, height], (300, 1, 2))
    corner_uv = centre + rng.normal(0, 12, (300, 3, 2))
    region, boxes = frame_regions(corner_uv, width, height, cell, pad)
    covered = np.zeros((math.ceil(height / cell), math.ceil(width / cell)), np.uint8)
    lo_all, hi_all = [], []
    for tri in corner_uv:
        lo = np.clip(np.floor(tri.min(axis=0)).astype(int) - pad, 0, [width - 1, height - 1])
        hi = np.clip(np.ceil(tri.max(axis=0)).astype(int) + pad + 1, lo + 1, [width, height])
        covered[lo[1] // cell:(hi[1] - 1) // cell + 1, lo[0] // cell:(hi[0] - 1) // cell + 1] = 1
        lo_all.append(lo)
        hi_all.append(hi)
    count, labels = cv2.connectedComponents(covered, connectivity=8)
    first_cell = labels[np.array(lo_all)[:, 1] // cell, np.array(lo_all)[:, 0] // cell]
    # faces in one 8-connected component of painted cells share a region or a tile of it
    for r in range(len(boxes)):
        mine = region == r
        assert len(set(first_cell[mine].tolist())) == 1
        np.testing.assert_array_equal(boxes[r, :2], np.array(lo_all)[mine].min(axis=0))
        np.testing.assert_array_equal(boxes[r, 2:], np.array(hi_all)[mine].max(axis=0))
    assert len(set(region.tolist())) >= count - 1


def test_textured_faces_name_the_camera_or_none() -> None:
    from scanpipe.stages.texture import textured_faces_table

    frame = np.array([2, -1, 0, 1, -1])
    table = textured_faces_table(np.zeros(5, np.int16), np.zeros((5, 3, 2), np.float32), frame,
                                 ["a", "b", "a"], np.array([10, 11, 12]))
    assert table.column("camera_id").to_pylist() == ["a", None, "a", "b", None]
    assert table.column("frame").to_pylist() == [12, -1, 10, 11, -1]
    empty = textured_faces_table(np.zeros(2, np.int16), np.zeros((2, 3, 2), np.float32),
                                 np.full(2, -1), [], np.zeros(0, np.int64))
    assert empty.column("camera_id").to_pylist() == [None, None]


def test_a_triangle_soup_is_textured_as_the_shared_mesh() -> None:
    """The stage on a mesh whose faces share no vertex (as some exporters write it): no seam
    step (no neighbours), every face still gets a frame where the shared mesh's best frame
    does; no error."""
    caster = Caster()
    rec = record(small_rig(), beta_step_deg=6.0, caster=caster)
    vertices, faces, normals = room_mesh(0.25)
    soup_v, soup_n = vertices[faces].reshape(-1, 3), normals[faces].reshape(-1, 3)
    soup_f = np.arange(3 * len(faces)).reshape(-1, 3)
    shared = STAGE.run(rec.inputs(*mesh_tables(vertices, faces, normals)))
    soup = STAGE.run(rec.inputs(*mesh_tables(soup_v, soup_f, soup_n)))
    assert soup.report["seam_edges"] == soup.report["seam_edges_best_frame"] == 0
    assert shared.report["seam_edges_best_frame"] > 0
    assert soup.report["faces_textured"] >= 0.95 * shared.report["faces_textured"] > 1000


def test_atlas_charts_found_beside_the_patches_are_the_atlas_own(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The stage finds the atlas's regions on a second thread while the patches are baked:
    the atlas built from them is the one it builds itself; with one thread
    (OMP_NUM_THREADS=1) the stage's result is the same; charts of another padding are
    refused."""
    import scanpipe.stages.texture as texture_module
    from scanpipe.texturing.atlas import build_atlas, frame_charts

    rec = record(small_rig(), beta_step_deg=30.0)
    inputs = rec.inputs(*mesh_tables(*room_mesh(0.25)))
    compared: list[int] = []

    def both(*args: Any, **kwargs: Any) -> Any:
        given = build_atlas(*args, **kwargs)
        own = build_atlas(*args, **{**kwargs, "charts": None})
        for a, b in zip(given.pages, own.pages, strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(given.face_uv, own.face_uv)
        np.testing.assert_array_equal(given.face_page, own.face_page)
        compared.append(given.regions)
        with pytest.raises(ValueError, match="pad_px"):
            build_atlas(*args, **{**kwargs, "charts": frame_charts(
                args[0], args[1], args[2], args[3], pad_px=kwargs["pad_px"] + 1)})
        return given

    monkeypatch.setattr(texture_module, "build_atlas", both)
    threaded = STAGE.run(inputs)
    assert compared and compared[0] > 0
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    single = STAGE.run(inputs)
    for name in ("textured_faces", "texture_pages"):
        assert threaded.tables[name].equals(single.tables[name])


def test_scattered_faces_share_points_by_a_sort() -> None:
    """A few faces far apart (ICM's movers) find their shared corners by a sort, not a
    mesh-sized scratch array: the same answers and rays as among all faces."""
    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, 201), np.linspace(-0.6, 0.6, 201))
    wall = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)], 1)
    pole = wall_and_pole()[0][31 * 31:]
    _, pole_faces = wall_and_pole()
    vertices = np.concatenate([wall, pole])
    faces = np.concatenate([grid_faces(201, 201),
                            pole_faces[2 * 30 * 30:] - 31 * 31 + len(wall)])
    on_wall = np.arange(2 * 200 * 200)
    origin = np.array(ORIGINS[1])
    whole = MeshOcclusion(vertices, faces).faces_visible(
        np.tile(origin, (len(on_wall), 1)), on_wall)
    assert (~whole).sum() > 0
    hidden, shown = np.flatnonzero(~whole), np.flatnonzero(whole)
    some = np.sort(np.concatenate([hidden[::max(1, len(hidden) // 20)], shown[::997]]))
    # a quad's two triangles (a shared edge and two corners) among them
    some = np.unique(np.concatenate([some, [1000, 1000 + 200 * 200]]))
    occlusion = MeshOcclusion(vertices, faces)
    got = occlusion.faces_visible(np.tile(origin, (len(some), 1)), some)
    np.testing.assert_array_equal(got, whole[some])
    assert occlusion.rays_cast < 7 * len(some)  # the quad's corners and edge cast once
