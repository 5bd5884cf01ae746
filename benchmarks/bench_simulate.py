"""Benchmark: ``simulate --direct`` at lab scale and at test scale, and its parts.

Targets (issue 4): the lab-scale scan (0.25° beam step, 0.108° motor step: 1667 positions ×
1440 samples, cameras off) in ≤ 30 s; a 2° × 2° test scan in ≤ 2 s. Measured in-process after
the libraries are imported (a fresh interpreter adds ~1–2 s of imports: Open3D, trimesh, mcap).
``python benchmarks/bench_simulate.py [--quick]`` prints the figures and saves JSON to
``benchmarks/results/simulate-<date>[-quick].json``.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, measure, table

from scanpipe.rig import default_rig
from scanpipe.sim.camera import render_rgb, scaled_camera
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.room import builtin_room

LAB_TARGET_S = 30.0
TEST_TARGET_S = 2.0


def run(quick: bool = False) -> dict[str, Any]:
    """Measure the direct simulation (and ray casting, rendering); return the figures."""
    scene = builtin_room()
    rays = 1_000_000
    rng = np.random.default_rng(0)
    directions = rng.standard_normal((rays, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    scene.cast(np.zeros(3), directions[:10])  # build the BVH outside the timing

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        test = SimOptions(motor_step_deg=2.0, beam_step_deg=2.0, cameras=False)
        lab = SimOptions(cameras=False) if not quick else SimOptions(
            cameras=False, motor_step_deg=0.72)
        summaries: dict[str, Any] = {}

        def simulate(name: str, options: SimOptions) -> None:
            summaries[name] = simulate_direct(root / f"{name}.mcap", root / f"{name}-truth",
                                              options)

        simulate("warm-up", test)  # imports and caches outside the timing
        measurements = [
            measure("cast rays (room)", lambda: scene.cast(np.zeros(3), directions),
                    rays, "rays", repeats=3, isolate=False),
            measure("render 960×540 frame",
                    lambda: render_rgb(scene, scaled_camera(default_rig().cameras[0], 0.5),
                                       30.0), 960 * 540, "pixels", repeats=3, isolate=False),
            measure("simulate --direct 2°×2°", lambda: simulate("test", test),
                    1.0, "scans", repeats=3, isolate=False),
        ]
        lab_name = "simulate --direct lab 0.25°×0.108°" if not quick else \
            "simulate --direct 0.25°×0.72° (quick)"
        measurements.append(measure(lab_name, lambda: simulate("lab", lab), 1.0, "scans",
                                    repeats=1, isolate=False))
    lab_summary = summaries["lab"]
    test_s = measurements[2].median_s
    lab_s = measurements[3].median_s
    return {
        "measurements": measurements,
        "lab": {"profiles": lab_summary["profiles"],
                "samples_per_profile": lab_summary["samples_per_profile"],
                "positions": lab_summary["positions"], "seconds": lab_s,
                "samples_per_s": lab_summary["profiles"] * lab_summary["samples_per_profile"]
                / lab_s,
                "target_s": LAB_TARGET_S, "meets_target": quick or lab_s <= LAB_TARGET_S},
        "test": {"seconds": test_s, "target_s": TEST_TARGET_S,
                 "meets_target": test_s <= TEST_TARGET_S},
        "quick": quick,
    }


def show(results: dict[str, Any]) -> None:
    """Print the figures."""
    rows = [(m.name, f"{m.median_s:.3f} s", f"{m.throughput:,.0f} {m.unit}/s")
            for m in results["measurements"]]
    print(table(rows, ("what", "median", "throughput")))
    print(f"lab: {results['lab']}")
    print(f"test: {results['test']}")


if __name__ == "__main__":
    cli("simulate", run, __doc__ or "", "a coarser lab scan", show)
