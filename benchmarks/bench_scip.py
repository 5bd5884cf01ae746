"""Benchmark: decode a lab-scale Hokuyo SCIP 2.0 capture (UST-10LX, 40 Hz, 1081 steps, ME).

A four-minute turntable scan: 9600 ``ME`` scans (range + intensity, 3-character encoding,
~70 MB) after the device's ``PP`` and ``ME`` replies, decoded by the registry's stream
decoder in the decode stage's 1 MiB feeds. Also: the same stream damaged (cuts, bit flips,
insertions): every intact message must come out and nothing that was not sent.
Target (issue 17): ≥ 10 M samples/s. ``python benchmarks/bench_scip.py [--quick]`` prints
the figures and saves JSON to ``benchmarks/results/scip-<date>.json``.
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
    damage_stream,
    measure,
    measurement_table,
    throughput_line,
)

from scanpipe.protocol import scip
from scanpipe.protocol.registry import StreamDecoder, decode_bytes, score_recovery

STEPS = 1081
#: As the decode stage feeds its decoder (stages/decode.py: 1 MiB at a time).
CHUNK_BYTES = 1 << 20


def lab_stream(scans: int, seed: int = 0) -> tuple[bytes, bytes, list[bytes]]:
    """The device's PP and ME replies, then ``scans`` ME scans (40 Hz timestamps): the
    replies, the whole stream and the scans."""
    rng = np.random.default_rng(seed)
    head = scip.parameter_reply(b"PP", scip.pp_fields(scip.UST_GEOMETRY, "UST-10LX", 60,
                                                      10000, 0, 1080))
    head += b"ME0000108001000\n00P\n\n"
    messages = []
    for i in range(scans):
        ranges = rng.uniform(0.06, 10.0, STEPS)
        ranges[rng.random(STEPS) < 0.02] = np.nan
        echo = rng.integers(0, 8000, STEPS)
        messages.append(scip.encode_scan(b"ME", 0, 1080, 1, i * 25, ranges, echo))
    return head, head + b"".join(messages), messages


def chunked_decode(stream: bytes) -> int:
    """Decode in the decode stage's feeds; the number of profiles."""
    decoder = StreamDecoder("scip")
    n = 0
    for at in range(0, len(stream), CHUNK_BYTES):
        n += len(decoder.feed(stream[at:at + CHUNK_BYTES]))
    return n + len(decoder.finish())


def damaged(stream: bytes, events: int, seed: int = 1) -> bytes:
    """Cuts, bit flips and insertions (:func:`harness.damage_stream`)."""
    return damage_stream(stream, np.random.default_rng(seed), events, 2000, 100)


def run(quick: bool = False) -> dict[str, Any]:
    """Measure the decoder and the recovery from damage; return the figures."""
    scans = 600 if quick else 9600
    head, stream, messages = lab_stream(scans)
    items = float(scans * STEPS)
    repeats = 3 if quick else 5
    measurements = [measure("SCIP stream decoder (1 MiB feeds)", lambda: chunked_decode(stream),
                            items, "samples", repeats=repeats)]
    cpu_s = cpu_seconds(lambda: chunked_decode(stream), repeats=repeats)
    bad = head + damaged(stream[len(head):], events=max(10, scans // 20))
    intact = [m for m in messages if m in bad]
    expected = [p for m in intact for p in decode_bytes(head + m, "scip")[0]]
    sent = [p for m in messages for p in decode_bytes(head + m, "scip")[0]]
    decoded, counters = decode_bytes(head + bad[len(head):], "scip")
    recovery = score_recovery(expected, decoded, counters)
    unsent = score_recovery(sent, decoded, counters).false_good
    m = measurements[0]
    return {
        "scans": scans, "samples_per_scan": STEPS, "stream_bytes": len(stream),
        "samples_per_s": m.throughput, "cpu_samples_per_s": items / cpu_s,
        "target_samples_per_s": 10e6, "meets_target": m.throughput >= 10e6,
        "load_average": os.getloadavg(),
        "damage": {"intact": len(expected), "recovered": recovery.recovered,
                   "lost": recovery.lost, "unsent_decoded": unsent,
                   "counters": counters.as_dict()},
        "measurements": measurements,
    }


def show(results: dict[str, Any]) -> None:
    """Print the figures."""
    print(measurement_table(results["measurements"]))
    d = results["damage"]
    print(throughput_line(f"{results['scans']} × {results['samples_per_scan']} samples, "
                          f"{results['stream_bytes'] / 1e6:.1f} MB",
                          results["samples_per_s"], results["cpu_samples_per_s"],
                          results["target_samples_per_s"], results["load_average"][0]))
    print(f"damaged stream: {d['recovered']}/{d['intact']} intact messages recovered, "
          f"{d['unsent_decoded']} unsent decoded")


if __name__ == "__main__":
    cli("scip", run, __doc__ or "", "600 scans instead of 9600", show)
