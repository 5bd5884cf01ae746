"""E57 export as other readers take it: ``intensityLimits`` are the echo's range (0…65535), not
the data's extremes (PDAL's E57 reader rescales intensity by the limits: data limits would
stretch every scan's intensities to 0…65535 differently), and ``cartesianBounds`` are in the
scan's own frame (ASTM E57 §8.4.5), also for a scan with a pose."""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from scanpipe.exporters.e57 import E57Scan, write_e57
from scanpipe.exporters.model import CloudModel, rig_to_z_up


def _xml(data: bytes) -> ET.Element:
    """The XML section of an E57 file (pages of 1020 data bytes + a CRC)."""
    xml_offset, xml_length, page_size = struct.unpack_from("<QQQ", data, 24)
    payload, position = bytearray(), xml_offset
    while len(payload) < xml_length:
        end = position - position % page_size + page_size - 4
        payload += data[position:end]
        position = end + 4
    text = bytes(payload[:xml_length]).decode()
    return ET.fromstring(re.sub(r'\sxmlns(:\w+)?="[^"]+"', "", text))


def _value(node: ET.Element, path: str) -> float:
    """A Float element's value; libE57 writes an empty element for 0 (the XML default)."""
    text = node.findtext(path)
    assert text is not None, path
    return float(text or 0.0)


def test_intensity_limits_are_the_echo_range_and_bounds_the_scan_frame(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    xyz = rng.uniform((-3.0, -1.0, -2.0), (3.0, 2.0, 4.0), (500, 3)).astype(np.float32)
    echo = rng.integers(300, 15000, 500).astype(np.uint16)
    half = np.sqrt(0.5)
    scan = E57Scan(CloudModel(xyz, intensity=echo), "s1",
                   rotation_wxyz=(half, 0.0, 0.0, half),  # 90° about z
                   translation_m=(10.0, 20.0, 1.5))
    path = tmp_path / "site.e57"
    write_e57(path, [scan])
    node = _xml(path.read_bytes()).find("./data3D/vectorChild")
    assert node is not None
    assert _value(node, "intensityLimits/intensityMinimum") == 0.0
    assert _value(node, "intensityLimits/intensityMaximum") == 65535.0
    local = rig_to_z_up(xyz)
    for axis, column in zip("xyz", local.T, strict=True):
        assert abs(_value(node, f"cartesianBounds/{axis}Minimum")
                   - column.min()) < 1e-5
        assert abs(_value(node, f"cartesianBounds/{axis}Maximum")
                   - column.max()) < 1e-5
