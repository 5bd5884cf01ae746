"""Benchmark: assemble a lab-scale scan (1667 × 1440) from synthetic tables; grid filters on it.

Targets (issue 6): assemble ≥ 20 M points/s; the grid filters on 2.4 M points ≤ 1 s.
``python benchmarks/bench_assemble.py [--quick]`` prints the figures and saves JSON into
``benchmarks/results/``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, cpu_seconds, measure, table

from scanpipe.progress import no_progress
from scanpipe.rig import MotorConfig, Rig, ScannerConfig, rig_table
from scanpipe.stages.assemble import AssembleParams, assemble_stage
from scanpipe.stages.filter import FilterParams, filter_stage

T0_NS = 1_700_000_000_000_000_000


def box_ranges(alpha_deg: np.ndarray, beta_deg: np.ndarray,
               half_extent_m: tuple[float, float, float] = (3.0, 1.5, 2.0)) -> np.ndarray:
    """Ranges from the origin to the inside of an axis-aligned box, with 1 cm noise."""
    a = np.radians(alpha_deg)[None, :]
    b = np.radians(beta_deg)[:, None]
    direction = (np.sin(a) * np.cos(b), np.cos(a) + 0 * b, np.sin(a) * np.sin(b))
    with np.errstate(divide="ignore"):
        t = np.min([np.abs(h / d) for h, d in zip(half_extent_m, direction, strict=True)], axis=0)
    noise = np.random.default_rng(1).normal(0.0, 0.01, t.shape)
    return (t + noise).astype(np.float32)


def lab_tables(profiles: int, samples: int, motor_steps: int = 3) -> dict[str, pa.Table]:
    """Step-and-scan tables: one profile per position, each inside its stationary interval."""
    rig = Rig(scanner=ScannerConfig(beam_step_deg=360.0 / samples),
              motor=MotorConfig(pulse_limit=10**6, unlimited_travel=True))
    period_ns = 400_000_000
    ok_ns = T0_NS + np.arange(profiles, dtype=np.int64) * period_ns
    steps = np.arange(profiles, dtype=np.int64) * motor_steps
    move_ns = ok_ns[1:] - 100_000_000
    motor = pa.table({
        "log_time_ns": np.concatenate([ok_ns, move_ns]),
        "step_count": np.concatenate([steps, steps[:-1]]),
        "target_step_count": np.concatenate([steps, steps[1:]]),
        "moving": np.concatenate([np.zeros(profiles, bool), np.ones(profiles - 1, bool)]),
        "device_time_us": np.zeros(2 * profiles - 1, np.int64),
    })
    alpha = np.arange(samples) * rig.scanner.beam_step_deg
    ranges = box_ranges(alpha, steps * rig.motor.pulse_step_deg)
    offsets = pa.array(np.arange(profiles + 1, dtype=np.int32) * samples)
    recv = ok_ns + 60_000_000 + 200_000_000
    none = pa.nulls(profiles, pa.int64())
    profile_table = pa.table({
        "recv_time_ns": recv, "device_time_ns": none, "device_end_time_ns": none,
        "frame": np.arange(profiles, dtype=np.int64),
        "sector": np.zeros(profiles, np.int32),
        "start_angle_deg": np.zeros(profiles), "step_deg": np.full(profiles, alpha[1]),
        "ranges_m": pa.ListArray.from_arrays(offsets, pa.array(ranges.ravel())),
        "echo": pa.nulls(profiles, pa.list_(pa.uint16())),
        "checksum_ok": np.ones(profiles, bool), "dialect": ["ldoem"] * profiles,
    })
    return {"profiles": profile_table, "motor": motor, "rig": rig_table(rig)}


def run(quick: bool = False) -> dict[str, Any]:
    """Measure assemble and the grid filters; return the figures."""
    profiles, samples = (400, 720) if quick else (1667, 1440)
    inputs = lab_tables(profiles, samples)
    points = assemble_stage(inputs, AssembleParams(), no_progress).tables["points"]
    n = points.num_rows
    grid_only = FilterParams(statistical_outlier={"enabled": False})
    with_smoothing = FilterParams(statistical_outlier={"enabled": False},
                                  smoothing={"enabled": True})
    repeats = 3
    results = [
        measure("assemble", lambda: assemble_stage(inputs, AssembleParams(), no_progress), n,
                "points", repeats),
        measure("grid filters (defaults)", lambda: filter_stage({"points": points}, grid_only,
                                                                 no_progress), n, "points",
                repeats),
        measure("grid filters + smoothing", lambda: filter_stage(
            {"points": points}, with_smoothing, no_progress), n, "points", repeats),
    ]
    # CPU seconds as well as wall time: on a shared 2-core machine the wall time also counts
    # other processes' turns.
    cpu = {
        "assemble": cpu_seconds(lambda: assemble_stage(inputs, AssembleParams(), no_progress)),
        "grid_filters": cpu_seconds(lambda: filter_stage({"points": points}, grid_only,
                                                          no_progress)),
    }
    report = filter_stage({"points": points}, grid_only, no_progress).report
    figures = {
        "grid": [profiles, samples],
        "points": n,
        "measurements": results,
        "assemble_points_per_s": results[0].throughput,
        "assemble_target_points_per_s": 20e6,
        "grid_filters_s": results[1].median_s,
        "grid_filters_with_smoothing_s": results[2].median_s,
        "grid_filters_target_s": 1.0,
        "cpu_s": cpu,
        "assemble_points_per_cpu_s": n / cpu["assemble"],
        "load_average": os.getloadavg(),
        "filter_report": report["filters"],
    }
    print(f"CPU: assemble {cpu['assemble']:.3f} s ({n / cpu['assemble'] / 1e6:.1f} M points/s), "
          f"grid filters {cpu['grid_filters']:.3f} s; load average {os.getloadavg()[0]:.1f}")
    print(table([(m.name, f"{m.median_s:.3f} s", f"{m.throughput / 1e6:.1f} M {m.unit}/s",
                  f"{m.peak_rss_mb:.0f} MB") for m in results],
                ("work", "median", "throughput", "peak RSS")))
    return figures


if __name__ == "__main__":
    cli("assemble", run, __doc__ or "", "a smaller grid")
