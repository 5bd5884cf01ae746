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
from collections.abc import Sequence
from dataclasses import dataclass
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
        1, ge=0, le=16,
        description="mesh every n-th profile and sample: 1 = every kept point (full "
                    "resolution); 0 = the smallest stride that keeps the vertices within "
                    "max_vertices")
    max_vertices: int = Field(
        1_500_000, ge=1000,
        description="with stride 0 only: the most grid points meshed (texture and export "
                    "time grow with the face count)")

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
    """For each sample, the sample at 360° − α (−1 when none lies within half a step).

    The nearest of the two sorted neighbours of each target (a binary search, not an S × S
    table); on a tie the lower sample index, as a scan in index order would find.
    """
    out = np.full(len(alpha_deg), -1, dtype=np.int64)
    finite = np.flatnonzero(np.isfinite(alpha_deg))
    if finite.size == 0:
        return out
    angles = np.mod(alpha_deg[finite], 360.0)
    order = np.argsort(angles, kind="stable")
    ordered = angles[order]
    target = np.mod(360.0 - alpha_deg, 360.0)
    above = np.searchsorted(ordered, np.nan_to_num(target, nan=0.0)) % finite.size
    below = (above - 1) % finite.size

    def gap(at: NDArray[np.int64]) -> NDArray[np.float64]:
        return np.abs(np.mod(ordered[at] - target + 180.0, 360.0) - 180.0)

    gap_above, gap_below = gap(above), gap(below)
    index_above, index_below = finite[order[above]], finite[order[below]]
    take_below = (gap_below < gap_above) | ((gap_below == gap_above)
                                            & (index_below < index_above))
    nearest = np.where(take_below, index_below, index_above)
    distance = np.where(take_below, gap_below, gap_above)
    ok = distance <= 0.5 * step_deg + 1e-6  # False for a NaN target
    out[ok] = nearest[ok]
    return out


def _merge_poles(rows: I32, grid: ScanGrid, vertices: F32, allowance_m: float) -> int:
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


def _continuous(r_i: F32, r_j: F32, u_i: Sequence[F32], u_j: Sequence[F32],
                tan_incidence: float, allowance_m: float) -> tuple[B, F32]:
    """Where the edge between two grid cells lies on one surface (False across jumps), and the
    range step ``|r_i − r_j|``.

    ``u_i``, ``u_j`` are the x, y and z planes (or 1-D arrays) of the unit rays; the chord
    between them is ≈ the angle between the rays, in radians.
    """
    chord = np.subtract(u_i[0], u_j[0])
    chord *= chord
    term = np.empty_like(chord)
    for k in (1, 2):
        np.subtract(u_i[k], u_j[k], out=term)
        term *= term
        chord += term
    np.sqrt(chord, out=chord)
    limit = np.minimum(r_i, r_j, out=term)
    limit *= chord
    limit *= np.float32(tan_incidence)
    limit += np.float32(allowance_m)
    step = np.subtract(r_i, r_j, out=chord)
    np.abs(step, out=step)
    with np.errstate(invalid="ignore"):
        return np.less_equal(step, limit), step


@dataclass(frozen=True)
class GridSurface:
    """The triangles over a grid, optionally already cleaned and compacted."""

    #: ``(M, 3)`` the vertices: the points in table order (pole points moved to their pole's
    #: centre), only those ``kept`` when compacted.
    vertices: F32
    #: ``(K, 3)`` indices into ``vertices``, counter-clockwise as seen from the sensor.
    faces: I32
    report: dict[str, Any]
    #: ``(N,)`` which points are vertices (None: all of them, in order).
    kept: B | None = None


def triangulate_grid(points: F32, origins: F32, grid: ScanGrid,
                     params: GridMeshParams | None = None) -> tuple[F32, I32, dict[str, Any]]:
    """Triangles over the grid: ``(vertices (N, 3), faces (K, 3), report)``.

    ``vertices`` are the points in table order (pole points moved to their pole's centre);
    ``faces`` index into them, wound counter-clockwise as seen from the sensor.
    """
    surface = grid_surface(points, origins, grid, params)
    return surface.vertices, surface.faces, surface.report


def _index_rows(grid: ScanGrid, params: GridMeshParams,
                vertices: F32) -> tuple[I32, dict[str, Any]]:
    """The int32 index grid that is meshed: one coverage half, the seam row, the poles merged
    and, when the samples wrap, column 0 repeated at the end."""
    extended, report = _extended_rows(grid, params)
    height, width = extended.shape
    rows = np.empty((height, width + 1 if grid.wraps_alpha else width), dtype=np.int32)
    rows[:, :width] = extended
    report["pole_points_merged"] = (
        _merge_poles(rows[:, :width], grid, vertices, params.jump_allowance_m)
        if params.merge_poles else 0)
    if grid.wraps_alpha:
        rows[:, width] = rows[:, 0]
    return rows, report


def _ray_planes(vertices: F32, origins: F32, rows: I32) -> tuple[F32, tuple[F32, F32, F32]]:
    """Range and unit-ray planes over ``rows`` (NaN where a cell holds no point).

    The differences are gathered once into the grid (index −1 reads a NaN pad entry) and the
    range and unit rays computed there, in float32.
    """
    n = len(vertices)
    planes = []
    for k in range(3):
        padded = np.empty(n + 1, dtype=np.float32)
        np.subtract(vertices[:, k], origins[:, k], out=padded[:n])
        padded[n] = np.nan
        planes.append(np.take(padded, rows))
    ranges = planes[0] * planes[0]
    for k in (1, 2):
        ranges += planes[k] * planes[k]
    np.sqrt(ranges, out=ranges)
    with np.errstate(invalid="ignore", divide="ignore"):
        for plane in planes:
            plane /= ranges
    return ranges, (planes[0], planes[1], planes[2])


def grid_surface(points: F32, origins: F32, grid: ScanGrid,
                 params: GridMeshParams | None = None, min_component_faces: int = 0,
                 compact: bool = False, remove_zero_area: bool = False) -> GridSurface:
    """:func:`triangulate_grid`, and optionally its clean-up done on the grid.

    In the order of the generic clean-up: ``remove_zero_area`` drops faces without area;
    ``min_component_faces`` > 1 drops connected pieces with fewer faces; ``compact`` drops the
    points no face uses (``kept`` says which stay). Every step works on
    whole (profile × sample) planes: a cell's neighbours are the next row and column, never a
    search; faces are written once, from the final masks, with their final vertex numbers, so
    the clean-up needs no per-face gathers.
    """
    params = params or GridMeshParams()
    vertices = np.array(points, dtype=np.float32, copy=True)
    rows, report = _index_rows(grid, params, vertices)
    r_grid, u_grid = _ray_planes(vertices, origins, rows)
    tan_inc = float(np.tan(np.radians(params.max_incidence_deg)))
    allow = params.jump_allowance_m

    def ok(i: tuple[slice, slice], j: tuple[slice, slice]) -> tuple[B, F32]:
        return _continuous(r_grid[i], r_grid[j], [u[i] for u in u_grid],
                           [u[j] for u in u_grid], tan_inc, allow)

    head, tail, every = slice(None, -1), slice(1, None), slice(None)
    along_profile, _ = ok((head, every), (tail, every))  # (p, s)–(p+1, s)
    along_sample, _ = ok((every, head), (every, tail))  # (p, s)–(p, s+1)
    e_ab, e_cd = along_profile[:, :-1], along_profile[:, 1:]
    e_ac, e_bd = along_sample[:-1, :], along_sample[1:, :]
    e_ad, step_ad = ok((head, head), (tail, tail))
    e_bc, step_bc = ok((tail, head), (head, tail))
    del along_profile, along_sample

    quad = _Quads(rows)
    # The diagonal with the smaller range step, where both are continuous.
    with np.errstate(invalid="ignore"):
        use_ad = np.less_equal(step_ad, step_bc)
    del step_ad, step_bc
    use_ad |= ~e_bc
    use_ad &= e_ad
    # Choices between masks as bitwise logic: np.where on a noise-driven mask branches.
    use_bc = ~use_ad
    first = _choose(use_ad, e_ad & e_bd, use_bc, e_bc & e_ac)
    first &= e_ab
    second = _choose(use_ad, e_ad & e_ac, use_bc, e_bd & e_bc)
    second &= e_cd
    del e_ab, e_cd, e_ac, e_bd, e_ad, e_bc
    valid = rows >= 0
    va, vb, vc, vd = valid[:-1, :-1], valid[1:, :-1], valid[:-1, 1:], valid[1:, 1:]
    could_1 = va & vb & _choose(use_ad, vd, use_bc, vc)
    could_2 = vd & vc & _choose(use_ad, va, use_bc, vb)
    del use_bc
    report["faces_broken_at_jumps"] = int(np.count_nonzero(could_1 & ~first)
                                          + np.count_nonzero(could_2 & ~second))
    del valid, could_1, could_2
    _drop_repeated_corners(first, second, use_ad, quad, grid, report)

    # Every triangle runs counter-clockwise in (β, α); seen from the sensor that is clockwise
    # where sin α > 0 (the Jacobian of (β, α) → ray direction has the sign of sin α), so
    # those triangles are reversed to face the sensor. Quad column s spans samples s and
    # s + 1 (S − 1 and 0 when the samples wrap). Angles that fall with the index (a motor
    # turning backwards) mirror (β, α) and so the rule.
    alpha = np.nan_to_num(grid.alpha_deg, nan=0.0)
    alpha_mid = alpha + 0.5 * (grid.alpha_step_deg if np.isfinite(grid.alpha_step_deg) else 0)
    mirrored = (grid.alpha_step_deg < 0) != (grid.beta_step_deg < 0)
    flip_column = (np.sin(np.radians(alpha_mid)) > 0) != mirrored
    shape = first.shape
    reverse = np.broadcast_to(flip_column[None, : shape[1]], shape)

    patches = np.empty((0, 3), dtype=np.int32)
    if params.fill_single_holes:
        patches = _single_sample_holes(rows, r_grid, u_grid, tan_inc, allow)
        report["single_holes_filled"] = len(patches) // 2
        patches = patches[(patches[:, 0] != patches[:, 1]) & (patches[:, 1] != patches[:, 2])
                          & (patches[:, 0] != patches[:, 2])]
        patches = _face_sensor(vertices, origins, patches)

    kept: B | None = None
    if remove_zero_area:
        if _may_have_flat_faces(grid, rows, vertices, r_grid):
            removed, patch_kept = _drop_zero_area(first, second, use_ad, reverse, quad,
                                                  vertices, patches)
            report["zero_area_faces_removed"] = removed
            patches = patches[patch_kept]
        else:
            report["zero_area_faces_removed"] = 0
    if min_component_faces > 1:
        removed, patch_kept = _drop_small_components(
            first, second, use_ad, rows, patches, len(vertices), min_component_faces)
        report["small_component_faces_removed"] = removed
        patches = patches[patch_kept]
    sensor_moves = any(_varies(origins[:, k]) for k in range(3))
    if compact:
        kept, rows, patches = _compact(first, second, use_ad, rows, patches, len(vertices))
        report["unreferenced_vertices_removed"] = len(vertices) - int(np.count_nonzero(kept))
        if report["unreferenced_vertices_removed"]:
            # np.compress along axis 0: a boolean index of an (N, 3) array is ~4× slower.
            vertices = np.compress(kept, vertices, axis=0)
            if sensor_moves:  # only the winding check below needs them
                origins = np.compress(kept, origins, axis=0)
            quad = _Quads(rows)
        else:
            kept = None

    # The patches go into the same array: appending them would copy every face again.
    faces = _faces_from_quads(first, second, use_ad, reverse, quad, patches)

    if sensor_moves:
        # A mounted offset moves the sensor with β; near the axis that offset is no longer
        # small against the point spacing and the (β, α) winding rule can be wrong: there
        # the winding is checked against the actual sensor position.
        near_axis = np.broadcast_to(
            (np.abs(np.sin(np.radians(alpha_mid))) < 0.3)[None, : shape[1]], shape)
        check = np.flatnonzero(np.concatenate([near_axis[first], near_axis[second]]))
        # Only the (few) faces found facing away are rewritten, not every checked one.
        flip = check[_facing_away(vertices, origins, faces[check])]
        faces[flip] = faces[flip][:, ::-1]
    report["grid_faces"] = len(faces)
    return GridSurface(vertices, faces, report, kept)


class _Quads:
    """The four corner views of every grid quad: a = (p, s), b = (p+1, s), c = (p, s+1),
    d = (p+1, s+1) of an index (or label) grid."""

    def __init__(self, grid: NDArray[Any]) -> None:
        self.a, self.b = grid[:-1, :-1], grid[1:, :-1]
        self.c, self.d = grid[:-1, 1:], grid[1:, 1:]


def _blend(x: NDArray[Any], y: NDArray[Any], flag: B) -> NDArray[Any]:
    """``y`` where ``flag`` else ``x``, as integer arithmetic (``x + (y − x)·flag``): no
    branches on a noise-driven mask, ~5× faster than ``np.where``."""
    out: NDArray[Any] = np.subtract(y, x)
    out *= flag
    out += x
    return out


def _choose(flag: B, if_set: B, flag_clear: B, if_clear: B) -> B:
    """``if_set`` where ``flag`` else ``if_clear`` (``flag_clear`` = ~``flag``), bitwise."""
    out = np.bitwise_and(flag, if_set)
    out |= flag_clear & if_clear
    return out


def _triangle_corners(quad: _Quads, use_ad: B) -> tuple[tuple[Any, Any, Any],
                                                        tuple[Any, Any, Any]]:
    """The corners of the first triangle (a, b, d | c) and the second (c, d, a | b), unwound."""
    return ((quad.a, quad.b, _blend(quad.c, quad.d, use_ad)),
            (quad.c, quad.d, _blend(quad.b, quad.a, use_ad)))


def _may_have_flat_faces(grid: ScanGrid, rows: I32, vertices: F32, r_grid: F32) -> bool:
    """Whether a zero-area triangle can occur: only from points that coincide or rays that
    repeat. A triangle spans two scan planes (two profiles); three distinct points on one
    line would need the one in the other plane on the planes' intersection, which measured
    points do not hit. So: repeated profile or sample angles, a zero range, or unmerged pole
    points that coincide."""
    with np.errstate(invalid="ignore"):
        if np.any(r_grid < 1e-6):  # points at the sensor
            return True
    for angles in (grid.beta_deg, grid.alpha_deg):
        finite = angles[np.isfinite(angles)]
        if finite.size > 1 and np.any(np.diff(finite) == 0):
            return True
    alpha = np.nan_to_num(grid.alpha_deg, nan=90.0)
    for column in np.flatnonzero(np.abs(np.sin(np.radians(alpha))) < _POLE_SINE):
        cells = rows[:, column]
        members = vertices[np.unique(cells[cells >= 0])]
        # Within a micrometre: a float32 cross product of such a sliver underflows to zero.
        if len(members) > 1 and np.any(np.abs(members[1:] - members[:-1]).max(axis=1) < 1e-6):
            return True
    return False


def _drop_zero_area(first: B, second: B, use_ad: B, reverse: B, quad: _Quads,
                    vertices: F32, patches: I32) -> tuple[int, B]:
    """Clear (in place) the triangles with zero area (or NaN corners); returns how many, and
    which ``patches`` stay.

    Per face (gathers), with the corners in their final winding (a sliver's float32 area can
    round to zero from one corner and not from another): only run when
    :func:`_may_have_flat_faces` says it can matter.
    """
    from scanpipe.meshing.mesh import face_cross

    def flat(faces: I32) -> B:
        cross = face_cross(vertices, faces)
        return np.asarray(~(np.einsum("ij,ij->i", cross, cross) > 0))

    removed = 0
    both = _faces_from_quads(first, second, use_ad, reverse, quad)
    zero = flat(both)
    for chosen, part in ((first, zero[: int(np.count_nonzero(first))]),
                         (second, zero[int(np.count_nonzero(first)):])):
        where = np.flatnonzero(chosen)
        removed += int(np.count_nonzero(part))
        chosen.reshape(-1)[where[part]] = False
    patch_zero = flat(patches)
    return removed + int(np.count_nonzero(patch_zero)), ~patch_zero


def _drop_small_components(first: B, second: B, use_ad: B, rows: I32, patches: I32,
                           n_vertices: int, min_faces: int) -> tuple[int, B]:
    """Clear (in place) the triangles of connected pieces with fewer than ``min_faces`` faces;
    returns how many, and which ``patches`` stay.

    Quads that keep both triangles connect their four corners, and 4-connected runs of them
    are one piece already (``scipy.ndimage.label``): only the face edges between two such
    groups go into the graph search, over the groups those edges touch (a few per cent of
    the vertices). Faces are counted per region and per lone triangle, never gathered per
    face; the per-cell piece planes are built only when some piece is small.
    """
    from scipy.ndimage import label

    full_quads = first & second
    full_labels, count = label(full_quads)
    # Group per vertex: its full region's label if it is the a corner of a full quad, else
    # its own; the last entry is the pad read by index −1 (cells without a point).
    groups = np.arange(count + 1, count + 2 + n_vertices, dtype=np.int32)
    full = full_labels > 0
    groups[rows[:-1, :-1][full]] = full_labels[full]
    del full
    group_plane = np.take(groups, rows)
    group_quad = _Quads(group_plane)
    edges_from, edges_to = [], []
    for chosen, corners in zip((first, second), _triangle_corners(group_quad, use_ad),
                               strict=True):
        for i, j in ((0, 1), (1, 2)):
            between = corners[i] != corners[j]
            between &= chosen
            edges_from.append(corners[i][between])
            edges_to.append(corners[j][between])
    patch_groups = groups[patches]
    edges_from += [patch_groups[:, 0], patch_groups[:, 1]]
    edges_to += [patch_groups[:, 1], patch_groups[:, 2]]
    nodes = count + 2 + n_vertices  # region labels 1..count, then one per vertex and the pad
    piece = _group_pieces(np.concatenate(edges_from), np.concatenate(edges_to), nodes)
    # Faces per piece: two per full quad (its region's piece; the b and d corners of a full
    # quad join its region by an edge or by the region itself), one per lone triangle (its
    # b corner's piece for a first triangle, its d corner's for a second) and per patch.
    region_quads = np.bincount(full_labels.reshape(-1), minlength=count + 1)
    del full_labels
    lone_first = first & ~full_quads
    lone_second = second & ~full_quads
    patch_piece = piece[patch_groups[:, 0]]
    sizes = np.bincount(piece[1: count + 1], weights=2 * region_quads[1:], minlength=nodes)
    sizes += np.bincount(piece[group_quad.b[lone_first]], minlength=nodes)
    sizes += np.bincount(piece[group_quad.d[lone_second]], minlength=nodes)
    sizes += np.bincount(patch_piece, minlength=nodes)
    small_piece = sizes < min_faces
    patch_small = small_piece[patch_piece]
    faced = np.concatenate([piece[1: count + 1], piece[group_quad.b[lone_first]],
                            piece[group_quad.d[lone_second]], patch_piece])
    if not np.any(small_piece[faced]):
        return 0, ~patch_small
    piece_plane = np.take(piece, group_plane)
    del group_quad, group_plane
    small_cells = _Quads(np.take(small_piece, piece_plane))
    small_first = small_cells.b & first
    small_second = small_cells.d & second
    removed = (int(np.count_nonzero(small_first)) + int(np.count_nonzero(small_second))
               + int(np.count_nonzero(patch_small)))
    first &= ~small_first
    second &= ~small_second
    return removed, ~patch_small


def _group_pieces(source: I32, target: I32, nodes: int) -> I32:
    """The connected piece of each of ``nodes`` nodes joined by the edges ``source``–
    ``target``: a node's piece is one of its members' numbers (a node without an edge is its
    own piece). The graph search runs over the nodes that have an edge only."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    piece = np.arange(nodes, dtype=np.int32)
    if len(source) == 0:
        return piece
    members, ends = np.unique(np.concatenate([source, target]), return_inverse=True)
    ends = ends.reshape(-1).astype(np.int32, copy=False)
    size = len(members)
    graph = coo_matrix((np.ones(len(source), dtype=np.int8),
                        (ends[: len(source)], ends[len(source):])), shape=(size, size))
    _, label = connected_components(graph, directed=False)
    representative = np.empty(int(label.max()) + 1, dtype=np.int32)
    representative[label] = members
    piece[members] = representative[label]
    return piece


def _compact(first: B, second: B, use_ad: B, rows: I32, patches: I32,
             n_vertices: int) -> tuple[B, I32, I32]:
    """Which points the kept triangles use, the index grid and patches renumbered to them."""
    used_cells = np.zeros(rows.shape, dtype=bool)
    used_cells[:-1, :-1] |= first | (second & use_ad)  # a
    used_cells[1:, :-1] |= first | (second & ~use_ad)  # b
    used_cells[:-1, 1:] |= second | (first & ~use_ad)  # c
    used_cells[1:, 1:] |= second | (first & use_ad)  # d
    used = np.zeros(n_vertices + 1, dtype=bool)
    used[rows[used_cells]] = True
    used[patches.reshape(-1)] = True
    used = used[:n_vertices]
    remap = np.empty(n_vertices + 1, dtype=np.int32)
    np.cumsum(used, out=remap[:n_vertices])
    remap -= 1
    remap[n_vertices] = -1
    return used, np.take(remap, rows), np.take(remap, patches)


def _drop_repeated_corners(first: B, second: B, use_ad: B, quad: _Quads, grid: ScanGrid,
                           report: dict[str, Any]) -> None:
    """Clear (in place) the triangles with a repeated corner.

    A corner repeats only where cells share a vertex: beside a merged pole column and in the
    seam row (mirrored samples); only those quads are tested.
    """
    def clear(where: Any) -> None:
        qa, qb, qc, qd = quad.a[where], quad.b[where], quad.c[where], quad.d[where]
        ad = use_ad[where]
        corner_1 = np.where(ad, qd, qc)
        corner_0 = np.where(ad, qa, qb)
        first[where] &= (qa != qb) & (qb != corner_1) & (qa != corner_1)
        second[where] &= (qc != qd) & (qd != corner_0) & (qc != corner_0)

    if report["pole_points_merged"]:
        alpha = np.nan_to_num(grid.alpha_deg, nan=90.0)
        pole = np.abs(np.sin(np.radians(alpha))) < _POLE_SINE
        # Pole flags per index column (the wrap column repeats column 0), then per quad column.
        pole = np.append(pole, pole[0])[: first.shape[1] + 1]
        columns = np.flatnonzero(pole[:-1] | pole[1:])
        clear((slice(None), columns))
    if report["seam_closed"]:
        clear((slice(-1, None), slice(None)))


def _faces_from_quads(first: B, second: B, use_ad: B, reverse: B, quad: _Quads,
                      extra: I32 | None = None) -> I32:
    """The ``(K, 3)`` faces: every quad's first triangle (a, b, a/d corner), then every quad's
    second (c, d, a/b corner), in row-major quad order, reversed where ``reverse``; then the
    ``extra`` faces, if any."""
    n_first, n_second = int(np.count_nonzero(first)), int(np.count_nonzero(second))
    n_extra = 0 if extra is None else len(extra)
    faces = np.empty((n_first + n_second + n_extra, 3), dtype=np.int32)
    if extra is not None:
        faces[n_first + n_second:] = extra
    for chosen, start, end, one, two, other_if_bc, other_if_ad in (
            (first, 0, n_first, quad.a, quad.b, quad.c, quad.d),  # (a, b, d) | (a, b, c)
            (second, n_first, n_first + n_second, quad.c, quad.d, quad.b, quad.a)):
        corner_one = one[chosen]
        corner_other = _blend(other_if_bc[chosen], other_if_ad[chosen], use_ad[chosen])
        flip = reverse[chosen]
        col0 = _blend(corner_one, corner_other, flip) if chosen is first else \
            _blend(corner_other, corner_one, flip)
        faces[start:end, 0] = col0
        faces[start:end, 1] = two[chosen]
        corner_one += corner_other
        corner_one -= col0
        faces[start:end, 2] = corner_one
    return faces


def _single_sample_holes(rows: I32, r_grid: F32, u_grid: Sequence[F32],
                         tan_incidence: float, allowance_m: float) -> I32:
    """Two triangles over every missing sample whose four neighbours lie on one surface.

    Each of the four quads around a missing sample keeps the triangle opposite it, so a dropout
    leaves a diamond-shaped hole bounded by its four neighbours; this closes it. Only the
    missing cells are tested: their neighbours' indices are arithmetic (± one row or column).
    """
    width = rows.shape[1]
    inner = rows[1:-1, 1:-1] < 0
    inner &= rows[:-2, 1:-1] >= 0
    inner &= rows[2:, 1:-1] >= 0
    inner &= rows[1:-1, :-2] >= 0
    inner &= rows[1:-1, 2:] >= 0
    p, s = np.nonzero(inner)
    centre = (p + 1) * width + (s + 1)
    up, down, left, right = centre - width, centre + width, centre - 1, centre + 1
    flat_r = r_grid.reshape(-1)
    flat_u = [u.reshape(-1) for u in u_grid]

    def ok(i: NDArray[np.intp], j: NDArray[np.intp]) -> B:
        return _continuous(flat_r[i], flat_r[j], [u[i] for u in flat_u],
                           [u[j] for u in flat_u], tan_incidence, allowance_m)[0]

    hole = ok(up, left) & ok(left, down) & ok(down, right) & ok(right, up) & ok(up, down)
    flat_rows = rows.reshape(-1)
    u, dn, lt, rt = (flat_rows[side[hole]] for side in (up, down, left, right))
    return np.concatenate([np.stack([u, lt, dn], 1), np.stack([u, dn, rt], 1)]).astype(np.int32)


def _varies(values: F32) -> bool:
    """True when not every value equals the first (−0.0 equals 0.0: a sensor on the axis has
    origins of either sign, from rotating a zero offset; NaN counts as varying).

    On a contiguous copy: comparisons over a strided column of an ``(N, 3)`` array are
    several times slower.
    """
    if len(values) == 0:
        return False
    column = np.ascontiguousarray(values)
    with np.errstate(invalid="ignore"):
        return bool(np.any(column != column[0]))


def _facing_away(vertices: F32, origins: F32, faces: I32) -> B:
    """Which ``faces`` have their normal pointing away from their first corner's sensor.

    Column by column (:func:`scanpipe.meshing.mesh.face_cross`): ``np.cross`` and the
    ``(K, 3)`` temporaries cost ~3× more on the million faces near the axis of a lab scan.
    """
    from scanpipe.meshing.mesh import face_cross

    normal = face_cross(vertices, faces)
    first = faces[:, 0]
    dot = np.zeros(len(faces), dtype=np.float32)
    for k in range(3):
        towards = np.take(origins[:, k], first)
        towards -= np.take(vertices[:, k], first)
        towards *= normal[:, k]
        dot += towards
    return np.asarray(dot < 0)


def _face_sensor(vertices: F32, origins: F32, faces: I32) -> I32:
    """``faces`` with the winding reversed where the normal points away from the sensor."""
    out = faces.copy()
    away = _facing_away(vertices, origins, faces)
    out[away] = out[away][:, ::-1]
    return out
