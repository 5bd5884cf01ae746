"""The texture stage's memory-bounded paths decide as the whole-array ones do: work in blocks
of faces (rays, atlas regions and UVs, multi-view texels) gives the same artifacts for any block
size, the multi-view texels levelled late from uint8 samples equal those levelled at once, and
the ray scene shares the stage's int32 corners instead of copying them."""

from __future__ import annotations

import numpy as np
import pytest
from texture_scene import Caster, mesh_tables, record, room_mesh, small_rig

from scanpipe.stages.texture import STAGE
from scanpipe.texturing import atlas, patches, visibility
from scanpipe.texturing.atlas import frame_regions, vertex_regions
from scanpipe.texturing.patches import MIN_FILLED, _combine
from scanpipe.texturing.photometric import nan_median
from scanpipe.texturing.visibility import MeshOcclusion, mesh_edges


def test_blocks_do_not_change_the_texture(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tiny blocks everywhere (rays, regions, projection, UVs, texel combination) give the
    same textured faces and pages as the defaults, multi-view faces included."""
    rec = record(small_rig(), beta_step_deg=6.0, caster=Caster())
    vertices, faces, normals = room_mesh(0.25)
    vt, ft = mesh_tables(vertices, faces, normals)
    default = STAGE.run(rec.inputs(vt, ft))
    for module, name, size in ((visibility, "FACES_PER_CAST", 64),
                               (atlas, "REGION_BLOCK_FACES", 53),
                               (atlas, "PROJECT_BLOCK_VERTICES", 41),
                               (atlas, "UV_BLOCK_FACES", 37),
                               (patches, "COMBINE_BLOCK_FACES", 3),
                               (patches, "PARTIAL_BLOCK_FACES", 2)):
        monkeypatch.setattr(module, name, size)
    blocked = STAGE.run(rec.inputs(vt, ft))
    assert default.report["faces_textured"] > 1000
    assert default.report["faces_multiview"] > 3  # several blocks of multi-view faces
    for name in ("textured_faces", "texture_pages"):
        assert default.tables[name].equals(blocked.tables[name]), name
    assert blocked.report["rays_cast"] > default.report["rays_cast"]  # fewer rays shared


def reference_combine(samples: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The texels as levelled at once: ``samples`` ``(faces, P², slots, 3)`` float64 (NaN =
    not seen), best slot first, the median where three or more frames see a texel."""
    seen = np.isfinite(samples[:, :, :, 0])
    filled = seen.any(axis=2)
    first = np.argmax(seen, axis=2)
    colour = np.take_along_axis(samples, first[:, :, None, None], axis=2)[:, :, 0]
    many = seen.sum(axis=2) >= 3
    colour[many] = nan_median(samples[many].transpose(0, 2, 1).copy(), axis=2)[:, :, 0]
    share = (filled & inside).sum(axis=1) / max(1, int(inside.sum()))
    colour = np.where(filled[:, :, None], colour, 0.0)
    mean = colour.sum(axis=1) / np.maximum(filled.sum(axis=1), 1)[:, None]
    colour = np.where(filled[:, :, None], colour, mean[:, None, :])
    return np.clip(colour + 0.5, 0, 255).astype(np.uint8), share >= MIN_FILLED


def test_texels_levelled_late_equal_texels_levelled_at_once() -> None:
    """uint8 samples and a seen mask, levelled by each slot's frame gains when combined: the
    same texels and kept faces as float64 samples levelled when taken."""
    rng = np.random.default_rng(5)
    faces, texels, slots = 40, 16, 5
    values = rng.integers(0, 256, (faces, texels, slots, 3), dtype=np.uint8)
    seen = rng.random((faces, texels, slots)) < rng.uniform(0.2, 1.0, (faces, 1, 1))
    gains = rng.uniform(0.5, 2.0, (faces, slots, 3))
    inside = np.arange(texels) % 4 != 3
    samples = np.where(seen[..., None], values * gains[:, None], np.nan)
    want_colour, want_keep = reference_combine(samples, inside)
    colour, keep = _combine(values, seen, gains, inside)
    np.testing.assert_array_equal(colour, want_colour)
    np.testing.assert_array_equal(keep, want_keep)
    assert 0 < keep.sum() < faces  # both outcomes tested
    assert ((seen.sum(axis=2) >= 3) & (seen.sum(axis=2) < slots)).any()  # medians with gaps


def test_regions_from_shared_vertices_in_any_block_size(monkeypatch: pytest.MonkeyPatch) -> None:
    """vertex_regions (corners as rows of shared vertices) gives frame_regions' regions and
    boxes of the gathered corner pixels, in one block or in blocks of 7 faces."""
    rng = np.random.default_rng(4)
    width, height = 1920, 1080
    # 60 clusters of 10 vertices, faces within a cluster (vertices shared), and a sparse band
    centre = rng.uniform([0, 0], [width, height], (60, 1, 2))
    clustered = (centre + rng.normal(0, 15, (60, 10, 2))).reshape(-1, 2)
    band = np.stack([np.linspace(0, width, 200), np.linspace(0, height, 200)], 1)
    vertex_uv = np.concatenate([clustered, band])
    corner = np.concatenate([
        (10 * rng.integers(0, 60, 500))[:, None] + rng.integers(0, 10, (500, 3)),
        600 + np.arange(198)[:, None] + np.array([0, 1, 2])])
    want_region, want_boxes = frame_regions(vertex_uv[corner], width, height)
    monkeypatch.setattr(atlas, "REGION_BLOCK_FACES", 7)
    for region, boxes in (vertex_regions(vertex_uv, corner, width, height),
                          frame_regions(vertex_uv[corner], width, height)):
        np.testing.assert_array_equal(region, want_region)
        np.testing.assert_array_equal(boxes, want_boxes)
    assert len(want_boxes) > 3


def test_the_ray_scene_shares_int32_corners() -> None:
    """int32 faces are the scene's own (no copy); int64 faces are converted; both decide the
    same, and edges handed in are used."""
    xs, ys = np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], 1)
    idx = np.arange(21 * 21).reshape(21, 21)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    int32_faces = np.ascontiguousarray(faces, dtype=np.int32)  # as the stage holds them
    edges = mesh_edges(int32_faces, len(vertices))
    shared = MeshOcclusion(vertices, int32_faces, edges)
    copied = MeshOcclusion(vertices, faces)
    assert np.shares_memory(shared.faces, int32_faces)
    assert shared.edges is edges
    assert not np.shares_memory(copied.faces, faces)
    face_ids = np.arange(len(faces))
    origin = np.tile([0.5, 0.5, 0.0], (len(faces), 1))
    np.testing.assert_array_equal(shared.faces_visible(origin, face_ids),
                                  copied.faces_visible(origin, face_ids))
    # Fortran-ordered int32 (astype keeps the order) is copied into rows
    assert not np.shares_memory(MeshOcclusion(vertices, faces.astype(np.int32)).faces, faces)


def test_edge_corners_of_some_edges_are_those_of_all() -> None:
    """MeshEdges.vertices for chosen pair rows = the rows of all; pair slots are int32."""
    idx = np.arange(6 * 7).reshape(6, 7)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    edges = mesh_edges(faces)
    assert edges.pair_slots.dtype == np.int32 and edges.pairs().dtype == np.int64
    rows = np.array([0, 5, 17, len(edges.pair_slots) - 1])
    np.testing.assert_array_equal(edges.vertices(faces, rows), edges.vertices(faces)[rows])


def test_regions_are_found_after_the_ray_scene_is_freed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The atlas's regions (and their temporaries) do not sit beside the ray scene: when
    ``frame_charts`` runs, no ``MeshOcclusion`` of the stage is alive any more; the stage's
    result is the same."""
    import gc
    import weakref

    from scanpipe.stages import texture as texture_module

    rec = record(small_rig(), beta_step_deg=6.0, caster=Caster())
    vertices, faces, normals = room_mesh(0.25)
    vt, ft = mesh_tables(vertices, faces, normals)
    default = STAGE.run(rec.inputs(vt, ft))
    scenes: list[weakref.ref[MeshOcclusion]] = []
    alive_at_charts: list[int] = []

    class Tracked(MeshOcclusion):
        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)  # type: ignore[arg-type]
            scenes.append(weakref.ref(self))

    def charts(*args: object, **kwargs: object) -> atlas.Charts:
        gc.collect()
        alive_at_charts.append(sum(ref() is not None for ref in scenes))
        return atlas.frame_charts(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(texture_module, "MeshOcclusion", Tracked)
    monkeypatch.setattr(texture_module, "frame_charts", charts)
    tracked = STAGE.run(rec.inputs(vt, ft))
    assert scenes and alive_at_charts == [0]
    for name in ("textured_faces", "texture_pages"):
        assert default.tables[name].equals(tracked.tables[name]), name
