"""Filter: clean a point cloud, on its scan grid where it has one. Filters never add points.

Each filter is one nested parameter model with ``enabled``; they run in this order:

1. ``no_return``: points without a return (NaN range or coordinates).
2. ``range_gate``: ranges outside ``[min_range_m, max_range_m]``.
3. ``depth_edges`` (grid): mixed pixels and veil points at depth discontinuities. For two grid
   neighbours (along the profile and along the sample axis) the angle at the farther point
   between its beam and the segment to the nearer point is small on a depth edge (a real
   surface seen at incidence θ gives 90° − θ). Pairs with an angle under ``min_angle_deg`` and
   a jump over ``min_jump_m`` take the farther point (``remove = far``) or both.
4. ``grid_median`` (grid): the median of each 3 × 3 window of the range image; ``action =
   remove`` takes points further than ``max_deviation_m + relative · r`` from it (isolated
   outliers), ``replace`` moves every point to it along its beam. Points with fewer than
   ``min_neighbours`` valid neighbours are taken in both cases.
5. ``smoothing`` (grid): an edge-preserving (bilateral) smoothing of the range image; points
   move along their beams. On by default; the grid mesh meshes the smoothed range image.
6. ``double_coverage`` (grid): with more than 180° of travel a 360° profile sees every
   direction twice, at (α, β) and (−α, β + 180°). ``keep`` both, ``merge`` them into the first
   view (mean position; the second is taken), or keep the ``best`` view: the one whose beam
   meets the local surface (grid normal) closer to perpendicular.
7. ``statistical_outlier`` (Open3D): points whose mean distance to their neighbours is more
   than ``std_ratio`` standard deviations above the average; by default only for clouds without
   a grid (the grid filters do the same job ~100× faster).
8. ``voxel``: one point per cubic voxel, the one nearest the voxel's centroid (so every column
   of the kept point stays consistent; no new coordinates are invented).

``mode = remove`` drops what the filters take; ``mark`` keeps every row and adds a
``filtered_by`` string column (the first filter that took the point; null = kept). Filters that
change values (median replace, smoothing, merge) change them in both modes. Rows already marked
by an earlier filter run count as taken. The report lists how many points each filter took.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field, model_validator

from scanpipe.errors import StageError
from scanpipe.grid import (
    ScanGrid,
    bilateral_smooth,
    from_grid,
    median3x3,
    neighbour_differences,
    scan_grid,
    shifted,
    to_grid,
)
from scanpipe.params import Params
from scanpipe.progress import ProgressFn
from scanpipe.schema import ORIGIN, POINTS
from scanpipe.stage import Stage, StageResult

F32 = NDArray[np.float32]
B = NDArray[np.bool_]
I64 = NDArray[np.int64]



class RangeGateParams(Params):
    """Keep ranges within the scanner's usable interval: by default (None) the scanner's own
    ``min_range_m`` / ``max_range_m`` as the rig gave them to assemble (carried in the points'
    metadata, :data:`SCANNER_RANGE_KEY`); points from another tool have none, and then the
    bound not set here is not applied."""

    enabled: bool = True
    min_range_m: float | None = Field(None, ge=0)
    max_range_m: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> RangeGateParams:
        if (self.max_range_m is not None and self.min_range_m is not None
                and self.max_range_m <= self.min_range_m):
            raise ValueError(f"max_range_m ({self.max_range_m}) must be greater than "
                             f"min_range_m ({self.min_range_m})")
        return self


class NoReturnParams(Params):
    """Drop samples without a return."""

    enabled: bool = True


class DepthEdgeParams(Params):
    """Mixed pixels / veil points at depth discontinuities (grid)."""

    enabled: bool = True
    min_angle_deg: float = Field(10.0, gt=0, lt=90,
                                 description="beam-to-neighbour angle below which it is an edge")
    min_jump_m: float = Field(0.05, ge=0, description="ignore smaller jumps (noise)")
    remove: Literal["far", "both"] = "far"


class GridMedianParams(Params):
    """3 × 3 median of the range image (grid): remove outliers or replace by the median."""

    enabled: bool = True
    action: Literal["remove", "replace"] = "remove"
    max_deviation_m: float = Field(0.1, ge=0)
    relative: float = Field(0.02, ge=0, le=1, description="extra deviation allowed per metre")
    min_neighbours: int = Field(2, ge=0, le=8, description="fewer valid neighbours: taken")


class SmoothingParams(Params):
    """Edge-preserving (bilateral) smoothing of the range image along the grid.

    The defaults (two passes, σ_r 3 cm: three times the rig's range noise) were chosen on the
    built-in room at the lab scan's resolution, three seeds (docs/assemble-filter.md): the grid
    mesh's mean distance to the truth 1.69 mm, against 2.72 mm with one pass at 2 cm and
    2.25 mm for the Open3D-only baseline; a third pass gains 0.24 mm there but costs
    completeness and accuracy on coarser scans (1° platform steps).
    """

    enabled: bool = True
    radius: int = Field(1, ge=1, le=3, description="window half-size in cells")
    sigma_cells: float = Field(1.0, gt=0, le=10)
    sigma_range_m: float = Field(0.03, gt=0, le=10,
                                 description="range differences well above this are edges")
    relative: float = Field(0.0, ge=0, le=1, description="σ_r grows by this per metre of range")
    iterations: int = Field(2, ge=1, le=10)


class DoubleCoverageParams(Params):
    """Directions seen twice (travel beyond 180° with a 360° profile)."""

    enabled: bool = True
    action: Literal["keep", "merge", "best"] = "keep"
    tolerance_steps: float = Field(0.5, gt=0, le=5,
                                   description="β and α match within this many grid steps")


class StatisticalOutlierParams(Params):
    """Open3D statistical outlier removal."""

    enabled: bool = True
    with_grid: bool = Field(False, description="also on clouds with a grid")
    neighbours: int = Field(20, ge=2, le=500)
    std_ratio: float = Field(2.0, gt=0)


class VoxelParams(Params):
    """Voxel downsampling to one point per voxel."""

    enabled: bool = False
    size_m: float = Field(0.01, gt=0)


#: Schema-metadata key of a points table: JSON ``[min_range_m, max_range_m]`` of the scanner
#: that measured them (written by assemble from the rig).
SCANNER_RANGE_KEY = b"scanpipe.scanner_range_m"


class FilterParams(Params):
    """Which filters run and how; see the module docstring for the order."""

    mode: Literal["remove", "mark"] = "remove"
    warn_taken_share: float = Field(
        0.3, gt=0, le=1, description="Warn when one filter takes more than this share of the "
                                     "points.")
    no_return: NoReturnParams = NoReturnParams()
    range_gate: RangeGateParams = RangeGateParams()
    depth_edges: DepthEdgeParams = DepthEdgeParams()
    grid_median: GridMedianParams = GridMedianParams()
    smoothing: SmoothingParams = SmoothingParams()
    double_coverage: DoubleCoverageParams = DoubleCoverageParams()
    statistical_outlier: StatisticalOutlierParams = StatisticalOutlierParams()
    voxel: VoxelParams = VoxelParams()


#: ``filtered_by`` values by code; code 0 = kept, 1 = marked by an earlier filter run.
FILTER_NAMES = ("kept", "previous", "no_return", "range_gate", "depth_edges", "grid_median",
                "smoothing", "double_coverage", "statistical_outlier", "voxel")


@dataclass
class Cloud:
    """The working state: the input table, ranges, and which filter took each point.

    Coordinates and origins are stacked into ``(N, 3)`` arrays only when a filter needs them
    (most grid filters work on the range image alone).
    """

    table: pa.Table
    range_m: F32
    grid: ScanGrid | None
    taken: NDArray[np.int8]
    values_changed: bool = False
    report: dict[str, Any] = field(default_factory=dict)
    _xyz: F32 | None = None
    _origin: F32 | None = None

    @property
    def xyz(self) -> F32:
        """Coordinates ``(N, 3)`` (current values)."""
        if self._xyz is None:
            self._xyz = np.stack([_column(self.table, c) for c in "xyz"], axis=1)
        return self._xyz

    @xyz.setter
    def xyz(self, value: F32) -> None:
        self._xyz = value

    @property
    def origin(self) -> F32:
        """Sensor origins ``(N, 3)``."""
        if self._origin is None:
            self._origin = np.stack([_column(self.table, c) for c in ORIGIN], axis=1)
        return self._origin

    @property
    def kept(self) -> B:
        """Points no filter has taken yet."""
        kept: B = self.taken == 0
        return kept

    @property
    def finite(self) -> B:
        """Points with finite coordinates."""
        if self._xyz is not None:
            return np.asarray(np.isfinite(self._xyz).all(axis=1), dtype=bool)
        finite: B = np.ones(self.taken.size, bool)
        for name in "xyz":
            finite &= np.isfinite(_column(self.table, name))
        return finite

    def take(self, name: str, mask: B, **details: Any) -> None:
        """Mark the kept points in ``mask`` as taken by ``name``; count them in the report."""
        newly = mask & self.kept
        self.taken[newly] = FILTER_NAMES.index(name)
        self.report[name] = {"taken": int(np.count_nonzero(newly)), **details}

    def range_grid(self) -> F32:
        """The range image of the kept points (NaN elsewhere)."""
        assert self.grid is not None
        ranges = np.where(self.kept, self.range_m, np.float32(np.nan)).astype(np.float32)
        return to_grid(ranges, self.grid)

    def move_along_beams(self, new_range_grid: F32) -> int:
        """Set new ranges (grid) for the kept points, moving them along their beams."""
        assert self.grid is not None
        new_range = from_grid(new_range_grid, self.grid)
        moved = self.kept & np.isfinite(new_range) & (new_range != self.range_m)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(moved, new_range / self.range_m, np.float32(1)).astype(np.float32)
        self.xyz = self.origin + (self.xyz - self.origin) * scale[:, None]
        self.range_m = np.where(moved, new_range, self.range_m).astype(np.float32)
        self.values_changed = True
        return int(np.count_nonzero(moved))


def _points_grid(cloud: Cloud, values: F32) -> F32:
    assert cloud.grid is not None
    return to_grid(values, cloud.grid)


def beam_separation_cosines(grid: ScanGrid) -> tuple[F32, F32]:
    """cos of the angle between neighbouring beams: along samples (scalar, as a (1, 1) array)
    and along profiles ``(P, S)`` (row p: profile p and p + 1).

    From the grid's angles with the paper's geometry: adjacent profiles are Δβ apart about the
    axis, so their beams at beam angle α meet at ``cos Δ = cos²α + sin²α cos Δβ``. A tilted
    mount changes this by far less than the edge criterion cares about.
    """
    alpha = np.radians(np.nan_to_num(grid.alpha_deg, nan=0.0))
    step = grid.alpha_step_deg
    along_samples = np.full((1, 1), np.cos(np.radians(step if np.isfinite(step) else 0.0)),
                            np.float32)
    d_beta = np.radians(np.nan_to_num(np.diff(grid.beta_deg), nan=0.0))
    d_beta = np.concatenate([d_beta, [0.0]])
    cos2 = np.cos(alpha) ** 2
    along_profiles = cos2[None, :] + (1.0 - cos2)[None, :] * np.cos(d_beta)[:, None]
    return along_samples, along_profiles.astype(np.float32)


def depth_edge_mask(cloud: Cloud, params: DepthEdgeParams) -> B:
    """Points at depth edges (see the module docstring), as a per-point mask.

    For neighbours at ranges ``r_f > r_n`` with beams Δ apart, the angle φ at the far point
    between its beam and the segment to the near one has ``tan φ = r_n sin Δ / (r_f − r_n cos
    Δ)``: range-image arithmetic, no 3-D vectors.
    """
    assert cloud.grid is not None
    wrap = cloud.grid.wraps_alpha
    ranges = cloud.range_grid()
    tan_limit = np.float32(np.tan(np.radians(params.min_angle_deg)))
    min_jump_sq = np.float32(params.min_jump_m ** 2)
    flagged = np.zeros(ranges.shape, bool)
    cos_samples, cos_profiles = beam_separation_cosines(cloud.grid)
    both = params.remove == "both"
    for dp, ds, cos_sep in ((1, 0, cos_profiles), (0, 1, cos_samples)):
        neighbour = shifted(ranges, dp, ds, wrap_samples=wrap)
        sin_sep = np.sqrt(np.maximum(np.float32(1) - cos_sep * cos_sep, np.float32(0)))
        here_far = ranges > neighbour
        far = np.fmax(ranges, neighbour)
        near = np.fmin(ranges, neighbour)
        across = near * sin_sep
        along = far - near * cos_sep
        jump_sq = across * across + along * along
        with np.errstate(invalid="ignore"):
            edge = (along > 0) & (across < along * tan_limit) & (jump_sq > min_jump_sq)
        edge &= ~np.isnan(neighbour) & ~np.isnan(ranges)
        flagged |= edge & (here_far | both)
        flagged |= shifted(edge & (~here_far | both), -dp, -ds, wrap_samples=wrap, fill=False)
    return from_grid(flagged, cloud.grid)


def grid_median_filter(cloud: Cloud, params: GridMedianParams) -> None:
    """Take isolated points and outliers, or replace ranges by the 3 × 3 median."""
    assert cloud.grid is not None
    ranges = cloud.range_grid()
    median, neighbours = median3x3(ranges, wrap_samples=cloud.grid.wraps_alpha)
    isolated = from_grid(neighbours < params.min_neighbours, cloud.grid)
    if params.action == "remove":
        limit = params.max_deviation_m + params.relative * ranges
        outlier = from_grid(np.abs(ranges - median) > limit, cloud.grid)
        cloud.take("grid_median", isolated | outlier,
                   isolated=int(np.count_nonzero(isolated & cloud.kept)))
    else:
        cloud.take("grid_median", isolated, isolated=int(np.count_nonzero(isolated & cloud.kept)))
        moved = cloud.move_along_beams(median)
        cloud.report["grid_median"]["replaced"] = moved


def _incidence_cosine(cloud: Cloud) -> F32:
    """|cos| of the angle between each beam and the local grid normal (0 where unknown)."""
    assert cloud.grid is not None
    wrap = cloud.grid.wraps_alpha
    xyz = _points_grid(cloud, np.where(cloud.kept[:, None], cloud.xyz, np.float32(np.nan)))
    along_profile = neighbour_differences(xyz, 0)
    along_profile = np.where(np.isnan(along_profile), -neighbour_differences(xyz[::-1], 0)[::-1],
                             along_profile)
    along_sample = neighbour_differences(xyz, 1, wrap_samples=wrap)
    normal = np.cross(along_profile, along_sample)
    beam = xyz - _points_grid(cloud, cloud.origin)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.abs(np.einsum("...k,...k->...", normal, beam)) / (
            np.linalg.norm(normal, axis=-1) * np.linalg.norm(beam, axis=-1))
    return from_grid(np.nan_to_num(cosine, nan=0.0).astype(np.float32), cloud.grid)


def double_coverage_pairs(grid: ScanGrid, tolerance_steps: float) -> tuple[I64, I64]:
    """Flat grid cells seen twice: ``first[i]`` at (α, β), ``second[i]`` at (−α, β + 180°)."""
    beta_step, alpha_step = abs(grid.beta_step_deg), abs(grid.alpha_step_deg)
    if not (np.isfinite(beta_step) and np.isfinite(alpha_step)) or beta_step == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    profiles, samples = grid.shape
    beta = np.where(np.isfinite(grid.beta_deg), grid.beta_deg, np.inf)
    order = np.argsort(beta)
    target = grid.beta_deg + 180.0
    pos = np.clip(np.searchsorted(beta[order], target), 1, profiles - 1) if profiles > 1 else \
        np.zeros(profiles, np.int64)
    candidates = np.stack([order[pos - 1], order[np.minimum(pos, profiles - 1)]])
    gap = np.abs(beta[candidates] - target)
    partner = candidates[np.argmin(gap, axis=0), np.arange(profiles)]
    has_partner = np.min(gap, axis=0) <= tolerance_steps * beta_step
    alpha = grid.alpha_deg
    mirrored = np.mod(-alpha, 360.0)
    alpha0 = np.nanmin(alpha) if np.isfinite(alpha).any() else 0.0
    partner_sample = np.rint(np.mod(mirrored - alpha0, 360.0) / alpha_step).astype(np.int64)
    partner_sample = np.where(partner_sample >= samples, partner_sample - samples, partner_sample)
    in_range = (partner_sample >= 0) & (partner_sample < samples)
    safe = np.clip(partner_sample, 0, samples - 1)
    miss = np.abs((alpha[safe] - mirrored + 180.0) % 360.0 - 180.0)
    sample_ok = in_range & (miss <= tolerance_steps * alpha_step)
    p = np.flatnonzero(has_partner)
    s = np.flatnonzero(sample_ok)
    first = (p[:, None] * samples + s[None, :]).ravel()
    second = (partner[p][:, None] * samples + safe[s][None, :]).ravel()
    return first, second


def double_coverage_filter(cloud: Cloud, params: DoubleCoverageParams) -> None:
    """Keep, merge or choose between the two views of directions seen twice."""
    assert cloud.grid is not None
    first_cell, second_cell = double_coverage_pairs(cloud.grid, params.tolerance_steps)
    index = cloud.grid.index.ravel()
    first, second = index[first_cell], index[second_cell]
    valid = (first >= 0) & (second >= 0) & (first != second)
    first, second = first[valid], second[valid]
    both = cloud.kept[first] & cloud.kept[second]
    first, second = first[both], second[both]
    # A direction pairs with itself when both (p, q) and (q, p) appear: keep one order.
    unique = first < second
    first, second = first[unique], second[unique]
    mask = np.zeros(cloud.taken.size, bool)
    if params.action == "merge":
        cloud.xyz[first] = (cloud.xyz[first] + cloud.xyz[second]) * np.float32(0.5)
        cloud.range_m[first] = np.linalg.norm(cloud.xyz[first] - cloud.origin[first], axis=1)
        cloud.values_changed = True
        mask[second] = True
    elif params.action == "best":
        cosine = _incidence_cosine(cloud)
        second_better = cosine[second] > cosine[first]
        mask[np.where(second_better, first, second)] = True
    cloud.take("double_coverage", mask, pairs=int(first.size), action=params.action)


def statistical_outlier_mask(xyz: F32, params: StatisticalOutlierParams) -> B:
    """Open3D's statistical outlier removal: True for the outliers among ``xyz``."""
    import open3d as o3d

    outliers = np.ones(len(xyz), bool)
    if len(xyz) <= params.neighbours:
        return ~outliers
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz.astype(np.float64)))
    try:
        _, inliers = cloud.remove_statistical_outlier(nb_neighbors=params.neighbours,
                                                      std_ratio=params.std_ratio)
    except RuntimeError as err:
        raise StageError(f"points: statistical outlier removal failed ({err})") from err
    outliers[np.asarray(inliers, dtype=np.int64)] = False
    return outliers


def voxel_representatives(xyz: F32, size_m: float) -> B:
    """One point per voxel of edge ``size_m``: the one nearest its voxel's centroid."""
    chosen = np.zeros(len(xyz), bool)
    if len(xyz) == 0:
        return chosen
    keys = np.floor(xyz.astype(np.float64) / size_m).astype(np.int64)
    _, voxel, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    voxel = voxel.ravel()
    centroid = np.stack([np.bincount(voxel, weights=xyz[:, k].astype(np.float64)) / counts
                         for k in range(3)], axis=1)
    distance = np.linalg.norm(xyz - centroid[voxel], axis=1)
    order = np.lexsort((distance, voxel))
    first = np.concatenate([[True], voxel[order][1:] != voxel[order][:-1]])
    chosen[order[first]] = True
    return chosen


def _column(table: pa.Table, name: str) -> F32:
    values: F32 = table.column(name).to_numpy().astype(np.float32, copy=False)
    return values


def make_cloud(table: pa.Table) -> Cloud:
    """The working state of a points table (earlier ``filtered_by`` marks count as taken)."""
    POINTS.check(table)
    taken = np.zeros(table.num_rows, np.int8)
    if "filtered_by" in table.column_names:
        marked = table.column("filtered_by").is_valid().to_numpy(zero_copy_only=False)
        taken[marked] = FILTER_NAMES.index("previous")
    return Cloud(table=table, range_m=_column(table, "range_m").copy(), grid=scan_grid(table),
                 taken=taken)


def run_filters(cloud: Cloud, params: FilterParams, progress: ProgressFn) -> dict[str, str]:
    """Apply the enabled filters in order; returns the filters skipped and why."""
    skipped: dict[str, str] = {}
    no_grid = "the points have no grid"
    steps = FILTER_NAMES[2:]
    for done, name in enumerate(steps):
        progress("filter", done, len(steps))
        settings = getattr(params, name)
        if not settings.enabled:
            continue
        if name == "no_return":
            cloud.take(name, ~(np.isfinite(cloud.range_m) & cloud.finite))
        elif name == "range_gate":
            low, high, source = range_gate_bounds(cloud.table, settings)
            if low is None and high is None:
                skipped[name] = source
                continue
            mask = np.zeros(cloud.taken.size, bool)
            if low is not None:
                mask |= cloud.range_m < low
            if high is not None:
                mask |= cloud.range_m > high
            cloud.take(name, mask, min_range_m=low, max_range_m=high, source=source)
        elif name == "statistical_outlier":
            if cloud.grid is not None and not settings.with_grid:
                skipped[name] = "the points have a grid (set statistical_outlier.with_grid)"
                continue
            kept = np.flatnonzero(cloud.kept & cloud.finite)
            mask = np.zeros(cloud.taken.size, bool)
            mask[kept] = statistical_outlier_mask(cloud.xyz[kept], settings)
            cloud.take(name, mask)
        elif name == "voxel":
            kept = np.flatnonzero(cloud.kept & cloud.finite)  # no voxel for a no-return
            mask = cloud.finite.copy()
            mask[kept[voxel_representatives(cloud.xyz[kept], settings.size_m)]] = False
            cloud.take(name, mask, size_m=settings.size_m)
        elif cloud.grid is None:
            skipped[name] = no_grid
        elif name == "depth_edges":
            cloud.take(name, depth_edge_mask(cloud, settings))
        elif name == "grid_median":
            grid_median_filter(cloud, settings)
        elif name == "smoothing":
            smoothed = cloud.range_grid()
            for _ in range(settings.iterations):
                smoothed = bilateral_smooth(smoothed, settings.radius, settings.sigma_cells,
                                            settings.sigma_range_m, settings.relative,
                                            wrap_samples=cloud.grid.wraps_alpha)
            cloud.report[name] = {"taken": 0, "moved": cloud.move_along_beams(smoothed)}
        elif name == "double_coverage":
            double_coverage_filter(cloud, settings)
    progress("filter", len(steps), len(steps))
    return skipped


def range_gate_bounds(table: pa.Table, gate: RangeGateParams
                      ) -> tuple[float | None, float | None, str]:
    """The range gate's ``(min, max, where they come from)``: the parameters where set, else
    the scanner's limits from the points' metadata; None where neither says."""
    import json

    raw = (table.schema.metadata or {}).get(SCANNER_RANGE_KEY)
    scanner: list[float | None] = [None, None]
    if raw is not None:
        try:
            scanner = [None if v is None else float(v) for v in json.loads(raw)][:2]
        except (ValueError, TypeError):
            scanner = [None, None]
    low = gate.min_range_m if gate.min_range_m is not None else scanner[0]
    high = gate.max_range_m if gate.max_range_m is not None else scanner[1]
    if raw is None and (gate.min_range_m is None or gate.max_range_m is None):
        if low is None and high is None:
            return None, None, ("the points carry no scanner range (not from assemble); set "
                                "range_gate.min_range_m / max_range_m")
        return low, high, "parameters (the points carry no scanner range for the other bound)"
    if gate.min_range_m is None or gate.max_range_m is None:
        return low, high, "the scanner's range (rig)" + (
            " and parameters" if gate.min_range_m is not None or gate.max_range_m is not None
            else "")
    return low, high, "parameters"


def taken_share_warnings(report: Mapping[str, Any], points_in: int, share: float) -> list[str]:
    """One warning per filter that took more than ``share`` of the points."""
    warnings = []
    for name, entry in report.items():
        taken = int(entry.get("taken", 0)) if isinstance(entry, Mapping) else 0
        if points_in and taken > share * points_in:
            extra = ""
            if name == "range_gate":
                extra = (f" (kept {entry.get('min_range_m')} to {entry.get('max_range_m')} m "
                         f"from {entry.get('source')})")
            warnings.append(f"filter {name} took {taken / points_in:.0%} of the points "
                            f"({taken} of {points_in}; warn_taken_share {share:g}){extra}")
    return warnings


def filtered_table(table: pa.Table, cloud: Cloud, mode: str) -> pa.Table:
    """The output table: changed values written back, then rows removed or marked."""
    if cloud.values_changed:
        for k, name in enumerate("xyz"):
            table = table.set_column(table.schema.get_field_index(name), name,
                                     pa.array(np.ascontiguousarray(cloud.xyz[:, k])))
        table = table.set_column(table.schema.get_field_index("range_m"), "range_m",
                                 pa.array(cloud.range_m))
    if mode == "remove":
        table = table.filter(pa.array(cloud.kept))
        if "filtered_by" in table.column_names:
            table = table.drop_columns(["filtered_by"])
        return table
    codes = cloud.taken.astype(np.int32)
    names = pa.DictionaryArray.from_arrays(pa.array(codes, mask=codes == 0),
                                           pa.array(FILTER_NAMES, pa.string())).cast(pa.string())
    if "filtered_by" in table.column_names:
        earlier = table.column("filtered_by").combine_chunks()
        names = pa.array(np.where(codes == FILTER_NAMES.index("previous"),
                                  earlier.to_numpy(zero_copy_only=False),
                                  names.to_numpy(zero_copy_only=False)), pa.string())
        return table.set_column(table.schema.get_field_index("filtered_by"), "filtered_by",
                                names)
    return table.append_column("filtered_by", names)


def filter_stage(inputs: Mapping[str, Any], params: FilterParams,
                  progress: ProgressFn) -> StageResult:
    """The filter stage: ``points`` → ``points`` with fewer (or marked) points."""
    table: pa.Table = inputs["points"]
    cloud = make_cloud(table)
    previous = int(np.count_nonzero(~cloud.kept))
    skipped = run_filters(cloud, params, progress)
    out = filtered_table(table, cloud, params.mode)
    grid = cloud.grid
    report = {
        "mode": params.mode,
        "points_in": table.num_rows,
        "points_out": out.num_rows,
        "kept": int(np.count_nonzero(cloud.kept)),
        "previously_marked": previous,
        "grid": None if grid is None else {"profiles": grid.shape[0], "samples": grid.shape[1]},
        "filters": cloud.report,
        "skipped": skipped,
        "warnings": taken_share_warnings(cloud.report, table.num_rows, params.warn_taken_share),
    }
    if "range_gate" in skipped and params.range_gate.enabled:
        report["warnings"].append(f"filter range_gate not applied: {skipped['range_gate']}")
    return StageResult(tables={"points": out}, report=report)


STAGE = Stage(
    name="filter",
    version=2,
    params=FilterParams,
    inputs=("points",),
    outputs=("points",),
    func=filter_stage,
    description="range gate, no-returns, depth edges, grid median, smoothing, double coverage, "
                "statistical outliers, voxels: mark or remove",
    libraries=("numpy", "pyarrow", "open3d"),
)
