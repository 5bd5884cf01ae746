"""Measuring the same way every time: median wall time over repeats, peak memory, JSON results.

Peak memory is measured in a forked child per measurement, as the growth of its peak resident set
over what it inherited, so that one stage's allocations do not hide another's.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import multiprocessing as mp
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

RESULTS_DIR = Path(__file__).parent / "results"


@dataclass(frozen=True)
class Measurement:
    """One timed piece of work."""

    name: str
    median_s: float
    runs_s: list[float]
    peak_rss_mb: float
    items: float
    unit: str
    #: Process CPU seconds of each run (all threads of the process doing the work): on a
    #: shared machine wall time counts other processes' turns, CPU time does not.
    cpu_runs_s: list[float] = field(default_factory=list)

    @property
    def cpu_median_s(self) -> float:
        """Median CPU seconds of the runs (NaN when not measured)."""
        return statistics.median(self.cpu_runs_s) if self.cpu_runs_s else float("nan")

    @property
    def throughput(self) -> float:
        """Items per second at the median time."""
        return self.items / self.median_s if self.median_s > 0 else float("inf")


def _rss_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def _timed_runs(fn: Callable[[], Any], repeats: int) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds of ``repeats`` calls of ``fn``."""
    runs, cpu_runs = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        runs.append(time.perf_counter() - t0)
        cpu_runs.append(time.process_time() - c0)
    return runs, cpu_runs


def _child(fn: Callable[[], Any], repeats: int, queue: Any) -> None:
    try:
        start_rss = _rss_mb()
        runs, cpu_runs = _timed_runs(fn, repeats)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        queue.put(("ok", (runs, cpu_runs), max(0.0, peak - start_rss)))
    except BaseException as err:  # report any failure to the parent, which re-raises
        queue.put(("error", repr(err), 0.0))


def measure(name: str, fn: Callable[[], Any], items: float, unit: str,
            repeats: int = 3, isolate: bool = True) -> Measurement:
    """Run ``fn`` ``repeats`` times (in a forked child when ``isolate``) and summarise."""
    if isolate:
        ctx = mp.get_context("fork")
        queue = ctx.Queue()
        proc = ctx.Process(target=_child, args=(fn, repeats, queue))
        proc.start()
        status, runs, peak = queue.get()
        proc.join()
        if status != "ok":
            raise RuntimeError(f"benchmark {name!r} failed: {runs}")
        runs, cpu_runs = runs
    else:
        runs, cpu_runs = _timed_runs(fn, repeats)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return Measurement(name, statistics.median(runs), runs, peak, items, unit, cpu_runs)


def cpu_seconds(work: Callable[[], object], repeats: int = 3, warm_up: bool = True) -> float:
    """Median process CPU time (all threads) of ``work``, after one untimed run if ``warm_up``.

    Beside wall time on a shared machine: CPU time does not count other processes' turns.
    """
    if warm_up:
        work()
    runs = []
    for _ in range(repeats):
        start = time.process_time()
        work()
        runs.append(time.process_time() - start)
    return statistics.median(runs)



def timed_say(started: float) -> Callable[[str], None]:
    """A progress printer for a benchmark: each line on stderr with the seconds since ``started``
    (a ``time.perf_counter()`` reading)."""

    def say(text: str) -> None:
        print(f"[{time.perf_counter() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    return say


def positive_int(text: str) -> int:
    """An argparse ``type`` for counts (repeats, seeds, jobs…): an integer of at least 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: must be at least 1")
    return value


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    return {
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
    }


def save(results: dict[str, Any], stem: str | None = None,
         results_dir: Path | None = None) -> Path:
    """Write results to ``<results_dir or benchmarks/results>/<stem or date>.json``; returns the
    path."""
    folder = results_dir or RESULTS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    stem = stem or dt.date.today().isoformat()
    path = folder / f"{stem}.json"
    payload = {"date": dt.datetime.now(dt.UTC).isoformat(), "machine": machine(), **results}
    path.write_text(json.dumps(payload, indent=2, default=_jsonable))
    return path


def _jsonable(value: Any) -> Any:
    if isinstance(value, Measurement):
        return {**asdict(value), "throughput": value.throughput,
                "cpu_median_s": value.cpu_median_s}
    return str(value)


def table(rows: list[tuple[str, ...]], header: tuple[str, ...]) -> str:
    """A plain aligned text table."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join(f"{{:<{w}}}" for w in widths)
    out = [line.format(*header), line.format(*("-" * w for w in widths))]
    out += [line.format(*map(str, r)) for r in rows]
    return "\n".join(out)


def measurement_table(measurements: list[Measurement]) -> str:
    """The measurements as a table: median time, throughput and peak memory of each."""
    rows = [(m.name, f"{m.median_s * 1000:.1f} ms", f"{m.throughput / 1e6:.1f} M {m.unit}/s",
             f"{m.peak_rss_mb:.0f} MB") for m in measurements]
    return table(rows, ("measurement", "median", "throughput", "peak RSS"))


def throughput_line(label: str, wall_per_s: float, cpu_per_s: float, target_per_s: float,
                    load_average: float, unit: str = "samples") -> str:
    """One line: wall and CPU throughput against the target, and the load it was measured
    under (wall time means little on a busy machine; CPU time counts this process only)."""
    met = "met" if wall_per_s >= target_per_s else "NOT met"
    return (f"{label}: {wall_per_s / 1e6:.1f} M {unit}/s wall, {cpu_per_s / 1e6:.1f} M per CPU "
            f"second (target {target_per_s / 1e6:.0f} M wall: {met}; load average "
            f"{load_average:.1f})")


def cli(name: str, run: Callable[[bool], Any], description: str, quick_help: str,
        show: Callable[[Any], None] | None = None) -> None:
    """The command line of a ``bench_<name>.py``: ``[--quick]``, run, show, save as
    ``results/<name>[-quick]-<date>.json``."""
    import argparse

    parser = argparse.ArgumentParser(description=description.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    args = parser.parse_args()
    results = run(args.quick)
    if show is not None:
        show(results)
    stem = f"{name}-{'quick-' if args.quick else ''}{dt.date.today().isoformat()}"
    print(f"saved {save(results, stem)}")
