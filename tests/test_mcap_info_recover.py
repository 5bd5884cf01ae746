"""``scanpipe info`` on any MCAP file and ``scanpipe recover`` on damaged ones, against files
written by the official ``mcap`` writer and by rosbags, read back by the official reader."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

T0 = 1_700_000_000_000_000_000


def _foreign_mcap(path: Path, messages: int = 300, chunk_size: int = 2048) -> None:
    """An MCAP file as another tool writes it: JSON schema, two topics, an attachment."""
    with path.open("wb") as handle:
        writer = Writer(handle, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        writer.start(profile="", library="other-tool 1.0")
        schema = writer.register_schema("acme.Reading", "jsonschema",
                                        json.dumps({"type": "object"}).encode())
        temp = writer.register_channel("/temperature", "json", schema, {"unit": "C"})
        raw = writer.register_channel("/raw", "application/octet-stream", 0)
        for i in range(messages):
            body = json.dumps({"i": i, "pad": "x" * 40}).encode()
            writer.add_message(temp, T0 + i * 10_000_000, body, T0 + i * 10_000_000 + 1, i)
            if i % 3 == 0:
                writer.add_message(raw, T0 + i * 10_000_000, bytes([i % 256]) * 20,
                                   T0 + i * 10_000_000)
        writer.add_metadata("acme.site", {"name": "yard"})
        writer.add_attachment(T0, T0, "calib.txt", "text/plain", b"fx=1")
        writer.finish()


def test_info_foreign_mcap_lists_channels_schemas_counts(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "other.mcap"
    _foreign_mcap(path, messages=30)
    result = cli("info", path, "--json")
    assert result.code == 0, result.err
    info = json.loads(result.out)
    assert info["recording"] is False
    mcap = info["mcap"]
    by_topic = {c["topic"]: c for c in mcap["channels"]}
    assert by_topic["/temperature"]["messages"] == 30
    assert by_topic["/temperature"]["schema"] == "acme.Reading"
    assert by_topic["/temperature"]["message_encoding"] == "json"
    assert by_topic["/temperature"]["metadata"] == {"unit": "C"}
    assert by_topic["/raw"]["messages"] == 10 and by_topic["/raw"]["schema"] is None
    assert mcap["messages"] == 40 and mcap["complete"]
    assert (mcap["start_ns"], mcap["end_ns"]) == (T0, T0 + 29 * 10_000_000)
    assert mcap["attachments"] == [{"name": "calib.txt", "media_type": "text/plain", "bytes": 4}]
    # The same counts as the official reader's summary.
    with path.open("rb") as handle:
        stats = make_reader(handle).get_summary().statistics  # type: ignore[union-attr]
    assert stats.message_count == mcap["messages"]
    text = cli("info", path)
    assert text.code == 0 and "/temperature" in text.out and "acme.Reading" in text.out
    assert "messages    40" in text.out


def test_info_ros2_mcap_from_rosbags(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    bag = tmp_path / "bag"
    store = get_typestore(Stores.ROS2_HUMBLE)
    string_type = store.types["std_msgs/msg/String"]
    with Ros2Writer(bag, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for i in range(7):
            writer.write(connection, T0 + i, store.serialize_cdr(string_type(data=f"m{i}"),
                                                                 "std_msgs/msg/String"))
    (mcap_file,) = bag.glob("*.mcap")
    result = cli("info", mcap_file, "--json")
    assert result.code == 0, result.err
    mcap = json.loads(result.out)["mcap"]
    assert mcap["profile"] == "ros2"
    (channel,) = mcap["channels"]
    assert (channel["topic"], channel["messages"], channel["message_encoding"]) == (
        "/chatter", 7, "cdr")
    assert channel["schema"] == "std_msgs/msg/String"


def _official_counts(path: Path) -> tuple[int, int]:
    """Messages the official readers get out of a file: (seeking reader, linear reader)."""
    counts = []
    for reader_class in ("seeking", "linear"):
        n = 0
        with path.open("rb") as handle:
            try:
                reader = (make_reader(handle) if reader_class == "seeking"
                          else NonSeekingReader(handle))
                for _ in reader.iter_messages(log_time_order=False):
                    n += 1
            except Exception:  # the official readers raise many types on damage
                pass
        counts.append(n)
    return counts[0], counts[1]


def _chunk_offsets(path: Path) -> list[int]:
    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None
    return sorted(ci.chunk_start_offset for ci in summary.chunk_indexes)


def test_recover_damaged_file_beats_official_readers(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    good = tmp_path / "good.mcap"
    _foreign_mcap(good)
    data = bytearray(good.read_bytes())
    offsets = _chunk_offsets(good)
    assert len(offsets) > 10
    # Damage: one chunk's compressed bytes in the first third hit, and the file cut at 80 %.
    hit = offsets[len(offsets) // 3]
    data[hit + 80:hit + 120] = b"\xff" * 40
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data[:int(len(data) * 0.8)]))
    official_seek, official_linear = _official_counts(damaged)

    fixed = tmp_path / "fixed.mcap"
    result = cli("recover", damaged, "--out", fixed, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    with fixed.open("rb") as handle:  # a valid file: the official seeking reader reads it all
        reader = make_reader(handle)
        recovered = list(reader.iter_messages())
        summary = reader.get_summary()
    assert len(recovered) == report["messages"]
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == report["messages"]
    assert {c.topic for c in summary.channels.values()} == {"/temperature", "/raw"}
    assert {s.name for s in summary.schemas.values()} == {"acme.Reading"}
    assert report["messages"] > max(official_seek, official_linear)
    total = 300 + 100
    assert report["messages"] < total  # something really was lost
    # Every recovered message is byte-identical to the original at the same log time.
    with good.open("rb") as handle:
        original = {(c.topic, m.log_time): m.data
                    for _, c, m in make_reader(handle).iter_messages()}
    for _, channel, message in recovered:
        assert original[(channel.topic, message.log_time)] == message.data
    sequences = [m.sequence for _, c, m in recovered if c.topic == "/temperature"]
    assert np.all(np.diff(sequences) > 0)
    print(f"recovered {report['messages']} of {total}; official seeking reader "
          f"{official_seek}, linear reader {official_linear}")


def test_recover_refuses_existing_out_and_input_as_out(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    source = tmp_path / "in.mcap"
    _foreign_mcap(source, messages=5)
    existing = tmp_path / "fixed.mcap"
    existing.write_bytes(b"keep me")
    result = cli("recover", source, "--out", existing)
    assert result.code == 2
    assert "already exists; pass --force" in result.err
    assert existing.read_bytes() == b"keep me"
    before = source.read_bytes()
    result = cli("recover", source, "--out", source, "--force")
    assert result.code == 2 and "is also an input" in result.err
    assert source.read_bytes() == before
    result = cli("recover", source, "--out", tmp_path / "fixed.txt")
    assert result.code == 2 and "expected a file name ending in .mcap" in result.err


def test_recover_not_an_mcap_file(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello, not an mcap file at all")
    out = tmp_path / "out.mcap"
    result = cli("recover", junk, "--out", out)
    assert result.code != 0
    assert result.err.startswith("scanpipe: error: ") and "not an MCAP file" in result.err
    assert result.err.count("\n") == 1
    assert not out.exists()
    # Only the header survived: nothing to recover, nothing written.
    header_only = tmp_path / "header.mcap"
    with header_only.open("wb") as handle:
        writer = Writer(handle)
        writer.start()
        handle.flush()
        header_only.write_bytes(header_only.read_bytes())
    result = cli("recover", header_only, "--out", out)
    assert result.code != 0 and "nothing to recover" in result.err
    assert not out.exists()
    assert struct.unpack_from("<B", header_only.read_bytes(), 8)[0] == 1  # a header record


def test_info_recording_has_the_generic_catalogue_too(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from scanpipe.sim.direct import simulate_direct
    from scanpipe.sim.options import SimOptions

    recording = tmp_path / "scan.mcap"
    simulate_direct(recording, tmp_path / "truth",
                    SimOptions(motor_step_deg=20.0, beam_step_deg=4.0, cameras=False))
    result = cli("info", recording, "--json")
    assert result.code == 0, result.err
    info = json.loads(result.out)
    assert info["recording"] is True and info["complete"] is True
    by_topic = {c["topic"]: c for c in info["mcap"]["channels"]}
    assert by_topic["/scanner/stream"]["messages"] == info["channels"]["/scanner/stream"][
        "messages"]
    assert by_topic["/motor/state"]["schema"] == "scanpipe.MotorState"
    with recording.open("rb") as handle:
        stats = make_reader(handle).get_summary().statistics  # type: ignore[union-attr]
    assert info["mcap"]["messages"] == stats.message_count
