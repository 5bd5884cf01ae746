"""Registration of the scans of a site: hypotheses per pair, checked against free space, then a
pose graph.

Kernel functions over numpy arrays (Open3D for the features, RANSAC and the coarse ICP);
:mod:`scanpipe.site` is the shell that reads workdirs and writes artifacts.

1. Per scan: a coarse cloud (voxel ``coarse_voxel_m``, normals, FPFH features), the fine clouds
   (the scan's own points with their normals — not voxel centroids, which bias the planes of a
   noisy scan by a few hundredths of a degree — all of them as the ICP target, an even subsample
   of ``fine_source_points`` as the source) and its *free-space image*: per direction from the
   scanner, the nearest range it measured. The fine clouds' points are, by default
   (``positions`` "unsmoothed"), where the filter's input had them, each averaged with its grid
   neighbours along its own beam (:func:`plane_projected_points`): the filter's range
   smoothing puts far and oblique surfaces a few mm behind where they are, by an amount that
   depends on the view, so two scans of one wall disagreed and the pairs slid by mm, in the
   same direction along the site (docs/sites.md).
2. Per candidate pair (all pairs; with a prior, those whose prior positions are within
   ``pair_max_distance_m``): up to ``hypotheses`` distinct starting guesses from FPFH
   correspondences by sequential RANSAC (each round removes the correspondences the last
   guess explained, so look-alike placements and the true one all come out), plus the prior's
   relative pose when given; each refined by coarse point-to-plane ICP. A hypothesis is
   *valid* when its overlap is at least ``min_overlap`` and its free-space conflict (the share
   of either scan's points that lie in space the other scan's beams passed through, more than
   ``free_space_margin_m`` in front of what they hit) is at most ``max_conflict`` — and, with a
   prior, when it lies within ``prior_gate_m`` / ``prior_gate_deg`` of the prior's relative
   pose. Room A laid onto a look-alike room B fits the walls but puts A's furniture into B's
   empty space: rejected. One valid hypothesis: refined by point-to-plane ICP on the fine
   clouds (:func:`plane_icp`: a point is paired only with a target point whose normal agrees
   within ``normal_compat_deg`` — at corners and edges a wall's point otherwise pairs with the
   next surface's and turns the pair; the last round weighted by Tukey's biweight: a hard
   cut-off near the noise biases the rotation of pairs that see little of each other) and
   kept when its residual to the target's planes is at most ``max_rmse_m``. None: the pair
   is left out. Two or more distinct ones: the pair is *ambiguous* and left out, never forced.
3. Pose graph over the kept pairs (:func:`_optimise`: sparse least squares of the pairs'
   misclosures, each weighed by the pair's information of step 6), started from the pairs'
   maximum-overlap spanning tree; edges that disagree with the optimum by more than
   ``max_edge_disagreement_m`` / ``_deg`` are dropped one at a time (worst first, never one
   the graph needs to stay connected) and the graph re-optimised: a loop that does not close
   is reported, never averaged in. An ambiguous pair whose scans the graph already joins is
   resolved by that loop when exactly one of its hypotheses agrees with it (the pair is then
   refined and added, and the graph re-run); a scan reached by no kept pair gets no pose.
   Then the loop-closing round (:func:`close_loops`): every pair still left out between two
   placed scans is refined once more, started from the relative pose the graph implies, and
   joins when it passes the pair checks and agrees with that pose within the covariances
   (the misclosure's squared Mahalanobis distance under the pair's covariance plus the implied
   pose's ≤ ``loop_gate_chi2``); the graph is re-run. Without a prior, the pairs two steps
   apart (15–30 % overlap) often get no valid RANSAC hypothesis, which left bare chains.
4. Check: every two registered scans (neighbours or not) are tested for free-space conflict at
   their final poses; a conflict is a warning naming both scans (one of them is misplaced).
5. Gauge: scan 0 at the identity, or with a prior, the rigid transform that best fits the
   optimised positions to the prior positions (so the site lands in the prior's frame).
6. Covariance per scan from the graph's information (scan 0 fixed). Each pair's information
   is the inverse of a cluster-robust ("sandwich") covariance of its point-to-plane fit: the
   residuals of neighbouring points are not independent (a wall's points share its normals'
   and its sampling's errors), so the points are grouped into ``covariance_cluster_m`` cells
   and the spread of each cell's summed score (Jacobianᵀ · residual) measures the fit's
   uncertainty, instead of the residual variance divided by the number of points (which was
   far too small). ``covariance_scale`` (1.3) multiplies every covariance: over 3 seeds of
   the virtual site the sandwich alone gave a mean χ² of 7.7 against the 6 of an honest
   covariance. Where the graph has loops, the variance factor (:func:`variance_factor`: the
   pairs' misclosures against their information) scales them up further when above 1 — pairs
   sharing a scan share its errors (docs/sites.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import StageError
from scanpipe.params import Params
from scanpipe.poses import invert, pose_error

F64 = NDArray[np.float64]


class RegisterParams(Params):
    """Parameters of site registration (see the module docstring)."""

    coarse_voxel_m: float = Field(0.15, gt=0, le=1)
    hypotheses: int = Field(8, ge=1, le=64, description="RANSAC rounds per pair (each "
                                                        "gives one starting guess)")
    ransac_iterations: int = Field(5_000, ge=1000, le=10_000_000,
                                   description="per RANSAC round")
    fine_source_points: int = Field(30_000, ge=500, description="Points of the source scan "
                                    "(an even subsample) in the fine ICP.")
    fine_distance_m: float = Field(0.03, gt=0, le=0.5, description="The scale of Tukey's "
                                   "biweight in the fine ICP's last round (~3 noise σ).")
    fine_method: Literal["point_to_plane", "generalized"] = "point_to_plane"
    positions: Literal["unsmoothed", "filtered"] = Field(
        "unsmoothed", description="unsmoothed: each point where the filter found it (its "
        "input, before the range smoothing, which puts far and oblique surfaces mm behind "
        "where they are) averaged with its grid neighbours along its own beam "
        "(plane_projected_points); filtered: the filter's points as they are.")
    normal_compat_deg: float = Field(30.0, gt=0, le=90, description="The fine ICP pairs a "
                                     "point with its nearest target point only when their "
                                     "normals agree within this angle (a wall's point with "
                                     "the floor's beside the corner biased the rotation).")
    overlap_distance_m: float = Field(0.05, gt=0, le=1)
    min_overlap: float = Field(0.15, gt=0, le=1)
    max_rmse_m: float = Field(0.03, gt=0, le=1)
    free_space_margin_m: float = Field(0.1, gt=0, le=2, description="How far in front of "
                                       "what a beam hit a point must lie to be in its free "
                                       "space (plus 2 % of the range).")
    max_conflict: float = Field(0.02, ge=0, le=1, description="Largest share of a scan's "
                                "points allowed in the other scan's free space.")
    same_hypothesis_m: float = Field(0.1, gt=0, description="Two hypotheses closer than "
                                     "this (and same_hypothesis_deg) are the same placement.")
    same_hypothesis_deg: float = Field(2.0, gt=0)
    pair_max_distance_m: float | None = Field(None, gt=0, description="With a prior: only "
                                              "pairs whose prior positions are this close.")
    max_edge_disagreement_m: float = Field(0.02, gt=0)
    max_edge_disagreement_deg: float = Field(0.5, gt=0)
    prior_gate_m: float = Field(1.5, gt=0, description="With a prior: a hypothesis that "
                                "moves the scans this far from the prior's relative pose is "
                                "not valid (a match to a look-alike place).")
    prior_gate_deg: float = Field(30.0, gt=0, le=180)
    loop_gate_chi2: float = Field(16.81, gt=0, description="A loop-closing pair (one placed "
                                  "from the pose the graph implies) joins the graph only when "
                                  "its squared Mahalanobis distance from that pose, under the "
                                  "pair's and the graph's covariance, is at most this (χ² with "
                                  "6 degrees of freedom: 16.81 at 99 %).")
    covariance_cluster_m: float = Field(0.5, gt=0, le=10, description="Cell size within which "
                                        "the residuals of a pair's points count as "
                                        "correlated (the pose covariance's clusters).")
    covariance_scale: float = Field(1.3, gt=0, description="Factor on every pose covariance "
                                    "(1.3: calibrated against the truth over seeds of the "
                                    "virtual site, docs/sites.md).")
    seed: int = Field(0, ge=0)


@dataclass
class FreeSpace:
    """The nearest range a scan measured per direction from its centre: a spherical image
    (elevation × azimuth, ``res_deg`` bins), each bin the minimum over its 3 × 3 neighbours
    (so a depth edge never claims the far side as free); ``inf`` where nothing was seen."""

    centre: F64
    res_deg: float
    range_m: F64


@dataclass
class ScanClouds:
    """One scan prepared for registration."""

    name: str
    coarse: Any
    features: Any
    fine: Any
    points: int
    fine_source: Any = None
    free_space: FreeSpace | None = None
    spacing_m: float = 0.0
    tree: Any = None


@dataclass
class Hypothesis:
    """One placement of a pair's source scan in its target's frame, coarsely refined."""

    transform: F64
    overlap: float
    conflict: float
    init: str
    valid: bool = False


@dataclass
class PairResult:
    """The registration of scan ``source`` into scan ``target``'s frame."""

    target: int
    source: int
    transform: F64
    fitness: float
    rmse_m: float
    init: str
    accepted: bool
    reason: str = ""
    #: The pair's information: its weight in the pose graph and its share of the pose
    #: covariance (:func:`pair_information`).
    pose_information: F64 = field(default_factory=lambda: np.zeros((6, 6)))
    conflict: float = 0.0
    hypotheses: int = 0
    alternatives: list[Hypothesis] = field(default_factory=list)

    @property
    def ambiguous(self) -> bool:
        """Two or more distinct valid hypotheses."""
        return len(self.alternatives) > 1

    def record(self, names: list[str]) -> dict[str, Any]:
        """The pair as the report shows it."""
        return {"target": names[self.target], "source": names[self.source],
                "overlap": round(self.fitness, 4), "rmse_m": round(self.rmse_m, 5),
                "conflict": round(self.conflict, 4), "hypotheses": self.hypotheses,
                "valid_hypotheses": len(self.alternatives),
                "init": self.init, "accepted": self.accepted, "reason": self.reason}


def _o3d() -> Any:
    import open3d as o3d

    return o3d


def _angles_deg(vectors: F64) -> tuple[F64, F64, F64]:
    """Range, azimuth (0…360°) and elevation (0…180°) of vectors from a scan's centre."""
    distance = np.linalg.norm(vectors, axis=1)
    azimuth = np.degrees(np.arctan2(vectors[:, 0], vectors[:, 2])) + 180.0
    elevation = np.degrees(np.arcsin(np.clip(vectors[:, 1] / np.maximum(distance, 1e-9),
                                             -1.0, 1.0))) + 90.0
    return distance, azimuth, elevation


def free_space_image(xyz: F64, origin: F64) -> FreeSpace:
    """The :class:`FreeSpace` of one scan (points and their beam origins, rig frame); the bin
    is twice the scan's mean angular spacing, at least 0.5°."""
    centre = origin.mean(axis=0)
    distance, azimuth, elevation = _angles_deg(xyz - centre)
    spacing_deg = math.degrees(math.sqrt(4.0 * math.pi * 0.8 / max(len(xyz), 1)))
    rows = max(1, int(180.0 / max(0.5, 2.0 * spacing_deg)))
    res_deg, cols = 180.0 / rows, 2 * rows
    row = np.minimum((elevation / res_deg).astype(np.int64), rows - 1)
    col = np.minimum((azimuth / res_deg).astype(np.int64), cols - 1)
    image = np.full((rows, cols), np.inf)
    np.minimum.at(image, (row, col), distance)
    padded = np.pad(image, ((1, 1), (0, 0)), constant_values=np.inf)
    eroded = image.copy()
    for d_row in (-1, 0, 1):
        for d_col in (-1, 0, 1):  # azimuth wraps around
            eroded = np.minimum(eroded, np.roll(padded, d_col, axis=1)[1 + d_row:1 + d_row + rows])
    return FreeSpace(centre, res_deg, eroded)


def conflict_share(space: FreeSpace, points: F64, margin_m: float) -> float:
    """The share of ``points`` (in the free-space scan's frame) that its beams saw through:
    nearer than the range it measured in their direction by ``margin_m`` + 2 %. Points in
    directions it saw nothing in are not counted."""
    distance, azimuth, elevation = _angles_deg(points - space.centre)
    rows, cols = space.range_m.shape
    row = np.minimum((elevation / space.res_deg).astype(np.int64), rows - 1)
    col = np.minimum((azimuth / space.res_deg).astype(np.int64), cols - 1)
    surface = space.range_m[row, col]
    seen = np.isfinite(surface)
    if not seen.any():
        return 0.0
    inside = distance[seen] < surface[seen] * 0.98 - margin_m
    return float(np.count_nonzero(inside)) / float(np.count_nonzero(seen))


def _transform(points: F64, pose: F64) -> F64:
    return np.asarray(points @ pose[:3, :3].T + pose[:3, 3], np.float64)


def pair_conflict(target: ScanClouds, source: ScanClouds, transform: F64,
                  params: RegisterParams) -> float:
    """Free-space conflict of ``source`` placed by ``transform`` in ``target``'s frame: the
    larger of the two directions (coarse points of each in the other's free space)."""
    assert target.free_space is not None and source.free_space is not None
    into_target = conflict_share(target.free_space,
                                 _transform(np.asarray(source.coarse.points), transform),
                                 params.free_space_margin_m)
    into_source = conflict_share(source.free_space,
                                 _transform(np.asarray(target.coarse.points), invert(transform)),
                                 params.free_space_margin_m)
    return max(into_target, into_source)


def plane_projected_points(xyz: F64, origin: F64, normals: F64, profile: NDArray[np.integer],
                           sample: NDArray[np.integer], gate_m: float) -> F64:
    """Each point of a grid scan moved along its own beam onto the plane (its ``normals``)
    through the mean of its 3 × 3 grid neighbours that lie within ``gate_m`` of that plane:
    noise averaged over ~9 points, without the bias of averaging *ranges*.

    A range image's neighbourhood mean (the filter's smoothing) is biased: along a plane the
    range ``d / cos θ`` is convex in the beam angle, so its mean over neighbouring beams lies
    behind the surface, by more the farther and more oblique it is — ~7 mm at 6 m on a 2° × 1°
    grid, which differs between two scans of the same wall and slid the site's pairs by mm
    (docs/sites.md). The mean of the *points* of a plane lies on the plane. Points with fewer
    than 3 such neighbours, no normal, or a beam within ~78° of the plane stay where they are.
    """
    rows, cols = int(profile.max()) + 1, int(sample.max()) + 1
    grid = np.full((rows + 2, cols + 2, 3), np.nan)
    grid[profile + 1, sample + 1] = xyz
    usable = np.all(np.isfinite(normals), axis=1)
    unit = np.where(usable[:, None], normals, 0.0)
    total = np.zeros_like(xyz)
    count = np.zeros(len(xyz))
    for d_row in (-1, 0, 1):
        for d_col in (-1, 0, 1):
            neighbour = grid[profile + 1 + d_row, sample + 1 + d_col]
            found = np.all(np.isfinite(neighbour), axis=1)
            near = np.abs(np.einsum("ij,ij->i", np.where(found[:, None], neighbour, xyz) - xyz,
                                    unit)) <= gate_m
            take = found & near & usable
            total[take] += neighbour[take]
            count[take] += 1
    beam = xyz - origin
    beam /= np.maximum(np.linalg.norm(beam, axis=1), 1e-12)[:, None]
    facing = np.einsum("ij,ij->i", beam, unit)
    moved = usable & (count >= 3) & (np.abs(facing) >= 0.2)
    centroid = total[moved] / count[moved][:, None]
    shift = np.einsum("ij,ij->i", centroid - xyz[moved], unit[moved]) / facing[moved]
    out = np.array(xyz, np.float64)
    out[moved] += beam[moved] * shift[:, None]
    return out


def prepare_scan(name: str, xyz: NDArray[np.floating], origin: NDArray[np.floating],
                 params: RegisterParams, normals: NDArray[np.floating] | None = None,
                 fine_xyz: NDArray[np.floating] | None = None) -> ScanClouds:
    """Downsample, estimate normals (toward the scanner) and FPFH features of one scan; the
    fine clouds keep the scan's own points (with ``normals`` when given, e.g. the grid's) —
    or ``fine_xyz``, the same points placed otherwise (:func:`plane_projected_points`), when
    given: the coarse cloud, its features and the free-space image stay ``xyz``'s (the
    hypotheses do not need millimetres, and RANSAC's draws then stay as they were)."""
    o3d = _o3d()
    finite = np.all(np.isfinite(xyz), axis=1)
    if fine_xyz is not None:
        finite &= np.all(np.isfinite(fine_xyz), axis=1)
    points = np.asarray(xyz, np.float64)[finite]
    origins = np.asarray(origin, np.float64)[finite]
    if len(points) < 100:
        raise StageError(f"{name}: only {len(points)} points; too few to register")
    centre = origins.mean(axis=0)
    fine_points = points if fine_xyz is None else np.asarray(fine_xyz, np.float64)[finite]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(fine_points))
    if normals is not None:
        given = np.asarray(normals, np.float64)[finite]
        usable = np.all(np.isfinite(given), axis=1)
        given[~usable] = 0.0
        cloud.normals = o3d.utility.Vector3dVector(given)
        if not usable.all():
            cloud = cloud.select_by_index(np.flatnonzero(usable).tolist())
    else:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(24))
        cloud.orient_normals_towards_camera_location(centre)
    step = max(1, math.ceil(len(cloud.points) / params.fine_source_points))
    fine_source = cloud.uniform_down_sample(step) if step > 1 else cloud
    coarse = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(
        params.coarse_voxel_m)
    coarse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
        radius=3 * params.coarse_voxel_m, max_nn=30))
    coarse.orient_normals_towards_camera_location(centre)
    features = o3d.pipelines.registration.compute_fpfh_feature(
        coarse, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * params.coarse_voxel_m,
                                                     max_nn=100))
    from scipy.spatial import cKDTree

    kept = np.asarray(cloud.points)
    tree = cKDTree(kept)
    probe = kept[::max(1, len(kept) // 5000)]
    spacing = float(np.median(tree.query(probe, k=2)[0][:, 1]))
    return ScanClouds(name, coarse, features, cloud, len(points), fine_source,
                      free_space_image(points, origins), spacing, tree)


def plane_fit(source: ScanClouds, target: ScanClouds, transform: F64, params: RegisterParams
              ) -> tuple[float, float, NDArray[np.bool_]]:
    """Overlap, RMS and inlier mask of ``source``'s fine points placed by ``transform`` against
    ``target``'s surface: a point overlaps when the target has a point within
    :func:`search_radius` whose plane (its normal) passes within ``overlap_distance_m``. The
    distance is to the plane, not to the nearest point, so a coarse scan's sample spacing
    does not count as misalignment."""
    points, residual, _, inlier = plane_residuals(source, target, transform, params)
    if not inlier.any():
        return 0.0, 0.0, inlier
    return (float(np.count_nonzero(inlier)) / len(points),
            float(np.sqrt(np.mean(residual[inlier] ** 2))), inlier)


def plane_residuals(source: ScanClouds, target: ScanClouds, transform: F64,
                    params: RegisterParams) -> tuple[F64, F64, F64, NDArray[np.bool_]]:
    """``source``'s fine points placed by ``transform`` (target frame), their signed distances
    to the planes of their nearest target points (``inf`` where none is within
    :func:`search_radius`), those planes' normals, and the inlier mask (within
    ``overlap_distance_m``)."""
    points = _transform(np.asarray(source.fine_source.points), transform)
    distance, index = target.tree.query(points, distance_upper_bound=search_radius(target,
                                                                                  params))
    found = np.isfinite(distance)
    normals = np.zeros_like(points)
    normals[found] = np.asarray(target.fine.normals)[index[found]]
    anchors = np.asarray(target.fine.points)
    residual = np.full(len(points), np.inf)
    residual[found] = np.einsum("ij,ij->i", points[found] - anchors[index[found]],
                                normals[found])
    inlier = np.abs(residual) <= params.overlap_distance_m
    return points, residual, normals, inlier


def pair_information(source: ScanClouds, target: ScanClouds, transform: F64,
                     params: RegisterParams) -> F64:
    """The information (inverse covariance, 6 × 6, target frame, twist order rx ry rz tx ty
    tz, perturbing the placed source from the left) of a pair's point-to-plane fit: the
    cluster-robust sandwich ``H⁻¹ M H⁻¹`` with ``H = Σ JᵀJ`` over the inliers (``J = [p × n,
    n]``) and ``M = Σ_cells g gᵀ``, ``g`` the sum of ``J r`` over the inliers of one
    ``covariance_cluster_m`` cell, inverted; times ``1 / covariance_scale``. With fewer than
    12 cells (too few to estimate ``M``): ``H`` over the residual variance, as if each cell
    were one point."""
    points, residual, normals, inlier = plane_residuals(source, target, transform, params)
    p, n, r = points[inlier], normals[inlier], residual[inlier]
    jacobian = np.concatenate([np.cross(p, n), n], axis=1)
    hessian = jacobian.T @ jacobian
    _, cell = np.unique(np.floor(p / params.covariance_cluster_m).astype(np.int64), axis=0,
                        return_inverse=True)
    cell = cell.ravel()
    cells = int(cell.max()) + 1 if len(cell) else 0
    if cells < 12:
        variance = float(np.mean(r ** 2)) if len(r) else 1.0
        return np.asarray(hessian * cells / max(len(r), 1) / max(variance, 1e-10)
                          / params.covariance_scale, np.float64)
    scores = np.stack([np.bincount(cell, weights=jacobian[:, k] * r, minlength=cells)
                       for k in range(6)], axis=1)
    # the residuals' mean over the whole fit is part of the error too: not removed
    meat = scores.T @ scores * cells / (cells - 6)  # small-sample correction
    bread = np.linalg.pinv(hessian)
    # a direction the fit does not constrain (a corridor sliding along itself) gets no
    # information, not an infinite one
    return _pseudo_inverse(bread @ meat @ bread * params.covariance_scale, 0.0)


def search_radius(target: ScanClouds, params: RegisterParams) -> float:
    """How far to look for a target point: the fine ICP's distance, or three of the target's
    point spacings when it is sparser (a coarse scan)."""
    return max(params.fine_distance_m, 3.0 * target.spacing_m)


def _coarse_refine(source: ScanClouds, target: ScanClouds, init: F64, params: RegisterParams
                   ) -> tuple[F64, float]:
    """Point-to-plane ICP on the coarse clouds; (transform, overlap at one coarse voxel)."""
    reg = _o3d().pipelines.registration
    transform = init
    for distance in (3.0 * params.coarse_voxel_m, params.coarse_voxel_m):
        result = reg.registration_icp(source.coarse, target.coarse, distance, transform,
                                      reg.TransformationEstimationPointToPlane(),
                                      reg.ICPConvergenceCriteria(1e-6, 1e-6, 20))
        transform = np.asarray(result.transformation, np.float64)
    return transform, float(result.fitness)


def _twist_step(x: F64, centre: F64) -> F64:
    """The rigid step of a twist (rx ry rz tx ty tz) whose rotation turns about ``centre``."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_rotvec(x[:3]).as_matrix()
    step = np.eye(4)
    step[:3, :3] = rotation
    step[:3, 3] = centre - rotation @ centre + x[3:]
    return step


def plane_icp(source: ScanClouds, target: ScanClouds, init: F64, distance_m: float,
              params: RegisterParams, tukey_m: float | None = None,
              iterations: int = 40) -> F64:
    """Point-to-plane ICP of ``source``'s fine points onto ``target``'s planes (Gauss–Newton,
    vectorised): each point is paired with its nearest target point within ``distance_m``
    when their normals agree within ``normal_compat_deg`` and its plane distance is within
    ``distance_m``; residuals weighed by Tukey's biweight at ``tukey_m`` when given."""
    points = np.asarray(source.fine_source.points)
    source_normals = np.asarray(source.fine_source.normals)
    anchors, normals = np.asarray(target.fine.points), np.asarray(target.fine.normals)
    min_cos = math.cos(math.radians(params.normal_compat_deg))
    transform = np.asarray(init, np.float64)
    for _ in range(iterations):
        placed = _transform(points, transform)
        distance, index = target.tree.query(placed, distance_upper_bound=distance_m)
        found = np.flatnonzero(np.isfinite(distance))
        p, n = placed[found], normals[index[found]]
        turned = source_normals[found] @ transform[:3, :3].T
        residual = np.einsum("ij,ij->i", p - anchors[index[found]], n)
        keep = ((np.einsum("ij,ij->i", turned, n) >= min_cos)
                & (np.abs(residual) <= distance_m))
        p, n, residual = p[keep], n[keep], residual[keep]
        if len(p) < 6:
            break
        weight = (np.ones_like(residual) if tukey_m is None
                  else np.clip(1.0 - (residual / tukey_m) ** 2, 0.0, None) ** 2)
        centre = p.mean(axis=0)
        jacobian = np.concatenate([np.cross(p - centre, n), n], axis=1)
        weighted = jacobian * weight[:, None]
        try:
            x = -np.linalg.solve(weighted.T @ jacobian, weighted.T @ residual)
        except np.linalg.LinAlgError:
            break  # a degenerate overlap: plane_fit and the checks judge the result
        transform = _twist_step(x, centre) @ transform
        if np.linalg.norm(x[:3]) < 1e-10 and np.linalg.norm(x[3:]) < 1e-9:
            break
    return transform


def refine(source: ScanClouds, target: ScanClouds, init: F64, params: RegisterParams
           ) -> tuple[F64, float, float]:
    """ICP on the fine clouds (the scans' own points and normals), ending with a round
    weighted by Tukey's biweight at ``fine_distance_m``; returns (transform, overlap, RMS)
    from :func:`plane_fit`."""
    transform = init
    wide = max(params.overlap_distance_m, params.fine_distance_m)
    # The last round weighs residuals by Tukey's biweight (scale fine_distance_m) instead of
    # cutting them off there: a hard cut-off near the noise keeps one tail of the residuals at
    # edges and door frames, and turned a pair seeing 30 % of the other 0.06° (Tukey: 0.01°).
    rounds = ((params.coarse_voxel_m, None), (wide, None), (wide, params.fine_distance_m))
    if params.fine_method == "generalized":
        reg = _o3d().pipelines.registration
        for distance, scale in rounds:
            estimation = (reg.TransformationEstimationForGeneralizedICP() if scale is None
                          else reg.TransformationEstimationForGeneralizedICP(
                              kernel=reg.TukeyLoss(scale)))
            result = reg.registration_generalized_icp(
                source.fine_source, target.fine, distance, transform, estimation,
                reg.ICPConvergenceCriteria(1e-9, 1e-9, 40))
            transform = np.asarray(result.transformation, np.float64)
    else:
        # Own point-to-plane rounds rather than Open3D's: pairs whose normals disagree (a
        # wall's point with the floor's or the next wall's, at corners and edges the two
        # scans see differently) are left out, which Open3D cannot do; with them a pair seeing
        # 17 % of the other came out 0.13° off, without 0.01° (docs/sites.md).
        for distance, scale in rounds:
            transform = plane_icp(source, target, transform, distance, params, scale)
    fitness, rmse, _ = plane_fit(source, target, transform, params)
    return transform, fitness, rmse


def same_placement(a: F64, b: F64, params: RegisterParams) -> bool:
    """Whether two relative poses are the same placement (within ``same_hypothesis_*``)."""
    dt, dr = pose_error(a, b)
    return dt <= params.same_hypothesis_m and dr <= params.same_hypothesis_deg


def pair_hypotheses(source: ScanClouds, target: ScanClouds, params: RegisterParams,
                    prior_guess: F64 | None = None) -> list[Hypothesis]:
    """Distinct placements of ``source`` in ``target``'s frame: sequential RANSAC over FPFH
    correspondences (each round drops the correspondences the previous guesses explained) and
    the prior's guess, each refined by coarse ICP and scored (overlap, free-space conflict,
    validity); best first."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    distance = 1.5 * params.coarse_voxel_m
    matches = np.asarray(reg.correspondences_from_features(source.features, target.features,
                                                           False), np.int64).reshape(-1, 2)
    src = np.asarray(source.coarse.points)[matches[:, 0]]
    tgt = np.asarray(target.coarse.points)[matches[:, 1]]
    alive = np.ones(len(matches), bool)
    guesses: list[tuple[str, F64]] = []
    if prior_guess is not None:
        guesses.append(("prior", prior_guess))
    for round_ in range(params.hypotheses):
        if np.count_nonzero(alive) < 3:
            break
        o3d.utility.random.seed(params.seed + round_)
        result = reg.registration_ransac_based_on_correspondence(
            source.coarse, target.coarse, o3d.utility.Vector2iVector(matches[alive]), distance,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(distance)],
            reg.RANSACConvergenceCriteria(params.ransac_iterations, 0.9999))
        guess = np.asarray(result.transformation, np.float64)
        explained = np.linalg.norm(_transform(src, guess) - tgt, axis=1) <= 2.0 * distance
        if not explained[alive].any():
            break
        alive &= ~explained
        guesses.append(("ransac", guess))
    found: list[Hypothesis] = []
    for label, guess in guesses:
        transform, overlap = _coarse_refine(source, target, guess, params)
        if any(same_placement(transform, h.transform, params) for h in found):
            continue
        conflict = pair_conflict(target, source, transform, params)
        valid = overlap >= params.min_overlap and conflict <= params.max_conflict
        if valid and prior_guess is not None:
            gap = pose_error(transform, prior_guess)
            valid = gap[0] <= params.prior_gate_m and gap[1] <= params.prior_gate_deg
        found.append(Hypothesis(transform, overlap, conflict, label, valid))
    found.sort(key=lambda h: (not h.valid, h.conflict > params.max_conflict, -h.overlap))
    return found


def _describe(h: Hypothesis, params: RegisterParams, prior_guess: F64 | None) -> str:
    if h.overlap < params.min_overlap:
        return f"overlap {h.overlap:.1%} < min_overlap {params.min_overlap:.0%}"
    if h.conflict > params.max_conflict:
        return (f"{h.conflict:.1%} of the points lie in the other scan's free space "
                f"(max_conflict {params.max_conflict:.0%}): a look-alike place")
    assert prior_guess is not None
    gap = pose_error(h.transform, prior_guess)
    return (f"{gap[0]:.2f} m / {gap[1]:.0f}° from the prior's relative pose (prior_gate_m / "
            "_deg): a look-alike place")


def finish_pair(clouds: list[ScanClouds], pair: PairResult, start: F64, init: str,
                params: RegisterParams) -> PairResult:
    """Refine a pair's chosen placement on the fine clouds; accept it when the residual and
    overlap pass (the information matrix is then set)."""
    source, target = clouds[pair.source], clouds[pair.target]
    transform, fitness, rmse = refine(source, target, start, params)
    pair.transform, pair.fitness, pair.rmse_m, pair.init = transform, fitness, rmse, init
    if fitness < params.min_overlap:
        pair.reason = f"overlap {fitness:.1%} < min_overlap {params.min_overlap:.0%}"
    elif rmse > params.max_rmse_m:
        pair.reason = f"residual {rmse * 1000:.1f} mm > max_rmse_m"
    else:
        pair.accepted, pair.reason = True, ""
        # the pose graph's weight of the pair and its covariance
        pair.pose_information = pair_information(source, target, transform, params)
    return pair


def register_pair(clouds: list[ScanClouds], target: int, source: int, params: RegisterParams,
                  prior: list[F64] | None) -> PairResult:
    """Align scan ``source`` to scan ``target``: hypotheses, free-space check, then the one
    valid hypothesis refined; none or several valid: left out with the reason."""
    prior_guess = None if prior is None else invert(prior[target]) @ prior[source]
    found = pair_hypotheses(clouds[source], clouds[target], params, prior_guess)
    valid = [h for h in found if h.valid]
    best = found[0] if found else Hypothesis(np.eye(4), 0.0, 1.0, "none")
    pair = PairResult(target, source, best.transform, best.overlap, 0.0, best.init, False,
                      conflict=best.conflict, hypotheses=len(found), alternatives=valid)
    if not valid:
        pair.reason = ("no hypothesis" if not found else _describe(best, params, prior_guess))
        return pair
    if len(valid) > 1:
        gaps = pose_error(valid[0].transform, valid[1].transform)
        pair.reason = (f"ambiguous: {len(valid)} placements fit (overlap "
                       f"{', '.join(f'{h.overlap:.0%}' for h in valid)}, {gaps[0]:.2f} m / "
                       f"{gaps[1]:.0f}° apart)")
        return pair
    return finish_pair(clouds, pair, best.transform, best.init, params)


def _spanning_tree(count: int, pairs: list[PairResult]) -> tuple[list[F64 | None], set[int]]:
    """Initial poses (scan 0 at the identity) along the maximum-fitness spanning tree, and the
    indices of the pairs in it."""
    poses: list[F64 | None] = [None] * count
    poses[0] = np.eye(4)
    used: set[int] = set()
    order = sorted(range(len(pairs)), key=lambda k: -pairs[k].fitness)
    grown = True
    while grown:
        grown = False
        for k in order:
            if k in used:
                continue
            p = pairs[k]
            t_pose, s_pose = poses[p.target], poses[p.source]
            if t_pose is not None and s_pose is None:
                poses[p.source] = t_pose @ p.transform
            elif s_pose is not None and t_pose is None:
                poses[p.target] = s_pose @ invert(p.transform)
            else:
                continue
            used.add(k)
            grown = True
            break
    return poses, used


def _invert_all(poses: F64) -> F64:
    """Inverses of a stack of rigid poses (…, 4, 4)."""
    inverse = np.zeros_like(poses)
    turned = np.swapaxes(poses[..., :3, :3], -1, -2)
    inverse[..., :3, :3] = turned
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", turned, poses[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def _optimise(poses: list[F64], pairs: list[PairResult], iterations: int = 50) -> list[F64]:
    """The pose graph: the poses (scan 0 fixed) minimising the pairs' misclosures weighed by
    their pose information, Σ eᵀ I e with ``measured = exp(e) · implied`` (the convention of
    :func:`pair_information` and :func:`variance_factor`), by Gauss–Newton from the spanning
    tree's poses (left perturbations; ``e`` moves by ``Ad(measured · P_s⁻¹)`` times the
    difference of the two scans' steps, to first order). Each pair counts by its own,
    cluster-robust information, so the pairs are combined as their errors deserve: with the
    same pairs, Open3D's pose graph (point-count information, a line process on the loop
    edges) left the virtual site's seed 0 0.050° (no prior) / 0.099° (wrong prior) off where
    this leaves it 0.034° / 0.048° (docs/sites.md)."""
    from scipy.spatial.transform import Rotation

    count = len(poses)
    if count < 2 or not pairs:
        return poses
    current = np.stack(poses).astype(np.float64)
    measured = np.stack([p.transform for p in pairs])
    target = np.array([p.target for p in pairs])
    source = np.array([p.source for p in pairs])
    information = np.stack([(p.pose_information + p.pose_information.T) / 2.0 for p in pairs])
    size = 6 * (count - 1)
    for _ in range(iterations):
        implied = _invert_all(current[target]) @ current[source]
        delta = measured @ _invert_all(implied)
        error = np.concatenate([Rotation.from_matrix(delta[:, :3, :3]).as_rotvec(),
                                delta[:, :3, 3]], axis=1)
        hessian = np.zeros((size, size))
        gradient = np.zeros(size)
        for e in range(len(pairs)):
            jac = _adjoint(measured[e] @ invert(current[source[e]]))
            block = jac.T @ information[e]
            # e(x) ≈ e + J (x_target − x_source)
            for node, sign in ((target[e], 1.0), (source[e], -1.0)):
                if node == 0:
                    continue
                rows = slice(6 * node - 6, 6 * node)
                gradient[rows] += sign * block @ error[e]
                for other, other_sign in ((target[e], 1.0), (source[e], -1.0)):
                    if other == 0:
                        continue
                    hessian[rows, 6 * other - 6:6 * other] += sign * other_sign * block @ jac
        step = -np.linalg.lstsq(hessian, gradient, rcond=None)[0]
        twist = step.reshape(-1, 6)
        moves = np.tile(np.eye(4), (count - 1, 1, 1))
        moves[:, :3, :3] = Rotation.from_rotvec(twist[:, :3]).as_matrix()
        moves[:, :3, 3] = twist[:, 3:]
        current[1:] = moves @ current[1:]
        if np.abs(twist[:, :3]).max() < 1e-11 and np.abs(twist[:, 3:]).max() < 1e-10:
            break
    return list(current)


def _adjoint(pose: F64) -> F64:
    rotation, t = pose[:3, :3], pose[:3, 3]
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    adjoint = np.zeros((6, 6))
    adjoint[:3, :3] = rotation
    adjoint[3:, 3:] = rotation
    adjoint[3:, :3] = skew @ rotation
    return adjoint


def joint_covariance(poses: list[F64], pairs: list[PairResult]) -> F64 | None:
    """The joint 6n × 6n covariance of all scans' poses (site frame, rx ry rz tx ty tz, left
    perturbations) from the graph's information, scan 0 fixed (its rows zero); None when the
    system is singular."""
    n = len(poses)
    hessian = np.zeros((6 * n, 6 * n))
    for p in pairs:
        a = _adjoint(invert(poses[p.target]))
        block = a.T @ p.pose_information @ a
        i, j = p.target, p.source
        for u, v, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            hessian[6 * u:6 * u + 6, 6 * v:6 * v + 6] += sign * block
    joint = np.zeros((6 * n, 6 * n))
    try:
        joint[6:, 6:] = np.linalg.inv(hessian[6:, 6:])
    except np.linalg.LinAlgError:
        return None
    return joint


def covariances(poses: list[F64], pairs: list[PairResult]) -> list[F64 | None]:
    """Per-scan 6 × 6 covariance (site frame, rx ry rz tx ty tz) from the graph's information,
    scan 0 fixed; None for scan 0 and when the system is singular."""
    joint = joint_covariance(poses, pairs)
    result: list[F64 | None] = [None] * len(poses)
    if joint is None:
        return result
    for k in range(1, len(poses)):
        result[k] = np.asarray(joint[6 * k:6 * k + 6, 6 * k:6 * k + 6], np.float64)
    return result


def relative_covariance(joint: F64, poses: list[F64], target: int, source: int) -> F64:
    """The covariance of the relative pose ``target⁻¹ · source`` the graph implies, in the
    pairs' convention (target frame, ``implied = exp(δ) · implied₀``): δ = Ad(P_t⁻¹)(ξ_s − ξ_t)
    with the two scans' correlated site-frame errors ξ from ``joint``."""
    rows = [slice(6 * k, 6 * k + 6) for k in (source, target)]
    difference = (joint[rows[0], rows[0]] + joint[rows[1], rows[1]]
                  - joint[rows[0], rows[1]] - joint[rows[1], rows[0]])
    a = _adjoint(invert(poses[target]))
    return np.asarray(a @ difference @ a.T, np.float64)


def misclosure(measured: F64, implied: F64) -> F64:
    """The twist ``e`` (rx ry rz tx ty tz) with ``measured = exp(e) · implied``."""
    from scipy.spatial.transform import Rotation

    delta = measured @ invert(implied)
    return np.concatenate([Rotation.from_matrix(delta[:3, :3]).as_rotvec(), delta[:3, 3]])


def _pseudo_inverse(matrix: F64, null_value: float) -> F64:
    """The inverse of a symmetric positive semi-definite 6 × 6 (a covariance or an
    information) through its eigenvalues; an eigenvalue below 1e-12 of the largest (a
    direction the data does not reach) gets ``null_value`` instead of its reciprocal."""
    values, vectors = np.linalg.eigh((matrix + matrix.T) / 2.0)
    floor = max(float(values.max()), 1e-300) * 1e-12
    inverse = np.where(values > floor, 1.0 / np.maximum(values, 1e-300), null_value)
    return np.asarray((vectors * inverse) @ vectors.T, np.float64)


def information_covariance(information: F64, unconstrained: float = 1e6) -> F64:
    """A pair's covariance from its information; a direction the pair does not constrain
    (zero information) gets the variance ``unconstrained`` instead of an infinite one."""
    return _pseudo_inverse(information, unconstrained)


def variance_factor(poses: list[F64], pairs: list[PairResult]) -> tuple[float, int]:
    """The graph's a-posteriori variance factor: the pairs' misclosures at the optimised poses
    (each pair's measured relative pose against the one the poses imply) weighed by their
    pose information, over the redundancy ``6 × (pairs − (scans − 1))``; (1, 0) without a
    loop. Above 1, the pairs disagree more than their covariances allow — their errors are
    correlated (pairs sharing a scan share its errors) — and the covariances are scaled up by
    it."""
    dof = 6 * (len(pairs) - (len(poses) - 1))
    if dof <= 0:
        return 1.0, 0
    total = 0.0
    for p in pairs:
        e = misclosure(p.transform, invert(poses[p.target]) @ poses[p.source])
        total += float(e @ p.pose_information @ e)
    return total / dof, dof


def _fit_to_prior(poses: list[F64], prior: list[F64]) -> F64:
    """The rigid transform that best maps the optimised positions onto the prior's (Kabsch);
    with fewer than 3 positions, scan 0's prior pose."""
    if len(poses) < 3:
        return prior[0] @ invert(poses[0])
    a = np.array([p[:3, 3] for p in poses])
    b = np.array([p[:3, 3] for p in prior])
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = cb - rotation @ ca
    return transform


def _solve_graph(n: int, kept: list[PairResult], names: list[str], params: RegisterParams
                 ) -> tuple[list[F64 | None], list[PairResult], list[dict[str, Any]]]:
    """Spanning tree from scan 0, pose graph, and the loop check: (poses of the reached scans,
    the pairs left in the graph, the pairs dropped for not closing a loop)."""
    dropped: list[dict[str, Any]] = []
    while True:
        initial, _ = _spanning_tree(n, kept)
        reached, start, edges = _subgraph(initial, kept)
        inside = [p for p in kept if initial[p.target] is not None
                  and initial[p.source] is not None]  # the same pairs as edges, in order
        optimised = _optimise(start, edges)
        worst, worst_score, worst_record = -1, 1.0, {}
        for e, p in enumerate(edges):
            implied = invert(optimised[p.target]) @ optimised[p.source]
            dt, dr = pose_error(implied, p.transform)
            score = max(dt / params.max_edge_disagreement_m, dr / params.max_edge_disagreement_deg)
            if score > worst_score and _connected_without(len(reached), edges, e):
                worst, worst_score = e, score
                worst_record = {"target": names[reached[p.target]],
                                "source": names[reached[p.source]],
                                "disagreement_m": round(dt, 5),
                                "disagreement_deg": round(dr, 4)}
        if worst < 0:
            poses: list[F64 | None] = [None] * n
            for new, old in enumerate(reached):
                poses[old] = optimised[new]
            return poses, inside, dropped
        dropped.append(worst_record)
        kept = [p for p in kept if p is not inside[worst]]


def _subgraph(poses: list[F64 | None], edges: list[PairResult]
              ) -> tuple[list[int], list[F64], list[PairResult]]:
    """The registered scans (their indices), their poses and the edges renumbered among
    them."""
    reached = [k for k, pose in enumerate(poses) if pose is not None]
    sub = {old: new for new, old in enumerate(reached)}
    sub_edges = [PairResult(sub[p.target], sub[p.source], p.transform, p.fitness, p.rmse_m,
                            p.init, True, "", pose_information=p.pose_information)
                 for p in edges if p.target in sub and p.source in sub]
    return reached, [poses[k] for k in reached], sub_edges  # type: ignore[misc]


def close_loops(clouds: list[ScanClouds], results: list[PairResult], poses: list[F64 | None],
                edges: list[PairResult], params: RegisterParams) -> list[dict[str, Any]]:
    """The second round: each pair left out (no valid hypothesis, or rejected) between two
    scans the graph already places is refined by the fine ICP started from the relative pose
    the graph implies, and joins (accepted, ``init`` "graph") when its overlap, residual and
    free-space conflict pass and its result agrees with that pose within its covariance: the
    squared Mahalanobis distance of the misclosure under the pair's covariance plus the
    implied pose's (from the graph's joint covariance, scaled by its variance factor when
    above 1) at most ``loop_gate_chi2``. A fixed distance gate either admits a pair that slid
    a few mm along a door or rejects a sound pair along a long chain; the covariance knows
    which directions each is sure of. Pairs that see less than half ``min_overlap`` of each
    other at the implied pose are not tried. Returns one record per pair tried."""
    reached, sub_poses, sub_edges = _subgraph(poses, edges)
    joint = joint_covariance(sub_poses, sub_edges)
    if joint is None:
        return []
    joint = joint * max(1.0, variance_factor(sub_poses, sub_edges)[0])
    sub = {old: new for new, old in enumerate(reached)}
    names = [c.name for c in clouds]
    records: list[dict[str, Any]] = []
    for pair in results:
        if pair.accepted or pair.target not in sub or pair.source not in sub:
            continue
        source, target = clouds[pair.source], clouds[pair.target]
        implied = invert(sub_poses[sub[pair.target]]) @ sub_poses[sub[pair.source]]
        if plane_fit(source, target, implied, params)[0] < params.min_overlap / 2.0:
            continue
        record: dict[str, Any] = {"target": names[pair.target], "source": names[pair.source]}
        transform, fitness, rmse = refine(source, target, implied, params)
        conflict = pair_conflict(target, source, transform, params)
        record.update(overlap=round(fitness, 4), rmse_m=round(rmse, 5),
                      conflict=round(conflict, 4), chi2=None, accepted=False)
        if fitness < params.min_overlap:
            record["reason"] = f"overlap {fitness:.1%} < min_overlap {params.min_overlap:.0%}"
        elif rmse > params.max_rmse_m:
            record["reason"] = f"residual {rmse * 1000:.1f} mm > max_rmse_m"
        elif conflict > params.max_conflict:
            record["reason"] = (f"{conflict:.1%} of the points lie in the other scan's free "
                                f"space (max_conflict {params.max_conflict:.0%})")
        else:
            information = pair_information(source, target, transform, params)
            spread = (information_covariance(information)
                      + relative_covariance(joint, sub_poses, sub[pair.target],
                                            sub[pair.source]))
            e = misclosure(transform, implied)
            chi2 = float(e @ np.linalg.solve(spread, e))
            dt, dr = pose_error(transform, implied)
            record.update(chi2=round(chi2, 2), from_graph_m=round(dt, 5),
                          from_graph_deg=round(dr, 4))
            if chi2 > params.loop_gate_chi2:
                record["reason"] = (f"{dt * 1000:.1f} mm / {dr:.3f}° from the pose the graph "
                                    f"implies: χ² {chi2:.1f} > loop_gate_chi2 "
                                    f"{params.loop_gate_chi2:g}")
            else:
                record.update(accepted=True, reason="")
                pair.transform, pair.fitness, pair.rmse_m = transform, fitness, rmse
                pair.conflict, pair.pose_information = conflict, information
                pair.init, pair.accepted = "graph", True
                pair.reason = (f"no valid hypothesis alone; placed from the graph's pose, "
                               f"χ² {chi2:.1f} within loop_gate_chi2")
        records.append(record)
    return records


def register_scans(clouds: list[ScanClouds], params: RegisterParams,
                   prior: list[F64] | None = None, progress: Any = None
                   ) -> tuple[list[F64 | None], list[F64 | None], dict[str, Any]]:
    """Register every scan: poses (None for a scan no kept pair reaches), covariances and the
    report (pairs, dropped edges, resolved and ambiguous pairs, conflicts, warnings)."""
    n = len(clouds)
    names = [c.name for c in clouds]
    candidates = [(i, j) for i in range(n) for j in range(i + 1, n)]
    if prior is not None and params.pair_max_distance_m is not None:
        candidates = [(i, j) for i, j in candidates if np.linalg.norm(
            prior[i][:3, 3] - prior[j][:3, 3]) <= params.pair_max_distance_m]
    results = []
    for k, (i, j) in enumerate(candidates):
        if progress is not None:
            progress("register", k, len(candidates))
        results.append(register_pair(clouds, i, j, params, prior))
    kept = [p for p in results if p.accepted]
    warnings: list[str] = []
    poses, edges, dropped = _solve_graph(n, kept, names, params)
    # an ambiguous pair between scans the graph already joins: its loop decides
    resolved: list[dict[str, Any]] = []
    for pair in (p for p in results if p.ambiguous):
        t_pose, s_pose = poses[pair.target], poses[pair.source]
        if t_pose is None or s_pose is None:
            continue
        implied = invert(t_pose) @ s_pose
        agree = [h for h in pair.alternatives if same_placement(h.transform, implied, params)]
        if len(agree) != 1:
            continue
        finish_pair(clouds, pair, agree[0].transform, agree[0].init, params)
        if pair.accepted:
            pair.reason = "ambiguous alone; resolved by the loop through the other pairs"
            resolved.append({"target": names[pair.target], "source": names[pair.source]})
    if resolved:
        kept = [p for p in results if p.accepted]
        poses, edges, dropped = _solve_graph(n, kept, names, params)
    # pairs that closed no loop alone: once more from the graph's poses, gated by covariance
    loops = close_loops(clouds, results, poses, edges, params)
    if any(record["accepted"] for record in loops):
        kept = [p for p in results if p.accepted]
        poses, edges, dropped = _solve_graph(n, kept, names, params)
    for record in dropped:
        warnings.append(f"pair {record['target']}–{record['source']} disagrees with the other "
                        f"pairs by {record['disagreement_m'] * 1000:.1f} mm / "
                        f"{record['disagreement_deg']:.2f}°: left out of the pose graph")
    reached = [k for k in range(n) if poses[k] is not None]
    missing = [names[k] for k in range(n) if poses[k] is None]
    for k in range(n):
        if poses[k] is not None:
            continue
        why = [p for p in results if k in (p.target, p.source) and p.ambiguous
               and not p.accepted]
        if why:
            other = names[why[0].source if why[0].target == k else why[0].target]
            warnings.append(f"{names[k]}: not registered (no pose written): its pair with "
                            f"{other} is ambiguous ({why[0].reason}) and no other pair places "
                            "it; add a position that links it, or give a --prior")
        else:
            warnings.append(f"{names[k]}: not registered (no pose written): it overlaps no "
                            "registered scan well enough; scan closer to its neighbours")
    conflicts = site_conflicts(clouds, poses, params)
    for record in conflicts:
        warnings.append(f"scans {record['a']} and {record['b']} conflict at their registered "
                        f"poses ({record['conflict']:.1%} of the points of one lie in the "
                        "other's free space): at least one of them is misplaced")
    gauge = np.eye(4)
    if prior is not None:
        gauge = _fit_to_prior([poses[k] for k in reached],  # type: ignore[misc]
                              [prior[k] for k in reached])
    _, sub_poses, sub_edges = _subgraph(poses, edges)
    sub_cov = covariances(sub_poses, sub_edges)
    factor, dof = variance_factor(sub_poses, sub_edges)
    sub_cov = [None if c is None else c * max(1.0, factor) for c in sub_cov]
    adjoint = _adjoint(gauge)
    final: list[F64 | None] = [None] * n
    covs: list[F64 | None] = [None] * n
    for new, old in enumerate(reached):
        final[old] = gauge @ poses[old]  # type: ignore[operator]
        cov = sub_cov[new]
        covs[old] = None if cov is None else adjoint @ cov @ adjoint.T
    for k, pose in enumerate(final):
        if pose is not None and prior is not None:
            dt, dr = pose_error(pose, prior[k])
            if dt > 2.0 or dr > 45.0:
                warnings.append(f"{names[k]}: registered {dt:.2f} m / {dr:.0f}° away from its "
                                "prior pose; check the prior (or the scan)")
    report = {"scans": names, "pairs": [p.record(names) for p in results],
              "pairs_kept": len(edges),
              "pairs_rejected": sum(1 for p in results if not p.accepted),
              "pairs_ambiguous": [{"target": names[p.target], "source": names[p.source],
                                   "reason": p.reason} for p in results
                                  if p.ambiguous and not p.accepted],
              "pairs_resolved_by_loop": resolved, "loop_closures": loops,
              "edges_dropped": dropped, "unregistered": missing, "conflicts": conflicts,
              "warnings": warnings,
              "covariance_variance_factor": {"value": round(factor, 3), "dof": dof,
                                             "applied": round(max(1.0, factor), 3)},
              "gauge": "prior (best fit of positions)" if prior is not None else
                       f"{names[0]} at the identity"}
    return final, covs, report


def site_conflicts(clouds: list[ScanClouds], poses: list[F64 | None], params: RegisterParams
                   ) -> list[dict[str, Any]]:
    """Every two registered scans whose free-space conflict at their poses exceeds
    ``max_conflict`` (neighbours or not: a scan placed onto another place shows here)."""
    found = []
    for i, pose_i in enumerate(poses):
        for j in range(i + 1, len(poses)):
            pose_j = poses[j]
            if pose_i is None or pose_j is None:
                continue
            conflict = pair_conflict(clouds[i], clouds[j], invert(pose_i) @ pose_j, params)
            if conflict > params.max_conflict:
                found.append({"a": clouds[i].name, "b": clouds[j].name,
                              "conflict": round(conflict, 4)})
    return found


def _connected_without(count: int, edges: list[PairResult], skip: int) -> bool:
    parent = list(range(count))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for e, p in enumerate(edges):
        if e != skip:
            parent[root(p.target)] = root(p.source)
    return len({root(k) for k in range(count)}) == 1


def error_twists(estimated: list[F64], truth: list[F64]) -> list[F64]:
    """Each scan's error as a twist (rx, ry, rz in rad, tx, ty, tz in m) in the estimate's
    site frame, the covariance's convention: the true pose, carried into the estimate's frame
    by tying the two frames at scan 0, is ``exp(twist) · estimate`` (so scan 0's is zero)."""
    tie = estimated[0] @ invert(truth[0])
    return [misclosure(tie @ true, estimate)
            for estimate, true in zip(estimated, truth, strict=True)]


def normalised_errors(twist: F64, covariance: F64) -> tuple[F64, float]:
    """Per-component error over its σ, and the squared Mahalanobis distance (χ² with 6 degrees
    of freedom when the covariance is honest: ≤ 20.1 in 99.7 % of cases)."""
    sigma = np.sqrt(np.maximum(np.diag(covariance), 1e-300))
    return twist / sigma, float(twist @ np.linalg.pinv(covariance) @ twist)


def rotation_deg(pose: F64) -> float:
    """The rotation angle of a pose (degrees)."""
    return math.degrees(math.acos(float(np.clip((np.trace(pose[:3, :3]) - 1) / 2, -1, 1))))
