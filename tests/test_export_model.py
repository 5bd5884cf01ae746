"""The mesh model's texture coordinates: stacked in place when every face is listed in order,
scattered otherwise; both give the same model."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import pyarrow as pa
from PIL import Image

from scanpipe.exporters.model import UV_COLUMNS, mesh_from_tables
from scanpipe.schema import MESH_FACES, MESH_VERTICES, TEXTURE_PAGES


def _png() -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (2, 2), (10, 20, 30)).save(buffer, format="PNG")
    return buffer.getvalue()


def test_face_uvs_in_order_and_scattered_agree() -> None:
    rng = np.random.default_rng(3)
    vertices = pa.table({n: rng.random(6, dtype=np.float32) for n in MESH_VERTICES.names()
                         if n in ("x", "y", "z", "nx", "ny", "nz")})
    faces = pa.table({n: pa.array(rng.integers(0, 6, 5), pa.int32()) for n in
                      MESH_FACES.names()})
    uv = rng.random((5, 6), dtype=np.float32)
    pages = pa.table({"page": pa.array([0], pa.int16()), "width": pa.array([2], pa.int32()),
                      "height": pa.array([2], pa.int32()), "png": [_png()]},
                     schema=TEXTURE_PAGES.arrow_schema)

    def textured(order: np.ndarray) -> pa.Table:
        return pa.table({"face": pa.array(order, pa.int32()),
                         "page": pa.array(np.zeros(len(order)), pa.int16()),
                         **{n: pa.array(uv[order, k]) for k, n in enumerate(UV_COLUMNS)}})

    in_order = mesh_from_tables(vertices, faces, textured(np.arange(5)), pages)
    shuffled = mesh_from_tables(vertices, faces, textured(np.array([3, 0, 4, 1, 2])), pages)
    assert in_order.face_uvs is not None and shuffled.face_uvs is not None
    np.testing.assert_array_equal(in_order.face_uvs, uv.reshape(-1, 3, 2))
    np.testing.assert_array_equal(shuffled.face_uvs, in_order.face_uvs)
    partial = mesh_from_tables(vertices, faces, textured(np.array([4, 1])), pages)
    assert partial.face_pages is not None and partial.face_uvs is not None
    assert partial.face_pages.tolist() == [-1, 0, -1, -1, 0]
    np.testing.assert_array_equal(partial.face_uvs[[1, 4]], uv[[1, 4]].reshape(-1, 3, 2))
    assert not partial.face_uvs[[0, 2, 3]].any()


def _split_reference(corner_vertex: np.ndarray, corner_uv: np.ndarray
                     ) -> tuple[list[int], list[tuple[float, float]], list[int]]:
    """split_by_uv by the obvious per-corner loop: a corner shares its vertex's first corner's
    new vertex when their UVs are equal, else it makes one."""
    first: dict[int, int] = {}
    made: dict[int, int] = {}
    source, uvs, index = [], [], []
    for k, (v, uv) in enumerate(zip(corner_vertex.tolist(), map(tuple, corner_uv.tolist()),
                                    strict=True)):
        f = first.setdefault(v, k)
        if f != k and tuple(corner_uv[f].tolist()) == uv:
            index.append(made[f])
            continue
        made[k] = len(source)
        source.append(v)
        uvs.append(uv)
        index.append(made[k])
    return source, uvs, index


def test_split_by_uv_matches_the_obvious_loop_across_slices(monkeypatch: Any) -> None:
    from scanpipe.exporters import model

    monkeypatch.setattr(model, "SPLIT_SLICE", 7)  # many slices, seams across their borders
    rng = np.random.default_rng(5)
    for n in (1, 6, 7, 8, 50, 333):
        corner_vertex = rng.integers(0, max(1, n // 3), n)
        corner_uv = rng.integers(0, 3, (n, 2)).astype(np.float32)
        source, uv, index = model.split_by_uv(corner_vertex, corner_uv)
        want_source, want_uv, want_index = _split_reference(corner_vertex, corner_uv)
        assert source.tolist() == want_source and index.tolist() == want_index
        assert [tuple(r) for r in uv.tolist()] == want_uv
