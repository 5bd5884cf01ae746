"""ASTM E57 point clouds (pye57 / libE57Format): z up, (x, −z, y) from the rig frame.

Intensity is the echo value, colour the 8-bit RGB; one scan named after the export.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from scanpipe.errors import ExportError
from scanpipe.exporters.model import CloudModel, rig_to_z_up


def e57_bytes(cloud: CloudModel, name: str = "scan") -> bytes:
    """The cloud as an E57 file (libE57Format writes only to paths: via a temporary file)."""
    if len(cloud.xyz) == 0:
        raise ExportError("points: no points to write")
    xyz = rig_to_z_up(cloud.xyz)
    data: dict[str, np.ndarray] = {
        "cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2],
    }
    if cloud.intensity is not None:
        data["intensity"] = cloud.intensity.astype(np.float32)
    if cloud.colors is not None:
        data["colorRed"] = cloud.colors[:, 0].copy()
        data["colorGreen"] = cloud.colors[:, 1].copy()
        data["colorBlue"] = cloud.colors[:, 2].copy()
    import pye57  # here, not at import: only an E57 export needs it

    with tempfile.TemporaryDirectory(prefix="scanpipe-e57-") as tmp:
        path = Path(tmp) / "scan.e57"
        try:
            writer = pye57.E57(str(path), mode="w")
            try:
                writer.write_scan_raw(data, name=name)
            finally:
                writer.close()
        except Exception as err:  # libE57Format raises its own exception types
            raise ExportError(f"E57 writer failed: {err}") from err
        return path.read_bytes()
