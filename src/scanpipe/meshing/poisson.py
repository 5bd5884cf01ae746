"""Screened Poisson reconstruction (Open3D), trimmed to the surface the scanner could see.

Poisson closes every surface it builds: where the scan has no points (behind furniture, out of
range, through a window) it invents smooth "bubbles". Two trims remove them:

- density: vertices supported by few samples (below the ``density_quantile`` of Open3D's density
  estimate) go;
- visibility: every point of the scan says "from its sensor, along this direction, space is
  empty up to this range, then there is surface". A vertex is kept only if, seen from the
  scanner, its range matches a measured range in its direction (within a tolerance): a vertex in
  front of the measured surface lies in space the beam passed through, one behind it lies where
  no beam reached, and one in a direction without any return was never seen. Directions are
  binned on the sphere (polar angle from the motor axis, azimuth about it), and each bin keeps
  the minimum and maximum measured range of itself and its eight neighbours, so that vertices at
  depth edges and between samples are not cut.

Open3D's multi-threaded Poisson has crashed intermittently in public reports, hence
``n_threads = 1`` by default. Open3D ignores per-point confidences (the normal length), so the
"point weight" here is the screening weight, how strongly the surface is pulled to the points.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator

from scanpipe.errors import StageError
from scanpipe.meshing.mesh import Mesh
from scanpipe.params import Params

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
B = NDArray[np.bool_]


class PoissonParams(Params):
    """Open3D Poisson settings and the trims applied to its result."""

    depth: int = Field(9, ge=1, le=12, description="octree depth (grid of 2^depth per side)")
    scale: float = Field(1.1, ge=1.0, le=4.0,
                         description="reconstruction cube / bounding cube of the samples")
    linear_fit: bool = Field(False, description="place iso-vertices by linear interpolation")
    point_weight: float = Field(10.0, ge=0.0,
                                description="screening weight: how closely to follow the points")
    samples_per_node: float = Field(1.5, gt=0.0,
                                    description="minimum samples per octree node (noise)")
    n_threads: int = Field(1, ge=-1, description="threads for Poisson; −1 = all (see docs)")
    density_quantile: float = Field(0.02, ge=0.0, lt=1.0,
                                    description="drop vertices below this density quantile")
    remove_unseen: bool = Field(True, description="drop surface the scanner could not have seen")
    visibility_tolerance_m: float = Field(0.05, ge=0.0,
                                          description="range tolerance of the visibility test")
    visibility_tolerance_rel: float = Field(0.01, ge=0.0,
                                            description="plus this fraction of the range")
    visibility_neighbour_bins: int = Field(
        0, ge=0, le=5, description="bins on each side whose ranges also count as seen")
    visibility_bin_deg: float | None = Field(
        None, gt=0.0, le=30.0,
        description="direction bin size; default: twice the coarser grid step, or 1°")

    @field_validator("n_threads")
    @classmethod
    def _threads(cls, value: int) -> int:
        if value == 0:
            raise ValueError("must be ≥ 1, or −1 for all cores")
        return value


def direction_bins(vectors: F64, bin_deg: float) -> tuple[NDArray[np.int64], tuple[int, int]]:
    """Bin index of each direction on the sphere about the y (motor) axis, and the bin grid."""
    n_polar = max(1, int(np.ceil(180.0 / bin_deg)))
    n_azimuth = max(1, int(np.ceil(360.0 / bin_deg)))
    length = np.linalg.norm(vectors, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        polar = np.degrees(np.arccos(np.clip(vectors[:, 1] / length, -1.0, 1.0)))
    azimuth = np.mod(np.degrees(np.arctan2(vectors[:, 2], vectors[:, 0])), 360.0)
    i_polar = np.clip((np.nan_to_num(polar) / 180.0 * n_polar).astype(np.int64), 0, n_polar - 1)
    i_azimuth = np.clip((azimuth / 360.0 * n_azimuth).astype(np.int64), 0, n_azimuth - 1)
    return i_polar * n_azimuth + i_azimuth, (n_polar, n_azimuth)


def seen_vertices(vertices: F32, points: F32, origins: F32, bin_deg: float,
                  tolerance_m: float, tolerance_rel: float, neighbour_bins: int = 1) -> B:
    """True for vertices whose range from the scanner matches a measured range there."""
    from scipy.ndimage import maximum_filter, minimum_filter

    centre = origins.astype(np.float64).mean(axis=0)
    rays = points.astype(np.float64) - centre
    ranges = np.linalg.norm(rays, axis=1)
    bins, shape = direction_bins(rays, bin_deg)
    nearest = np.full(shape[0] * shape[1], np.inf)
    farthest = np.full(shape[0] * shape[1], -np.inf)
    np.minimum.at(nearest, bins, ranges)
    np.maximum.at(farthest, bins, ranges)
    modes = ("nearest", "wrap")  # the azimuth wraps around; the polar angle does not
    size = 2 * neighbour_bins + 1
    nearest = minimum_filter(nearest.reshape(shape), size=size, mode=modes).ravel()
    farthest = maximum_filter(farthest.reshape(shape), size=size, mode=modes).ravel()

    v_rays = vertices.astype(np.float64) - centre
    v_ranges = np.linalg.norm(v_rays, axis=1)
    v_bins, _ = direction_bins(v_rays, bin_deg)
    tolerance = tolerance_m + tolerance_rel * v_ranges
    return np.asarray((v_ranges >= nearest[v_bins] - tolerance)
                      & (v_ranges <= farthest[v_bins] + tolerance))


def poisson_mesh(points: F32, normals: F32, origins: F32, colors: U8 | None,
                 params: PoissonParams, grid_steps_deg: tuple[float, float] | None = None,
                 ) -> tuple[Mesh, dict[str, Any]]:
    """Poisson surface of oriented points, trimmed by density and visibility.

    ``grid_steps_deg`` (beam step, platform step) sets the default visibility bin size.
    """
    import open3d as o3d

    if len(points) < 10:
        raise StageError(f"points: {len(points)} points are too few for Poisson reconstruction")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud.normals = o3d.utility.Vector3dVector(normals.astype(np.float64))
    if colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(colors.astype(np.float64) / 255.0)
    try:
        result, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=params.depth, scale=params.scale, linear_fit=params.linear_fit,
            n_threads=params.n_threads, samples_per_node=params.samples_per_node,
            point_weight=params.point_weight)
    except RuntimeError as err:
        raise StageError(f"mesh: Open3D Poisson reconstruction failed ({err})") from err
    mesh = Mesh.from_open3d(result)
    if colors is None:
        mesh = replace(mesh, colors=None)  # Open3D fills in black
    density = np.asarray(densities, dtype=np.float64)
    report: dict[str, Any] = {"poisson_vertices": len(mesh.vertices),
                              "poisson_faces": len(mesh.faces)}
    if len(mesh.vertices) == 0:
        raise StageError("mesh: Poisson reconstruction returned an empty surface")

    keep = np.ones(len(mesh.vertices), dtype=bool)
    if params.density_quantile > 0:
        keep &= density >= np.quantile(density, params.density_quantile)
    report["low_density_vertices_removed"] = int(np.count_nonzero(~keep))
    if params.remove_unseen:
        if params.visibility_bin_deg is not None:
            bin_deg = params.visibility_bin_deg
        elif grid_steps_deg is not None and all(np.isfinite(grid_steps_deg)):
            bin_deg = 2.0 * max(abs(grid_steps_deg[0]), abs(grid_steps_deg[1]))
        else:
            bin_deg = 1.0
        seen = seen_vertices(mesh.vertices, points, origins, bin_deg,
                             params.visibility_tolerance_m, params.visibility_tolerance_rel,
                             params.visibility_neighbour_bins)
        report["unseen_vertices_removed"] = int(np.count_nonzero(keep & ~seen))
        report["visibility_bin_deg"] = bin_deg
        keep &= seen
    mesh = mesh.select_vertices(keep)
    return mesh, report
