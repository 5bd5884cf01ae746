"""Study: the filter's smoothing settings against the grid mesh's accuracy on the built-in room.

The grid mesh's vertices are the filtered points, so its accuracy is the filter's smoothing
(issue 20: at full resolution the old defaults, one pass at σ_r 2 cm, were less accurate than
the Open3D-only baseline). For each seed the room is simulated without cameras (the rig's noise
σ 1 cm, dropouts) at the lab scan's resolution (0.25° × 0.108°; ``--quick``: 0.5° × 1°),
assembled once, then filtered with each candidate and meshed with the defaults; the mesh is
scored with ``scanpipe.evaluate.mesh_metrics`` (mean distance to the truth, completeness and
precision at τ = 2 cm). The Open3D-only baseline (``benchmarks/baseline.py``) is scored on the
first seed. ``python benchmarks/bench_smoothing.py [--quick]``; JSON in ``benchmarks/results/``.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: `benchmarks`

import numpy as np
import pyarrow as pa

from benchmarks.baseline import finite_xyz, open3d_baseline
from benchmarks.harness import cli, table
from benchmarks.pipeline_bench import scanner_centre
from benchmarks.scans import CACHE_DIR
from scanpipe.evaluate import Reference, SurfaceDistance, load_reference, mesh_metrics
from scanpipe.pipeline import get_stage
from scanpipe.render import RenderMesh
from scanpipe.rig import rig_from_table
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions

#: name → the filter's ``smoothing`` settings (the defaults are ``iterations`` 2, σ_r 0.03).
CANDIDATES: dict[str, dict[str, Any]] = {
    "off": {"enabled": False},
    "1 pass, σ_r 2 cm (before)": {"iterations": 1, "sigma_range_m": 0.02},
    "1 pass, σ_r 4 cm": {"iterations": 1, "sigma_range_m": 0.04},
    "2 passes, σ_r 2 cm": {"iterations": 2, "sigma_range_m": 0.02},
    "2 passes, σ_r 3 cm (defaults)": {"iterations": 2, "sigma_range_m": 0.03},
    "2 passes, σ_r 4 cm": {"iterations": 2, "sigma_range_m": 0.04},
    "3 passes, σ_r 3 cm": {"iterations": 3, "sigma_range_m": 0.03},
    "3 passes, σ_r 4 cm": {"iterations": 3, "sigma_range_m": 0.04},
}
SEEDS = (0, 1, 2)


def scores(vertices: np.ndarray, faces: np.ndarray, reference: Reference,
           surface: SurfaceDistance) -> dict[str, float]:
    """Mean distance (mm), completeness and precision at 2 cm of a mesh."""
    found = mesh_metrics(RenderMesh(vertices.astype(np.float32), faces.astype(np.int32)),
                         reference, 0.02, 100_000, truth_surface=surface)
    return {"mesh_mean_mm": 1000 * float(found["mesh_mean_m"]),
            "completeness": float(found["completeness"]), "precision": float(found["precision"])}


def scan(beam_step_deg: float, motor_step_deg: float,
         seed: int) -> tuple[Path, dict[str, pa.Table]]:
    """The simulated room (cached by its options and scanpipe's version) and its decoded
    tables."""
    from scanpipe import __version__

    folder = CACHE_DIR / f"smoothing-{beam_step_deg}-{motor_step_deg}-{seed}-{__version__}"
    if not (folder / "done").is_file():
        folder.mkdir(parents=True, exist_ok=True)
        simulate_direct(folder / "scan.mcap", folder / "truth", SimOptions(
            beam_step_deg=beam_step_deg, motor_step_deg=motor_step_deg, cameras=False,
            seed=seed))
        (folder / "done").write_text("")
    decoded = get_stage("decode").run({"recording": folder / "scan.mcap"}).tables
    return folder / "truth", decoded


def run(quick: bool = False) -> dict[str, Any]:
    """Score every candidate on every seed; return the figures."""
    steps = (0.5, 1.0) if quick else (0.25, 0.108)
    rows: dict[str, list[dict[str, float]]] = {}
    for seed in SEEDS:
        truth, decoded = scan(*steps, seed)
        points = get_stage("assemble").run(
            {k: decoded[k] for k in ("profiles", "motor", "rig")}).tables["points"]
        reference = load_reference(truth)
        surface = SurfaceDistance(reference.mesh)
        for name, smoothing in CANDIDATES.items():
            started = time.process_time()
            filtered = get_stage("filter").run({"points": points}, smoothing=smoothing)
            filter_cpu = time.process_time() - started
            mesh = get_stage("mesh").run({"points": filtered.tables["points"]}).tables
            v, f = mesh["mesh_vertices"], mesh["mesh_faces"]
            row = scores(np.stack([v.column(c).to_numpy() for c in "xyz"], axis=1),
                         np.stack([f.column(c).to_numpy() for c in ("v0", "v1", "v2")], axis=1),
                         reference, surface)
            rows.setdefault(name, []).append({**row, "filter_cpu_s": filter_cpu})
            print(f"seed {seed} {name}: {row}", file=sys.stderr, flush=True)
        if seed == SEEDS[0]:
            base = open3d_baseline(finite_xyz(points), scanner_centre(decoded["rig"]),
                                   decoded["frames"], decoded["motor"],
                                   rig_from_table(decoded["rig"]), depth=7 if quick else 9)
            rows["Open3D-only baseline"] = [{**scores(base.vertices, base.faces, reference,
                                                      surface), "filter_cpu_s": 0.0}]
    summary = {name: {key: statistics.mean(r[key] for r in runs) for key in runs[0]}
               for name, runs in rows.items()}
    print(table([(name, f"{s['mesh_mean_mm']:.3f} mm", f"{s['completeness']:.4f}",
                  f"{s['precision']:.5f}", f"{s['filter_cpu_s']:.2f} s", str(len(rows[name])))
                 for name, s in summary.items()],
                ("smoothing", "mesh mean", "completeness@2cm", "precision@2cm", "filter CPU",
                 "seeds")))
    return {"grid_steps_deg": steps, "seeds": SEEDS, "runs": rows, "mean_over_seeds": summary}


if __name__ == "__main__":
    cli("smoothing", run, __doc__ or "", "coarser scans (0.5° × 1°), Poisson depth 7")
