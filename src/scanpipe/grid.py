"""The organized scan grid: points table ↔ (profiles × samples) arrays, and neighbours on it.

A scan from a 2-D scanner on a turntable is a grid: profile ``p`` (one platform position or one
head turn) × sample ``s`` (one beam angle). The ``points`` artifact keeps both indices, so
neighbourhoods, filters, normals and meshing are array slicing, never a KD-tree search.

- :func:`scan_grid` finds the grid of a points table (``None`` when it has none: imported clouds
  carry ``profile = sample = −1``); :func:`to_grid` / :func:`from_grid` move per-point values
  into ``(P, S, ...)`` arrays and back (NaN where a cell holds no point).
- :func:`shifted` gives every cell its neighbour at ``(p + dp, s + ds)``;
  :func:`neighbour_differences` the forward differences along one axis. Both wrap along the
  sample axis when asked to (a 360° profile: sample S−1 neighbours sample 0).
- :func:`median3x3` and :func:`bilateral_smooth` are the NaN-aware window operations the
  filters use on the range image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.errors import StageError

I64 = NDArray[np.int64]
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
AnyArray = NDArray[Any]


@dataclass(frozen=True)
class ScanGrid:
    """Where each point sits in the profile × sample grid, and the grid's angles."""

    #: ``(P, S)`` row index of the point at (profile, sample); −1 where there is none.
    index: I64
    #: ``(P,)`` mean platform angle of each profile; NaN for a profile without points.
    beta_deg: F64
    #: ``(S,)`` mean beam angle of each sample; NaN for a sample without points.
    alpha_deg: F64
    #: True when row ``i`` of the table is cell ``i`` of the flattened grid (the assemble
    #: output): then moving values in and out of the grid is a reshape, not a scatter.
    dense: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        """``(profiles, samples)``."""
        return int(self.index.shape[0]), int(self.index.shape[1])

    @property
    def alpha_step_deg(self) -> float:
        """The beam step (median difference of consecutive sample angles)."""
        return _median_step(self.alpha_deg)

    @property
    def beta_step_deg(self) -> float:
        """The platform step (median difference of consecutive profile angles)."""
        return _median_step(self.beta_deg)

    @property
    def wraps_alpha(self) -> bool:
        """True when the samples cover the full circle, so sample S−1 neighbours sample 0."""
        step = self.alpha_step_deg
        return bool(np.isfinite(step)) and abs(self.shape[1] * step - 360.0) < 0.5 * abs(step)


def _median_step(angles_deg: F64) -> float:
    """The typical step between consecutive angles; NaN when there is none.

    Repeated angles (several profiles at one platform position, when a step scan was
    assembled as continuous) make the median 0; the mean step over the span is taken then,
    and NaN when the angles do not change at all, so that no caller divides by zero.
    """
    finite = angles_deg[np.isfinite(angles_deg)]
    if finite.size < 2:
        return float("nan")
    step = float(np.median(np.diff(finite)))
    if step == 0.0:
        step = float(finite[-1] - finite[0]) / (finite.size - 1)
    return step if step != 0.0 else float("nan")


def grid_from_indices(profile: NDArray[Any], sample: NDArray[Any],
                      alpha_deg: F64, beta_deg: F64) -> ScanGrid | None:
    """The grid spanned by per-point indices (``None`` if any index is −1 or there are none).

    The shape is ``max(profile) + 1`` × ``max(sample) + 1``. Two points in one cell are an error.
    """
    if profile.size == 0:
        return None
    profile = profile.astype(np.int64, copy=False)
    sample = sample.astype(np.int64, copy=False)
    if profile.min() < 0 or sample.min() < 0:
        return None
    shape = (int(profile.max()) + 1, int(sample.max()) + 1)
    flat = profile * shape[1] + sample
    cells = shape[0] * shape[1]
    dense = flat.size == cells and bool(np.array_equal(flat, np.arange(cells)))
    if dense:
        index = np.arange(cells, dtype=np.int64)
    else:
        index = np.full(cells, -1, dtype=np.int64)
        index[flat] = np.arange(flat.size, dtype=np.int64)
        if np.count_nonzero(index >= 0) != flat.size:
            raise StageError("points: two points share a (profile, sample) grid cell; "
                             "expected at most one point per cell")
    if dense and np.isfinite(beta_deg).all() and np.isfinite(alpha_deg).all():
        beta_mean = beta_deg.reshape(shape).mean(axis=1)
        alpha_mean = alpha_deg.reshape(shape).mean(axis=0)
    else:
        beta_mean = _mean_by(profile, beta_deg, shape[0])
        alpha_mean = _mean_by(sample, alpha_deg, shape[1])
    return ScanGrid(index=index.reshape(shape), beta_deg=beta_mean, alpha_deg=alpha_mean,
                    dense=dense)


def scan_grid(table: pa.Table) -> ScanGrid | None:
    """The grid of a points table, or None when it has none (profile or sample −1)."""
    if table.num_rows == 0:
        return None
    return grid_from_indices(
        table.column("profile").to_numpy(),
        table.column("sample").to_numpy(),
        table.column("alpha_deg").to_numpy().astype(np.float64),
        table.column("beta_deg").to_numpy().astype(np.float64),
    )


def _mean_by(group: I64, values: F64, size: int) -> F64:
    finite = np.isfinite(values)
    if not finite.all():  # else no copies: the gathers were most of the time
        group, values = group[finite], values[finite]
    counts = np.bincount(group, minlength=size).astype(np.float64)
    sums = np.bincount(group, weights=values, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan)


def to_grid(values: AnyArray, grid: ScanGrid, fill: float = np.nan) -> AnyArray:
    """Per-point ``values`` (N, ...) scattered into a new grid array (P, S, ...).

    Cells without a point get ``fill`` (NaN by default; pass a value the dtype can hold for
    integer arrays).
    """
    shape = grid.index.shape + values.shape[1:]
    if grid.dense:
        return values.reshape(shape).copy()
    out = np.full(shape, fill, dtype=values.dtype)
    valid = grid.index >= 0
    out[valid] = values[grid.index[valid]]
    return out


def from_grid(grid_values: AnyArray, grid: ScanGrid) -> AnyArray:
    """Inverse of :func:`to_grid`: the per-point values (N, ...) in table order."""
    if grid.dense:
        return grid_values.reshape((-1, *grid_values.shape[2:])).copy()
    valid = grid.index >= 0
    out = np.empty((int(np.count_nonzero(valid)), *grid_values.shape[2:]),
                   dtype=grid_values.dtype)
    out[grid.index[valid]] = grid_values[valid]
    return out


def shifted(grid_values: AnyArray, d_profile: int, d_sample: int, wrap_samples: bool = False,
            fill: float = np.nan) -> AnyArray:
    """Every cell's neighbour ``(p + d_profile, s + d_sample)``: ``out[p, s] = g[p+dp, s+ds]``.

    Cells whose neighbour lies outside the grid get ``fill``; along the sample axis the grid
    wraps around instead when ``wrap_samples`` (a full-circle profile).
    """
    out = np.full_like(grid_values, fill)
    profiles, samples = grid_values.shape[:2]
    if abs(d_profile) >= profiles:
        return out
    source = grid_values
    if wrap_samples and d_sample:
        source = np.roll(grid_values, -d_sample, axis=1)
        d_sample = 0
    if abs(d_sample) >= samples:
        return out
    dst_p, src_p = _span(d_profile, profiles)
    dst_s, src_s = _span(d_sample, samples)
    out[dst_p, dst_s] = source[src_p, src_s]
    return out


def _span(offset: int, size: int) -> tuple[slice, slice]:
    """Destination and source slices for a shift by ``offset`` along an axis of ``size``."""
    if offset >= 0:
        return slice(0, size - offset), slice(offset, size)
    return slice(-offset, size), slice(0, size + offset)


def neighbour_differences(grid_values: AnyArray, axis: int, step: int = 1,
                          wrap_samples: bool = False) -> AnyArray:
    """Forward differences ``g[next] − g[here]`` along ``axis`` (0 = profile, 1 = sample).

    ``step`` cells ahead; NaN where the neighbour is outside the grid (or wraps, see
    :func:`shifted`). Works on (P, S) and (P, S, k) arrays, e.g. the x, y, z grid.
    """
    if axis not in (0, 1):
        raise ValueError(f"axis must be 0 (profile) or 1 (sample), not {axis}")
    ahead = shifted(grid_values, step if axis == 0 else 0, step if axis == 1 else 0,
                    wrap_samples=wrap_samples)
    return ahead - grid_values


#: The 19 compare-exchanges of a median-of-9 sorting network (Paeth; Devillard's opt_med9).
_MEDIAN9_NETWORK = (
    (1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 3), (5, 8),
    (4, 7), (3, 6), (1, 4), (2, 5), (4, 7), (4, 2), (6, 4), (4, 2),
)


def window_offsets(radius: int) -> list[tuple[int, int]]:
    """The ``(dp, ds)`` offsets of a square window of ``radius`` cells, centre included."""
    span = range(-radius, radius + 1)
    return [(dp, ds) for dp in span for ds in span]


def median3x3(range_grid: F32, wrap_samples: bool = False) -> tuple[F32, NDArray[np.int8]]:
    """The median of every cell's 3 × 3 window, and how many of its 8 neighbours are valid.

    Missing neighbours (NaN or outside the grid) count as the centre's own value, so a cell
    with few neighbours stays close to itself; the neighbour count lets a caller reject such
    cells separately. A NaN centre gives NaN. A sorting network of elementwise min / max:
    about 20× faster than sorting the stacked windows.
    """
    window: list[F32] = []
    valid_neighbours = np.zeros(range_grid.shape, dtype=np.int8)
    for dp, ds in window_offsets(1):
        if dp == 0 and ds == 0:
            window.append(range_grid)
            continue
        neighbour = shifted(range_grid, dp, ds, wrap_samples=wrap_samples)
        missing = np.isnan(neighbour)
        valid_neighbours += ~missing
        window.append(np.where(missing, range_grid, neighbour))
    for i, j in _MEDIAN9_NETWORK:
        low = np.minimum(window[i], window[j])
        window[j] = np.maximum(window[i], window[j])
        window[i] = low
    return window[4], valid_neighbours


def bilateral_smooth(range_grid: F32, radius: int = 1, sigma_cells: float = 1.0,
                     sigma_range_m: float = 0.02, relative: float = 0.0,
                     wrap_samples: bool = False) -> F32:
    """Edge-preserving smoothing of a range image (a bilateral filter over the grid window).

    Each cell becomes the weighted mean of the valid cells of its ``(2·radius+1)²`` window,
    with weights ``exp(−d²/2σ_c²) · exp(−Δr²/2σ_r²)`` for a grid distance ``d`` (cells) and a
    range difference ``Δr``; ``σ_r = sigma_range_m + relative · r``. Neighbours across a depth
    edge (Δr ≫ σ_r) get almost no weight, so edges stay sharp. NaN cells stay NaN.

    The neighbours are views into one padded copy of the grid (NaN beyond the profiles, the
    wrapped samples of a 360° profile at the sides), not shifted copies. With a constant σ_r
    (``relative`` 0) the weight between two cells is the same seen from either, so each
    pair's exponential is computed once, for an offset and its opposite: half the ``exp``.
    """
    grid = np.asarray(range_grid, dtype=np.float32)
    profiles, samples = grid.shape
    r = int(radius)
    padded = np.full((profiles + 2 * r, samples + 2 * r), np.nan, dtype=np.float32)
    if wrap_samples:
        padded[r: r + profiles] = grid[:, np.mod(np.arange(-r, samples + r), samples)]
    else:
        padded[r: r + profiles, r: r + samples] = grid
    values = np.nan_to_num(padded, nan=0.0)  # a NaN neighbour adds nothing (its weight is 0)
    centre = padded[r: r + profiles, r: r + samples]
    total = values[r: r + profiles, r: r + samples].copy()  # the centre, weight 1
    weights = np.ones_like(total)
    weight = np.empty_like(total)

    def spatial(dp: int, ds: int) -> np.float32:
        return np.float32(np.exp(-(dp * dp + ds * ds) / (2.0 * sigma_cells ** 2)))

    def add(w: F32, dp: int, ds: int) -> None:
        """Add the neighbour at (+dp, +ds) of every cell with the weights ``w``."""
        np.add(weights, w, out=weights)
        np.multiply(w, values[r + dp: r + dp + profiles, r + ds: r + ds + samples], out=w)
        np.add(total, w, out=total)

    offsets = [(dp, ds) for dp, ds in window_offsets(r) if (dp, ds) != (0, 0)]
    if relative == 0.0:
        minus_inv_two_var = np.float32(-0.5 / (np.float32(sigma_range_m) ** 2))
        for dp, ds in offsets:
            if (dp, ds) < (0, 0):
                continue  # done with its opposite
            # Pair weights for the cells q and q + d, over every q that is a centre or a
            # centre − d: rows r − dp … r + P − 1, columns shifted alike.
            low_s = r - max(ds, 0)
            rows, cols = slice(r - dp, r + profiles), slice(low_s, r + samples - min(ds, 0))
            ahead = padded[r: r + profiles + dp, low_s + ds: r + samples - min(ds, 0) + ds]
            pair = np.subtract(ahead, padded[rows, cols])
            np.multiply(pair, pair, out=pair)
            np.multiply(pair, minus_inv_two_var, out=pair)
            np.exp(pair, out=pair)
            np.multiply(pair, spatial(dp, ds), out=pair)
            np.fmax(pair, np.float32(0.0), out=pair)  # NaN (a missing cell) → weight 0
            forward = max(ds, 0)
            np.copyto(weight, pair[dp: dp + profiles, forward: forward + samples])
            add(weight, dp, ds)
            np.copyto(weight, pair[:profiles, forward - ds: forward - ds + samples])
            add(weight, -dp, -ds)
    else:
        sigma_r = np.float32(sigma_range_m) + np.float32(relative) * centre
        minus_inv_var = np.float32(-0.5) / (sigma_r * sigma_r)
        for dp, ds in offsets:
            np.subtract(padded[r + dp: r + dp + profiles, r + ds: r + ds + samples], centre,
                        out=weight)
            np.multiply(weight, weight, out=weight)
            np.multiply(weight, minus_inv_var, out=weight)
            np.exp(weight, out=weight)
            np.multiply(weight, spatial(dp, ds), out=weight)
            np.fmax(weight, np.float32(0.0), out=weight)
            add(weight, dp, ds)
    with np.errstate(invalid="ignore", divide="ignore"):
        smoothed: F32 = np.divide(total, weights, out=total)
    smoothed[np.isnan(grid)] = np.nan
    return smoothed


def subsample(table: pa.Table, stride: int) -> pa.Table:
    """The grid at 1/``stride``: every ``stride``-th profile and sample, renumbered.

    Keeps profile 0 and sample 0 (so the poles at α = 0°/180° stay when the sample count allows).
    """
    if stride <= 1:
        return table
    profile = table.column("profile").to_numpy(zero_copy_only=False)
    sample = table.column("sample").to_numpy(zero_copy_only=False)
    keep = (profile % stride == 0) & (sample % stride == 0)
    part = table.filter(pa.array(keep))
    for name, values in (("profile", profile), ("sample", sample)):
        part = part.set_column(part.schema.get_field_index(name), name,
                               pa.array((values[keep] // stride).astype(np.int32)))
    return part
