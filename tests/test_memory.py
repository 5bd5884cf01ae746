"""Memory of the chain: decode shares the frames' bytes, artifacts are written and read in row
groups, the reader hands read pages back, the runner releases freed memory between stages, and
the benchmark measures a chain's own peak (not its parent's)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: `benchmarks`

from scanpipe import artifacts, pipeline
from scanpipe.artifacts import read_artifact
from scanpipe.pipeline import execute, get_stage, run_chain
from scanpipe.protocol import ldoem
from scanpipe.protocol.profile import Profile
from scanpipe.recording import reader
from scanpipe.recording.reader import read_recording
from scanpipe.recording.schemas import RX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import default_rig
from scanpipe.stages.decode import DecodeParams, blobs_array

T0 = 1_700_000_000_000_000_000


def noise_jpegs(count: int, seed: int = 0) -> list[bytes]:
    """JPEGs of noise (~100 kB each: they do not compress)."""
    rng = np.random.default_rng(seed)
    return [cv2.imencode(".jpg", rng.integers(0, 256, (180, 240, 3), np.uint8))[1].tobytes()
            for _ in range(count)]


def write_recording(path: Path, jpegs: list[bytes], profiles: int = 40) -> None:
    """A small scan: LD-OEM profiles, motor states and the frames ``jpegs`` (camera cam0)."""
    with RecordingWriter(path, default_rig(), {"mode": "test"}) as writer:
        for i in range(profiles):
            t_ms = (200 * i) & 0xFFFF
            wire = ldoem.encode_profile(Profile(
                frame=i, sector=0, start_angle_deg=0.0, step_deg=1.0,
                ranges_m=np.full(360, 2.0 + i / 100, np.float32),
                device_time_ms=t_ms, device_end_time_ms=(t_ms + 199) & 0xFFFF))
            writer.write_stream("scanner", wire, RX, T0 + (i + 1) * 200_000_000)
            writer.write_motor_state(T0 + i * 200_000_000, i, i + 1, False, i * 200_000)
        for k, jpeg in enumerate(jpegs):
            writer.write_image("cam0", T0 + k * 1_100_000_000, jpeg)  # across chunks


def codecs(path: Path) -> dict[str, str]:
    meta = pq.ParquetFile(path).metadata
    return {meta.row_group(0).column(i).path_in_schema: meta.row_group(0).column(i).compression
            for i in range(meta.num_columns)}


def test_blobs_array_shares_the_bytes_it_is_given() -> None:
    blobs = [b"abc", b"", bytes(range(256)) * 10]
    column = blobs_array(blobs)
    assert column.type == pa.binary() and column.to_pylist() == blobs
    for chunk, blob in zip(column.chunks, blobs, strict=True):  # the same memory, not a copy
        assert chunk.buffers()[2].address == pa.py_buffer(blob).address
    assert blobs_array([]).to_pylist() == []


def test_decode_writes_frames_in_row_groups_uncompressed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    jpegs = noise_jpegs(12)
    rec = tmp_path / "scan.mcap"
    write_recording(rec, jpegs)
    monkeypatch.setattr(artifacts, "ROW_GROUP_BYTES", 300_000)  # ~3 frames per row group
    record = execute(get_stage("decode"), {"recording": rec}, tmp_path / "decode",
                     DecodeParams(), force=True)
    frames_path = record.outputs["frames"]
    assert pq.ParquetFile(frames_path).metadata.num_row_groups >= 3
    assert codecs(frames_path) == {"camera_id": "ZSTD", "log_time_ns": "ZSTD",
                                   "sequence": "ZSTD", "format": "ZSTD", "width": "ZSTD",
                                   "height": "ZSTD", "data": "UNCOMPRESSED"}
    frames, provenance = read_artifact(frames_path)
    assert frames.column("data").to_pylist() == jpegs  # every byte, in order
    assert frames.column("width").to_pylist() == [240] * 12
    assert provenance["stage"] == "decode"
    # A table without binary columns: every leaf zstd, the list columns' values too.
    profile_codecs = codecs(record.outputs["profiles"])
    assert profile_codecs["ranges_m.list.element"] == "ZSTD"
    assert set(profile_codecs.values()) == {"ZSTD"}
    profiles = read_artifact(record.outputs["profiles"])[0]
    assert profiles.num_rows == 40


def test_row_groups_are_sized_by_bytes() -> None:
    table = pa.table({"x": np.zeros(1000, np.float64)})  # 8000 bytes
    assert artifacts.row_group_rows(table, 800) == 100
    assert artifacts.row_group_rows(table, 1) == 1
    assert artifacts.row_group_rows(table, 10**9) == 1000
    assert artifacts.row_group_rows(table.slice(0, 0), 800) == 1


def test_reader_releasing_pages_reads_the_same(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    rec = tmp_path / "scan.mcap"
    write_recording(rec, noise_jpegs(6))
    cut = tmp_path / "cut.mcap"  # a killed writer: the pages before the cut are released too
    cut.write_bytes(rec.read_bytes()[: rec.stat().st_size * 2 // 3])
    expected = {path: read_recording(path) for path in (rec, cut)}
    released: list[int] = []
    real = reader._release_pages

    def spy(data: Any, start: int, end: int) -> int:
        released.append(end - start)
        return real(data, start, end)

    monkeypatch.setattr(reader, "_release_pages", spy)
    monkeypatch.setattr(reader, "_RELEASE_BYTES", 4096)  # after every record of a page or more
    for path, before in expected.items():
        released.clear()
        after = read_recording(path)
        assert after.stream("scanner").data == before.stream("scanner").data
        assert [i.data for i in after.images] == [i.data for i in before.images]
        assert np.array_equal(after.motor.log_time_ns, before.motor.log_time_ns)
        assert after.warnings == before.warnings and after.loss == before.loss
        # Released as it went (the pages of the chunks read, all but the last few).
        assert len(released) >= 2 and sum(released) > path.stat().st_size // 4, path


def test_the_chain_releases_freed_memory_after_each_stage(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec = tmp_path / "scan.mcap"
    write_recording(rec, noise_jpegs(2))
    calls: list[int] = []
    real = pipeline.release_free_memory
    monkeypatch.setattr(pipeline, "release_free_memory", lambda: (calls.append(1), real()))
    records = run_chain(rec, tmp_path / "w", {}, to="assemble")
    assert [r.stage for r in records] == ["decode", "calibrate", "assemble"]
    assert len(calls) == len(records)


def test_chain_memory_reports_the_chains_own_peak(tmp_path: Path) -> None:
    """A chain started from a process that had used 1.5 GB reported 1.5 GB (getrusage's
    ru_maxrss survives vfork + exec); its own peak is far below."""
    from benchmarks.pipeline_bench import chain_memory

    rec = tmp_path / "scan.mcap"
    write_recording(rec, noise_jpegs(2))
    ballast = np.ones(1_500_000_000 // 8)  # touched: the parent's peak RSS is ≥ 1.5 GB
    del ballast
    figures = chain_memory(rec, tmp_path / "w", {}, to="calibrate")
    assert figures["rss_after_imports_mb"] > 50
    assert figures["rss_after_imports_mb"] <= figures["peak_rss_mb"] < 1200
    decode = figures["stages"]["decode"]
    assert decode["rss_after_mb"] <= decode["peak_rss_mb"] <= figures["peak_rss_mb"]
    # the timeline: each stage's entry and peak, and what it was doing (its progress tasks)
    timeline = figures["timeline"]
    assert {"decode", "calibrate"} <= set(timeline) <= {"decode", "calibrate", "(end)"}
    assert "(start)" in timeline["decode"]["tasks"]  # before its first progress report
    for stage in timeline.values():
        assert 50 < stage["entry_mb"] <= stage["peak_mb"] <= figures["peak_rss_mb"] + 1
        assert max(stage["tasks"].values()) == stage["peak_mb"]


def _chunk_offsets(path: Path) -> list[int]:
    data = path.read_bytes()
    pos, offsets = len(reader.MAGIC), []
    while pos + 9 <= len(data):
        opcode, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
        if opcode == reader.OP_CHUNK:
            offsets.append(pos)
        if opcode in (reader.OP_DATA_END, reader.OP_FOOTER):
            break
        pos += 9 + length
    return offsets


def _summary(recording: reader.Recording) -> tuple[Any, ...]:
    return (recording.stream("scanner").data, [i.data for i in recording.images],
            recording.motor.log_time_ns.tolist(), recording.warnings, recording.loss,
            recording.chunks_read, recording.chunks_damaged)


@pytest.mark.parametrize("damage", ["inflated bytes", "length field", "opcode", "cut"])
def test_reading_ahead_reads_damage_as_reading_in_order(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage: str) -> None:
    """The next chunk is decompressed in a worker while this one is parsed: a damaged chunk
    read ahead gives the same warnings, loss and data as reading one chunk at a time."""
    rec = tmp_path / "scan.mcap"
    write_recording(rec, noise_jpegs(6))
    offsets = _chunk_offsets(rec)
    assert len(offsets) >= 4
    data = bytearray(rec.read_bytes())
    at = offsets[2]  # a chunk that is read ahead
    if damage == "inflated bytes":
        data[at + 9 + 200] ^= 0xFF
    elif damage == "length field":
        data[at + 3] ^= 0x10
    elif damage == "opcode":
        data[at] = 0x42
    else:
        data = data[:at + 300]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    started: list[int] = []
    real_ahead = reader._ChunkPrefetch.ahead

    def ahead(self: Any, pos: int) -> None:
        started.append(pos)
        real_ahead(self, pos)

    monkeypatch.setattr(reader._ChunkPrefetch, "ahead", ahead)
    with_worker = read_recording(bad)
    assert started  # chunks were read ahead
    monkeypatch.setattr(reader._ChunkPrefetch, "ahead", lambda self, pos: None)
    in_order = read_recording(bad)
    assert _summary(with_worker) == _summary(in_order)
    assert with_worker.warnings  # the damage is reported


_RELEASE_CHILD = """
import sys
from pathlib import Path
import scanpipe  # first, as in every scanpipe process: it sets the allocator up
import pyarrow as pa
from scanpipe.artifacts import read_artifact, release_free_memory
def rss_mb():
    with open("/proc/self/status") as status:
        return next(int(l.split()[1]) for l in status if l.startswith("VmRSS")) / 1024
kept = []
for _ in range(5):
    release_free_memory()
    before = rss_mb()
    table = read_artifact(Path(sys.argv[1]))[0]
    held = rss_mb()
    del table
    release_free_memory()
    kept.append((round(held - before), round(rss_mb() - before)))
print(kept)
"""


def test_a_released_table_leaves_the_process(tmp_path: Path) -> None:
    """A table read from an artifact and dropped is handed back to the system at once (Arrow's
    allocator without its purge delay, the file read on the calling thread): before, a
    released 120 MB table of frames stayed resident in some runs, most of it in others."""
    import subprocess

    rng = np.random.default_rng(0)
    blobs = [rng.integers(0, 256, 300_000, np.uint8).tobytes() for _ in range(400)]
    path = tmp_path / "frames.parquet"
    artifacts.write_artifact(path, pa.table({"data": pa.array(blobs, pa.binary())}),
                             {"key": "k"})
    del blobs
    env = {k: v for k, v in __import__("os").environ.items() if not k.startswith("MIMALLOC")}
    done = subprocess.run([sys.executable, "-c", _RELEASE_CHILD, str(path)], env=env,
                          capture_output=True, text=True, check=True)
    # [(held MB, left MB) per read]; the first read leaves the reader's and the allocator's
    # own ~27 MB for good; the old code left 116–132 MB after most of the later reads
    reads = eval(done.stdout.strip())
    for held, left in reads[1:]:
        assert held >= 100, reads  # the table was resident
        assert left <= 10, reads  # and went
