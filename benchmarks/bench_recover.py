"""Benchmark: intact messages saved from damaged MCAP files, ``scanpipe recover`` against the
official ``mcap`` readers (the seeking ``make_reader`` and the linear ``NonSeekingReader``,
both stopped at their first exception, as a user's script would be). A message counts as saved
when its bytes equal the original's; messages yielded with other bytes are counted as wrong.

Damage kinds, each over several seeds: a cut (the writer killed), one damaged chunk, a damaged
chunk plus a cut, and random byte flips. ``python benchmarks/bench_recover.py [--quick]`` prints
the figures and saves JSON into ``benchmarks/results/``.
"""

from __future__ import annotations

import io
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, table

from scanpipe.recording.catalogue import recover_mcap


def source_file(messages: int, chunk_size: int = 4096) -> bytes:
    """An MCAP file of ``messages`` small messages on two topics, in many chunks."""
    stream = io.BytesIO()
    writer = Writer(stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
    writer.start(profile="", library="bench")
    schema = writer.register_schema("bench.Blob", "jsonschema", b"{}")
    channels = [writer.register_channel(t, "json", schema) for t in ("/a", "/b")]
    rng = np.random.default_rng(0)
    for i in range(messages):
        writer.add_message(channels[i % 2], 10**18 + i * 10**6,
                           rng.integers(0, 255, 60, dtype=np.uint8).tobytes(), 10**18 + i * 10**6)
    writer.finish()
    return stream.getvalue()


Original = dict[tuple[str, int], bytes]


def originals(data: bytes) -> Original:
    """Every message of the undamaged file by (topic, log time)."""
    return {(c.topic, m.log_time): m.data
            for _, c, m in make_reader(io.BytesIO(data)).iter_messages()}


def official(data: bytes, original: Original, linear: bool = False) -> tuple[int, int]:
    """(intact, wrong) messages an official reader yields before its first exception; wrong =
    yielded with bytes that differ from the original (CRCs are not checked by default)."""
    intact = wrong = 0
    try:
        reader = NonSeekingReader(io.BytesIO(data)) if linear else make_reader(io.BytesIO(data))
        for _, channel, message in reader.iter_messages(log_time_order=False):
            if original.get((channel.topic, message.log_time)) == message.data:
                intact += 1
            else:
                wrong += 1
    except Exception:  # the official readers raise many types on damage
        pass
    return intact, wrong


def chunk_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, length) of every chunk record, from the summary."""
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def damage(data: bytes, kind: str, rng: np.random.Generator) -> bytes:
    """One damaged copy of ``data``: ``chunk`` overwrites 32 bytes inside one chunk's
    compressed records; ``flips`` inverts 5 bytes anywhere before the summary."""
    out = bytearray(data)
    body = len(out) - 2000  # leave the summary's share out of the damage positions
    if kind in ("chunk", "chunk+cut"):
        spans = chunk_spans(data)
        start, length = spans[int(rng.integers(0, len(spans)))]
        at = start + 60 + int(rng.integers(0, max(1, length - 100)))
        out[at:at + 32] = rng.integers(0, 255, 32, dtype=np.uint8).tobytes()
    if kind == "flips":
        for at in rng.integers(100, body, 5):
            out[int(at)] ^= 0xFF
    if kind in ("cut", "chunk+cut"):
        out = out[:int(len(out) * rng.uniform(0.5, 0.95))]
    return bytes(out)


def run(quick: bool) -> dict[str, Any]:
    """Saved messages per damage kind, summed over seeds: recover, seeking, linear."""
    messages = 2000 if quick else 20000
    seeds = 3 if quick else 10
    data = source_file(messages)
    original = originals(data)
    figures: dict[str, Any] = {"messages": messages, "seeds": seeds, "kinds": {}}
    with tempfile.TemporaryDirectory() as folder:
        src, out = Path(folder) / "damaged.mcap", Path(folder) / "fixed.mcap"
        for kind in ("cut", "chunk", "chunk+cut", "flips"):
            rng = np.random.default_rng(1)
            totals = dict.fromkeys(("recover", "recover_wrong", "official_seeking",
                                    "official_seeking_wrong", "official_linear",
                                    "official_linear_wrong"), 0)
            for _ in range(seeds):
                damaged = damage(data, kind, rng)
                src.write_bytes(damaged)
                out.unlink(missing_ok=True)
                recover_mcap(src, out)
                for name, (intact, wrong) in (
                        ("recover", official(out.read_bytes(), original)),
                        ("official_seeking", official(damaged, original)),
                        ("official_linear", official(damaged, original, linear=True))):
                    totals[name] += intact
                    totals[f"{name}_wrong"] += wrong
            best = max(totals["official_seeking"], totals["official_linear"])
            figures["kinds"][kind] = {**totals, "of": messages * seeds,
                                      "ratio_to_best_official": totals["recover"] / best
                                      if best else None}
    rows = [(kind, *(f"{v[n]} ({v[n + '_wrong']} wrong)" for n in
                     ("recover", "official_seeking", "official_linear")),
             f"{v['of']}", "∞" if v["ratio_to_best_official"] is None
             else f"{v['ratio_to_best_official']:.2f}×")
            for kind, v in figures["kinds"].items()]
    print(table(rows, ("damage", "recover", "official seeking", "official linear", "of",
                       "recover / best official (intact)")))
    return figures


if __name__ == "__main__":
    cli("recover", run, __doc__ or "", "2000 messages, 3 seeds per damage kind")
