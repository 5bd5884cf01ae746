"""Accuracy of a result against ground truth: points, mesh, texture, and stage times.

Pure functions over arrays (and the shared :mod:`scanpipe.render` renderer), plus
:func:`evaluate_result`, which finds the artifacts of a workdir and the truth and runs them all.

- Points: unsigned distance of every point to the true surface: mean, RMS, 95th percentile.
- Mesh: ``accuracy`` is the mean distance of points sampled uniformly on the result's surface to
  the truth; ``precision`` the share of them within τ; ``completeness`` the share of points
  sampled on the true surface *that the scanner could see* (a ray from the scanner reaches them
  unobstructed, within its range limits) that lie within τ of the result; F = 2PR / (P + R).
- Texture: PSNR between the textured result and the truth, rendered by the same renderer from
  the same viewpoints, over the pixels where both show a texture at the same depth; and over
  all of the visible surface, where an unseen (untextured) face counts as error.
- Stage times: the ``seconds`` each stage recorded in its artifacts' provenance.
- Edges: how well the cameras sit on the scan (no truth needed): the scan's depth edges
  projected into the frames with the rig's camera values, the median distance (px) to the
  nearest image edge and the share within 2 px (:mod:`scanpipe.camera_selfcal`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ArtifactError, UsageError
from scanpipe.render import (
    PerspectiveView,
    Renderer,
    RenderMesh,
    load_mesh_file,
    load_render_mesh,
    vec3,
)
from scanpipe.workdir import all_provenance, find_artifact

F64 = NDArray[np.float64]

#: Depth agreement (m) for a pixel to count in the texture comparison.
PSNR_DEPTH_TOLERANCE_M = 0.05
#: The colour an untextured face is exported in (the texture stage's default ``neutral_rgb``).
UNSEEN_GREY = 128


@dataclass(frozen=True)
class Reference:
    """The true surface, where the scanner stood, and the scanner's range limits."""

    mesh: RenderMesh
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    min_range_m: float = 0.0
    max_range_m: float = math.inf


class SurfaceDistance:
    """Unsigned distances to, and rays against, one triangle mesh (Open3D ray casting)."""

    def __init__(self, mesh: RenderMesh) -> None:
        self.renderer = Renderer(mesh)

    def distance_m(self, points: NDArray[np.floating]) -> F64:
        """Distance from each point (N, 3) to the nearest surface."""
        o3d = self.renderer._o3d
        query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3))
        return np.asarray(self.renderer._scene.compute_distance(query).numpy(), np.float64)


def distance_stats(distances_m: NDArray[np.floating]) -> dict[str, float | int | None]:
    """Mean, RMS and 95th percentile of distances (None when there are none)."""
    d = np.asarray(distances_m, dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"mean_m": None, "rms_m": None, "p95_m": None, "count": 0}
    return {"mean_m": float(d.mean()), "rms_m": float(np.sqrt(np.mean(d * d))),
            "p95_m": float(np.percentile(d, 95)), "count": int(d.size)}


def sample_surface(vertices: NDArray[np.floating], faces: NDArray[np.integer], n: int,
                   seed: int = 0) -> F64:
    """``n`` points uniformly distributed over the area of a triangle mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces)]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(areas.sum())
    if total <= 0 or n <= 0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(tri), size=n, p=areas / total)
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[chosen]
    return np.asarray(t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0]),
                      dtype=np.float64)


def visible_from(surface: SurfaceDistance, points: F64, origin: Sequence[float],
                 min_range_m: float = 0.0, max_range_m: float = math.inf) -> NDArray[np.bool_]:
    """Which surface points a ray from ``origin`` reaches unobstructed, within range."""
    o = np.asarray(origin, dtype=np.float64)
    offset = points - o
    distance = np.linalg.norm(offset, axis=1)
    directions = offset / np.maximum(distance, 1e-12)[:, None]
    hits = surface.renderer.cast(o, directions)
    tolerance = 2e-3 + 1e-4 * distance
    unobstructed = hits["t_hit"].astype(np.float64) >= distance - tolerance
    return np.asarray(unobstructed & (distance >= min_range_m) & (distance <= max_range_m))



def surface_scores(to_truth: NDArray[np.floating], to_result: NDArray[np.floating],
                   seen: NDArray[np.bool_], tau_m: float) -> dict[str, Any]:
    """Mesh distance statistics, precision, completeness and F-score at ``tau_m`` from the
    result's samples' distances to the truth and the seen true samples' distances to the
    result (``seen``: which true samples a scanner could see)."""
    precision = float(np.mean(to_truth < tau_m)) if to_truth.size else 0.0
    completeness = float(np.mean(to_result < tau_m)) if to_result.size else 0.0
    fscore = (2 * precision * completeness / (precision + completeness)
              if precision + completeness > 0 else 0.0)
    stats = distance_stats(to_truth)
    return {"mesh_mean_m": stats["mean_m"], "mesh_rms_m": stats["rms_m"],
            "mesh_p95_m": stats["p95_m"], "precision": precision,
            "completeness": completeness, "fscore": fscore, "tau_m": tau_m,
            "visible_truth_share": float(np.mean(seen)) if seen.size else 0.0}

def mesh_metrics(result: RenderMesh, reference: Reference, tau_m: float = 0.02,
                 samples: int = 100_000, seed: int = 0,
                 truth_surface: SurfaceDistance | None = None) -> dict[str, Any]:
    """Accuracy, precision, completeness and F-score of a mesh at threshold ``tau_m``."""
    truth = truth_surface or SurfaceDistance(reference.mesh)
    result_surface = SurfaceDistance(result)
    on_result = sample_surface(result.vertices, result.faces, samples, seed)
    to_truth = truth.distance_m(on_result)
    on_truth = sample_surface(reference.mesh.vertices, reference.mesh.faces, samples, seed + 1)
    seen = visible_from(truth, on_truth, reference.origin, reference.min_range_m,
                        reference.max_range_m)
    to_result = result_surface.distance_m(on_truth[seen])
    return surface_scores(to_truth, to_result, seen, tau_m)


def matched_viewpoints(bounds: F64, origin: Sequence[float], count: int = 8, width: int = 160,
                       fov_deg: float = 70.0) -> list[PerspectiveView]:
    """``count`` viewpoints for comparing textures: from the scanner, turning about y (with a
    slight alternating tilt), when it stands inside the bounds; else on a ring around them."""
    height = max(1, width * 3 // 4)
    o = np.asarray(origin, dtype=np.float64)
    inside = bool(np.all(o > bounds[0]) and np.all(o < bounds[1]))
    views = []
    centre = bounds.mean(axis=0)
    radius = float(np.linalg.norm(bounds[1] - bounds[0]))
    for k in range(count):
        yaw = 2 * math.pi * k / count
        pitch = math.radians(-12.0 if k % 2 == 0 else 8.0)
        direction = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch),
                              math.cos(yaw) * math.cos(pitch)])
        if inside:
            eye, target = o, o + direction
        else:
            eye, target = centre - direction * radius, centre
        views.append(PerspectiveView(vec3(eye), vec3(target), width, height, fov_deg,
                                     name=f"match_{k}"))
    return views


def texture_psnr(result: RenderMesh, reference: Reference, views: int = 8,
                 width: int = 160) -> dict[str, Any]:
    """PSNR (dB) of the result's texture against the truth over matched viewpoints.

    ``texture_psnr_db``: pixels count where both renderings show a texture and their depths
    agree within :data:`PSNR_DEPTH_TOLERANCE_M`, so geometry errors do not pass for texture
    errors. ``texture_psnr_visible_db``: over *all* pixels where the result's surface meets
    the true (textured) surface, textured or not: an unseen (untextured) face counts with the
    neutral grey it is exported in (:data:`UNSEEN_GREY`), so coverage gaps are error;
    ``texture_unseen_share`` is the share of those pixels no frame textured.
    """
    empty: dict[str, Any] = {"texture_psnr_db": None, "texture_pixels": 0, "texture_views": 0,
             "texture_psnr_visible_db": None, "texture_visible_pixels": 0,
             "texture_unseen_share": None}
    if not reference.mesh.textured:
        return empty
    result_renderer, truth_renderer = Renderer(result), Renderer(reference.mesh)
    squared_error, pixels = 0.0, 0
    visible_error, visible_pixels, unseen_pixels = 0.0, 0, 0
    chosen = matched_viewpoints(reference.mesh.bounds, reference.origin, views, width)
    for view in chosen:
        a, b = result_renderer.render(view), truth_renderer.render(view)
        surface = b.textured & np.isfinite(a.depth_m)
        surface[surface] = np.abs(a.depth_m[surface] - b.depth_m[surface]
                                  ) < PSNR_DEPTH_TOLERANCE_M
        mask = surface & a.textured
        diff = a.rgb[mask].astype(np.float64) - b.rgb[mask].astype(np.float64)
        squared_error += float(np.sum(diff * diff))
        pixels += int(mask.sum())
        unseen = surface & ~a.textured
        grey = float(UNSEEN_GREY) - b.rgb[unseen].astype(np.float64)
        visible_error += float(np.sum(diff * diff)) + float(np.sum(grey * grey))
        visible_pixels += int(surface.sum())
        unseen_pixels += int(unseen.sum())
    report = {**empty, "texture_views": len(chosen), "texture_pixels": pixels,
              "texture_visible_pixels": visible_pixels}
    if pixels and result.textured:
        report["texture_psnr_db"] = _psnr(squared_error, pixels)
    if visible_pixels:
        report["texture_psnr_visible_db"] = _psnr(visible_error, visible_pixels)
        report["texture_unseen_share"] = unseen_pixels / visible_pixels
    return report


def _psnr(squared_error: float, pixels: int) -> float:
    """PSNR (dB, 8-bit) of a sum of squared errors over ``pixels`` RGB pixels."""
    mse = squared_error / (pixels * 3)
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


def edge_alignment(distances_px: NDArray[np.floating]) -> dict[str, float | int | None]:
    """Median image-edge to depth-edge distance (px) and the share within 2 px."""
    from scanpipe.camera_selfcal import WITHIN_PX

    d = np.asarray(distances_px, dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"edge_median_px": None, "edge_within_2px": None, "edge_points": 0}
    return {"edge_median_px": float(np.median(d)),
            "edge_within_2px": float(np.mean(d <= WITHIN_PX)), "edge_points": int(d.size)}


def edge_metrics(result: Path, max_frames: int = 12) -> dict[str, Any]:
    """The edge figures of a workdir (assembled points, frames, motor, rig): every camera
    together, pinhole and 360° (equirect) alike, and each camera's own under
    ``edge_cameras`` (a 360° frame's pixel spans more angle than a phone's: compare a camera
    with itself); None when something is missing (a cloud without a grid, no frames)."""
    from scanpipe.artifacts import read_artifact
    from scanpipe.camera_selfcal import (
        CameraFit,
        MotorTrack,
        depth_edges,
        frame_rows,
        observations,
    )
    from scanpipe.errors import ScanpipeError
    from scanpipe.grid import scan_grid
    from scanpipe.rig import rig_from_table

    empty: dict[str, Any] = {"edge_median_px": None, "edge_within_2px": None,
                             "edge_points": 0, "edge_cameras": {}}
    # the assembled grid (the filter's may have lost edge points) and the rig the chain
    # textured with (the calibrate stage's when it ran)
    preferred = {"points": result / "assemble" / "points.parquet",
                 "rig": result / "calibrate" / "rig.parquet"}
    paths = {n: preferred[n] if n in preferred and preferred[n].is_file()
             else find_artifact(result, n) for n in ("points", "frames", "motor", "rig")}
    if any(p is None for p in paths.values()):
        return empty
    tables = {n: read_artifact(p)[0] for n, p in paths.items() if p is not None}
    if tables["frames"].num_rows == 0 or scan_grid(tables["points"]) is None:
        return empty
    try:
        rig = rig_from_table(tables["rig"])
        edges = depth_edges(tables["points"])
        track = MotorTrack(tables["motor"], rig)
        distances: dict[str, NDArray[np.float64]] = {}
        for camera in rig.cameras:
            rows = frame_rows(tables["frames"], camera.id, max_frames)
            if rows.size == 0:
                continue
            fit = CameraFit(edges, observations(tables["frames"], rows, camera), track, ())
            x = fit.full(np.zeros(0))
            fit.select_visible(x)
            distances[camera.id] = fit.alignment(x).distances_px
    except ScanpipeError:
        return empty
    figures = edge_alignment(np.concatenate(list(distances.values())) if distances
                             else np.zeros(0))
    return {**figures, "edge_cameras": {k: edge_alignment(v) for k, v in distances.items()}}


def stage_times(result: Path) -> dict[str, float]:
    """Seconds per stage, from the provenance of the artifacts under ``result`` (a stage that
    wrote several artifacts in one run is counted once)."""
    runs: dict[tuple[str, str], float] = {}
    for record in all_provenance(result).values():
        stage, key, seconds = record.get("stage"), record.get("key"), record.get("seconds")
        if isinstance(stage, str) and isinstance(seconds, int | float):
            runs[(stage, str(key))] = float(seconds)
    times: dict[str, float] = {}
    for (stage, _), seconds in runs.items():
        times[stage] = times.get(stage, 0.0) + seconds
    return times


def load_reference(truth: Path) -> Reference:
    """A truth folder of the virtual rig (``scene.glb`` + ``rig.toml``) or any mesh file."""
    if truth.is_file():
        return Reference(load_mesh_file(truth))
    if not truth.is_dir():
        raise UsageError(f"--truth {truth}: not found (a truth folder or a mesh file)")
    scene = truth / "scene.glb"
    if not scene.is_file():
        raise ArtifactError(f"{truth}: no scene.glb; give a truth folder from `scanpipe "
                            "simulate` or a mesh file")
    mesh = load_mesh_file(scene)
    rig_file = truth / "rig.toml"
    if not rig_file.is_file():
        return Reference(mesh)
    from scanpipe.rig import load_rig

    rig = load_rig(rig_file)
    # The optical centre circles the axis with β; its height is what visibility depends on.
    height = float(rig.scanner.mount.translation_m[1])
    return Reference(mesh, (0.0, height, 0.0), rig.scanner.min_range_m, rig.scanner.max_range_m)


def _points_xyz(path: Path) -> F64:
    from scanpipe.artifacts import read_artifact
    from scanpipe.exporters.model import cloud_from_table

    return cloud_from_table(read_artifact(path)[0]).xyz.astype(np.float64)


def evaluate_result(result: Path, truth: Path, tau_m: float = 0.02, samples: int = 100_000,
                    views: int = 8, view_width: int = 160) -> dict[str, Any]:
    """``scanpipe eval``: every metric that applies, None for those that do not."""
    if not result.is_dir():
        raise UsageError(f"{result}: not a folder (give a workdir or a folder of artifacts)")
    reference = load_reference(truth)
    truth_surface = SurfaceDistance(reference.mesh)
    report: dict[str, Any] = {
        "result": str(result), "truth": str(truth), "tau_m": tau_m,
        "points_mean_m": None, "points_rms_m": None, "points_p95_m": None, "points_count": 0,
        "mesh_mean_m": None, "mesh_rms_m": None, "mesh_p95_m": None, "completeness": None,
        "precision": None, "fscore": None, "texture_psnr_db": None, "texture_pixels": 0,
        "texture_views": 0, "edge_median_px": None, "edge_within_2px": None, "edge_points": 0,
        "edge_cameras": {},
        "texture_psnr_visible_db": None, "texture_visible_pixels": 0,
        "texture_unseen_share": None,
    }
    points_path = find_artifact(result, "points")
    if points_path is not None:
        stats = distance_stats(truth_surface.distance_m(_points_xyz(points_path)))
        report.update(points_mean_m=stats["mean_m"], points_rms_m=stats["rms_m"],
                      points_p95_m=stats["p95_m"], points_count=stats["count"])
    has_mesh = (find_artifact(result, "mesh_vertices") is not None
                and find_artifact(result, "mesh_faces") is not None)
    if has_mesh:
        mesh = load_render_mesh(result)
        report.update(mesh_metrics(mesh, reference, tau_m, samples, 0, truth_surface))
        report.update(texture_psnr(mesh, reference, views, view_width))
    if points_path is None and not has_mesh:
        raise ArtifactError(f"{result}: neither points nor a mesh to evaluate")
    report.update(edge_metrics(result))
    report["stage_seconds"] = stage_times(result)
    return report


def format_evaluation(report: dict[str, Any]) -> str:
    """The evaluation as a text table."""

    def show(value: Any, unit: str = "", scale: float = 1.0, digits: int = 2) -> str:
        if value is None:
            return "n/a"
        return f"{value * scale:.{digits}f}{unit}"

    lines = [
        f"result   {report['result']}",
        f"truth    {report['truth']}",
        f"points   mean {show(report['points_mean_m'], ' mm', 1000)}   "
        f"RMS {show(report['points_rms_m'], ' mm', 1000)}   "
        f"p95 {show(report['points_p95_m'], ' mm', 1000)}   ({report['points_count']} points)",
        f"mesh     accuracy {show(report['mesh_mean_m'], ' mm', 1000)}   "
        f"precision {show(report['precision'], ' %', 100, 1)}   "
        f"completeness {show(report['completeness'], ' %', 100, 1)}   "
        f"F {show(report['fscore'], '', 1, 3)} at τ = {report['tau_m'] * 1000:g} mm",
        f"texture  PSNR {show(report['texture_psnr_db'], ' dB')} over "
        f"{report['texture_pixels']} textured pixels in {report['texture_views']} views; "
        f"over all visible surface {show(report.get('texture_psnr_visible_db'), ' dB')} "
        f"({show(report.get('texture_unseen_share'), ' %', 100, 1)} unseen)",
    ]
    if report.get("edge_points"):
        lines.append(f"edges    median {show(report['edge_median_px'], ' px')} from the image "
                     f"edges, {show(report['edge_within_2px'], ' %', 100, 1)} within 2 px "
                     f"({report['edge_points']} depth-edge points)")
        cameras = report.get("edge_cameras") or {}
        if len(cameras) > 1:
            lines.append("         " + "   ".join(
                f"{k} {show(v['edge_median_px'], ' px')} / "
                f"{show(v['edge_within_2px'], ' %', 100, 1)}" for k, v in cameras.items()))
    times = report.get("stage_seconds") or {}
    if times:
        lines.append("stages   " + "   ".join(f"{k} {v:.2f} s" for k, v in times.items()))
    return "\n".join(lines)


# -- sites: many scan positions, one model ---------------------------------------------------

#: The scene of a site truth folder (``scanpipe simulate --site``), in the site frame.
SITE_SCENE_FILE = "site_scene.glb"


@dataclass(frozen=True)
class SiteTruth:
    """The true site: its surface (site frame), each position's true pose (rig → site) and
    where each scanner stood (site frame), and the scanner's range limits."""

    mesh: RenderMesh
    poses: dict[str, F64]
    origins: dict[str, F64]
    min_range_m: float = 0.0
    max_range_m: float = math.inf


def is_site_truth(truth: Path) -> bool:
    """Whether ``truth`` is the truth folder of a simulated site."""
    return truth.is_dir() and (truth / SITE_SCENE_FILE).is_file()


def load_site_truth(truth: Path) -> SiteTruth:
    """A site truth folder: ``site_scene.glb``, ``poses.parquet`` and a folder per position
    with its ``rig.toml`` (the scanner's height and range limits)."""
    from scanpipe.artifacts import read_artifact
    from scanpipe.poses import poses_from_table
    from scanpipe.rig import load_rig

    poses_path = truth / "poses.parquet"
    if not poses_path.is_file():
        raise ArtifactError(f"{truth}: a site truth folder without poses.parquet; give the "
                            "--truth folder `scanpipe simulate --site` wrote")
    poses = poses_from_table(read_artifact(poses_path)[0], where=str(poses_path))
    origins: dict[str, F64] = {}
    min_range, max_range = 0.0, math.inf
    for name, pose in poses.items():
        height = 0.0
        rig_file = truth / name / "rig.toml"
        if rig_file.is_file():
            rig = load_rig(rig_file)
            height = float(rig.scanner.mount.translation_m[1])
            min_range, max_range = rig.scanner.min_range_m, rig.scanner.max_range_m
        origins[name] = np.asarray(pose[:3, :3] @ np.array([0.0, height, 0.0]) + pose[:3, 3],
                                   np.float64)
    return SiteTruth(load_mesh_file(truth / SITE_SCENE_FILE), poses, origins, min_range,
                     max_range)


def site_alignment(estimated: dict[str, F64], truth: dict[str, F64],
                   names: dict[str, str]) -> tuple[F64, str]:
    """The rigid transform from the result's site frame to the truth's, fixed by the first
    matched scan (the anchor): poses are compared relative to it, as registration fixes it."""
    if not names:
        raise ArtifactError(f"no scan of the result ({', '.join(sorted(estimated))}) is a "
                            f"position of the truth ({', '.join(sorted(truth))})")
    from scanpipe.poses import invert

    anchor = sorted(names)[0]
    return np.asarray(truth[names[anchor]] @ invert(estimated[anchor]), np.float64), anchor


def seen_from_any(surface: SurfaceDistance, points: F64, origins: Sequence[F64],
                  min_range_m: float = 0.0, max_range_m: float = math.inf
                  ) -> NDArray[np.bool_]:
    """Which surface points at least one of the scanners at ``origins`` sees
    (:func:`visible_from` for each)."""
    seen = np.zeros(len(points), dtype=bool)
    for origin in origins:
        rest = ~seen
        seen[rest] = visible_from(surface, points[rest], [float(v) for v in origin],
                                  min_range_m, max_range_m)
    return seen


def site_mesh_metrics(result: RenderMesh, truth: SiteTruth, origins: Sequence[F64],
                      tau_m: float = 0.02, samples: int = 100_000, seed: int = 0,
                      truth_surface: SurfaceDistance | None = None) -> dict[str, Any]:
    """:func:`mesh_metrics` of a site model (in the truth's frame): completeness over the true
    surface that any of the scanners at ``origins`` could see."""
    truth_surface = truth_surface or SurfaceDistance(truth.mesh)
    on_result = sample_surface(result.vertices, result.faces, samples, seed)
    to_truth = truth_surface.distance_m(on_result)
    on_truth = sample_surface(truth.mesh.vertices, truth.mesh.faces, samples, seed + 1)
    seen = seen_from_any(truth_surface, on_truth, origins, truth.min_range_m, truth.max_range_m)
    to_result = SurfaceDistance(result).distance_m(on_truth[seen])
    return surface_scores(to_truth, to_result, seen, tau_m)


def _site_poses(path: Path) -> dict[str, F64]:
    from scanpipe.artifacts import read_artifact
    from scanpipe.poses import poses_from_table

    return poses_from_table(read_artifact(path)[0], where=str(path))


def evaluate_site(result: Path, truth: Path, tau_m: float = 0.02, samples: int = 100_000
                  ) -> dict[str, Any]:
    """``scanpipe eval`` on a site: ``result`` is a site folder (``scanpipe register`` /
    ``site-model`` output) or its ``model`` folder, ``truth`` a site truth folder.

    Pose errors of every matched scan relative to the anchor scan (:func:`site_alignment`);
    the merged points and the model's mesh, moved into the truth's frame by the poses they were
    built with, against the true scene (completeness over what any position could see).
    """
    from scanpipe.poses import pose_error
    from scanpipe.site import match_scan_names

    if not result.is_dir():
        raise UsageError(f"{result}: not a folder (give a site folder from scanpipe register "
                         "or site-model)")
    site = load_site_truth(truth)
    poses_path = find_artifact(result, "poses")
    if poses_path is None:
        raise ArtifactError(f"{result}: no poses artifact (poses.parquet); give the --out "
                            "folder of scanpipe register or site-model")
    estimated = _site_poses(poses_path)
    names = match_scan_names(list(estimated), list(site.poses))
    to_truth, anchor = site_alignment(estimated, site.poses, names)
    errors = {}
    for name in sorted(names):
        dt, dr = pose_error(to_truth @ estimated[name], site.poses[names[name]])
        errors[name] = {"translation_m": dt, "rotation_deg": dr}
    report: dict[str, Any] = {
        "result": str(result), "truth": str(truth), "tau_m": tau_m, "poses": str(poses_path),
        "anchor": anchor, "pose_errors": errors,
        "pose_max_translation_m": max((e["translation_m"] for e in errors.values()),
                                      default=None),
        "pose_max_rotation_deg": max((e["rotation_deg"] for e in errors.values()),
                                     default=None),
        "unmatched_scans": sorted(set(estimated) - set(names)),
        "points_mean_m": None, "points_rms_m": None, "points_p95_m": None, "points_count": 0,
        "mesh_mean_m": None, "mesh_rms_m": None, "mesh_p95_m": None, "completeness": None,
        "precision": None, "fscore": None, "visible_truth_share": None,
        "texture_psnr_db": None, "texture_pixels": 0, "texture_views": 0,
    }
    model = result / "model" if (result / "model").is_dir() else result
    model_poses_path = find_artifact(model, "poses") or poses_path
    model_poses = _site_poses(model_poses_path)
    model_names = match_scan_names(list(model_poses), list(site.poses))
    model_to_truth, _ = site_alignment(model_poses, site.poses, model_names)
    report["model_poses"] = str(model_poses_path)
    truth_surface = SurfaceDistance(site.mesh)
    points_path = find_artifact(model, "points")
    if points_path is not None:
        xyz = _points_xyz(points_path)
        xyz = xyz @ model_to_truth[:3, :3].T + model_to_truth[:3, 3]
        stats = distance_stats(truth_surface.distance_m(xyz))
        report.update(points_mean_m=stats["mean_m"], points_rms_m=stats["rms_m"],
                      points_p95_m=stats["p95_m"], points_count=stats["count"])
    if (find_artifact(model, "mesh_vertices") is not None
            and find_artifact(model, "mesh_faces") is not None):
        mesh = load_render_mesh(model)
        vertices = (np.asarray(mesh.vertices, np.float64) @ model_to_truth[:3, :3].T
                    + model_to_truth[:3, 3])
        moved = RenderMesh(vertices.astype(np.float32), mesh.faces, mesh.vertex_colors,
                           mesh.face_uvs, mesh.face_pages, mesh.pages)
        origins = [site.origins[model_names[n]] for n in sorted(model_names)]
        report.update(site_mesh_metrics(moved, site, origins, tau_m, samples, 0,
                                        truth_surface))
        report.update(site_texture_psnr(moved, site, origins))
    return report


def site_texture_psnr(result: RenderMesh, truth: SiteTruth, origins: Sequence[F64],
                      views: int = 8, width: int = 160) -> dict[str, Any]:
    """:func:`texture_psnr` from every scan position's viewpoints together (the squared error
    summed over all their pixels)."""
    squared, pixels, count = 0.0, 0, 0
    for origin in origins:
        one = texture_psnr(result, Reference(truth.mesh, vec3(origin)), views, width)
        count += one["texture_views"]
        if one["texture_psnr_db"] is None:
            continue
        mse = 0.0 if math.isinf(one["texture_psnr_db"]) else 255.0**2 / 10 ** (
            one["texture_psnr_db"] / 10)
        squared += mse * one["texture_pixels"]
        pixels += one["texture_pixels"]
    if pixels == 0:
        return {"texture_psnr_db": None, "texture_pixels": 0, "texture_views": count}
    mse = squared / pixels
    return {"texture_psnr_db": math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse),
            "texture_pixels": pixels, "texture_views": count}


def format_site_evaluation(report: dict[str, Any]) -> str:
    """The site evaluation as a text table."""

    def mm(value: float | None) -> str:
        return "n/a" if value is None else f"{value * 1000:.2f} mm"

    lines = [f"result   {report['result']}", f"truth    {report['truth']}",
             f"poses    {report['poses']} (relative to {report['anchor']})"]
    for name, error in report["pose_errors"].items():
        lines.append(f"  {name:<16} {mm(error['translation_m'])}   "
                     f"{error['rotation_deg']:.4f}°")
    if report["unmatched_scans"]:
        lines.append(f"  not in the truth: {', '.join(report['unmatched_scans'])}")
    lines.append(f"points   mean {mm(report['points_mean_m'])}   RMS "
                 f"{mm(report['points_rms_m'])}   ({report['points_count']} points)")
    if report["mesh_mean_m"] is not None:
        lines.append(f"mesh     accuracy {mm(report['mesh_mean_m'])}   precision "
                     f"{report['precision'] * 100:.1f} %   completeness "
                     f"{report['completeness'] * 100:.1f} %   F {report['fscore']:.3f} at "
                     f"τ = {report['tau_m'] * 1000:g} mm")
        psnr = report.get("texture_psnr_db")
        lines.append(f"texture  PSNR {'n/a' if psnr is None else f'{psnr:.2f} dB'} over "
                     f"{report.get('texture_pixels', 0)} pixels in "
                     f"{report.get('texture_views', 0)} views (from every position)")
    else:
        lines.append("mesh     n/a (no model: run scanpipe site-model)")
    return "\n".join(lines)
