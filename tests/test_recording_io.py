"""The recording format: writer, tolerant reader, damaged files, schemas in sync with schemas/."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from scanpipe.errors import RecordingError
from scanpipe.recording import schemas
from scanpipe.recording.reader import read_recording
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import default_rig, rig_to_toml

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000


def write_sample(path: Path, chunks: int = 200, chunk_bytes: int = 4096) -> bytes:
    """A recording with every channel; returns the scanner RX bytes written."""
    sent = bytearray()
    with RecordingWriter(path, default_rig(), {"mode": "test", "host": "unit"},
                         chunk_bytes=chunk_bytes) as writer:
        for i in range(chunks):
            data = bytes([i % 251]) * (i % 17 + 1)
            sent += data
            writer.write_stream("scanner", data, schemas.RX, T0 + i * 1000)
            if i % 10 == 0:
                writer.write_stream("scanner", b"req", schemas.TX, T0 + i * 1000)
                writer.write_stream("motor", b"P\n", schemas.RX, T0 + i * 1000)
                writer.write_motor_state(T0 + i * 1000, i, i + 10, i % 20 == 0, i * 7)
            if i % 50 == 0:
                writer.write_image("cam0", T0 + i * 1000, b"\xff\xd8fake" + bytes([i]))
        writer.write_event(T0 + 5, "disconnect", "scanner went away", {"retry": 1})
    return bytes(sent)


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    sent = write_sample(path)
    rec = read_recording(path)
    assert rec.warnings == [] and rec.complete
    assert rec.stream("scanner").data == sent
    assert rec.stream("scanner", schemas.TX).data == b"req" * 20
    assert rec.stream("motor").data == b"P\n" * 20
    assert rec.stream("motor", schemas.TX).data == b""
    assert rec.motor.step_count.tolist() == list(range(0, 200, 10))
    assert rec.motor.moving.tolist() == [i % 20 == 0 for i in range(0, 200, 10)]
    assert [(i.camera_id, i.sequence, i.format) for i in rec.images] == [
        ("cam0", k, "jpeg") for k in range(4)]
    assert rec.events[0].kind == "disconnect" and rec.events[0].data == {"retry": 1}
    assert rec.rig_toml == rig_to_toml(default_rig())
    assert rec.rig() == default_rig()
    assert rec.session["mode"] == "test" and rec.session["format_version"] == "1"
    assert rec.profile == "scanpipe"


def test_foxglove_and_mcap_tools_read_it(tmp_path: Path) -> None:
    """The published reader sees the schemas by their exact names and decodes every message."""
    path = tmp_path / "r.mcap"
    write_sample(path, chunks=60)
    with path.open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        names = {s.name for s in reader.get_summary().schemas.values()}
        topics = [channel.topic for _, channel, _, _ in reader.iter_decoded_messages()]
    assert names == {"scanpipe.ByteChunk", "scanpipe.MotorState", "scanpipe.Event",
                     "foxglove.CompressedImage"}
    assert "/camera/cam0/image" in topics and "/motor/state" in topics


def test_file_is_fsynced_while_open(tmp_path: Path) -> None:
    """Data written before the fsync interval elapsed is readable from disk without close()."""
    path = tmp_path / "open.mcap"
    writer = RecordingWriter(path, default_rig(), {}, fsync_interval_s=0.05)
    writer.write_stream("scanner", b"first", schemas.RX, T0)
    time.sleep(0.1)
    writer.write_stream("scanner", b"second", schemas.RX, T0 + 1)
    rec = read_recording(path)
    assert rec.stream("scanner").data == b"firstsecond"
    assert not rec.complete and "incomplete" in rec.warnings[-1]
    writer.close()
    writer.close()  # idempotent
    with pytest.raises(RecordingError, match="write after close"):
        writer.write_stream("scanner", b"x", schemas.RX, T0)


def test_killed_writer_is_read_up_to_its_last_chunk(tmp_path: Path) -> None:
    """A real process writing a recording, killed with SIGKILL."""
    path = tmp_path / "killed.mcap"
    script = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from scanpipe.recording.writer import RecordingWriter\n"
        "from scanpipe.rig import default_rig\n"
        "w = RecordingWriter(Path(sys.argv[1]), default_rig(), {}, fsync_interval_s=0.05)\n"
        "i = 0\n"
        "while True:\n"
        "    w.write_stream('scanner', i.to_bytes(4, 'big'), 0, i)\n"
        "    i += 1\n"
        "    if i == 200: print('ready', flush=True)\n"
        "    time.sleep(0.0005)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline().strip() == b"ready"
    deadline = time.monotonic() + 20
    while len(read_recording(path).stream("scanner").data) < 800:  # fsynced while running
        assert time.monotonic() < deadline, "the writer never made its data durable"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    rec = read_recording(path)
    data = rec.stream("scanner").data
    assert len(data) >= 800 and len(data) % 4 == 0
    numbers = [int.from_bytes(data[i:i + 4], "big") for i in range(0, len(data), 4)]
    assert numbers == list(range(len(numbers)))  # a complete prefix, nothing invented
    assert not rec.complete
    assert any("recording incomplete" in w and "stopped at byte" in w for w in rec.warnings)


def test_cut_at_many_offsets_never_raises_and_keeps_a_prefix(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    sent = write_sample(full, chunks=300, chunk_bytes=512)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    previous = 0
    for offset in range(8, len(data), max(1, len(data) // 150)):
        cut.write_bytes(data[:offset])
        rec = read_recording(cut)
        got = rec.stream("scanner").data
        assert sent.startswith(got)
        assert len(got) >= previous  # more file, never less data
        previous = len(got)
        if rec.complete:  # cut inside the summary section: the data section is whole
            assert got == sent and rec.warnings == []
        else:
            assert any(re.search(r"read \d+ of \d+ bytes", w) for w in rec.warnings)
    assert previous == len(sent)


def test_flipped_bytes_never_raise(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    sent = write_sample(full, chunks=300, chunk_bytes=512)
    data = full.read_bytes()
    damaged = tmp_path / "damaged.mcap"
    lost_something = 0
    for offset in range(8, len(data), max(1, len(data) // 120)):
        for flip in (0x01, 0xFF):
            mutated = bytearray(data)
            mutated[offset] ^= flip
            damaged.write_bytes(bytes(mutated))
            rec = read_recording(damaged)
            got = rec.stream("scanner").data
            if got != sent:
                lost_something += 1
                assert rec.warnings  # damage that changed the result is always reported
    assert lost_something > 0


@pytest.mark.parametrize("damage", ["length", "opcode", "payload"])
def test_a_damaged_chunk_loses_only_itself(tmp_path: Path, damage: str) -> None:
    full = tmp_path / "full.mcap"
    sent = write_sample(full, chunks=300, chunk_bytes=512)
    with full.open("rb") as handle:
        chunks = make_reader(handle).get_summary().chunk_indexes
    assert len(chunks) > 6
    victim = chunks[len(chunks) // 2]
    mutated = bytearray(full.read_bytes())
    at = victim.chunk_start_offset
    if damage == "length":
        mutated[at + 1:at + 9] = (2**40).to_bytes(8, "little")
    elif damage == "opcode":
        mutated[at] = 0x7F
    else:
        mutated[at + 9 + 60] ^= 0xFF  # inside the compressed records
    (tmp_path / "d.mcap").write_bytes(bytes(mutated))
    rec = read_recording(tmp_path / "d.mcap")
    got = rec.stream("scanner").data
    if damage == "payload":
        assert rec.stream("scanner").missing_chunks > 0
        assert len(sent) - 300 < len(got) < len(sent)
        assert got.endswith(sent[-40:])  # the chunks after the damage are read
        assert any("damaged" in w for w in rec.warnings)
        assert rec.loss.chunks == 1 and rec.loss.from_summary
        assert rec.loss.bytes == victim.chunk_length  # the chunk record, not its indexes
        assert rec.loss.time_ns == victim.message_end_time - victim.message_start_time
    else:  # a damaged record header: the chunk is still found by its fields and its CRC
        assert got == sent
        assert any("recovered by its CRC" in w for w in rec.warnings)
        assert rec.loss.chunks == 0 and rec.chunks_read == len(chunks)


def test_not_a_recording(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="not found"):
        read_recording(tmp_path / "missing.mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(RecordingError, match="not an MCAP recording"):
        read_recording(tmp_path / "empty.mcap")
    (tmp_path / "text.mcap").write_text("hello, this is not MCAP")
    with pytest.raises(RecordingError, match="bad magic"):
        read_recording(tmp_path / "text.mcap")
    with pytest.raises(RecordingError, match="directory"):
        read_recording(tmp_path)


def test_writer_refuses_bad_arguments(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "w.mcap", default_rig(), {}) as writer:
        with pytest.raises(RecordingError, match="link 'camera'"):
            writer.write_stream("camera", b"x", 0, T0)  # type: ignore[arg-type]
        with pytest.raises(RecordingError, match="direction 2"):
            writer.write_stream("scanner", b"x", 2, T0)
    with pytest.raises(RecordingError, match=r"w\.mcap: cannot be created \(errno ENOENT: "):
        RecordingWriter(tmp_path / "no" / "dir" / "w.mcap", default_rig(), {})
    for name, value in [("chunk_s", 0.0), ("chunk_bytes", 0), ("fsync_interval_s", -1.0)]:
        with pytest.raises(RecordingError, match=rf"^{name} {value!r}: must be > 0$"):
            RecordingWriter(tmp_path / "x.mcap", default_rig(), {}, **{name: value})
        assert not (tmp_path / "x.mcap").exists()  # refused before the file is created


def _normalized(text: str) -> list[str]:
    lines = (re.sub(r"//.*", "", line).strip() for line in text.splitlines())
    return [re.sub(r"\s+", " ", line) for line in lines if line]


@pytest.mark.parametrize(("proto_file", "builder"), [
    ("schemas/scanpipe/recording.proto", schemas.scanpipe_file),
    ("schemas/foxglove/CompressedImage.proto", schemas.foxglove_file),
])
def test_proto_files_match_the_descriptors_in_code(proto_file: str, builder: object) -> None:
    text = (ROOT / proto_file).read_text()
    assert callable(builder)
    assert _normalized(text) == _normalized(schemas.proto_source(builder()))


def test_stream_seq_numbers_are_per_link_and_direction(tmp_path: Path) -> None:
    path = tmp_path / "seq.mcap"
    with RecordingWriter(path, default_rig(), {}) as writer:
        for i in range(3):
            writer.write_stream("scanner", b"a", schemas.RX, T0 + i)
            writer.write_stream("scanner", b"b", schemas.TX, T0 + i)
            writer.write_stream("motor", b"c", schemas.RX, T0 + i)
    with path.open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        seen = [(c.topic, m.direction, m.seq) for _, c, _, m in reader.iter_decoded_messages()]
    assert sorted(seen) == sorted(
        [(t, d, s) for s in range(3) for t, d in
         (("/scanner/stream", 0), ("/scanner/stream", 1), ("/motor/stream", 0))])
    assert os.path.getsize(path) > 0


def test_a_recording_made_before_a_stricter_rig_check_still_reads(tmp_path: Path) -> None:
    """A rig stored in a recording holds what was accepted when it was made: a principal point
    outside the image (a ROS ROI crop; refused for new rig files since the check tightened)
    does not make the recording unreadable, while a rig file with it is still refused."""
    from scanpipe.errors import RigError
    from scanpipe.rig import RECORDED, rig_from_dict, rig_from_toml, rig_to_dict

    data = rig_to_dict(default_rig())
    data["cameras"][0]["cx"] = -40.0
    with pytest.raises(RigError, match="cx = -40"):
        rig_from_dict(data, "new.toml")
    rig = rig_from_dict(data, "old", context=RECORDED)
    path = tmp_path / "old.mcap"
    with RecordingWriter(path, rig, {}):
        pass
    rec = read_recording(path)
    assert rec.rig().cameras[0].cx == -40.0
    with pytest.raises(RigError, match="cx = -40"):
        rig_from_toml(rec.rig_toml or "", "rig check")
