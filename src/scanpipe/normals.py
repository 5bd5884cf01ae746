"""Surface normals of a scan, always facing the sensor that measured each point.

On a grid the normal at a cell is the cross product of its neighbour differences along the
profile and along the sample direction: array slicing, no neighbour search. The differences
span a fixed angular baseline (``baseline_deg``) rather than one cell, so that range noise
does not swamp them, and on each side the shorter of the forward and backward difference is
taken, so that a normal at a depth edge comes from the surface it belongs to. Cells where the
grid cannot give a normal (missing neighbours, the poles on the axis) take the mean normal of
the grid window around them; only cells with no valid normal in that window use a KNN plane
fit. Clouds without a grid use Open3D's KNN estimate.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import StageError
from scanpipe.grid import ScanGrid, from_grid, neighbour_differences, scan_grid, to_grid
from scanpipe.params import Params
from scanpipe.schema import ORIGIN, XYZ

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


class NormalParams(Params):
    """How normals are estimated."""

    method: Literal["auto", "grid", "knn"] = Field(
        "auto", description="grid where the points have one (its window mean or KNN for "
                            "cells it cannot serve), KNN otherwise; or force one method")
    baseline_deg: float = Field(1.0, gt=0, le=30,
                                description="angular span of the grid differences")
    knn_neighbours: int = Field(24, ge=3, le=500, description="neighbours for the KNN fallback")


def points_xyz(table: pa.Table) -> F32:
    """The ``x, y, z`` columns as one ``(N, 3)`` float32 array."""
    return np.stack([table.column(c).to_numpy().astype(np.float32) for c in XYZ], axis=1)


def points_origins(table: pa.Table) -> F32:
    """The sensor-origin columns (each point's sensor origin) as ``(N, 3)`` float32."""
    return np.stack([table.column(c).to_numpy().astype(np.float32) for c in ORIGIN],
                    axis=1)


def orient_toward(normals: F32, points: F32, origins: F32) -> F32:
    """Flip every normal that points away from its sensor origin (in place; returned)."""
    away = np.einsum("ij,ij->i", normals, origins - points) < 0
    normals[away] *= -1
    return normals


def _normalised(vectors: F32, min_norm: float = 0.0) -> F32:
    """Unit vectors; NaN rows where the norm is not above ``min_norm`` or not finite."""
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = vectors / norm
    out[~(norm[..., 0] > min_norm)] = np.nan
    return np.asarray(out, dtype=np.float32)


def _shorter(forward: F32, backward: F32) -> F32:
    """Per cell, the shorter of two difference vectors (NaN counts as infinitely long)."""
    f_len = np.nan_to_num(np.einsum("...k,...k->...", forward, forward), nan=np.inf)
    b_len = np.nan_to_num(np.einsum("...k,...k->...", backward, backward), nan=np.inf)
    return np.where((f_len <= b_len)[..., None], forward, backward)


def grid_normals(xyz_grid: F32, grid: ScanGrid, baseline_deg: float = 1.0) -> F32:
    """Normals ``(P, S, 3)`` from neighbour differences on the grid; NaN where undefined.

    Unoriented (the sign follows the grid's parameterisation); see :func:`orient_toward`.
    """
    profiles, samples = grid.shape
    alpha_step = abs(grid.alpha_step_deg) if np.isfinite(grid.alpha_step_deg) else 1.0
    beta_step = abs(grid.beta_step_deg) if np.isfinite(grid.beta_step_deg) else 1.0
    k_sample = max(1, round(baseline_deg / alpha_step))
    # Adjacent profiles are sin α · Δβ apart in angle: widen the stride towards the poles.
    sin_alpha = np.abs(np.sin(np.radians(np.nan_to_num(grid.alpha_deg, nan=0.0))))
    wanted = baseline_deg / beta_step / np.maximum(sin_alpha, 1e-9)
    k_profile = np.clip(np.rint(wanted), 1, None).astype(np.int64)
    usable_rows = wanted <= max(1.0, profiles / 4)

    forward_s = neighbour_differences(xyz_grid, 1, k_sample, wrap_samples=grid.wraps_alpha)
    backward_s = -neighbour_differences(xyz_grid, 1, -k_sample, wrap_samples=grid.wraps_alpha)
    d_sample = _shorter(forward_s, backward_s)

    rows = np.arange(profiles)[:, None]
    cols = np.arange(samples)[None, :]
    ahead = rows + k_profile[None, :]
    behind = rows - k_profile[None, :]
    ahead_ok = ahead < profiles
    behind_ok = behind >= 0
    forward_p = xyz_grid[np.where(ahead_ok, ahead, 0), cols] - xyz_grid
    backward_p = xyz_grid - xyz_grid[np.where(behind_ok, behind, 0), cols]
    forward_p[~ahead_ok] = np.nan
    backward_p[~behind_ok] = np.nan
    d_profile = _shorter(forward_p, backward_p)

    normals = np.cross(d_profile, d_sample).astype(np.float32)
    # A nearly parallel pair of differences gives a direction dominated by noise.
    area = np.linalg.norm(normals, axis=-1)
    lengths = np.linalg.norm(d_profile, axis=-1) * np.linalg.norm(d_sample, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sine = area / lengths
    normals[~(sine > 0.05)] = np.nan
    normals[:, ~usable_rows] = np.nan
    return _normalised(normals)


def knn_normals(points: F32, origins: F32, neighbours: int = 24) -> F32:
    """Normals by Open3D's KNN plane fit, oriented toward each point's origin."""
    import open3d as o3d

    if len(points) == 0:
        return np.empty((0, 3), np.float32)
    if len(points) < 3:
        raise StageError(f"points: {len(points)} points are too few to estimate normals")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    try:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=neighbours))
    except RuntimeError as err:
        raise StageError(f"points: KNN normal estimation failed ({err})") from err
    normals = np.asarray(cloud.normals, dtype=np.float32)
    return orient_toward(normals, points, origins)


def estimate_normals(table: pa.Table, params: NormalParams | None = None,
                     grid: ScanGrid | None = None) -> tuple[F32, dict[str, int]]:
    """Oriented unit normals ``(N, 3)`` for a points table, and how many came from each method.

    ``grid`` is the table's :class:`ScanGrid` when the caller has it already.
    """
    params = params or NormalParams()
    points = points_xyz(table)
    origins = points_origins(table)
    if grid is None and params.method != "knn":
        grid = scan_grid(table)
    if params.method == "grid" and grid is None:
        raise StageError("points: normals.method = 'grid' but the points have no grid "
                         "(profile/sample are −1); use 'auto' or 'knn'")
    if params.method == "knn" or grid is None:
        return knn_normals(points, origins, params.knn_neighbours), {"knn": len(points)}
    normal_grid = grid_normals(to_grid(points, grid), grid, params.baseline_deg)
    normals = orient_toward(from_grid(normal_grid, grid).astype(np.float32), points, origins)
    missing = np.asarray(~np.isfinite(normals).all(axis=1))
    counts = {"grid": len(points) - int(np.count_nonzero(missing)), "grid_window": 0, "knn": 0}
    if missing.any():
        # Cells the grid cannot serve (the poles, gaps) take the mean oriented normal of the
        # grid window around them: an array filter, not a neighbour search.
        window = from_grid(_window_mean(to_grid(normals, grid), grid, params.baseline_deg),
                           grid)
        filled = missing & np.isfinite(window).all(axis=1)
        normals[filled] = window[filled]
        counts["grid_window"] = int(np.count_nonzero(filled))
        missing &= ~filled
    if missing.any():
        if len(points) >= 3:
            normals[missing] = _knn_subset(points, origins, missing, params.knn_neighbours)
        else:
            normals[missing] = _normalised(origins[missing] - points[missing])
        counts["knn"] = int(np.count_nonzero(missing))
    return normals, counts


def _window_mean(normal_grid: F32, grid: ScanGrid, baseline_deg: float) -> F32:
    """Per cell, the normalised sum of the valid normals within two baselines around it."""
    from scipy.ndimage import uniform_filter

    alpha_step = abs(grid.alpha_step_deg) if np.isfinite(grid.alpha_step_deg) else 1.0
    beta_step = abs(grid.beta_step_deg) if np.isfinite(grid.beta_step_deg) else 1.0
    size = (2 * max(1, round(2 * baseline_deg / beta_step)) + 1,
            2 * max(1, round(2 * baseline_deg / alpha_step)) + 1, 1)
    modes = ("nearest", "wrap" if grid.wraps_alpha else "nearest", "nearest")
    summed = uniform_filter(np.nan_to_num(normal_grid, nan=0.0), size=size, mode=modes)
    return _normalised(summed.astype(np.float32), min_norm=1e-6)


def _knn_subset(points: F32, origins: F32, wanted: NDArray[np.bool_], neighbours: int) -> F32:
    """KNN normals for the ``wanted`` points, fitted to the points that have one.

    Leaving the other wanted points out matters at the poles: every profile measures the same
    pole point, and a neighbourhood of those copies is a line along the beam, not the surface.
    """
    from scipy.spatial import cKDTree

    support = points[~wanted] if np.count_nonzero(~wanted) >= neighbours else points
    k = min(neighbours, len(support))
    _, neighbourhoods = cKDTree(support).query(points[wanted], k=k)
    local = support[neighbourhoods.reshape(-1, k)].astype(np.float64)
    centred = local - local.mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", centred, centred)
    _, vectors = np.linalg.eigh(covariance)
    normals = vectors[:, :, 0].astype(np.float32)  # eigenvector of the smallest eigenvalue
    return orient_toward(normals, points[wanted], origins[wanted])
