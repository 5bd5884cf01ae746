"""ASTM E57 point clouds (pye57 / libE57Format): z up, (x, −z, y) from the rig frame.

One ``data3D`` scan per :class:`E57Scan` (one per scan position), each with its pose (the
scan's own frame → the file's frame), ``rowIndex`` / ``columnIndex`` (the scan grid: profile ×
sample) where the cloud has a grid, ``intensity`` (the echo value, limits 0..65535) and the
8-bit colour. The provenance record (JSON) is the scan's ``sensorModel`` string (pye57 fixes
``description``), ``sensorVendor`` is ``scanpipe`` and ``sensorSoftwareVersion`` its version.

A georeferenced cloud (``offset_m``, an import shifted so float32 keeps 0.1 mm) keeps its
local coordinates; the offset goes into its scan's pose translation (doubles), so readers that
apply the pose (CloudCompare, PDAL, pye57's ``transform``, scanpipe's import) get the imported
file's coordinates.

One ``images2D`` entry per :class:`E57Image` (a camera frame): the recorded JPEG/PNG bytes in a
``pinholeRepresentation`` and the camera's ``pose`` (camera frame → the file's frame, the frame
the points are written in). The camera frame follows CloudCompare's E57 reader (the
open-source reader of E57 images in widest use): x right, y up, looking along −z, so a point
(x, y, z) in it lands at ``u = cx + fx·x/(−z)``, ``v = cy − fy·y/(−z)`` (see docs/export.md).
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ExportError
from scanpipe.exporters.model import CloudModel, rig_to_z_up
from scanpipe.protocol.profile import ECHO_FULL_SCALE

#: The pixel pitch written as ``pixelWidth`` (metres). E57 stores the focal length in metres
#: and the pixel size; only their ratio (the focal length in pixels) is known from a
#: calibration, so the pitch is nominal and ``focalLength = fx · pitch``.
NOMINAL_PIXEL_M = 1e-6
#: The echo's (u16) largest value: the intensity limit written.
ECHO_MAX = int(ECHO_FULL_SCALE)


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


@dataclass(frozen=True)
class E57Image:
    """One camera frame: the encoded image, its pinhole intrinsics (pixels) and pose.

    ``rotation_wxyz`` / ``translation_m`` map the camera frame (x right, y up, looking along
    −z) into the file's frame. ``image_format``: ``jpeg`` or ``png`` (the blob's name).
    ``description``: free text (e.g. the distortion the image was undistorted from).
    """

    data: bytes
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    rotation_wxyz: tuple[float, float, float, float]
    translation_m: tuple[float, float, float]
    name: str = "image"
    image_format: str = "jpeg"
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


def scan_translation(scan: E57Scan) -> NDArray[np.float64]:
    """The pose translation written for ``scan``: its own, plus its cloud's georeference offset
    turned into the file's frame (``p_file = R (p + offset) + t``)."""
    from scanpipe.poses import rotation_from_quaternion

    translation = np.asarray(scan.translation_m, np.float64)
    if any(scan.cloud.offset_m):
        offset = rig_to_z_up(np.asarray([scan.cloud.offset_m], np.float64))[0]
        translation = translation + rotation_from_quaternion(scan.rotation_wxyz) @ offset
    return translation


def _header_limits(data: dict[str, NDArray[Any]]) -> SimpleNamespace:
    """What pye57 takes from a ``scan_header``: ``intensityLimits`` 0…65535 (the echo's range;
    pye57 would write the data's extremes, and readers that rescale by the limits, such as
    PDAL's, would stretch each scan differently) and ``cartesianBounds`` in the scan's own frame
    (ASTM E57; pye57 would move the two corners by the pose)."""
    xyz = np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1)
    low, high = xyz.min(axis=0), xyz.max(axis=0)
    return SimpleNamespace(
        intensityMinimum=0.0, intensityMaximum=float(ECHO_MAX),
        xMinimum=float(low[0]), yMinimum=float(low[1]), zMinimum=float(low[2]),
        xMaximum=float(high[0]), yMaximum=float(high[1]), zMaximum=float(high[2]))


def write_e57(path: Path, scans: Sequence[E57Scan], images: Sequence[E57Image] = ()) -> None:
    """Write ``scans`` (one ``data3D`` entry each, in order) and ``images`` (one ``images2D``
    entry each) to the E57 file ``path``."""
    import pye57  # here, not at import: only an E57 export needs it

    if not scans:
        raise ExportError(f"{path}: an E57 file needs at least one scan")
    for scan in scans:
        if len(scan.cloud.xyz) == 0:
            raise ExportError(f"scan {scan.name!r}: no points to write")
    for image in images:
        if image.image_format not in ("jpeg", "png"):
            raise ExportError(f"image {image.name!r}: format {image.image_format!r}; "
                              "allowed: jpeg, png")
    crs = {scan.cloud.crs_wkt or "" for scan in scans}
    if len(crs) > 1:
        raise ExportError(f"{path}: the scans are in different coordinate systems; an E57 "
                          "file has one")

    class Writer(pye57.E57):  # type: ignore[misc]
        """pye57's writer with the root's ``coordinateMetadata`` set (a node is set once)."""

        def write_default_header(self) -> None:
            _write_header(self, crs.pop())

    try:
        writer = Writer(str(path), mode="w")
        try:
            for scan in scans:
                data = _scan_data(scan.cloud)
                writer.write_scan_raw(data, name=scan.name,
                                      rotation=np.asarray(scan.rotation_wxyz, np.float64),
                                      translation=scan_translation(scan),
                                      scan_header=_header_limits(data))
                _describe(writer, len(writer.data3d) - 1, scan)
            for image in images:
                _write_image(writer.image_file, image)
        finally:
            writer.close()
    except ExportError:
        raise
    except Exception as err:  # libE57Format raises its own exception types
        raise ExportError(f"E57 writer failed: {err}") from err


def _write_header(writer: Any, coordinate_metadata: str) -> None:
    """The E57 root as pye57 writes it, with ``coordinateMetadata``: the coordinate system
    (WKT) of the file's frame, the imported file's own when the points keep it (the scans'
    poses carry the georeference offset, so the posed points are in its coordinates), else
    empty (ASTM E2807: the string is empty when the system is unknown)."""
    import uuid

    import pye57.libe57 as libe57

    imf = writer.image_file
    root = imf.root()
    imf.extensionsAdd("", libe57.E57_V1_0_URI)
    root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
    root.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
    root.set("versionMajor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MAJOR))
    root.set("versionMinor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MINOR))
    root.set("e57LibraryVersion", libe57.StringNode(imf, libe57.E57_LIBRARY_ID))
    root.set("coordinateMetadata", libe57.StringNode(imf, coordinate_metadata))
    created = libe57.StructureNode(imf)
    created.set("dateTimeValue", libe57.FloatNode(imf, 0.0))
    created.set("isAtomicClockReferenced", libe57.IntegerNode(imf, 0))
    root.set("creationDateTime", created)
    root.set("data3D", libe57.VectorNode(imf, True))
    root.set("images2D", libe57.VectorNode(imf, True))


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


def _write_image(imf: Any, image: E57Image) -> None:
    """Append ``image`` to the root's ``images2D`` vector (created on first use)."""
    import uuid

    import pye57.libe57 as libe57

    root = imf.root()
    if not root.isDefined("images2D"):
        root.set("images2D", libe57.VectorNode(imf, True))
    node = libe57.StructureNode(imf)
    node.set("guid", libe57.StringNode(imf, "{" + str(uuid.uuid4()).upper() + "}"))
    node.set("name", libe57.StringNode(imf, image.name))
    if image.description:
        node.set("description", libe57.StringNode(imf, image.description))
    node.set("sensorVendor", libe57.StringNode(imf, "scanpipe"))
    pose = libe57.StructureNode(imf)
    rotation = libe57.StructureNode(imf)
    for key, value in zip("wxyz", image.rotation_wxyz, strict=True):
        rotation.set(key, libe57.FloatNode(imf, float(value)))
    translation = libe57.StructureNode(imf)
    for key, value in zip("xyz", image.translation_m, strict=True):
        translation.set(key, libe57.FloatNode(imf, float(value)))
    pose.set("rotation", rotation)
    pose.set("translation", translation)
    node.set("pose", pose)
    pinhole = libe57.StructureNode(imf)
    blob = libe57.BlobNode(imf, len(image.data))
    pinhole.set(f"{image.image_format}Image", blob)
    pinhole.set("imageWidth", libe57.IntegerNode(imf, image.width_px))
    pinhole.set("imageHeight", libe57.IntegerNode(imf, image.height_px))
    pinhole.set("focalLength", libe57.FloatNode(imf, image.fx_px * NOMINAL_PIXEL_M))
    pinhole.set("pixelWidth", libe57.FloatNode(imf, NOMINAL_PIXEL_M))
    pinhole.set("pixelHeight", libe57.FloatNode(imf, NOMINAL_PIXEL_M * image.fx_px / image.fy_px))
    pinhole.set("principalPointX", libe57.FloatNode(imf, image.cx_px))
    pinhole.set("principalPointY", libe57.FloatNode(imf, image.cy_px))
    node.set("pinholeRepresentation", pinhole)
    libe57.VectorNode(root.get("images2D")).append(node)
    # The blob is written once it is attached to the file's tree.
    blob.write(np.frombuffer(image.data, dtype=np.uint8).copy(), 0, len(image.data))


def e57_bytes(cloud: CloudModel, name: str = "scan", description: str = "",
              images: Sequence[E57Image] = ()) -> bytes:
    """The cloud as an E57 file of one scan, with ``images`` (libE57Format writes only to
    paths: via a temporary file)."""
    with tempfile.TemporaryDirectory(prefix="scanpipe-e57-") as tmp:
        path = Path(tmp) / "scan.e57"
        write_e57(path, [E57Scan(cloud, name, description=description)], images)
        return path.read_bytes()
