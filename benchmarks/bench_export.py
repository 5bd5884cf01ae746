"""Benchmark: OBJ and GLB export of a large textured grid mesh; LAZ and E57 of a lab-scale cloud.

Target (issue 9): the OBJ writer keeps up with big meshes, ≥ 1 M faces/s, measured on ≥ 2 M faces.
``python benchmarks/bench_export.py [--quick]`` prints the figures and saves JSON into
``benchmarks/results/``.
"""

from __future__ import annotations

import io
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, cpu_seconds, made, measure, table

from scanpipe.artifacts import file_size
from scanpipe.exporters.glb import glb_pieces
from scanpipe.exporters.las import las_bytes
from scanpipe.exporters.model import CloudModel, MeshModel
from scanpipe.exporters.obj import obj_files
from scanpipe.exporters.ply import ply_mesh_pieces


def grid_mesh(rows: int, cols: int, pages: int = 4) -> MeshModel:
    """A textured height field of ``2 (rows−1)(cols−1)`` faces spread over ``pages`` pages."""
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
    z = (0.05 * np.sin(x / 7.0) * np.cos(y / 5.0)).astype(np.float32)
    vertices = np.stack([x * 0.01, z, y * 0.01], axis=-1).reshape(-1, 3)
    normals = np.tile(np.array([0.0, 1.0, 0.0], np.float32), (len(vertices), 1))
    index = np.arange(rows * cols, dtype=np.int32).reshape(rows, cols)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    u = (vertices[:, 0] / vertices[:, 0].max()).astype(np.float32)
    v = (vertices[:, 2] / vertices[:, 2].max()).astype(np.float32)
    uv = np.stack([u, v], 1)[faces]
    face_pages = (np.arange(len(faces)) % pages).astype(np.int16)
    buffer = io.BytesIO()
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (512, 512, 3), np.uint8)).save(
        buffer, format="PNG")
    return MeshModel(vertices, faces, normals, None, face_pages, uv,
                     {p: buffer.getvalue() for p in range(pages)})


def run(quick: bool = False) -> dict[str, Any]:
    """Measure the exporters; return the figures."""
    side = 500 if quick else 1001  # 1001² vertices → 2 M faces
    mesh = grid_mesh(side, side)
    faces = len(mesh.faces)
    rng = np.random.default_rng(1)
    points = 400 * 720 if quick else 1667 * 1440
    cloud = CloudModel(xyz=rng.normal(0, 3, (points, 3)).astype(np.float32),
                       intensity=rng.integers(0, 4000, points).astype(np.uint16),
                       colors=rng.integers(0, 255, (points, 3)).astype(np.uint8),
                       time_ns=np.arange(points, dtype=np.int64) * 1000)
    repeats = 3
    results = [
        measure("obj (+mtl, png)", lambda: made(obj_files(mesh, "bench")), faces, "faces",
                repeats),
        measure("glb", lambda: made(glb_pieces(mesh)), faces, "faces", repeats),
        measure("ply (texture → vertex colours)", lambda: made(ply_mesh_pieces(mesh)), faces,
                "faces",
                repeats),
        measure("las", lambda: las_bytes(cloud), points, "points", repeats),
        measure("laz", lambda: las_bytes(cloud, compressed=True), points, "points", repeats),
    ]
    obj_size = sum(file_size(b) for b in obj_files(mesh, "bench").values())
    # CPU time too: on a shared machine wall time measures the neighbours as much as the code
    # (the writers are single-threaded numpy, so on an idle machine CPU ≈ wall).
    obj_cpu_s = cpu_seconds(lambda: made(obj_files(mesh, "bench")), warm_up=False)
    glb_cpu_s = cpu_seconds(lambda: made(glb_pieces(mesh)), warm_up=False)
    figures = {
        "faces": faces,
        "vertices": len(mesh.vertices),
        "points": points,
        "measurements": results,
        "obj_faces_per_s": results[0].throughput,
        "obj_target_faces_per_s": 1e6,
        "obj_bytes": obj_size,
        "glb_s": results[1].median_s,
        "glb_faces_per_s": results[1].throughput,
        "obj_cpu_s": obj_cpu_s,
        "obj_faces_per_cpu_s": faces / obj_cpu_s,
        "glb_cpu_s": glb_cpu_s,
        "load_average_1min": os.getloadavg()[0],
    }
    print(f"CPU time: obj {obj_cpu_s:.2f} s ({faces / obj_cpu_s / 1e6:.2f} M faces/s), "
          f"glb {glb_cpu_s:.2f} s; load average {os.getloadavg()[0]:.1f}")
    print(table([(m.name, f"{m.median_s:.3f} s", f"{m.throughput / 1e6:.2f} M {m.unit}/s",
                  f"{m.peak_rss_mb:.0f} MB") for m in results],
                ("work", "median", "throughput", "peak RSS")))
    return figures


if __name__ == "__main__":
    cli("export", run, __doc__ or "", "a smaller mesh and cloud")
