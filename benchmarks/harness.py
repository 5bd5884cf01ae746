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

import numpy as np

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


def made(files: Any) -> int:
    """Make every file of an export (``{name: FileData}``, or one file) as writing would,
    without writing: a streamed file (:class:`scanpipe.artifacts.Stream`) is formatted only
    when consumed, so timing the exporter call alone would time nothing. The total bytes."""
    from scanpipe.artifacts import file_pieces

    contents = files.values() if isinstance(files, dict) else [files]
    return sum(memoryview(piece).nbytes for data in contents for piece in file_pieces(data))


def damage_stream(stream: bytes, rng: Any, events: int, max_cut: int = 2000,
                  max_insert: int = 100, false_starts: tuple[bytes, ...] = ()) -> bytes:
    """``events`` random damages of a byte stream (``rng``: a numpy Generator): a cut of up to
    ``max_cut`` bytes, a flipped bit, up to ``max_insert`` random bytes inserted, or (when
    given) one of ``false_starts`` inserted. The protocol tests and benchmarks share it."""
    data = bytearray(stream)
    kinds = 4 if false_starts else 3
    for _ in range(events):
        at = int(rng.integers(0, len(data)))
        kind = int(rng.integers(0, kinds))
        if kind == 0:
            del data[at:at + int(rng.integers(1, max_cut))]
        elif kind == 1:
            data[at] ^= 1 << int(rng.integers(0, 8))
        elif kind == 2:
            data[at:at] = rng.bytes(int(rng.integers(1, max_insert)))
        else:
            data[at:at] = false_starts[int(rng.integers(0, len(false_starts)))]
    return bytes(data)


def damage_frames(frames: list[bytes], rng: Any, rate: float,
                  fake: Callable[[], bytes] | None = None,
                  markers: bytes = b"", flip_mask: int | None = None
                  ) -> tuple[bytes, list[int]]:
    """Damage whole frames at random, ``rate`` of them: a flipped bit (``flip_mask``: that
    XOR mask instead, e.g. 0xFF where a format has no checksum and a flipped bit of a digit
    would be another valid number), cut short, bytes lost in the middle (those three are
    lost), or garbage before the frame (kept intact): random bytes, with ``markers`` put
    inside, or followed by ``fake()`` (a frame-shaped fake with a good checksum). The stream
    and the indices of the frames left intact."""
    out = bytearray()
    intact = []
    for k, frame in enumerate(frames):
        data = bytearray(frame)
        kind = int(rng.integers(0, 6)) if rng.random() < rate else -1
        if kind == 0:  # a flipped bit past the marker
            mask = 1 << int(rng.integers(0, 8)) if flip_mask is None else flip_mask
            data[int(rng.integers(2, len(data)))] ^= mask
        elif kind == 1:  # cut short
            data = data[:int(rng.integers(1, len(data) - 1))]
        elif kind == 2:  # bytes lost in the middle
            a = int(rng.integers(2, len(data) - 7))
            del data[a:a + int(rng.integers(1, 6))]
        else:
            intact.append(k)
        if kind in (3, 4, 5):
            junk = bytearray(rng.integers(0, 256, int(rng.integers(1, 80)), np.uint8).tobytes())
            if kind == 4 and markers:
                for at in rng.integers(0, len(junk), 3):
                    junk[at:at + len(markers)] = markers
            if kind == 5 and fake is not None:
                junk += fake()
            out += junk
        out += data
    return bytes(out), intact


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
