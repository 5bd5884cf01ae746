"""Triangulate an organized scan: each grid quad becomes two triangles, unless it spans a jump.

The scan is a grid of profiles (β) × samples (α). Neighbouring samples of adjacent profiles form
quads; a quad's two triangles use the diagonal with the smaller range difference, so that one
missing corner still leaves a triangle. An edge is a depth discontinuity when the ranges at its
ends differ by more than a surface inclined at ``max_incidence_deg`` to the line of sight could
explain, plus ``jump_allowance_m`` for noise; a triangle with such an edge is dropped.

The grid closes on itself: samples wrap when the profile spans 360°, and a 360° profile turned
through 180° returns to where it started mirrored — the profile at β₀ + 180° is the first
profile with α → 360° − α. So the last profile is joined to the first one mirrored (the seam), and
profiles at β ≥ β₀ + 180° (a second, duplicate coverage half) are left out, so that no surface is
meshed twice. The samples on the axis (α = 0°, 180°) are the same point in every profile: they are
merged into one vertex per pole, where the quads around the pole become a fan.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.grid import ScanGrid
from scanpipe.params import Params

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
I32 = NDArray[np.int32]
B = NDArray[np.bool_]

#: A sample is on the axis when |sin α| is below this (α within ~0.06° of 0° or 180°).
_POLE_SINE = 1e-3


class GridMeshParams(Params):
    """Triangulation of the organized grid."""

    max_incidence_deg: float = Field(
        85.0, gt=0, lt=90,
        description="steepest incidence angle of a surface still meshed across a range step")
    jump_allowance_m: float = Field(
        0.03, ge=0, description="range difference always allowed between neighbours (noise)")
    close_seam: bool = Field(True, description="join the last profile to the first, mirrored")
    merge_poles: bool = Field(True, description="merge the samples on the axis into one vertex")
    fill_single_holes: bool = Field(
        True, description="close the hole a lone missing sample (a dropout) leaves in a surface")
    stride: int = Field(
        0, ge=0, le=16,
        description="mesh every n-th profile and sample (0 = the smallest that keeps the "
                    "vertices within max_vertices)")
    max_vertices: int = Field(
        1_500_000, ge=1000,
        description="with stride 0: the most grid points meshed (texture and export time "
                    "grow with the face count)")

    def stride_for(self, points: int) -> int:
        """The stride to mesh ``points`` grid points with."""
        if self.stride:
            return self.stride
        return max(1, math.ceil(math.sqrt(points / self.max_vertices)))


def _extended_rows(grid: ScanGrid, params: GridMeshParams) -> tuple[I64, dict[str, Any]]:
    """The index grid of one coverage half, with the seam row appended when it closes."""
    index = grid.index
    beta = grid.beta_deg
    step = abs(grid.beta_step_deg)
    report: dict[str, Any] = {"duplicate_profiles_dropped": 0, "seam_closed": False}
    finite = np.flatnonzero(np.isfinite(beta))
    if finite.size < 2 or not np.isfinite(step) or step == 0:
        return index, report
    beta0 = beta[finite[0]]
    relative = np.abs(beta - beta0)
    in_half = np.flatnonzero(np.isfinite(beta) & (relative < 180.0 - 0.5 * step))
    last = int(in_half.max())
    report["duplicate_profiles_dropped"] = int(
        np.count_nonzero(np.isfinite(beta[last + 1:])))
    rows = index[: last + 1]
    gap_to_half_turn = abs(relative[last] + step - 180.0)
    if params.close_seam and grid.wraps_alpha and gap_to_half_turn <= 0.75 * step:
        mirror = _mirror_samples(grid.alpha_deg, abs(grid.alpha_step_deg))
        seam = np.where(mirror >= 0, index[0, np.maximum(mirror, 0)], -1)
        rows = np.vstack([rows, seam[None, :]])
        report["seam_closed"] = True
    return rows, report


def _mirror_samples(alpha_deg: NDArray[np.float64], step_deg: float) -> I64:
    """For each sample, the sample at 360° − α (−1 when none lies within half a step)."""
    target = np.mod(360.0 - alpha_deg, 360.0)
    diff = np.mod(alpha_deg[None, :] - target[:, None] + 180.0, 360.0) - 180.0
    diff = np.nan_to_num(np.abs(diff), nan=np.inf)
    nearest = np.argmin(diff, axis=1)
    ok = diff[np.arange(len(target)), nearest] <= 0.5 * step_deg + 1e-6
    return np.where(ok, nearest, -1).astype(np.int64)


def _merge_poles(rows: I64, grid: ScanGrid, vertices: F32, allowance_m: float) -> int:
    """Point every grid cell on the axis at one vertex per pole; returns how many merged."""
    alpha = np.nan_to_num(grid.alpha_deg, nan=90.0)
    merged = 0
    for column in np.flatnonzero(np.abs(np.sin(np.radians(alpha))) < _POLE_SINE):
        cells = rows[:, column]
        members = np.unique(cells[cells >= 0])
        if members.size < 2:
            continue
        centre = vertices[members].mean(axis=0)
        # Merge only when the points really coincide (a mounted offset moves them apart).
        if np.linalg.norm(vertices[members] - centre, axis=1).max() > max(allowance_m, 1e-6):
            continue
        vertices[members[0]] = centre
        rows[cells >= 0, column] = members[0]
        merged += members.size - 1
    return merged


def _continuous(r_i: F32, r_j: F32, u_i: F32, u_j: F32, tan_incidence: float,
                allowance_m: float) -> B:
    """True where the edge between two grid cells lies on one surface (False across jumps)."""
    chord = np.linalg.norm(u_i - u_j, axis=-1)  # ≈ the angle between the two rays, radians
    limit = np.fmin(r_i, r_j) * chord * tan_incidence + allowance_m
    with np.errstate(invalid="ignore"):
        return np.asarray(np.abs(r_i - r_j) <= limit)


def triangulate_grid(points: F32, origins: F32, grid: ScanGrid,
                     params: GridMeshParams | None = None) -> tuple[F32, I32, dict[str, Any]]:
    """Triangles over the grid: ``(vertices (N, 3), faces (K, 3), report)``.

    ``vertices`` are the points in table order (pole points moved to their pole's centre);
    ``faces`` index into them, wound counter-clockwise as seen from the sensor.
    """
    params = params or GridMeshParams()
    vertices = np.array(points, dtype=np.float32, copy=True)
    rows, report = _extended_rows(grid, params)
    rows = rows.copy()
    report["pole_points_merged"] = (
        _merge_poles(rows, grid, vertices, params.jump_allowance_m) if params.merge_poles else 0)
    if grid.wraps_alpha:
        rows = np.hstack([rows, rows[:, :1]])
    rows = rows.astype(np.int32)

    rays = vertices - origins
    ranges = np.linalg.norm(rays, axis=1).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        units = (rays / ranges[:, None]).astype(np.float32)
    # One padding entry (NaN) so that index −1 reads as "no point".
    r_pad = np.append(ranges, np.float32(np.nan))
    u_pad = np.vstack([units, np.full((1, 3), np.nan, np.float32)])
    r_grid = r_pad[rows]
    u_grid = u_pad[rows]

    tan_inc = float(np.tan(np.radians(params.max_incidence_deg)))
    allow = params.jump_allowance_m

    def ok(rs: tuple[slice, slice], rt: tuple[slice, slice]) -> B:
        return _continuous(r_grid[rs], r_grid[rt], u_grid[rs], u_grid[rt], tan_inc, allow)

    top, bottom, left, right, every = slice(None, -1), slice(1, None), slice(None, -1), \
        slice(1, None), slice(None)
    along_profile = ok((top, every), (bottom, every))  # (p, s)–(p+1, s)
    along_sample = ok((every, left), (every, right))  # (p, s)–(p, s+1)
    e_ab, e_cd = along_profile[:, :-1], along_profile[:, 1:]
    e_ac, e_bd = along_sample[:-1, :], along_sample[1:, :]
    e_ad = ok((top, left), (bottom, right))
    e_bc = ok((bottom, left), (top, right))

    a, b, c, d = rows[:-1, :-1], rows[1:, :-1], rows[:-1, 1:], rows[1:, 1:]
    step_ad = np.abs(r_grid[:-1, :-1] - r_grid[1:, 1:])
    step_bc = np.abs(r_grid[1:, :-1] - r_grid[:-1, 1:])
    with np.errstate(invalid="ignore"):
        use_ad = np.where(e_ad & e_bc, step_ad <= step_bc, e_ad)

    first = np.where(use_ad, e_ab & e_bd & e_ad, e_ab & e_bc & e_ac)
    second = np.where(use_ad, e_ad & e_cd & e_ac, e_bd & e_cd & e_bc)
    # Every triangle below runs counter-clockwise in (β, α); seen from the sensor that is
    # clockwise where sin α > 0 (the Jacobian of (β, α) → ray direction has the sign of sin α),
    # so those triangles are reversed to face the sensor.
    alpha = np.nan_to_num(grid.alpha_deg, nan=0.0)
    alpha_mid = alpha + 0.5 * (grid.alpha_step_deg if np.isfinite(grid.alpha_step_deg) else 0)
    # Quad column s spans samples s and s + 1 (S − 1 and 0 when the samples wrap). Angles
    # that fall with the index (a motor turning backwards) mirror (β, α) and so the rule.
    mirrored = (grid.alpha_step_deg < 0) != (grid.beta_step_deg < 0)
    flip = (np.sin(np.radians(alpha_mid)) > 0) != mirrored
    reverse = np.broadcast_to(flip[None, : a.shape[1]], a.shape)
    corner_1 = np.where(use_ad, d, c)
    corner_0 = np.where(use_ad, a, b)
    faces = np.concatenate([
        np.stack([np.where(reverse, corner_1, a), b, np.where(reverse, a, corner_1)],
                 axis=-1)[first],
        np.stack([np.where(reverse, c, corner_0), d, np.where(reverse, corner_0, c)],
                 axis=-1)[second],
    ])
    valid = rows >= 0
    va, vb, vc, vd = valid[:-1, :-1], valid[1:, :-1], valid[:-1, 1:], valid[1:, 1:]
    could_1 = np.where(use_ad, va & vb & vd, va & vb & vc)
    could_2 = np.where(use_ad, va & vd & vc, vb & vd & vc)
    report["faces_broken_at_jumps"] = int(np.count_nonzero(could_1 & ~first)
                                          + np.count_nonzero(could_2 & ~second))

    sensor_moves = bool(np.ptp(origins, axis=0).max() > 0) if len(origins) else False
    if sensor_moves:
        # A mounted offset moves the sensor with β; near the axis that offset is no longer
        # small against the point spacing and the (β, α) winding rule can be wrong: there
        # the winding is checked against the actual sensor position.
        near_axis = np.broadcast_to(
            (np.abs(np.sin(np.radians(alpha_mid))) < 0.3)[None, : a.shape[1]], a.shape)
        check = np.flatnonzero(np.concatenate([near_axis[first], near_axis[second]]))
        faces[check] = _face_sensor(vertices, origins, faces[check])

    if params.fill_single_holes:
        patches = _single_sample_holes(rows, r_grid, u_grid, tan_inc, allow)
        report["single_holes_filled"] = len(patches) // 2
        faces = np.concatenate([faces, _face_sensor(vertices, origins, patches)])

    merged_corner = ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
                     | (faces[:, 0] == faces[:, 2]))
    faces = faces[~merged_corner]
    report["grid_faces"] = len(faces)
    return vertices, faces, report


def _single_sample_holes(rows: NDArray[np.integer[Any]], r_grid: F32, u_grid: F32,
                         tan_incidence: float, allowance_m: float) -> I32:
    """Two triangles over every missing sample whose four neighbours lie on one surface.

    Each of the four quads around a missing sample keeps the triangle opposite it, so a dropout
    leaves a diamond-shaped hole bounded by its four neighbours; this closes it.
    """
    up, down = (slice(None, -2), slice(1, -1)), (slice(2, None), slice(1, -1))
    left, right = (slice(1, -1), slice(None, -2)), (slice(1, -1), slice(2, None))

    def ok(i: tuple[slice, slice], j: tuple[slice, slice]) -> B:
        return _continuous(r_grid[i], r_grid[j], u_grid[i], u_grid[j], tan_incidence,
                           allowance_m)

    hole = rows[1:-1, 1:-1] < 0
    for side in (up, down, left, right):
        hole &= rows[side] >= 0
    hole &= ok(up, left) & ok(left, down) & ok(down, right) & ok(right, up) & ok(up, down)
    u, d, lt, rt = (rows[side][hole] for side in (up, down, left, right))
    return np.concatenate([np.stack([u, lt, d], 1), np.stack([u, d, rt], 1)]).astype(np.int32)


def _face_sensor(vertices: F32, origins: F32, faces: I32) -> I32:
    """``faces`` with the winding reversed where the normal points away from the sensor."""
    v0 = vertices[faces[:, 0]]
    normal = np.cross(vertices[faces[:, 1]] - v0, vertices[faces[:, 2]] - v0)
    away = np.einsum("ij,ij->i", normal, origins[faces[:, 0]] - v0) < 0
    out = faces.copy()
    out[away] = out[away][:, ::-1]
    return out
