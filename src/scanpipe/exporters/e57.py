"""ASTM E57 point clouds (pye57 / libE57Format): z up, (x, −z, y) from the rig frame.

One ``data3D`` scan per :class:`E57Scan` (one per scan position), each with its pose (the
scan's own frame → the file's frame), ``rowIndex`` / ``columnIndex`` (the scan grid: profile ×
sample) where the cloud has a grid, ``intensity`` (the echo value, limits 0..65535) and the
8-bit colour. The provenance record (JSON) is the scan's ``sensorModel`` string (pye57 fixes
``description``), ``sensorVendor`` is ``scanpipe`` and ``sensorSoftwareVersion`` its version.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ExportError
from scanpipe.exporters.model import CloudModel, rig_to_z_up


@dataclass(frozen=True)
class E57Scan:
    """One scan position: its cloud (rig frame of that position), name and pose.

    ``rotation_wxyz`` / ``translation_m`` map the scan's z-up frame into the file's frame
    (identity: the scan is the file's frame). ``description``: free text (e.g. provenance).
    """

    cloud: CloudModel
    name: str = "scan"
    rotation_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    description: str = ""


def _scan_data(cloud: CloudModel) -> dict[str, NDArray[Any]]:
    xyz = rig_to_z_up(cloud.xyz)
    data: dict[str, NDArray[Any]] = {
        "cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2],
    }
    if cloud.intensity is not None:
        data["intensity"] = cloud.intensity.astype(np.float32)
    if cloud.colors is not None:
        data["colorRed"] = cloud.colors[:, 0].copy()
        data["colorGreen"] = cloud.colors[:, 1].copy()
        data["colorBlue"] = cloud.colors[:, 2].copy()
    if (cloud.profile is not None and cloud.sample is not None
            and bool(np.all(cloud.profile >= 0)) and bool(np.all(cloud.sample >= 0))):
        data["rowIndex"] = cloud.profile.astype(np.int32)
        data["columnIndex"] = cloud.sample.astype(np.int32)
    return data


def write_e57(path: Path, scans: Sequence[E57Scan]) -> None:
    """Write ``scans`` (one ``data3D`` entry each, in order) to the E57 file ``path``."""
    import pye57  # here, not at import: only an E57 export needs it

    if not scans:
        raise ExportError(f"{path}: an E57 file needs at least one scan")
    for scan in scans:
        if len(scan.cloud.xyz) == 0:
            raise ExportError(f"scan {scan.name!r}: no points to write")
    try:
        writer = pye57.E57(str(path), mode="w")
        try:
            for scan in scans:
                writer.write_scan_raw(_scan_data(scan.cloud), name=scan.name,
                                      rotation=np.asarray(scan.rotation_wxyz, np.float64),
                                      translation=np.asarray(scan.translation_m, np.float64))
                _describe(writer, len(writer.data3d) - 1, scan)
        finally:
            writer.close()
    except ExportError:
        raise
    except Exception as err:  # libE57Format raises its own exception types
        raise ExportError(f"E57 writer failed: {err}") from err


def _describe(writer: Any, index: int, scan: E57Scan) -> None:
    """Name the software and carry the provenance: data3D's optional ``sensorSoftwareVersion``
    and ``sensorModel`` strings (pye57 wrote its own ``description``, which cannot be set
    twice)."""
    import pye57.libe57 as libe57

    from scanpipe import __version__

    node = writer.data3d[index]
    node.set("sensorVendor", libe57.StringNode(writer.image_file, "scanpipe"))
    node.set("sensorSoftwareVersion", libe57.StringNode(writer.image_file, __version__))
    if scan.description:
        node.set("sensorModel", libe57.StringNode(writer.image_file, scan.description))


def e57_bytes(cloud: CloudModel, name: str = "scan", description: str = "") -> bytes:
    """The cloud as an E57 file of one scan (libE57Format writes only to paths: via a
    temporary file)."""
    with tempfile.TemporaryDirectory(prefix="scanpipe-e57-") as tmp:
        path = Path(tmp) / "scan.e57"
        write_e57(path, [E57Scan(cloud, name, description=description)])
        return path.read_bytes()
