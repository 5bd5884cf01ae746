"""``python -m benchmarks.bench_batch [--quick] [--recordings N]``: ``scanpipe batch`` over N
small recordings with 1 and 2 workers, in the local process pool and on a local Ray, and the cost
of Ray's scheduling per task; prints a table and writes
``benchmarks/results/batch-<date>[-quick].json``.

Target (issue 21): 2 workers at least 1.8× faster than 1 on a 2-core machine, on both engines.
Ray's cost per task is measured three ways: the round trip of one empty task (submit, run, get;
median of sequential ones), the wall time per empty task when many are in flight, and the batch's
own excess over the local pool per stage task (Ray wall − local wall, 1 worker, divided by the
number of stage tasks).
"""

from __future__ import annotations

import argparse
import datetime as dt
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.harness import machine, save, table
from scanpipe.batch import run_batch
from scanpipe.cli.main import main as scanpipe_main
from scanpipe.cli.pipeline import pipeline_params_from_cli
from scanpipe.stages import chain_stages

#: `scanpipe simulate --direct` settings of one small recording (lab figure) and of --quick.
SMALL = ["--beam-step", "2", "--motor-step", "3", "--camera-scale", "0.0625",
         "--camera-fps", "0.2"]
QUICK = ["--beam-step", "4", "--motor-step", "6", "--no-cameras"]
SPEEDUP_TARGET = 1.8
EMPTY_TASKS = 200


def make_recordings(folder: Path, count: int, settings: list[str]) -> list[Path]:
    """``count`` recordings made with ``scanpipe simulate --direct`` (seeds 0…count-1)."""
    paths = []
    for seed in range(count):
        path = folder / f"pos{seed:03d}" / "scan.mcap"  # equal file names, as on a site
        code = scanpipe_main(["simulate", "--direct", "--out", str(path), "--truth",
                              str(path.parent / "truth"), "--seed", str(seed), "-q", *settings])
        if code != 0:
            raise RuntimeError(f"scanpipe simulate failed with exit code {code}")
        paths.append(path)
    return paths


def ray_task_costs(ray: Any) -> dict[str, float]:
    """Round trip of one empty task, and wall time per empty task with many in flight (ms)."""
    @ray.remote(num_cpus=1)
    def empty(x: int) -> int:
        return x

    ray.get([empty.remote(i) for i in range(20)])  # workers started and warm
    trips = []
    for i in range(50):
        started = time.perf_counter()
        ray.get(empty.remote(i))
        trips.append(time.perf_counter() - started)
    started = time.perf_counter()
    ray.get([empty.remote(i) for i in range(EMPTY_TASKS)])
    in_flight_s = time.perf_counter() - started
    return {"round_trip_ms": round(statistics.median(trips) * 1e3, 3),
            "per_task_in_flight_ms": round(in_flight_s / EMPTY_TASKS * 1e3, 3)}


def run(count: int, settings: list[str], say: Any) -> dict[str, Any]:
    """Every measurement; returns the results (JSON-ready)."""
    import ray

    params = pipeline_params_from_cli(None, [])
    n_stages = len(chain_stages("recording"))
    results: dict[str, Any] = {"machine": machine(), "recordings": count,
                               "simulate_settings": settings, "stages": n_stages, "runs": {}}
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as scratch:
        root = Path(scratch)
        say(f"simulating {count} recordings")
        recordings = make_recordings(root / "recs", count, settings)
        started = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        results["ray_init_s"] = round(time.perf_counter() - started, 2)
        try:
            results["ray_task"] = ray_task_costs(ray)
            for engine in ("local", "ray"):
                for workers in (1, 2):
                    say(f"{engine}, {workers} worker(s)")
                    started = time.perf_counter()
                    summary = run_batch(recordings, root / f"{engine}-{workers}", params,
                                        engine=engine, workers=workers)
                    wall = time.perf_counter() - started
                    if summary["failed"]:
                        raise RuntimeError(f"{engine}/{workers}: {summary['failed']} failed")
                    results["runs"][f"{engine}-{workers}"] = {
                        "wall_s": round(wall, 3),
                        "stage_s": round(sum(s["seconds"] for i in summary["items"]
                                             for s in i["stages"]), 3)}
        finally:
            ray.shutdown()
    runs = results["runs"]
    tasks = count * n_stages
    results["ray_task"]["batch_excess_per_task_ms"] = round(
        (runs["ray-1"]["wall_s"] - runs["local-1"]["wall_s"]) / tasks * 1e3, 3)
    results["targets"] = [
        {"figure": f"speedup_{engine}", "value": round(
            runs[f"{engine}-1"]["wall_s"] / runs[f"{engine}-2"]["wall_s"], 3),
         "target": f">= {SPEEDUP_TARGET}"} for engine in ("local", "ray")]
    for target in results["targets"]:
        target["ok"] = target["value"] >= SPEEDUP_TARGET
    return results


def report(results: dict[str, Any]) -> str:
    """The results as a text table."""
    rows = [(name, f"{r['wall_s']:.2f}", f"{r['stage_s']:.2f}")
            for name, r in results["runs"].items()]
    lines = [table(rows, ("run", "wall s", "stage s (sum)")), ""]
    lines += [f"{t['figure']}: {t['value']:.2f} (target {t['target']}: "
              f"{'ok' if t['ok'] else 'MISSED'})" for t in results["targets"]]
    cost = results["ray_task"]
    lines.append(f"Ray per task: round trip {cost['round_trip_ms']:.2f} ms, in flight "
                 f"{cost['per_task_in_flight_ms']:.2f} ms, batch excess over local "
                 f"{cost['batch_excess_per_task_ms']:.2f} ms; Ray start {results['ray_init_s']} s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns 1 when a target is missed."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_batch",
                                     description=__doc__)
    parser.add_argument("--quick", action="store_true",
                        help="tiny recordings without cameras (a smoke run, not the figure)")
    parser.add_argument("--recordings", type=int, default=None,
                        help="how many recordings (default 20; 4 with --quick)")
    args = parser.parse_args(argv)
    if args.recordings is None:
        args.recordings = 4 if args.quick else 20
    if args.recordings < 1:
        parser.error(f"--recordings {args.recordings}: must be at least 1")
    started = time.perf_counter()

    def say(text: str) -> None:
        print(f"[{time.perf_counter() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    results = run(args.recordings, QUICK if args.quick else SMALL, say)
    results["quick"] = args.quick
    results["benchmark_s"] = round(time.perf_counter() - started, 1)
    stem = f"batch-{dt.date.today().isoformat()}" + ("-quick" if args.quick else "")
    saved = save(results, stem)
    print(report(results))
    print(f"\nsaved {saved}")
    return 0 if all(t["ok"] for t in results["targets"]) else 1


if __name__ == "__main__":
    sys.exit(main())
