"""The baseline a user would write by hand with Open3D only, from assembled points to a
coloured mesh: voxel downsample, statistical outlier removal, KNN normals oriented toward the
scanner, Poisson (trimmed by density as in Open3D's tutorial), per-vertex colour.

Colour: each vertex takes the pixel of the frame that sees it closest to the image centre, among
``frames_per_camera`` frames spread evenly over each camera's video, facing it, without an
occlusion test (what a hand-written script does). Projecting needs the camera model and the
platform angle of each frame, which the user would have to write too; we use scanpipe's
(:func:`scanpipe.camera.project_points`, :func:`scanpipe.motion.beta_deg_at`) so the baseline
does not pay for a slower re-implementation of them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.camera import camera_pose_in_rig, project_points
from scanpipe.motion import beta_deg_at
from scanpipe.rig import Rig
from scanpipe.texturing.frames import camera_for_size

#: Grey for vertices no chosen frame sees.
UNSEEN_RGB = 128


@dataclass(frozen=True)
class BaselineMesh:
    """The baseline's result and how long each of its steps took."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int32]
    colors: NDArray[np.uint8]
    steps_s: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)


def finite_xyz(points: pa.Table) -> NDArray[np.float64]:
    """The (N, 3) float64 coordinates of a points table, non-finite rows dropped."""
    xyz = np.stack([points.column(c).to_numpy(zero_copy_only=False) for c in "xyz"], axis=1)
    return np.asarray(xyz[np.isfinite(xyz).all(axis=1)], dtype=np.float64)


def vertex_colours(vertices: NDArray[np.float64], normals: NDArray[np.float64],
                   frames: pa.Table, motor: pa.Table, rig: Rig,
                   frames_per_camera: int = 36) -> NDArray[np.uint8]:
    """RGB per vertex from the frame that sees it nearest its image centre (grey if none)."""
    colours = np.full((len(vertices), 3), UNSEEN_RGB, dtype=np.uint8)
    best = np.full(len(vertices), np.inf)
    if frames.num_rows == 0:
        return colours
    ids = np.asarray(frames.column("camera_id").to_pylist())
    times_ns = frames.column("log_time_ns").to_numpy().astype(np.int64)
    beta_deg = beta_deg_at(times_ns, motor, rig.motor)
    data = frames.column("data")
    for cam in rig.cameras:
        rows = np.flatnonzero(ids == cam.id)
        if rows.size == 0:
            continue
        chosen = rows[np.unique(np.linspace(0, rows.size - 1, frames_per_camera).round()
                                .astype(np.int64))]
        for row in chosen:
            image = cv2.imdecode(np.frombuffer(data[int(row)].as_py(), np.uint8),
                                 cv2.IMREAD_COLOR)
            if image is None:
                continue
            height, width = image.shape[:2]
            sized = camera_for_size(cam, width, height)
            uv, depth = project_points(vertices, sized, float(beta_deg[row]))
            inside = ((depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1)
                      & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1))
            centre = np.array([(width - 1) / 2, (height - 1) / 2])
            off_centre = np.sum(((uv - centre) / centre) ** 2, axis=1)
            origin = camera_pose_in_rig(sized, float(beta_deg[row]))[1]
            facing = np.einsum("ij,ij->i", normals, origin - vertices) > 0
            better = inside & facing & (off_centre < best)
            pixels = np.rint(uv[better]).astype(np.int64)
            colours[better] = image[pixels[:, 1], pixels[:, 0], ::-1]
            best[better] = off_centre[better]
    return colours


def open3d_baseline(xyz: NDArray[np.float64], scanner_centre_m: tuple[float, float, float],
                    frames: pa.Table, motor: pa.Table, rig: Rig, voxel_m: float = 0.01,
                    knn: int = 30, depth: int = 9, density_quantile: float = 0.02,
                    frames_per_camera: int = 36) -> BaselineMesh:
    """Run the hand-written Open3D pipeline on ``xyz`` (N, 3)."""
    import open3d as o3d

    steps: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        steps[name] = now - clock
        clock = now

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    down = cloud.voxel_down_sample(voxel_m)
    lap("voxel_downsample")
    kept, _ = down.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    lap("statistical_outlier")
    kept.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=knn))
    kept.orient_normals_towards_camera_location(np.asarray(scanner_centre_m, dtype=np.float64))
    lap("knn_normals")
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        kept, depth=depth, n_threads=1)
    density = np.asarray(densities)
    mesh.remove_vertices_by_mask(density < np.quantile(density, density_quantile))
    mesh.compute_vertex_normals()
    lap("poisson")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    colours = vertex_colours(vertices, normals, frames, motor, rig, frames_per_camera)
    lap("vertex_colour")
    counts = {"points_in": len(xyz), "after_voxel": len(down.points),
              "after_outliers": len(kept.points), "vertices": len(vertices),
              "faces": len(mesh.triangles)}
    return BaselineMesh(vertices, np.asarray(mesh.triangles, dtype=np.int32), colours, steps,
                        counts)


def baseline_summary(result: BaselineMesh) -> dict[str, Any]:
    """Counts and step times as plain data."""
    return {"steps_s": {k: round(v, 3) for k, v in result.steps_s.items()},
            "counts": result.counts}
