"""Benchmark: the model while recording — ``scanpipe run --follow`` on a live simulated scan.

``scanpipe simulate`` (without ``--direct``: the emulators on loopback and a pty, driven by
``record``'s recorder, writing the recording as it goes) and ``scanpipe run REC --follow --to
mesh`` run as two processes at the same time, as on a rig and a workstation. Measured, on the
host clock the recording's receive times use:

- **model latency**: from the last profile's receipt to the model written (``follow/model.ply``,
  the chain up to the mesh on the scan as recorded; target ≤ 5 s);
- when the follower read the recorder's ``scan_end`` event and the recording's end record;
- the final artifacts (written when the recording ends, equal to the batch run: checked here
  table by table, bit for bit) and which stages were taken from the scan's end;
- the live preview (positions, points, faces, its cost) and the batch ``run`` on the finished
  file for comparison.

``python benchmarks/bench_follow.py [--quick] [--speedup S]`` prints the figures and saves JSON
to ``benchmarks/results/follow[-quick]-<date>.json``. The default is the lab scan (0.25° ×
0.108°, 1667 positions × 1440 samples, the built-in room, half-size frames): run it on a quiet
machine; ``--quick`` is 1° × 1.08° with small frames (a few minutes on a loaded machine).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import pyarrow.parquet as pq
from harness import save, table

from scanpipe.follow import FOLLOW_FOLDER, MODEL_FILE, tables_identical

SCANPIPE = [sys.executable, "-m", "scanpipe.cli.main"]
#: ``simulate`` options of each scale: beam step, motor step, frames.
SCALES: dict[str, list[str]] = {
    "lab": ["--beam-step", "0.25", "--motor-step", "0.108", "--camera-scale", "0.5",
            "--camera-fps", "0.45"],
    "quick": ["--beam-step", "1", "--motor-step", "1.08", "--camera-scale", "0.125",
              "--camera-fps", "1"],
}


def _env() -> dict[str, str]:
    src = str(Path(__file__).resolve().parents[1] / "src")
    return {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _artifacts_equal(follow: Path, batch: Path) -> dict[str, bool]:
    """Every artifact of the batch workdir against the follower's, bit for bit."""
    found = {}
    for path in sorted(batch.glob("*/*.parquet")):
        rel = path.relative_to(batch)
        other = follow / rel
        found[str(rel)] = other.exists() and tables_identical(
            pq.read_table(other).replace_schema_metadata(None),
            pq.read_table(path).replace_schema_metadata(None))
    return found


def run(quick: bool, speedup: float) -> dict[str, Any]:
    """One live simulation followed by ``run --follow``; the batch run after it."""
    scale = "quick" if quick else "lab"
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        rec = root / "live.mcap"
        started = time.monotonic()
        simulate = subprocess.Popen(
            [*SCANPIPE, "simulate", "--out", str(rec), "--truth", str(root / "truth"),
             "--scene", "room", *SCALES[scale], "--speedup", str(speedup), "--quiet"],
            env=_env(), stderr=subprocess.PIPE, text=True)
        follow = subprocess.run(
            [*SCANPIPE, "run", str(rec), "--workdir", str(root / "follow"), "--to", "mesh",
             "--follow", "--follow-timeout", "120", "--json"],
            env=_env(), capture_output=True, text=True)
        simulate_code = simulate.wait()
        simulate_s = time.monotonic() - started
        if simulate_code or follow.returncode:
            raise SystemExit(f"simulate exit {simulate_code}: "
                             f"{simulate.stderr.read() if simulate.stderr else ''}\n"
                             f"follow exit {follow.returncode}: {follow.stderr}")
        report = json.loads(follow.stdout)
        batch_started = time.monotonic()
        batch = subprocess.run([*SCANPIPE, "run", str(rec), "--workdir", str(root / "batch"),
                                "--to", "mesh", "--json", "--quiet"],
                               env=_env(), capture_output=True, text=True, check=True)
        batch_s = time.monotonic() - batch_started
        equal = _artifacts_equal(root / "follow", root / "batch")
        model_bytes = (root / "follow" / FOLLOW_FOLDER / MODEL_FILE).stat().st_size
        recording_bytes = rec.stat().st_size
    info = report["follow"]
    last = info["last_profile_ns"]

    def after_last(name: str) -> float | None:
        return None if info[name] is None or last is None else (info[name] - last) / 1e9

    stages = {s["stage"]: s for s in report["stages"]}
    return {
        "scale": scale, "speedup": speedup, "simulate_s": simulate_s,
        "recording_bytes": recording_bytes, "model_ply_bytes": model_bytes,
        "points": stages["assemble"]["report"]["points"],
        "positions": stages["assemble"]["report"]["grid"]["profiles"],
        "positions_without_profile": stages["assemble"]["report"]["positions_without_profile"],
        "faces": stages["mesh"]["report"]["faces"],
        "model_latency_s": info["model_latency_s"], "target_s": 5.0,
        "meets_target": info["model_latency_s"] is not None and info["model_latency_s"] <= 5.0,
        "scan_end_seen_after_last_profile_s": after_last("scan_end_seen_ns"),
        "end_seen_after_last_profile_s": after_last("end_seen_ns"),
        "decode": info["decode"], "reused_from_scan_end": info["reused_from_scan_end"],
        "changed_after_scan_end": info["changed_after_scan_end"],
        "final_chain_s": sum(s["seconds"] for s in report["stages"]),
        "preview": info["preview"], "warnings": info["warnings"],
        "visible_lag_s": info["visible_lag_s"],
        "batch_run_s": batch_s, "batch_stage_s": {s["stage"]: s["seconds"]
                                                  for s in json.loads(batch.stdout)["stages"]},
        "artifacts_equal_to_batch": equal, "all_equal": all(equal.values()),
        "load_average": os.getloadavg(),
    }


def show(results: dict[str, Any]) -> None:
    """Print the figures."""
    def seconds(value: float | None) -> str:
        return "—" if value is None else f"{value:.2f} s"

    preview = results["preview"]
    rows = [
        ("model written after the last profile", seconds(results["model_latency_s"]),
         "met" if results["meets_target"] else "NOT met (target ≤ 5 s)"),
        ("scan_end event read after it", seconds(results["scan_end_seen_after_last_profile_s"]),
         ""),
        ("end record read after it", seconds(results["end_seen_after_last_profile_s"]), ""),
        ("new profiles read after their receipt (median, max over polls)",
         f"{seconds(results['visible_lag_s']['median'])}, "
         f"{seconds(results['visible_lag_s']['max'])}", "the writer's flushes + the polls"),
        ("final chain (artifacts) after the end", seconds(results["final_chain_s"]),
         f"decode {results['decode']}; from the scan's end: "
         f"{', '.join(results['reused_from_scan_end']) or 'nothing'}"),
        ("batch run on the finished file", seconds(results["batch_run_s"]), ""),
        ("live preview", seconds(preview.get("seconds")),
         f"{preview.get('updates')} updates, {preview.get('positions')} positions, "
         f"{preview.get('faces')} faces"),
    ]
    print(table(rows, ("measure", "value", "")))
    print(f"{results['scale']} scan at speed-up {results['speedup']:g}: {results['points']} "
          f"points, {results['faces']} faces; artifacts equal to the batch run: "
          f"{'all' if results['all_equal'] else results['artifacts_equal_to_batch']}; load "
          f"average {results['load_average'][0]:.1f}")


def main() -> None:
    """``[--quick] [--speedup S]``: run, show, save."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a 1° × 1.08° scan")
    parser.add_argument("--speedup", type=float, default=10.0,
                        help="the emulators' clock speed-up (simulate --speedup)")
    args = parser.parse_args()
    results = run(args.quick, args.speedup)
    show(results)
    stem = f"follow-{'quick-' if args.quick else ''}{dt.date.today().isoformat()}"
    print(f"saved {save(results, stem)}")


if __name__ == "__main__":
    main()
