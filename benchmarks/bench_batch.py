"""``python -m benchmarks.bench_batch [--quick] [--recordings N] [--repeats N]``: ``scanpipe
batch`` over N (20) small recordings with 1 and 2 workers, in the local process pool and on a
local Ray, and the cost of Ray's scheduling per task; prints a table and writes
``benchmarks/results/batch-<date>[-quick].json``.

Target (issue 21): a batch of 20 small recordings, 2 workers at least 1.8× faster than 1 on a
2-core machine, on both engines. Each configuration runs ``--repeats`` times into fresh workdirs
(nothing cached) and its fastest wall time counts. Ray's cost per task is measured three ways:
the round trip of one empty task (submit, run, get; median of sequential ones), the wall time per
empty task when many are in flight, and the batch's own excess over the local pool per stage
task (Ray wall − local wall after the pool's start, 1 worker, divided by the number of stage
tasks). The fixed cost of starting a local pool (spawned workers importing the chain) is
measured apart (and the local speed-up without it shown beside the target's), and the load
average before each run is recorded: a speed-up measured while other work ran (load above
0.5 per CPU) is marked ``busy`` and is not the figure.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import datetime as dt
import multiprocessing as mp
import os
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
RECORDINGS = 20
#: Load average per CPU above which the machine counts as busy (the figure is not valid).
BUSY_LOAD_PER_CPU = 0.5


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


def _import_chain(_: int = 0) -> int:
    """What a spawned batch worker does before its first recording: import the chain."""
    from scanpipe.stages import chain_stages as stages

    return len(stages("recording"))


def pool_start_s(workers: int) -> float:
    """Wall time to spawn a local pool of ``workers`` and have each import the chain."""
    started = time.perf_counter()
    with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        list(pool.map(_import_chain, range(workers)))
    return round(time.perf_counter() - started, 3)


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def run(count: int, settings: list[str], say: Any, repeats: int = 1) -> dict[str, Any]:
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
        results["local_pool_start_s"] = {str(n): pool_start_s(n) for n in (1, 2)}
        started = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        results["ray_init_s"] = round(time.perf_counter() - started, 2)
        try:
            results["ray_task"] = ray_task_costs(ray)
            for attempt in range(repeats):
                for engine in ("local", "ray"):
                    for workers in (1, 2):
                        name = f"{engine}-{workers}"
                        say(f"{engine}, {workers} worker(s), run {attempt + 1} of {repeats}")
                        load = _load()
                        started = time.perf_counter()
                        summary = run_batch(recordings, root / f"{name}-{attempt}", params,
                                            engine=engine, workers=workers)
                        wall = time.perf_counter() - started
                        if summary["failed"]:
                            raise RuntimeError(f"{name}: {summary['failed']} failed")
                        entry = results["runs"].setdefault(name, {"walls_s": [],
                                                                  "load_before": []})
                        entry["walls_s"].append(round(wall, 3))
                        entry["load_before"].append(load)
                        entry["stage_s"] = round(sum(s["seconds"] for i in summary["items"]
                                                     for s in i["stages"]), 3)
        finally:
            ray.shutdown()
    runs = results["runs"]
    for entry in runs.values():
        entry["wall_s"] = min(entry["walls_s"])
    tasks = count * n_stages
    # the local pool's start (spawning and importing) is paid once per batch, Ray's workers
    # were started by ray.init: compare the work after the start
    start = results["local_pool_start_s"]
    results["ray_task"]["batch_excess_per_task_ms"] = round(
        (runs["ray-1"]["wall_s"] - (runs["local-1"]["wall_s"] - start["1"])) / tasks * 1e3, 3)
    results["speedup_local_after_pool_start"] = round(
        (runs["local-1"]["wall_s"] - start["1"]) / max(runs["local-2"]["wall_s"] - start["2"],
                                                       1e-9), 3)
    cpus = os.cpu_count() or 1
    results["busy"] = any(load > BUSY_LOAD_PER_CPU * cpus for entry in runs.values()
                          for load in entry["load_before"])
    results["targets"] = [
        {"figure": f"speedup_{engine}", "value": round(
            runs[f"{engine}-1"]["wall_s"] / runs[f"{engine}-2"]["wall_s"], 3),
         "target": f">= {SPEEDUP_TARGET}"} for engine in ("local", "ray")]
    for target in results["targets"]:
        target["ok"] = target["value"] >= SPEEDUP_TARGET
    return results


def report(results: dict[str, Any]) -> str:
    """The results as a text table."""
    rows = [(name, f"{r['wall_s']:.2f}", " ".join(f"{w:.1f}" for w in r["walls_s"]),
             f"{r['stage_s']:.2f}", " ".join(f"{v:.1f}" for v in r["load_before"]))
            for name, r in results["runs"].items()]
    lines = [table(rows, ("run", "wall s (min)", "every run", "stage s (sum)", "load before")),
             ""]
    if results["busy"]:
        lines.append("the machine was busy (load above "
                     f"{BUSY_LOAD_PER_CPU} per CPU before a run): these speed-ups are not the "
                     "figure; run again on a quiet machine")
    lines += [f"{t['figure']}: {t['value']:.2f} (target {t['target']}: "
              f"{'ok' if t['ok'] else 'MISSED'})" for t in results["targets"]]
    cost = results["ray_task"]
    lines.append(f"Ray per task: round trip {cost['round_trip_ms']:.2f} ms, in flight "
                 f"{cost['per_task_in_flight_ms']:.2f} ms, batch excess over local "
                 f"{cost['batch_excess_per_task_ms']:.2f} ms; Ray start {results['ray_init_s']} s")
    pool = results["local_pool_start_s"]
    lines.append(f"local pool start (spawn + import the chain): 1 worker {pool['1']:.2f} s, "
                 f"2 workers {pool['2']:.2f} s; local speed-up after it "
                 f"{results['speedup_local_after_pool_start']:.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns 1 when a target is missed."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_batch",
                                     description=__doc__)
    parser.add_argument("--quick", action="store_true",
                        help="tiny recordings without cameras (a smoke run, not the figure)")
    parser.add_argument("--recordings", type=int, default=RECORDINGS,
                        help=f"how many recordings (default {RECORDINGS}, the target's)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="runs per configuration, the fastest counts (default 1)")
    args = parser.parse_args(argv)
    if args.recordings < 1:
        parser.error(f"--recordings {args.recordings}: must be at least 1")
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: must be at least 1")
    started = time.perf_counter()

    def say(text: str) -> None:
        print(f"[{time.perf_counter() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    results = run(args.recordings, QUICK if args.quick else SMALL, say, args.repeats)
    results["quick"] = args.quick
    results["benchmark_s"] = round(time.perf_counter() - started, 1)
    stem = f"batch-{dt.date.today().isoformat()}" + ("-quick" if args.quick else "")
    saved = save(results, stem)
    print(report(results))
    print(f"\nsaved {saved}")
    return 0 if all(t["ok"] for t in results["targets"]) or results["busy"] else 1


if __name__ == "__main__":
    sys.exit(main())
