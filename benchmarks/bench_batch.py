"""``python -m benchmarks.bench_batch [--quick] [--recordings N] [--repeats N] [--threads N]``:
``scanpipe batch`` over N (20) small recordings with 1 and 2 workers, in the local process pool
and on a local Ray, with the CPU time of every worker, of the parent and (Ray) of Ray's own
processes, and the cost of scheduling per task on both engines; prints a table and writes
``benchmarks/results/batch-<date>[-quick].json``.

Target (issue 21): a batch of 20 small recordings, 2 workers at least 1.8× faster than 1 on a
2-core machine, on both engines. Every run pins each worker to ``--threads`` (1) threads —
OpenMP, BLAS, OpenCV, and on Ray the task's CPUs — so that the 1-worker run does not get both
cores' threads while each of 2 workers gets one (that compared 2 processes with 1 process of 2
threads). Each configuration runs ``--repeats`` times into fresh workdirs (nothing cached) and
its fastest wall time counts: the first run is *cold* (the local pool's fork server stopped
before it, so it starts — interpreter and imports — inside the run, as in a new ``scanpipe
batch`` process; on Ray, the first run's workers import the chain in their first tasks), later
ones *warm* (the server kept running, Ray's workers reused — as Ray is always measured,
``ray.init`` being outside the runs); the cold speed-ups are reported too. The load average
before each run is recorded, and a speed-up measured while other work ran (load above 0.5 per
CPU) is marked ``busy`` and is not the figure.

Because wall times mean nothing on a loaded machine, every run also gives CPU figures, which do
not depend on the load: each worker's CPU (its start — interpreter, imports — and its stage
steps), the parent's, and every process's (local: the fork server with its reaped workers; Ray:
the driver's descendants — raylet, GCS, workers). From them a *CPU bound* on the speed-up: each
run's wall cannot be shorter than its busiest worker's CPU, nor than all its CPU spread over the
cores it may use, so ``cpu_speedup = bound(1 worker) / bound(2 workers)`` is what a quiet
machine gives at best. On a loaded machine which worker takes the next recording depends on the
load, so ``cpu_speedup_even`` bounds it with the recordings split evenly (the largest
recording's CPU instead of the busiest worker's). Worker start: the local pool's, cold and warm
(wall until every worker answered, and its CPU). Scheduling per task: the round trip of an empty
task (local pool and Ray, median of sequential ones), Ray's wall per empty task with many in
flight, the parent's CPU per task, and (Ray) the CPU of Ray's own processes per stage task.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import datetime as dt
import os
import pickle
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.bench_site import pool_server_cpu_s
from benchmarks.harness import machine, positive_int, save, table, timed_say
from scanpipe.batch import run_batch, start_local_ray, stop_pool_server, stop_ray_workers
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


class _Empty:
    """An actor with an empty method, as a batch's Ray worker receives stage tasks."""

    def call(self, x: int) -> int:
        """Nothing."""
        return x


def ray_task_costs(ray: Any) -> dict[str, float]:
    """Ray's scheduling per task (ms): the round trip of one empty task and the wall time per
    empty task with many in flight, for plain tasks (scheduled by the raylet, each on a leased
    worker) and for actor tasks (sent straight to a running worker, as a batch's stage tasks
    are)."""
    @ray.remote(num_cpus=1)
    def empty(x: int) -> int:
        return x

    actor = ray.remote(num_cpus=1)(_Empty).remote()
    costs: dict[str, float] = {}
    for label, call in (("", empty.remote), ("actor_", actor.call.remote)):
        ray.get([call(i) for i in range(20)])  # workers started and warm
        trips = []
        for i in range(50):
            started = time.perf_counter()
            ray.get(call(i))
            trips.append(time.perf_counter() - started)
        started = time.perf_counter()
        ray.get([call(i) for i in range(EMPTY_TASKS)])
        in_flight_s = time.perf_counter() - started
        costs[f"{label}round_trip_ms"] = round(statistics.median(trips) * 1e3, 3)
        costs[f"{label}per_task_in_flight_ms"] = round(in_flight_s / EMPTY_TASKS * 1e3, 3)
    ray.kill(actor)
    return costs


def _nothing(x: int = 0) -> int:
    """An empty task."""
    return x


def pool_costs(workers: int, threads: int) -> dict[str, float]:
    """A local pool as ``run_batch`` starts it: *cold* (the fork server stopped first, so its
    start — interpreter and the chain's imports — counts, as in a new ``scanpipe batch``
    process) and *warm* (the server running, as for a second batch in one process): wall time
    until every worker answered and the CPU of that start; then the round trip of one empty
    task on the warm pool (ms, median of sequential ones)."""
    from scanpipe.batch import _start_worker, _thread_env, pool_context, stop_pool_server

    result: dict[str, float] = {}
    with _thread_env(threads):
        for label in ("cold", "warm"):
            if label == "cold":
                stop_pool_server()
            cpu_before = pool_server_cpu_s() + _children_cpu_s()
            started = time.perf_counter()
            pool = cf.ProcessPoolExecutor(workers, mp_context=pool_context(threads),
                                          initializer=_start_worker, initargs=(threads,))
            with pool:
                list(pool.map(_nothing, range(workers)))
                result[f"{label}_start_s"] = round(time.perf_counter() - started, 3)
                if label == "warm":
                    trips = []
                    for i in range(50):
                        begun = time.perf_counter()
                        pool.submit(_nothing, i).result()
                        trips.append(time.perf_counter() - begun)
                    result["round_trip_ms"] = round(statistics.median(trips) * 1e3, 3)
            result[f"{label}_start_cpu_s"] = round(
                pool_server_cpu_s() + _children_cpu_s() - cpu_before, 3)
    return result


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _children_cpu_s() -> float:
    """CPU seconds of this process's reaped children (the local pool's workers)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _descendants_cpu() -> dict[int, float]:
    """CPU seconds of every live descendant process (Ray's), by pid."""
    import psutil

    spent: dict[int, float] = {}
    for child in psutil.Process().children(recursive=True):
        try:
            times = child.cpu_times()
        except psutil.Error:  # gone meanwhile
            continue
        spent[child.pid] = times.user + times.system
    return spent


def cpu_figures(summary: dict[str, Any], processes_cpu_s: float, cores: int) -> dict[str, Any]:
    """A run's CPU figures and its CPU bound on wall time (see the module docstring)."""
    stage_cpu = sum(s["cpu_s"] for i in summary["items"] for s in i["stages"])
    starts = {pid: cpu for i in summary["items"]
              for pid, cpu in i["worker_start_cpu_s"].items()}
    per_worker = summary["workers_cpu_s"]
    busiest = max(per_worker.values(), default=0.0)
    total = processes_cpu_s + summary["parent_cpu_s"]
    largest_item = max((i["cpu_s"] for i in summary["items"]), default=0.0)
    by_stage: dict[str, float] = {}
    blocked: dict[str, float] = {}
    for item in summary["items"]:
        for s in item["stages"]:
            by_stage[s["stage"]] = by_stage.get(s["stage"], 0.0) + s["cpu_s"]
            blocked[str(s["pid"])] = blocked.get(str(s["pid"]), 0.0) + (s["blocked_s"] or 0.0)
    # a worker is busy for its CPU plus the time its main thread slept on its own waits
    # (flushes, helper threads): at one thread per worker they cannot overlap
    busiest_with_waits = max((cpu + blocked.get(pid, 0.0) for pid, cpu in per_worker.items()),
                             default=0.0)
    return {"workers_cpu_s": per_worker, "busiest_worker_cpu_s": round(busiest, 3),
            "stage_cpu_by_stage_s": {k: round(v, 3) for k, v in by_stage.items()},
            "workers_blocked_s": {k: round(v, 3) for k, v in sorted(blocked.items())},
            "blocked_s": round(sum(blocked.values()), 3),
            "worker_start_cpu_s": round(sum(starts.values()), 3),
            "stage_cpu_s": round(stage_cpu, 3), "parent_cpu_s": summary["parent_cpu_s"],
            "processes_cpu_s": round(processes_cpu_s, 3),
            # what neither the stages nor the workers' start account for: the engine's own
            # work (Ray: raylet, GCS, object store, task (de)serialisation; local: the fork server)
            "engine_cpu_s": round(total - stage_cpu - sum(starts.values()), 3),
            "cpu_bound_s": round(max(busiest, total / cores), 3),
            "cpu_waits_bound_s": round(max(busiest_with_waits, total / cores), 3),
            # the same with the work split evenly between the workers: which worker takes
            # the next recording depends on the load on a shared machine, not on a quiet one
            "cpu_bound_even_s": round(max(largest_item, total / cores), 3)}


def run(count: int, settings: list[str], say: Any, repeats: int = 1,
        threads: int = 1) -> dict[str, Any]:
    """Every measurement; returns the results (JSON-ready)."""
    import ray

    params = pipeline_params_from_cli(None, [])
    n_stages = len(chain_stages("recording"))
    cpus = os.cpu_count() or 1
    results: dict[str, Any] = {"machine": machine(), "recordings": count,
                               "simulate_settings": settings, "stages": n_stages,
                               "threads_per_worker": threads, "runs": {}}
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as scratch:
        root = Path(scratch)
        say(f"simulating {count} recordings")
        recordings = make_recordings(root / "recs", count, settings)
        results["params_pickle_bytes"] = len(pickle.dumps(params))
        results["local_pool"] = {str(n): pool_costs(n, threads) for n in (1, 2)}
        # the local runs first, with no Ray running: an idle local Ray takes ~3 % of a core
        # (raylet, GCS, agents, idle workers: measured), which a 2-worker run on 2 cores pays
        # and a 1-worker run does not; then Ray's runs
        for engine in ("local", "ray"):
            if engine == "ray":
                started = time.perf_counter()
                start_local_ray(2)  # as `scanpipe batch --engine ray` starts one
                results["ray_init_s"] = round(time.perf_counter() - started, 2)
                results["ray_task"] = ray_task_costs(ray)
            try:
                _engine_runs(engine, recordings, root, params, repeats, threads, say, results)
            finally:
                if engine == "ray":
                    stop_ray_workers()
                    ray.shutdown()
    return summarise(results, count, n_stages, cpus)


def _engine_runs(engine: str, recordings: list[Path], root: Path, params: Any, repeats: int,
                 threads: int, say: Any, results: dict[str, Any]) -> None:
    """Every run of one engine: ``repeats`` times 1 and 2 workers (alternating), each into a
    fresh workdir; the first of each configuration cold (nothing started yet)."""
    cpus = os.cpu_count() or 1
    for attempt in range(repeats):
        for workers in (1, 2):
            name = f"{engine}-{workers}"
            say(f"{engine}, {workers} worker(s), run {attempt + 1} of {repeats}")
            load = _load()
            cold = attempt == 0
            if engine == "local" and cold:
                stop_pool_server()
            if engine == "ray" and cold:
                stop_ray_workers()
            before_local = _children_cpu_s() + pool_server_cpu_s()
            before_ray = _descendants_cpu() if engine == "ray" else {}
            started = time.perf_counter()
            # Ray's workers kept between runs, as the local fork server is
            summary = run_batch(recordings, root / f"{name}-{attempt}", params, engine=engine,
                                workers=workers, threads=threads, keep_workers=True)
            wall = time.perf_counter() - started
            if engine == "local":
                processes = _children_cpu_s() + pool_server_cpu_s() - before_local
            else:
                after = _descendants_cpu()
                processes = sum(cpu - before_ray.get(pid, 0.0) for pid, cpu in after.items())
            if summary["failed"]:
                raise RuntimeError(f"{name}: {summary['failed']} failed")
            entry = results["runs"].setdefault(name, {"walls_s": [], "load_before": [],
                                                      "cpu": []})
            if cold:
                entry["cold_wall_s"] = round(wall, 3)
            entry["walls_s"].append(round(wall, 3))
            entry["load_before"].append(load)
            entry["cpu"].append(cpu_figures(summary, processes, min(workers, cpus)))
            entry["stage_s"] = round(sum(s["seconds"] for i in summary["items"]
                                         for s in i["stages"]), 3)


def summarise(results: dict[str, Any], count: int, n_stages: int, cpus: int) -> dict[str, Any]:
    """The figures from the runs: fastest walls, bounds, speed-ups, costs per task, targets."""
    runs = results["runs"]
    for entry in runs.values():
        entry["wall_s"] = min(entry["walls_s"])
        entry["cpu_bound_s"] = min(c["cpu_bound_s"] for c in entry["cpu"])
        entry["cpu_bound_even_s"] = min(c["cpu_bound_even_s"] for c in entry["cpu"])
        entry["cpu_waits_bound_s"] = min(c["cpu_waits_bound_s"] for c in entry["cpu"])
    tasks = {"local": count, "ray": count * n_stages}
    for engine in ("local", "ray"):
        cost = results.setdefault(f"{engine}_scheduling", {})
        if engine == "local":
            cost["round_trip_ms"] = results["local_pool"]["1"]["round_trip_ms"]
        else:
            cost.update(results["ray_task"])
        for workers in (1, 2):
            cpu = runs[f"{engine}-{workers}"]["cpu"][-1]
            cost[f"parent_cpu_per_task_ms_{workers}w"] = round(
                cpu["parent_cpu_s"] / tasks[engine] * 1e3, 3)
            cost[f"engine_cpu_per_task_ms_{workers}w"] = round(
                cpu["engine_cpu_s"] / tasks[engine] * 1e3, 3)
        cost["tasks"] = tasks[engine]
    # the fastest runs: with --repeats 2 or more, both engines warm (the local fork server
    # running, Ray's workers started and holding the chain's imports), so the difference is
    # Ray's own cost per stage task
    results["ray_scheduling"]["batch_excess_per_task_ms"] = round(
        (runs["ray-1"]["wall_s"] - runs["local-1"]["wall_s"]) / tasks["ray"] * 1e3, 3)
    # the first run of each configuration: nothing started (the fork server stopped, Ray's
    # workers without the chain's imports) — what one new `scanpipe batch` process sees
    results["speedup_cold"] = {engine: round(
        runs[f"{engine}-1"]["cold_wall_s"] / max(runs[f"{engine}-2"]["cold_wall_s"], 1e-9), 3)
        for engine in ("local", "ray")}
    results["busy"] = any(load > BUSY_LOAD_PER_CPU * cpus for entry in runs.values()
                          for load in entry["load_before"])
    results["cpu_speedup"] = {engine: round(runs[f"{engine}-1"]["cpu_bound_s"]
                                            / max(runs[f"{engine}-2"]["cpu_bound_s"], 1e-9), 3)
                              for engine in ("local", "ray")}
    results["cpu_speedup_even"] = {
        engine: round(runs[f"{engine}-1"]["cpu_bound_even_s"]
                      / max(runs[f"{engine}-2"]["cpu_bound_even_s"], 1e-9), 3)
        for engine in ("local", "ray")}
    # the same bound with each worker's own waits (flushes, helper threads) added: what a
    # quiet machine gives at best with the waits this code still has
    results["cpu_waits_speedup"] = {
        engine: round(runs[f"{engine}-1"]["cpu_waits_bound_s"]
                      / max(runs[f"{engine}-2"]["cpu_waits_bound_s"], 1e-9), 3)
        for engine in ("local", "ray")}
    results["targets"] = [
        {"figure": f"speedup_{engine}", "value": round(
            runs[f"{engine}-1"]["wall_s"] / runs[f"{engine}-2"]["wall_s"], 3),
         "target": f">= {SPEEDUP_TARGET}"} for engine in ("local", "ray")]
    for target in results["targets"]:
        target["ok"] = target["value"] >= SPEEDUP_TARGET
    return results


def report(results: dict[str, Any]) -> str:
    """The results as text tables."""
    rows = [(name, f"{r['wall_s']:.2f}", " ".join(f"{w:.1f}" for w in r["walls_s"]),
             f"{r['stage_s']:.2f}", " ".join(f"{v:.1f}" for v in r["load_before"]))
            for name, r in results["runs"].items()]
    lines = [f"threads per worker: {results['threads_per_worker']} (every run)",
             table(rows, ("run", "wall s (min)", "every run", "stage s (sum)", "load before")),
             ""]
    cpu_rows = []
    for name, r in results["runs"].items():
        c = r["cpu"][-1]
        cpu_rows.append((name, " ".join(f"{v:.2f}" for v in c["workers_cpu_s"].values()),
                         f"{c['worker_start_cpu_s']:.2f}", f"{c['stage_cpu_s']:.2f}",
                         f"{c['parent_cpu_s']:.2f}", f"{c['processes_cpu_s']:.2f}",
                         f"{c['engine_cpu_s']:.2f}", f"{c['cpu_bound_s']:.2f}",
                         " ".join(f"{v:.2f}" for v in c["workers_blocked_s"].values()),
                         f"{c['cpu_waits_bound_s']:.2f}"))
    lines += [table(cpu_rows, ("run", "CPU s per worker", "worker starts", "stages",
                               "parent", "all processes", "engine", "CPU bound s",
                               "own waits s per worker", "with waits s")), ""]
    stage_rows = [(name, *(f"{v:.2f}" for v in r["cpu"][-1]["stage_cpu_by_stage_s"].values()))
                  for name, r in results["runs"].items()]
    stages = list(next(iter(results["runs"].values()))["cpu"][-1]["stage_cpu_by_stage_s"])
    lines += ["stage CPU s (all recordings; the same work with 1 and 2 workers):",
              table(stage_rows, ("run", *stages)), ""]
    if results["busy"]:
        lines.append("the machine was busy (load above "
                     f"{BUSY_LOAD_PER_CPU} per CPU before a run): these speed-ups are not the "
                     "figure; run again on a quiet machine")
    lines += [f"{t['figure']}: {t['value']:.2f} (target {t['target']}: "
              f"{'ok' if t['ok'] else 'MISSED'})" for t in results["targets"]]
    lines.append("CPU bound on the speed-up (what a quiet machine gives at best): "
                 + ", ".join(f"{k} {v:.2f}" for k, v in results["cpu_speedup"].items())
                 + "; with the recordings split evenly between the workers: "
                 + ", ".join(f"{k} {v:.2f}" for k, v in results["cpu_speedup_even"].items())
                 + "; with each worker's own waits: "
                 + ", ".join(f"{k} {v:.2f}" for k, v in results["cpu_waits_speedup"].items()))
    for engine in ("local", "ray"):
        cost = results[f"{engine}_scheduling"]
        lines.append(f"{engine} per task ({cost['tasks']} tasks): round trip "
                     f"{cost['round_trip_ms']:.2f} ms, parent CPU "
                     f"{cost['parent_cpu_per_task_ms_1w']:.2f} / "
                     f"{cost['parent_cpu_per_task_ms_2w']:.2f} ms, engine CPU "
                     f"{cost['engine_cpu_per_task_ms_1w']:.2f} / "
                     f"{cost['engine_cpu_per_task_ms_2w']:.2f} ms (1 / 2 workers)")
    ray_cost = results["ray_scheduling"]
    lines.append(f"Ray: {ray_cost['per_task_in_flight_ms']:.2f} ms per empty task in flight "
                 f"(actor tasks, as the batch's stage tasks: round trip "
                 f"{ray_cost['actor_round_trip_ms']:.2f} ms, "
                 f"{ray_cost['actor_per_task_in_flight_ms']:.2f} ms in flight), "
                 f"batch excess over local {ray_cost['batch_excess_per_task_ms']:.2f} ms per "
                 f"stage task; Ray start {results['ray_init_s']} s")
    pool = results["local_pool"]
    for n in ("1", "2"):
        lines.append(f"local pool of {n} worker(s), until every worker answered: cold (fork "
                     f"server started: interpreter + imports) {pool[n]['cold_start_s']:.2f} s "
                     f"/ {pool[n]['cold_start_cpu_s']:.2f} s CPU, warm (forked) "
                     f"{pool[n]['warm_start_s']:.3f} s / {pool[n]['warm_start_cpu_s']:.3f} s CPU")
    lines.append("cold speed-up (the first run: a new process's figure): "
                 + ", ".join(f"{k} {v:.2f}" for k, v in results["speedup_cold"].items())
                 + f"; parameters pickled per task: {results['params_pickle_bytes']} bytes")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns 1 when a target is missed."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_batch",
                                     description=__doc__)
    parser.add_argument("--quick", action="store_true",
                        help="tiny recordings without cameras (a smoke run, not the figure)")
    parser.add_argument("--recordings", type=positive_int, default=RECORDINGS,
                        help=f"how many recordings (default {RECORDINGS}, the target's)")
    parser.add_argument("--repeats", type=positive_int, default=1,
                        help="runs per configuration, the fastest counts (default 1)")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="threads per worker in every run (default 1: equal pinning)")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    say = timed_say(started)

    results = run(args.recordings, QUICK if args.quick else SMALL, say, args.repeats,
                  args.threads)
    results["quick"] = args.quick
    results["benchmark_s"] = round(time.perf_counter() - started, 1)
    stem = f"batch-{dt.date.today().isoformat()}" + ("-quick" if args.quick else "")
    saved = save(results, stem)
    print(report(results))
    print(f"\nsaved {saved}")
    return 0 if all(t["ok"] for t in results["targets"]) or results["busy"] else 1


if __name__ == "__main__":
    sys.exit(main())
