"""Artifact tables built by hand, per docs/artifacts.md, for the export/render/eval tests."""

from __future__ import annotations

import io

import numpy as np
import pyarrow as pa
from PIL import Image

RED, GREEN, BLUE, WHITE = (255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 255)


def quadrant_png(size: int = 64) -> bytes:
    """A texture whose top-left quarter is red, top-right green, bottom-left blue, bottom-right
    white (rows from the top)."""
    image = np.zeros((size, size, 3), dtype=np.uint8)
    half = size // 2
    image[:half, :half] = RED
    image[:half, half:] = GREEN
    image[half:, :half] = BLUE
    image[half:, half:] = WHITE
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def vertices_table(xyz: np.ndarray, normals: np.ndarray | None = None,
                   colors: np.ndarray | None = None) -> pa.Table:
    xyz = np.asarray(xyz, dtype=np.float32)
    n = np.zeros_like(xyz) if normals is None else np.asarray(normals, dtype=np.float32)
    columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
               "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]}
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8)
        columns.update(red=c[:, 0], green=c[:, 1], blue=c[:, 2])
    return pa.table(columns)


def faces_table(faces: np.ndarray) -> pa.Table:
    f = np.asarray(faces, dtype=np.int32)
    return pa.table({"v0": f[:, 0], "v1": f[:, 1], "v2": f[:, 2]})


def textured_faces_table(face: np.ndarray, page: np.ndarray, uvs: np.ndarray) -> pa.Table:
    """``uvs`` (n, 3, 2) in glTF convention (v = 0 at the top)."""
    uv = np.asarray(uvs, dtype=np.float32).reshape(-1, 6)
    n = len(face)
    textured = np.asarray(page) >= 0
    return pa.table({
        "face": pa.array(np.asarray(face, dtype=np.int32)),
        "page": pa.array(np.asarray(page, dtype=np.int16)),
        **{name: pa.array(uv[:, j]) for j, name in enumerate(("u0", "v0", "u1", "v1", "u2",
                                                               "v2"))},
        "camera_id": pa.array(["cam0" if t else None for t in textured], pa.string()),
        "frame": pa.array(np.where(textured, np.arange(n), -1).astype(np.int64)),
    })


def pages_table(pngs: dict[int, bytes]) -> pa.Table:
    sizes = [Image.open(io.BytesIO(b)).size for b in pngs.values()]
    return pa.table({
        "page": pa.array(list(pngs), pa.int16()),
        "width": pa.array([s[0] for s in sizes], pa.int32()),
        "height": pa.array([s[1] for s in sizes], pa.int32()),
        "png": pa.array(list(pngs.values()), pa.binary()),
    })


def textured_quad() -> dict[str, pa.Table]:
    """A unit quad in the x-y plane facing +z; its texture's top-left (red) lies at (0, 1, 0)."""
    xyz = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv_of_vertex = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=np.float32)  # glTF
    return {
        "mesh_vertices": vertices_table(xyz, normals),
        "mesh_faces": faces_table(faces),
        "textured_faces": textured_faces_table(np.arange(2), np.zeros(2), uv_of_vertex[faces]),
        "texture_pages": pages_table({0: quadrant_png()}),
    }


def box_mesh(size_m: tuple[float, float, float] = (4.0, 3.0, 5.0),
             center: tuple[float, float, float] = (0.0, 0.3, 0.0),
             inward: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A box (12 triangles) with faces wound to face inwards (a room) or outwards."""
    half = np.asarray(size_m) / 2
    c = np.asarray(center)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)],
                       dtype=np.float64) * half + c
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    for a, b, cc, d in quads:
        faces += [(a, b, cc), (a, cc, d)]
    tri = np.array(faces, dtype=np.int32)
    centroid_dir = corners[tri].mean(axis=1) - c
    edge1, edge2 = corners[tri[:, 1]] - corners[tri[:, 0]], corners[tri[:, 2]] - corners[tri[:, 0]]
    normal = np.cross(edge1, edge2)
    outward = np.einsum("ij,ij->i", normal, centroid_dir) > 0
    flip = outward if inward else ~outward
    tri[flip] = tri[flip][:, ::-1]
    return corners.astype(np.float32), tri


def textured_box(pages: int = 2, untextured_faces: int = 2) -> dict[str, pa.Table]:
    """A box room whose faces are spread over ``pages`` atlas pages, a few left untextured."""
    xyz, faces = box_mesh()
    n = len(faces)
    page = (np.arange(n) % pages).astype(np.int16)
    page[:untextured_faces] = -1
    uvs = np.tile(np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]], dtype=np.float32), (n, 1, 1))
    colors = np.full((len(xyz), 3), 200, dtype=np.uint8)
    return {
        "mesh_vertices": vertices_table(xyz, None, colors),
        "mesh_faces": faces_table(faces),
        "textured_faces": textured_faces_table(np.arange(n), page, uvs),
        "texture_pages": pages_table({p: quadrant_png(32 + 16 * p) for p in range(pages)}),
    }


def points_table(profiles: int = 6, samples: int = 10, colors: bool = True,
                 echo: bool = True, seed: int = 0) -> pa.Table:
    """A small gridded cloud on a sphere of radius 2–3 m, per the points contract."""
    rng = np.random.default_rng(seed)
    alpha = np.linspace(10.0, 350.0, samples)
    beta = np.linspace(0.0, 180.0, profiles, endpoint=False)
    a, b = np.meshgrid(np.radians(alpha), np.radians(beta))
    r = 2.0 + rng.random(a.shape)
    x, y, z = r * np.sin(a) * np.cos(b), r * np.cos(a), r * np.sin(a) * np.sin(b)
    n = a.size
    profile = np.repeat(np.arange(profiles, dtype=np.int32), samples)
    columns: dict[str, object] = {
        "x": x.ravel().astype(np.float32), "y": y.ravel().astype(np.float32),
        "z": z.ravel().astype(np.float32), "range_m": r.ravel().astype(np.float32),
        "alpha_deg": np.degrees(a).ravel(), "beta_deg": np.degrees(b).ravel(),
        "time_ns": (1_700_000_000_000_000_000 + profile.astype(np.int64) * 200_000_000
                    + np.tile(np.arange(samples), profiles) * 1000),
        "profile": profile, "sample": np.tile(np.arange(samples, dtype=np.int32), profiles),
        "origin_x": np.zeros(n, np.float32), "origin_y": np.zeros(n, np.float32),
        "origin_z": np.zeros(n, np.float32),
    }
    if echo:
        columns["echo"] = pa.array(rng.integers(0, 4000, n).astype(np.uint16), pa.uint16())
    if colors:
        rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
        columns.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    return pa.table(columns)
