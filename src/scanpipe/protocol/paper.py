"""The ``paper`` dialect: the scanner frame printed in the paper (SICK CoLa-B framing).

Frame: ``02 02 02 02``, u32 big-endian length of the data, the data, one XOR byte of the data.
Data (all big-endian u16 after the header):

====== ===== ===================================================================
offset bytes  field
====== ===== ===================================================================
0      11     reply header, ``73 52 41`` ("sRA") and 8 bytes the paper leaves unexplained
11     2      frame number
13     2      unexplained (0 in the paper's sample)
15     2      angular step, 1/16° (eq. 5)
17     2      number of samples n
19     2      start angle, 1/16°
21     2·n    distances, 1/256 m (eq. 6); 0 = no return
====== ===== ===================================================================

There is no device timestamp, no echo and one sector per frame.
"""

from __future__ import annotations

import numpy as np

from scanpipe.errors import ProtocolError
from scanpipe.protocol.framing import LengthMismatch, encode_frame
from scanpipe.protocol.profile import (
    ANGLE_SCALE_PER_DEG,
    Profile,
    angle_to_wire,
    check_plausible,
    ranges_from_wire,
    ranges_to_wire,
)

MARKER = b"\x02\x02\x02\x02"
#: The 11 header bytes of the paper's sample ("sRA" and 8 unexplained bytes), reproduced as is.
REPLY_HEADER = bytes.fromhex("73524100 62000c81 ba0101".replace(" ", ""))
HEADER_BYTES = 21
MAX_SAMPLES = 0xFFFF
MAX_PAYLOAD_BYTES = HEADER_BYTES + 2 * MAX_SAMPLES


def payload_bytes(samples: int) -> int:
    """Data bytes of a frame with ``samples`` distances."""
    return HEADER_BYTES + 2 * samples


def encode_payload(profile: Profile) -> bytes:
    """The data part of a frame for ``profile`` (frame number modulo 2¹⁶)."""
    n = len(profile.ranges_m)
    if n > MAX_SAMPLES:
        raise ProtocolError(f"profile of {n} samples: the paper frame holds at most {MAX_SAMPLES}")
    fields = np.array([profile.frame & 0xFFFF, 0, angle_to_wire(profile.step_deg), n,
                       angle_to_wire(profile.start_angle_deg)], dtype=">u2")
    distances = ranges_to_wire(profile.ranges_m).astype(">u2")
    return REPLY_HEADER + fields.tobytes() + distances.tobytes()


def encode_profile(profile: Profile) -> bytes:
    """One whole frame (marker, length, data, XOR) carrying ``profile``."""
    return encode_frame(MARKER, encode_payload(profile))


def is_profile_payload(payload: bytes) -> bool:
    """Whether ``payload`` has the layout above: the "sRA" header and a consistent length."""
    if len(payload) < HEADER_BYTES or payload[:3] != REPLY_HEADER[:3]:
        return False
    return len(payload) == payload_bytes(int.from_bytes(payload[17:19], "big"))


def decode_payload(payload: bytes, checksum_ok: bool = True) -> list[Profile]:
    """The one profile in a frame's data; :class:`ProtocolError` when the layout does not fit
    (:class:`~scanpipe.protocol.framing.LengthMismatch` when the sample count disagrees with
    the length)."""
    if len(payload) < HEADER_BYTES or payload[:3] != REPLY_HEADER[:3]:
        raise ProtocolError(f"paper frame of {len(payload)} data bytes: expected the 'sRA' "
                            f"header and 21 + 2·samples bytes")
    samples = int.from_bytes(payload[17:19], "big")
    if len(payload) != payload_bytes(samples):
        raise LengthMismatch(f"paper frame of {len(payload)} data bytes declares {samples} "
                             f"samples: expected 21 + 2·samples = {payload_bytes(samples)}")
    head = np.frombuffer(payload, dtype=">u2", count=5, offset=11)
    wire = np.frombuffer(payload, dtype=">u2", offset=HEADER_BYTES)
    return [Profile(
        frame=int(head[0]),
        sector=0,
        start_angle_deg=float(head[4]) / ANGLE_SCALE_PER_DEG,
        step_deg=float(head[2]) / ANGLE_SCALE_PER_DEG,
        ranges_m=ranges_from_wire(wire),
        checksum_ok=checksum_ok,
    )]


def check_frame(profiles: list[Profile] | None) -> int | None:
    """The frame number of a decoded frame; ``ImplausibleFrame`` for angles no 360° scanner
    sends (see :func:`scanpipe.protocol.profile.check_plausible`)."""
    return check_plausible(profiles)
