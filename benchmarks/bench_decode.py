"""Benchmark: decode a lab-scale scan (1667 profiles × 1440 samples) end to end.

The stream is built with the ``ldoem`` encoder (mask 0x39FF, ~4.9 MB), cut into random chunks
(1 B … 8 kB, like TCP reads), written with :class:`RecordingWriter`, then decoded by the decode
stage through the runner (reading the MCAP, decoding, building the tables, writing Parquet with
provenance). Target (issue 3): ≥ 10 M samples/s end to end, Parquet included.
``python benchmarks/bench_decode.py [--quick]`` prints the figures and saves JSON to
``benchmarks/results/decode-<date>.json``.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, measure, table

from scanpipe.pipeline import execute, get_stage
from scanpipe.protocol import ldoem
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import decode_bytes
from scanpipe.recording.reader import read_recording
from scanpipe.recording.schemas import RX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import default_rig
from scanpipe.stages.decode import DecodeParams

T0_NS = 1_700_000_000_000_000_000


def lab_stream(profiles: int, samples: int, seed: int = 0) -> bytes:
    """``profiles`` LD-OEM profile replies of ``samples`` ranges each, 5 Hz device timestamps."""
    rng = np.random.default_rng(seed)
    step = 360.0 / samples
    frames = []
    for i in range(profiles):
        ranges = rng.uniform(0.5, 20.0, samples).astype(np.float32)
        ranges[rng.random(samples) < 0.02] = np.nan
        t_ms = (i * 200) & 0xFFFF
        frames.append(ldoem.encode_profile(Profile(
            frame=i, sector=0, start_angle_deg=0.0, step_deg=step, ranges_m=ranges,
            device_time_ms=t_ms, device_end_time_ms=(t_ms + 200) & 0xFFFF)))
    return b"".join(frames)


def write_recording(path: Path, stream: bytes, seed: int = 0) -> int:
    """Write ``stream`` in random chunks as a recording; returns the number of chunks."""
    rng = np.random.default_rng(seed)
    cuts = np.cumsum(rng.integers(1, 8192, size=len(stream) // 2048 + 2))
    cuts = np.unique(np.concatenate([[0], cuts[cuts < len(stream)], [len(stream)]]))
    duration_ns = 400_000_000 * max(1, len(stream) // 3000)
    times = T0_NS + (cuts[1:] * (duration_ns / len(stream))).astype(np.int64)
    with RecordingWriter(path, default_rig(), {"mode": "benchmark"}) as writer:
        for a, b, t in zip(cuts[:-1], cuts[1:], times, strict=True):
            writer.write_stream("scanner", stream[a:b], RX, int(t))
        for k in range(0, len(times), 50):
            writer.write_motor_state(int(times[k]), k, k, False, k * 1000)
    return len(cuts) - 1


def run(quick: bool = False) -> dict[str, Any]:
    """Measure decode end to end (and its parts); return the figures."""
    profiles, samples = (300, 1440) if quick else (1667, 1440)
    stream = lab_stream(profiles, samples)
    items = float(profiles * samples)
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "lab.mcap"
        chunks = write_recording(rec, stream)
        stage, params = get_stage("decode"), DecodeParams()
        out = Path(tmp) / "out"

        def end_to_end() -> None:
            execute(stage, {"recording": rec}, out, params, force=True)

        repeats = 3 if quick else 5
        measurements = [
            measure("decode end to end (MCAP → Parquet)", end_to_end, items, "samples",
                    repeats=repeats),
            measure("read recording", lambda: read_recording(rec), items, "samples",
                    repeats=repeats),
            measure("stream decoder only", lambda: decode_bytes(stream, "ldoem"), items,
                    "samples", repeats=repeats),
        ]
        cpu_s = []  # CPU time (all threads): less sensitive than wall time to a busy machine
        for _ in range(repeats):
            started = time.process_time()
            end_to_end()
            cpu_s.append(time.process_time() - started)
        record = execute(stage, {"recording": rec}, out, params, force=True)
        parquet_bytes = sum(p.stat().st_size for p in record.outputs.values())
        mcap_bytes = rec.stat().st_size
    e2e = measurements[0]
    return {
        "profiles": profiles, "samples_per_profile": samples, "stream_bytes": len(stream),
        "stream_chunks": chunks, "recording_bytes": mcap_bytes, "parquet_bytes": parquet_bytes,
        "decoded_profiles": record.report["counts"]["profiles"],
        "samples_per_s": e2e.throughput, "target_samples_per_s": 10e6,
        "cpu_s": cpu_s, "cpu_samples_per_s": items / statistics.median(cpu_s),
        "load_average": os.getloadavg(),
        "meets_target": e2e.throughput >= 10e6,
        "measurements": measurements,
    }


def show(results: dict[str, Any]) -> None:
    """Print the figures."""
    rows = [(m.name, f"{m.median_s * 1000:.1f} ms", f"{m.throughput / 1e6:.1f} M {m.unit}/s",
             f"{m.peak_rss_mb:.0f} MB") for m in results["measurements"]]
    print(table(rows, ("measurement", "median", "throughput", "peak RSS")))
    print(f"{results['profiles']} × {results['samples_per_profile']} samples, stream "
          f"{results['stream_bytes'] / 1e6:.2f} MB in {results['stream_chunks']} chunks, "
          f"end to end {results['samples_per_s'] / 1e6:.1f} M samples/s wall, "
          f"{results['cpu_samples_per_s'] / 1e6:.1f} M samples per CPU second "
          f"(target 10 M: {'met' if results['meets_target'] else 'NOT met'}; load average "
          f"{results['load_average'][0]:.1f})")


if __name__ == "__main__":
    cli("decode", run, __doc__ or "", "a smaller scan", show)
