"""LAS 1.4 / LAZ point clouds (laspy): z up, (x, −z, y) from the rig frame.

Intensity is the scanner's echo value; colour (8-bit in the points artifact) is scaled to LAS's
16 bits (× 257). GPS time holds the measurement time in seconds since the Unix epoch.
"""

from __future__ import annotations

import io

import numpy as np

from scanpipe.errors import ExportError
from scanpipe.exporters.model import CloudModel, rig_to_z_up

#: Coordinate resolution: 0.1 mm, well below the scanner's 3.9 mm range step.
SCALE_M = 0.0001


def las_bytes(cloud: CloudModel, compressed: bool = False) -> bytes:
    """The cloud as a LAS (or, with ``compressed``, LAZ) file."""
    import laspy  # here, not at import: only an LAS export needs it

    if len(cloud.xyz) == 0:
        raise ExportError("points: no points to write")
    xyz = rig_to_z_up(cloud.xyz)
    has_time = cloud.time_ns is not None
    point_format = (3 if has_time else 2) if cloud.colors is not None else (1 if has_time else 0)
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales = np.array([SCALE_M] * 3)
    header.offsets = np.floor(xyz.min(axis=0))
    header.generating_software = "scanpipe"
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if cloud.intensity is not None:
        las.intensity = cloud.intensity
    if cloud.colors is not None:
        colors16 = cloud.colors.astype(np.uint16) * 257
        las.red, las.green, las.blue = colors16[:, 0], colors16[:, 1], colors16[:, 2]
    if cloud.time_ns is not None:
        las.gps_time = cloud.time_ns.astype(np.float64) / 1e9
    stream = io.BytesIO()
    try:
        las.write(stream, do_compress=compressed,
                  laz_backend=laspy.LazBackend.Lazrs if compressed else None)
    except laspy.errors.LaspyException as err:
        raise ExportError(f"LAS/LAZ writer failed: {err}") from err
    return stream.getvalue()
