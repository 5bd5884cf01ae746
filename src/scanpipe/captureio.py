"""Network captures (pcap, pcapng) of a scanner's TCP link: packets, TCP streams, reassembly.

A small reader of its own (pcap and pcapng are simple, and every length is checked against the
bytes that are there, so a damaged file is one line naming it): both byte orders, micro- and
nanosecond pcap, pcapng with several sections and interfaces (``if_tsresol``, ``if_tsoffset``);
link types Ethernet (with VLAN tags), Linux cooked SLL and SLL2, raw IP and BSD loopback (null
and OpenBSD loop); IPv4 and IPv6 (extension headers walked). Fragmented IP is counted, not
reassembled.

Each TCP connection is reassembled per direction by sequence number: a retransmission or an
overlap is used once, out-of-order segments are put in order, and a hole (a segment the capture
never saw) is a :class:`Gap` — counted and reported, never silently joined. A chunk of the
reassembled stream carries the capture time at which it could be delivered in order (the latest
capture time of it and of everything before it).
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from scanpipe.errors import ProtocolError, UsageError
from scanpipe.protocol.registry import DIALECTS, StreamDecoder
from scanpipe.recording.schemas import RX, TX
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import Rig

PCAP_MAGICS = {b"\xd4\xc3\xb2\xa1": ("<", 1_000), b"\xa1\xb2\xc3\xd4": (">", 1_000),
               b"\x4d\x3c\xb2\xa1": ("<", 1), b"\xa1\xb2\x3c\x4d": (">", 1)}
PCAPNG_MAGIC = b"\x0a\x0d\x0d\x0a"
#: Link types read (LINKTYPE_* numbers of the tcpdump.org list).
LINKTYPES = {0: "null (BSD loopback)", 1: "Ethernet", 12: "raw IP", 101: "raw IP",
             108: "OpenBSD loop", 113: "Linux cooked (SLL)", 228: "raw IPv4", 229: "raw IPv6",
             276: "Linux cooked v2 (SLL2)"}
_PCAPNG_SHB, _PCAPNG_IDB, _PCAPNG_PB, _PCAPNG_SPB, _PCAPNG_EPB = 0x0A0D0D0A, 1, 2, 3, 6
_MAX_BLOCK_BYTES = 1 << 28
#: How many bytes of each direction auto-detection decodes.
_DETECT_BYTES = 1 << 20


class CaptureError(ProtocolError):
    """A network capture could not be read or holds no usable scanner stream."""


def is_capture(head: bytes) -> bool:
    """Whether the first bytes of a file are a pcap or pcapng header."""
    return head[:4] in PCAP_MAGICS or head[:4] == PCAPNG_MAGIC


@dataclass(frozen=True)
class Packet:
    """One captured packet: capture time (ns since the epoch), link type, captured bytes, and
    whether the capture cut it short (snap length)."""

    time_ns: int
    linktype: int
    data: bytes
    truncated: bool


@dataclass
class Capture:
    """The packets of a capture file and what was skipped while reading it."""

    path: Path
    kind: str  # "pcap" or "pcapng"
    packets: list[Packet]
    warnings: list[str] = field(default_factory=list)


def read_capture(path: Path) -> Capture:
    """Read a pcap or pcapng file; :class:`CaptureError` (one line naming it) if it is neither or
    is damaged before its first packet. A cut at the end is a warning: the packets before it
    are kept."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise UsageError(f"{path}: cannot be read ({err.strerror or err})") from None
    if data[:4] in PCAP_MAGICS:
        return _read_pcap(path, data)
    if data[:4] == PCAPNG_MAGIC:
        return _read_pcapng(path, data)
    raise CaptureError(f"{path}: not a pcap or pcapng capture (it begins {data[:8].hex(' ')}"
                       f"{'' if data else '<empty>'})")


def _read_pcap(path: Path, data: bytes) -> Capture:
    endian, ns_per_frac = PCAP_MAGICS[data[:4]]
    if len(data) < 24:
        raise CaptureError(f"{path}: pcap header cut short ({len(data)} of 24 bytes)")
    _, _, _, _, snaplen, network = struct.unpack_from(endian + "HHiIII", data, 4)
    linktype = network & 0x0FFFFFFF  # the upper bits may carry FCS information
    capture = Capture(path, "pcap", [])
    offset = 24
    while offset < len(data):
        if offset + 16 > len(data):
            capture.warnings.append(f"{path}: cut inside a packet header at byte {offset}; "
                                    f"{len(capture.packets)} packets read")
            break
        sec, frac, incl, orig = struct.unpack_from(endian + "IIII", data, offset)
        if incl > max(snaplen, 1 << 18) or offset + 16 + incl > len(data):
            if offset + 16 + incl > len(data) and incl <= max(snaplen, 1 << 18):
                what = f"cut inside packet {len(capture.packets) + 1}"
            else:
                what = f"packet {len(capture.packets) + 1} claims {incl} bytes"
            if not capture.packets:
                raise CaptureError(f"{path}: damaged pcap: {what} (byte {offset})")
            capture.warnings.append(f"{path}: {what} at byte {offset}; "
                                    f"{len(capture.packets)} packets read")
            break
        capture.packets.append(Packet(sec * 1_000_000_000 + frac * ns_per_frac, linktype,
                                      data[offset + 16:offset + 16 + incl], incl < orig))
        offset += 16 + incl
    return capture


@dataclass
class _Interface:
    linktype: int
    snaplen: int
    ns_num: int = 1_000  # timestamp unit in ns = ns_num / ns_den (default: microseconds)
    ns_den: int = 1
    offset_s: int = 0


def _read_pcapng(path: Path, data: bytes) -> Capture:
    capture = Capture(path, "pcapng", [])
    endian = "<"
    interfaces: list[_Interface] = []
    offset = 0
    while offset < len(data):
        if offset + 12 > len(data):
            _pcapng_cut(capture, f"cut inside a block header at byte {offset}")
            break
        if data[offset:offset + 4] == PCAPNG_MAGIC:
            bom = data[offset + 8:offset + 12]
            if bom not in (b"\x4d\x3c\x2b\x1a", b"\x1a\x2b\x3c\x4d"):
                raise CaptureError(f"{path}: damaged pcapng: section header at byte {offset} "
                                   f"has byte-order magic {bom.hex(' ')}")
            endian = "<" if bom == b"\x4d\x3c\x2b\x1a" else ">"
            interfaces = []
        block_type, length = struct.unpack_from(endian + "II", data, offset)
        if length < 12 or length % 4 or length > _MAX_BLOCK_BYTES or offset + length > len(data):
            _pcapng_cut(capture, f"block at byte {offset} claims {length} bytes "
                                 f"({len(data) - offset} left)")
            break
        body = data[offset + 8:offset + length - 4]
        try:
            if block_type == _PCAPNG_IDB:
                interfaces.append(_interface(body, endian))
            elif block_type in (_PCAPNG_EPB, _PCAPNG_PB):
                capture.packets.append(_enhanced_packet(body, endian, interfaces,
                                                        block_type == _PCAPNG_PB))
            elif block_type == _PCAPNG_SPB:
                if not interfaces:
                    raise struct.error("simple packet before any interface")
                (orig,) = struct.unpack_from(endian + "I", body, 0)
                iface = interfaces[0]
                cap = min(orig, iface.snaplen or orig, len(body) - 4)
                last = capture.packets[-1].time_ns if capture.packets else 0
                capture.packets.append(Packet(last, iface.linktype, body[4:4 + cap], cap < orig))
        except (struct.error, IndexError) as err:
            _pcapng_cut(capture, f"block at byte {offset} is damaged ({err})")
            break
        offset += length
    return capture


def _pcapng_cut(capture: Capture, what: str) -> None:
    if not capture.packets:
        raise CaptureError(f"{capture.path}: damaged pcapng: {what}")
    capture.warnings.append(f"{capture.path}: {what}; {len(capture.packets)} packets read")


def _interface(body: bytes, endian: str) -> _Interface:
    linktype, _, snaplen = struct.unpack_from(endian + "HHI", body, 0)
    iface = _Interface(linktype, snaplen)
    pos = 8
    while pos + 4 <= len(body):
        code, size = struct.unpack_from(endian + "HH", body, pos)
        value = body[pos + 4:pos + 4 + size]
        if code == 0:
            break
        if code == 9 and size >= 1:  # if_tsresol: 10^-v s, or 2^-v s with the high bit
            v = value[0]
            if v & 0x80:
                iface.ns_num, iface.ns_den = 1_000_000_000, 1 << (v & 0x7F)
            else:
                iface.ns_num, iface.ns_den = (10 ** (9 - v), 1) if v <= 9 else (1, 10 ** (v - 9))
        elif code == 14 and size >= 8:  # if_tsoffset: seconds added to every timestamp
            (iface.offset_s,) = struct.unpack_from(endian + "q", value, 0)
        pos += 4 + size + (-size % 4)
    return iface


def _enhanced_packet(body: bytes, endian: str, interfaces: list[_Interface],
                     obsolete: bool) -> Packet:
    if obsolete:
        iface_id, _, high, low, cap, orig = struct.unpack_from(endian + "HHIIII", body, 0)
    else:
        iface_id, high, low, cap, orig = struct.unpack_from(endian + "IIIII", body, 0)
    if iface_id >= len(interfaces):
        raise IndexError(f"packet names interface {iface_id}, {len(interfaces)} described")
    if 20 + cap > len(body):
        raise struct.error(f"packet claims {cap} bytes, block holds {len(body) - 20}")
    iface = interfaces[iface_id]
    ticks = (high << 32) | low
    time_ns = ticks * iface.ns_num // iface.ns_den + iface.offset_s * 1_000_000_000
    return Packet(time_ns, iface.linktype, body[20:20 + cap], cap < orig)


# -- IP and TCP -------------------------------------------------------------------------------

Endpoint = tuple[str, int]


@dataclass(frozen=True)
class Segment:
    """One TCP segment: endpoints, sequence number, flags, payload and capture time."""

    time_ns: int
    src: Endpoint
    dst: Endpoint
    seq: int
    syn: bool
    fin: bool
    rst: bool
    payload: bytes
    missing_bytes: int  # payload bytes the capture cut off (snap length)


@dataclass
class PacketCounts:
    """What the packets of a capture were, for the report."""

    packets: int = 0
    tcp: int = 0
    other_ip: int = 0  # UDP, ICMP … (not TCP)
    not_ip: int = 0  # ARP, other link payloads
    fragments: int = 0  # fragmented IP: not reassembled
    unknown_linktype: dict[int, int] = field(default_factory=dict)
    malformed: int = 0

    def as_dict(self) -> dict[str, object]:
        """Plain data for reports and ``--json``."""
        return {"packets": self.packets, "tcp": self.tcp, "other_ip": self.other_ip,
                "not_ip": self.not_ip, "fragments": self.fragments, "malformed": self.malformed,
                "unknown_linktypes": {str(k): v for k, v in self.unknown_linktype.items()}}


def _ip_payload(linktype: int, frame: bytes) -> tuple[int, bytes] | None:
    """(IP version, IP packet) of a link-layer frame, or None when it carries no IP."""
    ethertype: int | None
    if linktype == 1:
        if len(frame) < 14:
            return None
        ethertype, pos = struct.unpack_from(">H", frame, 12)[0], 14
        while ethertype in (0x8100, 0x88A8, 0x9100) and len(frame) >= pos + 4:
            ethertype, pos = struct.unpack_from(">H", frame, pos + 2)[0], pos + 4
        packet = frame[pos:]
    elif linktype == 113:
        if len(frame) < 16:
            return None
        ethertype, packet = struct.unpack_from(">H", frame, 14)[0], frame[16:]
    elif linktype == 276:
        if len(frame) < 20:
            return None
        ethertype, packet = struct.unpack_from(">H", frame, 0)[0], frame[20:]
    elif linktype in (0, 108):
        if len(frame) < 4:
            return None
        family = {struct.unpack_from(order + "I", frame, 0)[0] for order in "<>"}
        ethertype = 0x0800 if 2 in family else 0x86DD if family & {10, 24, 28, 30} else None
        packet = frame[4:]
    elif linktype in (12, 101, 228, 229):
        ethertype, packet = None, frame
    else:
        raise KeyError(linktype)
    if ethertype is not None and ethertype not in (0x0800, 0x86DD):
        return None
    if not packet:
        return None
    version = packet[0] >> 4
    return (version, packet) if version in (4, 6) else None


def _tcp_of(version: int, packet: bytes, counts: PacketCounts
            ) -> tuple[str, str, bytes, int] | None:
    """(source address, destination address, TCP segment, bytes cut off) or None."""
    if version == 4:
        if len(packet) < 20:
            counts.malformed += 1
            return None
        ihl = (packet[0] & 0x0F) * 4
        total, frag, proto = (struct.unpack_from(">H", packet, 2)[0],
                              struct.unpack_from(">H", packet, 6)[0], packet[9])
        if ihl < 20 or total < ihl:
            counts.malformed += 1
            return None
        if frag & 0x3FFF:  # more fragments, or an offset
            counts.fragments += 1
            return None
        if proto != 6:
            counts.other_ip += 1
            return None
        src = str(ipaddress.IPv4Address(packet[12:16]))
        dst = str(ipaddress.IPv4Address(packet[16:20]))
        end = total if total else len(packet)  # 0: TCP segmentation offload, length unknown
        return src, dst, packet[ihl:end], max(0, end - len(packet))
    if len(packet) < 40:
        counts.malformed += 1
        return None
    length, nxt = struct.unpack_from(">H", packet, 4)[0], packet[6]
    src = str(ipaddress.IPv6Address(packet[8:24]))
    dst = str(ipaddress.IPv6Address(packet[24:40]))
    end = 40 + length if length else len(packet)
    pos = 40
    while nxt in (0, 43, 60):  # hop-by-hop, routing, destination options
        if len(packet) < pos + 8:
            counts.malformed += 1
            return None
        nxt, pos = packet[pos], pos + (packet[pos + 1] + 1) * 8
    if nxt == 44:
        counts.fragments += 1
        return None
    if nxt != 6:
        counts.other_ip += 1
        return None
    return src, dst, packet[pos:end], max(0, end - len(packet))


def tcp_segments(capture: Capture) -> tuple[list[Segment], PacketCounts]:
    """Every TCP segment of the capture, in capture order, and what the other packets were."""
    counts = PacketCounts(packets=len(capture.packets))
    segments: list[Segment] = []
    for packet in capture.packets:
        try:
            ip = _ip_payload(packet.linktype, packet.data)
        except KeyError:
            counts.unknown_linktype[packet.linktype] = counts.unknown_linktype.get(
                packet.linktype, 0) + 1
            continue
        if ip is None:
            counts.not_ip += 1
            continue
        tcp = _tcp_of(*ip, counts)
        if tcp is None:
            continue
        src, dst, seg, cut = tcp
        if len(seg) < 20 or (seg[12] >> 4) * 4 < 20 or (seg[12] >> 4) * 4 > len(seg):
            counts.malformed += 1
            continue
        sport, dport, seq = struct.unpack_from(">HHI", seg, 0)
        flags = seg[13]
        counts.tcp += 1
        segments.append(Segment(packet.time_ns, (src, sport), (dst, dport), seq,
                                bool(flags & 0x02), bool(flags & 0x01), bool(flags & 0x04),
                                seg[(seg[12] >> 4) * 4:], cut))
    return segments, counts


# -- streams and reassembly -------------------------------------------------------------------


@dataclass(frozen=True)
class Gap:
    """Bytes of a direction the capture never saw: at ``offset`` of the reassembled stream."""

    offset: int
    missing_bytes: int
    time_ns: int


@dataclass
class Reassembled:
    """One direction of a TCP connection in order: chunks with delivery times, gaps, counts."""

    chunks: list[tuple[int, bytes]]  # (capture time ns, bytes), in stream order
    gaps: list[Gap]
    retransmitted_bytes: int  # bytes seen again (retransmissions, overlaps): used once
    out_of_order_segments: int

    @property
    def data(self) -> bytes:
        """The reassembled bytes (gaps left out: see :attr:`gaps`)."""
        return b"".join(chunk for _, chunk in self.chunks)

    @property
    def byte_count(self) -> int:
        """How many bytes were reassembled."""
        return sum(len(chunk) for _, chunk in self.chunks)


def reassemble(segments: Sequence[Segment]) -> Reassembled:
    """Put one direction's segments in sequence order (see the module notes)."""
    syn = next((s for s in segments if s.syn), None)
    data_segments = [s for s in segments if s.payload]  # a cut segment: what was kept
    if not data_segments:
        return Reassembled([], [], 0, 0)
    ref = syn.seq + 1 if syn is not None else data_segments[0].seq

    def relative(seq: int) -> int:  # sequence numbers wrap at 2^32: signed distance from ref
        d = (seq - ref) & 0xFFFFFFFF
        return d - (1 << 32) if d >= 1 << 31 else d

    out_of_order = 0
    highest = None
    for s in data_segments:
        rel = relative(s.seq)
        if highest is not None and rel < highest:
            out_of_order += 1
        highest = rel + len(s.payload) if highest is None else max(highest,
                                                                   rel + len(s.payload))
    ordered = sorted(data_segments, key=lambda s: (relative(s.seq), s.time_ns))
    following = 0 if syn is not None else relative(ordered[0].seq)
    chunks: list[tuple[int, bytes]] = []
    gaps: list[Gap] = []
    retransmitted = 0
    delivered = 0  # bytes handed out so far
    latest_ns = 0
    for s in ordered:
        start = relative(s.seq)
        end = start + len(s.payload)
        if end <= following:
            retransmitted += len(s.payload)
            continue
        if start > following:
            gaps.append(Gap(delivered, start - following, s.time_ns))
            start_in = 0
        else:
            start_in = following - start
            retransmitted += start_in
        latest_ns = max(latest_ns, s.time_ns)
        piece = s.payload[start_in:]
        chunks.append((latest_ns, piece))
        delivered += len(piece)
        following = end
    return Reassembled(chunks, gaps, retransmitted, out_of_order)


@dataclass
class TcpStream:
    """One TCP connection: its two endpoints (``a`` opened it when the SYN was seen) and its
    segments per direction (``a → b`` and ``b → a``)."""

    index: int
    a: Endpoint
    b: Endpoint
    a_to_b: list[Segment] = field(default_factory=list)
    b_to_a: list[Segment] = field(default_factory=list)
    syn_seen: bool = False

    def payload_bytes(self, src: Endpoint) -> int:
        """Payload bytes (with repeats) sent by ``src``."""
        return sum(len(s.payload) for s in (self.a_to_b if src == self.a else self.b_to_a))

    def describe(self) -> str:
        """``#1 10.0.0.2:50000 ↔ 10.0.0.5:2111 (180 B →, 25,310 B ←)``."""
        return (f"#{self.index} {format_endpoint(self.a)} ↔ {format_endpoint(self.b)} "
                f"({self.payload_bytes(self.a):,} B →, {self.payload_bytes(self.b):,} B ←)")


def format_endpoint(endpoint: Endpoint) -> str:
    """``host:port``, IPv6 hosts in brackets."""
    host, port = endpoint
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def tcp_streams(segments: Sequence[Segment]) -> list[TcpStream]:
    """The TCP connections of a capture in order of first appearance. A SYN on a 4-tuple that
    already carried data (a port reused) starts a new connection."""
    streams: list[TcpStream] = []
    current: dict[frozenset[Endpoint], TcpStream] = {}
    for s in segments:
        key = frozenset((s.src, s.dst))
        stream = current.get(key)
        if s.syn and stream is not None and (stream.a_to_b or stream.b_to_a):
            opening_ack = stream.syn_seen and s.src == stream.b  # the SYN-ACK of this one
            if not opening_ack and any(x.payload for x in stream.a_to_b + stream.b_to_a):
                stream = None
        if stream is None:
            # The SYN without ACK comes from the client; otherwise the first sender is 'a'.
            stream = TcpStream(len(streams) + 1, s.src, s.dst, syn_seen=s.syn)
            streams.append(stream)
            current[key] = stream
        (stream.a_to_b if s.src == stream.a else stream.b_to_a).append(s)
    return streams


def parse_endpoint(text: str) -> Endpoint:
    """``HOST:PORT`` or ``[V6HOST]:PORT`` as an endpoint (the host normalised); UsageError."""
    host, sep, port = text.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")
    try:
        if not sep or not host:
            raise ValueError(text)
        number = int(port)
        if not 0 < number < 65536:
            raise ValueError(port)
        return str(ipaddress.ip_address(host)), number
    except ValueError:
        raise UsageError(f"--stream {text!r}: expected HOST:PORT of the scanner (an IP address, "
                         "IPv6 in brackets: [::1]:2111)") from None


# -- the scanner's stream ---------------------------------------------------------------------


@dataclass
class ScannerCapture:
    """The scanner's connection in a capture: who is who, both directions reassembled."""

    path: Path
    kind: str
    stream: TcpStream
    scanner: Endpoint
    host: Endpoint
    received: Reassembled  # scanner → host (RX)
    sent: Reassembled  # host → scanner (TX)
    dialect: str | None  # the dialect whose profiles the received bytes hold, if any
    counts: PacketCounts
    warnings: list[str]

    def summary(self) -> dict[str, object]:
        """Plain data for reports and ``--json``."""
        def side(r: Reassembled) -> dict[str, object]:
            return {"bytes": r.byte_count, "chunks": len(r.chunks), "gaps": len(r.gaps),
                    "missing_bytes": sum(g.missing_bytes for g in r.gaps),
                    "retransmitted_bytes": r.retransmitted_bytes,
                    "out_of_order_segments": r.out_of_order_segments}
        return {"capture": str(self.path), "format": self.kind,
                "stream": self.stream.describe(), "scanner": format_endpoint(self.scanner),
                "host": format_endpoint(self.host), "dialect": self.dialect,
                "received": side(self.received), "sent": side(self.sent),
                "packets": self.counts.as_dict(), "warnings": self.warnings}


def _profile_dialect(data: bytes) -> tuple[str | None, int]:
    """The dialect whose profile frames ``data`` holds most of, and how many (lenient)."""
    best: tuple[str | None, int] = (None, 0)
    for name, dialect in DIALECTS.items():
        decoder = StreamDecoder(dialect, "lenient")
        decoder.feed(data[:_DETECT_BYTES])
        decoder.finish()
        if decoder.counters.frames_decoded > best[1]:
            best = (name, decoder.counters.frames_decoded)
    return best


def _choose(path: Path, streams: list[TcpStream], port: int | None, endpoint: Endpoint | None
            ) -> tuple[TcpStream, Endpoint]:
    """The scanner's stream and the scanner's endpoint in it."""
    listing = "; ".join(s.describe() for s in streams)
    if endpoint is not None:
        found = [s for s in streams if endpoint in (s.a, s.b)]
        if not found:
            raise UsageError(f"--stream {format_endpoint(endpoint)}: no TCP stream of {path} has "
                             f"that endpoint; its streams: {listing}")
        if len(found) > 1:  # the same endpoint in several connections: the one with most bytes
            found.sort(key=lambda s: -s.payload_bytes(endpoint))
        return found[0], endpoint
    if port is not None:
        found = [s for s in streams if port in (s.a[1], s.b[1])]
        if not found:
            raise UsageError(f"--port {port}: no TCP stream of {path} uses that port; its "
                             f"streams: {listing}")
        ends = {(s.a if s.a[1] == port else s.b) for s in found}
        if len(found) > 1 and len(ends) > 1:
            raise UsageError(f"--port {port}: {len(found)} TCP streams of {path} use that port; "
                             f"pick one with --stream HOST:PORT: "
                             + "; ".join(s.describe() for s in found))
        best = max(found, key=lambda s: s.payload_bytes(s.a if s.a[1] == port else s.b))
        return best, best.a if best.a[1] == port else best.b
    hits: list[tuple[TcpStream, Endpoint, int]] = []
    for s in streams:
        for src, segs in ((s.a, s.a_to_b), (s.b, s.b_to_a)):
            name, count = _profile_dialect(reassemble(segs).data)
            if name is not None:
                hits.append((s, src, count))
    if not hits:
        raise CaptureError(f"{path}: no TCP stream holds frames of {', '.join(DIALECTS)}; pick "
                           f"the scanner's with --port N or --stream HOST:PORT; its streams: "
                           f"{listing or 'none'}")
    if len({id(h[0]) for h in hits}) > 1:
        raise UsageError(f"{path}: {len(hits)} TCP streams hold scanner frames; pick one with "
                         "--stream HOST:PORT (the scanner's end): "
                         + "; ".join(h[0].describe() for h in hits))
    stream, src, _ = max(hits, key=lambda h: h[2])
    return stream, src


def load_scanner_capture(path: Path, port: int | None = None,
                         endpoint: Endpoint | None = None) -> ScannerCapture:
    """Read a capture and reassemble the scanner's TCP stream (chosen as
    :func:`scanpipe.captureio` describes: by decodable frames, ``port`` or ``endpoint``)."""
    if port is not None and endpoint is not None:
        raise UsageError("--port and --stream: give one of them")
    if port is not None and not 0 < port < 65536:
        raise UsageError(f"--port {port}: allowed 1…65535")
    capture = read_capture(path)
    segments, counts = tcp_segments(capture)
    warnings = list(capture.warnings)
    if counts.unknown_linktype:
        names = ", ".join(str(k) for k in counts.unknown_linktype)
        warnings.append(f"{path}: {sum(counts.unknown_linktype.values())} packets of link "
                        f"types {names} skipped (read: "
                        f"{', '.join(sorted(set(LINKTYPES.values())))})")
    if counts.fragments:
        warnings.append(f"{path}: {counts.fragments} fragmented IP packets skipped (not "
                        "reassembled)")
    if not segments:
        kinds = sorted({p.linktype for p in capture.packets})
        raise CaptureError(f"{path}: no TCP segments among its {counts.packets} packets "
                           f"(link types {', '.join(map(str, kinds)) or 'none'}; "
                           f"{counts.other_ip} other IP, {counts.not_ip} not IP, "
                           f"{counts.malformed} malformed)")
    streams = tcp_streams(segments)
    stream, scanner = _choose(path, streams, port, endpoint)
    host = stream.b if scanner == stream.a else stream.a
    received = reassemble(stream.a_to_b if scanner == stream.a else stream.b_to_a)
    sent = reassemble(stream.b_to_a if scanner == stream.a else stream.a_to_b)
    if not stream.syn_seen:
        warnings.append(f"{path}: the capture starts inside the connection (no SYN seen): the "
                        "stream begins at its first captured byte")
    for name, side in (("received from", received), ("sent to", sent)):
        if side.gaps:
            warnings.append(
                f"{path}: the bytes {name} the scanner have {len(side.gaps)} gaps "
                f"({sum(g.missing_bytes for g in side.gaps)} bytes the capture never saw, first "
                f"at stream byte {side.gaps[0].offset}); frames across a gap are resynchronised")
    dialect, _ = _profile_dialect(received.data)
    return ScannerCapture(path, capture.kind, stream, scanner, host, received, sent, dialect,
                          counts, warnings)


# -- into a recording -------------------------------------------------------------------------


def write_capture_recording(scan: ScannerCapture, out: Path, rig: Rig,
                            session: dict[str, object]) -> None:
    """Write the scanner's stream into a recording's raw scanner channel, both directions, each
    chunk at its capture time; a gap leaves one chunk number unused (readers count it missing)
    and is logged as a ``capture_gap`` event. Written under a temporary name and renamed, so an
    existing ``out`` is replaced only by a complete recording."""
    temporary = out.with_name(f".{out.name}.{os.getpid()}.partial")
    items: list[tuple[int, int, int, bytes | Gap]] = []
    for direction, side in ((RX, scan.received), (TX, scan.sent)):
        gaps = iter(side.gaps)
        gap = next(gaps, None)
        offset = 0
        for time_ns, chunk in side.chunks:
            while gap is not None and gap.offset <= offset:
                items.append((time_ns, direction, len(items), gap))
                gap = next(gaps, None)
            items.append((time_ns, direction, len(items), chunk))
            offset += len(chunk)
    items.sort(key=lambda item: (item[0], item[2]))
    try:
        with RecordingWriter(temporary, rig, session) as writer:
            for time_ns, direction, _, item in items:
                if isinstance(item, Gap):
                    writer.skip_stream_chunk("scanner", direction)
                    writer.write_event(time_ns, "capture_gap",
                                       f"{item.missing_bytes} bytes "
                                       f"{'from' if direction == RX else 'to'} the scanner "
                                       "missing from the capture",
                                       {"direction": "RX" if direction == RX else "TX",
                                        "stream_offset": item.offset,
                                        "missing_bytes": item.missing_bytes})
                else:
                    writer.write_stream("scanner", item, direction, time_ns)
        os.replace(temporary, out)
    except BaseException:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise
