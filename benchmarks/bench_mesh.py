"""Benchmark: grid mesh of a lab-scale scan (1667 × 1440) and Poisson depth 9 on ~1.4 M points.

Targets (issue 7): grid mesh ≤ 2 s; Poisson depth 9 on ~1.4 M points ≤ 60 s with peak memory
≤ 2 GB. The scans are analytic (a box room with a ball, 1 cm range noise), so the figures do
not depend on the simulator. ``python benchmarks/bench_mesh.py [--quick]`` prints the figures
and saves JSON into ``benchmarks/results/``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, cpu_seconds, measure, table

from scanpipe.grid import scan_grid
from scanpipe.meshing.grid_mesh import triangulate_grid
from scanpipe.meshing.poisson import PoissonParams, poisson_mesh
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.normals import estimate_normals, points_origins, points_xyz
from scanpipe.stages.mesh import MeshParams, mesh_points

ROOM = BoxRoom(ball_centre_m=(1.5, -0.2, 1.0), ball_radius_m=0.5)


def run(quick: bool = False) -> dict[str, Any]:
    """Measure the grid mesh and Poisson; return the figures."""
    # lab scan: 0.25° beam step × 0.108° platform step (1667 profiles over 180°)
    alpha_step, beta_step, profiles = (0.5, 0.45, 400) if quick else (0.25, 0.108, 1667)
    lab = scan_table(ROOM, alpha_step, beta_step, profiles=profiles, noise_m=0.01)
    grid = scan_grid(lab)
    assert grid is not None
    points, origins = points_xyz(lab), points_origins(lab)
    grid_params = MeshParams(method="grid")
    repeats = 1 if quick else 3
    grid_results = [
        measure("grid triangulation", lambda: triangulate_grid(points, origins, grid),
                lab.num_rows, "points", repeats),
        measure("grid normals", lambda: estimate_normals(lab, grid=grid), lab.num_rows,
                "points", repeats),
        measure("grid mesh stage (normals + faces + clean-up)",
                lambda: mesh_points(lab, grid_params), lab.num_rows, "points", repeats),
    ]
    cpu = {"grid_triangulation": cpu_seconds(lambda: triangulate_grid(points, origins, grid)),
           "grid_mesh_stage": cpu_seconds(lambda: mesh_points(lab, grid_params), repeats=1)}
    _, grid_report = mesh_points(lab, grid_params)

    # Poisson: ~1.4 M points (0.3° × 0.15°, 1200 × 1200), depth 9, one thread
    poisson_scan = (scan_table(ROOM, 1.0, 1.0, noise_m=0.01) if quick
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

    results = [*grid_results, poisson]
    figures = {
        "grid": list(grid.shape),
        "grid_points": lab.num_rows,
        "measurements": results,
        "grid_triangulation_s": grid_results[0].median_s,
        "grid_mesh_stage_s": grid_results[2].median_s,
        "grid_mesh_target_s": 2.0,
        "grid_faces": grid_report["faces"],
        "grid_stage_step_seconds": grid_report["seconds"],
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
    print(f"CPU: grid triangulation {cpu['grid_triangulation']:.2f} s, grid mesh stage "
          f"{cpu['grid_mesh_stage']:.2f} s, Poisson {cpu['poisson']:.1f} s; "
          f"load average {os.getloadavg()[0]:.1f}")
    print(table([(m.name, f"{m.median_s:.2f} s", f"{m.throughput / 1e6:.2f} M {m.unit}/s",
                  f"{m.peak_rss_mb:.0f} MB") for m in results],
                ("work", "median", "throughput", "peak RSS growth")))
    return figures


if __name__ == "__main__":
    cli("mesh", run, __doc__ or "", "smaller scans, depth 7")
