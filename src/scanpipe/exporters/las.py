"""LAS / LAZ point clouds (laspy): z up, (x, −z, y) from the rig frame.

- Version: LAS 1.2 by default (point formats 0–3; what web readers such as loaders.gl accept),
  or 1.4 (point formats 6–7, a full-range scan angle).
- Intensity is the scanner's echo value (u16); colour (8-bit) is scaled to 16 bits (× 257).
- GPS time is **adjusted standard GPS time** (global-encoding bit 0 set): seconds since the GPS
  epoch (1980-01-06) minus 10⁹, from the host clock's Unix time plus the 18 leap seconds
  counted since 2017 (:func:`adjusted_gps_time_s`).
- Point source ID: the scan-grid row (profile) + 1, so a reader can select one profile
  ("flight line" in airborne terms); 0 for a cloud without a grid. Wraps after 65535.
- Scan angle: the beam angle α measured from nadir (α = 180° points down), signed, in −180..180.
  LAS 1.2's ``scan_angle_rank`` holds only whole degrees in −90..90 (clipped); 1.4 holds it
  to 0.006°.
- Georeferenced clouds (``import-points`` of UTM/state-plane files, shifted by ``offset_m``):
  the offset is added back in float64 before the points are scaled to ints, so x, y, z are the
  imported file's coordinates (in metres) to the 0.1 mm scale; the header offsets are whole
  metres below the bounds.
- VLRs: a WKT ``LOCAL_CS`` (LASF_Projection 2112: the rig's local frame in metres, no
  geo-reference; the imported file's own WKT when the points keep it, else :data:`GEO_WKT`
  for a georeferenced cloud) and a provenance record (user
  ``scanpipe``, record 1: JSON with the scanpipe
  version, the artifact's key, stage and parameters).
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ExportError
from scanpipe.exporters.model import CloudModel, geo_z_up, provenance_bytes

#: Coordinate resolution: 0.1 mm, well below the scanner's 3.9 mm range step.
SCALE_M = 0.0001
LAS_VERSIONS = ("1.2", "1.4")
#: Seconds from the Unix epoch to the GPS epoch (1980-01-06T00:00:00Z).
GPS_EPOCH_UNIX_S = 315_964_800
#: GPS time is ahead of UTC by the leap seconds since 1980: 18 since 2017-01-01.
GPS_LEAP_S = 18
#: The rig frame as a WKT 1 local coordinate system (no geo-reference).
LOCAL_WKT = ('LOCAL_CS["scanpipe rig frame (z up)",LOCAL_DATUM["scanpipe turntable",0],'
             'UNIT["metre",1],AXIS["X",EAST],AXIS["Y",NORTH],AXIS["Z",UP]]')
#: The frame of a georeferenced cloud (an import shifted by ``offset_m``, added back here):
#: the imported file's own coordinates in metres; its CRS is not carried (a CRS in feet would
#: not fit metre coordinates: the user assigns the source's CRS, or its metre equivalent).
GEO_WKT = ('LOCAL_CS["imported coordinates in metres (scanpipe added the import offset '
           'back; assign the source CRS if it is in metres; a source CRS in feet does not fit '
           'these coordinates: assign its metre equivalent)",LOCAL_DATUM["unknown",0],'
           'UNIT["metre",1],'
           'AXIS["X",EAST],AXIS["Y",NORTH],AXIS["Z",UP]]')
PROVENANCE_USER_ID = "scanpipe"
PROVENANCE_RECORD_ID = 1


def frame_wkt(cloud: CloudModel) -> str:
    """The WKT of the frame a cloud is written in: the imported file's coordinate system when
    the points keep it, else (with a georeference offset) the imported file's coordinates in
    metres, else the rig's."""
    if cloud.crs_wkt:
        return cloud.crs_wkt
    return GEO_WKT if any(cloud.offset_m) else LOCAL_WKT


def adjusted_gps_time_s(time_ns: NDArray[np.int64]) -> NDArray[np.float64]:
    """Host-clock Unix nanoseconds to adjusted standard GPS time (GPS seconds − 10⁹)."""
    return np.asarray((time_ns - (GPS_EPOCH_UNIX_S - GPS_LEAP_S) * 10**9 - 10**18) / 1e9,
                      dtype=np.float64)


def unix_time_ns(adjusted_gps_s: NDArray[np.floating]) -> NDArray[np.int64]:
    """The inverse of :func:`adjusted_gps_time_s` (to the float's resolution)."""
    return np.asarray(np.rint((np.asarray(adjusted_gps_s, np.float64) + 1e9
                               + GPS_EPOCH_UNIX_S - GPS_LEAP_S) * 1e9), dtype=np.int64)


def scan_angle_from_nadir_deg(alpha_deg: NDArray[np.floating]) -> NDArray[np.float64]:
    """The beam angle α as a signed angle from nadir (α = 180°), in [−180, 180)."""
    return np.asarray(np.mod(np.asarray(alpha_deg, np.float64), 360.0) - 180.0,
                      dtype=np.float64)


def las_bytes(cloud: CloudModel, compressed: bool = False, version: str = "1.2",
              provenance: Mapping[str, Any] | None = None) -> bytes:
    """The cloud as a LAS (or, with ``compressed``, LAZ) file of LAS ``version``."""
    import laspy  # here, not at import: only an LAS export needs it

    if version not in LAS_VERSIONS:
        raise ExportError(f"--las-version {version!r}: allowed: {', '.join(LAS_VERSIONS)}")
    if len(cloud.xyz) == 0:
        raise ExportError("points: no points to write")
    xyz = geo_z_up(cloud.xyz, cloud.offset_m)
    has_time = cloud.time_ns is not None
    coloured = cloud.colors is not None
    if version == "1.2":
        point_format = (3 if has_time else 2) if coloured else (1 if has_time else 0)
    else:
        point_format = 7 if coloured else 6
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([SCALE_M] * 3)
    header.offsets = np.floor(xyz.min(axis=0))
    header.generating_software = "scanpipe"
    header.system_identifier = "scanpipe turntable scanner"
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    if version == "1.4":
        header.global_encoding.wkt = True
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(frame_wkt(cloud)))
    record = provenance_bytes(provenance or {})
    if len(record) > 65535:
        raise ExportError(f"provenance record of {len(record)} bytes: a VLR holds 65535")
    header.vlrs.append(laspy.VLR(PROVENANCE_USER_ID, PROVENANCE_RECORD_ID,
                                 "scanpipe provenance (JSON)", record))
    las = laspy.LasData(header)
    fill_points(las, cloud, xyz, version)
    stream = io.BytesIO()
    try:
        las.write(stream, do_compress=compressed,
                  laz_backend=laspy.LazBackend.Lazrs if compressed else None)
    except laspy.errors.LaspyException as err:
        raise ExportError(f"LAS/LAZ writer failed: {err}") from err
    return stream.getvalue()


def fill_points(las: Any, cloud: CloudModel, xyz: NDArray[np.float64], version: str) -> None:
    """Set every point field of ``las`` (a ``laspy.LasData``) from the cloud, as the module
    docstring describes; ``xyz`` is the cloud in the z-up frame."""
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if cloud.intensity is not None:
        las.intensity = cloud.intensity
    if cloud.colors is not None:
        colors16 = cloud.colors.astype(np.uint16) * 257
        las.red, las.green, las.blue = colors16[:, 0], colors16[:, 1], colors16[:, 2]
    if cloud.time_ns is not None:
        las.gps_time = adjusted_gps_time_s(cloud.time_ns)
    if cloud.profile is not None:
        las.point_source_id = np.where(cloud.profile >= 0, (cloud.profile + 1) % 65536,
                                       0).astype(np.uint16)
    if cloud.alpha_deg is not None:
        angle = scan_angle_from_nadir_deg(cloud.alpha_deg)
        if version == "1.2":
            las.scan_angle_rank = np.clip(np.rint(angle), -90, 90).astype(np.int8)
        else:
            las.scan_angle = np.clip(np.rint(angle / 0.006), -30000, 30000).astype(np.int16)


def pdal_pipeline_bytes(las_name: str, reader: str = "readers.las", srs: str = LOCAL_WKT
                        ) -> bytes:
    """A PDAL pipeline beside a LAS/LAZ export that reads it back (``pdal pipeline
    NAME.pipeline.json`` or ``pdal info``): ``reader`` (``readers.las``, or ``readers.copc``
    for COPC) on the file, next to it, with the
    file's own SRS (its WKT VLR, ``srs``: :func:`frame_wkt`) and ``default_srs`` set to the
    same, so a PDAL built without that VLR's support still labels the points rightly."""
    pipeline = {"pipeline": [{
        "type": reader,
        "filename": las_name,
        "default_srs": srs,
        "tag": "scanpipe_points",
    }]}
    return (json.dumps(pipeline, indent=2) + "\n").encode()
