"""Hokuyo SCIP 2.0: the text protocol of URG and UST scanners (serial or TCP 10940).

A message is lines ended by LF and closed by an empty line (LF LF). A reply repeats the
command (the *echo* line), then a status line (two characters and a check character), then
for a scan a timestamp line and data lines of at most 64 characters, each followed by its
check character. A check character is the sum of the line's bytes, lower 6 bits, + 0x30.

Values are sent as 2, 3 or 4 characters of 6 bits each (+ 0x30), most significant first:
``MS``/``GS`` ranges in 2 characters (mm, < 4096), ``MD``/``GD`` in 3, ``ME``/``GE`` range and
intensity pairs in 3 + 3, the timestamp in 4 (24-bit milliseconds, wrapping every 4.66 h).
``MD``/``ME``/``MS`` stream: the reply to the command carries status ``00`` and no data, then
each scan comes as a message with status ``99`` and the echo's remaining-scan count counting
down (``00``: until ``QT``). ``GD``/``GE``/``GS`` answer once, with status ``00``.

Angles: step ``s`` is at ``(s - AFRT) · 360° / ARES`` (``PP`` reply: ARES, AFRT). The decoder
takes ARES/AFRT from a ``PP`` reply in the stream (the recorder asks for one first) and
otherwise assumes the UST/UTM geometry (1440, 540). Multi-echo commands (``HD``, ``HE``,
``ND``, ``NE``) are refused with :class:`~scanpipe.errors.ProtocolError`.

A profile's ``frame`` is the low 16 bits of its timestamp (SCIP sends no scan counter); ranges
below 20 mm are the URG error codes and decode as "no return".
"""

from __future__ import annotations

import re
from bisect import bisect_left
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ProtocolError
from scanpipe.protocol.framing import FrameCounters, ImplausibleFrame, RawFrame
from scanpipe.protocol.profile import Profile, check_plausible

LF = 0x0A
TERMINATOR = b"\n\n"
CHAR_OFFSET = 0x30
BITS_PER_CHAR = 6
DATA_LINE_CHARS = 64
#: The device clock: 24-bit milliseconds.
TIMESTAMP_WRAP_MS = 1 << 24
#: Ranges below this (mm) are the URG error codes (no return).
MIN_VALID_RANGE_MM = 20
#: The UST/UTM geometry assumed when no PP reply came before the scans.
DEFAULT_ARES = 1440
DEFAULT_AFRT = 540
#: Longest message accepted (a multi-echo UTM scan is ~ 20 kB); longer is a false start.
MAX_MESSAGE_BYTES = 1 << 16

#: Status codes common to the commands, and what they mean (SCIP 2.0). Codes 01–0F are the
#: command's own parameter errors; BM answers 02 when the laser is already on.
STATUS_MEANINGS: dict[str, str] = {
    "00": "command accepted",
    "99": "scan data (streaming)",
    "01": "starting step has a non-numeric value",
    "02": "ending step has a non-numeric value (BM: laser already on)",
    "03": "cluster count has a non-numeric value",
    "04": "ending step is out of range",
    "05": "ending step is smaller than the starting step",
    "06": "scan interval (skip) has a non-numeric value",
    "07": "number of scans has a non-numeric value",
    "0E": "command not defined",
    "0L": "command not defined",
    "0M": "command too long / invalid",
    "10": "hardware trouble (laser, motor) or a data transfer failure",
    "50": "hardware trouble",
    "98": "resumed after a device error",
}

#: Data commands: (characters per value, values per step).
DATA_COMMANDS: dict[bytes, tuple[int, int]] = {
    b"MD": (3, 1), b"GD": (3, 1), b"MS": (2, 1), b"GS": (2, 1), b"ME": (3, 2), b"GE": (3, 2),
}
MULTI_ECHO_COMMANDS = (b"HD", b"HE", b"ND", b"NE")
_MULTI_ECHO = re.compile(rb"^[HN][DE]\d{10}(\d{3})?(;[ -~]{0,16})?$")
#: A streaming echo's scan parameters: command, start, end, cluster, skip (not the count).
STREAM_PARAM_CHARS = 13
_STREAM_ECHO = re.compile(rb"^(M[DSE])(\d{4})(\d{4})(\d{2})(\d)(\d{2})(;[ -~]{0,16})?$")
_SINGLE_ECHO = re.compile(rb"^(G[DSE])(\d{4})(\d{4})(\d{2})(;[ -~]{0,16})?$")
#: The command that switches a URG from SCIP 1.1 to 2.0 (answered ``0`` in 1.1: done).
SCIP20_SWITCH = b"SCIP2.0"
#: A SCIP 1.1 ``G`` echo: start and end step (3 digits each), cluster count (2).
_SCIP11_ECHO = re.compile(rb"^G(\d{3})(\d{3})(\d{2})$")
#: Where a data message's echo line may begin (a resync target at any byte).
_DATA_ECHO = re.compile(rb"[MGHN][DSE]\d{8}")
#: The next place to try after a false start: the next line, or a data echo within this one.
_RESYNC = re.compile(rb"\n|(?=[MGHN][DSE]\d{8})")


def status_meaning(status: str) -> str:
    """What a status code means (the table above; others are command-specific errors)."""
    return STATUS_MEANINGS.get(status, "command-specific error (see the device manual)")


def check_char(line: bytes | bytearray | memoryview | NDArray[np.uint8]) -> int:
    """The check character of a line: sum of its bytes, lower 6 bits, + 0x30."""
    if isinstance(line, bytes):
        return (sum(line) & 0x3F) + CHAR_OFFSET
    return (int(np.frombuffer(line, np.uint8).sum(dtype=np.int64)) & 0x3F) + CHAR_OFFSET


def encode_values(values: NDArray[np.integer], chars: int) -> bytes:
    """Values as ``chars`` characters each (6 bits per character + 0x30, big-endian).

    :class:`ProtocolError` for a value that does not fit ``6·chars`` bits."""
    v = np.asarray(values, dtype=np.int64).ravel()
    if v.size and (v.min() < 0 or v.max() >= 1 << (BITS_PER_CHAR * chars)):
        raise ProtocolError(f"value outside 0…{(1 << (BITS_PER_CHAR * chars)) - 1}: does not "
                            f"fit {chars} SCIP characters")
    shifts = BITS_PER_CHAR * np.arange(chars - 1, -1, -1, dtype=np.int64)
    out = ((v[:, None] >> shifts) & 0x3F) + CHAR_OFFSET
    return out.astype(np.uint8).tobytes()


def decode_values(data: NDArray[np.uint8] | bytes, chars: int) -> NDArray[np.int64]:
    """Characters back to values (``len(data)`` a multiple of ``chars``)."""
    arr = np.frombuffer(data, np.uint8) if isinstance(data, bytes) else data
    if arr.size % chars:
        raise ProtocolError(f"{arr.size} data characters: not a multiple of {chars}")
    digits = (arr.reshape(-1, chars).astype(np.int64) - CHAR_OFFSET) & 0x3F
    shifts = BITS_PER_CHAR * np.arange(chars - 1, -1, -1, dtype=np.int64)
    return np.asarray((digits << shifts).sum(axis=1), dtype=np.int64)


def data_block(data: bytes) -> bytes:
    """Data characters cut into lines of 64, each with its check character and LF."""
    arr = np.frombuffer(data, np.uint8)
    full = arr.size // DATA_LINE_CHARS
    out = bytearray()
    if full:
        lines = arr[:full * DATA_LINE_CHARS].reshape(full, DATA_LINE_CHARS)
        sums = ((lines.sum(axis=1, dtype=np.int64) & 0x3F) + CHAR_OFFSET).astype(np.uint8)
        block = np.empty((full, DATA_LINE_CHARS + 2), np.uint8)
        block[:, :DATA_LINE_CHARS] = lines
        block[:, DATA_LINE_CHARS] = sums
        block[:, DATA_LINE_CHARS + 1] = LF
        out += block.tobytes()
    rest = bytes(arr[full * DATA_LINE_CHARS:])
    if rest:
        out += rest + bytes([check_char(rest), LF])
    return bytes(out)


def status_line(status: str) -> bytes:
    """A status line: the two-character code, its check character, LF."""
    code = status.encode("ascii")
    return code + bytes([check_char(code), LF])


def timestamp_line(time_ms: int) -> bytes:
    """The 4-character timestamp (24-bit ms) with its check character and LF."""
    chars = encode_values(np.array([time_ms % TIMESTAMP_WRAP_MS]), 4)
    return chars + bytes([check_char(chars), LF])


@dataclass(frozen=True)
class Geometry:
    """Where steps point: ``ARES`` steps per turn, step ``AFRT`` straight ahead."""

    ares: int = DEFAULT_ARES
    afrt: int = DEFAULT_AFRT
    scan_rpm: int = 0

    @property
    def step_deg(self) -> float:
        """One step in degrees."""
        return 360.0 / self.ares

    def angle_deg(self, step: int) -> float:
        """The angle of a step."""
        return (step - self.afrt) * 360.0 / self.ares

    def step_of(self, angle_deg: float) -> int:
        """The step nearest an angle."""
        return round(angle_deg / self.step_deg) + self.afrt


UST_GEOMETRY = Geometry(1440, 540, 2400)
URG04_GEOMETRY = Geometry(1024, 384, 600)


def geometry_for_step(step_deg: float) -> Geometry:
    """The geometry whose step divides ``step_deg`` (UST/UTM first, then URG-04LX)."""
    for geometry in (UST_GEOMETRY, URG04_GEOMETRY):
        n = step_deg / geometry.step_deg
        if abs(n - round(n)) < 1e-6 and round(n) >= 1:
            return geometry
    raise ProtocolError(f"step {step_deg}°: not a multiple of a SCIP device's step "
                        f"(0.25° UST/UTM, 0.3515625° URG-04LX)")


def parameter_lines(fields: dict[str, str]) -> bytes:
    """``NAME:value;`` lines with check characters (over ``NAME:value``), as VV/PP/II send."""
    out = bytearray()
    for name, value in fields.items():
        text = f"{name}:{value}".encode("ascii")
        out += text + b";" + bytes([check_char(text), LF])
    return bytes(out)


def parameter_reply(command: bytes, fields: dict[str, str]) -> bytes:
    """A whole VV/PP/II reply."""
    return command + b"\n" + status_line("00") + parameter_lines(fields) + b"\n"


def pp_fields(geometry: Geometry, model: str, dmin_mm: int, dmax_mm: int, amin: int,
              amax: int) -> dict[str, str]:
    """The PP reply's fields for a device."""
    return {"MODL": model, "DMIN": str(dmin_mm), "DMAX": str(dmax_mm),
            "ARES": str(geometry.ares), "AMIN": str(amin), "AMAX": str(amax),
            "AFRT": str(geometry.afrt), "SCAN": str(geometry.scan_rpm)}


def ranges_to_mm(ranges_m: NDArray[np.floating], chars: int) -> NDArray[np.int64]:
    """Ranges in metres to wire millimetres; NaN, ≤ 0 or too long for ``chars`` → 0 (error)."""
    mm = np.rint(np.asarray(ranges_m, dtype=np.float64) * 1000.0)
    top = (1 << (BITS_PER_CHAR * chars)) - 1
    ok = np.isfinite(mm) & (mm >= MIN_VALID_RANGE_MM) & (mm <= top)
    return np.where(ok, mm, 0.0).astype(np.int64)


def encode_scan(command: bytes, start_step: int, end_step: int, cluster: int,
                time_ms: int, ranges_m: NDArray[np.floating],
                echo: NDArray[np.integer] | None = None, skip: int = 0,
                remaining: int = 0, status: str = "99") -> bytes:
    """One scan message: echo, status, timestamp and data (``command`` MD/ME/MS streaming,
    GD/GE/GS single)."""
    if command not in DATA_COMMANDS:
        raise ProtocolError(f"command {command!r}: not a SCIP data command "
                            f"({', '.join(c.decode() for c in DATA_COMMANDS)})")
    chars, per_step = DATA_COMMANDS[command]
    mm = ranges_to_mm(ranges_m, chars)
    if per_step == 2:
        intensity = np.zeros(mm.size, np.int64) if echo is None else np.asarray(echo, np.int64)
        values = np.stack([mm, np.clip(intensity, 0, (1 << 18) - 1)], axis=1).ravel()
    else:
        values = mm
    if command[:1] == b"M":
        echo_line = b"%s%04d%04d%02d%01d%02d\n" % (command, start_step, end_step, cluster,
                                                     skip, remaining)
    else:
        echo_line = b"%s%04d%04d%02d\n" % (command, start_step, end_step, cluster)
    return (echo_line + status_line(status) + timestamp_line(time_ms)
            + data_block(encode_values(values, chars)) + b"\n")


def encode_profile(profile: Profile) -> bytes:
    """A profile as an ``MD`` (``ME`` with echo) streaming message; a PP reply goes first for
    a geometry other than the assumed UST/UTM one."""
    geometry = geometry_for_step(profile.step_deg)
    cluster = round(profile.step_deg / geometry.step_deg)
    start = geometry.step_of(profile.start_angle_deg)
    n = len(profile.ranges_m)
    end = start + max(n - 1, 0) * cluster + cluster - 1
    command = b"MD" if profile.echo is None else b"ME"
    prefix = b""
    if geometry != UST_GEOMETRY:
        # the URG-04LX's DMAX, or beyond it the longest range sent (the decoder takes values
        # above DMAX for no return)
        ranges = np.asarray(profile.ranges_m, np.float64)
        finite = ranges[np.isfinite(ranges)]
        dmax = max(5600, int(np.ceil(finite.max() * 1000.0)) if finite.size else 0)
        prefix = parameter_reply(b"PP", pp_fields(geometry, "URG-04LX", 20, dmax, 44, 725))
    time_ms = profile.device_time_ms or 0
    return prefix + encode_scan(command, start, end, cluster, time_ms, profile.ranges_m,
                                profile.echo)


def check_frame(profiles: list[Profile] | None) -> int | None:
    """Angles a SCIP device can send (its zero lies inside its field of view)."""
    return check_plausible(profiles, min_start_deg=-180.0)


def decode_payload(payload: bytes, checksum_ok: bool) -> list[Profile] | None:
    """One message decoded on its own (UST/UTM geometry unless it is a PP reply)."""
    reader = ScipReader()
    message = payload if payload.endswith(TERMINATOR) else payload + TERMINATOR
    frames = reader.feed(message) + reader.finish()
    if not frames:
        raise ProtocolError("not a SCIP message")
    parsed: list[Profile] | None = frames[0].parsed
    return parsed


class _Bad(Exception):
    """A message that does not parse (false start)."""


class ScipReader:
    """SCIP byte stream in (chunks of any size), messages out, resyncing past false starts.

    A message runs up to the next LF LF. One that does not parse (no echo line, a malformed
    status or timestamp, a data length that disagrees with the echo) is a false start: decoding
    resumes at the next line that could begin a message. A scan whose check characters fail is
    a checksum failure, unless another echo line begins inside it (a cut that lost the
    terminator): then it is a false start too, so the message after the cut is still found.
    ``RawFrame.parsed`` is the scan's profiles, or None for a non-scan reply.
    """

    def __init__(self, geometry: Geometry | None = None) -> None:
        self.counters = FrameCounters()
        self.geometry = geometry or Geometry()
        self.geometry_from_device = geometry is not None
        #: The ranges the device measures, ``DMIN`` … ``DMAX`` mm, from its PP reply (values
        #: outside are its codes for no echo, too near, interference …: no return, as
        #: urg_library's ``urg_distance_min_max`` and urg_node's range_min/range_max take
        #: them). Without a PP reply: the 20 mm error-code floor, no upper bound.
        self.range_limits_mm: tuple[int, int | None] = (MIN_VALID_RANGE_MM, None)
        self.scans_decoded = 0
        #: The last non-scan reply's (command, status), for drivers.
        self.last_status: tuple[str, str] | None = None
        self._buf = bytearray()
        self._offset = 0  # stream offset of _buf[0]
        # The echo line has no check character: a stream's scans must repeat the parameters
        # the device acknowledged (or, without an acknowledgement, the first scan's; two
        # scans agreeing on other parameters replace them).
        self._stream_params: bytes | None = None
        self._candidate: bytes | None = None

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[RawFrame]:
        """Add bytes; return the messages they complete."""
        self._buf += chunk
        return self._drain(final=False)

    def finish(self) -> list[RawFrame]:
        """End of stream: an incomplete message is a false start (its bytes are skipped)."""
        frames = self._drain(final=True)
        if self._buf:
            self.counters.bytes_skipped += len(self._buf)
            self.counters.resyncs += 1
            self._offset += len(self._buf)
            self._buf.clear()
        return frames

    def stream_warnings(self) -> list[str]:
        """Scans decoded before any PP reply: their angles assume the default geometry."""
        if self.geometry_from_device or not self.scans_decoded:
            return []
        return [f"no SCIP PP reply before the scans: their angles assume the UST/UTM geometry "
                f"(ARES {DEFAULT_ARES}, AFRT {DEFAULT_AFRT}); another model (a URG-04LX: "
                "1024, 384) decodes with wrong angles (scanpipe record asks for PP first)"]

    def _drain(self, final: bool) -> list[RawFrame]:
        frames: list[RawFrame] = []
        buf = self._buf
        pos = 0
        terminators = _terminators(buf)
        while True:
            pending: list[RawFrame | _Scan] = []
            pos = self._collect(buf, pos, pending, terminators)
            done, restart = self._finish_scans(pending)
            frames += done
            if restart is None:
                break
            pos = self._resync(buf, restart - self._offset, len(buf))
        del buf[:pos]
        self._offset += pos
        return frames

    def _collect(self, buf: bytearray, pos: int, pending: list[RawFrame | _Scan],
                 terminators: list[int]) -> int:
        """Cut complete messages from ``buf`` at ``pos``: replies parsed, scans checked for
        structure only (their data is checked and decoded together, :meth:`_finish_scans`).
        ``terminators``: where LF LF begins in ``buf`` (:func:`_terminators`)."""
        while True:
            # A message starts at the buffer start or after a LF; skip stray LFs.
            while pos < len(buf) and buf[pos] == LF:
                pos += 1
                self.counters.bytes_skipped += 1
            at = bisect_left(terminators, pos)
            end = terminators[at] if at < len(terminators) else -1
            if end < 0:
                if len(buf) - pos > MAX_MESSAGE_BYTES:
                    pos = self._resync(buf, pos, len(buf))
                    continue
                return pos
            end += 2
            if end - pos > MAX_MESSAGE_BYTES:
                pos = self._resync(buf, pos, end)
                continue
            try:
                pending.append(self._parse(bytes(buf[pos:end]), self._offset + pos))
            except _Bad:
                pos = self._resync(buf, pos, end)
                continue
            pos = end

    def _resync(self, buf: bytearray, pos: int, end: int) -> int:
        """Past a false start: the next line, or a data echo beginning inside this line."""
        self.counters.resyncs += 1
        m = _RESYNC.search(buf, pos + 1, end)
        nxt = end if m is None else (m.end() if m.group(0) == b"\n" else m.start())
        self.counters.bytes_skipped += nxt - pos
        return nxt

    def _parse(self, message: bytes, offset: int) -> RawFrame | _Scan:
        # Scans are split only into echo, status, timestamp and the rest (checked in batch).
        lines = message[:-2].split(b"\n", 3)
        echo = lines[0]
        end = offset + len(message)
        if _is_scip11_scan(message):
            raise ProtocolError(
                "Hokuyo SCIP 1.1 scan data (a 'G' reply: one-character status, no check "
                "characters; a URG-04LX with old firmware or not switched): not supported; "
                "scanpipe reads SCIP 2.0 — switch the device with the command 'SCIP2.0' "
                "(urg_library does; firmware without it needs an update) and stream MD/GD")
        if len(echo) < 2 or not echo[:2].isalpha() or not echo[:2].isupper():
            raise _Bad
        command = echo[:2]
        if command in MULTI_ECHO_COMMANDS:
            if len(lines) >= 2 and _status_ok(lines[1]) and _MULTI_ECHO.match(echo):
                raise ProtocolError(f"SCIP multi-echo data ({command.decode()}): not supported; "
                                    f"stream MD/ME/GD/GE (first echo) instead")
            raise _Bad
        scip11 = len(lines) == 2 and len(lines[1]) == 1 and (echo.isalnum()
                                                             or echo == SCIP20_SWITCH)
        if scip11 or (echo == SCIP20_SWITCH and len(lines) == 2 and _status_ok(lines[1])):
            # A SCIP 1.1 answer (one-character status, no check character, no data): what a
            # URG in SCIP 1.1 answers a SCIP 2.0 command ('E') and the switch ('0'); or a SCIP
            # 2.0 device's answer to the switch. The recorder's driver reads them
            # (docs/protocols.md); a decode counts them as other frames.
            self.last_status = (echo.decode("ascii", "replace"),
                                lines[1].decode("ascii", "replace"))
            return RawFrame(message, True, 0, 0, offset, end, None)
        if len(lines) < 2 or len(lines[1]) != 3:
            raise _Bad
        status_ok = _status_ok(lines[1])
        status = lines[1][:2].decode("ascii", "replace")
        if command in DATA_COMMANDS and len(lines) > 2:
            return self._parse_scan(message, lines, offset, end, status_ok)
        lines = message[:-2].split(b"\n")
        if not status_ok or _DATA_ECHO.search(message, 1) is not None \
                or not all(_parameter_ok(line) for line in lines[2:]):
            raise _Bad  # a reply's further lines are NAME:value;check (VV, PP, II)
        self.last_status = (command.decode("ascii", "replace"), status)
        if command == b"PP" and status == "00":
            self._read_parameters(lines[2:])
        return RawFrame(message, True, 0, 0, offset, end, None)

    def _read_parameters(self, lines: list[bytes]) -> None:
        fields: dict[str, str] = {}
        for line in lines:
            text = line[:-2]
            if not _parameter_ok(line) or b":" not in text:
                return  # a damaged PP reply teaches nothing
            name, _, value = text.partition(b":")
            fields[name.decode("ascii", "replace")] = value.decode("ascii", "replace")
        try:
            ares, afrt = int(fields["ARES"]), int(fields["AFRT"])
            rpm = int(fields.get("SCAN", "0"))
            dmin = int(fields.get("DMIN", str(MIN_VALID_RANGE_MM)))
            dmax: int | None = int(fields["DMAX"]) if "DMAX" in fields else None
        except (KeyError, ValueError):
            return
        if dmax is not None and dmax <= dmin:
            dmax = None  # a reply that makes no sense keeps only the error-code floor
        if 0 < ares <= 1 << 16 and 0 <= afrt < ares:
            self.geometry = Geometry(ares, afrt, rpm)
            self.geometry_from_device = True
            self.range_limits_mm = (max(dmin, MIN_VALID_RANGE_MM), dmax)

    def _echo_agrees(self, params: bytes) -> bool:
        if self._stream_params is None or self._stream_params == params:
            self._stream_params, self._candidate = params, None
            return True
        if self._candidate == params:  # two scans agree: the parameters changed
            self._stream_params, self._candidate = params, None
            return True
        self._candidate = params
        return False

    def _parse_scan(self, message: bytes, lines: list[bytes], offset: int, end: int,
                    status_ok: bool) -> _Scan:
        command = lines[0][:2]
        match = (_STREAM_ECHO if command[:1] == b"M" else _SINGLE_ECHO).match(lines[0])
        if match is None:
            raise _Bad
        start, last, cluster = int(match[2]), int(match[3]), max(int(match[4]), 1)
        if last < start:
            raise _Bad
        chars, per_step = DATA_COMMANDS[command]
        count = -(-(last - start + 1) // cluster)
        stamp = lines[2]
        if len(stamp) != 5:
            raise _Bad
        n_chars = count * chars * per_step
        body_start = len(lines[0]) + len(lines[1]) + len(stamp) + 3
        full, tail = divmod(n_chars, DATA_LINE_CHARS)
        if len(message) - 1 - body_start != full * (DATA_LINE_CHARS + 2) + (tail + 2 if tail
                                                                             else 0):
            raise _Bad
        return _Scan(message, offset, end, body_start, n_chars, chars, per_step, start, last,
                     cluster, status_ok, command[:1] == b"M", self.geometry,
                     self.range_limits_mm)

    def _finish_scans(self, pending: list[RawFrame | _Scan]
                      ) -> tuple[list[RawFrame], int | None]:
        """Check and decode the collected scans together (one numpy pass per layout); the
        frames in order, and the stream offset to resync at when a scan failed its check
        characters with another message's echo inside it (then later messages are redone)."""
        scans = [x for x in pending if isinstance(x, _Scan)]
        layouts: dict[tuple[int, int, int], list[_Scan]] = {}
        for scan in scans:
            layouts.setdefault((scan.n_chars, scan.chars, scan.per_step), []).append(scan)
        for (n_chars, chars, per_step), group in layouts.items():
            _decode_group(group, n_chars, chars, per_step)
        frames: list[RawFrame] = []
        for item in pending:
            if isinstance(item, RawFrame):
                echo, _, rest = item.payload.partition(b"\n")
                if rest[:3] == b"00P" and _STREAM_ECHO.match(echo):  # a stream acknowledged
                    self._stream_params, self._candidate = echo[:STREAM_PARAM_CHARS], None
                frames.append(item)
                continue
            ok = item.ok
            if ok and item.stream:
                ok = self._echo_agrees(item.message[:STREAM_PARAM_CHARS])
            if not ok and _DATA_ECHO.search(item.message, 1) is not None:
                return frames, item.offset
            profile = item.profile(ok)
            if ok:
                try:
                    check_frame([profile])
                except ImplausibleFrame:
                    self.counters.implausible_frames += 1
                    return frames, item.offset
            else:
                self.counters.checksum_failures += 1
            frames.append(RawFrame(item.message, ok, 0, 0, item.offset, item.end, [profile]))
            self.scans_decoded += 1
        return frames, None


@dataclass
class _Scan:
    """A scan message whose structure is sound; data checked and decoded in a batch."""

    message: bytes
    offset: int
    end: int
    body_start: int
    n_chars: int
    chars: int
    per_step: int
    start: int
    last: int
    cluster: int
    status_ok: bool
    stream: bool
    geometry: Geometry
    limits_mm: tuple[int, int | None]
    ok: bool = False
    time_ms: int = 0
    ranges: NDArray[np.float32] | None = None
    echo: NDArray[np.uint16] | None = None

    def profile(self, ok: bool) -> Profile:
        """The decoded profile."""
        assert self.ranges is not None
        g = self.geometry
        end_ms = None
        if g.scan_rpm > 0:
            span_s = (self.last - self.start + 1) / g.ares * 60.0 / g.scan_rpm
            end_ms = (self.time_ms + round(span_s * 1000.0)) % TIMESTAMP_WRAP_MS
        return Profile(frame=self.time_ms & 0xFFFF, sector=0,
                       start_angle_deg=g.angle_deg(self.start),
                       step_deg=self.cluster * g.step_deg, ranges_m=self.ranges,
                       echo=self.echo,
                       device_time_ms=self.time_ms, device_end_time_ms=end_ms,
                       checksum_ok=ok, device_tick_ns=1_000_000,
                       device_wrap_ticks=TIMESTAMP_WRAP_MS)


def _decode_group(group: list[_Scan], n_chars: int, chars: int, per_step: int) -> None:
    """Check characters and values of scans of one layout, all at once."""
    k = len(group)
    full, tail = divmod(n_chars, DATA_LINE_CHARS)
    line = DATA_LINE_CHARS + 2
    body_len = full * line + (tail + 2 if tail else 0)
    # Timestamp line (4 chars + check) sits just before the body.
    blob = np.frombuffer(b"".join(s.message[s.body_start - 6:s.body_start + body_len]
                                  for s in group), np.uint8).reshape(k, body_len + 6)
    stamp = blob[:, :4].astype(np.int32)
    ok = ((stamp.sum(axis=1) & 0x3F) + CHAR_OFFSET) == blob[:, 4]
    times = ((stamp - CHAR_OFFSET) & 0x3F) @ np.array([1 << 18, 1 << 12, 1 << 6, 1], np.int32)
    body = blob[:, 6:]
    head = body[:, :full * line].reshape(k, full, line)
    ok &= (head[:, :, DATA_LINE_CHARS + 1] == LF).all(axis=1)
    # sums in uint8 wrap modulo 256, a multiple of the check's 64 (and need no widening copy)
    sums = (head[:, :, :DATA_LINE_CHARS].sum(axis=2, dtype=np.uint8) & 0x3F) + CHAR_OFFSET
    ok &= (sums == head[:, :, DATA_LINE_CHARS]).all(axis=1)
    data = head[:, :, :DATA_LINE_CHARS].reshape(k, full * DATA_LINE_CHARS)
    if tail:
        rest = body[:, full * line:]
        tail_sum = (rest[:, :tail].sum(axis=1, dtype=np.uint8) & 0x3F) + CHAR_OFFSET
        ok &= (tail_sum == rest[:, tail]) & (rest[:, tail + 1] == LF)
        data = np.concatenate([data, rest[:, :tail]], axis=1)
    digits = (data.reshape(k, -1, chars) - np.uint8(CHAR_OFFSET)) & np.uint8(0x3F)
    values = digits[:, :, 0].astype(np.int32)
    for c in range(1, chars):
        values <<= BITS_PER_CHAR
        values |= digits[:, :, c]
    echo = None
    if per_step == 2:
        echo = np.minimum(values[:, 1::2], 65535).astype(np.uint16)
        values = values[:, 0::2]
    ranges = values.astype(np.float32) * np.float32(0.001)
    # each scan's own device limits (a PP reply may arrive between scans of one feed)
    low = np.array([s.limits_mm[0] for s in group], np.int32)[:, None]
    high = np.array([s.limits_mm[1] or (1 << 30) for s in group], np.int32)[:, None]
    ranges[(values < low) | (values > high)] = np.nan
    for row, scan in enumerate(group):
        scan.ok = bool(ok[row]) and scan.status_ok
        scan.time_ms = int(times[row])
        scan.ranges = ranges[row]
        scan.echo = None if echo is None else echo[row]


def _is_scip11_scan(message: bytes) -> bool:
    """Whether ``message`` (ending LF LF) is a whole SCIP 1.1 ``G`` reply: the echo, a
    one-character status, then exactly the 2-character ranges the echo asks for in lines of
    at most 64 characters (no check characters)."""
    if message[:1] != b"G":
        return False
    lines = message[:-2].split(b"\n")
    match = _SCIP11_ECHO.match(lines[0])
    if match is None or len(lines) < 3 or len(lines[1]) != 1:
        return False
    start, end, cluster = int(match[1]), int(match[2]), max(int(match[3]), 1)
    if end < start:
        return False
    body = lines[2:]
    if any(len(line) > DATA_LINE_CHARS for line in body) or any(
            len(line) != DATA_LINE_CHARS for line in body[:-1]):
        return False
    return sum(len(line) for line in body) == 2 * -(-(end - start + 1) // cluster)


def _terminators(buf: bytearray) -> list[int]:
    """Every position where LF LF begins in ``buf``, in order (``buf.find(TERMINATOR, pos)`` for
    every ``pos`` at once: ``find`` stops at every line's LF, ~8 µs per UST scan against ~3)"""
    data = np.frombuffer(buf, np.uint8)
    lf = data == LF
    del data  # the bytearray may be resized again
    both = lf[:-1]
    both &= lf[1:]
    found: list[int] = np.flatnonzero(both).tolist()
    return found


def _parameter_ok(line: bytes) -> bool:
    # NAME:value ; check — the check character itself may be a ';'.
    return len(line) >= 3 and line[-2:-1] == b";" and check_char(line[:-2]) == line[-1]


def _status_ok(line: bytes) -> bool:
    return len(line) == 3 and check_char(line[:2]) == line[2]


def reader_factory(dialect: object, max_payload_bytes: int, confirm: bool) -> ScipReader:
    """The registry's reader for the ``scip`` dialect."""
    return ScipReader()
