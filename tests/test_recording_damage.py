"""Recordings survive bad bytes, cuts and full disks.

1 s chunks bound what one bad byte or a cut can lose; the tolerant reader reads every intact
chunk after a damaged one and counts the loss; a full disk ends the recording with one
RecordingError and leaves a readable file.
"""

from __future__ import annotations

import errno
import io
import json
import os
import random
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from scanpipe.acquire.sink import RecordingSink
from scanpipe.errors import RecordingError
from scanpipe.recording import schemas
from scanpipe.recording.reader import Recording, read_recording
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import Rig, default_rig

T0 = 1_700_000_000_000_000_000
RATE_HZ = 50  # scanner chunks per second of log time
SECONDS = 10
MS = 1_000_000


def _payload(index: int) -> bytes:
    """A scanner chunk that names its index (so the test can tell which ones were lost),
    then 36 bytes that do not compress (so a disk fills up)."""
    return index.to_bytes(4, "little") + random.Random(index).randbytes(36)


def _write_scan(path: Path, **writer_args: Any) -> int:
    """10 s of scanner bytes (50 chunks/s), motor states at 10 Hz; returns the chunk count."""
    n = RATE_HZ * SECONDS
    with RecordingWriter(path, default_rig(), {"mode": "test"}, **writer_args) as writer:
        for i in range(n):
            t = T0 + i * (10**9 // RATE_HZ)
            writer.write_stream("scanner", _payload(i), schemas.RX, t)
            if i % 5 == 0:
                writer.write_motor_state(t, i, i + 5, True, i * 100)
    return n


def _indices(rec: Recording) -> set[int]:
    data = rec.stream("scanner").data
    return {int.from_bytes(data[k:k + 4], "little") for k in range(0, len(data), 40)}


class _Scan(tuple):  # type: ignore[type-arg]
    """(path, bytes, chunk indexes) with a short repr (hypothesis prints its arguments)."""

    def __repr__(self) -> str:
        return f"<scan {self[0]}>"


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, bytes, list[Any]]:
    path = tmp_path_factory.mktemp("scan") / "scan.mcap"
    _write_scan(path)
    with path.open("rb") as handle:
        chunk_indexes = make_reader(handle).get_summary().chunk_indexes
    return _Scan((path, path.read_bytes(), chunk_indexes))


def test_chunks_span_at_most_a_second_and_official_readers_read_them(scan: Any) -> None:
    path, _, chunk_indexes = scan
    assert SECONDS <= len(chunk_indexes) <= SECONDS + 2
    assert all(c.message_end_time - c.message_start_time < 10**9 for c in chunk_indexes)
    with path.open("rb") as handle:
        reader = make_reader(handle)
        messages = list(reader.iter_messages(topics=["/scanner/stream"]))
        stats = reader.get_summary().statistics
    assert len(messages) == RATE_HZ * SECONDS and stats.chunk_count == len(chunk_indexes)
    rec = read_recording(path)
    assert rec.warnings == [] and not rec.loss.any and rec.chunks_read == len(chunk_indexes)


def test_size_bounds_a_chunk_within_a_second(tmp_path: Path) -> None:
    path = tmp_path / "big.mcap"
    with RecordingWriter(path, default_rig(), {}, chunk_bytes=4096) as writer:
        for i in range(100):  # 1 KB every ms: 0.1 s of log time, 100 KB
            writer.write_stream("scanner", bytes(1000), schemas.RX, T0 + i * MS)
    with path.open("rb") as handle:
        chunks = make_reader(handle).get_summary().chunk_indexes
    assert len(chunks) >= 20 and all(c.uncompressed_size < 4096 + 1200 for c in chunks)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 7)),
                min_size=1, max_size=8))
def test_each_flipped_byte_loses_at_most_the_chunk_it_hits(
        scan: Any, tmp_path_factory: pytest.TempPathFactory,
        flips: list[tuple[float, int]]) -> None:
    _, data, chunk_indexes = scan
    first = chunk_indexes[0].chunk_start_offset  # header and metadata are not this test's
    mutated = bytearray(data)
    hit: set[int] = set()  # indices of scanner chunks in the MCAP chunks that were hit
    for where, bit in flips:
        offset = first + int(where * (len(data) - first))
        mutated[offset] ^= 1 << bit
        for c in chunk_indexes:
            if c.chunk_start_offset <= offset < c.chunk_start_offset + c.chunk_length:
                step = 10**9 // RATE_HZ
                hit |= set(range((c.message_start_time - T0) // step,
                                 (c.message_end_time - T0) // step + 1))
    damaged = tmp_path_factory.mktemp("flip") / "d.mcap"
    damaged.write_bytes(bytes(mutated))
    rec = read_recording(damaged)
    lost = set(range(RATE_HZ * SECONDS)) - _indices(rec)
    assert lost <= hit  # every chunk not hit is read, wherever the damage is
    assert len(lost) <= RATE_HZ * len(flips)  # at most about 1 s per flipped byte
    assert rec.loss.chunks <= len(flips) and rec.loss.time_s <= len(flips)
    if lost:
        assert rec.loss.any and any("lost" in w for w in rec.warnings)


@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.9])
def test_a_cut_loses_at_most_about_a_second_before_it(scan: Any, tmp_path: Path,
                                                      fraction: float) -> None:
    _, data, chunk_indexes = scan
    cut_at = int(len(data) * fraction)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:cut_at])
    rec = read_recording(cut)
    whole = [c for c in chunk_indexes if c.chunk_start_offset + c.chunk_length <= cut_at]
    kept = _indices(rec)
    assert kept == set(range(len(kept)))  # a prefix: every whole chunk before the cut
    assert T0 + (len(kept) - 1) * (10**9 // RATE_HZ) == whole[-1].message_end_time
    assert rec.loss.chunks <= 1 and rec.loss.time_s <= 1.05 and rec.loss.bytes > 0
    assert not rec.complete


def test_loss_in_info_text_and_json(scan: Any, tmp_path: Path,
                                    cli: Callable[..., Any]) -> None:
    _, data, chunk_indexes = scan
    victim = chunk_indexes[3]
    mutated = bytearray(data)
    mutated[victim.chunk_start_offset + victim.chunk_length - 5] ^= 0x10  # compressed bytes
    damaged = tmp_path / "d.mcap"
    damaged.write_bytes(bytes(mutated))
    info = json.loads(cli("info", damaged, "--json").out)
    assert info["loss"]["chunks"] == 1 and info["loss"]["exact"] is True
    assert info["loss"]["bytes"] == victim.chunk_length
    assert info["loss"]["time_ns"] == victim.message_end_time - victim.message_start_time
    text = cli("info", damaged)
    assert text.code == 0 and "lost        1 chunks" in text.out
    assert "warning     lost 1 chunks" in text.out


# -- full disks and I/O errors ------------------------------------------------------------


class _FailingRaw(io.FileIO):
    """A file whose disk fills up after ``budget`` bytes (or fails with another errno)."""

    def __init__(self, path: Path, budget: int, code: int) -> None:
        super().__init__(path, "wb")
        self.budget, self.code = budget, code

    def write(self, data: Any) -> int:
        if self.budget < len(data):
            raise OSError(self.code, os.strerror(self.code))
        self.budget -= len(data)
        return super().write(data)


FullDisk = Callable[..., list[_FailingRaw]]


@pytest.fixture
def full_disk(monkeypatch: pytest.MonkeyPatch) -> FullDisk:
    """``full_disk(path, budget, errno)``: opening ``path`` for writing gives a file that fails
    after ``budget`` bytes; returns the list the opened raw file is put in."""
    original = Path.open

    def arm(target: Path, budget: int, code: int = errno.ENOSPC) -> list[_FailingRaw]:
        opened: list[_FailingRaw] = []

        def fake_open(self: Path, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
            if self == target and mode == "wb":
                opened.append(_FailingRaw(self, budget, code))
                return io.BufferedWriter(opened[-1])
            return original(self, mode, *args, **kwargs)

        monkeypatch.setattr(Path, "open", fake_open)
        return opened

    return arm


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EIO])
def test_a_failed_write_is_one_error_and_the_file_stays_readable(
        tmp_path: Path, full_disk: FullDisk, code: int) -> None:
    path = tmp_path / "rec.mcap"
    full_disk(path, 12_000, code)
    written = 0
    with pytest.raises(RecordingError) as raised, \
            RecordingWriter(path, default_rig(), {}) as writer:
        for i in range(RATE_HZ * SECONDS):
            writer.write_stream("scanner", _payload(i), schemas.RX, T0 + i * (10**9 // RATE_HZ))
            written += 1
    message = str(raised.value)
    assert message.startswith(f"{path}: cannot be written (errno {errno.errorcode[code]}: ")
    assert "\n" not in message and raised.value.__suppress_context__
    assert raised.value is writer.failed
    with pytest.raises(RecordingError) as again:  # later writes: the same error, no other
        writer.write_event(T0, "x", "y")
    assert again.value is raised.value
    writer.close()  # no second error
    assert 0 < written < RATE_HZ * SECONDS
    rec = read_recording(path)
    kept = _indices(rec)
    assert kept == set(range(len(kept))) and len(kept) >= written - RATE_HZ  # ≤ 1 s lost
    assert not rec.complete


def test_a_failed_fsync_is_one_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "rec.mcap"
    writer = RecordingWriter(path, default_rig(), {})
    writer.write_stream("scanner", b"abc", schemas.RX, T0)

    def no_space(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", no_space)
    with pytest.raises(RecordingError, match=r"rec\.mcap: cannot be written \(errno ENOSPC"):
        writer.flush()
    with pytest.raises(RecordingError, match="ENOSPC"):
        writer.flush()
    writer.close()
    monkeypatch.undo()
    assert read_recording(path).warnings  # what reached the disk reads, with a warning


def test_a_failure_while_closing_is_one_error(tmp_path: Path,
                                              full_disk: FullDisk) -> None:
    path = tmp_path / "rec.mcap"
    opened = full_disk(path, 1 << 30)
    writer = RecordingWriter(path, default_rig(), {})
    for i in range(200):  # 4 s of log time
        writer.write_stream("scanner", _payload(i), schemas.RX, T0 + i * 20 * MS)
    writer.flush()
    opened[0].budget = 100  # the disk fills up: the last chunk fits, the summary does not
    with pytest.raises(RecordingError, match="ENOSPC") as raised:
        writer.close()
    assert raised.value.__suppress_context__
    writer.close()  # idempotent, silent
    assert _indices(read_recording(path))


def test_sink_reports_a_full_disk_once_then_stops(tmp_path: Path,
                                                  full_disk: FullDisk) -> None:
    path = tmp_path / "rec.mcap"
    full_disk(path, 12_000)

    def factory(p: Path, rig: Rig, session: Any) -> RecordingWriter:
        return RecordingWriter(p, rig, session)

    sink = RecordingSink(path, default_rig(), {}, factory)
    for i in range(RATE_HZ * SECONDS):  # driver threads never see the failure
        sink.write_stream("scanner", _payload(i), schemas.RX, T0 + i * (10**9 // RATE_HZ))
    assert sink.failure is not None and "ENOSPC" in str(sink.failure)
    sink.event("recording_end", "ended")  # kept for the summary, not written
    assert sink.stats.events["recording_end"] == 1
    with pytest.raises(RecordingError) as flushed:  # the flush loop learns of it, once
        sink.flush()
    assert flushed.value is sink.failure
    sink.flush()
    sink.close()  # no second error
    kept = _indices(read_recording(path))
    assert kept and kept == set(range(len(kept)))


def test_sink_raises_an_unreported_failure_when_closed(tmp_path: Path,
                                                       full_disk: FullDisk) -> None:
    path = tmp_path / "rec.mcap"
    full_disk(path, 12_000)
    sink = RecordingSink(path, default_rig(), {},
                         lambda p, rig, session: RecordingWriter(p, rig, session))
    for i in range(RATE_HZ * SECONDS):
        sink.write_stream("scanner", _payload(i), schemas.RX, T0 + i * (10**9 // RATE_HZ))
    with pytest.raises(RecordingError, match="ENOSPC"):
        sink.close()
    sink.close()
    # The recorder takes the failure itself (to put it in its summary): no raise then.
    other = RecordingSink(tmp_path / "b.mcap", default_rig(), {},
                          lambda p, rig, session: RecordingWriter(p, rig, session))
    assert other.take_failure() is None
    full_disk(tmp_path / "c.mcap", 12_000)
    third = RecordingSink(tmp_path / "c.mcap", default_rig(), {},
                          lambda p, rig, session: RecordingWriter(p, rig, session))
    for i in range(RATE_HZ * SECONDS):
        third.write_stream("scanner", _payload(i), schemas.RX, T0 + i * (10**9 // RATE_HZ))
    taken = third.take_failure()
    assert taken is not None and "ENOSPC" in str(taken)
    third.flush()
    third.close()
    other.close()


@pytest.fixture
def tiny_fs(tmp_path: Path) -> Iterator[Callable[[int], Path]]:
    """``tiny_fs(kib)``: a real filesystem (tmpfs) of that size, unmounted afterwards."""
    mounts: list[Path] = []

    def mount(kib: int) -> Path:
        target = tmp_path / f"tiny{len(mounts)}"
        target.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(target)],
                       check=True)
        mounts.append(target)
        return target

    try:
        yield mount
    finally:
        for target in mounts:
            subprocess.run(["umount", str(target)], check=True)


def test_simulate_onto_a_full_filesystem_is_one_line(tiny_fs: Callable[[int], Path],
                                                     tmp_path: Path,
                                                     cli: Callable[..., Any]) -> None:
    out = tiny_fs(64) / "scan.mcap"
    result = cli("simulate", "--direct", "--out", out, "--truth", tmp_path / "truth",
                 "--motor-step", "5", "--beam-step", "1", "--no-cameras")
    assert result.code == 1
    # simulate writes under a temporary name (a simulation can be made again): nothing is left
    assert result.err == (f"scanpipe: error: {out}: cannot be written (errno ENOSPC: No space "
                          "left on device); nothing was written and an earlier file of that "
                          "name is unchanged\n")
    assert list(out.parent.iterdir()) == []


def test_record_onto_a_full_filesystem_fails_once_and_keeps_the_data(
        tiny_fs: Callable[[int], Path]) -> None:
    from acquire_helpers import record_against, sim_options

    from scanpipe.sim.emulators import VirtualRig
    from scanpipe.sim.room import box_room
    from scanpipe.stages.decode import DecodeParams, decode_recording

    out = tiny_fs(16) / "rec.mcap"
    # Without echoes (as the recorder recorded before echoes became the default): the 16 KiB
    # disk then fills after the first chunks, not before any of them.
    with VirtualRig(sim_options("ldoem"), speedup=10.0, scene=box_room()) as rig:
        summary = record_against(rig, out, with_echo=False)
    assert summary["status"] == "failed"
    assert summary["reason"] == (f"cannot write the recording: {out}: cannot be written (errno "
                                 "ENOSPC: No space left on device); the recording ends with "
                                 "what reached the disk")
    recording = read_recording(out)
    assert decode_recording(recording, DecodeParams()).tables["profiles"].num_rows > 0


@pytest.mark.parametrize("with_summary", [True, False])
def test_a_zeroed_stretch_loses_only_the_chunks_it_covers(scan: Any, tmp_path: Path,
                                                          with_summary: bool) -> None:
    _, data, chunk_indexes = scan
    a, b = chunk_indexes[3], chunk_indexes[5]
    start = a.chunk_start_offset + 100  # from inside chunk 3 to inside chunk 5
    end = b.chunk_start_offset + 100
    mutated = bytearray(data)
    mutated[start:end] = bytes(end - start)
    if not with_summary:  # a killed writer: no data end, no summary
        mutated = mutated[:chunk_indexes[-1].chunk_start_offset + chunk_indexes[-1].chunk_length]
    damaged = tmp_path / "z.mcap"
    damaged.write_bytes(bytes(mutated))
    rec = read_recording(damaged)
    step = 10**9 // RATE_HZ
    lost = set(range(RATE_HZ * SECONDS)) - _indices(rec)
    assert lost == set(range((a.message_start_time - T0) // step,
                             (b.message_end_time - T0) // step + 1))
    loss = rec.loss
    assert loss.from_summary is with_summary
    if with_summary:
        assert loss.chunks == 3
        assert loss.time_ns == sum(c.message_end_time - c.message_start_time
                                   for c in chunk_indexes[3:6])
    else:  # lower bound on chunks; time between the intact chunks either side
        assert 1 <= loss.chunks <= 3
        assert loss.time_ns == (chunk_indexes[6].message_start_time
                                - chunk_indexes[2].message_end_time)
    assert sum(r.length for r in loss.regions) == loss.bytes >= end - start


def test_a_chunk_of_highly_compressible_data_is_not_taken_for_damage(tmp_path: Path) -> None:
    # A blank 1.5 MB image compresses ~5000:1 in zstd; an earlier guard on the inflation ratio
    # called that chunk damaged and dropped it silently.
    path = tmp_path / "blank.mcap"
    with RecordingWriter(path, default_rig(), {}) as writer:
        writer.write_image("cam0", 1_700_000_000_000_000_000, bytes(1_500_000))
        writer.write_image("cam0", 1_700_000_000_100_000_000, b"\xff\xd8" + bytes(100))
    recording = read_recording(path)
    assert recording.warnings == [] and not recording.loss.any
    assert [len(i.data) for i in recording.images] == [1_500_000, 102]
