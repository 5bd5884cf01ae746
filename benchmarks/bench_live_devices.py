"""Benchmark: every simulated scanner through the user's path, live, and its accuracy.

For each device (LMS111 and TiM571 on CoLa-B over TCP, UST-10LX on SCIP over TCP, URG-04LX on
SCIP over a pty, LD06 and STL-27L on LDRobot packets over a pty): ``scanpipe simulate`` with the
emulators on their real transports (the recorder drives the device with its own commands and
records the MCAP), then ``scanpipe run`` on the recording; the assembled points are compared with
the built-in room's true surface. Measured per device: points RMS to the surface in mm and in
units of the device's range noise σ (target, issue 17: ≤ 1.1 σ), coverage (turns decoded ÷
turns the emulator sent while recording, and ÷ the turns the head made in that time: the
emulator skips turns it cannot send in time on a loaded host), the fitted clock rates, and wall
and CPU time (this process and its children) of simulate and run.

``--load N`` runs N busy-loop processes alongside (the robustness check: accuracy must hold on a
loaded host; coverage may drop). ``python benchmarks/bench_live_devices.py [--quick] [--load N]
[--devices lms111,ld06]`` prints a table and saves JSON to
``benchmarks/results/live_devices[-quick][-loadN]-<date>.json``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import save, table

from scanpipe.artifacts import read_provenance
from scanpipe.evaluate import SurfaceDistance, load_reference
from scanpipe.scanner_models import SCANNER_MODELS

#: Per device: simulate options (continuous mode) for the full and the quick run. Speed-ups
#: that a quiet machine keeps up with; a 40 Hz UST-10LX runs in real time.
DEVICES: dict[str, dict[str, Any]] = {
    "lms111": {"speedup": 2.0, "motor_step": 1.44, "quick_step": 3.0},
    "tim571": {"speedup": 2.0, "motor_step": 1.0, "quick_step": 3.0},
    "ust10lx": {"speedup": 1.0, "motor_step": 3.0, "quick_step": 6.0, "beam_step": 1.0},
    "urg04lx": {"speedup": 2.0, "motor_step": 1.0, "quick_step": 3.0},
    "ld06": {"speedup": 3.0, "motor_step": 1.0, "quick_step": 3.0},
    "stl27l": {"speedup": 3.0, "motor_step": 1.0, "quick_step": 3.0},
}
TARGET_SIGMA = 1.1


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _scanpipe(*args: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "scanpipe.cli.main", *args]
    return subprocess.run(command, capture_output=True, text=True, check=False)


def _timed(*args: str) -> tuple[subprocess.CompletedProcess[str], float, float]:
    wall, cpu = time.perf_counter(), _children_cpu_s()
    result = _scanpipe(*args)
    return result, time.perf_counter() - wall, _children_cpu_s() - cpu


def run_device(name: str, folder: Path, quick: bool, seed: int = 4) -> dict[str, Any]:
    """Simulate ``name`` live, run the chain, and measure (module docstring)."""
    spec = DEVICES[name]
    model = SCANNER_MODELS[name]
    rec, truth, work = folder / f"{name}.mcap", folder / f"{name}-truth", folder / f"{name}-work"
    args = ["simulate", "--scanner", name, "--out", str(rec), "--truth", str(truth),
            "--mode", "continuous", "--no-cameras", "--seed", str(seed),
            "--motor-step", str(spec["quick_step" if quick else "motor_step"]),
            "--speedup", str(spec["speedup"]), "--quiet"]
    if "beam_step" in spec:
        args += ["--beam-step", str(spec["beam_step"])]
    simulated, sim_wall, sim_cpu = _timed(*args)
    out: dict[str, Any] = {"device": name, "dialect": model.dialect,
                           "transport": model.transport, "speedup": spec["speedup"],
                           "noise_sigma_mm": model.noise_sigma_m * 1e3,
                           "simulate_wall_s": sim_wall, "simulate_cpu_s": sim_cpu}
    if simulated.returncode != 0:
        return {**out, "error": simulated.stderr.strip()[-500:]}
    ran, run_wall, run_cpu = _timed("run", str(rec), "--workdir", str(work), "--quiet")
    out.update(run_wall_s=run_wall, run_cpu_s=run_cpu)
    if ran.returncode != 0:
        return {**out, "error": ran.stderr.strip()[-500:]}
    points = pq.read_table(work / "assemble" / "points.parquet", columns=["x", "y", "z"])
    xyz = np.stack([points.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    distance = SurfaceDistance(load_reference(truth).mesh).distance_m(xyz)
    rms_m = float(np.sqrt(np.mean(np.square(distance))))
    assemble = read_provenance(work / "assemble" / "points.parquet")["report"]
    profiles = pq.read_table(work / "decode" / "profiles.parquet",
                             columns=["frame", "recv_time_ns"])
    turns = len(set(profiles.column("frame").to_pylist()))
    meta = json.loads((truth / "meta.json").read_text())
    sent = pq.read_table(truth / "truth.parquet", columns=["time_ns"]).column(
        "time_ns").to_numpy()
    recv = profiles.column("recv_time_ns").to_numpy()
    # Turns the emulator sent while the recorder was receiving (host clock).
    turn_host_ns = 1e9 / model.modes[0][0] / spec["speedup"]
    in_window = int(np.count_nonzero((sent >= recv.min() - turn_host_ns)
                                     & (sent <= recv.max())))
    head_turns = (recv.max() - recv.min()) / turn_host_ns + 1
    clock = assemble.get("clock") or {}
    motor = assemble.get("motor_clock") or {}
    return {**out, "points": int(xyz.shape[0]), "rms_mm": rms_m * 1e3,
            "rms_sigma": rms_m / model.noise_sigma_m,
            "within_target": rms_m <= TARGET_SIGMA * model.noise_sigma_m,
            "turns_decoded": turns, "turns_sent_while_recording": in_window,
            "coverage_of_sent": turns / max(in_window, 1),
            "coverage_of_head": turns / max(head_turns, 1.0),
            "scans_skipped": meta.get("scans_skipped"),
            "time_source": assemble.get("time_source"), "mode": assemble.get("mode"),
            "clock_rate": clock.get("rate"), "motor_clock_rate": motor.get("rate"),
            "clock_floor_drift_ms": clock.get("floor_drift_ms"),
            "true_rate": 1.0 / spec["speedup"], "warnings": assemble.get("warnings", [])}


def _busy() -> None:  # pragma: no cover - a load generator
    while True:
        pass


def run(quick: bool, devices: list[str], load: int) -> dict[str, Any]:
    """Every device in ``devices`` with ``load`` busy processes alongside."""
    import multiprocessing as mp

    hogs = [mp.Process(target=_busy, daemon=True) for _ in range(load)]
    for hog in hogs:
        hog.start()
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
            rows = [run_device(name, Path(tmp), quick) for name in devices]
    finally:
        for hog in hogs:
            hog.terminate()
            hog.join()
    return {"benchmark": "live_devices", "quick": quick, "load_processes": load,
            "target_rms_sigma": TARGET_SIGMA, "devices": rows,
            "all_within_target": all(r.get("within_target", False) for r in rows),
            "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
            "cpu_children_s": _children_cpu_s()}


def show(results: dict[str, Any]) -> None:
    """Print the table."""
    rows = []
    for r in results["devices"]:
        if "error" in r:
            rows.append((r["device"], "error", r["error"][:60], "", "", ""))
            continue
        rows.append((r["device"], f"{r['rms_mm']:.2f}", f"{r['rms_sigma']:.3f}",
                     f"{r['coverage_of_sent']:.0%} / {r['coverage_of_head']:.0%}",
                     f"{r['clock_rate']:.5f} ({r['true_rate']:.5f})",
                     f"{r['simulate_wall_s'] + r['run_wall_s']:.0f} / "
                     f"{r['simulate_cpu_s'] + r['run_cpu_s']:.0f}"))
    print(table(rows, ("device", "RMS mm", "RMS/σ", "coverage sent/head", "clock rate (true)",
                       "wall/cpu s")))
    print(f"load processes: {results['load_processes']}; all ≤ {TARGET_SIGMA} σ: "
          f"{results['all_within_target']}")


def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="coarser motor steps (fewer turns) for a smoke run")
    parser.add_argument("--load", type=int, default=0, help="busy-loop processes alongside")
    parser.add_argument("--devices", default=",".join(DEVICES),
                        help=f"comma-separated, from {', '.join(DEVICES)}")
    args = parser.parse_args(argv)
    devices = [d for d in args.devices.split(",") if d]
    unknown = [d for d in devices if d not in DEVICES]
    if unknown or args.load < 0:
        parser.error(f"--devices: unknown {unknown}; allowed {list(DEVICES)}" if unknown
                     else "--load: must be 0 or more")
    results = run(args.quick, devices, args.load)
    show(results)
    stem = "live_devices" + ("-quick" if args.quick else "") + (
        f"-load{args.load}" if args.load else "") + f"-{dt.date.today().isoformat()}"
    print(f"saved {save(results, stem)}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
