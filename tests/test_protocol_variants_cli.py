"""The user's path for protocol variants scanpipe refuses or now reads: ``scanpipe frames`` on
the raw bytes (auto-detected), one line and exit code 1 for a refusal, no traceback."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from scanpipe.protocol import sick_cola
from scanpipe.protocol.profile import Profile

FIXTURES = Path(__file__).parent / "fixtures"


def _mrs_layers() -> bytes:
    flat = sick_cola.profile_telegram(Profile(
        frame=1, sector=0, start_angle_deg=-45.0, step_deg=0.5,
        ranges_m=np.full(541, 2.0, np.float32), echo=None, device_time_ms=1000))
    return b"".join(sick_cola.encode_frame(sick_cola.MARKER, sick_cola.encode_telegram(
        dataclasses.replace(flat, layer_angle=a, scan_counter=k)))
        for k, a in enumerate((0, -250, 250, 500) * 4))


def _scip11() -> bytes:
    data = bytes([(1000 >> 6) + 0x30, (1000 & 0x3F) + 0x30]) * 682
    lines = b"".join(data[i:i + 64] + b"\n" for i in range(0, len(data), 64))
    return (b"G04472501\n0\n" + lines + b"\n") * 3


def test_refused_variants_are_one_line(tmp_path: Path, cli: Callable[..., Any]) -> None:
    for name, data, message in (
            ("mrs.bin", _mrs_layers(), "SICK multi-layer telegram (layer angle field -250"),
            ("urg11.bin", _scip11(), "Hokuyo SCIP 1.1 scan data")):
        path = tmp_path / name
        path.write_bytes(data)
        result = cli("frames", path)
        err = result.err.strip()
        assert result.code == 1 and "Traceback" not in err, err
        assert err.count("\n") == 0 and err.startswith("scanpipe: error: ") and message in err
        assert path.read_bytes() == data  # the input is only read


def test_a_real_tim55x_cola_a_stream_reads(tmp_path: Path, cli: Callable[..., Any]) -> None:
    lines = (FIXTURES / "sick" / "tim55x_cola_a_lmdscandata.txt").read_text().splitlines()
    body = [line.encode() for line in lines if not line.startswith("#")]
    path = tmp_path / "tim.bin"
    path.write_bytes(b"".join(b"\x02" + t + b"\x03" for t in body) * 3)
    result = cli("frames", path, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["dialect"] == "cola_a" and len(report["frames"]) == 6
    assert report["counters"]["frames_decoded"] == 6
    assert report["counters"]["malformed_frames"] == 0
