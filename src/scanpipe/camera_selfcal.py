"""Camera self-calibration: each camera's mount, focal length and clock offset from the data.

No targets. The scan's depth edges — occlusion boundaries (range jumps) and creases (where the
surface turns sharply) of the range image, found on the profile × sample grid, each on a line of
them (an isolated one is noise) with that line's direction — are projected into the camera's
frames with :func:`scanpipe.camera.project_points` at the platform angle of each frame's time
(:func:`scanpipe.motion.beta_deg_at`). Where the parameters are right they land on image edges:
Canny's pixels on each colour channel, each moved across the edge to the peak of the gradient
(a fraction of a pixel). A handful of global parameters per camera is fitted, never a per-frame
pose:

- the mount's rotation (a small rotation vector applied in the platform frame) and translation,
- the focal length (fx and fy scaled together; the principal point is kept),
- optionally the clock offset of its frames (an imported video): a frame taken at host time t
  shows the platform at β(t + δ).

The fit runs coarse to fine: first on the distance transform of the image edges, blurred by 2 %,
0.7 % and 0.25 % of the focal length, then 1 px, and truncated at 5 σ (a wide basin: the start
may be degrees off); then point to line, as ICP: each projected depth edge is matched with the
nearest image edge within a few pixels that runs its way (within 30°), and the signed distance
along that edge's normal is minimised (soft-L1), matches renewed until the values settle. The
distance map's whole pixels and its blur leave a bias of a fraction of a pixel that the point-to-
line pass does not; the alignment figures are its distances. With a clock offset to find and a
video that films the platform's start and stop, the clock is read from the video's own motion
(:func:`motion_clock`: the change between consecutive frames against the platform's turn
between their times) and the mount fitted at it. Otherwise the mount is first fitted to the
frames of the platform standing still, then δ is scanned over the search window, then
everything is fitted together; every basin of the cost that competes, over δ and along the
valley where δ and the camera's orbit about the axis trade, is refined and the least final
cost wins — two that end alike leave δ undetermined (a warning, the 1σ widened to
cover both). The point-to-line passes run from the distance map's
subset of edge points and from every visible one; the result that fits all visible points
better wins. The 1σ of each value is the largest of the curvature (the Jacobian's
``s² (JᵀJ)⁻¹``) with the scan's placement error added (each edge line between two profiles off
by one error within ± half a cell, the same in every frame: :func:`_placement_sigma`), the
spread over groups of frames and over groups of the scan's edge pieces
(jackknifes: the fit repeated with each group left out; for a 360° camera, whose every frame
sees the whole scene, also over sectors of the scene) and half the distance between the two
line-pass results, because neighbouring edge points share their errors, the scan's edge
errors are the same in every frame, and the curvature alone is optimistic. The values'
correlations say which trade (a tilt against a height, a dolly against a zoom). A value
whose 1σ exceeds its limit is reported unobservable
and keeps the rig's value unless it moved 2σ or more (a clock offset always keeps it, and then
the mount's turn is reported undetermined too).

Why frames outside the scan matter for δ: while the platform turns at a steady rate ω, a clock
offset δ looks exactly like a turn of the camera about the axis by ω·δ. Frames while the platform
stands still (before the scan starts, after it ends) separate the two; the video should run a few
seconds before and after the scan. Without them a warning says δ is found only together with
the camera's turn (``still_frames`` False). A stepping platform repeats itself every step: a δ
one step period off looks like a turn by one step in every frame of the scan, and only the
frames where the motion starts and stops tell them apart (:func:`frame_rows` takes some). Once δ
is chosen the mount is fitted afresh at it, every view weighing alike. See docs/calibration.md
("Cameras").
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from scanpipe.camera import project_points
from scanpipe.errors import StageError
from scanpipe.geometry import CAMERA_BASE, camera_to_platform, platform_rotation
from scanpipe.grid import bilateral_smooth, scan_grid, to_grid
from scanpipe.motion import beta_deg_at, motor_times_ns
from scanpipe.rig import CameraConfig, Pose, Rig
from scanpipe.schema import ORIGIN, XYZ

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]
B = NDArray[np.bool_]

#: Parameter names in the fit's order, their units, and the step one "unit" of the scaled fit
#: stands for (about a pixel's worth for a Full-HD phone 2–3 m from the walls).
PARAMETERS = ("rot_x_deg", "rot_y_deg", "rot_z_deg", "tx_m", "ty_m", "tz_m", "focal_scale",
              "time_offset_s")
_UNITS = np.array([0.05, 0.05, 0.05, 0.005, 0.005, 0.005, 0.001, 0.01])
#: A mount value over its limit is still applied when it moved this many 1σ (the time offset
#: never: an undetermined offset keeps the start value).
SIGNIFICANT_SIGMAS = 2.0
#: Above these 1σ a value counts as unobservable (kept at the rig's value unless it moved
#: :data:`SIGNIFICANT_SIGMAS`). The clock's: a stepping platform's cost has a basin every step
#: period (0.4 s at the benchmark's 0.25° steps), so a clock is trusted only when its 1σ
#: puts the next step's basin 8σ away (benchmark seed 5 once reported a clock 342 ms off,
#: one step, as determined with a 1σ of 73 ms).
SIGMA_LIMITS = {"rot_x_deg": 0.2, "rot_y_deg": 0.2, "rot_z_deg": 0.2, "tx_m": 0.02,
                "ty_m": 0.02, "tz_m": 0.02, "focal_scale": 0.01, "time_offset_s": 0.05}
#: A mount rotation is aimed at within this (°, issue 19's target); a determined one whose
#: :data:`PRECISION_SIGMAS` σ exceed it is reported with a warning that says so (the scan's
#: motor step places its silhouettes to ± half a step, and a coarse step may not pin the pan).
ROTATION_AIM_DEG = 0.1
PRECISION_SIGMAS = 2.0
#: The share of edge points within this many pixels is the alignment's second figure.
WITHIN_PX = 2.0
#: A depth edge counts in the alignment figures when an image edge lies within this many
#: pixels (× the frame's size / 1000): a crease between two surfaces of one colour, or an edge
#: hidden from the camera, has no image edge to be measured against.
MATCH_PX = 10.0
#: Edge points per frame used by the fit (a random subset; the figures use all).
FIT_POINTS_PER_FRAME = 4000


@dataclass(frozen=True)
class DepthEdges:
    """Depth-edge points of a scan in the rig frame, and what made each one an edge."""

    xyz: F64
    #: True for an occlusion boundary (range jump), False for a crease.
    occluding: B
    #: A subsample of all the scan's points (for the cameras' visibility test).
    surface: F64
    #: Unit direction of the edge line through each point (rig frame): the image edge it is
    #: matched with must run the same way.
    tangent: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    #: One cell of the scan's grid at the point, along the axis across which the edge was
    #: found (rig frame, m): the scan samples the edge there only every cell, so the point
    #: lies anywhere within ± half of it of the true edge (uniform: 1σ = |cell| / √12).
    cell: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    #: The edge line each point belongs to: a run of edge cells between the same two
    #: profiles, whose points the scan places with ONE error (a vertical silhouette or corner
    #: between two profiles is off by the same fraction of a motor step along its whole
    #: height and in every frame). −1: each point on its own (edges found across the samples
    #: of a profile, whose placement error changes along them).
    line: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    def line_ids(self) -> NDArray[np.int64]:
        """:attr:`line`, a point of unknown line given its own id."""
        n = len(self.xyz)
        if self.line.shape != (n,):
            return np.arange(n, dtype=np.int64)
        own = np.max(self.line, initial=-1) + 1 + np.arange(n, dtype=np.int64)
        return np.asarray(np.where(self.line >= 0, self.line, own), np.int64)


def depth_edges(points: pa.Table, max_edges: int = 60_000, crease_deg: float = 35.0,
                crease_span_deg: float = 4.0, min_jump_m: float = 0.08,
                max_surface: int = 200_000, seed: int = 0) -> DepthEdges:
    """The depth edges of a gridded ``points`` table (the assemble output), vectorised.

    A **jump** between two neighbouring cells (along a profile or across profiles) is an
    occlusion boundary when the range changes by more than ``min_jump_m`` and by 4× the
    differences on either side (a wall seen at a grazing angle changes steadily; an edge at
    once). The edge point is the nearer cell's range along the direction halfway between the
    two beams: the true boundary lies somewhere between them, and the nearer cell alone would
    pull every silhouette inwards by half a cell. A **crease** is a cell where the surface
    turns by more than ``crease_deg`` over arms of ``crease_span_deg`` either side, kept where
    the turn is largest along that axis.
    """
    grid = scan_grid(points)
    if grid is None:
        raise StageError("points: no scan grid (profile/sample −1); camera self-calibration "
                         "needs the assembled scan, not an imported cloud")
    xyz = np.stack([to_grid(points.column(c).to_numpy().astype(np.float64), grid)
                    for c in XYZ], axis=-1)
    origin = np.stack([to_grid(points.column(c).to_numpy().astype(np.float64), grid)
                       for c in ORIGIN], axis=-1)
    offset = xyz - origin
    ranges = np.linalg.norm(offset, axis=-1)
    valid = np.isfinite(ranges) & (ranges > 0)
    ranges = np.where(valid, ranges, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        directions = offset / ranges[..., None]
    # creases need the range noise smoothed away (edges kept: a bilateral filter on the grid)
    smooth = bilateral_smooth(ranges.astype(np.float32), radius=2, sigma_cells=1.5,
                              sigma_range_m=0.03).astype(np.float64)
    xyz = origin + smooth[..., None] * directions
    steps = [abs(grid.beta_step_deg), abs(grid.alpha_step_deg)]
    cell_rad = math.radians(max((s for s in steps if math.isfinite(s)), default=1.0))
    found: list[F64] = []
    occluding: list[B] = []
    tangents: list[F64] = []
    cells: list[F64] = []
    line_ids: list[NDArray[np.int64]] = []
    next_line = 0
    for axis in (0, 1):
        jump_points, jump_mask, jump_cell, jump_line = _jumps(smooth, directions, origin, axis,
                                                              min_jump_m)
        step_deg = steps[axis]
        span = max(2, math.ceil(crease_span_deg / step_deg)) if math.isfinite(step_deg) else 2
        crease, peak = _creases(xyz, jump_mask, axis, span, crease_deg)
        crease_cell = np.nan_to_num(_along(xyz, axis, 1)[peak] - xyz[peak])
        crease_line = _run_labels(peak, axis)
        if axis == 1:
            # across the samples of a profile: a horizontal edge's elevation from the scanner
            # changes along it, so its placement error runs through the cell as it crosses
            # the profiles (a run averages it out): each point on its own. Across profiles
            # the scan plane holds a vertical edge whole, at one platform angle: one error.
            jump_line = np.full(jump_line.shape, -1, np.int64)
            crease_line = np.full(crease_line.shape, -1, np.int64)
        for points, occludes, cell, line in ((jump_points, True, jump_cell, jump_line),
                                             (crease, False, crease_cell, crease_line)):
            # each edge point lies on a chain of them (an edge line); an isolated one is noise
            tangent, chained = _edge_lines(points, cell_rad)
            found.append(points[chained])
            tangents.append(tangent[chained])
            occluding.append(np.full(int(chained.sum()), occludes))
            cells.append(cell[chained])
            line_ids.append(np.where(line[chained] >= 0, line[chained] + next_line, -1))
            next_line += int(line.max(initial=-1)) + 1
    edges = np.concatenate(found)
    kinds = np.concatenate(occluding)
    lines = np.concatenate(tangents)
    cell_vectors = np.concatenate(cells)
    line_of = np.concatenate(line_ids)
    rng = np.random.default_rng(seed)
    if len(edges) > max_edges:
        keep = np.sort(rng.choice(len(edges), max_edges, replace=False))
        edges, kinds, lines = edges[keep], kinds[keep], lines[keep]
        cell_vectors, line_of = cell_vectors[keep], line_of[keep]
    surface = xyz[valid]
    if len(surface) > max_surface:
        surface = surface[rng.choice(len(surface), max_surface, replace=False)]
    return DepthEdges(edges, kinds, surface, lines, cell_vectors, line_of)


def _run_labels(mask: B, axis: int) -> NDArray[np.int64]:
    """For each True cell of ``mask`` (edges found across ``axis``, in row-major order), the
    label of its run along the other axis — one edge line between the same two rows of
    samples — a gap of one cell (a dropout) bridged; labels from 0."""
    runs = mask if axis == 0 else mask.T  # runs along the last axis
    before = np.zeros_like(runs)
    before[:, 1:] |= runs[:, :-1]
    before[:, 2:] |= runs[:, :-2]
    labels = np.cumsum((runs & ~before).ravel()).reshape(runs.shape) - 1
    if axis == 1:
        labels = labels.T
    return np.asarray(labels[mask], np.int64)


#: Neighbours that define an edge point's line, and how straight they must lie.
_LINE_NEIGHBOURS = 6
_MIN_LINEARITY = 0.8


def _edge_lines(points: F64, cell_rad: float) -> tuple[F64, B]:
    """Each edge point's line direction (principal axis of its nearest edge points) and
    whether it lies on a line: its neighbours within a few cells and nearly collinear."""
    from scipy.spatial import cKDTree

    n = len(points)
    k = _LINE_NEIGHBOURS + 1
    if n < k:
        return np.zeros((n, 3)), np.zeros(n, dtype=bool)
    distance, index = cKDTree(points).query(points, k=k)
    neighbours = points[index]
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    linearity = (values[:, 2] - values[:, 1]) / np.maximum(values[:, 2], 1e-18)
    ranges = np.linalg.norm(points, axis=1)
    near = distance[:, -1] <= 2.0 * k * np.maximum(ranges, 0.5) * cell_rad
    return np.asarray(vectors[:, :, 2], np.float64), near & (linearity >= _MIN_LINEARITY)


def _along(values: NDArray[Any], axis: int, k: int) -> NDArray[Any]:
    """``values`` shifted so that cell i holds cell i + k along ``axis`` (NaN past the end)."""
    out = np.full_like(values, np.nan)
    n = values.shape[axis]
    if abs(k) >= n:
        return out
    src = [slice(None)] * values.ndim
    dst = [slice(None)] * values.ndim
    if k >= 0:
        src[axis], dst[axis] = slice(k, n), slice(0, n - k)
    else:
        src[axis], dst[axis] = slice(0, n + k), slice(-k, n)
    out[tuple(dst)] = values[tuple(src)]
    return out


def _jumps(ranges: F64, directions: F64, origin: F64, axis: int,
           min_jump_m: float) -> tuple[F64, B, F64, NDArray[np.int64]]:
    """Occlusion-boundary points between cell i and i+1 along ``axis``, a mask of the
    cells on either side of a jump, each point's cell (the two beams apart at its range:
    the boundary lies anywhere between them) and its edge line (:func:`_run_labels`)."""
    ahead = _along(ranges, axis, 1)
    diff = np.abs(ahead - ranges)
    before, after = _along(diff, axis, -1), _along(diff, axis, 1)
    neighbours = np.fmax(np.nan_to_num(before, nan=0.0), np.nan_to_num(after, nan=0.0))
    with np.errstate(invalid="ignore"):
        jump = (diff > min_jump_m) & (diff > 4.0 * neighbours)
    jump &= np.isfinite(diff)
    near_is_here = ranges <= ahead
    dir_ahead = _along(directions, axis, 1)
    origin_ahead = _along(origin, axis, 1)
    mid = directions + dir_ahead
    mid /= np.linalg.norm(mid, axis=-1, keepdims=True)
    near_range = np.where(near_is_here, ranges, ahead)
    near_origin = np.where(near_is_here[..., None], origin, origin_ahead)
    points = near_origin + near_range[..., None] * mid
    mask = jump | _along(jump.astype(np.float64), axis, -1).astype(bool)
    cell = near_range[jump][:, None] * (dir_ahead[jump] - directions[jump])
    return points[jump], mask, np.nan_to_num(cell), _run_labels(jump, axis)


def _creases(xyz: F64, jump_mask: B, axis: int, span: int, crease_deg: float
             ) -> tuple[F64, B]:
    """Crease points along ``axis``: the surface turns by more than ``crease_deg`` between the
    arms to the cells ``span`` back and ``span`` ahead; the largest turn within ±span/2 kept.
    Returns the points and the mask of their cells."""
    back = xyz - _along(xyz, axis, -span)
    ahead = _along(xyz, axis, span) - xyz
    dot = np.sum(back * ahead, axis=-1)
    norms = np.linalg.norm(back, axis=-1) * np.linalg.norm(ahead, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        turn = np.degrees(np.arccos(np.clip(dot / norms, -1.0, 1.0)))
    turn = np.where(np.isfinite(turn), turn, 0.0)
    # no arm may straddle an occlusion boundary: the turn there is the jump's, not a crease
    near_jump = jump_mask.astype(np.float64)
    for k in range(1, span + 1):
        near_jump = np.fmax(near_jump, np.nan_to_num(_along(jump_mask.astype(np.float64),
                                                            axis, k)))
        near_jump = np.fmax(near_jump, np.nan_to_num(_along(jump_mask.astype(np.float64),
                                                            axis, -k)))
    turn[near_jump > 0] = 0.0
    peak = turn > crease_deg
    for k in range(1, max(1, span // 2) + 1):
        peak &= turn >= np.nan_to_num(_along(turn, axis, k), nan=0.0)
        peak &= turn > np.nan_to_num(_along(turn, axis, -k), nan=0.0)
    # the crease between cells: the peak of a parabola through the turns at i−1, i, i+1
    left, right = _along(turn, axis, -1)[peak], _along(turn, axis, 1)[peak]
    curvature = left - 2 * turn[peak] + right
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.clip(np.where(curvature < 0, 0.5 * (left - right) / curvature, 0.0),
                        -0.5, 0.5)
    shift = np.nan_to_num(shift)
    toward = np.where(shift[:, None] >= 0, _along(xyz, axis, 1)[peak],
                      _along(xyz, axis, -1)[peak])
    here = xyz[peak]
    moved = here + np.abs(shift)[:, None] * (toward - here)
    moved = np.where(np.isfinite(moved), moved, here)
    return _arm_intersection(xyz, peak, axis, span, np.asarray(moved, dtype=np.float64)), peak


def _arm_line(xyz: F64, peak: B, axis: int, offsets: range) -> tuple[F64, F64, B]:
    """A line fitted to the cells at ``offsets`` along ``axis`` from each peak cell: its centre,
    unit direction and whether the cells lie on a line (all valid, nearly collinear)."""
    arm = np.stack([_along(xyz, axis, k)[peak] for k in offsets], axis=1)  # (n, k, 3)
    valid = np.all(np.isfinite(arm), axis=(1, 2))
    arm = np.where(valid[:, None, None], arm, 0.0)
    centre = arm.mean(axis=1)
    centred = arm - centre[:, None, :]
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    # straight: the spread across the line is small against the spread along it
    straight = values[:, 1] <= (0.05**2) * np.maximum(values[:, 2], 1e-18)
    return centre, np.asarray(vectors[:, :, 2], np.float64), valid & straight


def _arm_intersection(xyz: F64, peak: B, axis: int, span: int, fallback: F64) -> F64:
    """Each crease point placed where the lines of its two arms meet (the midpoint of their
    closest approach); ``fallback`` where an arm is not straight or the lines meet far away.

    The peak of the turn lies off the corner by a fraction of a cell, and always the same way
    for one kind of corner (the arm on a surface seen at a grazing angle spans more space per
    cell), so the floor–wall creases all move alike: a bias that tilts the camera. Two planes
    meet on a line wherever the cells fall; the cells next to the corner (rounded by the
    smoothing) stay out of the arms.
    """
    gap = max(1, min(3, span // 3))
    if span - gap < 2:
        return fallback
    c1, d1, ok1 = _arm_line(xyz, peak, axis, range(-span, -gap + 1))
    c2, d2, ok2 = _arm_line(xyz, peak, axis, range(gap, span + 1))
    w = c1 - c2
    b = np.sum(d1 * d2, axis=1)
    d, e = np.sum(d1 * w, axis=1), np.sum(d2 * w, axis=1)
    denominator = 1.0 - b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (b * e - d) / denominator
        t = (e - b * d) / denominator
    meet = 0.5 * ((c1 + s[:, None] * d1) + (c2 + t[:, None] * d2))
    apart = np.linalg.norm((c1 + s[:, None] * d1) - (c2 + t[:, None] * d2), axis=1)
    cell = np.linalg.norm(_along(xyz, axis, 1)[peak] - xyz[peak], axis=1)
    near = np.linalg.norm(meet - fallback, axis=1)
    ok = (ok1 & ok2 & (denominator > 0.05) & np.isfinite(meet).all(axis=1)
          & (near <= 2.0 * np.nan_to_num(cell, nan=0.0)) & (apart <= np.nan_to_num(cell, nan=0.0)))
    return np.asarray(np.where(ok[:, None], meet, fallback), np.float64)


@dataclass(frozen=True)
class ImageEdges:
    """A frame's image edges: the distance map to the nearest edge pixel and every edge pixel
    placed to a fraction of a pixel across the edge, with its unit normal (the gradient's
    direction)."""

    distance: F32
    uv: F64
    normal: F64


def image_edges(image: U8, low: float = 40.0, high: float = 120.0) -> ImageEdges:
    """Image edges of a BGR or grey frame, to a fraction of a pixel.

    Edge pixels are Canny's on each colour channel of a lightly blurred image, combined: two
    surfaces of different colour but the same brightness (a red ceiling over a purple wall)
    meet at no edge of the grey image. Each edge pixel then moves along the gradient of its
    strongest channel to the peak of the gradient magnitude (a parabola through the magnitude
    one pixel either side): Canny's pixels lie up to half a pixel off the edge, and a depth
    edge measured against them inherits that error.
    """
    blurred = cv2.GaussianBlur(image, (3, 3), 0.8)
    channels = [blurred] if blurred.ndim == 2 else [blurred[:, :, c] for c in
                                                    range(blurred.shape[2])]
    edges = np.zeros(image.shape[:2], dtype=np.uint8)
    best = np.full(image.shape[:2], -1.0, np.float32)
    gx = np.zeros(image.shape[:2], np.float32)
    gy = np.zeros(image.shape[:2], np.float32)
    for channel in channels:
        plane = np.ascontiguousarray(channel)
        edges |= np.asarray(cv2.Canny(plane, low, high, L2gradient=True), np.uint8)
        cx = cv2.Sobel(plane, cv2.CV_32F, 1, 0, ksize=3)
        cy = cv2.Sobel(plane, cv2.CV_32F, 0, 1, ksize=3)
        magnitude = cx * cx + cy * cy
        stronger = magnitude > best
        best = np.where(stronger, magnitude, best)
        gx = np.where(stronger, cx, gx)
        gy = np.where(stronger, cy, gy)
    if not edges.any():
        return ImageEdges(np.full(image.shape[:2], np.float32(max(image.shape[:2])),
                                  dtype=np.float32), np.zeros((0, 2)), np.zeros((0, 2)))
    rows, cols = np.nonzero(edges)
    gxs, gys = gx[rows, cols].astype(np.float64), gy[rows, cols].astype(np.float64)
    norm = np.hypot(gxs, gys)
    ok = norm > 0
    rows, cols, gxs, gys, norm = rows[ok], cols[ok], gxs[ok], gys[ok], norm[ok]
    normal = np.stack([gxs / norm, gys / norm], axis=1)
    strength = np.sqrt(best, dtype=np.float32)
    here = strength[rows, cols].astype(np.float64)
    around = [map_coordinates(strength, [rows + k * normal[:, 1], cols + k * normal[:, 0]],
                              order=1, mode="nearest") for k in (-1.0, 1.0)]
    curvature = around[0] - 2.0 * here + around[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(curvature < 0, 0.5 * (around[0] - around[1]) / curvature, 0.0)
    shift = np.clip(np.nan_to_num(shift), -0.5, 0.5)
    uv = np.stack([cols + shift * normal[:, 0], rows + shift * normal[:, 1]], axis=1)
    return ImageEdges(_distance_to(uv, image.shape[:2]), uv, normal)


def _distance_to(uv: F64, shape: tuple[int, ...]) -> F32:
    """Distance (px) from every pixel to the nearest of the sub-pixel edge points ``uv``, on
    the pixel grid: each point marks the pixels within half a pixel of it along each axis
    (one, or the two either side of a point halfway between them).

    Canny marks the pixel before a step on both axes (a step between columns 31 and 32 at
    column 31): a distance map of its pixels puts every straight edge half a pixel up and to
    the left, the same in every frame, and the coarse passes then turn the camera by half a
    pixel for the last pass to undo. Marked symmetrically about the sub-pixel point, the
    map's zero is centred on the edge.
    """
    height, width = int(shape[0]), int(shape[1])
    mask = np.full((height, width), 255, np.uint8)
    low = np.ceil(uv - 0.5).astype(np.int64)
    high = np.floor(uv + 0.5).astype(np.int64)
    for col in (low[:, 0], high[:, 0]):
        for row in (low[:, 1], high[:, 1]):
            ok = (col >= 0) & (col < width) & (row >= 0) & (row < height)
            mask[row[ok], col[ok]] = 0
    return np.asarray(cv2.distanceTransform(mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE),
                      np.float32)


def edge_distance_map(image: U8, low: float = 40.0, high: float = 120.0) -> F32:
    """Distance (px) from every pixel to the nearest image edge pixel (of
    :func:`image_edges`)."""
    return image_edges(image, low, high).distance


#: Pixels one radian of doubled orientation counts as in the matching's k-d tree, and the
#: largest angle between a depth edge and the image edge it is matched with.
ORIENTATION_PX = 4.0
MAX_ANGLE_DEG = 30.0


def _oriented(uv: F64, normal: F64) -> F64:
    """Points in (u, v, orientation) space: the normal's angle doubled (an edge's normal has
    no sign) on a circle of :data:`ORIENTATION_PX`."""
    angle = 2.0 * np.arctan2(normal[:, 1], normal[:, 0])
    return np.column_stack([uv, ORIENTATION_PX * np.cos(angle), ORIENTATION_PX * np.sin(angle)])


@dataclass
class FrameObservation:
    """One frame used by the fit: its camera (sized to the frame), time and edge distances."""

    camera: CameraConfig
    time_ns: int
    distance: F32
    #: The frame's edge pixels to a fraction of a pixel and their normals (the final fit's
    #: point-to-line matches and the alignment figures).
    edge_uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    edge_normal: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    #: Indices into the edge points the frame sees (set by the fit at the starting values).
    edges: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    #: How much the frame counts in the fit (frames of the platform standing still count
    #: as much together as all the others when a clock offset is fitted).
    weight: float = 1.0
    #: Every edge point the frame sees (``edges`` is the fit's subset of them).
    all_edges: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    _blurred: dict[float, F32] = field(default_factory=dict, repr=False)
    _tree: Any = field(default=None, repr=False)

    def tree(self) -> Any:
        """A k-d tree over the edge pixels in (u, v, orientation) space (cached): the nearest
        image edge that also runs the way the depth edge does."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(_oriented(self.edge_uv, self.edge_normal))
        return self._tree

    def blurred(self, sigma_px: float) -> F32:
        """The distance map blurred by ``sigma_px`` (cached): a smooth, wide basin."""
        if sigma_px <= 0:
            return self.distance
        if sigma_px not in self._blurred:
            self._blurred[sigma_px] = np.asarray(
                cv2.GaussianBlur(self.distance, (0, 0), sigma_px), np.float32)
        return self._blurred[sigma_px]


def observe(camera: CameraConfig, time_ns: int, image: U8) -> FrameObservation:
    """A frame for the fit; :class:`StageError` when its size differs from the camera's."""
    if image.shape[:2] != (camera.height, camera.width):
        raise StageError(f"frames: a frame of camera {camera.id!r} is "
                         f"{image.shape[1]}×{image.shape[0]}, the camera "
                         f"{camera.width}×{camera.height}")
    found = image_edges(image)
    return FrameObservation(camera, int(time_ns), found.distance, found.uv, found.normal)


@dataclass(frozen=True)
class MotorTrack:
    """The platform angle over time: the ``motor`` artifact and the rig's motor."""

    motor: pa.Table
    rig: Rig

    def beta_deg(self, times_ns: NDArray[np.int64]) -> F64:
        """Platform angle at each host time."""
        return beta_deg_at(times_ns, self.motor, self.rig.motor)

    def moving_span_ns(self) -> tuple[int, int]:
        """Host times of the first and last change of the platform angle."""
        steps = self.motor.column("step_count").to_numpy()
        times = motor_times_ns(self.motor)
        order = np.argsort(times, kind="stable")
        changes = np.flatnonzero(np.diff(steps[order]) != 0)
        if changes.size == 0:
            return int(times[order][0]), int(times[order][0])
        return int(times[order][changes[0]]), int(times[order][changes[-1] + 1])

    def step_period_s(self) -> float:
        """The median time (s) from one move of the platform to the next (a stepping platform
        repeats itself so often); 0.0 for a platform that moves once (turns steadily)."""
        steps = self.motor.column("step_count").to_numpy()
        times = motor_times_ns(self.motor)
        order = np.argsort(times, kind="stable")
        changed = times[order][1:][np.diff(steps[order]) != 0]
        if changed.size < 3:
            return 0.0
        gaps = np.diff(changed)
        # a move's own states follow each other closely; a pause parts one move from the next
        starts = changed[np.concatenate([[True], gaps > 3 * np.median(gaps)])]
        return float(np.median(np.diff(starts))) / 1e9 if starts.size >= 2 else 0.0


#: Frames at most this far apart (s) form a pair for the motion signal: the platform's steps
#: must fall between frames one by one (a phone's video, 25–60 fps; not a camera at 0.5 fps).
MOTION_MAX_GAP_S = 0.1
#: Frames of the motion signal are compared at this width (px) at most (a step of the platform
#: moves a Full-HD frame by some pixels; a quarter of them still shows it).
MOTION_WIDTH_PX = 480
#: The clock from the motion is determined when its best correlation beats the best one a
#: quarter step period or more away by this much (of 1).
MOTION_MIN_CONTRAST = 0.1
#: ... and when at least this many frame pairs see the platform move (and as many see it stand).
MOTION_MIN_PAIRS = 3
#: Offsets tried by the motion signal, this far apart (s).
MOTION_GRID_S = 0.001
#: Draws of the frame pairs for the motion clock's 1σ, and the share of them that must find
#: the same basin.
MOTION_BOOTSTRAP = 64
MOTION_MIN_AGREEMENT = 0.9


@dataclass(frozen=True)
class MotionClock:
    """A video's clock offset read from its own motion: when the image changes between two
    consecutive frames, the platform turned between them. Every offset within
    ``[low_s, high_s]`` explains the changes equally well (the frames' spacing bounds it)."""

    offset_s: float
    low_s: float
    high_s: float
    #: Frame pairs compared, and those in which the platform turned at the offset.
    pairs: int
    moving_pairs: int
    #: The correlation of the image change with the platform's turn at the offset, and the
    #: best one at an offset a quarter step period or more away.
    score: float
    rival_score: float
    determined: bool
    #: The best offset's spread when the frame pairs are drawn again (a bootstrap: half the
    #: 16–84 % range), and the share of the draws that found the same basin.
    bootstrap_s: float = 0.0
    agreement: float = 1.0

    @property
    def trusted(self) -> bool:
        """Determined, and its 1σ within the clock's limit (:data:`SIGMA_LIMITS`)."""
        return self.determined and self.sigma_s <= SIGMA_LIMITS["time_offset_s"]

    @property
    def sigma_s(self) -> float:
        """1σ of the offset: the larger of the bootstrap's spread, a uniform spread over the
        interval of equal scores, and :data:`MOTION_GRID_S`."""
        return max(self.bootstrap_s, (self.high_s - self.low_s) / math.sqrt(12.0),
                   MOTION_GRID_S)

    def as_dict(self) -> dict[str, Any]:
        """The values for a report."""
        return {"offset_s": self.offset_s, "low_s": self.low_s, "high_s": self.high_s,
                "sigma_s": self.sigma_s, "pairs": self.pairs, "moving_pairs": self.moving_pairs,
                "score": self.score, "rival_score": self.rival_score,
                "bootstrap_s": self.bootstrap_s, "agreement": self.agreement,
                "determined": self.determined, "trusted": self.trusted}


def motion_image(data: bytes, what: str) -> F32:
    """A frame decoded grey, at most :data:`MOTION_WIDTH_PX` wide and lightly blurred (the
    sensor's noise), for the motion signal."""
    from scanpipe.images import MAX_FRAME_PX, decode_image_bytes

    return motion_grey(decode_image_bytes(data, f"frames: {what}", MAX_FRAME_PX,
                                          cv2.IMREAD_REDUCED_GRAYSCALE_2, StageError))


def motion_grey(image: NDArray[Any]) -> F32:
    """A decoded frame (grey or BGR) made ready for the motion signal: grey, at most
    :data:`MOTION_WIDTH_PX` wide, lightly blurred."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    out = np.asarray(grey, np.float32)
    if out.shape[1] > MOTION_WIDTH_PX:
        size = (MOTION_WIDTH_PX, max(1, round(out.shape[0] * MOTION_WIDTH_PX / out.shape[1])))
        out = np.asarray(cv2.resize(out, size, interpolation=cv2.INTER_AREA), np.float32)
    return np.asarray(cv2.GaussianBlur(out, (0, 0), 1.0), np.float32)


def motion_reach_ns(track: MotorTrack, window_s: float) -> int:
    """How far (ns) from the platform's start and stop the motion signal takes frames: the
    clock's search window and two step periods (the steps either side of the start and
    stop), at least 0.2 s."""
    return round((window_s + max(0.2, 2 * track.step_period_s())) * 1e9)


def motion_rows(frames: pa.Table, camera_id: str, track: MotorTrack, start_offset_s: float,
                window_s: float) -> NDArray[np.int64]:
    """Rows of ``camera_id``'s frames within ``window_s`` (and two step periods) of the
    platform's start and stop in the frames' rough clock: the motion signal's frames."""
    ids = np.asarray(frames.column("camera_id").to_pylist(), dtype=object)
    rows = np.flatnonzero(ids == camera_id)
    times = frames.column("log_time_ns").to_numpy()[rows] + np.int64(round(start_offset_s * 1e9))
    first, last = track.moving_span_ns()
    reach = motion_reach_ns(track, window_s)
    near = (np.abs(times - first) <= reach) | (np.abs(times - last) <= reach)
    return np.asarray(rows[near], np.int64)


def motion_clock(times_ns: NDArray[np.int64], images: Sequence[F32], track: MotorTrack,
                 start_offset_s: float = 0.0, window_s: float = 1.0) -> MotionClock | None:
    """The clock offset δ (a frame stamped t shows the platform at β(t + δ)) within
    ``start_offset_s`` ± ``window_s`` from the frames' own motion; None when too few
    consecutive frame pairs (a camera taking a frame every few seconds).

    The change between consecutive frames (mean absolute difference of the grey images) is
    correlated with the platform's turn between their times (the motor's states interpolated)
    at each offset tried; the best correlation is the clock (the middle of its top where that
    is flat). A clock found from the
    start and stop of the motion cannot trade with a turn of the camera (the edges' fit can:
    a stepping platform looks the same one step period later, turned by a step).
    """
    order = np.argsort(times_ns, kind="stable")
    times = np.asarray(times_ns, np.int64)[order]
    shapes = [images[i].shape for i in order]
    gaps_s = np.diff(times) / 1e9
    pair = np.flatnonzero((gaps_s > 0) & (gaps_s <= MOTION_MAX_GAP_S)
                          & np.array([a == b for a, b in itertools.pairwise(shapes)], dtype=bool))
    if pair.size < 2 * MOTION_MIN_PAIRS:
        return None
    change = np.array([float(cv2.norm(images[order[k + 1]], images[order[k]], cv2.NORM_L1))
                       / images[order[k]].size for k in pair])
    offsets = np.arange(start_offset_s - window_s, start_offset_s + window_s + MOTION_GRID_S / 2,
                        MOTION_GRID_S)
    shift = np.round(offsets * 1e9).astype(np.int64)
    before = track.beta_deg((times[pair][None, :] + shift[:, None]).ravel()).reshape(
        offsets.size, pair.size)
    after = track.beta_deg((times[pair + 1][None, :] + shift[:, None]).ravel()).reshape(
        offsets.size, pair.size)
    turn = np.abs(after - before)
    score = _correlation(turn, change)
    best = int(np.argmax(score))
    top = score[best]
    # the plateau of the best score around it (every offset there explains the frames alike)
    tie = score >= top - 1e-9
    low = best
    while low > 0 and tie[low - 1]:
        low -= 1
    high = best
    while high < offsets.size - 1 and tie[high + 1]:
        high += 1
    apart_s = max(0.1, track.step_period_s() / 4)
    away = (offsets < offsets[low] - apart_s) | (offsets > offsets[high] + apart_s)
    rival = float(score[away].max()) if away.any() else -1.0
    moving = int(np.count_nonzero(turn[best] > 0))
    at_edge = low == 0 or high == offsets.size - 1
    determined = bool(top - rival >= MOTION_MIN_CONTRAST and not at_edge
                      and MOTION_MIN_PAIRS <= moving <= pair.size - MOTION_MIN_PAIRS)
    # the frame pairs drawn again (a bootstrap): how far the best offset moves with them
    rng = np.random.default_rng(0)
    draws = rng.integers(0, pair.size, size=(MOTION_BOOTSTRAP, pair.size))
    found = np.array([offsets[int(np.argmax(_correlation(turn[:, d], change[d])))]
                      for d in draws])
    spread_s = float(0.5 * np.subtract(*np.percentile(found, [84.0, 16.0])))
    # a draw of the pairs that prefers another basin: the clock hangs on a few pairs
    agree = float(np.mean(np.abs(found - offsets[best]) <= apart_s))
    determined = determined and agree >= MOTION_MIN_AGREEMENT
    return MotionClock(float(0.5 * (offsets[low] + offsets[high])), float(offsets[low]),
                       float(offsets[high]), int(pair.size), moving, float(top), rival,
                       determined, spread_s, agree)


def _correlation(turn: F64, change: F64) -> F64:
    """The correlation of ``change`` (per frame pair) with each row of ``turn``; −1 where a
    row is constant."""
    turn_c = turn - turn.mean(axis=1, keepdims=True)
    change_c = change - change.mean()
    with np.errstate(invalid="ignore", divide="ignore"):
        score = (turn_c @ change_c) / (np.linalg.norm(turn_c, axis=1)
                                       * np.linalg.norm(change_c))
    return np.asarray(np.where(np.isfinite(score), score, -1.0), np.float64)


def camera_with(camera: CameraConfig, x: F64) -> CameraConfig:
    """``camera`` changed by the fit's parameters ``x`` (in :data:`PARAMETERS` units, the time
    offset ignored): rotation vector applied in the platform frame, translation added, focal
    length scaled."""
    delta = Rotation.from_rotvec(np.radians(x[:3])).as_matrix()
    to_platform = delta @ camera_to_platform(camera.pose.rotation_deg)
    euler = Rotation.from_matrix(to_platform @ CAMERA_BASE).as_euler("xyz", degrees=True)
    translation = np.asarray(camera.pose.translation_m, dtype=np.float64) + x[3:6]
    pose = Pose.model_construct(
        translation_m=(float(translation[0]), float(translation[1]), float(translation[2])),
        rotation_deg=(float(euler[0]), float(euler[1]), float(euler[2])))
    scale = float(x[6])
    return camera.model_copy(update={"pose": pose, "fx": camera.fx * scale,
                                     "fy": camera.fy * scale})


@dataclass
class Alignment:
    """How well depth edges land on image edges: the distance (px) from each projected depth
    edge to the nearest image edge, over the depth edges with an image edge within the match
    radius (:data:`MATCH_PX`); ``unmatched`` counts the others."""

    distances_px: F64
    unmatched: int = 0

    @classmethod
    def of(cls, distances_px: F64, match_px: float) -> Alignment:
        """Split raw distances into matched ones and the unmatched count."""
        matched = distances_px <= match_px
        return cls(np.asarray(distances_px[matched], np.float64),
                   int(np.count_nonzero(~matched)))

    @property
    def median_px(self) -> float | None:
        """Median distance, None without points."""
        return float(np.median(self.distances_px)) if self.distances_px.size else None

    @property
    def within_share(self) -> float | None:
        """Share of points within :data:`WITHIN_PX`."""
        if not self.distances_px.size:
            return None
        return float(np.mean(self.distances_px <= WITHIN_PX))

    def as_dict(self) -> dict[str, Any]:
        """The figures for a report."""
        total = int(self.distances_px.size) + self.unmatched
        return {"edge_median_px": self.median_px, "edge_within_2px": self.within_share,
                "edge_points": total,
                "edge_matched_share": self.distances_px.size / total if total else None}


class CameraFit:
    """The fit of one camera's parameters to its frames."""

    def __init__(self, edges: DepthEdges, frames: Sequence[FrameObservation], track: MotorTrack,
                 free: Sequence[str], margin_px: float = 4.0) -> None:
        if not frames:
            raise StageError("frames: no frames of this camera to calibrate from")
        self.edges = edges
        self.frames = list(frames)
        self.track = track
        self.free = np.array([p in free for p in PARAMETERS])
        self.margin_px = margin_px
        self.base = np.array([0, 0, 0, 0, 0, 0, 1.0, 0.0])
        self.times_ns = np.array([f.time_ns for f in self.frames], dtype=np.int64)
        self.rng = np.random.default_rng(0)
        #: How much each edge point counts in the point-to-line passes (:func:`_weigh_edge_lines`:
        #: the points of one edge line share one placement error and count together as one).
        self.point_weight = np.ones(len(edges.xyz))

    def full(self, scaled: F64) -> F64:
        """All parameters (natural units) from the free ones (scaled units)."""
        x = self.base.copy()
        x[self.free] += scaled * _UNITS[self.free]
        return x

    def betas(self, x: F64) -> F64:
        """Platform angle of every frame at the clock offset of ``x``."""
        return self.track.beta_deg(self.times_ns + np.int64(round(x[7] * 1e9)))

    def select_visible(self, x: F64, gate_px: float | None = None) -> None:
        """Each frame's edge points: inside the image and not hidden (a z-buffer of the scan's
        points at 1/8 of the frame's resolution) at the parameters ``x``; with ``gate_px``,
        the fit's subset only those with an image edge that near (as ICP keeps only close
        pairs: a crease between two surfaces of one colour has no image edge and would only
        pull the fit towards the clutter of the textures)."""
        betas = self.betas(x)
        for frame, beta in zip(self.frames, betas, strict=True):
            cam = camera_with(frame.camera, x)
            uv, depth = project_points(self.edges.xyz, cam, float(beta))
            top, bottom = _rows_used(cam, self.margin_px)
            inside = ((depth > 0.1) & (uv[:, 0] >= self.margin_px)
                      & (uv[:, 0] <= cam.width - 1 - self.margin_px)
                      & (uv[:, 1] >= top) & (uv[:, 1] <= bottom))
            candidates = np.flatnonzero(inside)
            if candidates.size:
                nearest = _zbuffer(self.edges.surface, cam, float(beta), 8)
                cell = (uv[candidates] / 8).astype(np.int64)
                limit = nearest[cell[:, 1], cell[:, 0]]
                seen = depth[candidates] <= limit * 1.03 + 0.03
                candidates = candidates[seen]
            frame.all_edges = candidates
            if gate_px is not None and candidates.size:
                near_uv = uv[candidates]
                found = map_coordinates(frame.distance, [near_uv[:, 1], near_uv[:, 0]], order=1,
                                        mode="nearest")
                candidates = candidates[found <= gate_px]
            if candidates.size > FIT_POINTS_PER_FRAME:
                candidates = np.sort(self.rng.choice(candidates, FIT_POINTS_PER_FRAME,
                                                     replace=False))
            frame.edges = candidates

    def _lookup(self, x: F64, sigma_px: float, truncate_px: float, fit_subset: bool,
                weighted: bool) -> F64:
        """The (blurred, truncated) distance map at every projected edge point of every
        frame: the fit's subset or all the frame sees; ``weighted`` divides each frame's by
        √n so that every frame counts alike."""
        betas = self.betas(x)
        out = []
        for frame, beta in zip(self.frames, betas, strict=True):
            chosen = frame.edges if fit_subset else frame.all_edges
            if chosen.size == 0:
                continue
            cam = camera_with(frame.camera, x)
            uv, depth = project_points(self.edges.xyz[chosen], cam, float(beta))
            values = map_coordinates(frame.blurred(sigma_px), [uv[:, 1], uv[:, 0]], order=1,
                                     mode="constant", cval=truncate_px)
            values[depth <= 0] = truncate_px
            values = np.minimum(values, truncate_px)
            out.append(values * math.sqrt(frame.weight / chosen.size) if weighted else values)
        return np.concatenate(out) if out else np.zeros(0)

    def residuals(self, scaled: F64, sigma_px: float, truncate_px: float) -> F64:
        """The least-squares residuals: truncated distances, each frame weighted alike."""
        return self._lookup(self.full(scaled), sigma_px, truncate_px, fit_subset=True,
                            weighted=True)

    def match_radius_px(self) -> float:
        """The match radius (px) for this camera's frames: :data:`MATCH_PX` per 1000 px."""
        return MATCH_PX * max(self.frames[0].camera.width, self.frames[0].camera.height) / 1000.0

    def alignment(self, x: F64) -> Alignment:
        """The distances at ``x`` (the figures before and after): every edge point each
        frame sees, to the sub-pixel line of the nearest image edge that runs its way."""
        radius = self.match_radius_px()
        distances, unmatched = [], 0
        for _, _, _, residual, total in self.matches(x, radius, fit_subset=False):
            distances.append(np.abs(residual))
            unmatched += total - residual.size
        values = np.concatenate(distances) if distances else np.zeros(0)
        return Alignment(np.asarray(values, np.float64), unmatched)

    def _edge_projection(self, chosen: NDArray[np.int64], cam: CameraConfig,
                         beta: float) -> tuple[F64, F64, B]:
        """Projected edge points, their unit image normals and which are usable (in front
        of the camera, not running along the view ray)."""
        uv, depth = project_points(self.edges.xyz[chosen], cam, beta)
        ahead, _ = project_points(self.edges.xyz[chosen] + 0.02 * self.edges.tangent[chosen],
                                  cam, beta)
        along = ahead - uv
        length = np.hypot(along[:, 0], along[:, 1])
        usable = (depth > 0) & (length > 0.05)
        with np.errstate(invalid="ignore", divide="ignore"):
            normal = np.column_stack([-along[:, 1], along[:, 0]]) / length[:, None]
        return uv, np.nan_to_num(normal), usable

    def matches(self, x: F64, gate_px: float, fit_subset: bool = True
                ) -> list[tuple[int, NDArray[np.int64], NDArray[np.int64], F64, int]]:
        """Per frame: (frame index, matched edge points, their image edge pixels, signed
        point-to-line distances at ``x``, points tried). An edge point is matched with the
        nearest image edge pixel (placed to a fraction of a pixel) within ``gate_px`` that
        runs within :data:`MAX_ANGLE_DEG` of its projected direction; the distance is along
        that pixel's normal (ICP's point-to-line)."""
        betas = self.betas(x)
        cos_limit = math.cos(math.radians(2 * MAX_ANGLE_DEG))
        out = []
        for i, (frame, beta) in enumerate(zip(self.frames, betas, strict=True)):
            chosen = frame.edges if fit_subset else frame.all_edges
            if chosen.size == 0 or frame.edge_uv.shape[0] == 0:
                continue
            cam = camera_with(frame.camera, x)
            uv, normal, usable = self._edge_projection(chosen, cam, float(beta))
            reach = math.hypot(gate_px, 2 * ORIENTATION_PX)
            _, nearest = frame.tree().query(_oriented(uv, normal), k=1,
                                            distance_upper_bound=reach)
            found = usable & (nearest < frame.edge_uv.shape[0])
            pixel = np.where(found, nearest, 0)
            q, n = frame.edge_uv[pixel], frame.edge_normal[pixel]
            residual = np.sum((uv - q) * n, axis=1)
            gap = np.hypot(*(uv - q).T)
            agree = np.abs(np.sum(normal * n, axis=1))
            cos_double = 2.0 * agree**2 - 1.0
            found &= (gap <= gate_px) & (cos_double >= cos_limit)
            out.append((i, chosen[found], pixel[found], residual[found], int(chosen.size)))
        return out

    def line_score(self, scaled: F64, gate_px: float) -> float:
        """The truncated point-to-line cost at ``scaled`` over every edge point the frames
        see (``all_edges``): soft-L1 of each matched point's distance, and of ``gate_px`` for
        one with no image edge within the gate; the frames weighted, per point. Comparable
        between parameters (the same points), unlike a fit's cost over its own matches."""
        cap = 2.0 * (math.sqrt(1.0 + gate_px**2) - 1.0)
        total = weight = 0.0
        for i, _, _, residual, tried in self.matches(self.full(scaled), gate_px,
                                                     fit_subset=False):
            rho = 2.0 * (np.sqrt(1.0 + residual**2) - 1.0)
            frame_weight = self.frames[i].weight
            total += frame_weight * (float(np.sum(rho)) + cap * (tried - residual.size))
            weight += frame_weight * tried
        return total / weight if weight > 0 else math.inf

    def line_residuals(self, scaled: F64,
                       pairs: list[tuple[int, NDArray[np.int64], NDArray[np.int64], F64, int]],
                       moved_m: F64 | None = None) -> F64:
        """Signed point-to-line distances of fixed matches at ``scaled``, each frame
        weighted alike and each point by :attr:`point_weight` (``moved_m``: every edge point
        moved by this, rig frame, for the placement's derivative)."""
        x = self.full(scaled)
        betas = self.betas(x)
        xyz = self.edges.xyz if moved_m is None else self.edges.xyz + moved_m
        out = []
        for i, points, pixels, _, _ in pairs:
            if points.size == 0:
                continue
            frame = self.frames[i]
            uv, _ = project_points(xyz[points], camera_with(frame.camera, x), float(betas[i]))
            residual = np.sum((uv - frame.edge_uv[pixels]) * frame.edge_normal[pixels], axis=1)
            out.append(residual * np.sqrt(frame.weight * self.point_weight[points]))
        return np.concatenate(out) if out else np.zeros(0)

    def solve_lines(self, scaled: F64, gate_px: float = 3.0, rounds: int = 8,
                    max_nfev: int = 30, only: B | None = None) -> tuple[F64, Any]:
        """The final fit: rounds of matching (:meth:`matches`) and a robust least-squares
        fit of the point-to-line distances, until the parameters settle (``only``: a mask of
        the free parameters to move; the others stay)."""
        moving = np.ones(len(scaled), dtype=bool) if only is None else only
        result: Any = None
        for _ in range(rounds):
            pairs = self.matches(self.full(scaled), gate_px)
            if sum(p[1].size for p in pairs) < 10:
                break

            def residuals(sub: F64, pairs: Any = pairs, base: F64 = scaled) -> F64:
                full = base.copy()
                full[moving] = sub
                return self.line_residuals(full, pairs)

            result = least_squares(residuals, scaled[moving], method="trf", x_scale=1.0,
                                   max_nfev=max_nfev, loss="soft_l1", f_scale=1.0,
                                   diff_step=1e-3)
            moved = float(np.max(np.abs(result.x - scaled[moving]))) if moving.any() else 0.0
            scaled = scaled.copy()
            scaled[moving] = result.x
            if moved < 0.05:
                break
        if result is None:
            raise StageError("frames: no depth edge matches an image edge; nothing to "
                             "calibrate against")
        return scaled, result

    def solve(self, scaled: F64, sigma_px: float, truncate_px: float,
              max_nfev: int = 60, only: B | None = None) -> tuple[F64, Any]:
        """One least-squares fit of the free parameters at one scale (``only``: a mask of the
        free parameters to move; the others stay)."""
        moving = np.ones(len(scaled), dtype=bool) if only is None else only
        step = max(0.5, 0.25 * sigma_px)  # finite differences across the map's kinks

        def residuals(sub: F64) -> F64:
            full = scaled.copy()
            full[moving] = sub
            return self.residuals(full, sigma_px, truncate_px)

        def jacobian(sub: F64) -> F64:
            base = residuals(sub)
            columns = []
            for k in range(len(sub)):
                trial = sub.copy()
                trial[k] += step
                columns.append((residuals(trial) - base) / step)
            return np.stack(columns, axis=1)

        result = least_squares(residuals, scaled[moving], jac=jacobian, method="trf",
                               x_scale=1.0, max_nfev=max_nfev, loss="soft_l1",
                               f_scale=max(1.0, sigma_px))
        out = scaled.copy()
        out[moving] = result.x
        return out, result


#: A 360° (equirect) frame is used within this latitude: towards the poles one pixel spans
#: ever less longitude, an edge's image direction turns within a few pixels (the point-to-line
#: match assumes a straight edge), and the floor right under the rig is mostly the rig itself.
EQUIRECT_MAX_LATITUDE_DEG = 60.0


def _rows_used(cam: CameraConfig, margin_px: float) -> tuple[float, float]:
    """The first and last image row (px) whose edges the fit uses."""
    if cam.model == "equirect":
        band = cam.height * (0.5 - EQUIRECT_MAX_LATITUDE_DEG / 180.0)
        return max(margin_px, band), cam.height - 1 - max(margin_px, band)
    return margin_px, cam.height - 1 - margin_px


def _zbuffer(points: F64, cam: CameraConfig, beta_deg: float, cell_px: int) -> F64:
    """The nearest depth per ``cell_px`` cell of the frame (inf where no point lands)."""
    uv, depth = project_points(points, cam, beta_deg)
    width, height = math.ceil(cam.width / cell_px), math.ceil(cam.height / cell_px)
    col = np.floor(uv[:, 0] / cell_px)
    row = np.floor(uv[:, 1] / cell_px)
    ok = (depth > 0.05) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    nearest = np.full(width * height, np.inf)
    np.minimum.at(nearest, (row[ok] * width + col[ok]).astype(np.int64), depth[ok])
    grid = nearest.reshape(height, width)
    # a cell a point missed (sparse scan, far surface) takes its neighbours' nearest depth
    return np.asarray(np.minimum(grid, cv2.erode(np.where(np.isfinite(grid), grid, 1e9).astype(
        np.float32), np.ones((3, 3), np.uint8)).astype(np.float64)), np.float64)


@dataclass
class ParameterResult:
    """One calibrated value: the change found, its 1σ, and whether the data determine it."""

    name: str
    change: float
    sigma: float | None
    observable: bool
    fitted: bool
    #: Whether the change was applied (an observable value, or one over its 1σ limit that
    #: moved :data:`SIGNIFICANT_SIGMAS` or more); False: the rig's value was kept.
    applied: bool = True


#: Two fitted values whose correlation is at least this in size are reported as trading.
TRADE_OFF = 0.9


def _parameter_correlation(result: Any) -> F64:
    """The correlation matrix of the fitted values from the curvature at the solution
    (``(JᵀJ)⁻¹`` normalised); NaN where J is singular."""
    jac = np.asarray(result.jac, dtype=np.float64)
    try:
        cov = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return np.full((jac.shape[1], jac.shape[1]), np.nan)
    scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return np.asarray(np.clip(cov / np.outer(scale, scale), -1.0, 1.0), np.float64)


@dataclass
class CameraCalibration:
    """The result for one camera."""

    camera_id: str
    before: CameraConfig
    after: CameraConfig
    time_offset_s: float | None
    parameters: list[ParameterResult]
    alignment_before: Alignment
    alignment_after: Alignment
    frames: int
    edge_points: int
    warnings: list[str] = field(default_factory=list)
    #: With a clock offset fitted: whether some frames show the platform standing still.
    still_frames: bool = True
    #: With a clock offset fitted: False when it is not determined (competing basins of the
    #: cost, or its 1σ over the limit: the rig's/start value is kept); None without one.
    time_offset_determined: bool | None = None
    #: The clock read from the video's own motion (:class:`MotionClock`), when its frames
    #: follow each other closely enough.
    motion_clock: dict[str, Any] | None = None
    #: The fitted values' names and their correlation matrix at the solution (curvature):
    #: values near ±1 trade (a tilt against a height, a dolly against a zoom); None where it
    #: is not known (a singular curvature), never a 0 that would read as "independent".
    correlation_names: list[str] = field(default_factory=list)
    correlation: list[list[float | None]] = field(default_factory=list)

    def trade_offs(self, threshold: float = TRADE_OFF) -> list[tuple[str, str, float]]:
        """The pairs of fitted values whose correlation is at least ``threshold`` in size:
        each is known only together with the other."""
        out = []
        for i, j in itertools.combinations(range(len(self.correlation_names)), 2):
            r = self.correlation[i][j]
            if r is not None and abs(r) >= threshold:
                out.append((self.correlation_names[i], self.correlation_names[j], r))
        return out

    def report(self) -> dict[str, Any]:
        """The calibration as JSON-ready values."""
        return {
            "camera_id": self.camera_id, "frames": self.frames, "edge_points": self.edge_points,
            "rotation_deg_before": list(self.before.pose.rotation_deg),
            "rotation_deg_after": list(self.after.pose.rotation_deg),
            "translation_m_before": list(self.before.pose.translation_m),
            "translation_m_after": list(self.after.pose.translation_m),
            "fx_before": self.before.fx, "fx_after": self.after.fx,
            "fy_before": self.before.fy, "fy_after": self.after.fy,
            "time_offset_s": self.time_offset_s,
            "time_offset_determined": self.time_offset_determined,
            "parameters": [{"name": p.name, "change": p.change, "sigma": p.sigma,
                            "observable": p.observable, "fitted": p.fitted,
                            "applied": p.applied}
                           for p in self.parameters],
            "alignment_before": self.alignment_before.as_dict(),
            "alignment_after": self.alignment_after.as_dict(),
            "motion_clock": self.motion_clock,
            "correlation": {"names": list(self.correlation_names),
                            "matrix": [list(row) for row in self.correlation]},
            "trade_offs": [{"values": [a, b], "correlation": r}
                           for a, b, r in self.trade_offs()],
            "warnings": list(self.warnings),
        }


#: Blur σ of the distance transform per pass, as a fraction of the focal length (px): the first
#: pass's basin holds a mount a few degrees and centimetres off; the last is at 1 px. The
#: distances are truncated at :data:`TRUNCATE` σ.
LEVELS = (0.02, 0.007, 0.0025, 0.0)
FINAL_SIGMA_PX = 1.0
TRUNCATE = 5.0
#: The final point-to-line fit matches depth edges with image edges within this many pixels
#: (per 1000 px of focal length, at least this); a first round takes twice as far.
LINE_GATE_PX = 2.0
LINE_GATE_STEPS = (2.0, 1.0)
#: Weigh the point-to-line passes by edge line (:func:`_weigh_edge_lines`), not point by point.
WEIGH_EDGE_LINES = False


def _levels(camera: CameraConfig) -> list[tuple[float, float]]:
    """``(σ, truncation)`` in pixels of each pass for ``camera``."""
    focal = camera.px_per_rad
    sigmas = [max(FINAL_SIGMA_PX, f * focal) for f in LEVELS]
    return [(s, TRUNCATE * s) for s in sigmas]


def calibrate_camera(edges: DepthEdges, frames: Sequence[FrameObservation], track: MotorTrack,
                     fit_time_offset: bool = False, time_window_s: float = 1.0,
                     start_offset_s: float = 0.0, jackknife_groups: int = 4,
                     fit_focal: bool = True, motion: MotionClock | None = None
                     ) -> CameraCalibration:
    """Fit one camera (all ``frames`` are of it) and report values, 1σ and alignment.

    With ``fit_time_offset`` and a determined ``motion`` clock (:func:`motion_clock`), the
    clock is the motion's and the edges fit the mount at it, as for recorded frames: the
    edges alone cannot tell a clock from a turn of the camera about the axis."""
    camera = frames[0].camera
    motion_fixed = fit_time_offset and motion is not None and motion.trusted
    if motion is not None and motion_fixed:
        start_offset_s = motion.offset_s
        fit_time_offset = False
    # a 360° image has no focal length: its scale is fixed by the sphere (width = 360°)
    fit_focal = fit_focal and camera.model == "pinhole"
    free = [p for p in PARAMETERS if (p != "time_offset_s" or fit_time_offset)
            and (p != "focal_scale" or fit_focal)]
    fit = CameraFit(edges, frames, track, free)
    fit.base[7] = start_offset_s
    levels = _levels(camera)
    warnings: list[str] = []
    start = np.zeros(int(fit.free.sum()))
    fit.select_visible(fit.full(start))
    before = fit.alignment(fit.full(start))
    if before.distances_px.size < 50:
        raise StageError(f"camera {camera.id!r}: only {before.distances_px.size} depth-edge "
                         "points fall into its frames; nothing to calibrate against (is the "
                         "camera looking at the scanned scene?)")
    x = start
    names = [p for p in PARAMETERS if p in free]
    rotation_and_time = np.array([n.startswith("rot_") or n == "time_offset_s" for n in names])
    first_level = 0
    determined = True
    spread_s = 0.0
    if fit_time_offset:
        # The mount first from the frames of the platform standing still (whatever the
        # clock), then the clock from all frames with that mount, then both together.
        x = _fit_mount_on_still_frames(fit, x, levels, time_window_s)
        _weigh_still_frames(fit, time_window_s)
        first_level = 1
        starts = _scan_time_offset(fit, x, time_window_s, *levels[first_level])
        # every coarse basin that competes with the best is refined; the final cost picks
        ends = [_descend(fit, s, levels, first_level, rotation_and_time, True) for s in starts]
        # the other basins along the valley where a clock shift and a turn about the axis trade
        # (a mount fitted to the still frames of one view can be off by such a turn)
        valley = _valley_starts(fit, ends[0], time_window_s, levels[first_level])
        ends += [_descend(fit, s, levels, first_level, rotation_and_time, True) for s in valley]
        x = ends[0]
        if len(ends) > 1:
            scores = [_basin_score(fit, e, levels[-1]) for e in ends]
            offsets_s = np.array([fit.full(e)[7] for e in ends])
            pick, rivals = _pick_basin(offsets_s, np.array(scores))
            x = ends[pick]
            fit.select_visible(fit.full(x), gate_px=levels[-1][1])
        if len(ends) > 1 and rivals.size:
            determined = False
            spread_s = float(np.max(np.abs(offsets_s[rivals] - offsets_s[pick])))
            listed = ", ".join(f"{offsets_s[i]:+.3f} s (cost {scores[i]:.3g})"
                               for i in [pick, *rivals.tolist()])
            warnings.append(f"camera {camera.id!r}: the clock offset is not determined: "
                            f"the edges fit alike at {listed}: a clock offset looks like a "
                            "turn of the camera about the axis, and the frames of the platform "
                            "standing still do not pin that turn (film it still from more than "
                            "one side, or start from an offset known within "
                            f"±{spread_s / 2:.2f} s)")
    else:
        x = _descend(fit, x, levels, first_level, rotation_and_time, False)
    # the last pass: point-to-line distances to the sub-pixel image edges that run the depth
    # edges' way (the distance map's pixels and blur leave a bias of a fraction of a pixel)
    # the last pass point to line — for the mount alone: with a clock offset to find, a frame
    # of the turning platform a little off in time matches nothing within a few pixels' gate,
    # and the clock stays with the finest distance map (see docs/calibration.md, "Cameras")
    gate = LINE_GATE_PX * max(1.0, camera.px_per_rad / 1000.0)
    lines = not fit_time_offset
    if fit_time_offset:
        # the basin is chosen: from here every VIEW counts alike. The still frames and those
        # where the platform starts and stops show two views (β at the start and at the end)
        # in half the frames, and each view's scan edges carry the same placement errors in
        # all its frames: weighted so, the mount slid along the valleys one view leaves open
        # (tilt against height, dolly against zoom: benchmark seed 1, 0.33° and 6 cm off
        # with its clock right)
        _weigh_views_alike(fit, fit.full(x))
        # and the mount fitted afresh from the rig's at that clock, as without one (the
        # joint passes from the still frames' turn can end far along those valleys: seed 3,
        # 1.8° and 28 cm off with its clock within 13 ms); then everything together below
        clock = np.array([n == "time_offset_s" for n in names])
        x = np.where(clock, x, 0.0)
        rotation = np.array([n.startswith("rot_") for n in names])
        x = _descend(fit, x, levels, 0, rotation, True, rest=~clock)
    support_spread = np.zeros(len(x))
    if lines:
        x, result, other = _line_passes(fit, x, gate, levels[-1])
        # the two supports' results apart: how much the answer hangs on which edges it
        # starts from (the scan's placement errors, shared by every frame, that no frame
        # jackknife sees)
        support_spread = 0.5 * np.abs(x - other)
    else:
        x, result = _final_fit(fit, x, gate, levels[-1], False)
    if fit_time_offset:
        x = _mount_on_lines(fit, x, gate, levels[-1], names)
    # the curvature sees the images' noise, the placement the scan's sampling: they add
    curvature = np.hypot(_curvature_sigma(result), _placement_sigma(fit, x, gate))
    correlation = _parameter_correlation(result)
    spread = _jackknife_sigma(fit, x, gate, levels[-1], lines, jackknife_groups)
    if camera.model == "equirect":  # every frame sees the whole scene: leave parts of it out
        spread = np.fmax(spread, _scene_jackknife_sigma(fit, x, gate, levels[-1], lines,
                                                        jackknife_groups))
    spread = np.fmax(spread, _edge_jackknife_sigma(fit, x, gate, levels[-1], lines))
    sigma_scaled = np.fmax(np.fmax(curvature, spread), support_spread)
    if spread_s > 0:  # the 1σ covers the competing basins: never a confident wrong offset
        k = names.index("time_offset_s")
        sigma_scaled[k] = max(float(sigma_scaled[k]), spread_s / _UNITS[7])
    results: list[ParameterResult] = []
    observable = np.ones(len(names), dtype=bool)
    # a mount value over its limit still moves when the move is far beyond its 1σ: a camera
    # 2° off that the fit puts right to ±0.4° is better served by the fit than by the rig
    applied = np.ones(len(names), dtype=bool)
    for i, name in enumerate(names):
        sigma_value = float(sigma_scaled[i] * _UNITS[PARAMETERS.index(name)])
        ok = bool(np.isfinite(sigma_value)) and sigma_value <= SIGMA_LIMITS[name]
        observable[i] = ok
        if ok:
            continue
        ratio = abs(float(x[i])) / float(sigma_scaled[i]) if np.isfinite(sigma_scaled[i]) \
            else 0.0
        applied[i] = name != "time_offset_s" and ratio >= SIGNIFICANT_SIGMAS
        outcome = (f"applied, being {ratio:.1f}σ from the rig's value" if applied[i]
                   else "kept")
        warnings.append(f"camera {camera.id!r}: {name} is not determined by these frames "
                        f"(1σ {sigma_value:.3g}, limit {SIGMA_LIMITS[name]:g}); {outcome}")
    if not applied.all():
        start = np.where(applied, x, 0.0)
        kept = fit.free.copy()
        kept[fit.free] = applied
        refit = CameraFit(edges, frames, track, [p for p, k in zip(PARAMETERS, kept,
                                                                    strict=True) if k])
        refit.base = fit.base
        refit.frames = fit.frames
        refit.point_weight = fit.point_weight
        x = np.zeros(len(names))
        if applied.any():
            x[applied], _ = _final_fit(refit, start[applied], gate, levels[-1], lines)
            # what the held values' errors push into the others: a value that moved when
            # they were held is known no better than that move (the coarse test scan: the
            # tilt took 0.3° from a depth and focal length kept 3 cm and 2 % off)
            held = ", ".join(n for n, a in zip(names, applied, strict=True) if not a)
            for j in np.flatnonzero(applied).tolist():
                sigma_scaled[j] = max(float(sigma_scaled[j]), abs(float(x[j] - start[j])))
                name = names[j]
                sigma_value = float(sigma_scaled[j] * _UNITS[PARAMETERS.index(name)])
                if observable[j] and sigma_value > SIGMA_LIMITS[name]:
                    observable[j] = False
                    warnings.append(f"camera {camera.id!r}: {name} is not determined with "
                                    f"{held} kept (it moves by {sigma_value:.3g} when they "
                                    "are held: their errors go into it); applied")
    final = fit.full(x)
    for i, name in enumerate(names):
        k = PARAMETERS.index(name)
        change = float(final[k] - (1.0 if name == "focal_scale" else 0.0))
        if name == "time_offset_s":
            change = float(final[k])
        results.append(ParameterResult(name, change,
                                       float(sigma_scaled[i] * _UNITS[k])
                                       if np.isfinite(sigma_scaled[i]) else None,
                                       bool(observable[i]), True, bool(applied[i])))
    for p in results:
        if p.name.startswith("rot_") and p.observable and p.sigma is not None \
                and PRECISION_SIGMAS * p.sigma > ROTATION_AIM_DEG:
            warnings.append(f"camera {camera.id!r}: {p.name} is known only to ±{p.sigma:.3f}° "
                            f"(1σ; {PRECISION_SIGMAS:g}σ {PRECISION_SIGMAS * p.sigma:.2f}° > "
                            f"{ROTATION_AIM_DEG:g}°): the scan places its edges only to ± half "
                            "a step (scan with a finer motor step, or give the camera more "
                            "views)")
    clock_determined = bool(determined and observable[names.index("time_offset_s")]) \
        if fit_time_offset else None
    if motion is not None and motion_fixed:
        clock_determined = True
        results.append(ParameterResult("time_offset_s", float(final[7]), motion.sigma_s,
                                       True, True, True))
    elif motion is not None and fit_time_offset:
        warnings.append(f"camera {camera.id!r}: the video's own motion did not determine the "
                        f"clock (best {motion.offset_s:+.3f} s ± {motion.sigma_s * 1000:.0f} ms, "
                        f"correlation {motion.score:.2f} against {motion.rival_score:.2f} "
                        f"elsewhere, {motion.moving_pairs} of {motion.pairs} frame pairs "
                        "moving); fitted from the edges instead (keep filming through the "
                        "platform's start and stop)")
    if clock_determined is False:
        # the mount was refitted at the start offset; a clock offset looks like a turn about
        # the axis (and, off the axis, a shift): never report those as known
        for p in results:
            if p.name in ("rot_x_deg", "rot_y_deg", "rot_z_deg", "tx_m", "tz_m"):
                p.observable = False
        warnings.append(f"camera {camera.id!r}: the clock offset is not determined, so neither "
                        "is the mount's turn about the platform's axis (a clock offset looks "
                        f"like one): the mount values hold only with the clock at "
                        f"{final[7]:+.3f} s and are not determined")
    if not np.isfinite(correlation).all():
        warnings.append(f"camera {camera.id!r}: the fit's curvature is singular: which fitted "
                        "values trade against each other is not known (correlations null)")
    after_camera = camera_with(_rig_camera(camera, track.rig), final)
    after = fit.alignment(final)
    if after.median_px is not None and before.median_px is not None \
            and after.median_px > before.median_px:
        warnings.append(f"camera {camera.id!r}: the edges align worse after the fit "
                        f"({before.median_px:.2f} → {after.median_px:.2f} px median); check the "
                        "frames and the scan")
    still = not fit_time_offset or _has_still_frames(fit, final)
    if not still:
        warnings.append(f"camera {camera.id!r}: no frames while the platform stands still "
                        "(before or after the scan); the clock offset and the camera's turn "
                        "about the axis are found only together")
    return CameraCalibration(
        camera_id=camera.id, before=_rig_camera(camera, track.rig), after=after_camera,
        time_offset_s=float(final[7]) if fit_time_offset or motion_fixed else None,
        parameters=results,
        alignment_before=before, alignment_after=after, frames=len(frames),
        edge_points=int(after.distances_px.size), warnings=warnings, still_frames=still,
        time_offset_determined=clock_determined,
        motion_clock=motion.as_dict() if motion is not None else None,
        correlation_names=names, correlation=_known_correlations(correlation))


def _known_correlations(correlation: F64) -> list[list[float | None]]:
    """The correlation matrix rounded for the report, None where it is not known (NaN)."""
    return [[None if not math.isfinite(r) else round(float(r), 3) for r in row]
            for row in correlation]


def _mount_on_lines(fit: CameraFit, x: F64, gate_px: float, level: tuple[float, float],
                    names: list[str]) -> F64:
    """With the clock found on the distance map, the mount point to line (the clock held),
    the clock once more on the finest map (the mount held), and the mount again: the distance
    map's own minimum lies a fraction of a pixel off (its whole pixels, its blur, the texture
    it lands on), and with the clock within a few tens of ms the turning platform's frames
    match their image edges within the gate."""
    time_only = np.array([n == "time_offset_s" for n in names])
    mount = ~time_only
    _ungate(fit, x)
    for passes in range(2):
        for widen in LINE_GATE_STEPS:
            try:
                x, _ = fit.solve_lines(x, widen * gate_px, rounds=4, max_nfev=60, only=mount)
            except StageError:  # nothing matched within the gate: keep the map's values
                return x
        if passes == 0:
            x, _ = fit.solve(x, *level, max_nfev=30, only=time_only)
    return x


def _line_passes(fit: CameraFit, x: F64, gate_px: float, level: tuple[float, float]
                 ) -> tuple[F64, Any, F64]:
    """The point-to-line passes after the distance maps (:func:`_final_fit`), from two
    supports: the edge points the last map kept (an image edge within its truncation at its
    minimum) and every edge point the frames see (:func:`_ungate`). The result that fits
    every visible edge point better (:meth:`CameraFit.line_score`) wins, and its support
    stays for the 1σ. Returns the winner, its least-squares result and the other result.

    The map's subset agrees with the map's minimum, and from it the line passes stayed near
    that minimum at lab scale (Full-HD: 0.20° off along the tilt–height valley, 0.04° from
    every visible point); on a coarse scan (1° steps, 0.19° per pixel) every visible point
    let creases without an image edge pull towards the textures' clutter (0.60° against
    0.34°). The truncated cost over all visible points, the same set for both, tells which.
    """
    kept = [frame.edges for frame in fit.frames]
    if WEIGH_EDGE_LINES:
        _weigh_edge_lines(fit, x)
    x_kept, result_kept = _final_fit(fit, x, gate_px, level, True)
    score_kept = fit.line_score(x_kept, gate_px)
    _ungate(fit, x)
    x_all, result_all = _final_fit(fit, x, gate_px, level, True)
    if fit.line_score(x_all, gate_px) <= score_kept:
        return x_all, result_all, x_kept
    for frame, edges in zip(fit.frames, kept, strict=True):
        frame.edges = edges
    return x_kept, result_kept, x_all


def _ungate(fit: CameraFit, x: F64) -> None:
    """Before the point-to-line passes: every edge point each frame sees at ``x``, not only
    those the last distance map found near an image edge.

    The line passes gate by their own matching, renewed every round; a subset kept by the
    distance map's gate at the map's minimum is the subset that agrees with that minimum, and
    the line passes then stay near it (lab scale, Full-HD: the map ended 0.57° and 36 mm off
    along the tilt–height valley, and the line passes on its subset stopped at 0.20° and
    13 mm; on every visible edge point they reach 0.04° and 2 mm).
    """
    fit.select_visible(fit.full(x))


def _rig_camera(camera: CameraConfig, rig: Rig) -> CameraConfig:
    """The rig's own camera of ``camera`` (which may be sized to its frames); the fit's changes
    (rotation, translation, focal scale) hold at any resolution."""
    return next((c for c in rig.cameras if c.id == camera.id), camera)


def _fit_mount_on_still_frames(fit: CameraFit, x: F64, levels: list[tuple[float, float]],
                               window_s: float) -> F64:
    """The mount fitted (two coarse passes) to the frames that show the platform standing
    still even at the ends of the clock's search window; ``x`` unchanged without two such."""
    still = _still_mask(fit, window_s)
    if np.count_nonzero(still) < 2:
        return x
    everything, all_times = fit.frames, fit.times_ns
    fit.frames = [f for f, s in zip(everything, still, strict=True) if s]
    fit.times_ns = all_times[still]
    rotation = np.zeros(len(x), dtype=bool)
    rotation[:3] = True
    try:
        fit.select_visible(fit.full(x))
        for level in (0, 1):  # two views: the shift and the focal length wait for the rest
            x, _ = fit.solve(x, *levels[level], only=rotation)
            fit.select_visible(fit.full(x), gate_px=levels[level + 1][1])
    finally:
        fit.frames, fit.times_ns = everything, all_times
    return x


def _still_mask(fit: CameraFit, window_s: float) -> B:
    """Frames that show the platform standing still even at the ends of the search window."""
    first, last = fit.track.moving_span_ns()
    times = fit.times_ns + np.int64(round(fit.base[7] * 1e9))
    margin = np.int64(round(window_s * 1e9))
    return np.asarray((times < first - margin) | (times > last + margin), dtype=bool)


#: Frames whose platform angles lie within this of each other show one view.
VIEW_BIN_DEG = 5.0


def _weigh_views_alike(fit: CameraFit, x: F64) -> None:
    """Weigh each frame by one over the number of frames that show its view (the platform
    angle at the clock of ``x`` within :data:`VIEW_BIN_DEG`), the mean weight one."""
    views = np.floor(fit.betas(x) / VIEW_BIN_DEG).astype(np.int64)
    _, inverse, counts = np.unique(views, return_inverse=True, return_counts=True)
    weights = 1.0 / counts[inverse]
    weights *= len(weights) / float(np.sum(weights))
    for frame, weight in zip(fit.frames, weights, strict=True):
        frame.weight = float(weight)


def _weigh_still_frames(fit: CameraFit, window_s: float) -> None:
    """Give the still frames together the weight of all the others: only they hold the
    camera's turn about the axis apart from the clock offset."""
    still = _still_mask(fit, window_s)
    count = int(np.count_nonzero(still))
    if 0 < count < len(still):
        for frame, is_still in zip(fit.frames, still, strict=True):
            frame.weight = (len(still) - count) / count if is_still else 1.0


def _scan_time_offset(fit: CameraFit, x: F64, window_s: float, sigma_px: float,
                      truncate_px: float) -> list[F64]:
    """Starts for the clock offset from the cost over ``base ± window_s`` (other values kept),
    scanned at 20 ms steps: the least cost first, then the other basins that compete with it
    (:func:`_coarse_basins`)."""
    steps = np.linspace(-window_s, window_s, max(21, round(2 * window_s / 0.02) + 1))
    index = int(np.flatnonzero(fit.free[:7]).size)  # the time offset is the last free one
    costs = np.empty(len(steps))
    for i, dt in enumerate(steps):
        trial = x.copy()
        trial[index] = dt / _UNITS[7]
        costs[i] = float(np.sum(fit.residuals(trial, sigma_px, truncate_px) ** 2))
    starts = []
    for k in _coarse_basins(costs):
        start = x.copy()
        start[index] = steps[k] / _UNITS[7]
        starts.append(start)
    return starts


#: A coarse basin competes when its least cost lies within this share of the cost curve's
#: depth (its highest minus its least value) above the best one, parted from every other by a
#: ridge higher than this share (ripples along one valley are not basins: a flat valley with
#: two dips is, as in benchmark seed 2); at most this many are refined.
BASIN_MARGIN = 0.35
RIDGE_SHARE = 0.015
MAX_BASINS = 3
#: Refined basins whose offsets differ by more than this (s) and whose final costs lie within
#: this share of each other leave the offset undetermined.
BASIN_APART_S = 0.05
FINAL_MARGIN = 0.05


def _coarse_basins(costs: F64) -> list[int]:
    """Indices of the separate local minima of a scanned cost that compete with the least:
    the least first. A neighbour minimum counts as separate only when a ridge parts them
    (:data:`RIDGE_SHARE`; wiggles of one valley are one basin)."""
    best = int(np.argmin(costs))
    depth = float(np.max(costs) - costs[best])
    if depth <= 0:
        return [best]
    margin, ridge = BASIN_MARGIN * depth, RIDGE_SHARE * depth
    inner = np.flatnonzero((costs[1:-1] <= costs[:-2]) & (costs[1:-1] <= costs[2:])) + 1
    ends = [i for i in (0, len(costs) - 1) if costs[i] <= costs[i - 1 if i else 1]]
    minima = sorted(set(inner.tolist()) | set(ends), key=lambda i: float(costs[i]))
    chosen = [best]
    for i in minima:
        if len(chosen) >= MAX_BASINS or costs[i] - costs[best] > margin:
            break
        # parted from every chosen one by a ridge above both
        if all(np.max(costs[min(i, j):max(i, j) + 1]) - max(costs[i], costs[j]) > ridge
               for j in chosen):
            chosen.append(i)
    return chosen


def _orbit(fit: CameraFit, x: F64, shift_s: float) -> F64:
    """``x`` (scaled) with the clock moved by ``shift_s`` and the camera turned about the
    platform's axis by the platform's mean rate times ``-shift_s``: a point of the valley along
    which a clock offset and the camera's turn trade."""
    first, last = fit.track.moving_span_ns()
    if last <= first:
        return x
    betas = fit.track.beta_deg(np.array([first, last], dtype=np.int64))
    rate_deg_s = float(betas[1] - betas[0]) / ((last - first) * 1e-9)
    turn = platform_rotation(-rate_deg_s * shift_s)
    full = fit.full(x)
    rotation = Rotation.from_matrix(turn) * Rotation.from_rotvec(np.radians(full[:3]))
    full[:3] = np.degrees(rotation.as_rotvec())
    origin = np.asarray(fit.frames[0].camera.pose.translation_m, dtype=np.float64)
    full[3:6] = turn @ (origin + full[3:6]) - origin
    full[7] += shift_s
    out = (full - fit.base)[fit.free] / _UNITS[fit.free]
    return np.asarray(out, np.float64)


def _valley_starts(fit: CameraFit, x: F64, window_s: float, level: tuple[float, float]
                   ) -> list[F64]:
    """Starts in the other competing basins of the cost along the clock-for-turn valley
    through ``x`` (over ± ``window_s``); none without translation free to orbit."""
    if not fit.free[3:6].all():
        return []
    steps = np.linspace(-window_s, window_s, max(21, round(2 * window_s / 0.02) + 1))
    fit.select_visible(fit.full(x))  # ungated: a gate at ``x`` would favour ``x``
    trials = [_orbit(fit, x, float(dt)) for dt in steps]
    costs = np.array([float(np.sum(fit.residuals(t, *level) ** 2)) for t in trials])
    here = int(np.argmin(np.abs(steps)))
    return [trials[k] for k in _coarse_basins(costs) if abs(k - here) > 2]


def _pick_basin(offsets_s: F64, scores: F64) -> tuple[int, NDArray[np.int64]]:
    """The refined basin with the least final cost, and the others that fit alike (within
    :data:`FINAL_MARGIN`) at an offset :data:`BASIN_APART_S` or more away: its rivals."""
    pick = int(np.argmin(scores))
    alike = scores <= scores[pick] * (1.0 + FINAL_MARGIN)
    apart = np.abs(offsets_s - offsets_s[pick]) >= BASIN_APART_S
    return pick, np.flatnonzero(alike & apart)


def _descend(fit: CameraFit, x: F64, levels: list[tuple[float, float]], first_level: int,
             rotation_and_time: B, select_first: bool, rest: B | None = None) -> F64:
    """The coarse-to-fine passes on the distance maps from ``first_level`` on (``select_first``:
    what the frames see chosen at ``x`` first): the coarsest moves the parameters of the mask
    ``rotation_and_time``, the others those of ``rest`` (None: all)."""
    if select_first:
        fit.select_visible(fit.full(x), gate_px=levels[first_level][1])
    for level in range(first_level, len(levels)):
        sigma, truncate = levels[level]
        # the coarsest pass turns the camera (and shifts its clock) only: the rest would
        # wander along the flat valleys of a blurred cost
        x, _ = fit.solve(x, sigma, truncate, only=rotation_and_time if level == 0 else rest)
        if level < len(levels) - 1:  # what each frame sees moves with a changed pose
            fit.select_visible(fit.full(x), gate_px=levels[level + 1][1])
    return x


def _basin_score(fit: CameraFit, x: F64, level: tuple[float, float]) -> float:
    """A basin's final cost, comparable between basins: the mean squared truncated distance
    (finest map) of every edge point the frames see, not the gated subset each fit kept."""
    fit.select_visible(fit.full(x))
    values = fit._lookup(fit.full(x), *level, fit_subset=False, weighted=True)
    weight = sum(f.weight for f in fit.frames if f.all_edges.size)
    return float(np.sum(values ** 2) / max(weight, 1e-12))


def _curvature_sigma(result: Any) -> F64:
    """1σ (scaled units) from ``s² (JᵀJ)⁻¹`` at the solution; inf where J is singular."""
    jac = np.asarray(result.jac, dtype=np.float64)
    residuals = np.asarray(result.fun, dtype=np.float64)
    dof = max(1, len(residuals) - jac.shape[1])
    s2 = float(residuals @ residuals) / dof
    try:
        cov = np.linalg.inv(jac.T @ jac) * s2
    except np.linalg.LinAlgError:
        return np.full(jac.shape[1], np.inf)
    return np.asarray(np.sqrt(np.clip(np.diag(cov), 0, None)), np.float64)


def _final_fit(fit: CameraFit, x: F64, gate_px: float, level: tuple[float, float],
               lines: bool, rounds: int = 8, max_nfev: int | None = None) -> tuple[F64, Any]:
    """The last pass: point to line (the gate widened first) with ``lines``, else on the
    finest distance map; the least-squares result."""
    result: Any = None
    if not lines:
        return fit.solve(x, *level, max_nfev=max_nfev or 60)
    for widen in LINE_GATE_STEPS:
        x, result = fit.solve_lines(x, widen * gate_px, rounds=rounds,
                                    max_nfev=max_nfev or 100)
    return x, result


def _jackknife_sigma(fit: CameraFit, x: F64, gate_px: float, level: tuple[float, float],
                     lines: bool, groups: int) -> F64:
    """1σ (scaled units) from the spread of the fit over groups of frames, each left out."""
    n = len(fit.frames)
    groups = min(groups, n)
    if groups < 3:
        return np.zeros(len(x))
    estimates = []
    everything, all_times = fit.frames, fit.times_ns
    try:
        for g in range(groups):
            fit.frames = [f for i, f in enumerate(everything) if i % groups != g]
            fit.times_ns = np.array([f.time_ns for f in fit.frames], dtype=np.int64)
            estimate, _ = _final_fit(fit, x, gate_px, level, lines, rounds=3, max_nfev=10)
            estimates.append(estimate)
    finally:
        fit.frames, fit.times_ns = everything, all_times
    values = np.array(estimates)
    return np.asarray(np.sqrt((groups - 1) / groups * np.sum(
        (values - values.mean(axis=0)) ** 2, axis=0)), np.float64)


def _scene_jackknife_sigma(fit: CameraFit, x: F64, gate_px: float,
                           level: tuple[float, float], lines: bool, groups: int) -> F64:
    """1σ (scaled units) from the spread of the fit over sectors of the scene (the edge
    points' azimuth about the platform's axis), each left out in turn.

    The scan's edges carry errors of their own (a corner placed a fraction of a cell off, an
    object's outline seen from the scanner and not from the camera), the same in every frame:
    leaving frames out does not show them, leaving parts of the scene out does. A 360° camera
    sees every edge in every frame, so for it this is the only spread there is. (A pinhole
    camera's frames each see one sector: left out, a quarter of the room takes the valleys'
    conditioning with it, and the spread measured the missing quarter, not the error — on the
    benchmark a 0.1° mount read 0.4°: so only for 360° cameras.)
    """
    if groups < 3:
        return np.zeros(len(x))
    azimuth = np.arctan2(fit.edges.xyz[:, 0], fit.edges.xyz[:, 2])
    sector = np.floor((azimuth + np.pi) / (2 * np.pi) * groups).astype(np.int64) % groups
    return _edge_group_jackknife(fit, x, gate_px, level, lines, sector, groups)


#: Edge points within one cube of this size (m) form one piece of an edge line for
#: :func:`_edge_jackknife_sigma`: the scan places a piece as a whole (the same error along it
#: and in every frame); the pieces are dealt at random into this many groups.
EDGE_PIECE_M = 0.5
EDGE_GROUPS = 6


def _edge_jackknife_sigma(fit: CameraFit, x: F64, gate_px: float,
                          level: tuple[float, float], lines: bool) -> F64:
    """1σ (scaled units) from the spread of the fit over groups of the scan's edge pieces
    (cubes of :data:`EDGE_PIECE_M`, dealt at random into :data:`EDGE_GROUPS` groups), each
    group left out in turn.

    A frame jackknife does not see the scan's own edge errors (a silhouette placed a fraction
    of a motor step off is off in every frame), and leaving a sector of the scene out takes
    a pinhole camera's whole view of it (the valleys' conditioning with it): pieces dealt at
    random leave every view with most of its edges and still leave each piece's error out
    in turn (the lab mount's pan: frame jackknife 0.005°, its error 0.025°).
    """
    key = np.floor(fit.edges.xyz / EDGE_PIECE_M).astype(np.int64)
    _, piece = np.unique(key, axis=0, return_inverse=True)
    piece = np.asarray(piece).ravel()
    dealt = np.random.default_rng(0).integers(0, EDGE_GROUPS, int(piece.max()) + 1)
    return _edge_group_jackknife(fit, x, gate_px, level, lines, dealt[piece], EDGE_GROUPS)


def _edge_group_jackknife(fit: CameraFit, x: F64, gate_px: float, level: tuple[float, float],
                          lines: bool, group: NDArray[np.int64], groups: int) -> F64:
    """1σ (scaled units) from the fit repeated with the edge points of each ``group`` label
    left out in turn (the frames keep the rest)."""
    kept = [(frame.edges, frame.all_edges) for frame in fit.frames]
    estimates = []
    try:
        for g in range(groups):
            for frame, (chosen, seen) in zip(fit.frames, kept, strict=True):
                frame.edges = chosen[group[chosen] != g]
                frame.all_edges = seen[group[seen] != g]
            if sum(f.edges.size for f in fit.frames) < 50:
                continue
            estimate, _ = _final_fit(fit, x, gate_px, level, lines, rounds=3, max_nfev=10)
            estimates.append(estimate)
    finally:
        for frame, (chosen, seen) in zip(fit.frames, kept, strict=True):
            frame.edges, frame.all_edges = chosen, seen
    if len(estimates) < 3:
        return np.zeros(len(x))
    values = np.array(estimates)
    n = len(estimates)
    return np.asarray(np.sqrt((n - 1) / n * np.sum(
        (values - values.mean(axis=0)) ** 2, axis=0)), np.float64)


#: The point-to-line noise of one matched edge point (px, the soft-L1 scale of the line
#: passes) against which an edge line's shared placement error is weighed.
POINT_NOISE_PX = 1.0
#: The derivative of the residuals by a placement error is taken over this share of a cell.
_PLACEMENT_STEP = 0.01


def _placement_px(fit: CameraFit, frame: FrameObservation, chosen: NDArray[np.int64], x: F64,
                  beta: float) -> F64:
    """How far (px, across the projected edge line) each of ``chosen`` moves in ``frame`` when
    its point moves by one scan cell (:attr:`DepthEdges.cell`)."""
    if fit.edges.cell.shape != fit.edges.xyz.shape or chosen.size == 0:
        return np.zeros(chosen.size)
    cam = camera_with(frame.camera, x)
    uv, normal, usable = fit._edge_projection(chosen, cam, beta)
    moved, _ = project_points(fit.edges.xyz[chosen] + _PLACEMENT_STEP * fit.edges.cell[chosen],
                              cam, beta)
    across = np.sum((moved - uv) * normal, axis=1) / _PLACEMENT_STEP
    return np.asarray(np.where(usable & np.isfinite(across), across, 0.0), np.float64)


def _weigh_edge_lines(fit: CameraFit, scaled: F64) -> None:
    """Each edge point's weight in the point-to-line passes, so that the points of one edge
    line count together as one measurement of it (generalised least squares).

    The scan places every point of an edge line with ONE error — a vertical silhouette between
    two profiles is off by the same fraction of a motor step along its whole height and in
    every frame — so its n points (over all frames) tell no more about the camera than its
    placement, ± a cell / √12, allows. Counted point by point, a long silhouette in view of
    many frames outweighed the rest of the room, and the pan followed where the scan happened
    to sample it (benchmark, 0.25° steps: one silhouette held 190 of cam0's 436 motor-direction
    edge points, placed 0.39 of a step off; the pan −0.13…−0.18° on two seeds of four). Each
    point gets ``1 / (σ_p² + n·s²)`` (σ_p :data:`POINT_NOISE_PX`, s the line's placement 1σ
    in px, n its points seen over all frames), scaled to a mean of 1."""
    x = fit.full(scaled)
    betas = fit.betas(x)
    ids = fit.edges.line_ids()
    seen_points, seen_s2 = [], []
    for frame, beta in zip(fit.frames, betas, strict=True):
        chosen = frame.all_edges
        if chosen.size == 0:
            continue
        seen_points.append(chosen)
        seen_s2.append(_placement_px(fit, frame, chosen, x, float(beta)) ** 2 / 12.0)
    fit.point_weight = np.ones(len(fit.edges.xyz))
    if not seen_points:
        return
    points = np.concatenate(seen_points)
    s2 = np.concatenate(seen_s2)
    lines, line_of = np.unique(ids[points], return_inverse=True)
    count = np.bincount(line_of, minlength=lines.size).astype(np.float64)
    line_s2 = np.bincount(line_of, weights=s2, minlength=lines.size) / np.maximum(count, 1.0)
    point_w = 1.0 / (POINT_NOISE_PX**2 + count[line_of] * line_s2[line_of])
    total = np.zeros(len(fit.edges.xyz))
    seen = np.zeros(len(fit.edges.xyz))
    np.add.at(total, points, point_w)
    np.add.at(seen, points, 1.0)
    weight = np.where(seen > 0, total / np.maximum(seen, 1.0), 0.0)
    mean = float(np.sum(weight[points]) / points.size)
    if mean > 0:
        fit.point_weight = np.where(seen > 0, weight / mean, 1.0)


def _placement_sigma(fit: CameraFit, scaled: F64, gate_px: float) -> F64:
    """1σ (scaled units) of the values from where the scan places its edges: each edge
    line's points off by one shared error, uniform within ± half a cell (1σ cell / √12),
    independent between lines, propagated through the point-to-line fit at ``scaled``
    (its matches and weights, soft-L1 as iteratively reweighted least squares):
    ``H⁻¹ (Σ_l g_l g_lᵀ / 12) H⁻¹`` with ``H = Σ w JᵀJ`` and ``g_l = Σ_{i∈l} w_i a_i J_i``
    (``a_i`` the residual's change by a cell of placement).

    The scan's sampling, not the images' noise: the same in every frame (no frame jackknife
    sees it) and concentrated in the few long edge lines in view, so the curvature alone
    (which counts every point as independent) was 2–6× optimistic for the pan."""
    if fit.edges.cell.shape != fit.edges.xyz.shape:
        return np.zeros(len(scaled))
    pairs = [p for p in fit.matches(fit.full(scaled), gate_px) if p[1].size]
    if not pairs:
        return np.zeros(len(scaled))
    base = fit.line_residuals(scaled, pairs)
    step = 0.01
    columns = []
    for k in range(len(scaled)):
        trial = scaled.copy()
        trial[k] += step
        columns.append((fit.line_residuals(trial, pairs) - base) / step)
    jac = np.stack(columns, axis=1)
    moved = fit.line_residuals(scaled, pairs, _PLACEMENT_STEP * fit.edges.cell)
    placement = (moved - base) / _PLACEMENT_STEP
    weight = 1.0 / np.sqrt(1.0 + base**2)  # soft-L1 at scale 1, as the fit
    lines = fit.edges.line_ids()[np.concatenate([p[1] for p in pairs])]
    _, line_of = np.unique(lines, return_inverse=True)
    per_point = (weight * placement)[:, None] * jac
    grouped = np.zeros((int(line_of.max()) + 1, jac.shape[1]))
    np.add.at(grouped, line_of, per_point)
    hessian = (jac * weight[:, None]).T @ jac
    try:
        inverse = np.linalg.inv(hessian)
    except np.linalg.LinAlgError:
        return np.full(len(scaled), np.inf)
    cov = inverse @ (grouped.T @ grouped / 12.0) @ inverse
    return np.asarray(np.sqrt(np.clip(np.diag(cov), 0.0, None)), np.float64)


def _has_still_frames(fit: CameraFit, x: F64) -> bool:
    """Whether some frames fall before the platform starts or after it stops."""
    first, last = fit.track.moving_span_ns()
    times = fit.times_ns + np.int64(round(x[7] * 1e9))
    return bool(np.any(times < first) or np.any(times > last))


def frame_rows(frames: pa.Table, camera_id: str, max_frames: int,
               still_ns: tuple[int, int] | None = None, window_ns: int = 0
               ) -> NDArray[np.int64]:
    """Rows of ``camera_id``'s frames, at most ``max_frames`` spread evenly over its time.

    With ``still_ns`` (the host times the platform starts and stops turning, in the frames'
    rough clock), a quarter of the frames each come from before the start and after the stop:
    only those separate a clock offset from a turn of the camera about the axis, and a video
    has few of them. With ``window_ns`` (the clock's search window) too, an eighth each from
    before and after, and an eighth each from within the window around the start and around
    the stop, half the frames spread over the scan (the mount needs its views): a stepping
    platform repeats itself every step, so a clock one step off looks like a turn of the
    camera by one step in every frame of the scan, and only frames where the motion starts or
    stops (the recording has them at the video's rate) tell the steps apart.
    """
    ids = np.asarray(frames.column("camera_id").to_pylist(), dtype=object)
    rows = np.flatnonzero(ids == camera_id)
    if rows.size == 0:
        return rows.astype(np.int64)
    times = frames.column("log_time_ns").to_numpy()[rows]
    order = np.argsort(times, kind="stable")
    rows, times = rows[order], times[order]
    if rows.size <= max_frames:
        return rows.astype(np.int64)
    if still_ns is None:
        return np.sort(rows[_spread_in_time(times, max_frames)]).astype(np.int64)
    first, last = still_ns
    w = max(0, int(window_ns))
    # before, around the start, during, around the stop, after
    parts = [times < first - w, (times >= first - w) & (times <= first + w),
             (times > first + w) & (times < last - w),
             (times >= last - w) & (times <= last + w), times > last + w]
    share = max_frames // 8 if w else max_frames // 4
    quota = [share, share if w else 0, 0, share if w else 0, share]
    quota = [min(q, int(p.sum())) for q, p in zip(quota, parts, strict=True)]
    quota[2] = max_frames - sum(quota)
    chosen = []
    for mask, count in zip(parts, quota, strict=True):
        part = rows[mask]
        if count > 0 and part.size:
            count = min(count, part.size)
            # over the frames of each share (where a video's frames are denser, around the
            # start and stop, more of them: the edges' clock fit needs those)
            chosen.append(part[np.round(np.linspace(0, part.size - 1, count)).astype(np.int64)])
    return np.sort(np.concatenate(chosen)).astype(np.int64) if chosen else rows[:0]


def _spread_in_time(times: NDArray[np.int64], count: int) -> NDArray[np.int64]:
    """Indices of at most ``count`` of the sorted ``times`` spread evenly over their span (each
    the nearest to an even step; where frames are denser in places, as a video's around the
    platform's start and stop, evenly over time, not over the frames), all when fewer.

    Where the frames leave gaps, fewer: filling the count from where they are dense would
    give a few views most of the weight (a video of the benchmark, its frames dense only
    around the start and stop, then fitted its mount on two views: 0.6° off on the test scan).
    """
    if times.size <= count:
        return np.arange(times.size, dtype=np.int64)
    targets = np.linspace(float(times[0]), float(times[-1]), count)
    after = np.clip(np.searchsorted(times, targets), 1, times.size - 1)
    nearer = np.where(targets - times[after - 1] <= times[after] - targets, after - 1, after)
    return np.asarray(np.unique(nearer), np.int64)


def observations(frames: pa.Table, rows: NDArray[np.int64], camera: CameraConfig
                 ) -> list[FrameObservation]:
    """The chosen frames decoded, each with its camera sized to the frame."""
    from scanpipe.texturing.frames import camera_for_size, decode_image

    data = frames.column("data")
    times = frames.column("log_time_ns").to_numpy()
    sequences = frames.column("sequence").to_numpy()
    out = []
    for row in rows.tolist():
        image = decode_image(data[row].as_py(), f"frame {sequences[row]} of {camera.id!r}")
        sized = camera_for_size(camera, image.shape[1], image.shape[0])
        out.append(observe(sized, int(times[row]), image))
    return out


def _frames_between_moves(frames: pa.Table, camera_id: str, track: MotorTrack,
                          motion: MotionClock, max_frames: int) -> NDArray[np.int64]:
    """:func:`frame_rows` (spread in time) of ``camera_id``'s frames taken while the platform
    stands between moves at the motion clock (within its 3σ and 20 ms): a frame taken during a
    move shows an angle that the motor's states, tens of ms apart, give only roughly. All
    frames when too few stand (a platform that turns steadily)."""
    ids = np.asarray(frames.column("camera_id").to_pylist(), dtype=object)
    rows = np.flatnonzero(ids == camera_id)
    times = frames.column("log_time_ns").to_numpy()[rows] + np.int64(round(motion.offset_s
                                                                            * 1e9))
    margin = np.int64(round((3 * motion.sigma_s + 0.02) * 1e9))
    standing = np.abs(track.beta_deg(times + margin) - track.beta_deg(times - margin)) < 1e-9
    if np.count_nonzero(standing) >= min(max_frames, rows.size) // 2:
        rows = rows[standing]
    return np.asarray(rows[frame_rows(frames.take(rows), camera_id, max_frames)], np.int64)


def frames_motion_clock(frames: pa.Table, camera_id: str, track: MotorTrack,
                        start_offset_s: float, window_s: float) -> MotionClock | None:
    """:func:`motion_clock` of ``camera_id``'s frames around the platform's start and stop."""
    rows = motion_rows(frames, camera_id, track, start_offset_s, window_s)
    if rows.size < 2 * MOTION_MIN_PAIRS:
        return None
    data = frames.column("data")
    times = frames.column("log_time_ns").to_numpy()
    sequences = frames.column("sequence").to_numpy()
    images = [motion_image(data[r].as_py(), f"frame {sequences[r]} of {camera_id!r}")
              for r in rows.tolist()]
    return motion_clock(times[rows], images, track, start_offset_s, window_s)


def calibrate_cameras(points: pa.Table, frames: pa.Table, motor: pa.Table, rig: Rig,
                      camera_ids: Sequence[str] | None = None, fit_time_offset: bool = False,
                      time_window_s: float = 1.0, max_frames: int = 24,
                      start_offsets_s: dict[str, float] | None = None,
                      fit_focal: bool = True, clock_from_motion: bool = True
                      ) -> list[CameraCalibration]:
    """Calibrate each camera (default: every rig camera with frames) against the scan.

    With ``fit_time_offset``, the clock is read from the frames' own motion where they follow
    each other closely around the platform's start and stop (:func:`motion_clock`; a video)
    and the mount is fitted at it; else (or with ``clock_from_motion`` False) the clock and
    the mount are fitted to the edges together."""
    ids = list(camera_ids) if camera_ids is not None else [
        c.id for c in rig.cameras if frame_rows(frames, c.id, 1).size]
    if not ids:
        raise StageError("frames: no frames of any rig camera "
                         f"(cameras: {', '.join(c.id for c in rig.cameras) or 'none'})")
    edges = depth_edges(points)
    if len(edges.xyz) < 100:
        raise StageError(f"points: only {len(edges.xyz)} depth-edge points in the scan; camera "
                         "self-calibration needs a scene with edges (corners, objects)")
    track = MotorTrack(motor, rig)
    results = []
    for camera_id in ids:
        camera = rig.camera(camera_id)
        start = (start_offsets_s or {}).get(camera_id, 0.0)
        still = None
        motion = None
        if fit_time_offset:  # the still periods in the frames' own (rough) clock
            first, last = track.moving_span_ns()
            shift = round(start * 1e9)
            still = (first - shift, last - shift)
            if clock_from_motion:
                motion = frames_motion_clock(frames, camera_id, track, start, time_window_s)
        if motion is not None and motion.trusted:  # the frames spread over the views
            rows = _frames_between_moves(frames, camera_id, track, motion, max_frames)
        else:
            rows = frame_rows(frames, camera_id, max_frames, still,
                              round(time_window_s * 1e9) if still is not None else 0)
        if rows.size == 0:
            raise StageError(f"frames: camera {camera_id!r} has no frames")
        results.append(calibrate_camera(edges, observations(frames, rows, camera), track,
                                        fit_time_offset, time_window_s, start,
                                        fit_focal=fit_focal, motion=motion))
    return results


def calibrated_rig(rig: Rig, results: Sequence[CameraCalibration]) -> Rig:
    """``rig`` with each calibrated camera's pose and focal length replaced (validated)."""
    from scanpipe.rig import rig_from_dict

    by_id = {r.camera_id: r.after for r in results}
    cameras = [by_id.get(c.id, c).model_dump(mode="json") for c in rig.cameras]
    data = rig.model_dump(mode="json")
    data["cameras"] = cameras
    return rig_from_dict(data, "calibrated rig")
