"""Network captures (pcap, pcapng) of the scanner's TCP link: import-capture and frames.

The fixtures in tests/fixtures/capture were written by dumpcap/tshark/editcap while a real
``scanpipe simulate`` ran (see tests/fixtures/README.md); the synthetic captures here are built
by a small pcap/pcapng writer of the test's own.
"""

from __future__ import annotations

import ipaddress
import random
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from scanpipe.captureio import load_scanner_capture, read_capture, reassemble, tcp_segments
from scanpipe.recording.reader import read_recording
from scanpipe.stages.decode import DecodeParams, decode_recording

FIXTURES = Path(__file__).parent / "fixtures" / "capture"
SIM_MCAP = FIXTURES / "simulate.mcap"
CAPTURES = ["simulate-lo.pcapng", "simulate-lo.pcap", "simulate-any-sll.pcapng"]
SCANNER = ("10.1.2.3", 2111)
HOST = ("10.1.2.9", 50123)


def _profiles(path: Path) -> list[str]:
    """Each profile as text (frame, sector, start angle, ranges; NaN compares equal as text)."""
    table = decode_recording(read_recording(path), DecodeParams()).tables["profiles"]
    frame, sector = table.column("frame").to_pylist(), table.column("sector").to_pylist()
    start = table.column("start_angle_deg").to_pylist()
    ranges = table.column("ranges_m").to_pylist()
    return [repr(row) for row in zip(frame, sector, start, ranges, strict=True)]


# -- captures written by another tool ------------------------------------------------------------


@pytest.mark.parametrize("name", CAPTURES)
def test_import_capture_gives_the_profiles_of_the_simulate_recording(
        name: str, tmp_path: Path, cli: Callable[..., object]) -> None:
    out = tmp_path / "imported.mcap"
    result = cli("import-capture", FIXTURES / name, "--out", out)
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    assert "no motor states" in result.err  # type: ignore[attr-defined]
    imported, simulated = read_recording(out), read_recording(SIM_MCAP)
    for direction in (0, 1):  # both directions, byte for byte
        assert imported.stream("scanner", direction).data == \
            simulated.stream("scanner", direction).data
    got, want = _profiles(out), _profiles(SIM_MCAP)
    assert len(got) == len(want) > 40
    assert got == want
    # Log times are the capture's: within the simulate's own timeline (same host clock).
    times = imported.stream("scanner", 0).log_time_ns
    sim_times = simulated.stream("scanner", 0).log_time_ns
    assert abs(int(times[0]) - int(sim_times[0])) < 50_000_000
    assert np.all(np.diff(times) >= 0)


def test_frames_reads_a_capture_like_the_recording(cli: Callable[..., object]) -> None:
    import json

    from scanpipe.cli.decode import frame_records
    from scanpipe.protocol.registry import StreamDecoder

    result = cli("frames", FIXTURES / "simulate-lo.pcapng", "--json")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    data = json.loads(result.out)  # type: ignore[attr-defined]
    decoder = StreamDecoder("ldoem", "lenient")
    rx = read_recording(SIM_MCAP).stream("scanner", 0).data
    want = frame_records(decoder.feed_frames(rx) + decoder.finish_frames())
    assert data["dialect"] == "ldoem" and data["frames"] == want
    assert data["capture"]["scanner"] == "127.0.0.1:41243"
    assert len(data["requests"]) == 7 and data["requests"][0]["payload_hex"] == "01 01"
    text = cli("frames", FIXTURES / "simulate-lo.pcap")
    assert text.code == 0 and "requests (host → scanner): 7 frames" in text.out  # type: ignore


def test_run_on_an_imported_capture_says_there_are_no_motor_states(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    out = tmp_path / "imported.mcap"
    assert cli("import-capture", FIXTURES / "simulate-lo.pcap", "--out", out).code == 0  # type: ignore
    result = cli("run", out, "--workdir", tmp_path / "w", "-q")
    assert result.code != 0  # type: ignore[attr-defined]
    lines = result.err.strip().splitlines()  # type: ignore[attr-defined]
    assert lines[-1].startswith("scanpipe: error:") and "no motor states" in lines[-1]


# -- a small pcap/pcapng writer for synthetic captures --------------------------------------


def _tcp(src: tuple[str, int], dst: tuple[str, int], seq: int, payload: bytes,
         flags: int = 0x18) -> bytes:
    return struct.pack(">HHIIBBHHH", src[1], dst[1], seq, 0, 5 << 4, flags, 65535, 0, 0) + payload


def _ip(src: str, dst: str, segment: bytes) -> bytes:
    a, b = ipaddress.ip_address(src), ipaddress.ip_address(dst)
    if a.version == 4:
        return struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + len(segment), 0, 0x4000, 64, 6, 0,
                           a.packed, b.packed) + segment
    return struct.pack(">IHBB16s16s", 6 << 28, len(segment), 6, 64, a.packed, b.packed) + segment


def _link(linktype: int, ip: bytes) -> bytes:
    v6 = ip[0] >> 4 == 6
    ethertype = 0x86DD if v6 else 0x0800
    if linktype == 1:  # Ethernet, with a VLAN tag, padded to the 60-byte minimum
        frame = b"\x02" * 6 + b"\x04" * 6 + struct.pack(">HHH", 0x8100, 5, ethertype) + ip
        return frame + b"\0" * max(0, 60 - len(frame))
    if linktype == 113:
        return struct.pack(">HHH8sH", 0, 772, 0, b"", ethertype) + ip
    if linktype == 276:
        return struct.pack(">HHIHBB8s", ethertype, 0, 1, 772, 0, 0, b"") + ip
    if linktype == 0:
        return struct.pack("<I", 30 if v6 else 2) + ip
    return ip  # 101 raw


Packet = tuple[int, bytes]  # (time ns, link frame)


def write_pcap(path: Path, linktype: int, packets: list[Packet], big_endian: bool = False,
               nanoseconds: bool = False) -> None:
    e = ">" if big_endian else "<"
    magic = 0xA1B23C4D if nanoseconds else 0xA1B2C3D4
    out = [struct.pack(e + "IHHiIII", magic, 2, 4, 0, 0, 65535, linktype)]
    for t, frame in packets:
        sec, frac = divmod(t, 1_000_000_000)
        out.append(struct.pack(e + "IIII", sec, frac if nanoseconds else frac // 1000,
                               len(frame), len(frame)) + frame)
    path.write_bytes(b"".join(out))


def write_pcapng(path: Path, linktype: int, packets: list[Packet],
                 big_endian: bool = False) -> None:
    e = ">" if big_endian else "<"

    def block(kind: int, body: bytes) -> bytes:
        body += b"\0" * (-len(body) % 4)
        return struct.pack(e + "II", kind, len(body) + 12) + body + struct.pack(e + "I",
                                                                               len(body) + 12)

    shb = block(0x0A0D0D0A, struct.pack(e + "IHHq", 0x1A2B3C4D, 1, 0, -1))
    tsresol = struct.pack(e + "HH", 9, 1) + b"\x09\0\0\0" + struct.pack(e + "HH", 0, 0)
    idb = block(1, struct.pack(e + "HHI", linktype, 0, 0) + tsresol)
    epbs = [block(6, struct.pack(e + "IIIII", 0, t >> 32, t & 0xFFFFFFFF, len(f), len(f)) + f)
            for t, f in packets]
    path.write_bytes(shb + idb + b"".join(epbs))


def _scanner_bytes() -> bytes:
    return read_recording(SIM_MCAP).stream("scanner", 0).data


def _segments(data: bytes, size: int = 700) -> list[tuple[int, bytes]]:
    """(relative seq, payload) pieces of ``data``."""
    return [(i, data[i:i + size]) for i in range(0, len(data), size)]


def build_capture(path: Path, pieces: list[tuple[int, bytes]], linktype: int = 1,
                  scanner: tuple[str, int] = SCANNER, host: tuple[str, int] = HOST,
                  isn: int = 0xFFFFF000, fmt: str = "pcap", big_endian: bool = False) -> None:
    """A connection (SYN, SYN-ACK, one request, then ``pieces`` from the scanner in the given
    order) written as a capture. ``isn`` near 2^32 makes the sequence numbers wrap."""
    t = 1_700_000_000_000_000_000
    frames = [_tcp(host, scanner, 1000, b"", 0x02), _tcp(scanner, host, isn, b"", 0x12),
              _tcp(host, scanner, 1001, b"\x02USP\0\0\0\x02\x03\x01\x00\x02")]
    senders = [(host, scanner), (scanner, host), (host, scanner)]
    for rel, payload in pieces:
        frames.append(_tcp(scanner, host, (isn + 1 + rel) & 0xFFFFFFFF, payload))
        senders.append((scanner, host))
    packets = [(t + i * 1_000_000, _link(linktype, _ip(s[0], d[0], f)))
               for i, (f, (s, d)) in enumerate(zip(frames, senders, strict=True))]
    if fmt == "pcap":
        write_pcap(path, linktype, packets, big_endian, nanoseconds=big_endian)
    else:
        write_pcapng(path, linktype, packets, big_endian)


# -- reassembly --------------------------------------------------------------------------------


@pytest.mark.parametrize(("linktype", "scanner", "host", "fmt", "big"), [
    (1, SCANNER, HOST, "pcap", False),
    (113, ("fd00::5", 2111), ("fd00::9", 50123), "pcapng", True),  # SLL, IPv6
    (276, SCANNER, HOST, "pcapng", False),  # SLL2
    (0, ("::1", 2111), ("::1", 40000), "pcap", True),  # BSD loopback, IPv6
    (101, SCANNER, HOST, "pcapng", True),  # raw IP
])
def test_link_types_and_ip_versions(linktype: int, scanner: tuple[str, int],
                                    host: tuple[str, int], fmt: str, big: bool,
                                    tmp_path: Path) -> None:
    data = _scanner_bytes()
    path = tmp_path / f"x.{fmt}"
    build_capture(path, _segments(data), linktype, scanner, host, fmt=fmt, big_endian=big)
    scan = load_scanner_capture(path)
    assert scan.received.data == data and not scan.received.gaps
    assert scan.scanner == (str(ipaddress.ip_address(scanner[0])), scanner[1])
    assert scan.dialect == "ldoem" and scan.sent.byte_count == 12


def test_out_of_order_retransmitted_and_overlapping_segments_are_used_once(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    data = _scanner_bytes()
    pieces = _segments(data)
    rng = random.Random(7)
    shuffled = pieces[:]
    rng.shuffle(shuffled)
    extra = [pieces[3], pieces[10], (pieces[5][0] + 100, data[pieces[5][0] + 100:
                                                              pieces[5][0] + 1100])]
    path = tmp_path / "messy.pcap"
    build_capture(path, shuffled + extra)  # the sequence numbers wrap past 2^32 too
    scan = load_scanner_capture(path)
    assert scan.received.data == data
    assert scan.received.gaps == []
    assert scan.received.retransmitted_bytes == len(pieces[3][1]) + len(pieces[10][1]) + 1000
    assert scan.received.out_of_order_segments > 5
    out = tmp_path / "messy.mcap"
    result = cli("import-capture", path, "--out", out)
    assert result.code == 0 and "2,400 bytes retransmitted" in result.out  # type: ignore
    assert _profiles(out) == _profiles(SIM_MCAP)


def test_a_missing_segment_is_a_gap_counted_and_never_joined_silently(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    data = _scanner_bytes()
    pieces = _segments(data)
    lost = pieces.pop(12)
    path = tmp_path / "lossy.pcapng"
    build_capture(path, pieces, fmt="pcapng")
    scan = load_scanner_capture(path)
    assert [(g.offset, g.missing_bytes) for g in scan.received.gaps] == [(lost[0], len(lost[1]))]
    assert scan.received.data == data[:lost[0]] + data[lost[0] + len(lost[1]):]
    out = tmp_path / "lossy.mcap"
    result = cli("import-capture", path, "--out", out)
    assert result.code == 0  # type: ignore[attr-defined]
    assert "1 gaps (700 bytes missing)" in result.out  # type: ignore[attr-defined]
    assert "1 gaps (700 bytes the capture never saw" in result.err  # type: ignore[attr-defined]
    recording = read_recording(out)
    assert recording.stream("scanner", 0).missing_chunks == 1
    assert [e.kind for e in recording.events] == ["capture_gap"]
    decoded = decode_recording(recording, DecodeParams())
    assert decoded.report["gaps"]["missing_stream_chunks"] == 1
    want = _profiles(SIM_MCAP)
    got = _profiles(out)
    # 700 bytes lost touch at most 3 frames of ~400 bytes; no false frame across the gap.
    assert 0 < len(want) - len(got) <= 3
    assert set(got) <= set(want)
    frames = cli("frames", path)
    assert frames.code == 0 and "1 gaps" in frames.out  # type: ignore[attr-defined]


def test_reassemble_without_syn_starts_at_the_lowest_sequence_number() -> None:
    from scanpipe.captureio import Segment

    seg = [Segment(i, HOST, SCANNER, (0xFFFFFFF0 + off) & 0xFFFFFFFF, False, False, False, p, 0)
           for i, (off, p) in enumerate([(10, b"bbbbb"), (0, b"aaaaaaaaaa"), (15, b"cc")])]
    r = reassemble(seg)
    assert r.data == b"aaaaaaaaaabbbbbcc" and r.gaps == [] and r.out_of_order_segments == 1
    assert [t for t, _ in r.chunks] == [1, 1, 2]  # delivered when everything before it was


# -- choosing the stream -----------------------------------------------------------------------


def _two_scanner_streams(path: Path) -> None:
    data = _scanner_bytes()
    t = 1_700_000_000_000_000_000
    packets = []
    for k, (scanner, host) in enumerate([(SCANNER, HOST), (("10.1.2.4", 2112), HOST)]):
        for i, (rel, payload) in enumerate(_segments(data)):
            packets.append((t + (2 * i + k) * 1000,
                            _link(1, _ip(scanner[0], host[0], _tcp(scanner, host, rel, payload)))))
    write_pcap(path, 1, packets)


def test_two_scanner_streams_are_listed_in_one_line(tmp_path: Path,
                                                    cli: Callable[..., object]) -> None:
    path = tmp_path / "two.pcap"
    _two_scanner_streams(path)
    out = tmp_path / "x.mcap"
    result = cli("import-capture", path, "--out", out)
    assert result.code == 2 and not out.exists()  # type: ignore[attr-defined]
    err = result.err.strip()  # type: ignore[attr-defined]
    assert "\n" not in err and "--stream" in err
    assert "10.1.2.3:2111" in err and "10.1.2.4:2112" in err and "21,244 B" in err
    assert cli("import-capture", path, "--out", out, "--port", "2112").code == 0  # type: ignore
    assert read_recording(out).stream("scanner", 0).data == _scanner_bytes()
    again = cli("import-capture", path, "--out", out, "--stream", "10.1.2.3:2111")
    assert again.code == 2 and "already exists" in again.err  # type: ignore[attr-defined]
    assert cli("import-capture", path, "--out", out, "--stream", "10.1.2.3:2111",
               "--force").code == 0  # type: ignore[attr-defined]
    bad = cli("import-capture", path, "--out", out, "--port", "9", "--force")
    assert bad.code == 2 and "no TCP stream" in bad.err  # type: ignore[attr-defined]
    assert read_recording(out).stream("scanner", 0).data == _scanner_bytes()


# -- bad input -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("content", "message"), [
    (b"garbage, not a capture at all", "not a pcap or pcapng capture (it begins 67 61 72"),
    (b"", "not a pcap or pcapng capture"),
    (bytes.fromhex("d4c3b2a1") + b"\0" * 10, "pcap header cut short"),
    (bytes.fromhex("d4c3b2a1020004000000000000000000ffff000001000000")
     + struct.pack("<IIII", 1, 0, 500, 500) + b"x" * 20, "damaged pcap: cut inside packet 1"),
    (bytes.fromhex("0a0d0d0a1c000000ffffffff") + b"\0" * 16, "damaged pcapng"),
])
def test_garbage_capture_is_one_line(content: bytes, message: str, tmp_path: Path,
                                     cli: Callable[..., object]) -> None:
    path = tmp_path / "bad.pcap"
    path.write_bytes(content)
    out = tmp_path / "keep.mcap"
    out.write_bytes(b"valid data")
    result = cli("import-capture", path, "--out", out, "--force")
    err = result.err.strip()  # type: ignore[attr-defined]
    assert result.code == 1 and message in err and "\n" not in err  # type: ignore
    assert err.startswith("scanpipe: error: ") and str(path) in err
    assert out.read_bytes() == b"valid data"  # nothing valid lost
    assert set(tmp_path.iterdir()) == {path, out}  # no partial file left


def test_a_capture_without_tcp_is_one_line(tmp_path: Path, cli: Callable[..., object]) -> None:
    path = tmp_path / "udp.pcap"
    udp = _ip("10.0.0.1", "10.0.0.2", b"\0" * 28)
    udp = udp[:9] + b"\x11" + udp[10:]
    write_pcap(path, 1, [(1, _link(1, udp)), (2, b"\xff" * 60)])
    result = cli("frames", path)
    assert result.code == 1 and "no TCP segments among its 2 packets" in result.err  # type: ignore
    assert "1 other IP, 1 not IP" in result.err  # type: ignore[attr-defined]


def test_a_cut_capture_keeps_the_packets_before_the_cut(tmp_path: Path) -> None:
    path = tmp_path / "cut.pcap"
    build_capture(path, _segments(_scanner_bytes()))
    whole = path.read_bytes()
    path.write_bytes(whole[:-300])
    capture = read_capture(path)
    assert capture.warnings and "cut inside packet" in capture.warnings[0]
    segments, counts = tcp_segments(capture)
    assert counts.tcp == len(segments) > 30


# -- dialect messages ----------------------------------------------------------------------------


def test_explicit_dialect_that_finds_nothing_exits_non_zero(tmp_path: Path,
                                                             cli: Callable[..., object]) -> None:
    result = cli("frames", FIXTURES / "simulate-lo.pcapng", "--dialect", "paper")
    err = result.err.strip()  # type: ignore[attr-defined]
    assert result.code == 1 and "\n" not in err  # type: ignore[attr-defined]
    assert "--dialect paper: no paper frame in its 21244 bytes" in err
    raw = tmp_path / "stream.bin"
    raw.write_bytes(_scanner_bytes())
    assert cli("frames", raw, "--dialect", "paper").code == 1  # type: ignore[attr-defined]
    assert cli("frames", raw, "--dialect", "ldoem").code == 0  # type: ignore[attr-defined]
    decoded = cli("decode", SIM_MCAP, "--out", tmp_path / "d", "--set", "dialect=paper", "-q")
    assert decoded.code == 1  # type: ignore[attr-defined]
    assert "decode.dialect = paper: no frame of it" in decoded.err  # type: ignore[attr-defined]
    assert not list((tmp_path / "d").glob("*.parquet"))


@pytest.mark.parametrize(("head", "what"), [
    (bytes.fromhex("0a0d0d0a"), "pcapng"),
    (b"\x89MCAP0\r\n", "MCAP"),
    (b"#ROSBAG V2.0\n", "ROS 1 bag"),
    (b"SQLite format 3\x00", "ROS 2 bag"),
    (b"\x13\x37" * 40, "not a pcap/pcapng, MCAP or ROS bag container"),
])
def test_auto_detect_failure_says_what_it_saw(head: bytes, what: str, tmp_path: Path,
                                              cli: Callable[..., object]) -> None:
    from scanpipe.errors import ProtocolError
    from scanpipe.protocol.registry import detect_dialect

    with pytest.raises(ProtocolError) as err:
        detect_dialect(head + b"\0" * 64)
    message = str(err.value)
    assert "paper, ldoem, cola_b, cola_a, ldrobot, scip (tried)" in message and what in message
    assert head[:4].hex(" ") in message and "\n" not in message
    if not head.startswith(bytes.fromhex("0a0d0d0a")):
        path = tmp_path / "x.bin"
        path.write_bytes(head + b"\0" * 64)
        result = cli("frames", path)
        assert result.code == 1 and what in result.err  # type: ignore[attr-defined]
