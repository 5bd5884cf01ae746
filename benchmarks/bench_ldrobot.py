"""Benchmark: decode a lab-scale LDRobot capture (an STL-27L, 5 minutes: 6.5 M samples).

The stream is what the virtual STL-27L sends over the built-in room (21 600 samples/s,
wobbling head, noise, dropouts; ~25 MB of 47-byte packets). Measured: the stream decoder
(packets located, checked and resampled into revolutions) fed in 1 MiB chunks as the decode
stage feeds it, in wall and CPU time; the decode stage end to end (MCAP → Parquet) when the
``ldrobot`` dialect is registered; and the share of intact packets recovered from a damaged
copy of the stream (byte flips, cuts, garbage with markers and fake packets with good CRCs).
Targets (issue 17): ≥ 10 M samples/s, 100 % of intact packets, no false packet.
``python benchmarks/bench_ldrobot.py [--quick]`` prints the figures and saves JSON to
``benchmarks/results/ldrobot-<date>.json``.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
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

from scanpipe.protocol import ldrobot as ld
from scanpipe.rig import default_rig
from scanpipe.sim.ldrobot_device import LdrobotHead, ldrobot_model
from scanpipe.sim.motion import PlatformState
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.scanner import MeasurementModel

T0_NS = 1_700_000_000_000_000_000
FEED_BYTES = 1 << 20


def lab_stream(seconds: float, model: str = "stl27l", seed: int = 0) -> bytes:
    """What the virtual ``model`` sends in ``seconds`` over the built-in room."""
    rig = default_rig()
    m = ldrobot_model(model)
    scanner = rig.scanner.model_copy(update={"min_range_m": m.min_range_m,
                                             "max_range_m": m.max_range_m})
    platform = PlatformState(rig.motor.pulse_step_deg)
    pulses = int(360.0 / rig.motor.pulse_step_deg)  # one platform turn in ``seconds``
    platform.start_move(0.0, pulses, pulses / max(seconds, 1.0), 1e9)
    head = LdrobotHead(m, resolve_scene("room"), scanner, platform,
                       MeasurementModel(noise_sigma_m=m.noise_sigma_m, seed=seed))
    total = int(seconds / head.packet_s)
    parts, batch = [], 20_000
    for first in range(0, total, batch):
        parts.append(head.packets(first, min(batch, total - first)).data)
    return b"".join(parts)


def decode_chunks(stream: bytes, sl_correction: bool = False) -> int:
    """Decode ``stream`` in 1 MiB chunks (an LD14's with its angle correction); the number of
    revolutions."""
    decoder = ld.RevolutionDecoder(sl_correction=sl_correction)
    view = memoryview(stream)
    count = 0
    for start in range(0, len(stream), FEED_BYTES):
        count += len(decoder.feed(view[start:start + FEED_BYTES]))
    return count + len(decoder.finish())


def damage(stream: bytes, seed: int, rate: float) -> tuple[bytes, list[int]]:
    """Damage packets at random (the protocol tests' damage: :func:`harness.damage_frames`);
    the new stream and the indices of the packets left intact."""
    rng = np.random.default_rng(seed)

    def fake() -> bytes:
        packet = bytearray(rng.integers(0, 256, ld.PACKET_BYTES, np.uint8).tobytes())
        packet[:2] = b"\x54\x2c"
        packet[-1] = ld.crc8(bytes(packet[:-1]))
        return bytes(packet)

    n = len(stream) // ld.PACKET_BYTES
    packets = [stream[k * ld.PACKET_BYTES:(k + 1) * ld.PACKET_BYTES] for k in range(n)]
    return damage_frames(packets, rng, rate, fake, markers=b"\x54\x2c")


def recovery(stream: bytes, packets: int) -> dict[str, Any]:
    """Damage the first ``packets`` packets of ``stream``; how many intact ones come back."""
    part = stream[:packets * ld.PACKET_BYTES]
    damaged, intact = damage(part, seed=1, rate=0.2)
    sent, _ = ld.locate_packets(part)
    got, counters = ld.locate_packets(damaged)

    def keys(p: ld.Packets) -> list[bytes]:
        return [p.distance_mm[i].tobytes() + p.start_cdeg[i:i + 1].tobytes()
                + p.timestamp_ms[i:i + 1].tobytes() for i in range(len(p))]

    sent_keys = keys(sent)
    got_keys = set(keys(got))
    recovered = sum(1 for k in intact if sent_keys[k] in got_keys)
    return {"packets": packets, "intact": len(intact), "recovered": recovered,
            "false_packets": len(got_keys - set(sent_keys)),
            "recovered_share": recovered / max(len(intact), 1),
            "counters": counters.as_dict()}


def stage_end_to_end(stream: bytes, tmp: Path, repeats: int) -> Any:
    """The decode stage (MCAP → Parquet) on a recording of ``stream``; None if the dialect is
    not registered yet."""
    from scanpipe.pipeline import execute, get_stage
    from scanpipe.protocol.registry import DIALECTS
    from scanpipe.recording.schemas import RX
    from scanpipe.recording.writer import RecordingWriter
    from scanpipe.stages.decode import DecodeParams

    if "ldrobot" not in DIALECTS:
        return None
    rec = tmp / "lab.mcap"
    rng = np.random.default_rng(0)
    cuts = np.cumsum(rng.integers(1, 4096, size=len(stream) // 2048 + 2))
    cuts = np.unique(np.concatenate([[0], cuts[cuts < len(stream)], [len(stream)]]))
    bytes_per_s = 21_600 / 12 * ld.PACKET_BYTES
    times = T0_NS + (cuts[1:] / bytes_per_s * 1e9).astype(np.int64)
    with RecordingWriter(rec, default_rig(), {"mode": "benchmark"}) as writer:
        for a, b, t in zip(cuts[:-1], cuts[1:], times, strict=True):
            writer.write_stream("scanner", stream[a:b], RX, int(t))
    stage = get_stage("decode")
    params = DecodeParams.model_validate({"dialect": "ldrobot"})
    out = tmp / "out"
    samples = len(stream) // ld.PACKET_BYTES * ld.POINTS_PER_PACKET
    return measure("decode stage end to end (MCAP → Parquet)",
                   lambda: execute(stage, {"recording": rec}, out, params, force=True),
                   float(samples), "samples", repeats=repeats)


def run(quick: bool = False) -> dict[str, Any]:
    """Measure; return the figures."""
    seconds = 30.0 if quick else 300.0
    started = time.perf_counter()
    stream = lab_stream(seconds)
    made_s = time.perf_counter() - started
    samples = len(stream) // ld.PACKET_BYTES * ld.POINTS_PER_PACKET
    repeats = 3 if quick else 5
    decoder = measure("stream decoder (1 MiB chunks)", lambda: decode_chunks(stream),
                      float(samples), "samples", repeats=repeats)
    cpu_s = cpu_seconds(lambda: decode_chunks(stream), repeats=repeats)
    measurements = [decoder]
    with tempfile.TemporaryDirectory() as tmp:
        stage = stage_end_to_end(stream, Path(tmp), repeats)
    if stage is not None:
        measurements.append(stage)
    rec = recovery(stream, 20_000 if quick else 100_000)
    # The LD14P (4 000 samples/s, 6 Hz) decoded with its per-sample angle correction.
    ld14 = lab_stream(seconds, "ld14p")
    ld14_samples = len(ld14) // ld.PACKET_BYTES * ld.POINTS_PER_PACKET
    ld14_decoder = measure("LD14P stream decoder (angle correction)",
                           lambda: decode_chunks(ld14, True), float(ld14_samples), "samples",
                           repeats=repeats)
    ld14_cpu_s = cpu_seconds(lambda: decode_chunks(ld14, True), repeats=repeats)
    measurements.append(ld14_decoder)
    return {
        "model": "stl27l", "seconds": seconds, "stream_bytes": len(stream), "samples": samples,
        "revolutions": decode_chunks(stream), "stream_made_s": made_s,
        "samples_per_s": decoder.throughput, "cpu_samples_per_s": samples / cpu_s,
        "stage_samples_per_s": None if stage is None else stage.throughput,
        "target_samples_per_s": 10e6, "meets_target": decoder.throughput >= 10e6,
        "recovery": rec, "load_average": os.getloadavg(), "measurements": measurements,
        "ld14p": {"seconds": seconds, "samples": ld14_samples,
                  "samples_per_s": ld14_decoder.throughput,
                  "cpu_samples_per_s": ld14_samples / ld14_cpu_s},
    }


def show(results: dict[str, Any]) -> None:
    """Print the figures."""
    print(measurement_table(results["measurements"]))
    rec = results["recovery"]
    print(throughput_line(f"STL-27L {results['seconds']:.0f} s: {results['samples'] / 1e6:.2f} M "
                          f"samples, {results['stream_bytes'] / 1e6:.1f} MB, "
                          f"{results['revolutions']} revolutions; decoder",
                          results["samples_per_s"], results["cpu_samples_per_s"],
                          results["target_samples_per_s"], results["load_average"][0]))
    print(f"damaged stream: {rec['recovered']} of {rec['intact']} intact packets recovered "
          f"({100 * rec['recovered_share']:.2f} %), {rec['false_packets']} false")


if __name__ == "__main__":
    cli("ldrobot", run, __doc__ or "", "30 s instead of 5 minutes", show)
