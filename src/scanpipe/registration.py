"""Registration of the scans of a site: pairwise (coarse + fine), then a pose graph.

Kernel functions over numpy arrays (Open3D inside); :mod:`scanpipe.site` is the shell that reads
workdirs and writes artifacts.

1. Per scan: a coarse cloud (voxel ``coarse_voxel_m``, normals, FPFH features) and a fine one
   (voxel ``fine_voxel_m``, normals oriented toward the scanner).
2. Per candidate pair (all pairs; with a prior, those whose prior positions are within
   ``pair_max_distance_m``): initial guesses from FPFH + RANSAC (global, needs no prior) and,
   when given, from the prior; each refined by point-to-plane ICP (or generalized ICP) from
   coarse to fine; the guess with the best fitness wins. A pair is kept when its overlap
   (fitness: share of the source's points with a counterpart within ``overlap_distance_m``)
   is at least ``min_overlap`` and its inlier RMS at most ``max_rmse_m``; else it is reported
   and left out.
3. Pose graph over the kept pairs (Open3D, Levenberg–Marquardt), started from the pairs'
   maximum-fitness spanning tree; edges that disagree with the optimum by more than
   ``max_edge_disagreement_m`` / ``_deg`` are dropped one at a time (worst first, never one
   the graph needs to stay connected) and the graph re-optimised: a loop that does not close
   is reported, never averaged in.
4. Gauge: scan 0 at the identity, or with a prior, the rigid transform that best fits the
   optimised positions to the prior positions (so the site lands in the prior's frame).
5. Covariance per scan from the graph's information (ICP correspondences, scaled by each pair's
   residual; scan 0 fixed): a lower bound, since it treats point residuals as independent.
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

    coarse_voxel_m: float = Field(0.08, gt=0, le=1)
    fine_voxel_m: float = Field(0.03, gt=0, le=0.5)
    fine_method: Literal["point_to_plane", "generalized"] = "point_to_plane"
    overlap_distance_m: float = Field(0.05, gt=0, le=1)
    min_overlap: float = Field(0.15, gt=0, le=1)
    max_rmse_m: float = Field(0.03, gt=0, le=1)
    ransac_iterations: int = Field(50_000, ge=1000, le=10_000_000)
    pair_max_distance_m: float | None = Field(None, gt=0, description="With a prior: only "
                                              "pairs whose prior positions are this close.")
    max_edge_disagreement_m: float = Field(0.02, gt=0)
    max_edge_disagreement_deg: float = Field(0.5, gt=0)
    prior_gate_m: float = Field(1.5, gt=0, description="With a prior: a pair whose result "
                                "moves the scans this far from the prior's relative pose is "
                                "left out (a match to a look-alike place).")
    prior_gate_deg: float = Field(30.0, gt=0, le=180)
    seed: int = Field(0, ge=0)


@dataclass
class ScanClouds:
    """One scan prepared for registration."""

    name: str
    coarse: Any
    features: Any
    fine: Any
    points: int


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
    information: F64 = field(default_factory=lambda: np.zeros((6, 6)))

    def record(self, names: list[str]) -> dict[str, Any]:
        """The pair as the report shows it."""
        return {"target": names[self.target], "source": names[self.source],
                "overlap": round(self.fitness, 4), "rmse_m": round(self.rmse_m, 5),
                "init": self.init, "accepted": self.accepted, "reason": self.reason}


def _o3d() -> Any:
    import open3d as o3d

    return o3d


def prepare_scan(name: str, xyz: NDArray[np.floating], origin: NDArray[np.floating],
                 params: RegisterParams) -> ScanClouds:
    """Downsample, estimate normals (toward the scanner) and FPFH features of one scan."""
    o3d = _o3d()
    finite = np.all(np.isfinite(xyz), axis=1)
    points = np.asarray(xyz, np.float64)[finite]
    if len(points) < 100:
        raise StageError(f"{name}: only {len(points)} points; too few to register")
    centre = np.asarray(origin, np.float64)[finite].mean(axis=0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))

    def down(voxel: float) -> Any:
        small = cloud.voxel_down_sample(voxel)
        small.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
        small.orient_normals_towards_camera_location(centre)
        return small

    coarse = down(params.coarse_voxel_m)
    features = o3d.pipelines.registration.compute_fpfh_feature(
        coarse, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * params.coarse_voxel_m,
                                                     max_nn=100))
    return ScanClouds(name, coarse, features, down(params.fine_voxel_m), len(points))


def _ransac(source: ScanClouds, target: ScanClouds, params: RegisterParams) -> F64:
    o3d = _o3d()
    reg = o3d.pipelines.registration
    distance = 1.5 * params.coarse_voxel_m
    o3d.utility.random.seed(params.seed)
    result = reg.registration_ransac_based_on_feature_matching(
        source.coarse, target.coarse, source.features, target.features, True, distance,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(params.ransac_iterations, 0.9999))
    return np.asarray(result.transformation, np.float64)


def refine(source: ScanClouds, target: ScanClouds, init: F64, params: RegisterParams
           ) -> tuple[F64, float, float]:
    """ICP from coarse to fine; returns (transform, fitness, inlier RMS) at the overlap
    distance."""
    o3d = _o3d()
    reg = o3d.pipelines.registration
    transform = init
    schedule = ((source.coarse, target.coarse, 2.0 * params.coarse_voxel_m, 30),
                (source.fine, target.fine, 2.0 * params.fine_voxel_m, 30),
                (source.fine, target.fine, params.overlap_distance_m, 60))
    for src, tgt, distance, iterations in schedule:
        criteria = reg.ICPConvergenceCriteria(1e-8, 1e-8, iterations)
        if params.fine_method == "generalized":
            result = reg.registration_generalized_icp(
                src, tgt, distance, transform,
                reg.TransformationEstimationForGeneralizedICP(), criteria)
        else:
            result = reg.registration_icp(src, tgt, distance, transform,
                                          reg.TransformationEstimationPointToPlane(), criteria)
        transform = np.asarray(result.transformation, np.float64)
    check = reg.evaluate_registration(source.fine, target.fine, params.overlap_distance_m,
                                      transform)
    return transform, float(check.fitness), float(check.inlier_rmse)


def register_pair(clouds: list[ScanClouds], target: int, source: int, params: RegisterParams,
                  prior: list[F64] | None) -> PairResult:
    """Align scan ``source`` to scan ``target``: every initial guess refined, the best kept."""
    o3d = _o3d()
    guesses = [("ransac", _ransac(clouds[source], clouds[target], params))]
    if prior is not None:
        guesses.append(("prior", invert(prior[target]) @ prior[source]))
    best: PairResult | None = None
    best_rank: tuple[bool, float] = (False, -1.0)
    for label, guess in guesses:
        transform, fitness, rmse = refine(clouds[source], clouds[target], guess, params)
        gap = (pose_error(transform, invert(prior[target]) @ prior[source])
               if prior is not None else (0.0, 0.0))
        # a result near the prior beats a better-fitting one at a look-alike place
        rank = (gap[0] <= params.prior_gate_m and gap[1] <= params.prior_gate_deg, fitness)
        if best is None or rank[0] > best_rank[0] or (
                rank[0] == best_rank[0] and fitness > best.fitness + 1e-3):
            best, best_rank = PairResult(target, source, transform, fitness, rmse, label,
                                         False), rank
    assert best is not None
    prior_gap = (pose_error(best.transform, invert(prior[target]) @ prior[source])
                 if prior is not None else (0.0, 0.0))
    if best.fitness < params.min_overlap:
        best.reason = f"overlap {best.fitness:.1%} < min_overlap {params.min_overlap:.0%}"
    elif best.rmse_m > params.max_rmse_m:
        best.reason = f"residual {best.rmse_m * 1000:.1f} mm > max_rmse_m"
    elif prior_gap[0] > params.prior_gate_m or prior_gap[1] > params.prior_gate_deg:
        best.reason = (f"{prior_gap[0]:.2f} m / {prior_gap[1]:.0f}° from the prior's relative "
                       "pose (prior_gate_m / _deg): a look-alike place")
    else:
        best.accepted = True
        info = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
            clouds[source].fine, clouds[target].fine, params.overlap_distance_m, best.transform)
        variance = max(best.rmse_m ** 2 / 3.0, 1e-10)
        best.information = np.asarray(info, np.float64) / variance
    return best


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


def _optimise(poses: list[F64], pairs: list[PairResult], tree: set[int],
              params: RegisterParams) -> list[F64]:
    o3d = _o3d()
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    for pose in poses:
        graph.nodes.append(reg.PoseGraphNode(pose))
    for k, p in enumerate(pairs):
        # Open3D's edge maps the source node's frame into the target node's
        graph.edges.append(reg.PoseGraphEdge(p.source, p.target, p.transform, p.information,
                                             uncertain=k not in tree))
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=params.overlap_distance_m, edge_prune_threshold=0.25,
        preference_loop_closure=1.0, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    return [np.asarray(node.pose, np.float64) for node in graph.nodes]


def _adjoint(pose: F64) -> F64:
    rotation, t = pose[:3, :3], pose[:3, 3]
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    adjoint = np.zeros((6, 6))
    adjoint[:3, :3] = rotation
    adjoint[3:, 3:] = rotation
    adjoint[3:, :3] = skew @ rotation
    return adjoint


def covariances(poses: list[F64], pairs: list[PairResult]) -> list[F64 | None]:
    """Per-scan 6 × 6 covariance (site frame, rx ry rz tx ty tz) from the graph's information,
    scan 0 fixed; None for scan 0 and when the system is singular."""
    n = len(poses)
    hessian = np.zeros((6 * n, 6 * n))
    for p in pairs:
        a = _adjoint(invert(poses[p.target]))
        block = a.T @ p.information @ a
        i, j = p.target, p.source
        for u, v, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            hessian[6 * u:6 * u + 6, 6 * v:6 * v + 6] += sign * block
    reduced = hessian[6:, 6:]
    result: list[F64 | None] = [None] * n
    try:
        inverse = np.linalg.inv(reduced)
    except np.linalg.LinAlgError:
        return result
    for k in range(1, n):
        result[k] = np.asarray(inverse[6 * k - 6:6 * k, 6 * k - 6:6 * k], np.float64)
    return result


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


def register_scans(clouds: list[ScanClouds], params: RegisterParams,
                   prior: list[F64] | None = None, progress: Any = None
                   ) -> tuple[list[F64 | None], list[F64 | None], dict[str, Any]]:
    """Register every scan: poses (None for a scan no kept pair reaches), covariances and the
    report (pairs, dropped edges, warnings)."""
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
    dropped: list[dict[str, Any]] = []
    while True:
        initial, tree = _spanning_tree(n, kept)
        reached = [k for k in range(n) if initial[k] is not None]
        sub = {old: new for new, old in enumerate(reached)}
        edges = [PairResult(sub[p.target], sub[p.source], p.transform, p.fitness, p.rmse_m,
                            p.init, True, "", p.information)
                 for p in kept if p.target in sub and p.source in sub]
        tree_sub = {e for e, p in enumerate(kept) if e in tree}
        optimised = _optimise([initial[k] for k in reached], edges,  # type: ignore[misc]
                              tree_sub, params)
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
            break
        dropped.append(worst_record)
        bad = edges[worst]
        kept = [p for p in kept if not (sub.get(p.target) == bad.target
                                        and sub.get(p.source) == bad.source)]
    for record in dropped:
        warnings.append(f"pair {record['target']}–{record['source']} disagrees with the other "
                        f"pairs by {record['disagreement_m'] * 1000:.1f} mm / "
                        f"{record['disagreement_deg']:.2f}°: left out of the pose graph")
    rejected = [p for p in results if not p.accepted]
    missing = [names[k] for k in range(n) if k not in sub]
    if missing:
        warnings.append(f"scans {', '.join(missing)} overlap no other scan well enough: not "
                        "registered (no pose written); scan closer to their neighbours")
    gauge = np.eye(4)
    if prior is not None:
        gauge = _fit_to_prior(optimised, [prior[k] for k in reached])
    poses: list[F64 | None] = [None] * n
    covs: list[F64 | None] = [None] * n
    sub_cov = covariances(optimised, edges)
    adjoint = _adjoint(gauge)
    for new, old in enumerate(reached):
        poses[old] = gauge @ optimised[new]
        cov = sub_cov[new]
        covs[old] = None if cov is None else adjoint @ cov @ adjoint.T
    for k, pose in enumerate(poses):
        if pose is not None and prior is not None:
            dt, dr = pose_error(pose, prior[k])
            if dt > 2.0 or dr > 45.0:
                warnings.append(f"{names[k]}: registered {dt:.2f} m / {dr:.0f}° away from its "
                                "prior pose; check the prior (or the scan)")
    report = {"scans": names, "pairs": [p.record(names) for p in results],
              "pairs_kept": len(kept), "pairs_rejected": len(rejected),
              "edges_dropped": dropped, "unregistered": missing, "warnings": warnings,
              "gauge": "prior (best fit of positions)" if prior is not None else
                       f"{names[0]} at the identity"}
    return poses, covs, report


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


def rotation_deg(pose: F64) -> float:
    """The rotation angle of a pose (degrees)."""
    return math.degrees(math.acos(float(np.clip((np.trace(pose[:3, :3]) - 1) / 2, -1, 1))))
