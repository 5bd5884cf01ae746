"""Benchmark: SICK CoLa decode throughput, damaged-stream recovery and fuzzing.

Lab scale: 2000 LMS111 scans of 1081 samples (0.25°, 270°) with an RSSI channel, as CoLa-B
(~8.7 MB) and as CoLa-A. Measured: the stream decoder (framing, resync checks, telegram parse,
profiles) in samples per second (target, issue 17: ≥ 10 M samples/s for both); the share of
intact frames recovered from a damaged stream (bytes flipped in 5 % of the frames, garbage
and false starts between frames; target 100 %, no false frame passed as good); and a fuzz run
(random and mutated streams: nothing may escape but scanpipe's own errors).
``python benchmarks/bench_sick.py [--quick]`` prints the figures and saves JSON to
``benchmarks/results/sick-<date>.json``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import (
    cli,
    cpu_seconds,
    damage_frames,
    measure,
    measurement_table,
    throughput_line,
)

from scanpipe.errors import ScanpipeError
from scanpipe.protocol import sick_cola
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import decode_bytes, score_recovery


def lab_profiles(scans: int, samples: int = 1081, seed: int = 0) -> list[Profile]:
    """LMS111-like scans: −45° … 225° at 0.25°, 25 Hz µs timestamps, RSSI echo."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(scans):
        ranges = rng.uniform(0.5, 20.0, samples).astype(np.float32)
        ranges[rng.random(samples) < 0.02] = np.nan
        t_us = (k * 40_000) % (1 << 32)
        out.append(Profile(frame=k & 0xFFFF, sector=0, start_angle_deg=-45.0, step_deg=0.25,
                           ranges_m=np.round(ranges * 1000) / 1000,
                           echo=rng.integers(0, 4000, samples).astype(np.uint16),
                           device_time_ms=t_us, device_end_time_ms=(t_us + 30_000) % (1 << 32),
                           device_tick_ns=1000, device_wrap_ticks=1 << 32))
    return out


def damage(frames: list[bytes], seed: int = 1) -> tuple[bytes, list[int]]:
    """Damage 10 % of the frames (:func:`harness.damage_frames`: bytes inverted, as CoLa-A has
    no checksum, cuts, garbage with markers, false starts: a frame's beginning cut off); the
    indices of the frames left intact."""
    rng = np.random.default_rng(seed)

    def false_start() -> bytes:
        frame = frames[int(rng.integers(0, len(frames)))]
        return frame[:int(rng.integers(1, len(frame)))]

    marker = frames[0][:4] if frames[0][:1] == b"\x02" and frames[0][1:2] != b"s" else b"\x02"
    return damage_frames(frames, rng, 0.1, false_start, markers=marker, flip_mask=0xFF)


def fuzz(base: bytes, dialect: str, cases: int, seed: int = 2) -> dict[str, int]:
    """Random and mutated streams; count what escaped (anything but a ScanpipeError)."""
    rng = np.random.default_rng(seed)
    escaped = refused = 0
    for k in range(cases):
        if k % 2:
            blob = rng.integers(0, 256, int(rng.integers(0, 4096)), dtype=np.uint8).tobytes()
        else:
            mutated = bytearray(base[: int(rng.integers(1, len(base)))])
            for _ in range(int(rng.integers(1, 20))):
                mutated[rng.integers(0, len(mutated))] = int(rng.integers(0, 256))
            blob = bytes(mutated)
        try:
            decode_bytes(blob, dialect)
        except ScanpipeError:
            refused += 1
        except Exception:  # counting escapes is the point
            escaped += 1
    return {"cases": cases, "escaped": escaped, "refused": refused}


def run(quick: bool = False) -> dict[str, Any]:
    """Measure; return the figures."""
    scans = 150 if quick else 2000
    profiles = lab_profiles(scans)
    items = float(scans * len(profiles[0].ranges_m))
    streams = {"cola_b": [sick_cola.encode_profile(p) for p in profiles],
               "cola_a": [sick_cola.encode_profile_ascii(p) for p in profiles]}
    repeats = 3 if quick else 5
    measurements, recovery, fuzzing, cpu = [], {}, {}, {}
    for dialect, frames in streams.items():
        data = b"".join(frames)
        measurements.append(measure(f"{dialect} stream decoder", lambda d=data, n=dialect:
                                    decode_bytes(d, n), items, "samples", repeats=repeats))
        cpu[dialect] = items / cpu_seconds(lambda d=data, n=dialect: decode_bytes(d, n),
                                           repeats=repeats)
        expected = decode_bytes(data, dialect)[0]
        damaged, intact = damage(frames)
        decoded, counters = decode_bytes(damaged, dialect)
        score = score_recovery([expected[i] for i in intact], decoded, counters)
        recovery[dialect] = {"intact_frames": len(intact), "recovered": score.recovered,
                             "share": score.recovered / max(len(intact), 1),
                             "false_good": score.false_good}
        # six frames: runs long enough for the bulk paths (framing.BULK_MIN_FRAMES)
        fuzzing[dialect] = fuzz(b"".join(frames[:6]), dialect, 200 if quick else 2000)
    colab, colaa = measurements[0].throughput, measurements[1].throughput
    return {
        "scans": scans, "samples_per_scan": len(profiles[0].ranges_m),
        "stream_bytes": {k: sum(len(f) for f in v) for k, v in streams.items()},
        "cola_b_samples_per_s": colab, "cola_a_samples_per_s": colaa,
        "cola_b_cpu_samples_per_s": cpu["cola_b"], "cola_a_cpu_samples_per_s": cpu["cola_a"],
        "target_samples_per_s": 10e6, "meets_target": min(colab, colaa) >= 10e6,
        "recovery": recovery, "fuzz": fuzzing, "load_average": os.getloadavg(),
        "measurements": measurements,
    }


def show(results: dict[str, Any]) -> None:
    """Print the figures."""
    print(measurement_table(results["measurements"]))
    for dialect, r in results["recovery"].items():
        f = results["fuzz"][dialect]
        print(f"{dialect}: recovered {r['recovered']}/{r['intact_frames']} intact frames "
              f"({100 * r['share']:.1f} %), {r['false_good']} false; fuzz {f['cases']} cases, "
              f"{f['escaped']} escaped")
    for name in ("cola_b", "cola_a"):
        print(throughput_line(name, results[name + "_samples_per_s"],
                              results[name + "_cpu_samples_per_s"],
                              results["target_samples_per_s"], results["load_average"][0]))


if __name__ == "__main__":
    cli("sick", run, __doc__ or "", "a smaller scan", show)
