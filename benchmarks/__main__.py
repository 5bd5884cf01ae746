"""``python -m benchmarks [--quick] [--repeats N]``: every stage, the Open3D-only baseline and end
to end on the lab-scale scan (or a small one with ``--quick``); prints a table and writes
``benchmarks/results/<date>[-quick].json``. See docs/performance.md."""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time

from benchmarks.harness import positive_int, save, timed_say
from benchmarks.pipeline_bench import report, run
from benchmarks.scans import LAB, QUICK


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("--quick", action="store_true",
                        help="a small scan (1° × 1.08°, 2 s of video) for CI smoke runs")
    parser.add_argument("--repeats", type=positive_int, default=3,
                        help="runs per fast stage (median); slow ones run max(1, N // 3) times")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    say = timed_say(started)

    results = run(QUICK if args.quick else LAB, args.repeats, say=say)
    results["quick"] = args.quick
    results["benchmark_s"] = round(time.perf_counter() - started, 1)
    print(report(results))
    stem = dt.date.today().isoformat() + ("-quick" if args.quick else "")
    print(f"\nsaved {save(results, stem)} ({results['benchmark_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
