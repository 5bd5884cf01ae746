"""import-capture → decode on a capture nobody here made: SICK's own TiM5xx pcapng (the
scanner streams CoLa-B, the capture starts mid-connection). Every profile that lands in the
workdir equals the one read at the SICK driver's offsets."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
from test_protocol_sick_cola import FIXTURE, _reference_scans

from scanpipe.captureio import load_scanner_capture


def test_public_sick_capture_through_import_capture_and_decode(tmp_path: Path,
                                                               cli: Any) -> None:
    out = tmp_path / "tim.mcap"
    result = cli("import-capture", FIXTURE, "--out", out)
    assert result.code == 0, result.err
    assert "(cola_b)" in result.out and "no SYN seen" in result.err
    result = cli("decode", out, "--out", tmp_path / "dec", "-q")
    assert result.code == 0, result.err
    profiles = pq.read_table(tmp_path / "dec" / "profiles.parquet")
    capture = load_scanner_capture(FIXTURE)
    reference = _reference_scans(b"".join(chunk for _, chunk in capture.received.chunks))
    assert profiles.num_rows == len(reference) == 16
    assert profiles.column("dialect").to_pylist() == ["cola_b"] * 16
    for k, (counter, start, step, ranges) in enumerate(reference):
        assert profiles.column("frame")[k].as_py() == counter
        assert profiles.column("start_angle_deg")[k].as_py() == start
        assert abs(profiles.column("step_deg")[k].as_py() - step) < 1e-9
        got = np.array(profiles.column("ranges_m")[k].as_py(), np.float64)
        expected = np.array(ranges)
        assert np.array_equal(np.isnan(got), expected == 0.0)
        np.testing.assert_allclose(got[expected > 0], expected[expected > 0], atol=1e-6)
