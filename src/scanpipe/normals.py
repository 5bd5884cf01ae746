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

from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import StageError
from scanpipe.grid import ScanGrid, scan_grid
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


def column_f32(table: pa.Table, name: str) -> F32:
    """One float column as a float32 array, without a copy when it is one float32 chunk.

    The array may share the table's (read-only) buffer: never write into it.
    """
    values: F32 = table.column(name).to_numpy()
    return values if values.dtype == np.float32 else values.astype(np.float32)


def points_xyz(table: pa.Table) -> F32:
    """The ``x, y, z`` columns as one ``(N, 3)`` float32 array."""
    return np.stack([column_f32(table, c) for c in XYZ], axis=1)


def points_origins(table: pa.Table) -> F32:
    """The sensor-origin columns (each point's sensor origin) as ``(N, 3)`` float32."""
    return np.stack([column_f32(table, c) for c in ORIGIN], axis=1)


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


#: Three (P, S) float32 planes: the x, y and z components of a vector per grid cell.
Planes = tuple[F32, F32, F32]


def _shift_samples(plane: F32, k: int, wrap: bool) -> F32:
    """``out[:, s] = plane[:, s + k]``, wrapping around the samples when ``wrap``, else NaN
    where ``s + k`` falls outside."""
    samples = plane.shape[1]
    out = np.empty_like(plane)
    if wrap:
        k %= samples
        out[:, : samples - k] = plane[:, k:]
        out[:, samples - k:] = plane[:, :k]
        return out
    if abs(k) >= samples:
        out.fill(np.nan)
    elif k >= 0:
        out[:, : samples - k] = plane[:, k:]
        out[:, samples - k:] = np.nan
    else:
        out[:, -k:] = plane[:, : samples + k]
        out[:, :-k] = np.nan
    return out


def _squared_length(a: F32, b: F32, c: F32) -> F32:
    out = a * a
    out += b * b
    out += c * c
    return out


def _sample_differences(xyz: Planes, k: int, wrap: bool) -> tuple[Planes, F32]:
    """Per cell the shorter of the forward and backward difference ``k`` samples away, and its
    squared length (NaN where neither exists).

    The backward difference at ``s`` is the forward one at ``s − k``, so it is a shift, not a
    second subtraction. NaN lengths count as infinitely long.
    """
    forward = tuple(np.subtract(_shift_samples(c, k, wrap), c) for c in xyz)
    length = _squared_length(*forward)
    behind = _shift_samples(length, -k, wrap)
    take_forward = length <= behind
    take_forward |= np.isnan(behind)
    chosen = tuple(np.where(take_forward, f, _shift_samples(f, -k, wrap)) for f in forward)
    return (chosen[0], chosen[1], chosen[2]), np.where(take_forward, length, behind)


def _profile_differences(xyz: Planes, k_profile: NDArray[np.int64]) -> tuple[Planes, F32]:
    """As :func:`_sample_differences` along the profiles, ``k_profile[s]`` profiles away for
    sample ``s``: the neighbour's index is arithmetic (``cell + k·S``), one gather per plane."""
    profiles, samples = xyz[0].shape
    cells = profiles * samples
    index_type = np.int32 if cells < 2**31 - 1 else np.int64
    here = np.arange(cells, dtype=index_type).reshape(profiles, samples)
    offset = (k_profile * samples).astype(index_type)[None, :]
    ahead = here + offset
    ahead_ok = ahead < cells
    np.copyto(ahead, here, where=~ahead_ok)
    forward = tuple(np.take(c.reshape(-1), ahead) - c for c in xyz)
    length = _squared_length(*forward)
    length[~ahead_ok] = np.nan  # the vectors stay 0 there: a NaN length marks them missing
    behind = here - offset
    behind_ok = behind >= 0
    np.copyto(behind, here, where=~behind_ok)
    length_behind = np.take(length.reshape(-1), behind)
    length_behind[~behind_ok] = np.nan
    take_forward = length <= length_behind
    take_forward |= np.isnan(length_behind)
    # The chosen difference starts at this cell (forward) or k profiles before it (backward).
    source = np.where(take_forward, here, behind)
    chosen = tuple(np.take(f.reshape(-1), source) for f in forward)
    return (chosen[0], chosen[1], chosen[2]), np.where(take_forward, length, length_behind)


def grid_normal_planes(xyz: Planes, grid: ScanGrid, baseline_deg: float = 1.0) -> Planes:
    """Normals as three ``(P, S)`` planes from neighbour differences; NaN where undefined.

    Unoriented (the sign follows the grid's parameterisation). Works on one float32 plane per
    component, so every step is a contiguous array operation or an arithmetic gather.
    """
    profiles, _ = grid.shape
    alpha_step = abs(grid.alpha_step_deg) if np.isfinite(grid.alpha_step_deg) else 1.0
    beta_step = abs(grid.beta_step_deg) if np.isfinite(grid.beta_step_deg) else 1.0
    k_sample = max(1, round(baseline_deg / alpha_step))
    # Adjacent profiles are sin α · Δβ apart in angle: widen the stride towards the poles.
    sin_alpha = np.abs(np.sin(np.radians(np.nan_to_num(grid.alpha_deg, nan=0.0))))
    wanted = baseline_deg / beta_step / np.maximum(sin_alpha, 1e-9)
    k_profile = np.clip(np.rint(wanted), 1, None).astype(np.int64)
    usable = wanted <= max(1.0, profiles / 4)

    (sx, sy, sz), s_len = _sample_differences(xyz, k_sample, grid.wraps_alpha)
    k_profile = np.minimum(k_profile, profiles)  # beyond the grid either way
    (px, py, pz), p_len = _profile_differences(xyz, k_profile)

    nx = py * sz
    nx -= pz * sy
    ny = pz * sx
    ny -= px * sz
    nz = px * sy
    nz -= py * sx
    area = _squared_length(nx, ny, nz)
    # A nearly parallel pair of differences gives a direction dominated by noise: keep the
    # normal where sin(angle) > 0.05, i.e. area² > 0.05² · |d_p|² · |d_s|².
    with np.errstate(invalid="ignore", over="ignore"):
        p_len *= s_len
        p_len *= np.float32(0.05 ** 2)
        ok = area > p_len
    ok &= usable[None, :]
    np.sqrt(area, out=area)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.divide(np.float32(1.0), area, out=area)
    scale[~ok] = np.nan
    for component in (nx, ny, nz):
        component *= scale
    return nx, ny, nz


def _orient_planes(normals: Planes, xyz: Planes, origins: Planes) -> None:
    """Flip (in place) the normals that point away from their sensor origin."""
    facing = np.subtract(origins[0], xyz[0])
    facing *= normals[0]
    for k in (1, 2):
        term = np.subtract(origins[k], xyz[k])
        term *= normals[k]
        facing += term
    sign = np.where(facing < 0, np.float32(-1.0), np.float32(1.0))
    for component in normals:
        component *= sign


def grid_normals(xyz_grid: F32, grid: ScanGrid, baseline_deg: float = 1.0) -> F32:
    """Normals ``(P, S, 3)`` from neighbour differences on the grid; NaN where undefined.

    Unoriented (the sign follows the grid's parameterisation); see :func:`orient_toward`.
    """
    planes = tuple(np.ascontiguousarray(xyz_grid[..., k], dtype=np.float32) for k in range(3))
    return np.stack(grid_normal_planes((planes[0], planes[1], planes[2]), grid, baseline_deg),
                    axis=-1)


class _Layout:
    """Moves per-point values into grid planes and back: a reshape when the grid is dense,
    else one scatter through the cells that hold a point."""

    def __init__(self, grid: ScanGrid) -> None:
        self.grid = grid
        if grid.dense:
            return
        flat_index = grid.index.reshape(-1)
        self.cells = np.flatnonzero(flat_index >= 0)
        rows = flat_index[self.cells]
        # A table in grid order (assemble's, filtered) needs no gather.
        self.rows: NDArray[np.int64] | None = (
            None if rows.size and rows[0] == 0 and rows[-1] == rows.size - 1
            and bool(np.all(np.diff(rows) == 1)) else rows)

    def plane(self, values: F32) -> F32:
        """A ``(P, S)`` plane of per-point ``values`` (NaN where no point); may be a view."""
        shape = self.grid.shape
        if self.grid.dense:
            return values.reshape(shape)
        out = np.full(shape[0] * shape[1], np.nan, dtype=np.float32)
        out[self.cells] = values if self.rows is None else values[self.rows]
        return out.reshape(shape)

    def points(self, planes: Planes) -> F32:
        """Per-point ``(N, 3)`` values from three planes."""
        if self.grid.dense:
            return np.stack([p.reshape(-1) for p in planes], axis=1)
        out = np.empty((len(self.cells), 3), dtype=np.float32)
        for k, p in enumerate(planes):
            values = p.reshape(-1)[self.cells]
            if self.rows is None:
                out[:, k] = values
            else:
                out[self.rows, k] = values
        return out


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
                     grid: ScanGrid | None = None,
                     columns: Mapping[str, F32] | None = None) -> tuple[F32, dict[str, int]]:
    """Oriented unit normals ``(N, 3)`` for a points table, and how many came from each method.

    ``grid`` is the table's :class:`ScanGrid` and ``columns`` its float32 ``x, y, z`` and
    origin columns (:func:`column_f32`) when the caller has them already.
    """
    params = params or NormalParams()
    if grid is None and params.method != "knn":
        grid = scan_grid(table)
    if params.method == "grid" and grid is None:
        raise StageError("points: normals.method = 'grid' but the points have no grid "
                         "(profile/sample are −1); use 'auto' or 'knn'")
    if params.method == "knn" or grid is None:
        return (knn_normals(points_xyz(table), points_origins(table), params.knn_neighbours),
                {"knn": table.num_rows})
    layout = _Layout(grid)

    def column(name: str) -> F32:
        return columns[name] if columns is not None else column_f32(table, name)

    xyz = tuple(layout.plane(column(c)) for c in XYZ)
    origins = tuple(layout.plane(column(c)) for c in ORIGIN)
    xyz_planes: Planes = (xyz[0], xyz[1], xyz[2])
    normals = grid_normal_planes(xyz_planes, grid, params.baseline_deg)
    _orient_planes(normals, xyz_planes, (origins[0], origins[1], origins[2]))
    missing = np.isnan(normals[0])
    if not grid.dense:
        missing &= grid.index >= 0  # empty cells need no normal
    missing_points = int(np.count_nonzero(missing))
    counts = {"grid": table.num_rows - missing_points, "grid_window": 0, "knn": 0}
    if missing_points:
        # Cells the grid cannot serve (the poles, gaps) take the mean oriented normal of the
        # grid window around them: an array filter, not a neighbour search.
        counts["grid_window"] = _fill_from_window(normals, missing, grid, params.baseline_deg)
    out = layout.points(normals)
    if counts["grid"] + counts["grid_window"] < table.num_rows:
        still = np.isnan(out[:, 0])
        points, origins_n = points_xyz(table), points_origins(table)
        if len(points) >= 3:
            out[still] = _knn_subset(points, origins_n, still, params.knn_neighbours)
        else:
            out[still] = _normalised(origins_n[still] - points[still])
        counts["knn"] = int(np.count_nonzero(still))
    return out, counts


def _window_size(grid: ScanGrid, baseline_deg: float) -> tuple[int, int]:
    """The (profiles, samples) size of the window of :func:`_fill_from_window`."""
    alpha_step = abs(grid.alpha_step_deg) if np.isfinite(grid.alpha_step_deg) else 1.0
    beta_step = abs(grid.beta_step_deg) if np.isfinite(grid.beta_step_deg) else 1.0
    return (2 * max(1, round(2 * baseline_deg / beta_step)) + 1,
            2 * max(1, round(2 * baseline_deg / alpha_step)) + 1)


def _fill_from_window(normals: Planes, wanted: NDArray[np.bool_], grid: ScanGrid,
                      baseline_deg: float) -> int:
    """Give the ``wanted`` cells (in place) the normalised mean of the valid normals within
    two baselines around them (a ``uniform_filter`` window, ``nearest`` at the grid's ends,
    wrapping around the samples of a 360° profile); returns how many got one.

    Only what the wanted cells read is computed: they are mostly the bands around the poles
    (a few per cent of the grid), plus lone cells at gaps. Columns with more wanted cells
    than a window is tall take the separable mean over the columns their windows reach;
    the other cells sum their own windows (an arithmetic gather).
    """
    size = _window_size(grid, baseline_deg)
    per_column = np.count_nonzero(wanted, axis=0)
    band = np.flatnonzero(per_column > size[0])
    lone = np.flatnonzero((per_column > 0) & (per_column <= size[0]))
    # Both means from the normals as they are, before either writes.
    band_means = _column_window_means(normals, band, grid, size) if len(band) else None
    rows, at = np.nonzero(wanted[:, lone])
    lone_means = _cell_window_means(normals, rows, lone[at], grid, size)
    filled = _put_normalised(normals, lone_means, (rows, lone[at]), None)
    if band_means is not None:
        filled += _put_normalised(normals, band_means, (slice(None), band), wanted[:, band])
    return filled


def _window_columns(columns: NDArray[np.int64], width: int, grid: ScanGrid) -> NDArray[np.int64]:
    """``(len(columns), width)``: the sample columns of each column's window (wrapped around a
    360° profile, else clamped to the grid as ``mode="nearest"``)."""
    samples = grid.shape[1]
    reach = columns[:, None] + np.arange(-(width // 2), width // 2 + 1)[None, :]
    out: NDArray[np.int64] = (np.mod(reach, samples) if grid.wraps_alpha
                              else np.clip(reach, 0, samples - 1))
    return out


def _column_window_means(normals: Planes, columns: NDArray[np.int64], grid: ScanGrid,
                         size: tuple[int, int]) -> Planes:
    """The window mean of each component over whole ``columns``: ``(P, len(columns))``."""
    from scipy.ndimage import uniform_filter1d

    samples = grid.shape[1]
    reach = _window_columns(columns, size[1], grid)
    needed = np.unique(reach)
    whole = 2 * len(needed) > samples  # most columns: filter the whole grid, no gathers
    if not whole:
        position = np.zeros(samples, dtype=np.int64)
        position[needed] = np.arange(len(needed))
        reach = position[reach]  # the window's columns in the gathered block
    means = []
    for component in normals:
        block = np.nan_to_num(component if whole else component[:, needed], nan=0.0)
        block = uniform_filter1d(block, size[0], axis=0, mode="nearest")
        if whole:
            block = uniform_filter1d(block, size[1], axis=1,
                                     mode="wrap" if grid.wraps_alpha else "nearest")
            means.append(block[:, columns])
            continue
        total = block[:, reach[:, 0]]
        for k in range(1, reach.shape[1]):
            total += block[:, reach[:, k]]
        total *= np.float32(1.0 / size[1])
        means.append(total)
    return means[0], means[1], means[2]


def _cell_window_means(normals: Planes, rows: NDArray[np.intp], columns: NDArray[np.int64],
                       grid: ScanGrid, size: tuple[int, int]) -> Planes:
    """The window mean of each component at the cells ``(rows, columns)``: ``(M,)`` each."""
    profiles, samples = grid.shape
    window_rows = np.clip(rows[:, None] + np.arange(-(size[0] // 2), size[0] // 2 + 1)[None, :],
                          0, profiles - 1)
    cells = (window_rows[:, :, None] * samples
             + _window_columns(columns, size[1], grid)[:, None, :]).reshape(
                 len(rows), size[0] * size[1])
    means = []
    for component in normals:
        values = np.nan_to_num(np.take(component.reshape(-1), cells), nan=0.0)
        means.append((values.sum(axis=1) / np.float32(size[0] * size[1])).astype(np.float32))
    return means[0], means[1], means[2]


def _put_normalised(normals: Planes, means: Planes, where: tuple[Any, Any],
                    wanted: NDArray[np.bool_] | None) -> int:
    """Write the unit vectors of ``means`` into ``normals[where]`` (only where ``wanted``, when
    given, and where the mean is not ~0); returns how many cells were written."""
    norm = np.sqrt(_squared_length(means[0], means[1], means[2]))
    ok = norm > 1e-6
    if wanted is not None:
        ok &= wanted
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.divide(np.float32(1.0), norm)
    for component, mean in zip(normals, means, strict=True):
        with np.errstate(invalid="ignore"):  # 0 · inf where the mean is 0: not written
            mean *= scale
        part = component[where]
        np.copyto(part, mean, where=ok)
        component[where] = part
    return int(np.count_nonzero(ok))


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
