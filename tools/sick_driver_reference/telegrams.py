"""Dev tool (not run in CI): feed a pcap_json_converter capture to SICK's driver harness.

``extract CAPTURE.json`` prints every whole ``sSN LMDscandata`` CoLa-B telegram of the capture
(both directions concatenated, as the test reads them) as one hex line, for ``lmd_harness``.
``fixture CAPTURE.json COMMIT < harness.jsonl`` writes the fixture JSON from the harness output.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def capture_stream(path: Path) -> bytes:
    """The TCP payloads of a pcap_json_converter capture, in order."""
    entries = json.loads(path.read_text())
    return b"".join(bytes.fromhex(e["_source"]["layers"]["tcp"]["tcp.payload"].replace(":", ""))
                    for e in entries)


def scan_telegrams(stream: bytes) -> list[bytes]:
    """Whole CoLa-B frames (02 02 02 02, u32 length, payload, XOR) carrying LMDscandata."""
    frames = []
    pos = stream.find(b"\x02\x02\x02\x02")
    while pos >= 0 and pos + 8 <= len(stream):
        length = int.from_bytes(stream[pos + 4:pos + 8], "big")
        frame = stream[pos:pos + 9 + length]
        if frame[8:24] == b"sSN LMDscandata ":
            frames.append(frame)
        pos = stream.find(b"\x02\x02\x02\x02", pos + 9 + length)
    return frames


def _f32(values: list[float]) -> list[float]:
    # the shortest decimal that reads back to the same float32: the fixture stays small and exact
    return [float(np.format_float_positional(np.float32(v), unique=True, trim="-"))
            for v in values]


def main(argv: list[str]) -> None:
    """Entry point: ``extract`` or ``fixture`` (see the module docstring)."""
    if len(argv) >= 2 and argv[0] == "extract":
        for frame in scan_telegrams(capture_stream(Path(argv[1]))):
            print(frame.hex())
        return
    if len(argv) >= 3 and argv[0] == "fixture":
        frames = scan_telegrams(capture_stream(Path(argv[1])))
        rows = [json.loads(line) for line in sys.stdin if line.strip()]
        if len(rows) != len(frames) or not all(r["ok"] for r in rows):
            raise SystemExit(f"harness answered {len(rows)} scans for {len(frames)} telegrams")
        scans = []
        for frame, row in zip(frames, rows, strict=True):
            scans.append({
                "scan_counter": int.from_bytes(frame[36:38], "big"),
                "num_echos": row["num_echos"],
                "angle_min_rad": _f32([row["angle_min"]])[0],
                "angle_increment_rad": _f32([row["angle_increment"]])[0],
                "angle_max_rad": _f32([row["angle_max"]])[0],
                "scan_time_s": _f32([row["scan_time"]])[0],
                "time_increment_s": _f32([row["time_increment"]])[0],
                "ranges_m": _f32(row["ranges"]),
            })
        doc = {
            "source": "SICKAG/sick_scan_xd driver/src/sick_lmd_scandata_parser.cpp "
                      "parseCommonBinaryResultTelegram(), scanner sick_lms_1xx, run by "
                      "tools/sick_driver_reference/regenerate.sh",
            "sick_scan_xd_commit": argv[2],
            "capture": Path(argv[1]).name,
            "float32": "every number is the shortest decimal of the driver's float32 value",
            "scans": scans,
        }
        sys.stdout.write(json.dumps(doc, separators=(",", ":")).replace('{"scan_counter"',
                                                                          '\n{"scan_counter"'))
        sys.stdout.write("\n")
        return
    raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
