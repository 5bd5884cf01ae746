"""SICK CoLa scan telegrams (``sSN LMDscandata``): CoLa-B (binary) and CoLa-A (ASCII).

CoLa-B frame: ``02 02 02 02``, u32 big-endian payload length, payload, one XOR byte over the
payload (the shared framing of :mod:`scanpipe.protocol.framing`). CoLa-A frame: STX (0x02),
space-separated ASCII tokens, ETX (0x03); numbers are hexadecimal (signed ones in two's
complement), floats IEEE-754 in hex. Both carry the same fields, in this order (CoLa-B widths):

=========================== =========================================================
``sSN LMDscandata ``        command (``sRA`` for the answer to a poll)
version, device number      u16, u16
serial number               u32
device status               2 × u8
telegram, scan counter      u16, u16
time since start-up         u32 µs (the scan's first sample); time of transmission u32 µs
inputs, outputs             2 × u8, 2 × u8
reserved (layer angle)      i16
scan frequency              u32, 1/100 Hz
measurement frequency       u32 (100 Hz units on most devices; some firmware sends Hz)
encoders                    u16 n, n × (u32 position, u16 speed)
16-bit channels             u16 n, n × (5-char name DIST1…5 / RSSI1…5, f32 scale, f32 offset,
                            i32 start angle 1/10000°, u16 step 1/10000°, u16 count, count × u16)
8-bit channels              the same with u8 data
position                    u16 flag; 1: 6 × f32 (x y z, rotations), u8 rotation type, u8
device name, comment        u16 flag; 1: u8 length + characters (each)
time                        u16 flag; 1: u16 year, u8 month day hour minute second, u32 µs
event                       u16 flag; 1: 4-char type, u32 encoder, u32 µs, i32 angle
=========================== =========================================================

Range in metres = raw × scale / 1000 + offset (as SICK's driver computes it); raw 0 is "no
return" (NaN). Angles stay the device's (SICK: −45° … 225°, 90° straight ahead); the rig's
``alpha_offset_deg`` and mount place them. Where the optional blocks' layout is uncertain see
docs/protocols.md; the decoder accepts telegrams that end after any whole block flag (firmware
that omits the trailing flags).
"""

from __future__ import annotations

import struct
from bisect import bisect_left
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ProtocolError
from scanpipe.protocol.framing import (
    BULK_MIN_FRAMES,
    NOT_PARSED,
    FrameCounters,
    LengthMismatch,
    RawFrame,
    UnsupportedVariant,
    encode_frame,
)
from scanpipe.protocol.profile import Profile, check_plausible

MARKER = b"\x02\x02\x02\x02"
COMMANDS = (b"sSN LMDscandata ", b"sRA LMDscandata ")
#: The device clock: µs, 32 bits.
TICK_NS = 1000
WRAP_TICKS = 1 << 32
ANGLE_UNITS_PER_DEG = 10_000.0
#: A header of 16 (command) + 46 (fixed fields) + 2 (encoders) + 2 + 2 (channel counts).
MIN_PAYLOAD_BYTES = 16 + 46 + 2 + 2 + 2
#: The largest telegram any listed device sends is far below (LMS5xx: 5 echoes × 1141 × 2 + RSSI).
MAX_PAYLOAD_BYTES = 1 << 17
MAX_SAMPLES = 16_384
STX, ETX = 0x02, 0x03
_HEAD = struct.Struct(">HHI2sHHII2s2shII")
_CHANNEL = struct.Struct(">5sffiHH")


@dataclass(frozen=True)
class Channel:
    """One data channel: its name, scale and offset, start angle and step (1/10000°) and raw
    data (u16 or u8)."""

    name: str
    scale: float
    offset: float
    start_angle: int
    step: int
    data: NDArray[np.uint16] | NDArray[np.uint8]


@dataclass(frozen=True)
class ScanTelegram:
    """Every field of one ``LMDscandata`` telegram (see the module docstring)."""

    version: int = 1
    device_number: int = 1
    serial_number: int = 0
    device_status: bytes = b"\x00\x00"
    telegram_counter: int = 0
    scan_counter: int = 0
    time_since_startup_us: int = 0
    time_of_transmission_us: int = 0
    inputs: bytes = b"\x00\x00"
    outputs: bytes = b"\x00\x00"
    layer_angle: int = 0
    scan_frequency_centihz: int = 2500
    measurement_frequency: int = 0
    encoders: tuple[tuple[int, int], ...] = ()
    channels16: tuple[Channel, ...] = ()
    channels8: tuple[Channel, ...] = ()
    position: tuple[float, float, float, float, float, float, int, int] | None = None
    name: str | None = None
    comment: str | None = None
    time: tuple[int, int, int, int, int, int, int] | None = None
    event: tuple[bytes, int, int, int] | None = None
    command: bytes = COMMANDS[0]
    trailing_flags: int = 5  # how many optional-block flags the telegram carried
    extra: dict[str, Any] = field(default_factory=dict)

    def channel(self, name: str) -> Channel | None:
        """The first channel called ``name`` (16-bit first), or None."""
        for ch in (*self.channels16, *self.channels8):
            if ch.name == name:
                return ch
        return None


# -- CoLa-B --------------------------------------------------------------------------------

def _string(payload: bytes, pos: int) -> tuple[str, int]:
    if pos >= len(payload):
        raise LengthMismatch("CoLa-B telegram ends inside a string length")
    n = payload[pos]
    end = pos + 1 + n
    if end > len(payload):
        raise LengthMismatch("CoLa-B telegram ends inside a string")
    return payload[pos + 1:end].decode("latin-1"), end


def parse_telegram(payload: bytes) -> ScanTelegram:
    """All fields of a CoLa-B ``LMDscandata`` payload; :class:`ProtocolError` when it is not
    one (:class:`LengthMismatch` when its counts disagree with its length)."""
    if payload[:16] not in COMMANDS:
        raise ProtocolError("not an LMDscandata telegram")
    size = len(payload)
    if size < MIN_PAYLOAD_BYTES:
        raise LengthMismatch(f"LMDscandata telegram of {size} bytes: below the fixed header")
    head = _HEAD.unpack_from(payload, 16)
    pos = 16 + _HEAD.size
    n_enc = int.from_bytes(payload[pos:pos + 2], "big")
    pos += 2
    if pos + 6 * n_enc + 4 > size:
        raise LengthMismatch(f"LMDscandata: {n_enc} encoders do not fit {size} bytes")
    encoders = tuple(struct.unpack_from(">IH", payload, pos + 6 * i) for i in range(n_enc))
    pos += 6 * n_enc
    channel_sets: list[tuple[Channel, ...]] = []
    for width, dtype in ((2, ">u2"), (1, "u1")):
        if pos + 2 > size:
            raise LengthMismatch("LMDscandata ends before a channel count")
        n_ch = int.from_bytes(payload[pos:pos + 2], "big")
        pos += 2
        channels = []
        for _ in range(n_ch):
            if pos + _CHANNEL.size > size:
                raise LengthMismatch("LMDscandata ends inside a channel header")
            name, scale, offset, start, step, count = _CHANNEL.unpack_from(payload, pos)
            pos += _CHANNEL.size
            end = pos + width * count
            if end > size:
                raise LengthMismatch(f"LMDscandata channel of {count} samples does not fit "
                                     f"{size} bytes")
            data = np.frombuffer(payload, dtype=dtype, count=count, offset=pos)
            channels.append(Channel(name.decode("latin-1"), scale, offset, start, step, data))
            pos = end
        channel_sets.append(tuple(channels))
    optional: dict[str, Any] = {}
    flags = 0
    for block in ("position", "name", "comment", "time", "event"):
        if pos == size:
            break  # firmware that omits the trailing flags
        if pos + 2 > size:
            raise LengthMismatch("LMDscandata ends inside a block flag")
        flag = int.from_bytes(payload[pos:pos + 2], "big")
        pos += 2
        flags += 1
        if flag == 0:
            continue
        if flag != 1:
            raise ProtocolError(f"LMDscandata {block} flag {flag}: expected 0 or 1")
        try:
            if block == "position":
                optional[block] = struct.unpack_from(">6fBB", payload, pos)
                pos += 26
            elif block in ("name", "comment"):
                optional[block], pos = _string(payload, pos)
            elif block == "time":
                optional[block] = struct.unpack_from(">HBBBBBI", payload, pos)
                pos += 11
            else:
                optional[block] = struct.unpack_from(">4sIIi", payload, pos)
                pos += 16
        except struct.error as err:
            raise LengthMismatch(f"LMDscandata ends inside the {block} block") from err
    if pos != size:
        raise LengthMismatch(f"LMDscandata of {size} bytes: fields end at byte {pos}")
    return ScanTelegram(
        version=head[0], device_number=head[1], serial_number=head[2], device_status=head[3],
        telegram_counter=head[4], scan_counter=head[5], time_since_startup_us=head[6],
        time_of_transmission_us=head[7], inputs=head[8], outputs=head[9], layer_angle=head[10],
        scan_frequency_centihz=head[11], measurement_frequency=head[12], encoders=encoders,
        channels16=channel_sets[0], channels8=channel_sets[1], command=payload[:16],
        trailing_flags=flags, **optional)


def encode_telegram(t: ScanTelegram) -> bytes:
    """The CoLa-B payload of a telegram (no framing)."""
    parts = [t.command, _HEAD.pack(
        t.version, t.device_number, t.serial_number, t.device_status, t.telegram_counter,
        t.scan_counter, t.time_since_startup_us, t.time_of_transmission_us, t.inputs, t.outputs,
        t.layer_angle, t.scan_frequency_centihz, t.measurement_frequency),
        len(t.encoders).to_bytes(2, "big")]
    parts += [struct.pack(">IH", p, s) for p, s in t.encoders]
    for channels, dtype in ((t.channels16, ">u2"), (t.channels8, "u1")):
        parts.append(len(channels).to_bytes(2, "big"))
        for ch in channels:
            parts.append(_CHANNEL.pack(ch.name.encode("latin-1")[:5].ljust(5), ch.scale,
                                       ch.offset, ch.start_angle, ch.step, len(ch.data)))
            parts.append(np.asarray(ch.data).astype(dtype).tobytes())
    blocks: list[bytes] = []
    if t.position is not None:
        blocks.append(b"\x00\x01" + struct.pack(">6fBB", *t.position))
    else:
        blocks.append(b"\x00\x00")
    for text in (t.name, t.comment):
        raw = b"" if text is None else text.encode("latin-1")
        blocks.append(b"\x00\x00" if text is None else b"\x00\x01" + bytes([len(raw)]) + raw)
    blocks.append(b"\x00\x00" if t.time is None else b"\x00\x01" + struct.pack(">HBBBBBI",
                                                                             *t.time))
    blocks.append(b"\x00\x00" if t.event is None else b"\x00\x01" + struct.pack(">4sIIi",
                                                                              *t.event))
    parts += blocks[:t.trailing_flags]
    return b"".join(parts)


# -- telegram ↔ profile -------------------------------------------------------------------

def _range_table(scale: float, offset: float) -> NDArray[np.float32]:
    table = (np.arange(1 << 16, dtype=np.float64) * (scale / 1000.0) + offset).astype(np.float32)
    table[0] = np.nan
    return table


_TABLES: dict[tuple[float, float], NDArray[np.float32]] = {(1.0, 0.0): _range_table(1.0, 0.0)}


def _table_for(name: str, scale: float, offset: float) -> NDArray[np.float32]:
    """Metres of every raw value of a DIST channel with this scale and offset (cached)."""
    key = (scale, offset)
    table = _TABLES.get(key)
    if table is None:
        if not (np.isfinite(scale) and np.isfinite(offset)) or scale <= 0:
            raise ProtocolError(f"channel {name}: scale {scale} / offset {offset} not usable")
        if len(_TABLES) < 64:
            table = _TABLES[key] = _range_table(scale, offset)
        else:
            table = _range_table(scale, offset)
    return table


def ranges_from_channel(ch: Channel) -> NDArray[np.float32]:
    """Metres of a DIST channel (raw × scale / 1000 + offset; raw 0 → NaN)."""
    return _table_for(ch.name, ch.scale, ch.offset)[np.asarray(ch.data, dtype=np.uint16)]


def _end_time_us(start_us: int, samples: int, step_deg: float, freq_centihz: int) -> int | None:
    """The device time of a scan's last sample (None without a scan frequency)."""
    if freq_centihz <= 0:
        return None
    span_s = max(samples - 1, 0) * step_deg / 360.0 / (freq_centihz / 100.0)
    return (start_us + round(span_s * 1e6)) % WRAP_TICKS


def telegram_profile(t: ScanTelegram, checksum_ok: bool = True) -> Profile:
    """The profile of a telegram: DIST1 ranges, RSSI1 echo (if sent), device times in µs;
    :class:`UnsupportedVariant` for a multi-layer scanner's telegram (a layer angle)."""
    if t.layer_angle:
        raise UnsupportedVariant(
            f"SICK multi-layer telegram (layer angle field {t.layer_angle}: "
            f"{t.layer_angle / 100:g}° on an MRS1000, {t.layer_angle / 200:g}° on an MRS6000; "
            "its beams lie on a cone, not in the scan plane): not supported; scanpipe reads "
            "single-plane scanners (LMS1xx, LMS5xx, TiM), whose telegrams carry layer angle 0")
    dist = t.channel("DIST1")
    if dist is None:
        raise ProtocolError("LMDscandata without a DIST1 channel")
    rssi = t.channel("RSSI1")
    echo = None
    if rssi is not None and len(rssi.data) == len(dist.data):
        echo = np.asarray(rssi.data, dtype=np.uint16)
    step_deg = dist.step / ANGLE_UNITS_PER_DEG
    return Profile(
        frame=t.scan_counter, sector=0, start_angle_deg=dist.start_angle / ANGLE_UNITS_PER_DEG,
        step_deg=step_deg, ranges_m=ranges_from_channel(dist), echo=echo,
        device_time_ms=t.time_since_startup_us,
        device_end_time_ms=_end_time_us(t.time_since_startup_us, len(dist.data), step_deg,
                                        t.scan_frequency_centihz),
        checksum_ok=checksum_ok, device_tick_ns=TICK_NS, device_wrap_ticks=WRAP_TICKS)


# -- many telegrams of one layout at once ----------------------------------------------------
#
# A scanner streams telegrams of one layout (the same channels, counts and blocks). The first
# telegram of a layout is parsed field by field (``parse_telegram`` / ``_parse_tokens``); the
# positions of its fields then hold for every telegram whose layout-fixing fields (counts,
# flags, channel names, string lengths) equal its own, and those are read for all such
# telegrams with one numpy operation per field. A telegram the bulk path cannot vouch for is
# left to the field-by-field path (NOT_PARSED), so both paths give the same profiles and the
# same errors.

#: The optional blocks in their order, and how many fields (CoLa-B: bytes, CoLa-A: tokens)
#: each holds after its flag; None: a string (a length, then its characters / one token).
_BLOCKS: tuple[tuple[str, int | None, int | None], ...] = (
    ("position", 26, 8), ("name", None, None), ("comment", None, None), ("time", 11, 7),
    ("event", 16, 4))
#: Layouts tried per bulk batch (more distinct ones go field by field).
_MAX_LAYOUTS = 4


@dataclass(frozen=True)
class _Layout:
    """Where one telegram layout's fields lie: bytes (CoLa-B) or tokens (CoLa-A) from the
    telegram's start. ``fixed`` must hold the template's values for a telegram to share the
    layout; ``texts`` (CoLa-A) are tokens that are no number; ``names`` must equal the
    template's text. ``dist`` is the DIST1 channel's scale field (offset, start angle and step
    follow, then the count and the data at ``dist_data``); ``rssi_data`` the RSSI1 data when
    the profile keeps it."""

    size: int
    fixed: NDArray[np.intp]
    texts: tuple[int, ...]
    names: tuple[tuple[int, bytes], ...]
    dist: int
    dist_data: int
    count: int
    dist_width: int
    rssi_data: int | None
    rssi_width: int


def _layout(t: ScanTelegram, binary: bool) -> _Layout | None:
    """The layout of a parsed telegram (None without DIST1 or with a layer angle: the
    field-by-field path says so). The layer angle is a layout-fixing field (0)."""
    if t.layer_angle:
        return None
    fixed: list[int] = [42, 43] if binary else [15]
    texts: list[int] = [0, 1]
    names: list[tuple[int, bytes]] = [(1, b"LMDscandata")]
    first: dict[str, tuple[int, int, int]] = {}  # name → (header position, width, count)
    if binary:
        fixed += range(16)  # the command
        pos = 16 + _HEAD.size
        fixed += (pos, pos + 1)
        pos += 2 + 6 * len(t.encoders)
    else:
        pos = 18
        fixed.append(pos)
        pos += 1 + 2 * len(t.encoders)
    for channels, width in ((t.channels16, 2), (t.channels8, 1)):
        fixed += (pos, pos + 1) if binary else (pos,)
        pos += 2 if binary else 1
        for ch in channels:
            first.setdefault(ch.name, (pos, width, len(ch.data)))
            if binary:
                fixed += (*range(pos, pos + 5), pos + 19, pos + 20)
                pos += 21 + width * len(ch.data)
            else:
                texts.append(pos)
                names.append((pos, ch.name.encode("latin-1")))
                fixed.append(pos + 5)
                pos += 6 + len(ch.data)
    for block, n_bytes, n_tokens in _BLOCKS[:t.trailing_flags]:
        fixed += (pos, pos + 1) if binary else (pos,)
        pos += 2 if binary else 1
        value = getattr(t, block)
        if value is None:
            continue
        if n_bytes is None:  # a string: its length fixes the layout
            fixed.append(pos)
            text = value.encode("latin-1")
            if binary:
                pos += 1 + len(text)
            else:  # the length token, then the tokens the string spans (it may hold spaces)
                words = len([w for w in text.split(b" ") if w])
                texts += range(pos + 1, pos + 1 + words)
                pos += 1 + words
        elif binary:
            pos += n_bytes
        else:
            if block == "event":
                texts.append(pos)
            pos += n_tokens or 0
    if "DIST1" not in first:
        return None
    dist, dist_width, count = first["DIST1"]
    rssi = first.get("RSSI1")
    rssi_data, rssi_width = None, 0
    header = 21 if binary else 6  # from a channel's name to its data
    if rssi is not None and rssi[2] == count:
        rssi_data, rssi_width = rssi[0] + header, rssi[1]
    return _Layout(pos, np.array(fixed, np.intp), tuple(texts), tuple(names),
                   dist + (5 if binary else 1), dist + (21 if binary else 6), count, dist_width,
                   rssi_data, rssi_width)


def _bulk_profiles(counters: list[int], starts_us: list[int], freqs: list[int],
                   channel: NDArray[np.uint32], dist: NDArray[Any], echo: NDArray[Any] | None
                   ) -> list[Any]:
    """The profiles of telegrams of one layout (as ``telegram_profile`` makes them), or
    NOT_PARSED for those whose scale and offset are not usable. ``channel`` holds each
    telegram's DIST1 scale and offset (IEEE-754 bits), start angle (two's complement) and
    step; ``dist`` its raw ranges, ``echo`` its RSSI1 values (one row per telegram)."""
    k = len(counters)
    keys = (channel[:, 0].astype(np.uint64) << np.uint64(32)) | channel[:, 1]
    floats = channel[:, :2].view(np.float32).astype(np.float64)
    ranges = np.empty(dist.shape, np.float32)
    usable = np.ones(k, bool)
    unique, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    for u in range(len(unique)):
        rows = first[u]
        try:
            table = _table_for("DIST1", float(floats[rows, 0]), float(floats[rows, 1]))
        except ProtocolError:
            usable[inverse == u] = False
            continue
        if len(unique) == 1:
            np.take(table, dist, out=ranges)
        else:
            ranges[inverse == u] = table[dist[inverse == u]]
    echoes = None if echo is None else echo.astype(np.uint16)
    angles = (channel[:, 2].view(np.int32) / ANGLE_UNITS_PER_DEG).tolist()
    step_deg = channel[:, 3] / ANGLE_UNITS_PER_DEG
    # _end_time_us for all at once (the same float64 operations in the same order; np.rint
    # rounds half to even as round() does)
    freq = np.array(freqs, np.int64)
    span_s = max(dist.shape[1] - 1, 0) * step_deg / 360.0 / (np.maximum(freq, 1) / 100.0)
    ends = (np.array(starts_us, np.int64) + np.rint(span_s * 1e6).astype(np.int64)) % WRAP_TICKS
    end_times = [None if f <= 0 else e for f, e in zip(freqs, ends.tolist(), strict=True)]
    steps = step_deg.tolist()
    out: list[Any] = []
    for i in range(k):
        if not usable[i]:
            out.append(NOT_PARSED)
            continue
        out.append([Profile(
            frame=counters[i], sector=0, start_angle_deg=angles[i], step_deg=steps[i],
            ranges_m=ranges[i], echo=None if echoes is None else echoes[i],
            device_time_ms=starts_us[i], device_end_time_ms=end_times[i], checksum_ok=True,
            device_tick_ns=TICK_NS, device_wrap_ticks=WRAP_TICKS)])
    return out


def _big_endian(rows: NDArray[np.uint8], at: int, width: int) -> NDArray[np.uint32]:
    """The unsigned big-endian field of ``width`` bytes at ``at`` of every row."""
    out = rows[:, at].astype(np.uint32)
    for i in range(1, width):
        out <<= np.uint32(8)
        out |= rows[:, at + i]
    return out


def decode_payloads(payloads: list[bytes], block: NDArray[np.uint8] | None = None,
                    starts: NDArray[np.intp] | None = None) -> list[Any]:
    """``decode_payload(p, True)`` for each CoLa-B payload, those of a layout at once; NOT_PARSED
    for payloads left to :func:`decode_payload` (another telegram, another layout, an error).
    ``block``/``starts``: the payloads' bytes where they already lie (payload ``i`` at
    ``starts[i]``, the framing's buffer); without them they are joined here."""
    if block is None or starts is None:
        block = np.frombuffer(b"".join(payloads), np.uint8)
        starts = np.cumsum([0, *(len(p) for p in payloads[:-1])], dtype=np.intp)
    out: list[Any] = [NOT_PARSED] * len(payloads)
    by_size: dict[int, list[int]] = {}
    for i, payload in enumerate(payloads):
        by_size.setdefault(len(payload), []).append(i)
    layouts = 0
    for size, members in by_size.items():
        at = starts[members]
        gaps = np.diff(at)
        if len(at) > 1 and (gaps == gaps[0]).all() and gaps[0] >= size:
            # evenly spaced (a run of one telegram size): the rows are a view, not a copy
            rows = np.lib.stride_tricks.as_strided(block[at[0]:], (len(at), size),
                                                   (int(gaps[0]), 1), writeable=False)
        else:  # gathered in one copy
            rows = block[at[:, None] + np.arange(size, dtype=np.intp)]
        left = np.arange(len(members))
        while left.size and layouts < _MAX_LAYOUTS:
            layouts += 1
            template = payloads[members[left[0]]]
            try:
                layout = _layout(parse_telegram(template), binary=True)
            except ProtocolError:
                layout = None
            if layout is None or layout.size != size:
                left = left[1:]
                continue
            fixed = rows[np.ix_(left, layout.fixed)]
            same = (fixed == fixed[0]).all(axis=1)
            take, left = left[same], left[~same]
            group = rows if take.size == len(members) else rows[take]
            n, d = layout.count, layout.dist
            channel = np.stack([_big_endian(group, d, 4), _big_endian(group, d + 4, 4),
                                _big_endian(group, d + 8, 4), _big_endian(group, d + 12, 2)],
                               axis=1)
            dist = _channel_data(group, layout.dist_data, n, layout.dist_width)
            echo = None
            if layout.rssi_data is not None:
                echo = _channel_data(group, layout.rssi_data, n, layout.rssi_width)
            profiles = _bulk_profiles(_big_endian(group, 28, 2).tolist(),
                                      _big_endian(group, 30, 4).tolist(),
                                      _big_endian(group, 44, 4).tolist(), channel, dist, echo)
            for row, parsed in zip(take.tolist(), profiles, strict=True):
                out[members[row]] = parsed
    return out


def _channel_data(rows: NDArray[np.uint8], at: int, count: int, width: int) -> NDArray[Any]:
    """A channel's raw values in every row (u16 big-endian or u8)."""
    block = rows[:, at:at + width * count]
    if width == 1:
        return block
    return np.ascontiguousarray(block).view(">u2")


def profile_telegram(profile: Profile, serial_number: int = 0x01234567) -> ScanTelegram:
    """A telegram carrying ``profile`` (scale 1 mm, or 2 mm past 65.5 m; RSSI1 if it has an
    echo); the scan frequency follows its device start and end times (25 Hz without)."""
    ranges = np.asarray(profile.ranges_m, dtype=np.float64)
    finite = np.isfinite(ranges) & (ranges > 0)
    scale = 2.0 if finite.any() and float(ranges[finite].max()) > 65.5 else 1.0
    raw = np.where(finite, np.rint(np.where(finite, ranges, 0.0) * 1000.0 / scale), 0.0)
    raw = np.clip(raw, 0, 65535).astype(np.uint16)
    raw[(raw == 0) & finite] = 1
    start = round(profile.start_angle_deg * ANGLE_UNITS_PER_DEG)
    step = round(profile.step_deg * ANGLE_UNITS_PER_DEG)
    if not 0 <= step <= 0xFFFF or not -(1 << 31) <= start < (1 << 31) or len(raw) > 0xFFFF:
        raise ProtocolError(f"profile of {len(raw)} samples at {profile.step_deg}° from "
                            f"{profile.start_angle_deg}°: LMDscandata holds steps up to "
                            "6.5535° and 65535 samples")
    channels = [Channel("DIST1", scale, 0.0, start, step, raw)]
    if profile.echo is not None:
        channels.append(Channel("RSSI1", 1.0, 0.0, start, step,
                                np.asarray(profile.echo, dtype=np.uint16)))
    t0 = profile.device_time_ms or 0
    freq = 2500
    if profile.device_end_time_ms is not None and len(raw) > 1:
        span_us = (profile.device_end_time_ms - t0) % WRAP_TICKS
        if span_us > 0:
            freq = round((len(raw) - 1) * profile.step_deg / 360.0 / (span_us / 1e6) * 100)
    return ScanTelegram(
        serial_number=serial_number, telegram_counter=profile.frame & 0xFFFF,
        scan_counter=profile.frame & 0xFFFF, time_since_startup_us=t0 % WRAP_TICKS,
        time_of_transmission_us=(t0 + 1000) % WRAP_TICKS, scan_frequency_centihz=freq,
        measurement_frequency=round(freq / 100 * 360 / max(profile.step_deg, 1e-6) / 100),
        channels16=tuple(channels))


def encode_profile(profile: Profile) -> bytes:
    """One CoLa-B frame carrying ``profile``."""
    return encode_frame(MARKER, encode_telegram(profile_telegram(profile)))


def decode_payload(payload: bytes, checksum_ok: bool = True) -> list[Profile] | None:
    """The profile of a CoLa-B payload; None for another CoLa telegram (an ``sEA`` answer …);
    :class:`ProtocolError` for bytes that are no CoLa telegram at all."""
    if payload[:16] not in COMMANDS:
        if len(payload) >= 4 and payload[0] == 0x73 and payload[3] == 0x20 and payload[
                1:3].isalpha():
            return None  # sEA, sAN, sWA …: a reply without scan data
        raise ProtocolError("not a CoLa telegram")
    return [telegram_profile(parse_telegram(payload), checksum_ok)]


def check_frame(profiles: list[Profile] | None) -> int | None:
    """The scan counter; ``ImplausibleFrame`` for angles or sizes no SICK scanner sends."""
    return check_plausible(profiles, MAX_SAMPLES, min_start_deg=-360.0)


# -- CoLa-A --------------------------------------------------------------------------------
#
# A CoLa-A stream is parsed in bulk: every token of a batch of frames is found and converted
# from hex at once (numpy over the bytes), then each frame's fields are read from those arrays.

#: Tokens are read through an 8-byte window ending at their last byte: this much padding
#: in front of the data keeps the first token's window inside it.
_PAD = b" " * 8
#: The digits a token of L hex digits keeps of its 4-digit window (index: L, clipped at 4).
_MASK4 = np.array([(1 << (4 * n)) - 1 for n in range(5)], np.uint32)
#: The same for the 8-digit window of a longer token.
_MASK8 = np.array([(1 << (4 * n)) - 1 for n in range(9)], np.uint64)
#: Frames tokenised together (bounds the temporaries of a large stream; half a MiB keeps more
#: of them in the cache than the 2 MiB before: ~10 % faster).
_BATCH_BYTES = 1 << 19


@dataclass(frozen=True)
class _Tokens:
    """The tokens of a stretch of CoLa-A bytes: where each lies in ``data`` (padded in front
    by :data:`_PAD`), its value as hex, and the (sorted) indices of the tokens that are no
    number (not 1–8 hex digits) and of those with more than 4 digits."""

    data: bytes | bytearray
    starts: NDArray[np.int64]
    ends: NDArray[np.int64]
    values: NDArray[np.uint32]
    bad: list[int]
    wide: list[int]

    def text(self, i: int) -> bytes:
        """Token ``i``'s bytes."""
        return bytes(self.data[int(self.starts[i]):int(self.ends[i])])

    def numbers(self, first: int, stop: int) -> bool:
        """Whether tokens ``first … stop-1`` are all numbers."""
        return bisect_left(self.bad, first) == bisect_left(self.bad, stop)

    def narrow(self, first: int, stop: int) -> bool:
        """Whether tokens ``first … stop-1`` all have at most 4 digits (fit 16 bits)."""
        return bisect_left(self.wide, first) == bisect_left(self.wide, stop)


def _hex_words(word: NDArray[Any], width: int) -> NDArray[Any]:
    """Words of ``width`` (4 or 8) ASCII hex digits to their values, in place (SWAR: a digit's
    low 4 bits, plus 9 for a letter — bit 6 set —, then the nibbles packed pairwise).
    Bytes that are no hex digit give garbage, confined to their own nibble."""
    dtype = word.dtype.type
    ones = dtype(int.from_bytes(b"\x01" * width, "big"))
    letters = word >> dtype(6)
    letters &= ones
    letters *= dtype(9)
    word &= dtype(ones * 0x0F)
    word += letters
    shift = 4
    while shift < 4 * width:  # lanes of 4·shift bits keep their low 2·shift bits
        lane = b"\x00" * (shift // 4) + b"\xff" * (shift // 4)
        word |= word >> dtype(shift)
        word &= dtype(int.from_bytes(lane * (2 * width // shift), "big"))
        shift *= 2
    return word


def _tokenise(padded: bytes | bytearray, begin: int, end: int) -> _Tokens:
    """The tokens of ``padded[begin:end]``: ``padded`` starts with :data:`_PAD`, the stretch
    starts with an STX and ends with an ETX. Separators are space, STX and ETX."""
    assert begin >= len(_PAD)
    data = np.frombuffer(padded, np.uint8)
    stretch = data[begin:end]
    sep = stretch == 0x20
    sep |= stretch == STX
    sep |= stretch == ETX
    seps = np.flatnonzero(sep)
    seps += begin
    # bytes that are neither a hex digit nor a separator make their token no number
    work = stretch - np.uint8(0x30)
    odd = np.less(work, 10)
    np.bitwise_or(stretch, np.uint8(0x20), out=work)
    work -= np.uint8(0x61)
    odd |= work < 6
    odd |= sep
    np.logical_not(odd, out=odd)
    odd_at = np.flatnonzero(odd)
    odd_at += begin
    del sep, work, odd
    starts, ends = seps[:-1] + 1, seps[1:]
    # Separators next to each other leave empty tokens. Those between one frame's ETX and the
    # next one's STX lie outside every frame's tokens and may stay; others (two spaces) go.
    empty = np.flatnonzero(ends == starts)
    if empty.size and not (data[starts[empty] - 1] == ETX).all():
        keep = ends > starts
        starts, ends = starts[keep], ends[keep]
    lengths = ends - starts
    # Each token's last 4 bytes as one big-endian word (the last 8 for the few longer ones),
    # hex digits to nibbles in parallel, the nibbles packed, the token's own digits kept.
    # (gathered as 4-byte items through a stride-1 view, then byte-swapped: np.take on the
    # big-endian view was 60 % of the decode)
    # (np.take copies a strided source whole first: the views span this stretch only)
    first = begin - len(_PAD)
    windows = np.ndarray((end - first - 3,), "V4", padded, first, (1,))
    values = np.take(windows, ends - (first + 4)).view("<u4").byteswap()
    _hex_words(values, 4)
    values &= np.take(_MASK4, lengths, mode="clip")
    wide = np.flatnonzero(lengths > 4)
    if wide.size:
        windows = np.ndarray((end - first - 7,), "<u8", padded, first, (1,))
        word8 = windows[ends[wide] - (first + 8)].byteswap()
        values[wide] = _hex_words(word8, 8) & np.take(_MASK8, lengths[wide], mode="clip")
    del data, stretch, windows
    bad = set((np.searchsorted(starts, odd_at, "right") - 1).tolist())
    bad.update(wide[lengths[wide] > 8].tolist())
    return _Tokens(padded, starts, ends, values, sorted(bad), wide.tolist())


def _signed32(value: int) -> int:
    return value - (1 << 32) if value & 0x80000000 else value


def _float(value: int) -> float:
    result: float = struct.unpack(">f", value.to_bytes(4, "big"))[0]
    return result


def _parse_tokens(tok: _Tokens, lo: int, hi: int) -> ScanTelegram:
    """All fields of the CoLa-A ``LMDscandata`` telegram made of tokens ``lo … hi-1``."""
    if hi - lo < 2 or tok.text(lo) not in (b"sSN", b"sRA") or tok.text(lo + 1) != (
            b"LMDscandata"):
        raise ProtocolError("not a CoLa-A LMDscandata telegram")
    pos = lo + 2
    values = tok.values

    def span(n: int) -> int:
        nonlocal pos
        if n < 0 or pos + n > hi:
            raise LengthMismatch("CoLa-A LMDscandata ends early")
        if not tok.numbers(pos, pos + n):
            raise ProtocolError("CoLa-A: a number token is empty, longer than 8 digits or "
                                "not hexadecimal")
        first = pos
        pos += n
        return first

    def num(n: int = 1) -> list[int]:
        first = span(n)
        out: list[int] = values[first:first + n].tolist()
        return out

    def text() -> bytes:
        nonlocal pos
        if pos >= hi:
            raise LengthMismatch("CoLa-A LMDscandata ends early")
        pos += 1
        return tok.text(pos - 1)

    def string(length: int) -> bytes:
        # A string is its length's characters after the length token's separator, spaces
        # included (a device's factory name is "not defined"): as many tokens as it spans.
        nonlocal pos
        if length == 0:  # "1 0": a string present and empty spans no token
            return b""
        begin = int(tok.ends[pos - 1]) + 1
        end = begin + length
        stop = pos
        while stop < hi and tok.starts[stop] < end:
            stop += 1
        if (stop < hi and tok.starts[stop] <= end) or (stop == hi and end > tok.ends[hi - 1]):
            raise LengthMismatch(f"CoLa-A string of {length} characters does not end before "
                                 "a separator")
        pos = stop
        return bytes(tok.data[begin:end])

    version, device_number, serial, s1, s2, tcount, scount, t_start, t_tx, i1, i2, o1, o2, \
        layer, freq, mfreq, n_enc = num(17)
    enc_values = num(2 * n_enc)
    encoders = tuple((enc_values[2 * i], enc_values[2 * i + 1]) for i in range(n_enc))
    channel_sets: list[tuple[Channel, ...]] = []
    for limit in (0xFFFF, 0xFF):
        (n_ch,) = num(1)
        channels = []
        for _ in range(n_ch):
            name = text()
            scale, offset, start, step, count = num(5)
            if count > MAX_SAMPLES:
                raise ProtocolError(f"CoLa-A channel of {count} samples")
            first = span(count)
            data = values[first:first + count]
            # ≤ 4 digits always fit 16 bits: the maximum is needed only otherwise
            fits = limit == 0xFFFF and tok.narrow(first, first + count)
            if count and not fits and int(data.max()) > limit:
                raise ProtocolError(f"CoLa-A channel {name!r}: value above its width")
            typed: NDArray[np.uint16] | NDArray[np.uint8] = (
                data.astype(np.uint16) if limit == 0xFFFF else data.astype(np.uint8))
            channels.append(Channel(name.decode("latin-1"), _float(scale), _float(offset),
                                    _signed32(start), step, typed))
        channel_sets.append(tuple(channels))
    optional: dict[str, Any] = {}
    flags = 0
    for block in ("position", "name", "comment", "time", "event"):
        if pos == hi:
            break
        (flag,) = num(1)
        flags += 1
        if flag == 0:
            continue
        if flag != 1:
            raise ProtocolError(f"CoLa-A {block} flag {flag}: expected 0 or 1")
        if block == "position":
            v = num(8)
            optional[block] = (*[_float(x) for x in v[:6]], v[6], v[7])
        elif block in ("name", "comment"):
            (length,) = num(1)
            optional[block] = string(length).decode("latin-1")
        elif block == "time":
            optional[block] = tuple(num(7))
        else:
            kind = text()
            enc, us, angle = num(3)
            optional[block] = (kind, enc, us, _signed32(angle))
    if pos != hi:
        raise LengthMismatch(f"CoLa-A LMDscandata: {hi - pos} tokens after the fields")
    return ScanTelegram(
        version=version, device_number=device_number, serial_number=serial,
        device_status=bytes([s1 & 0xFF, s2 & 0xFF]), telegram_counter=tcount,
        scan_counter=scount, time_since_startup_us=t_start, time_of_transmission_us=t_tx,
        inputs=bytes([i1 & 0xFF, i2 & 0xFF]), outputs=bytes([o1 & 0xFF, o2 & 0xFF]),
        layer_angle=layer - 0x10000 if layer & 0x8000 else layer,
        scan_frequency_centihz=freq, measurement_frequency=mfreq, encoders=encoders,
        channels16=channel_sets[0], channels8=channel_sets[1],
        command=tok.text(lo) + b" LMDscandata ", trailing_flags=flags, **optional)


def parse_ascii(body: bytes) -> ScanTelegram:
    """All fields of a CoLa-A ``LMDscandata`` telegram (the bytes between STX and ETX)."""
    padded = _PAD + bytes([STX]) + body + bytes([ETX])
    tok = _tokenise(padded, len(_PAD), len(padded))
    return _parse_tokens(tok, 0, len(tok.starts))


def _hex(values: NDArray[np.integer] | list[int]) -> list[bytes]:
    return [format(int(v), "X").encode() for v in values]


def _float_hex(value: float) -> bytes:
    return struct.pack(">f", value).hex().upper().encode()


def encode_ascii(t: ScanTelegram) -> bytes:
    """A whole CoLa-A frame (STX, tokens, ETX) for a telegram."""
    tokens: list[bytes] = [t.command[:3], b"LMDscandata"]
    tokens += _hex([t.version, t.device_number, t.serial_number, t.device_status[0],
                    t.device_status[1], t.telegram_counter, t.scan_counter,
                    t.time_since_startup_us, t.time_of_transmission_us, t.inputs[0],
                    t.inputs[1], t.outputs[0], t.outputs[1], t.layer_angle & 0xFFFF,
                    t.scan_frequency_centihz, t.measurement_frequency, len(t.encoders)])
    for p, s in t.encoders:
        tokens += _hex([p, s])
    for channels in (t.channels16, t.channels8):
        tokens += _hex([len(channels)])
        for ch in channels:
            tokens += [ch.name.encode("latin-1"), _float_hex(ch.scale), _float_hex(ch.offset)]
            tokens += _hex([ch.start_angle & 0xFFFFFFFF, ch.step, len(ch.data)])
            tokens += _hex(np.asarray(ch.data))
    blocks: list[list[bytes]] = []
    blocks.append([b"0"] if t.position is None else [b"1", *[_float_hex(v) for v in
                                                          t.position[:6]],
                                                     *_hex(list(t.position[6:]))])
    for text in (t.name, t.comment):
        if text is None:
            blocks.append([b"0"])
        elif "\x02" in text or "\x03" in text:
            raise ProtocolError("CoLa-A strings cannot hold STX or ETX")
        else:
            raw = text.encode("latin-1")
            blocks.append([b"1", *_hex([len(raw)])] + ([raw] if raw else []))
    blocks.append([b"0"] if t.time is None else [b"1", *_hex(list(t.time))])
    blocks.append([b"0"] if t.event is None else [
        b"1", t.event[0], *_hex([t.event[1], t.event[2], t.event[3] & 0xFFFFFFFF])])
    for block in blocks[:t.trailing_flags]:
        tokens += block
    return bytes([STX]) + b" ".join(tokens) + bytes([ETX])


def encode_profile_ascii(profile: Profile) -> bytes:
    """One CoLa-A frame carrying ``profile``."""
    return encode_ascii(profile_telegram(profile))


def _other_telegram(body: bytes | bytearray) -> list[Profile] | None:
    """None for a CoLa-A telegram other than scan data (``sEA``, ``sAN`` …);
    :class:`ProtocolError` for bytes that are no CoLa-A telegram."""
    if len(body) >= 4 and body[:1] == b"s" and body[3:4] == b" " and body[1:3].isalpha():
        return None
    raise ProtocolError("not a CoLa-A telegram")


_SCAN_PREFIXES = (b"sSN LMDscandata", b"sRA LMDscandata")


def decode_ascii(body: bytes, checksum_ok: bool = True) -> list[Profile] | None:
    """The profile of a CoLa-A telegram body; None for another CoLa-A telegram."""
    if not body.startswith(_SCAN_PREFIXES):
        return _other_telegram(body)
    return [telegram_profile(parse_ascii(body), checksum_ok)]


class AsciiFrameReader:
    """STX … ETX frames from a byte stream in chunks of any size, with resync.

    A frame is the bytes between an STX and the next ETX. An STX inside that span means the
    first one was a false start: decoding resumes at the later STX (one byte past the false
    start, then the next STX). A frame that does not parse is counted (malformed, or a
    length mismatch) and skipped; so is a frame longer than the cap. There is no checksum.
    Frames are found and tokenised in bulk (numpy over all bytes received so far), so the
    stream is scanned only when an ETX has arrived (or the cap is passed); scan telegrams of
    one layout are then read together (``_parse_token_frames``; ``bulk=False`` reads each
    field by field, which gives the same frames and counters).
    """

    def __init__(self, max_payload_bytes: int = MAX_PAYLOAD_BYTES * 3,
                 check: Any = check_frame, parse: bool = True, bulk: bool = True) -> None:
        self.max_payload_bytes = max_payload_bytes
        self.check = check
        self.parse = parse
        self.bulk = bulk  # False: every frame field by field (the reference the tests hold)
        self.counters = FrameCounters()
        self._buffer = bytearray()
        self._base = 0

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[RawFrame]:
        """Add bytes; return the frames they complete."""
        chunk = bytes(chunk)
        self._buffer += chunk
        if chunk.find(ETX) < 0 and len(self._buffer) <= self.max_payload_bytes:
            return []  # nothing can end here, and no open frame can pass the cap
        return self._scan()

    def finish(self) -> list[RawFrame]:
        """End of stream: an open frame is a false start; the rest is skipped."""
        frames = self._scan()
        if self._buffer:
            if self._buffer.find(STX) >= 0:
                self.counters.resyncs += 1
            self.counters.bytes_skipped += len(self._buffer)
            self._base += len(self._buffer)
            self._buffer.clear()
        return frames

    def _scan(self) -> list[RawFrame]:
        padded = bytearray(_PAD)
        padded += self._buffer
        counters, size = self.counters, len(padded)
        spans: list[tuple[int, int]] = []
        pos = keep = len(_PAD)
        while True:
            start = padded.find(STX, pos)
            if start < 0:
                counters.bytes_skipped += size - pos
                keep = size
                break
            counters.bytes_skipped += start - pos
            end = padded.find(ETX, start + 1)
            limit = size if end < 0 else end
            inner = padded.rfind(STX, start + 1, limit)
            if inner >= 0:  # false starts: resume at the last STX before the ETX
                counters.resyncs += padded.count(STX, start, inner)
                counters.bytes_skipped += inner - start
                start = inner
            if end < 0:
                keep = size if size - start > self.max_payload_bytes else start
                if keep == size:  # an open frame past the cap: a false start
                    counters.resyncs += 1
                    counters.bytes_skipped += size - start
                break
            spans.append((start, end))
            pos = end + 1
        frames: list[RawFrame] = []
        done = 0
        if not self.parse:  # frames only (a command link): ``parsed`` is NOT_PARSED
            for start, end in spans:
                offset = self._base + start - len(_PAD)
                frames.append(RawFrame(bytes(padded[start + 1:end]), True, 0, 0, offset,
                                       offset + end + 1 - start, NOT_PARSED))
            done = len(spans)
        while done < len(spans):  # batches of whole frames, tokenised together
            first = spans[done][0]
            stop = done + 1
            while stop < len(spans) and spans[stop][1] - first < _BATCH_BYTES:
                stop += 1
            tok = _tokenise(padded, first, spans[stop - 1][1] + 1)
            # a frame's tokens start after its STX and before its ETX
            edges = np.array(spans[done:stop], np.int64)
            edges[:, 0] += 1
            bounds = np.searchsorted(tok.starts, edges)
            batch = spans[done:stop]
            bulk = _parse_token_frames(padded, tok, batch, bounds) if self.bulk else [
                NOT_PARSED] * len(batch)
            for (start, end), (lo, hi), parsed in zip(batch, bounds.tolist(), bulk, strict=True):
                if parsed is not NOT_PARSED:
                    try:
                        self.check(parsed)
                    except ProtocolError:
                        parsed = NOT_PARSED  # the field-by-field path counts it
                if parsed is NOT_PARSED:
                    frames += self._frame(padded, tok, lo, hi, start, end)
                    continue
                offset = self._base + start - len(_PAD)
                frames.append(RawFrame(bytes(padded[start + 1:end]), True, 0, 0, offset,
                                       offset + end + 1 - start, parsed))
            done = stop
        del self._buffer[:keep - len(_PAD)]
        self._base += keep - len(_PAD)
        return frames

    def _frame(self, padded: bytearray, tok: _Tokens, lo: int, hi: int, start: int,
               end: int) -> list[RawFrame]:
        """The frame between the STX at ``start`` and the ETX at ``end`` (padded offsets)."""
        body = bytes(padded[start + 1:end])
        offset = self._base + start - len(_PAD)
        try:
            if body.startswith(_SCAN_PREFIXES):
                parsed: list[Profile] | None = [telegram_profile(_parse_tokens(tok, lo, hi))]
                self.check(parsed)
            else:
                parsed = _other_telegram(body)
        except UnsupportedVariant:
            raise
        except (LengthMismatch, ProtocolError) as err:
            if isinstance(err, LengthMismatch):
                self.counters.length_mismatches += 1
            else:
                self.counters.malformed_frames += 1
            self.counters.resyncs += 1
            self.counters.bytes_skipped += end + 1 - start
            return []
        return [RawFrame(body, True, 0, 0, offset, offset + end + 1 - start, parsed)]


def _token_rows(values: NDArray[np.uint32], first: NDArray[np.int64], at: int, count: int
                ) -> NDArray[np.uint32]:
    """Tokens ``at … at+count-1`` of each frame whose tokens begin at ``first`` (one row per
    frame; a strided view when the frames lie evenly, as a stream's frames of one layout do)."""
    if first.size > 1:
        step = np.unique(np.diff(first))
        if step.size == 1 and step[0] >= count:
            base = values[int(first[0]) + at:]
            rows: NDArray[np.uint32] = np.lib.stride_tricks.as_strided(
                base, (first.size, count), (int(step[0]) * values.itemsize, values.itemsize),
                writeable=False)
            return rows
    gathered: NDArray[np.uint32] = values[first[:, None] + (at + np.arange(count))]
    return gathered


def _parse_token_frames(padded: bytes | bytearray, tok: _Tokens, spans: list[tuple[int, int]],
                        bounds: NDArray[np.int64]) -> list[Any]:
    """What ``_frame`` would parse for each frame (STX at ``start``, ETX at ``end``, tokens
    ``lo … hi-1``), scan telegrams of a layout at once; NOT_PARSED for frames left to it."""
    out: list[Any] = [NOT_PARSED] * len(spans)
    if len(spans) < BULK_MIN_FRAMES:
        return out
    los = bounds[:, 0]
    sizes = bounds[:, 1] - los
    by_size: dict[int, list[int]] = {}
    for i, (start, _) in enumerate(spans):
        if padded.startswith(_SCAN_PREFIXES, start + 1):
            by_size.setdefault(int(sizes[i]), []).append(i)
    values = tok.values
    bad = np.array(tok.bad, np.int64)
    layouts = 0
    for size, members in by_size.items():
        left = np.array(members, np.intp)
        while left.size and layouts < _MAX_LAYOUTS:
            layouts += 1
            lo = int(los[left[0]])
            try:
                layout = _layout(_parse_tokens(tok, lo, lo + size), binary=False)
            except ProtocolError:
                layout = None
            if layout is None or layout.size != size:
                left = left[1:]
                continue
            first = los[left]
            fixed = values[first[:, None] + layout.fixed]
            same = (fixed == fixed[0]).all(axis=1)
            take, left = left[same], left[~same]
            first = first[same]
            ok = np.ones(take.size, bool)
            # every token but the texts must be a number
            frame = np.searchsorted(first, bad, "right") - 1
            inside = (frame >= 0) & (bad < first[np.maximum(frame, 0)] + size)
            rel = bad[inside] - first[frame[inside]]
            ok[frame[inside][~np.isin(rel, layout.texts)]] = False
            for at, name in layout.names:
                where = first + at
                ok &= tok.ends[where] - tok.starts[where] == len(name)
                at_text = tok.starts[where[ok]]  # tokens of the name's length: inside the data
                if at_text.size:
                    low = int(at_text.min())
                    texts = np.ndarray((int(at_text.max()) - low + 1,), f"S{len(name)}",
                                       padded, low, (1,))
                    ok[ok] = texts[at_text - low] == name
            n = layout.count
            dist = _token_rows(values, first, layout.dist_data, n)
            ok &= dist.max(axis=1, initial=0) <= (0xFFFF if layout.dist_width == 2 else 0xFF)
            echo = None
            if layout.rssi_data is not None:
                echo = _token_rows(values, first, layout.rssi_data, n)
                ok &= echo.max(axis=1, initial=0) <= (0xFFFF if layout.rssi_width == 2 else 0xFF)
            if not ok.all():
                take, first, dist = take[ok], first[ok], dist[ok]
                echo = None if echo is None else echo[ok]
            channel = values[first[:, None] + (layout.dist + np.arange(4))]
            head = values[first[:, None] + np.array([8, 9, 16])].T.tolist()
            profiles = _bulk_profiles(head[0], head[1], head[2], channel, dist, echo)
            for row, parsed in zip(take.tolist(), profiles, strict=True):
                out[row] = parsed
    return out


def ascii_reader(dialect: Any, max_payload_bytes: int, confirm: bool) -> AsciiFrameReader:
    """The registry's reader factory for CoLa-A."""
    return AsciiFrameReader(max_payload_bytes, dialect.check_frame)



# -- CoLa-B commands (start/stop, log-in, scan configuration) -------------------------------

#: The "authorised client" level and its documented default password (SICK manuals).
ACCESS_LEVEL_CLIENT = 3
CLIENT_PASSWORD = 0xF4724744
SCANCFG = struct.Struct(">IHIii")  # frequency 1/100 Hz, sectors, resolution, start, end


def command(kind: str, name: str, args: bytes = b"") -> bytes:
    """A whole CoLa-B frame ``kind name args`` (``sEN LMDscandata`` + ``b"\\x01"`` …)."""
    return encode_frame(MARKER, f"{kind} {name} ".encode("ascii") + args)


def parse_command(payload: bytes) -> tuple[str, str, bytes]:
    """``(kind, name, args)`` of a CoLa-B telegram; :class:`ProtocolError` if it is none."""
    first = payload.find(b" ")
    second = payload.find(b" ", first + 1)
    if first != 3 or not payload[:3].isalpha():
        raise ProtocolError("not a CoLa telegram")
    if second < 0:  # a name without arguments may end the telegram without its space
        second = len(payload)
    try:
        name = payload[first + 1:second].decode("ascii")
    except UnicodeDecodeError as err:
        raise ProtocolError("CoLa telegram name is not ASCII") from err
    return payload[:3].decode("ascii"), name, payload[second + 1:]


def scan_config_args(scan_hz: float, step_deg: float, start_deg: float, end_deg: float) -> bytes:
    """The arguments of ``sMN mLMPsetscancfg``: one sector from start to end (the last
    sample's angle), at ``step_deg``."""
    return SCANCFG.pack(round(scan_hz * 100), 1, round(step_deg * ANGLE_UNITS_PER_DEG),
                        round(start_deg * ANGLE_UNITS_PER_DEG),
                        round(end_deg * ANGLE_UNITS_PER_DEG))


def failure(code: int) -> bytes:
    """An ``sFA`` frame with a u16 error code (2: unknown method, 10: access denied)."""
    return encode_frame(MARKER, b"sFA " + code.to_bytes(2, "big"))


# -- CoLa-A commands: the same telegrams as ASCII tokens ------------------------------------

#: The argument fields of the commands and answers scanpipe exchanges, as ``struct`` formats
#: of their CoLa-B bytes. CoLa-A sends one token per field: unsigned hex, signed fields in
#: two's complement hex (what the LMDscandata telegram does), or decimal with a sign (``+5000``,
#: ``-450000``: the manuals' own examples), which the parser also reads.
ARGUMENTS: dict[tuple[str, str], str] = {
    ("sMN", "SetAccessMode"): ">BI", ("sAN", "SetAccessMode"): ">B",
    ("sMN", "mLMPsetscancfg"): ">" + SCANCFG.format.lstrip(">"),
    ("sAN", "mLMPsetscancfg"): ">B" + SCANCFG.format.lstrip(">"),
    ("sMN", "Run"): "", ("sAN", "Run"): ">B",
    ("sEN", "LMDscandata"): ">B", ("sEA", "LMDscandata"): ">B",
    ("sRN", "DeviceIdent"): "",
}


def _ascii_field(value: int, code: str) -> bytes:
    width = struct.calcsize(">" + code) * 8
    return format(value & ((1 << width) - 1), "X").encode()


def _field_value(token: bytes, code: str) -> int:
    width = struct.calcsize(">" + code) * 8
    try:
        value = int(token, 10) if token[:1] in b"+-" else int(token, 16)
    except ValueError as err:
        raise ProtocolError(f"CoLa-A argument {token!r}: not a number") from err
    if code.islower() and token[:1] not in b"+-" and value >= 1 << (width - 1):
        value -= 1 << width  # two's complement hex
    low, high = (-(1 << (width - 1)), (1 << (width - 1)) - 1) if code.islower() else (
        0, (1 << width) - 1)
    if not low <= value <= high:
        raise ProtocolError(f"CoLa-A argument {token!r}: outside its {width}-bit field")
    return value


def command_ascii(kind: str, name: str, args: bytes = b"") -> bytes:
    """The CoLa-A frame (STX … ETX) of the telegram whose CoLa-B arguments are ``args``
    (fields as :data:`ARGUMENTS` lists them; ``sFA``: the error code)."""
    if kind == "sFA":
        return bytes([STX]) + b"sFA " + format(int.from_bytes(args[:2], "big"), "X").encode() \
            + bytes([ETX])
    fmt = ARGUMENTS.get((kind, name))
    if fmt is None:
        raise ProtocolError(f"CoLa-A: no argument layout for {kind} {name}")
    tokens = [kind.encode("ascii"), name.encode("ascii")]
    if fmt:
        tokens += [_ascii_field(v, c) for v, c in zip(struct.unpack(fmt, args),
                                                     fmt.lstrip(">"), strict=True)]
    return bytes([STX]) + b" ".join(tokens) + bytes([ETX])


def parse_command_ascii(body: bytes) -> tuple[str, str, bytes]:
    """``(kind, name, args)`` of a CoLa-A telegram body, the arguments packed as their CoLa-B
    bytes (so one handler serves both flavours); :class:`ProtocolError` if it is no telegram
    scanpipe knows. An ``sFA`` answer is ``("sFA", "", u16 error code)``."""
    tokens = body.split(b" ")
    if len(tokens[0]) != 3 or not tokens[0].isalpha() or not tokens[0].startswith(b"s"):
        raise ProtocolError("not a CoLa-A telegram")
    kind = tokens[0].decode("ascii")
    if kind == "sFA":
        code = _field_value(tokens[1], "H") if len(tokens) == 2 else 0xFFFF
        return kind, "", code.to_bytes(2, "big")
    if len(tokens) < 2:
        raise ProtocolError(f"CoLa-A {kind} telegram without a name")
    name = tokens[1].decode("latin-1")
    fmt = ARGUMENTS.get((kind, name))
    if fmt is None:  # a telegram scanpipe does not speak: no arguments read
        return kind, name, b""
    codes = fmt.lstrip(">")
    if len(tokens) - 2 != len(codes):
        raise ProtocolError(f"CoLa-A {kind} {name}: {len(tokens) - 2} arguments, expected "
                            f"{len(codes)}")
    return kind, name, struct.pack(fmt, *[_field_value(t, c) for t, c in zip(
        tokens[2:], codes, strict=True)])
