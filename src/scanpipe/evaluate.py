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
    precision = float(np.mean(to_truth < tau_m)) if to_truth.size else 0.0
    completeness = float(np.mean(to_result < tau_m)) if to_result.size else 0.0
    fscore = (2 * precision * completeness / (precision + completeness)
              if precision + completeness > 0 else 0.0)
    stats = distance_stats(to_truth)
    return {"mesh_mean_m": stats["mean_m"], "mesh_rms_m": stats["rms_m"],
            "mesh_p95_m": stats["p95_m"], "precision": precision,
            "completeness": completeness, "fscore": fscore, "tau_m": tau_m,
            "visible_truth_share": float(np.mean(seen)) if seen.size else 0.0}


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
        "texture_views": 0, "texture_psnr_visible_db": None, "texture_visible_pixels": 0,
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
    times = report.get("stage_seconds") or {}
    if times:
        lines.append("stages   " + "   ".join(f"{k} {v:.2f} s" for k, v in times.items()))
    return "\n".join(lines)
