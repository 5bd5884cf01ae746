"""Benchmark: the grid mesh of a lab-scale scan (1667 × 1440) at full resolution, step by step,
beside stride 2 and Poisson depth 9 on ~1.4 M points, each measured against the truth.

Targets (issue 20): the grid mesh stage at full resolution (every kept point, ≈ 4.8 M faces)
≤ 1.5 s on 2 cores; Poisson depth 9 (issue 7) ≤ 60 s, ≤ 2 GB. The scan is analytic (a box
room with a ball, 1 cm range noise) run through the filter stage's defaults (the default chain's
input to the mesh; since issue 20 two smoothing passes at σ_r 3 cm), so the figures do not depend
on the simulator. Besides wall time: CPU time
(on a loaded machine wall time counts other processes' turns), the stage's own per-step
seconds, peak RSS growth (``resource.getrusage`` in a forked child) and the peak of traced
allocations (``tracemalloc``, numpy's arrays included). Accuracy: mean distance from points
sampled on each mesh to the analytic surface. ``python benchmarks/bench_mesh.py [--quick]``
prints the figures and saves JSON into ``benchmarks/results/``.
"""

from __future__ import annotations

import os
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import pyarrow as pa
from harness import cli, cpu_seconds, measure, table

from scanpipe.evaluate import distance_stats, sample_surface
from scanpipe.grid import scan_grid
from scanpipe.meshing.grid_mesh import triangulate_grid
from scanpipe.meshing.poisson import PoissonParams, poisson_mesh
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.normals import estimate_normals, points_origins, points_xyz
from scanpipe.pipeline import get_stage
from scanpipe.stages.mesh import MeshParams, mesh_points

ROOM = BoxRoom(ball_centre_m=(1.5, -0.2, 1.0), ball_radius_m=0.5)
GRID_MESH_TARGET_S = 1.5


def traced_peak_mb(work: Callable[[], object]) -> float:
    """Peak of the allocations ``tracemalloc`` sees during ``work`` (numpy's included), MB."""
    tracemalloc.start()
    try:
        work()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def mean_distance_mm(vertices: Any, faces: Any, samples: int) -> float:
    """Mean distance from ``samples`` points spread over the mesh to the analytic room, mm."""
    points = sample_surface(vertices, faces, samples)
    mean = distance_stats(ROOM.distance_m(points))["mean_m"]
    return float(mean) * 1000 if mean is not None else float("nan")


def filtered(scan: pa.Table) -> pa.Table:
    """The scan after the filter stage's defaults (outlier marks and smoothing)."""
    return get_stage("filter").run({"points": scan}).tables["points"]


def run(quick: bool = False) -> dict[str, Any]:
    """Measure the grid mesh (full resolution and stride 2) and Poisson; return the figures."""
    # lab scan: 0.25° beam step × 0.108° platform step (1667 profiles over 180°)
    alpha_step, beta_step, profiles = (0.5, 0.45, 400) if quick else (0.25, 0.108, 1667)
    lab = filtered(scan_table(ROOM, alpha_step, beta_step, profiles=profiles, noise_m=0.01))
    grid = scan_grid(lab)
    assert grid is not None
    points, origins = points_xyz(lab), points_origins(lab)
    default = MeshParams()
    stride2 = MeshParams.model_validate({"grid": {"stride": 2}})
    repeats = 1 if quick else 3
    samples = 20_000 if quick else 200_000
    grid_results = [
        measure("grid triangulation alone (all points)",
                lambda: triangulate_grid(points, origins, grid), lab.num_rows, "points",
                repeats),
        measure("grid normals alone", lambda: estimate_normals(lab, grid=grid), lab.num_rows,
                "points", repeats),
        measure("mesh stage, defaults (full resolution: normals + faces + clean-up)",
                lambda: mesh_points(lab, default), lab.num_rows, "points", repeats),
        measure("mesh stage, grid.stride=2", lambda: mesh_points(lab, stride2), lab.num_rows,
                "points", repeats),
    ]
    cpu = {"grid_mesh_stage": cpu_seconds(lambda: mesh_points(lab, default), repeats=repeats),
           "grid_mesh_stage_stride2": cpu_seconds(lambda: mesh_points(lab, stride2),
                                                  repeats=repeats)}
    traced = {"grid_mesh_stage_mb": traced_peak_mb(lambda: mesh_points(lab, default))}
    full_mesh, full_report = mesh_points(lab, default)
    half_mesh, half_report = mesh_points(lab, stride2)
    accuracy_mm = {
        "grid_full_resolution": mean_distance_mm(full_mesh.vertices, full_mesh.faces, samples),
        "grid_stride2": mean_distance_mm(half_mesh.vertices, half_mesh.faces, samples),
        "filtered_points": 1000 * float(ROOM.distance_m(points).mean()),
    }

    # Poisson: ~1.4 M points (0.3° × 0.15°, 1200 × 1200), depth 9, one thread
    poisson_scan = filtered(scan_table(ROOM, 1.0, 1.0, noise_m=0.01) if quick
                            else scan_table(ROOM, 0.3, 0.15, noise_m=0.01))
    depth = 7 if quick else 9
    p_points, p_origins = points_xyz(poisson_scan), points_origins(poisson_scan)
    p_normals, _ = estimate_normals(poisson_scan)
    p_grid = scan_grid(poisson_scan)
    assert p_grid is not None
    steps = (p_grid.alpha_step_deg, p_grid.beta_step_deg)
    params = PoissonParams(depth=depth)
    poisson = measure(f"Poisson depth {depth} + trims",
                      lambda: poisson_mesh(p_points, p_normals, p_origins, None, params, steps),
                      poisson_scan.num_rows, "points", repeats=1)
    started = time.process_time()
    mesh, poisson_report = poisson_mesh(p_points, p_normals, p_origins, None, params, steps)
    cpu["poisson"] = time.process_time() - started
    accuracy_mm["poisson"] = mean_distance_mm(mesh.vertices, mesh.faces, samples)

    results = [*grid_results, poisson]
    stage = grid_results[2]
    figures = {
        "grid": list(grid.shape),
        "grid_points": lab.num_rows,
        "measurements": results,
        "grid_triangulation_s": grid_results[0].median_s,
        "grid_mesh_stage_s": stage.median_s,
        "grid_mesh_stage_stride2_s": grid_results[3].median_s,
        "grid_mesh_target_s": GRID_MESH_TARGET_S,
        "grid_mesh_target_met_wall": stage.median_s <= GRID_MESH_TARGET_S,
        "grid_mesh_target_met_cpu": cpu["grid_mesh_stage"] <= GRID_MESH_TARGET_S,
        "grid_faces": full_report["faces"],
        "grid_faces_stride2": half_report["faces"],
        "grid_stage_step_seconds": full_report["seconds"],
        "grid_stage_step_cpu_seconds": full_report["cpu_seconds"],
        "grid_stage_report": {k: full_report[k] for k in ("triangulation", "cleanup", "normals")},
        "grid_mesh_stage_peak_rss_growth_mb": stage.peak_rss_mb,
        "traced_peak_mb": traced,
        "mesh_mean_distance_mm": accuracy_mm,
        "poisson_points": poisson_scan.num_rows,
        "poisson_depth": depth,
        "poisson_s": poisson.median_s,
        "poisson_target_s": 60.0,
        "poisson_peak_rss_growth_mb": poisson.peak_rss_mb,
        "poisson_peak_target_mb": 2048.0,
        "poisson_report": poisson_report,
        "poisson_faces": len(mesh.faces),
        "cpu_s": cpu,
        "load_average": os.getloadavg(),
    }
    print(f"CPU: grid mesh stage {cpu['grid_mesh_stage']:.2f} s (stride 2: "
          f"{cpu['grid_mesh_stage_stride2']:.2f} s), Poisson {cpu['poisson']:.1f} s; "
          f"steps (CPU) {full_report['cpu_seconds']}; "
          f"traced peak {traced['grid_mesh_stage_mb']:.0f} MB; "
          f"load average {os.getloadavg()[0]:.1f}")
    print("mesh mean distance to the truth: " + ", ".join(
        f"{k} {v:.2f} mm" for k, v in accuracy_mm.items()))
    print(table([(m.name, f"{m.median_s:.2f} s", f"{m.cpu_median_s:.2f} s",
                  f"{m.throughput / 1e6:.2f} M {m.unit}/s", f"{m.peak_rss_mb:.0f} MB")
                 for m in results],
                ("work", "median", "CPU", "throughput", "peak RSS growth")))
    return figures


if __name__ == "__main__":
    cli("mesh", run, __doc__ or "", "smaller scans, depth 7")
