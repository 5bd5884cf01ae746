"""COPC (Cloud Optimized Point Cloud, copc.io 1.0): a LAZ 1.4 file whose points are ordered by
an octree, one LAZ chunk per node, for Potree, QGIS and PDAL to stream.

Layout, as the specification requires: the LAS 1.4 header (375 bytes); the COPC info VLR
(``copc``/1, 160 bytes) first, then the LAZ VLR (variable-size chunks), the local WKT and the
provenance VLR (as :mod:`scanpipe.exporters.las`); the point data (LAZ chunks, node by node,
then the chunk table); one EVLR ``copc``/1000 holding the hierarchy page: per node its voxel
key (depth, x, y, z), the file offset and byte size of its chunk and its point count.

The octree: the root is the cube around the bounds (centre, half size). Each depth keeps, per
cell of ``GRID_CELLS``³ cells of its node, the first point of the cloud order not yet taken
(a spacing of ``2 · halfsize / GRID_CELLS`` at the root, halving per depth); what is left goes
deeper. Point fields, time, source and angle are those of LAS 1.4 formats 6 / 7.
"""

from __future__ import annotations

import datetime as dt
import io
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ExportError
from scanpipe.exporters.las import (
    PROVENANCE_RECORD_ID,
    PROVENANCE_USER_ID,
    SCALE_M,
    fill_points,
    frame_wkt,
)
from scanpipe.exporters.model import CloudModel, geo_z_up, provenance_bytes

#: Cells per node edge at which a depth keeps one point each.
GRID_CELLS = 64
#: Deeper than this, every remaining point stays in its node.
MAX_DEPTH = 16
HEADER_SIZE = 375
VLR_HEADER = 54
EVLR_HEADER = 60
COPC_INFO_SIZE = 160
HIERARCHY_ENTRY = struct.Struct("<4iQii")


def octree_nodes(xyz: NDArray[np.float64], center: NDArray[np.float64], halfsize: float
                 ) -> tuple[NDArray[np.int64], NDArray[np.int32]]:
    """``(order, keys)``: the point indices grouped node by node, and per point (in that
    order) its voxel key (depth, x, y, z). Vectorised per depth."""
    n = len(xyz)
    corner = center - halfsize
    depth_of = np.full(n, -1, dtype=np.int32)
    cell_of = np.zeros((n, 3), dtype=np.int64)
    remaining = np.arange(n)
    for depth in range(MAX_DEPTH + 1):
        cells_per_edge = GRID_CELLS << depth
        cell = np.clip(np.floor((xyz[remaining] - corner) / (2 * halfsize) * cells_per_edge),
                       0, cells_per_edge - 1).astype(np.int64)
        if depth == MAX_DEPTH:
            taken = np.ones(len(remaining), dtype=bool)
        else:
            flat = (cell[:, 0] * cells_per_edge + cell[:, 1]) * cells_per_edge + cell[:, 2]
            _, first = np.unique(flat, return_index=True)
            taken = np.zeros(len(remaining), dtype=bool)
            taken[first] = True
        chosen = remaining[taken]
        depth_of[chosen] = depth
        cell_of[chosen] = cell[taken] // GRID_CELLS  # the node holding that cell
        remaining = remaining[~taken]
        if len(remaining) == 0:
            break
    keys = np.column_stack([depth_of, cell_of]).astype(np.int64)
    order = np.lexsort((keys[:, 3], keys[:, 2], keys[:, 1], keys[:, 0]))
    return order, keys[order].astype(np.int32)


def _vlr(user_id: str, record_id: int, description: str, data: bytes) -> bytes:
    return (struct.pack("<H16sHH32s", 0, user_id.encode(), record_id, len(data),
                        description.encode()) + data)


def copc_bytes(cloud: CloudModel, provenance: Mapping[str, Any] | None = None) -> bytes:
    """The cloud as a COPC file (LAZ 1.4, point format 6 or 7)."""
    import laspy
    import lazrs  # type: ignore[import-untyped]

    if len(cloud.xyz) == 0:
        raise ExportError("points: no points to write")
    xyz = geo_z_up(cloud.xyz, cloud.offset_m)  # georeferenced: as LAS, the offset added back
    point_format = 7 if cloud.colors is not None else 6
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales = np.array([SCALE_M] * 3)
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    fill_points(las, cloud, xyz, "1.4")
    records = las.points.array
    # bounds of the stored (quantised) coordinates
    stored = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    lo, hi = stored.min(axis=0), stored.max(axis=0)
    center = (lo + hi) / 2
    halfsize = float(max(np.max(hi - lo) / 2, SCALE_M)) * (1 + 1e-9) + SCALE_M
    order, keys = octree_nodes(stored, center, halfsize)
    records = records[order]
    starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
    ends = np.r_[starts[1:], len(keys)]

    laz_vlr = lazrs.LazVlr.new_for_compression(point_format, 0, True)
    record_size = records.dtype.itemsize
    provenance_record = provenance_bytes(provenance or {})
    vlrs_after_info = (_vlr("laszip encoded", 22204, "lazrs variable chunks",
                            bytes(laz_vlr.record_data()))
                       + _vlr("LASF_Projection", 2112, "local WKT",
                              frame_wkt(cloud).encode() + b"\0")
                       + _vlr(PROVENANCE_USER_ID, PROVENANCE_RECORD_ID,
                              "scanpipe provenance (JSON)", provenance_record))
    point_start = HEADER_SIZE + VLR_HEADER + COPC_INFO_SIZE + len(vlrs_after_info)

    body = io.BytesIO()
    body.write(bytes(point_start))  # lazrs records absolute offsets (the chunk table's)
    compressor = lazrs.LasZipCompressor(body, laz_vlr)
    compressor.reserve_offset_to_chunk_table()
    raw = records.tobytes()
    chunks: list[tuple[int, int]] = []
    for start, end in zip(starts, ends, strict=True):  # one chunk per node (not per point)
        before = body.tell()
        compressor.compress_many(raw[start * record_size:end * record_size])
        compressor.finish_current_chunk()
        chunks.append((before, body.tell() - before))
    compressor.done()
    points = body.getvalue()[point_start:]

    evlr_start = point_start + len(points)
    hierarchy = b"".join(
        HIERARCHY_ENTRY.pack(*(int(v) for v in keys[s]), offset, size, int(e - s))
        for s, e, (offset, size) in zip(starts, ends, chunks, strict=True))
    root_offset = evlr_start + EVLR_HEADER
    gps = np.asarray(las.gps_time) if cloud.time_ns is not None else np.zeros(1)
    info = struct.pack("<5d2Q2d11Q", *center, halfsize, 2 * halfsize / GRID_CELLS,
                       root_offset, len(hierarchy), float(gps.min()), float(gps.max()),
                       *([0] * 11))
    evlr = struct.pack("<H16sHQ32s", 0, b"copc", 1000, len(hierarchy),
                       b"EPT hierarchy") + hierarchy
    return _header(point_format, record_size, point_start, evlr_start, len(records), lo, hi,
                   header.offsets, 4) + _vlr("copc", 1, "COPC info", info) + vlrs_after_info \
        + points + evlr


def _header(point_format: int, record_size: int, point_start: int, evlr_start: int,
            count: int, lo: NDArray[np.float64], hi: NDArray[np.float64],
            offsets: NDArray[np.float64], n_vlrs: int) -> bytes:
    """The LAS 1.4 public header block (375 bytes), written field by field."""
    today = dt.date.today()
    global_encoding = 0b1 | 0b10000  # adjusted standard GPS time, WKT
    out = struct.pack("<4sHH16sBB32s32sHHHIIBHI5I3d3d6dQQIQ15Q",
                      b"LASF", 0, global_encoding, b"\0" * 16, 1, 4,
                      b"scanpipe turntable scanner", b"scanpipe", today.timetuple().tm_yday,
                      today.year, HEADER_SIZE, point_start, n_vlrs, point_format | 0x80,
                      record_size, 0, 0, 0, 0, 0, 0, SCALE_M, SCALE_M, SCALE_M, *offsets,
                      hi[0], lo[0], hi[1], lo[1], hi[2], lo[2], 0, evlr_start, 1, count,
                      count, *([0] * 14))
    assert len(out) == HEADER_SIZE
    return out
